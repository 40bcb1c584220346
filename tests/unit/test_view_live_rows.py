"""The live view's rows: the chain's newest companion step from each engine's (sitl.view.live.
chain_step_row) and a flying fleet's newest rows from its log streams (sitl.view.fleet_rows)."""

import dataclasses
import types

import numpy as np
import pytest

from companion.estimation.constraints import joint_error_norms
from companion.logstream import LogStream
from link_firmware_sim.vehicle.hil import SITL_GPS_EPOCH_US
from companion.linkstate import DOWN, condition
from sitl.scenarios import load
from sitl.view.fleet_rows import KEEP_S, POLL_S, FleetRows, _Buffer
from sitl.view.live import chain_step_row

from ..paths import THREE_LINK

STATE_KEYS = ("p_ekf_sckf", "v_ekf_sckf", "q_ekf_sckf", "w_sckf", "p_corr_sckf", "v_corr_sckf", "q_corr_sckf")
WIDTHS = {"p": 3, "v": 3, "q": 4, "w": 3}
D4 = np.tile([0.5, 0.0, 0.0], (4, 1))


def _unit_quats(rng, *shape):
    q = rng.normal(size=(*shape, 4))
    return q / np.linalg.norm(q, axis=-1, keepdims=True)


def chain_state(seed: int, n: int = 4) -> dict[str, np.ndarray]:
    """A random chain's states: what a step used (``*_ekf_sckf``, ``w_sckf``) and made of them."""
    rng = np.random.default_rng(seed)
    return {"p_ekf_sckf": rng.normal(size=(n, 3)), "v_ekf_sckf": rng.normal(size=(n, 3)),
            "q_ekf_sckf": _unit_quats(rng, n), "w_sckf": rng.normal(size=(n, 3)),
            "p_corr_sckf": rng.normal(size=(n, 3)), "v_corr_sckf": rng.normal(size=(n, 3)),
            "q_corr_sckf": _unit_quats(rng, n)}


def engine_row(state, idx, t=1.0, applied=True):
    """An engine's newest step row for chain links ``idx`` of the chain's ``state``."""
    row = {key: state[key][idx] for key in STATE_KEYS}
    row.update(t_sckf=np.float64(t), global_applied=np.bool_(applied), corrected_sckf=np.ones(len(idx), bool))
    return row


def oracle(state, d=D4):
    before = joint_error_norms(state["p_ekf_sckf"], state["v_ekf_sckf"], state["q_ekf_sckf"], state["w_sckf"], d)
    after = joint_error_norms(state["p_corr_sckf"], state["v_corr_sckf"], state["q_corr_sckf"], state["w_sckf"], d)
    return {"con_pos_before": before[0], "con_vel_before": before[1],
            "con_pos_after": after[0], "con_vel_after": after[1]}


CHAIN_KEYS = (*STATE_KEYS, "con_pos_before", "con_vel_before", "con_pos_after", "con_vel_after")


@pytest.mark.parametrize("seed", range(5))
def test_single_engine_matches_the_joint_errors(seed):
    state = chain_state(seed)
    out = chain_step_row([(list(range(4)), engine_row(state, list(range(4)), t=2.5, applied=False))], 4, D4)
    assert out["t_sckf"] == 2.5 and type(out["t_sckf"]) is float
    assert out["global_applied"].tolist() == [False]
    expected = oracle(state)
    for key, value in expected.items():
        assert out[key].shape == (3,)
        np.testing.assert_allclose(out[key], value, rtol=1e-12, atol=1e-15)
    for key in STATE_KEYS:
        np.testing.assert_array_equal(out[key], state[key])
    assert expected["con_pos_before"].min() > 1e-3  # a random chain: the errors are not all zero


