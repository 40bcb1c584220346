"""A run's recordings for other tools: MCAP files that Foxglove and Lichtblick open
(:mod:`.mcap_log`: a SITL run folder's ``run.mcap``, the companion daemon's ``companion.mcap``)
with Foxglove's schemas (:mod:`.foxglove`). Needs the ``mcap`` package (the ``view`` extra)."""
