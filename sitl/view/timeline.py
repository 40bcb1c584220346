"""A finished run as frames by time (:class:`Timeline`), read from its run folder (:func:`open_run`),
with its cameras' images when it kept them."""

from __future__ import annotations

import logging
import zipfile
from collections.abc import Mapping
from pathlib import Path

import numpy as np

from .frame import ViewFrame, figures, frame
from .spec import SceneSpec, spec_of_run

__all__ = ["Timeline", "open_run", "RunUnreadable"]

_log = logging.getLogger(__name__)


class RunUnreadable(ValueError):
    """A run folder whose log cannot be shown (the message says which file and why)."""


def _rows(log: Mapping[str, np.ndarray], stamp: str) -> dict[str, np.ndarray]:
    """The arrays of ``log`` with one row per sample of ``log[stamp]``."""
    k = len(log[stamp])
    return {key: a for key, a in log.items() if np.ndim(a) and len(a) == k}


def _check_times(name: str, t: np.ndarray) -> np.ndarray:
    t = np.asarray(t, dtype=float)
    if t.ndim != 1 or t.size == 0:
        raise RunUnreadable(f"{name}: expected a non-empty 1-D array of times, got shape {t.shape}")
    if not np.isfinite(t).all() or np.any(np.diff(t) < 0):
        raise RunUnreadable(f"{name}: the times must be finite and never go back")
    return t


class Timeline:
    """The frames of a run's log (``t``, ``p_true``, ``q_true`` and what else it holds; the
    companion's step rows at ``t_sckf``; ``load`` the load's rows at ``load_t``), by time."""

    def __init__(self, log: Mapping[str, np.ndarray], load: Mapping[str, np.ndarray] | None = None):
        if "t" not in log or "p_true" not in log or "q_true" not in log:
            raise RunUnreadable("the log holds no truth (t, p_true, q_true)")
        self.t = _check_times("t", log["t"])
        p, q = np.asarray(log["p_true"]), np.asarray(log["q_true"])
        if p.ndim != 3 or p.shape[0] != self.t.size or p.shape[2] != 3 or q.shape != p.shape[:2] + (4,):
            raise RunUnreadable(f"p_true {p.shape} and q_true {q.shape}: expected (samples, links, 3) and "
                                f"(samples, links, 4) with {self.t.size} samples")
        self.n = p.shape[1]
        self.rows = _rows(log, "t")
        #: where the companion flew from (``None``: not logged), for the targets in the truth's frame
        self.home = np.asarray(log["home_offset_w_m"], dtype=float) if "home_offset_w_m" in log else None
        self.steps: dict[str, np.ndarray] = {}
        if "t_sckf" in log and np.size(log["t_sckf"]):
            self.t_step = _check_times("t_sckf", log["t_sckf"])
            self.steps = _rows(log, "t_sckf")
        else:
            self.t_step = np.zeros(0)
        self.frames: dict = {}
        self.loads: dict[str, np.ndarray] = {}
        self.t_load = np.zeros(0)
        if load and "load_t" in load and np.size(load["load_t"]):
            self.t_load = _check_times("load_t", load["load_t"])
            self.loads = _rows(load, "load_t")

    @property
    def start_s(self) -> float:
        return float(self.t[0])

    @property
    def end_s(self) -> float:
        return float(self.t[-1])

    @staticmethod
    def _at(t: np.ndarray, t_s: float) -> int:
        """The index of the newest sample of ``t`` at or before ``t_s`` (-1: none)."""
        return int(np.searchsorted(t, t_s, side="right")) - 1

    def frame(self, t_s: float) -> ViewFrame:
        """The frame of the newest log row at or before ``t_s`` (the first row before the log starts)."""
        k = max(self._at(self.t, t_s), 0)
        j = self._at(self.t_step, self.t[k])
        i = self._at(self.t_load, self.t[k])
        step = {key: a[j] for key, a in self.steps.items()} if j >= 0 else None
        load = {key: a[i] for key, a in self.loads.items()} if i >= 0 else None
        return frame(self.t[k], self._with_home({key: a[k] for key, a in self.rows.items()}), step, load)

    def _with_home(self, rows: dict) -> dict:
        return rows if self.home is None else {**rows, "home_offset_w_m": self.home}

    def images_at(self, t_s: float) -> dict[int, tuple[int, bytes]]:
        """Per camera (its index in the scenario), ``(frame number, JPEG bytes)`` of its newest frame
        captured at or before ``t_s`` (the run folder's ``camera_frames.npz``; none without it)."""
        f = self.frames
        if not f:
            return {}
        out = {}
        for cam, (t, rows) in f["by_camera"].items():
            k = self._at(t, t_s)
            if k >= 0:
                r = int(rows[k])
                out[cam] = (r, f["frame_jpeg"][f["frame_offsets"][r]:f["frame_offsets"][r + 1]].tobytes())
        return out

    def series(self) -> dict[str, tuple[np.ndarray, np.ndarray]]:
        """Every figure of the panel over the whole run: name -> (times [s], values)."""
        out = {name: (self.t, v) for name, v in figures(self._with_home(self.rows)).items()}
        if self.steps:
            out.update({name: (self.t_step, v) for name, v in figures({}, self.steps).items()})
        return out


