"""The truth is judged against the targets in the simulator's frame (sitl.metrics.planned_positions):
the companion flies the trajectory from its home, in the links' frame."""

from __future__ import annotations

import numpy as np
import pytest

from companion.trajectory import planned_positions
from sitl.campaign.fault_campaign import _load
from sitl.campaign.faults import FaultEvent, event_figures
from sitl.metrics import outage_split


def _log(home):
    """Three links tracking the trajectory exactly in the world, their targets moved by ``home``
    (where their receivers put the chain at the start, less the anchor)."""
    t = np.arange(0.0, 10.0, 0.02)
    truth = np.stack([np.stack([np.sin(t), np.full_like(t, i), 2.0 + 0.1 * t], axis=-1) for i in range(3)], axis=1)
    log = {"t": t, "p_true": truth, "p_target": truth + np.asarray(home), "p_ctrl": truth + np.asarray(home)}
    if home is not None:
        log["home_offset_w_m"] = np.asarray(home, dtype=float)
    return log


@pytest.mark.parametrize("home", [(0.3, -0.2, 1.5), (0.0, 0.0, 0.0)])
def test_a_chain_flying_its_trajectory_from_home_tracks_it_exactly_in_the_world(home):
    log = _log(home)
    np.testing.assert_allclose(planned_positions(log), log["p_true"], atol=1e-12)
    split = outage_split(log, 0.0, [{"start_s": 2.0, "end_s": 4.0, "kind": "gps"}])
    for part in (split["during_outages"], split["outside_outages"]):
        np.testing.assert_allclose(part["rms_track_true_m"], 0.0, atol=1e-12)
    figures = event_figures(FaultEvent("gps", 1, 2.0, 4.0), log)
    assert figures["track_during_m"] == pytest.approx(0.0, abs=1e-12)


def test_a_log_without_a_home_is_judged_as_logged():
    log = _log((0.3, -0.2, 1.5))
    del log["home_offset_w_m"]
    np.testing.assert_array_equal(planned_positions(log), log["p_target"])
    worst = event_figures(FaultEvent("gps", 1, 2.0, 4.0), log)["track_during_m"]
    assert worst == pytest.approx(np.sqrt(0.3**2 + 0.2**2 + 1.5**2))


def test_the_fault_campaign_reads_a_flights_home_with_its_log(tmp_path):
    log = _log((0.3, -0.2, 1.5))
    np.savez(tmp_path / "log.npz", **log)
    _, loaded = _load(tmp_path)
    np.testing.assert_array_equal(loaded["home_offset_w_m"], log["home_offset_w_m"])
    assert event_figures(FaultEvent("gps", 1, 2.0, 4.0), loaded)["track_during_m"] == pytest.approx(0.0, abs=1e-12)


def test_the_tracking_plot_draws_target_estimate_and_truth_in_one_frame(monkeypatch, tmp_path):
    """The estimate is in the links' frame like the targets: the plot takes the home off both, so a
    chain tracking its targets exactly draws three lines on one another."""
    import sitl.plots as plots

    drawn = {}

    def keep(fig, title, path):
        drawn["axes"] = fig.axes

    monkeypatch.setattr(plots, "_save", keep)
    log = _log((0.3, -0.2, 1.5))
    plots.plot_tracking(log, tmp_path / "tracking.png")
    for ax in drawn["axes"]:
        lines = {line.get_label(): line.get_ydata() for line in ax.get_lines()}
        np.testing.assert_allclose(lines["estimate"], lines["true"], atol=1e-12)
        np.testing.assert_allclose(lines["target"], lines["true"], atol=1e-12)
