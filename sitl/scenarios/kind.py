"""What a scenario kind declares to the registry (:mod:`sitl.scenarios`) and the command line."""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

__all__ = ["ScenarioKind", "SUMMARY_KEYS"]

#: the metrics ``python -m sitl fly`` and ``launch`` print of a chain flight (all in ``metrics.json``)
SUMMARY_KEYS = ("load_pose_err", "rms_track_est_m", "rms_track_true_m", "rms_est_err_m", "constraint_pos_p95_m",
                "constraint_vel_p95_m_s", "correction_latency_ms", "rotor_zero_crossings", "min_altitude_m",
                "took_off", "crashed", "realtime_factor")


@dataclass(frozen=True)
class ScenarioKind:
    """A kind of scenario: how its file loads and what flies it.

    ``load(path, **overrides)`` reads and validates a file of this kind (a
    :class:`~companion.configfile.ConfigError` names the file, key and reason); it imports no
    simulator (no MuJoCo, no OpenCV), so that a file is checked before the rendering backend is
    chosen. ``fly(scenario, out_dir, *, progress, plots, video)`` flies it in batch mode, writes
    its run folder and returns its metrics (it imports the simulator when called). ``launch`` is
    its fleet form (``python -m sitl launch``: :func:`sitl.fleet.launcher.launch`'s signature), ``None``
    for a kind that flies in batch mode only. ``runs``: flights per ``fly`` (the progress bar's
    length in scenario durations); ``video``: ``fly`` takes ``--video``; ``summary``: the metrics
    the command line prints; ``tables``: the top-level tables only this kind's files have (a file
    with one and without ``kind`` is told which kind it is).
    """

    name: str
    description: str
    load: Callable
    fly: Callable
    launch: Callable | None = None
    runs: int = 1
    video: bool = False
    summary: tuple[str, ...] = SUMMARY_KEYS
    tables: tuple[str, ...] = ()
