"""run.mcap (companion.recording.mcap_log): a synthetic log.npz exported and read back with the mcap reader."""

import json
import logging
import sys

import numpy as np
import pytest
from mcap.reader import make_reader

from companion.recording.foxglove import COMPRESSED_IMAGE, LOG, SCHEMAS
from companion.recording.mcap_log import CONTACT_FIELDS, LOAD_POSES, STEP_FIELDS, export_log, write_beside_log, write_run_mcap

T, S = 50, 25  # log samples (50 Hz) and companion steps (25 Hz)
SCKF_KEYS = ("t_sckf", "p_corr_sckf", "q_corr_sckf", *STEP_FIELDS.values())


def synthetic_log(n: int, rate_hz: float = 50.0) -> dict[str, np.ndarray]:
    """A log.npz's arrays for ``n`` links: poses, thrusts and the companion's step log."""
    rng = np.random.default_rng(n)

    def quats(*shape):
        q = rng.normal(size=(*shape, 4))
        return q / np.linalg.norm(q, axis=-1, keepdims=True)

    t = np.arange(T) / rate_hz
    t_sckf = t[::2][:S]
    log = {"t": t, "thrust": rng.uniform(0, 8, (T, n, 8)), "t_sckf": t_sckf,
           "iterations": rng.integers(1, 5, S), "global_applied": rng.random((S, 1)) < 0.5,
           "nis_max_sckf": rng.uniform(0, 10, S), "corrected_sckf": rng.random((S, n)) < 0.5,
           "cycle_us": rng.integers(100, 900, S)}
    for kind in ("true", "ekf", "target"):
        log[f"p_{kind}"], log[f"q_{kind}"] = rng.normal(size=(T, n, 3)), quats(T, n)
    log["p_corr_sckf"], log["q_corr_sckf"] = rng.normal(size=(S, n, 3)), quats(S, n)
    for key in ("con_pos_before", "con_pos_after", "con_vel_before", "con_vel_after"):
        log[key] = rng.uniform(0, 0.1, (S, n - 1))
    log["nis_max_sckf"][3] = np.nan  # a step without a NIS
    return log


def expected_topics(n: int, dropped: tuple[str, ...] = ()) -> set[str]:
    per_link = {"truth", "ekf", "corrected", "target", "thrust"} - set(dropped)
    topics = {"/tf", "/scene", "/companion/step"} - set(dropped)
    return topics | {f"/link{i}/{name}" for i in range(1, n + 1) for name in per_link}


def read_back(path):
    """``(summary, {topic: [(log_time, publish_time, sequence, decoded message)]})``."""
    with open(path, "rb") as f:
        reader = make_reader(f)
        summary = reader.get_summary()
        out: dict[str, list] = {}
        for schema, channel, message in reader.iter_messages(log_time_order=False):
            assert schema.encoding == "jsonschema" and channel.message_encoding == "json"
            out.setdefault(channel.topic, []).append(
                (message.log_time, message.publish_time, message.sequence, json.loads(message.data)))
    return summary, out


def ns(t) -> list[int]:
    return np.round(np.asarray(t) * 1e9).astype(np.int64).tolist()


@pytest.mark.parametrize("n", [2, 3])
def test_every_channel_holds_the_log_at_its_times(tmp_path, n):
    log = synthetic_log(n)
    counts = export_log(log, tmp_path / "run.mcap")
    summary, messages = read_back(tmp_path / "run.mcap")
    assert set(counts) == set(messages) == {c.topic for c in summary.channels.values()} == expected_topics(n)
    # (no STATUSTEXT, no camera in the log)
    assert {s.name for s in summary.schemas.values()} == set(SCHEMAS) - {LOG, COMPRESSED_IMAGE}
    for topic, rows in messages.items():
        stamps = ns(log["t_sckf"] if topic in ("/companion/step",) or topic.endswith("/corrected") else log["t"])
        assert counts[topic] == len(rows) == summary.statistics.channel_message_counts[
            next(c.id for c in summary.channels.values() if c.topic == topic)]
        assert [r[0] for r in rows] == [r[1] for r in rows] == stamps  # log and publish time: the log's t
        assert [r[2] for r in rows] == list(range(len(rows)))
    for i in range(n):
        for name, p_key, q_key, t_key in (("truth", "p_true", "q_true", "t"), ("ekf", "p_ekf", "q_ekf", "t"),
                                          ("target", "p_target", "q_target", "t"),
                                          ("corrected", "p_corr_sckf", "q_corr_sckf", "t_sckf")):
            for k, (log_time, _, _, m) in enumerate(messages[f"/link{i + 1}/{name}"]):
                assert m["frame_id"] == "world"
                assert m["timestamp"]["sec"] * 10**9 + m["timestamp"]["nsec"] == log_time
                pos, rot = m["pose"]["position"], m["pose"]["orientation"]
                assert [pos["x"], pos["y"], pos["z"]] == log[p_key][k, i].tolist()
                assert [rot["w"], rot["x"], rot["y"], rot["z"]] == log[q_key][k, i].tolist()
        thrust = [m["thrust_n"] for *_, m in messages[f"/link{i + 1}/thrust"]]
        assert thrust == log["thrust"][:, i].tolist()


