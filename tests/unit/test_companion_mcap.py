"""companion.mcap (companion.recording.companion_mcap): a group's links numbered by their place in the
chain, the eq. 3 joint errors of each step, health rows and STATUSTEXT severities, read back."""

import json

import numpy as np
import pytest
from mcap.reader import make_reader

from companion.estimation.constraints import joint_error_norms
from companion.recording.companion_mcap import write_companion_mcap
from companion.recording.foxglove import LOG_LEVEL_OF_SEVERITY

S, N = 6, 3
D = np.tile([0.5, 0.0, 0.0], (N, 1))


def step_log(seed=0):
    rng = np.random.default_rng(seed)
    q = rng.normal(size=(S, N, 4))
    q /= np.linalg.norm(q, axis=-1, keepdims=True)
    log = {"t_sckf": 0.05 * np.arange(S), "iterations": np.ones(S, int), "global_applied": np.ones(S, bool),
           "corrected_sckf": np.ones((S, N), bool), "w_sckf": rng.normal(size=(S, N, 3))}
    for kind in ("ekf", "corr"):
        log[f"p_{kind}_sckf"], log[f"v_{kind}_sckf"] = rng.normal(size=(S, N, 3)), rng.normal(size=(S, N, 3))
        log[f"q_{kind}_sckf"] = q
    return log


def read(path):
    with open(path, "rb") as f:
        return [(ch.topic, m.log_time, json.loads(m.data)) for _, ch, m in make_reader(f).iter_messages()]


@pytest.mark.parametrize("first_link", [1, 4])
def test_a_groups_links_keep_their_place_in_the_chain(tmp_path, first_link):
    log = step_log()
    counts = write_companion_mcap(tmp_path / "c.mcap", log, D, first_link=first_link)
    links = range(first_link, first_link + N)
    assert counts == {"/companion/step": S, **{f"/link{i}/{k}": S for i in links
                                               for k in ("state_in", "corrected", "correction")}}
    msgs = read(tmp_path / "c.mcap")
    before, _ = joint_error_norms(log["p_ekf_sckf"], log["v_ekf_sckf"], log["q_ekf_sckf"], log["w_sckf"], D)
    after, _ = joint_error_norms(log["p_corr_sckf"], log["v_corr_sckf"], log["q_corr_sckf"], log["w_sckf"], D)
    steps = [m for t, _, m in msgs if t == "/companion/step"]
    np.testing.assert_allclose([m["con_pos_before"] for m in steps], before)
    np.testing.assert_allclose([m["con_pos_after"] for m in steps], after)
    last = [m for t, _, m in msgs if t == f"/link{first_link + N - 1}/state_in"]
    np.testing.assert_allclose([m["pose"]["position"]["x"] for m in last], log["p_ekf_sckf"][:, -1, 0])


@pytest.mark.parametrize("severity", range(8))
def test_statustext_levels_and_health_rows(tmp_path, severity):
    health = [(1.0, [{"link": 2, "state_hz": 50.0, "age_ms": float("nan"), "rejected": 3, "status": "gate",
                      "latency_p50_ms": None, "latency_p99_ms": 12.0}])]
    write_companion_mcap(tmp_path / "c.mcap", step_log(), D, health=health, statustext=[(2.5, 3, severity, "hello")])
    msgs = {t: (ns, m) for t, ns, m in read(tmp_path / "c.mcap") if t in ("/statustext", "/link2/health")}
    ns, text = msgs["/statustext"]
    assert ns == 2_500_000_000 and text["level"] == LOG_LEVEL_OF_SEVERITY[severity] and text["name"] == "link 3"
    assert text["level"] == {0: 5, 1: 5, 2: 5, 3: 4, 4: 3, 5: 2, 6: 2, 7: 1}[severity]
    ns, row = msgs["/link2/health"]
    assert ns == 1_000_000_000 and row["rejected"] == 3 and row["left_out"] == 1.0
    assert row["age_ms"] is None and row["latency_p50_ms"] is None and row["latency_p99_ms"] == 12.0


def test_a_runs_statustexts_are_its_log_channel(tmp_path):
    """run.mcap's /statustext from a SITL log's statustext_* arrays (batch: the firmware's events;
    fleet: the vehicles' flight logs), in time order; arrays that do not fit give no channel."""
    from companion.recording.mcap_log import export_log
    from link_firmware_sim.events import statustext_arrays

    from .test_mcap_log import synthetic_log

    log = synthetic_log(2) | statustext_arrays([(0.5, 2, 4, "thrust at the rotors' limit"), (0.1, 1, 6, "GPS ok")])
    counts = export_log(log, tmp_path / "run.mcap")
    assert counts["/statustext"] == 2
    texts = [(ns, m["name"], m["level"], m["message"]) for t, ns, m in read(tmp_path / "run.mcap") if t == "/statustext"]
    assert texts == [(100_000_000, "link 1", 2, "GPS ok"), (500_000_000, "link 2", 3, "thrust at the rotors' limit")]
    log["statustext_link"] = log["statustext_link"][:1]
    assert "/statustext" not in export_log(log, tmp_path / "bad.mcap")
