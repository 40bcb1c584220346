"""The chain flight: the skeleton of ``[skeleton]`` flying its ``[trajectory]`` (``kind = "chain"``,
the default).

Its schema is :class:`sitl.scenario.Scenario`; cameras (``[[cameras]]``, ``[[markers]]``) and
scripted faults (``[faults]``) are options of it. Batch mode: :func:`.flight.fly`; fleet mode:
:func:`sitl.fleet.launcher.launch`.
"""

from __future__ import annotations

from sitl.scenario import load_scenario

from ..kind import ScenarioKind

__all__ = ["KIND"]


def _fly(scenario, out_dir, **options) -> dict:
    from .flight import fly  # the simulator: imported once the rendering backend is chosen

    return fly(scenario, out_dir, **options)


def _launch(scenario, out_dir, **options) -> dict:
    from sitl.fleet.launcher import launch

    return launch(scenario, out_dir, **options)


KIND = ScenarioKind("chain", "a chain of links flying its trajectory (cameras and faults as options)",
                    load=load_scenario, fly=_fly, launch=_launch, video=True)