def test_tf_scene_and_step_messages(tmp_path):
    n, log = 3, synthetic_log(3)
    (tmp_path / "scenario.toml").write_text("[skeleton]\nlink_length_m = 0.8\n")
    np.savez_compressed(tmp_path / "log.npz", **log)
    path, _ = write_run_mcap(tmp_path)
    assert path == tmp_path / "run.mcap"
    _, messages = read_back(path)
    k = 7
    tf = messages["/tf"][k][3]["transforms"]
    assert [(f["parent_frame_id"], f["child_frame_id"]) for f in tf] == [("world", f"link{i}") for i in (1, 2, 3)]
    assert [f["translation"]["z"] for f in tf] == log["p_true"][k, :, 2].tolist()
    entities = messages["/scene"][k][3]["entities"]
    assert [e["id"] for e in entities] == ["link1", "link2", "link3", "cable1", "cable2"]
    assert entities[0]["cubes"][0]["size"] == {"x": 0.8, "y": 0.1, "z": 0.1}
    assert entities[0]["cubes"][0]["pose"]["position"]["x"] == log["p_true"][k, 0, 0]
    line = entities[3]["lines"][0]
    assert [pt["y"] for pt in line["points"]] == log["p_true"][k, :2, 1].tolist()
    steps = [m for *_, m in messages["/companion/step"]]
    assert set(steps[0]) == {"timestamp", *STEP_FIELDS}
    assert [s["con_pos_after"] for s in steps] == log["con_pos_after"].tolist()
    assert [s["global_applied"] for s in steps] == log["global_applied"].tolist()
    assert [s["iterations"] for s in steps] == log["iterations"].tolist()
    assert steps[3]["nis_max"] is None and steps[4]["nis_max"] == log["nis_max_sckf"][4]
    assert len(steps[0]["corrected"]) == n


def test_scene_without_link_length_is_a_cube_and_at_most_50_hz(tmp_path):
    log = synthetic_log(2, rate_hz=200.0)
    counts = export_log(log, tmp_path / "run.mcap")
    assert counts["/tf"] == T and counts["/scene"] == len(range(0, T, 4))
    _, messages = read_back(tmp_path / "run.mcap")
    assert [r[0] for r in messages["/scene"]] == ns(log["t"][::4])
    assert messages["/scene"][0][3]["entities"][0]["cubes"][0]["size"] == {"x": 0.4, "y": 0.4, "z": 0.4}


@pytest.mark.parametrize("missing, dropped", [
    (SCKF_KEYS, ("corrected", "/companion/step")),
    (("t_sckf",), ("corrected", "/companion/step")),
    (("q_corr_sckf",), ("corrected",)),
    (("p_ekf",), ("ekf",)),
    (("thrust",), ("thrust",)),
    (("p_true",), ("truth", "/tf", "/scene")),
])
def test_a_missing_key_drops_only_its_channels(tmp_path, missing, dropped):
    log = {k: v for k, v in synthetic_log(2).items() if k not in missing}
    counts = export_log(log, tmp_path / "run.mcap")
    _, messages = read_back(tmp_path / "run.mcap")
    assert set(counts) == set(messages) == expected_topics(2, dropped)


def test_partial_step_log_keeps_the_fields_it_has(tmp_path):
    log = {k: v for k, v in synthetic_log(2).items() if k not in ("iterations", "con_vel_after")}
    export_log(log, tmp_path / "run.mcap")
    _, messages = read_back(tmp_path / "run.mcap")
    assert set(messages["/companion/step"][0][3]) == {"timestamp", *STEP_FIELDS} - {"iterations", "con_vel_after"}


def test_a_log_without_channels_is_refused(tmp_path):
    with pytest.raises(ValueError, match="none of the arrays"):
        export_log({"pspm_t": np.zeros(3)}, tmp_path / "run.mcap")
    assert not (tmp_path / "run.mcap").exists()


def test_after_a_run_a_missing_mcap_package_is_one_log_line(tmp_path, monkeypatch, caplog):
    np.savez_compressed(tmp_path / "log.npz", **synthetic_log(2))
    monkeypatch.setitem(sys.modules, "mcap.writer", None)  # import mcap.writer raises ImportError
    with caplog.at_level(logging.INFO):
        assert write_beside_log(tmp_path) is None
    assert [r.getMessage() for r in caplog.records if "run.mcap" in r.getMessage()] == [
        "run.mcap not written: the mcap package is missing; pip install 'aerial-skeleton-stack[view]' "
        "(or pip install 'mcap>=1.1')"]
    assert not (tmp_path / "run.mcap").exists()


def test_after_a_run_an_unreadable_log_is_a_warning(tmp_path, caplog):
    (tmp_path / "log.npz").write_bytes(b"not a zip")
    with caplog.at_level(logging.WARNING):
        assert write_beside_log(tmp_path) is None
    assert any("run.mcap not written" in r.getMessage() for r in caplog.records)


