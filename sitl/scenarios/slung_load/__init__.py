"""The slung load (``kind = "slung_load"``): three or more unjoined vehicles of this stack carry a
box by cables, its pose estimated from their cameras (:mod:`companion.load`), batch mode only.

* :mod:`.config`: the scenario's ``[load]`` table (no MuJoCo, no OpenCV);
* :mod:`.formation`: the formation's circle and every vehicle's target, with the cables'
  feed-forward force;
* :mod:`.model`: the vehicles, the load and the cables in MuJoCo;
* :mod:`.estimation`: the companion's load estimation beside the flight, against the truth;
* :mod:`.flight`: the task, the flight and its metrics; :mod:`.plots`: its plots;
* :mod:`.synthetic`: the same carrying without a physics engine, the load filters' reference
  (``python -m sitl.bench load_filter``).
"""

from __future__ import annotations

from ..kind import SUMMARY_KEYS, ScenarioKind
from .config import load_slung_scenario

__all__ = ["KIND"]


def _fly(scenario, out_dir, **options) -> dict:
    from .flight import fly_slung_load  # MuJoCo rendering and OpenCV: imported once the backend is chosen

    return fly_slung_load(scenario, out_dir, **options)


KIND = ScenarioKind("slung_load", "vehicles carrying a box by cables, its pose from their cameras",
                    load=load_slung_scenario, fly=_fly, video=True, tables=("load",), summary=SUMMARY_KEYS)
