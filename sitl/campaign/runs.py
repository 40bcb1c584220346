"""What a campaign worker does with one :class:`~sitl.campaign.grid.RunSpec`: fly it.

:func:`fly_spec` loads the scenario with the run's settings and seed, flies it in batch mode
(:func:`python -m sitl fly`'s flight) or as an unpaced fleet on instance offsets it leases
(:mod:`sitl.fleet.lease`), writes the run's folder (``metrics.json``, ``log.npz``,
``scenario.toml``, ``run.log`` with the flight's own log lines, ``console.txt`` with what it
printed) and returns its metrics. It
imports nothing of the simulator until the rendering backend is chosen.
"""

from __future__ import annotations

import logging
import socket
from contextlib import contextmanager, redirect_stdout
from dataclasses import replace
from pathlib import Path
from typing import Iterator

from companion.cli import LOG_FORMAT, single_thread_blas

from .grid import RunSpec

__all__ = ["fly_spec", "load_spec"]


@contextmanager
def _run_log(out_dir: Path) -> Iterator[None]:
    """This process's log lines go to ``out_dir/run.log`` while the block runs (not the worker's console)."""
    handler = logging.FileHandler(out_dir / "run.log", mode="w")
    handler.setFormatter(logging.Formatter(LOG_FORMAT))
    root = logging.getLogger()
    saved = (list(root.handlers), root.level)
    for h in saved[0]:
        root.removeHandler(h)
    root.addHandler(handler)
    root.setLevel(logging.INFO)
    try:
        yield
    finally:
        root.removeHandler(handler)
        handler.close()
        for h in saved[0]:
            root.addHandler(h)
        root.setLevel(saved[1])


def load_spec(spec: RunSpec):
    """``(kind, scenario)`` of ``spec``: its file with its settings, seed, duration and sensor
    profile (a :class:`~companion.configfile.ConfigError` for an invalid combination)."""
    from sitl.scenarios import load

    overrides = {"seed": spec.seed}
    if spec.duration_s is not None:
        overrides["duration_s"] = spec.duration_s
    kind, sc = load(spec.config, settings=dict(spec.settings), **overrides)
    if spec.profile is not None:
        sc = replace(sc, sensors=replace(sc.sensors, profile=spec.profile))
    if spec.mode == "batch" and sc.faults.fleet_only:
        raise ValueError(f"{spec.config}: {', '.join(sc.faults.fleet_only)}: fleet mode only")
    if spec.mode == "fleet":
        if kind.launch is None:
            raise ValueError(f"{spec.config}: a {kind.name} scenario has no fleet form")
        from sitl.fleet.layout import check_fleet_scenario

        check_fleet_scenario(sc)
    return kind, sc


def _unused_udp_port() -> int:
    """A UDP port the kernel just handed out: a fleet's ground-station traffic goes there, where no
    ground station of the user's listens."""
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def fly_spec(out_dir: Path, spec: RunSpec, renders: bool = False) -> dict:
    """Fly ``spec`` into ``out_dir``; its metrics. ``renders``: whether any run of the campaign
    renders (the worker's MuJoCo backend is chosen once, at its first import)."""
    from sitl.cameras.rendering import choose_backend, require_rendering

    out_dir = Path(out_dir)
    with _run_log(out_dir), single_thread_blas(), open(out_dir / "console.txt", "w") as console, \
            redirect_stdout(console):  # what the flight prints (a fleet's port table) is the run's, not the worker's
        kind, sc = load_spec(spec)
        choose_backend(renders or bool(sc.cameras))
        if sc.cameras:
            require_rendering()
        if spec.mode == "batch":
            return kind.fly(sc, out_dir, plots=False)
        from sitl.fleet.lease import lease_instance_offset

        gcs_port = _unused_udp_port()
        with lease_instance_offset(sc, gcs_port) as k:
            metrics = kind.launch(sc, out_dir, speed=spec.speed, plots=False, instance_offset=k, gcs_port=gcs_port)
    if metrics.get("interrupted"):
        # the fleet stopped on Ctrl-C or SIGTERM (and kept what it flew): the campaign stops too,
        # and this run is not a finished one (the same command flies it again)
        raise KeyboardInterrupt
    return metrics