def test_a_consistent_chain_has_no_joint_error():
    rng = np.random.default_rng(7)
    q = np.tile([1.0, 0, 0, 0], (4, 1))
    p = np.array([[i * 1.0, 0.0, 2.0] for i in range(4)])  # tips meet: centres 1 m apart along x
    v = np.tile(rng.normal(size=3), (4, 1))
    state = {"p_ekf_sckf": p, "v_ekf_sckf": v, "q_ekf_sckf": q, "w_sckf": np.zeros((4, 3)),
             "p_corr_sckf": p + [0.0, 0.01, 0.0] * np.arange(4)[:, None], "v_corr_sckf": v, "q_corr_sckf": q}
    out = chain_step_row([(list(range(4)), engine_row(state, list(range(4))))], 4, D4)
    np.testing.assert_allclose(out["con_pos_before"], 0.0, atol=1e-12)
    np.testing.assert_allclose(out["con_vel_before"], 0.0, atol=1e-12)
    np.testing.assert_allclose(out["con_pos_after"], 0.01, atol=1e-12)


@pytest.mark.parametrize("layout", [([0, 1], [2, 3]), ([2, 3], [0, 1]), ([0, 2], [1, 3]), ([3], [0, 1, 2])])
@pytest.mark.filterwarnings("error")
def test_distributed_engines_give_the_whole_chain(layout):
    state = chain_state(11)
    whole = chain_step_row([(list(range(4)), engine_row(state, list(range(4)), t=3.0))], 4, D4)
    engines = [(list(idx), engine_row(state, list(idx), t=2.9 + 0.1 * j, applied=bool(j)))
               for j, idx in enumerate(layout)]
    out = chain_step_row(engines, 4, D4)
    for key in CHAIN_KEYS:
        np.testing.assert_allclose(out[key], whole[key], rtol=1e-12, err_msg=key)
    assert out["global_applied"].tolist() == [False, True]  # one per engine, in the engines' order
    assert out["t_sckf"] == pytest.approx(3.0)  # the newest engine's


@pytest.mark.filterwarnings("error")
def test_an_engine_without_a_row_is_skipped():
    state = chain_state(3)
    out = chain_step_row([([0, 1], {}), ([2, 3], engine_row(state, [2, 3], applied=True))], 4, D4)
    assert out["global_applied"].tolist() == [True]
    assert np.isnan(out["p_ekf_sckf"][:2]).all() and np.isnan(out["q_corr_sckf"][:2]).all()
    np.testing.assert_array_equal(out["p_ekf_sckf"][2:], state["p_ekf_sckf"][2:])
    # joints 0-1 and 1-2 touch a link without a state; joint 2-3 is the engine's own
    assert np.isnan(out["con_pos_before"][:2]).all()
    sub = {key: a[2:] for key, a in state.items()}
    np.testing.assert_allclose(out["con_pos_before"][2], oracle(sub, D4[2:])["con_pos_before"][0], rtol=1e-12)


@pytest.mark.filterwarnings("error")
def test_a_link_no_engine_covers_has_nan_rows():
    state = chain_state(5)
    out = chain_step_row([([0, 1], engine_row(state, [0, 1])), ([3], engine_row(state, [3]))], 4, D4)
    for key in STATE_KEYS:
        assert np.isnan(out[key][2]).all(), key
        assert np.isfinite(out[key][[0, 1, 3]]).all(), key
    assert out["global_applied"].shape == (2,)
    expected = oracle(state)
    np.testing.assert_allclose(out["con_pos_before"][0], expected["con_pos_before"][0], rtol=1e-12)
    np.testing.assert_allclose(out["con_vel_after"][0], expected["con_vel_after"][0], rtol=1e-12)
    assert np.isnan(out["con_pos_before"][1:]).all() and np.isnan(out["con_pos_after"][1:]).all()


@pytest.mark.parametrize("engines", [[], [([0, 1], {}), ([2, 3], {})], [(list(range(4)), {})]])
def test_no_engine_row_no_step_row(engines):
    assert chain_step_row(engines, 4, D4) is None


def test_a_row_without_a_global_flag_counts_as_not_applied():
    state = chain_state(2)
    row = engine_row(state, list(range(4)))
    del row["global_applied"]
    assert chain_step_row([(list(range(4)), row)], 4, D4)["global_applied"].tolist() == [False]


# ---- fleet_rows._Buffer ---------------------------------------------------------------------


