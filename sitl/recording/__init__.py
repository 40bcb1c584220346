"""A run's recordings in other formats: ``run.mcap`` (:mod:`sitl.recording.mcap_log`), the run
folder's ``log.npz`` as an MCAP file for Foxglove and Lichtblick."""
