"""A scenario kind's part in a fleet run: the public hooks :class:`~sitl.fleet.launcher.Fleet` calls.

The fleet is the vehicles, the companion(s) and the vision consumer as processes, and the harness
with the plant in lockstep with them (:mod:`sitl.fleet.launcher`); a :class:`FleetTask` is what a
kind of scenario adds to them (as :class:`sitl.task.Task` does to a batch flight): its own plant,
a companion where the chain's would not run, the consumer's measurements, its truth and metrics.
Every hook keeps the chain's behaviour here; a kind overrides those it needs.

The fleet calls them in this order: :meth:`FleetTask.plant` and :meth:`FleetTask.companion_setup`
while it writes the run folder's configs, :meth:`FleetTask.consumer_setup` when it starts the
vision consumer, :meth:`FleetTask.start` once the harness is connected (before the first tick),
:meth:`FleetTask.metrics` after the flight.
"""

from __future__ import annotations

__all__ = ["FleetTask"]


class FleetTask:
    """The hooks of a fleet run (module docstring); this base class is the chain's."""

    #: whether the vision consumer publishes measurements a companion takes (besides neighbour poses)
    consumer_publishes = False

    def companion_runs(self, sc) -> bool:
        """Whether the scenario has companions to start (the chain's: when its constraint is on)."""
        return sc.companion.enabled

    def plant(self, sc):
        """The plant the harness flies (:class:`~sitl.plant.plant.Plant`), reset to its start."""
        from sitl.plant.plant import Plant

        return Plant(sc)

    def companion_setup(self, fleet, setup):
        """The companions' config (:class:`~companion.config.CompanionSetup`) as the fleet wrote it so far."""
        return setup

    def consumer_setup(self, fleet, setup):
        """The vision consumer's config (:class:`~companion.vision.node_config.VisionNodeSetup`)."""
        return setup

    def start(self, fleet) -> None:
        """Once the harness is connected (``fleet.harness``), before the first tick: e.g. tick hooks."""

    def metrics(self, fleet, plots: bool) -> dict:
        """What the kind adds to ``metrics.json`` after the flight (it may write files into ``fleet.out_dir``)."""
        return {}
