"""The pivotboard (``kind = "pivotboard"``, thesis sec. 4.2.2 and 4.3.3): a deck and two foot plates
on wheels, the plates oscillated by its CPG, in MuJoCo; batch mode only.

* :mod:`.config`: the scenario's schema (no MuJoCo): body, ground, CPG, control, commands;
* :mod:`.model`: the board and its ground in MuJoCo;
* :mod:`.flight`: its CPG on the shared loop (:mod:`sitl.scenarios.ground.run`), the metrics;
* :mod:`.control`: motion commands through the inverse model and the adaptation (secs. 4.6, 4.7.2);
* :mod:`.phase_map`, :mod:`.da_fit`, :mod:`.inverse`: the commands that write eq. 4.1's map, eq.
  4.2's fits and the inverse models (``models/``).
"""

from __future__ import annotations

from ..ground.config import GROUND_SUMMARY, GROUND_TABLES
from ..kind import ScenarioKind
from .config import load_pivot_scenario

__all__ = ["KIND"]


def _fly(scenario, out_dir, **options) -> dict:
    from .flight import fly_pivotboard  # MuJoCo: imported once the rendering backend is chosen

    return fly_pivotboard(scenario, out_dir, **options)


KIND = ScenarioKind("pivotboard", "the thesis's pivotboard rolling on its CPG", load=load_pivot_scenario,
                    fly=_fly, tables=GROUND_TABLES, summary=GROUND_SUMMARY)
