"""run.mcap's per-link state and correction channels (companion.recording.mcap_log): ``/link{i}/state``
and ``/link{i}/correction`` exported from a synthetic log and read back with the mcap reader."""

import json

import numpy as np
import pytest
from mcap.reader import make_reader

from companion.recording.mcap_log import STATE_BITS, export_log

K, S, N = 40, 16, 3
#: the word's bits by name, as the dialect and companion.linkstate define them
BITS = {"ekf_ok": 1, "armed": 2, "correction_active": 4, "gps_fault": 8, "carried": 16, "excluded": 32, "down": 64}


def synthetic_log(n: int = N) -> dict[str, np.ndarray]:
    rng = np.random.default_rng(42)
    t = np.arange(K) / 50.0
    q = np.tile([1.0, 0, 0, 0], (K, n, 1))
    words = (np.arange(K * n).reshape(K, n) * 37) % 128  # every bit set and clear somewhere
    latency = rng.uniform(5, 60, (K, n))
    latency[rng.random((K, n)) < 0.3] = np.nan
    latency[0] = np.nan
    return {"t": t, "p_true": rng.normal(size=(K, n, 3)), "q_true": q,
            "link_state": words.astype(np.uint8), "correction_latency_ms": latency,
            "t_sckf": 0.01 + np.arange(S) / 20.0,
            "p_ekf_sckf": rng.normal(size=(S, n, 3)), "p_corr_sckf": rng.normal(size=(S, n, 3)),
            "corrected_sckf": rng.random((S, n)) < 0.5}


def read_back(path) -> dict[str, list[tuple[int, dict]]]:
    with open(path, "rb") as f:
        out: dict[str, list] = {}
        for _, channel, message in make_reader(f).iter_messages(log_time_order=True):
            out.setdefault(channel.topic, []).append((message.log_time, json.loads(message.data)))
    return out


def ns(t) -> list[int]:
    return np.round(np.asarray(t) * 1e9).astype(np.int64).tolist()


def test_state_bits_are_the_documented_ones():
    assert STATE_BITS == BITS


@pytest.fixture
def exported(tmp_path):
    log = synthetic_log()
    counts = export_log(log, tmp_path / "run.mcap")
    return log, counts, read_back(tmp_path / "run.mcap")


def test_one_message_per_row(exported):
    log, counts, messages = exported
    assert all(np.bincount(log["link_state"].ravel() >> b & 1, minlength=2).all() for b in range(7))
    for i in range(1, N + 1):
        assert counts[f"/link{i}/state"] == len(messages[f"/link{i}/state"]) == K
        assert counts[f"/link{i}/correction"] == len(messages[f"/link{i}/correction"]) == S
        assert [m[0] for m in messages[f"/link{i}/state"]] == ns(log["t"])
        assert [m[0] for m in messages[f"/link{i}/correction"]] == ns(log["t_sckf"])
    assert f"/link{N + 1}/state" not in counts


def test_state_messages_hold_the_word_and_its_bits(exported):
    log, _, messages = exported
    for i in range(N):
        for k, (_, msg) in enumerate(messages[f"/link{i + 1}/state"]):
            word = int(log["link_state"][k, i])
            assert msg["state_word"] == word
            assert set(msg) == {"timestamp", "state_word", "correction_latency_ms", *BITS}
            for name, bit in BITS.items():
                assert msg[name] in (0, 1) and type(msg[name]) is int
                assert msg[name] == (1 if word & bit else 0), (name, word)
            latency = log["correction_latency_ms"][k, i]
            if np.isnan(latency):
                assert msg["correction_latency_ms"] is None
            else:
                assert msg["correction_latency_ms"] == pytest.approx(latency)
            assert msg["timestamp"] == {"sec": ns(log["t"])[k] // 10**9, "nsec": ns(log["t"])[k] % 10**9}


def test_correction_messages_hold_the_move(exported):
    log, _, messages = exported
    for i in range(N):
        for j, (_, msg) in enumerate(messages[f"/link{i + 1}/correction"]):
            assert set(msg) == {"timestamp", "delta_p_m", "corrected"}
            np.testing.assert_allclose(msg["delta_p_m"], log["p_corr_sckf"][j, i] - log["p_ekf_sckf"][j, i],
                                       rtol=1e-12)
            assert msg["corrected"] == int(log["corrected_sckf"][j, i])


def test_a_nan_move_is_null(tmp_path):
    log = synthetic_log()
    log["p_ekf_sckf"][2, 1] = np.nan  # the step had no estimate of link 2
    export_log(log, tmp_path / "run.mcap")
    msg = read_back(tmp_path / "run.mcap")["/link2/correction"][2][1]
    assert msg["delta_p_m"] == [None, None, None]


@pytest.mark.parametrize("drop, present, absent", [
    ("correction_latency_ms", {"state_word", "down"}, {"correction_latency_ms"}),
    ("corrected_sckf", {"delta_p_m"}, {"corrected"}),
])
def test_optional_fields(tmp_path, drop, present, absent):
    log = synthetic_log()
    del log[drop]
    export_log(log, tmp_path / "run.mcap")
    messages = read_back(tmp_path / "run.mcap")
    topic = "/link1/state" if drop == "correction_latency_ms" else "/link1/correction"
    fields = set(messages[topic][0][1])
    assert present <= fields and not absent & fields


@pytest.mark.parametrize("change", ["no link_state", "link_state width", "link_state rows", "no p_ekf_sckf",
                                    "p_corr_sckf width"])
def test_channels_need_their_arrays(tmp_path, change):
    log = synthetic_log()
    if change == "no link_state":
        del log["link_state"]
    elif change == "link_state width":
        log["link_state"] = log["link_state"][:, :2]
    elif change == "link_state rows":
        log["link_state"] = log["link_state"][:-1]
    elif change == "no p_ekf_sckf":
        del log["p_ekf_sckf"]
    else:
        log["p_corr_sckf"] = log["p_corr_sckf"][:, :2]
    counts = export_log(log, tmp_path / "run.mcap")
    state = change.startswith("link_state") or change == "no link_state"
    assert ("/link1/state" in counts) != state
    assert ("/link1/correction" in counts) == state
    assert "/link1/truth" in counts
