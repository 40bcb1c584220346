"""The view's side panel: what to show, the links' conditions and the figures plotted over time.

The time controls differ between a replay and a live run (:mod:`sitl.view.app`); this module holds
what both have: the checkboxes that show or hide each part of the scene, the colour legend with
each link's condition, and a plot per figure (:data:`~sitl.view.frame.FIGURES`).
"""

from __future__ import annotations

import math
import threading
from collections import deque

import numpy as np

from companion.linkstate import CONDITIONS, condition

from .frame import FIGURES, ViewFrame
from .scene import CONDITION_COLORS, GHOST_COLORS, Scene

__all__ = ["Panel", "PLOT_POINTS", "PLOTS", "LOG_PLOTS"]

#: points a plot keeps (a longer series is thinned to this many)
PLOT_POINTS = 1500
#: plots on a logarithmic axis (the errors before and after a step are orders of magnitude apart)
LOG_PLOTS = frozenset({"constraint error [mm]"})
#: the plots: title -> the figures drawn in it (each a line)
PLOTS = {
    "constraint error [mm]": ("constraint_before_mm", "constraint_after_mm"),
    "tracking error [cm]": ("tracking_cm",),
    "correction latency [ms]": ("latency_ms",),
    "global step (fraction of groups)": ("global_step",),
}
_STROKES = ("#d62728", "#1f77b4")
_CHECKS = (("truth", "truth (links, rotors)"), ("ekf", "link EKF estimates"), ("corrected", "SCKF-corrected estimates"),
           ("target", "targets"), ("corrections", "corrections (arrows)"), ("cables", "cables / joints"),
           ("labels", "labels"))


def _swatch(rgb) -> str:
    return f"<span style='color:rgb{tuple(rgb)}'>&#9632;</span>"


def _thin(t: np.ndarray, columns: list[np.ndarray], log: bool = False) -> tuple[np.ndarray, ...]:
    """Rows where every column is finite (and positive for a ``log`` plot), at most
    :data:`PLOT_POINTS` of them evenly spaced."""
    ok = np.isfinite(t)
    for c in columns:
        ok &= np.isfinite(c)
    if log:
        for c in columns:
            ok &= c > 0
    idx = np.flatnonzero(ok)
    if idx.size > PLOT_POINTS:
        idx = idx[np.linspace(0, idx.size - 1, PLOT_POINTS).round().astype(int)]
    return (t[idx].astype(np.float64), *(c[idx].astype(np.float64) for c in columns))


class Panel:
    """The shared part of the panel in ``server``'s GUI, acting on ``scene``."""

    def __init__(self, server, scene: Scene, title: str):
        self.server, self.scene = server, scene
        gui = server.gui
        gui.configure_theme(dark_mode=False, control_width="large")
        self.header = gui.add_markdown(f"**{title}**")
        self.clock = gui.add_markdown("t = -")
        with gui.add_folder("Show"):
            for key, label in _CHECKS:
                box = gui.add_checkbox(label, initial_value=scene.visible[key])
                box.on_update(lambda ev, key=key: scene.set_visible(key, ev.target.value))
            gain = gui.add_slider("arrow gain (x)", min=1.0, max=200.0, step=1.0, initial_value=scene.arrow_gain)
            gain.on_update(lambda ev: setattr(scene, "arrow_gain", float(ev.target.value)))
        with gui.add_folder("Links"):
            legend = " ".join(f"{_swatch(CONDITION_COLORS[c])} {c}" for c in CONDITIONS)
            ghosts = " ".join(f"{_swatch(rgb)} {k}" for k, rgb in GHOST_COLORS.items())
            gui.add_markdown(f"{legend}<br>ghosts: {ghosts}")
            self.states = gui.add_markdown("-")
        self.plots: dict[str, object] = {}
        self._series: dict[str, deque] = {}
        self._lock = threading.Lock()
        with gui.add_folder("Figures"):
            for title_, keys in PLOTS.items():
                self.plots[title_] = gui.add_uplot(
                    data=(np.zeros(0),) + tuple(np.zeros(0) for _ in keys),
                    series=({"label": "t [s]"},) + tuple({"label": FIGURES[k][0].split(" (")[0], "stroke": _STROKES[j],
                                                          "width": 1.5} for j, k in enumerate(keys)),
                    scales={"x": {"time": False}, **({"y": {"distr": 3}} if title_ in LOG_PLOTS else {})},
                    title=title_, aspect=2.0, visible=False)
        self._states_text = ""

    def show_frame(self, f: ViewFrame) -> None:
        """The clock and each link's condition at frame ``f``."""
        step = "" if f.step_t_s is None else f" (companion step {f.step_t_s:.2f} s)"
        self.clock.content = f"t = **{f.t_s:.2f} s**{step}"
        if f.link_state is not None:
            text = " · ".join(f"{_swatch(CONDITION_COLORS[c])} {i + 1}: {c}"
                              for i, c in enumerate(condition(w) for w in f.link_state))
        else:
            text = "(the log holds no link states)"
        if text != self._states_text:
            self.states.content = text
            self._states_text = text

    def set_series(self, series: dict[str, tuple[np.ndarray, np.ndarray]]) -> None:
        """Plot whole series (a replay): figure -> (times, values); plots without data stay hidden."""
        for title, keys in PLOTS.items():
            have = [series[k] for k in keys if k in series]
            if len(have) != len(keys):
                continue
            t = have[0][0]
            if any(len(s[0]) != len(t) for s in have):
                continue
            data = _thin(np.asarray(t, float), [np.asarray(s[1], float) for s in have], title in LOG_PLOTS)
            if data[0].size:
                self.plots[title].data = data
                self.plots[title].visible = True

    def append(self, f: ViewFrame, keep_s: float = 60.0) -> None:
        """Add frame ``f``'s figures to the live plots' last ``keep_s`` seconds (drawn by :meth:`redraw`)."""
        if not f.figures:
            return
        with self._lock:
            for key, value in f.figures.items():
                buf = self._series.setdefault(key, deque())
                buf.append((f.t_s, value))
                while buf and buf[0][0] < f.t_s - keep_s:
                    buf.popleft()

    def redraw(self) -> None:
        """Draw the live plots from what :meth:`append` collected."""
        with self._lock:
            series = {k: (np.array([r[0] for r in v]), np.array([r[1] for r in v])) for k, v in self._series.items()}
        # a plot's lines need one time axis: the first figure's, the others taken at its times
        for title, keys in PLOTS.items():
            if not all(k in series and series[k][0].size for k in keys):
                continue
            t = series[keys[0]][0]
            cols = [np.interp(t, *series[k]) if len(series[k][0]) != len(t) else series[k][1] for k in keys]
            data = _thin(t, cols, title in LOG_PLOTS)
            if data[0].size and not math.isnan(float(data[0][-1])):
                self.plots[title].data = data
                self.plots[title].visible = True
