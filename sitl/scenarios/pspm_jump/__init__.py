"""The PSPM jump (``kind = "pspm_jump"``, thesis sec. 2.3.4): a scripted operator jumps one ODAR's
set pose, flown once with PSPM and once without (two flights), batch mode only.

:mod:`.config`: the scenario's ``[teleop]`` table; :mod:`.flight`: the scripted operator, the
jump metrics and the plot.
"""

from __future__ import annotations

from ..kind import ScenarioKind
from .config import load_teleop_scenario

__all__ = ["KIND"]


def _fly(scenario, out_dir, **options) -> dict:
    from .flight import pspm_jump  # MuJoCo: imported once the rendering backend is chosen

    return pspm_jump(scenario, out_dir, **options)


KIND = ScenarioKind("pspm_jump", "one ODAR under a scripted operator's jumps, with and without PSPM",
                    load=load_teleop_scenario, fly=_fly, runs=2, tables=("teleop",),
                    summary=("jump_m", "yaw_jump_deg", "runs"))
