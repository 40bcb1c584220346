"""Campaigns: many runs (scenarios x parameter settings x seeds) on Dask ``distributed``, resumable,
with one results table (``python -m sitl campaign``).

* :mod:`.grid`: what ``--set`` and ``--seeds`` mean; a :class:`~.grid.RunSpec` per run, its key
  and folder (pure);
* :mod:`.engine`: jobs, their records (``run_record.json``, written as each run ends), resuming,
  the serial executor;
* :mod:`.cluster`: the Dask client (local cluster or ``--scheduler``) and executor;
* :mod:`.runs`: what a worker does with a run (batch flight, or a fleet on leased ports);
* :mod:`.table`, :mod:`.summary`: the results table and its summaries;
* :mod:`.flights`: a campaign of flights, its folder's files; :mod:`.cli`: the command line.

Importing this package imports neither Dask nor the simulator.
"""
