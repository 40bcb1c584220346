"""ODAR design optimisation (thesis sec. 2.2.2): guaranteed wrench metrics, aerodynamic clearance, grid search.

* :mod:`.metrics`: ``F_min`` (2.2), ``F_min^W``, ``F_min^xz``, ``M_min`` (2.3), ``M_min^V``, the
  tapered-cylinder flow volume and ``d_aero`` (2.6); :func:`evaluate` / :class:`OdarDesign`.
* :mod:`.search`: the sequential grid search (2.4)-(2.6), first ``U`` then ``R`` and ``S``.
* :mod:`.plots`: Fig. 2-2 (matplotlib, imported lazily).
* ``python -m link_firmware_sim.design evaluate|search``: the CLI; ``search`` writes the
  ``[rotors.geometry]`` table that firmware configs and SITL scenarios accept.

Pure numpy/scipy; no simulator.
"""

from .metrics import (
    DesignMetrics,
    DesignProblem,
    FlowVolume,
    OdarDesign,
    aero_clearance_m,
    evaluate,
    flow_radius_m,
    force_min,
    force_min_weighted,
    force_min_xz,
    torque_generators,
    torque_min,
    torque_min_weighted,
    zonotope_inradius,
    zonotope_plane_inradius,
)
from .search import SearchGrid, SearchResult, search

__all__ = [
    "DesignMetrics",
    "DesignProblem",
    "FlowVolume",
    "OdarDesign",
    "SearchGrid",
    "SearchResult",
    "aero_clearance_m",
    "evaluate",
    "flow_radius_m",
    "force_min",
    "force_min_weighted",
    "force_min_xz",
    "search",
    "torque_generators",
    "torque_min",
    "torque_min_weighted",
    "zonotope_inradius",
    "zonotope_plane_inradius",
]
