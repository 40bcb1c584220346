"""The wall push (``kind = "wall_push"``, thesis sec. 2.3.3): one ODAR pushes on a wall with a
commanded normal force under the hybrid pose/wrench controller, batch mode only.

:mod:`.config`: the scenario's ``[contact]`` table; :mod:`.flight`: the task and its metrics.
"""

from __future__ import annotations

from ..kind import ScenarioKind
from .config import load_wall_scenario

__all__ = ["KIND"]


def _fly(scenario, out_dir, **options) -> dict:
    from .flight import wall_push  # MuJoCo: imported once the rendering backend is chosen

    return wall_push(scenario, out_dir, **options)


KIND = ScenarioKind("wall_push", "one ODAR pushing a wall under hybrid pose/wrench control", load=load_wall_scenario,
                    fly=_fly, tables=("contact",),
                    summary=("force_mean_true_n", "force_error_rms_n", "force_error_rms_rel", "observer_force_error_rms_n",
                             "free_pos_error_rms_m", "att_error_rms_deg", "crashed", "realtime_factor"))