class Writer:
    """A process's log stream: rows appended and flushed as the process does (closed after the
    test, :func:`_close_streams`)."""

    opened: list["Writer"] = []

    def __init__(self, path):
        self.stream = LogStream(path)
        self.rows: dict[str, list] = {}
        Writer.opened.append(self)

    def add(self, **row):
        for key, value in row.items():
            self.rows.setdefault(key, []).append(value)

    def flush(self):
        self.stream.flush(self.rows)


@pytest.fixture(autouse=True)
def _close_streams():
    yield
    while Writer.opened:
        Writer.opened.pop().stream.close()


def test_buffer_before_its_file_exists(tmp_path):
    b = _Buffer(tmp_path / "x.stream", "t")
    b.poll()
    assert b.at(0.0) is None and b.at(np.inf) is None
    assert b.newest_s == -np.inf


def test_buffer_rows_by_time(tmp_path):
    w = Writer(tmp_path / "x.stream")
    for k in range(11):
        w.add(t=0.1 * k, x=np.array([k, 2 * k]))
    w.flush()
    b = _Buffer(tmp_path / "x.stream", "t")
    assert b.at(0.5) is None  # not polled yet
    b.poll()
    assert b.newest_s == pytest.approx(1.0)
    assert b.at(-0.01) is None
    assert b.at(0.0)["x"].tolist() == [0, 0]
    assert b.at(0.55)["x"].tolist() == [5, 10]
    assert b.at(0.1 * 5)["x"].tolist() == [5, 10]  # exactly at a row's time
    assert b.at(99.0)["x"].tolist() == [10, 20]
    for k in range(11, 15):
        w.add(t=0.1 * k, x=np.array([k, 2 * k]))
    w.flush()
    assert b.at(99.0)["x"].tolist() == [10, 20]  # until the next poll
    b.poll()
    assert b.at(99.0)["x"].tolist() == [14, 28]
    assert b.at(1.25)["x"].tolist() == [12, 24]
    b.poll()  # nothing new: nothing changes
    assert len(b.t) == 15 and b.at(0.0)["x"].tolist() == [0, 0]


def test_buffer_drops_rows_older_than_keep_s(tmp_path):
    w = Writer(tmp_path / "x.stream")
    b = _Buffer(tmp_path / "x.stream", "t")
    written = []
    for chunk in range(5):
        for k in range(chunk * 16, (chunk + 1) * 16):
            w.add(t=0.5 * k, x=k)
            written.append(0.5 * k)
        w.flush()
        b.poll()
        newest = written[-1]
        kept = [t for t in written if t >= newest - KEEP_S]
        np.testing.assert_array_equal(b.t, kept)
        np.testing.assert_array_equal(b.rows["x"], [int(round(t / 0.5)) for t in kept])
    assert written[-1] - written[0] > 2 * KEEP_S  # the test did drop rows
    assert b.at(written[-1] - KEEP_S - 0.25) is None  # a dropped time: nothing at or before it
    assert b.at(written[-1] - KEEP_S)["x"] == int(round((written[-1] - KEEP_S) / 0.5))


def test_buffer_shift_is_added_to_the_times(tmp_path):
    w = Writer(tmp_path / "x.stream")
    for k in range(5):
        w.add(t_sckf=1000.0 + k, x=k)
    w.flush()
    b = _Buffer(tmp_path / "x.stream", "t_sckf", shift_s=-1000.0)
    b.poll()
    np.testing.assert_allclose(b.t, np.arange(5.0))
    assert b.newest_s == pytest.approx(4.0)
    assert b.at(2.5)["x"] == 2
    assert b.at(-0.5) is None


def test_buffer_ignores_a_key_that_appears_later_and_rows_without_the_stamp(tmp_path):
    w = Writer(tmp_path / "x.stream")
    w.add(t=0.0, x=0)
    w.flush()
    b = _Buffer(tmp_path / "x.stream", "t")
    b.poll()
    w.add(t=1.0, x=1, late=5)
    w.flush()
    b.poll()
    assert b.at(1.0) == {"t": 1.0, "x": 1}


# ---- fleet_rows.FleetRows -------------------------------------------------------------------