@pytest.mark.parametrize("rows_at_once", [1, 7, 10_000])
def test_the_messages_made_row_block_by_row_block_give_the_same_file(tmp_path, monkeypatch, rows_at_once):
    from companion.recording import mcap_log

    log = synthetic_log(3)
    export_log(log, tmp_path / "default.mcap")
    monkeypatch.setattr(mcap_log, "_ROWS_AT_ONCE", rows_at_once)
    export_log(log, tmp_path / "blocks.mcap")
    assert (tmp_path / "blocks.mcap").read_bytes() == (tmp_path / "default.mcap").read_bytes()


def test_a_log_whose_time_goes_back_keeps_each_message_with_its_own_sample(tmp_path):
    log = synthetic_log(2)
    log["t"] = log["t"].copy()
    log["t"][[10, 11]] = log["t"][[11, 10]]  # two samples out of order
    export_log(log, tmp_path / "run.mcap")
    _, messages = read_back(tmp_path / "run.mcap")
    for topic in ("/link1/truth", "/link2/ekf", "/tf"):
        by_sequence = {seq: (log_time, m) for log_time, _, seq, m in messages[topic]}
        assert sorted(by_sequence) == list(range(T))
        for k, (log_time, m) in by_sequence.items():
            assert log_time == ns([log["t"][k]])[0]
    pos = {seq: m["pose"]["position"] for _, _, seq, m in messages["/link1/truth"]}
    assert [pos[10]["x"], pos[11]["x"]] == [log["p_true"][10, 0, 0], log["p_true"][11, 0, 0]]


def test_the_wall_contact_and_the_slung_load_get_their_own_channels(tmp_path):
    """A wall push's contact series in log.npz and a slung load's poses in load.npz beside it."""
    rng = np.random.default_rng(7)
    log = synthetic_log(1)
    log.update(contact_t=log["t"], contact_force_true_n=rng.uniform(0, 5, T), contact_force_cmd_n=np.full(T, 3.0),
               contact_force_hat_n=rng.uniform(0, 5, T), contact_wrench_true=rng.normal(size=(T, 6)),
               contact_wrench_hat=rng.normal(size=(T, 6)), contact_engaged=rng.random(T) < 0.5)
    np.savez(tmp_path / "log.npz", **log)
    load = {"load_t": np.arange(40) / 20.0}
    for _, p_key, q_key in LOAD_POSES:
        q = rng.normal(size=(40, 4))
        load[p_key], load[q_key] = rng.normal(size=(40, 3)), q / np.linalg.norm(q, axis=1, keepdims=True)
    np.savez(tmp_path / "load.npz", **load)
    _, counts = write_run_mcap(tmp_path)
    _, messages = read_back(tmp_path / "run.mcap")
    assert set(counts) == set(messages) == expected_topics(1) | {"/contact", "/load/truth", "/load/ekf", "/load/ukf"}
    contact = [m for *_, m in messages["/contact"]]
    assert [r[0] for r in messages["/contact"]] == ns(log["contact_t"])
    assert set(contact[0]) == {"timestamp", *CONTACT_FIELDS}
    assert [m["force_true_n"] for m in contact] == log["contact_force_true_n"].tolist()
    assert [m["wrench_hat"] for m in contact] == log["contact_wrench_hat"].tolist()
    for name, p_key, q_key in LOAD_POSES:
        rows = messages[f"/load/{name}"]
        assert [r[0] for r in rows] == ns(load["load_t"])
        pos, rot = rows[5][3]["pose"]["position"], rows[5][3]["pose"]["orientation"]
        assert [pos["x"], pos["y"], pos["z"]] == load[p_key][5].tolist()
        assert [rot["w"], rot["x"], rot["y"], rot["z"]] == load[q_key][5].tolist()


def test_a_load_pose_of_the_wrong_width_is_left_out(tmp_path):
    log = synthetic_log(2)
    log.update(load_t=np.arange(10.0), load_p_true=np.zeros((10, 2)), load_q_true=np.tile([1.0, 0, 0, 0], (10, 1)),
               load_ekf_p=np.zeros((10, 3)), load_ekf_q=np.tile([1.0, 0, 0, 0], (10, 1)))
    counts = export_log(log, tmp_path / "run.mcap")
    assert "/load/truth" not in counts and counts["/load/ekf"] == 10 and "/load/ukf" not in counts


def test_the_targets_are_written_in_the_truths_frame(tmp_path):
    """A run flown from home (``home_offset_w_m``): ``/link{i}/target`` holds the targets less it."""
    log = synthetic_log(2)
    log["home_offset_w_m"] = np.array([0.3, -0.2, 1.5])
    export_log(log, tmp_path / "run.mcap")
    _, messages = read_back(tmp_path / "run.mcap")
    for i in range(2):
        got = [[m["pose"]["position"][a] for a in "xyz"] for *_, m in messages[f"/link{i + 1}/target"]]
        np.testing.assert_allclose(got, log["p_target"][:, i] - log["home_offset_w_m"], atol=1e-12)