def open_run(run_dir: str | Path) -> tuple[Timeline, SceneSpec]:
    """The timeline and scene of run folder ``run_dir`` (its ``log.npz``, ``load.npz`` when it has
    one, ``scenario.toml``); :class:`RunUnreadable` when there is nothing to show."""
    run_dir = Path(run_dir)
    path = run_dir / "log.npz"
    if not path.is_file():
        raise RunUnreadable(f"{run_dir}: no log.npz (a run folder of python -m sitl fly or launch holds one)")
    try:
        with np.load(path, allow_pickle=False) as npz:
            log = {k: npz[k] for k in npz.files}
        load = None
        if (run_dir / "load.npz").is_file():
            with np.load(run_dir / "load.npz", allow_pickle=False) as npz:
                load = {k: npz[k] for k in npz.files}
    except (OSError, ValueError, EOFError, zipfile.BadZipFile) as exc:
        raise RunUnreadable(f"{path}: unreadable ({exc})") from None
    try:
        timeline = Timeline(log, load)
    except RunUnreadable as exc:
        raise RunUnreadable(f"{path}: {exc}") from None
    timeline.frames = _camera_frames(run_dir / "camera_frames.npz")
    return timeline, spec_of_run(run_dir, timeline.n)


def _camera_frames(path: Path) -> dict:
    """The run's JPEG camera frames (:mod:`sitl.cameras.frame_archive`) with, per camera, its frames'
    capture times in order and their rows; ``{}`` without the file or when it does not hold together."""
    if not path.is_file():
        return {}
    try:
        with np.load(path, allow_pickle=False) as npz:
            f = {k: npz[k] for k in npz.files}
        t, cam, offsets = f["frame_t"], f["frame_camera"].astype(np.int64), f["frame_offsets"].astype(np.int64)
        if (offsets.shape != (len(t) + 1,) or np.any(np.diff(offsets) < 0) or (len(t) and offsets[-1] != f["frame_jpeg"].size)
                or not np.isfinite(t).all() or cam.shape != t.shape):
            raise ValueError("the arrays do not fit together")
    except (OSError, ValueError, KeyError, EOFError, zipfile.BadZipFile) as exc:
        _log.warning("%s: %s; no camera images", path, exc)
        return {}
    by_camera = {}
    for c in np.unique(cam).tolist():
        rows = np.flatnonzero(cam == c)
        rows = rows[np.argsort(t[rows], kind="stable")]
        by_camera[int(c)] = (t[rows], rows)
    return {"frame_jpeg": f["frame_jpeg"], "frame_offsets": offsets, "by_camera": by_camera}