SCENARIO = load(THREE_LINK)[1]
N = 3
DT = 0.02
T_TRUTH = [k * DT for k in range(101)]  # 0 .. 2 s at 50 Hz
Q_ID = np.array([1.0, 0.0, 0.0, 0.0])


def harness(scenario=SCENARIO, down=(), t=T_TRUTH):
    return types.SimpleNamespace(scenario=scenario, n=N, down=set(down),
                                 rows={"t": list(t), "p_true": [np.full((N, 3), tk) for tk in t],
                                       "q_true": [np.tile(Q_ID, (N, 1)) for _ in t]})


def vehicle(out_dir, i, times, flags=3, folder=None) -> Writer:
    """Link ``i`` (1-based)'s firmware stream with rows at ``times``: its estimate is (i, t, 0)."""
    w = Writer(out_dir / (folder or f"link{i}") / f"link{i}_firmware.stream")
    for t in times:
        w.add(t=t, p_ekf=np.array([i, t, 0.0]), q_ekf=Q_ID, p_target=np.array([i, t, 1.0]), q_target=Q_ID,
              flags=flags)
    w.flush()
    return w


STEP_T = [0.005 + 0.05 * j for j in range(40)]  # 20 Hz


def companion(out_dir, times=STEP_T, links=range(N), folder="companion", offset=0.0, home=None) -> Writer:
    """A companion's stream with steps at ``times`` (+ ``offset``) over ``links``: step j corrected
    to (j, link, 0); ``home(j)``: step j's home offset (none logged without it)."""
    w = Writer(out_dir / folder / "companion_log.stream")
    links = list(links)
    m = len(links)
    for j, t in enumerate(times):
        extra = {} if home is None else {"home_offset_sckf": home(j)}
        w.add(t_sckf=t + offset, p_ekf_sckf=np.zeros((m, 3)), v_ekf_sckf=np.zeros((m, 3)),
              q_ekf_sckf=np.tile(Q_ID, (m, 1)), w_sckf=np.zeros((m, 3)),
              p_corr_sckf=np.array([[j, i, 0.0] for i in links]), v_corr_sckf=np.zeros((m, 3)),
              q_corr_sckf=np.tile(Q_ID, (m, 1)), global_applied=j % 2 == 0, corrected_sckf=np.ones(m, bool), **extra)
    w.flush()
    return w


class Clock:
    def __init__(self):
        self.now = 100.0

    def __call__(self):
        return self.now


def newest_step_before(t, times=STEP_T):
    return max(j for j, ts in enumerate(times) if ts <= t)


def test_three_link_companion_is_on_the_flight_controller_clock(tmp_path):
    assert SCENARIO.companion.time_base == "flight_controller"
    assert SCENARIO.companion.enabled and not SCENARIO.companion.distributed
    rows = FleetRows(harness(), tmp_path, clock=Clock())
    assert [b.shift_s for _, buffers in rows.companions for b in buffers] == [0.0]
    np.testing.assert_array_equal(rows.d, SCENARIO.skeleton.d_b_m)


def test_no_truth_yet_no_rows(tmp_path):
    assert FleetRows(harness(t=[]), tmp_path, clock=Clock()).newest() is None


def test_the_time_shown_is_the_newest_every_running_vehicle_has_logged(tmp_path):
    vehicle(tmp_path, 1, T_TRUTH[:76], flags=3)  # to 1.5 s
    vehicle(tmp_path, 2, T_TRUTH[:61], flags=1)  # to 1.2 s: the slowest
    vehicle(tmp_path, 3, T_TRUTH[2::5], flags=11)  # 10 Hz, to 1.94 s
    companion(tmp_path)
    t, row, step = FleetRows(harness(), tmp_path, clock=Clock()).newest()
    assert t == T_TRUTH[60] != T_TRUTH[-1]  # not the newest truth
    np.testing.assert_array_equal(row["p_true"], np.full((N, 3), T_TRUTH[60]))
    assert row["t"] == t
    np.testing.assert_array_equal(row["p_ekf"], [[1, T_TRUTH[60], 0], [2, T_TRUTH[60], 0], [3, T_TRUTH[57], 0]])
    np.testing.assert_array_equal(row["p_target"][:, 2], 1.0)
    assert row["q_ekf"].shape == (N, 4) and row["q_target"].shape == (N, 4)
    assert row["link_state"].dtype == np.uint8 and row["link_state"].tolist() == [3, 1, 11]
    j = newest_step_before(t)
    assert step["t_sckf"] == pytest.approx(STEP_T[j]) and STEP_T[j] <= t < STEP_T[j + 1]
    np.testing.assert_array_equal(step["p_corr_sckf"], [[j, i, 0] for i in range(N)])
    assert step["global_applied"].tolist() == [j % 2 == 0]
    assert step["con_pos_before"].shape == (N - 1,)


