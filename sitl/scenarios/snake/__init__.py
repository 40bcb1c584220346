"""The snake-like robot (``kind = "snake"``, thesis sec. 4.2.2 and 4.3.2): 15 modules on joints
alternately horizontal and vertical, driven by its CPG on the ground in MuJoCo; batch mode only.

* :mod:`.config`: the scenario's schema (no MuJoCo): body, ground, CPG, commands;
* :mod:`.model`: the robot and its ground in MuJoCo, the ground's anisotropic friction;
* :mod:`.flight`: its CPG on the shared run (:mod:`sitl.scenarios.ground.run`), the metrics;
* :mod:`.control`: velocity commands through the inverse model (and the adaptation), once per period;
* :mod:`.phase_map`: eq. 4.1's sweep; :mod:`.inverse`: the inverse model's data and training.
"""

from __future__ import annotations

from ..ground.config import GROUND_SUMMARY, GROUND_TABLES
from ..kind import ScenarioKind
from .config import load_snake_scenario

__all__ = ["KIND"]


def _fly(scenario, out_dir, **options) -> dict:
    from .flight import fly_snake  # MuJoCo: imported once the rendering backend is chosen

    return fly_snake(scenario, out_dir, **options)


KIND = ScenarioKind("snake", "the thesis's snake-like robot crawling on its CPG", load=load_snake_scenario,
                    fly=_fly, tables=GROUND_TABLES, summary=GROUND_SUMMARY)
