"""The slung load (``kind = "slung_load"``): three or more unjoined vehicles of this stack carry a
box by cables, its pose estimated from their cameras (:mod:`companion.load`), in batch mode or as a
fleet.

* :mod:`.config`: the scenario's schema (no MuJoCo, no OpenCV); its ``[load]`` table and the
  formation's targets, which the companion flies, are the companion's
  (:mod:`companion.load.config`, :mod:`companion.load.formation`);
* :mod:`.model`: the vehicles, the load and the cables in MuJoCo;
* :mod:`.estimation`: the companion's load estimation beside the flight, against the truth;
* :mod:`.flight`: the task, the flight and its metrics; :mod:`.plots`: its plots;
* :mod:`.fleet`: its fleet form (``python -m sitl launch``), the same estimate in the companion;
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


def _launch(scenario, out_dir, **options) -> dict:
    from .fleet import launch_slung_load  # the fleet's processes, MuJoCo rendering and OpenCV

    return launch_slung_load(scenario, out_dir, **options)


KIND = ScenarioKind("slung_load", "vehicles carrying a box by cables, its pose from their cameras",
                    load=load_slung_scenario, fly=_fly, launch=_launch, video=True, tables=("load",),
                    summary=SUMMARY_KEYS)