def test_a_down_link_is_down_and_does_not_hold_the_view_back(tmp_path):
    vehicle(tmp_path, 1, T_TRUTH[:76])
    vehicle(tmp_path, 2, T_TRUTH[:11])  # died at 0.2 s
    vehicle(tmp_path, 3, T_TRUTH[:91])
    t, row, _ = FleetRows(harness(down={1}), tmp_path, clock=Clock()).newest()
    assert t == T_TRUTH[75]
    assert row["link_state"][1] & DOWN and condition(row["link_state"][1]) == "down"
    assert row["link_state"][0] == 3 and row["link_state"][2] == 3
    for key in ("p_ekf", "q_ekf", "p_target", "q_target"):
        assert np.isnan(row[key][1]).all(), key
        assert np.isfinite(row[key][[0, 2]]).all(), key


def test_a_vehicle_that_has_logged_nothing_holds_the_view_at_the_first_truth_row(tmp_path):
    vehicle(tmp_path, 1, T_TRUTH[:50])
    vehicle(tmp_path, 3, T_TRUTH[:50])
    clock = Clock()
    rows = FleetRows(harness(), tmp_path, clock=clock)
    t, row, _ = rows.newest()
    assert t == T_TRUTH[0]
    assert condition(row["link_state"][1]) == "down"  # no row of it: shown as down
    assert np.isnan(row["p_ekf"][1]).all()
    np.testing.assert_array_equal(row["p_ekf"][0], [1, 0.0, 0.0])
    assert row["link_state"][0] == 3 and row["link_state"][2] == 3
    vehicle(tmp_path, 2, T_TRUTH[:31])  # it starts logging
    clock.now += POLL_S
    t, row, _ = rows.newest()
    assert t == T_TRUTH[30]
    assert row["link_state"].tolist() == [3, 3, 3]


def test_the_streams_are_read_once_per_poll_period(tmp_path):
    writers = [vehicle(tmp_path, i, T_TRUTH[:21]) for i in (1, 2, 3)]
    clock = Clock()
    rows = FleetRows(harness(), tmp_path, clock=clock)
    assert rows.newest()[0] == T_TRUTH[20]
    for i, w in enumerate(writers, 1):
        for t in T_TRUTH[21:41]:
            w.add(t=t, p_ekf=np.array([i, t, 0.0]), q_ekf=Q_ID, p_target=np.zeros(3), q_target=Q_ID, flags=3)
        w.flush()
    clock.now += 0.5 * POLL_S
    assert rows.newest()[0] == T_TRUTH[20]  # not read again yet
    clock.now += 0.5 * POLL_S
    t, row, _ = rows.newest()
    assert t == T_TRUTH[40]
    np.testing.assert_array_equal(row["p_ekf"][:, 1], T_TRUTH[40])


def test_a_restarted_vehicle_continues_in_its_restart_folder(tmp_path):
    vehicle(tmp_path, 1, T_TRUTH[:26], flags=3)  # to 0.5 s
    vehicle(tmp_path, 1, T_TRUTH[30:76], flags=1, folder="link1-restart")  # from 0.6 s to 1.5 s
    vehicle(tmp_path, 2, T_TRUTH[:101])
    vehicle(tmp_path, 3, T_TRUTH[:101])
    t, row, _ = FleetRows(harness(), tmp_path, clock=Clock()).newest()
    assert t == T_TRUTH[75]
    np.testing.assert_array_equal(row["p_ekf"][0], [1, T_TRUTH[75], 0])
    assert row["link_state"][0] == 1  # the restarted process's flags


def test_a_fleet_without_a_companion_step_yet_has_no_step_row(tmp_path):
    for i in (1, 2, 3):
        vehicle(tmp_path, i, T_TRUTH)
    companion(tmp_path, times=[1.5, 1.55])
    rows = FleetRows(harness(t=T_TRUTH[:51]), tmp_path, clock=Clock())
    t, _, step = rows.newest()
    assert t == T_TRUTH[50] and step is None  # its first step is after the time shown


def test_a_disabled_companion_gives_no_step_row(tmp_path):
    sc = dataclasses.replace(SCENARIO, companion=dataclasses.replace(SCENARIO.companion, enabled=False))
    for i in (1, 2, 3):
        vehicle(tmp_path, i, T_TRUTH)
    companion(tmp_path)
    rows = FleetRows(harness(sc), tmp_path, clock=Clock())
    assert rows.companions == []
    assert rows.newest()[2] is None


def test_distributed_companions_are_joined_in_chain_order(tmp_path):
    sc = dataclasses.replace(SCENARIO, companion=dataclasses.replace(SCENARIO.companion, distributed=True,
                                                                      groups=[[1], [2, 3]]))
    for i in (1, 2, 3):
        vehicle(tmp_path, i, T_TRUTH[:61])
    companion(tmp_path, links=[0], folder="companion-g1")
    companion(tmp_path, times=[t + 0.01 for t in STEP_T], links=[1, 2], folder="companion-g2")
    clock = Clock()
    rows = FleetRows(harness(sc), tmp_path, clock=clock)
    t, _, step = rows.newest()
    j = newest_step_before(t)
    np.testing.assert_array_equal(step["p_corr_sckf"], [[j, 0, 0], [j, 1, 0], [j, 2, 0]])
    assert step["global_applied"].tolist() == [j % 2 == 0, j % 2 == 0]
    assert step["t_sckf"] == pytest.approx(STEP_T[j] + 0.01)


def test_a_distributed_group_without_a_step_leaves_its_links_nan(tmp_path):
    sc = dataclasses.replace(SCENARIO, companion=dataclasses.replace(SCENARIO.companion, distributed=True,
                                                                      groups=[[1], [2, 3]]))
    for i in (1, 2, 3):
        vehicle(tmp_path, i, T_TRUTH[:61])
    companion(tmp_path, links=[1, 2], folder="companion-g2-restart")  # only group 2, restarted
    _, _, step = FleetRows(harness(sc), tmp_path, clock=Clock()).newest()
    assert np.isnan(step["p_corr_sckf"][0]).all() and np.isfinite(step["p_corr_sckf"][1:]).all()
    assert step["global_applied"].shape == (1,)


GPS = dataclasses.replace(SCENARIO, companion=dataclasses.replace(SCENARIO.companion, time_base="gps"))
EPOCH_S = SITL_GPS_EPOCH_US * 1e-6


def test_a_gps_companion_is_shifted_to_the_simulated_clock(tmp_path):
    for i in (1, 2, 3):
        vehicle(tmp_path, i, T_TRUTH[:61])  # the vehicles log on the simulated clock
    companion(tmp_path, offset=EPOCH_S)  # the companion on GPS time
    rows = FleetRows(harness(GPS), tmp_path, clock=Clock())
    assert [b.shift_s for _, buffers in rows.companions for b in buffers] == [-EPOCH_S]
    t, _, step = rows.newest()
    assert t == T_TRUTH[60]
    j = newest_step_before(t)
    np.testing.assert_array_equal(step["p_corr_sckf"][:, 0], j)  # the step at or before the time shown


def test_a_gps_companion_step_time_is_on_the_simulated_clock(tmp_path):
    for i in (1, 2, 3):
        vehicle(tmp_path, i, T_TRUTH[:61])
    companion(tmp_path, offset=EPOCH_S)
    t, _, step = FleetRows(harness(GPS), tmp_path, clock=Clock()).newest()
    assert step["t_sckf"] == pytest.approx(STEP_T[newest_step_before(t)], abs=1e-6)


def test_a_link_left_out_of_the_newest_step_is_excluded(tmp_path):
    """As the replay's link states (sitl/fleet/logs.py): a link the companion's newest step did not
    correct carries the EXCLUDED bit."""
    for i in range(1, N + 1):
        vehicle(tmp_path, i, T_TRUTH[:61], flags=3)
    w = Writer(tmp_path / "companion" / "companion_log.stream")
    for j, t in enumerate(STEP_T):
        w.add(t_sckf=t, p_ekf_sckf=np.zeros((N, 3)), v_ekf_sckf=np.zeros((N, 3)), q_ekf_sckf=np.tile(Q_ID, (N, 1)),
              w_sckf=np.zeros((N, 3)), p_corr_sckf=np.zeros((N, 3)), v_corr_sckf=np.zeros((N, 3)),
              q_corr_sckf=np.tile(Q_ID, (N, 1)), global_applied=True, corrected_sckf=np.array([True, False, True]))
    w.flush()
    _, row, _ = FleetRows(harness(), tmp_path, clock=Clock()).newest()
    assert [condition(x) for x in row["link_state"]] == ["flying", "excluded", "flying"]


def test_a_batch_flights_live_rows_carry_the_home_its_companion_flies_from():
    from sitl.view.frame import frame
    from sitl.view.live import batch_rows

    truth = np.zeros((3, 3))
    home = np.array([0.3, -0.2, 1.5])
    log = types.SimpleNamespace(t=[2.0], p_true=[truth], q_true=[np.tile([1.0, 0, 0, 0], (3, 1))],
                                p_target=[truth + home], q_target=[np.tile([1.0, 0, 0, 0], (3, 1))])
    engine = types.SimpleNamespace(links=[types.SimpleNamespace(index=i) for i in range(3)],
                                   step=types.SimpleNamespace(log={}),
                                   targets=types.SimpleNamespace(home_offset_w_m=home))
    runner = types.SimpleNamespace(log=log, engines=[engine], n=3, d=np.tile([0.5, 0.0, 0.0], (3, 1)))
    t, row, step = batch_rows(runner)()
    assert t == 2.0 and step is None
    np.testing.assert_array_equal(row["home_offset_w_m"], home)
    np.testing.assert_allclose(frame(t, row).target.p_w_m, truth, atol=1e-12)


@pytest.mark.parametrize("distributed", [False, True])
def test_a_fleets_live_rows_carry_the_home_of_the_companions_newest_step(tmp_path, distributed):
    """The targets the vehicles log are in the links' frame; the home each companion step logs
    takes them back to the truth's frame, the home of the step at the time shown (it is measured
    again while the chain rests)."""
    from sitl.view.frame import frame

    sc = SCENARIO if not distributed else dataclasses.replace(
        SCENARIO, companion=dataclasses.replace(SCENARIO.companion, distributed=True, groups=[[1], [2, 3]]))
    for i in (1, 2, 3):
        vehicle(tmp_path, i, T_TRUTH[:61])
    home = lambda j: np.array([0.01 * j, -0.2, 1.0])  # noqa: E731
    if distributed:
        companion(tmp_path, links=[0], folder="companion-g1", home=home)
        companion(tmp_path, links=[1, 2], folder="companion-g2", home=home)
    else:
        companion(tmp_path, home=home)
    t, row, _ = FleetRows(harness(sc), tmp_path, clock=Clock()).newest()
    np.testing.assert_array_equal(row["home_offset_w_m"], home(newest_step_before(t)))
    target = frame(t, row).target.p_w_m  # the vehicles' targets (i, t, 1) less the home
    np.testing.assert_allclose(target, np.array([[i, t, 1.0] for i in (1, 2, 3)]) - home(newest_step_before(t)))


def test_a_fleet_whose_companions_log_no_home_shows_the_targets_as_flown(tmp_path):
    for i in (1, 2, 3):
        vehicle(tmp_path, i, T_TRUTH[:61])
    companion(tmp_path)
    _, row, _ = FleetRows(harness(), tmp_path, clock=Clock()).newest()
    assert "home_offset_w_m" not in row
