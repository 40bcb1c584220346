"""Scripted SITL faults (sitl.scenario [faults], sitl.fleet.wire) and the metrics that report them
(sitl.metrics outage windows, sitl.steplog with a companion down)."""

import json
import socket
import subprocess
import sys
import threading
from contextlib import contextmanager
from dataclasses import replace

import numpy as np
import pytest

from companion.configfile import ConfigError
from companion.engine import STEP_LOG_KEYS
from companion.estimation.so3 import attitude_error
from companion.linkstate import CARRIED, DOWN
from sitl.scenarios.chain.flight import fly
from sitl.metrics import flag_windows, outage_split
from sitl.scenario import GpsFault, InjectFault, LinkRebootFault, MavlinkWireFault, load_scenario
from sitl.steplog import merge_step_logs
from sitl.fleet.wire import Impairment, WireProxy

from ..flights import seeded_metrics
from ..paths import ROOT
from ..ports import free_ports
from ..waits import wait_for

FAULTS = "configs/sitl/faults"


@pytest.mark.parametrize("name, fleet_only", [("link_reboot", []), ("mavlink_loss", ["faults.mavlink"]),
                                              ("gps_glitch", [])])
def test_fault_scenarios_load(name, fleet_only):
    sc = load_scenario(f"{FAULTS}/{name}.toml")
    assert sc.faults.fleet_only == fleet_only
    if name == "link_reboot":
        assert (sc.skeleton.n_links, sc.faults.link.kill, sc.faults.link.kill_at_s, sc.faults.link.restart_after_s) == \
            (7, 4, 20.0, 3.0)
    if name == "mavlink_loss":
        assert sc.skeleton.n_links == 3 and sc.faults.mavlink.loss == 0.2 and sc.faults.mavlink.links == ()
    if name == "gps_glitch":
        g = sc.faults.gps
        assert sc.skeleton.n_links == 3 and g.link == 2 and np.linalg.norm(g.step_m) == 10.0
        assert np.linalg.norm(g.ramp_m) == 10.0 and g.ramp_duration_s == 10.0


@pytest.mark.parametrize("text, fragment", [
    ("[faults.link]\nkill = 5\n", "faults.link.kill: the skeleton has links 1..3"),
    ("[faults.mavlink]\nloss = 1.0\n", "loss must be in [0, 1)"),
    ("[faults.mavlink]\nlinks = [0]\n", "1-based"),
    ("[faults.gps]\nlink = 2\nstep_m = [1.0, 2.0]\n", "faults.gps.step_m"),
    ("[faults.gps]\nramp_duration_s = -1.0\n", "ramp_duration_s"),
])
def test_fault_config_errors(tmp_path, text, fragment):
    path = tmp_path / "bad.toml"
    path.write_text('name = "x"\n[skeleton]\nn_links = 3\n' + text)
    with pytest.raises(ConfigError) as err:
        load_scenario(path)
    assert fragment in str(err.value)


def test_batch_mode_refuses_fleet_only_faults(tmp_path):
    proc = subprocess.run([sys.executable, "-m", "sitl", "fly", "--config", f"{FAULTS}/mavlink_loss.toml", "--quiet",
                           "--out", str(tmp_path / "run")], capture_output=True, text=True, timeout=120)
    assert proc.returncode == 2 and "faults.mavlink: fleet mode only" in proc.stderr and "sitl launch" in proc.stderr
    assert not (tmp_path / "run").exists()


def test_gps_fault_step_ramp_and_outage():
    g = GpsFault(link=2, step_m=(10.0, 0.0, 0.0), step_at_s=5.0, step_duration_s=2.0, ramp_m=(0.0, 4.0, 0.0),
                 ramp_at_s=10.0, ramp_duration_s=4.0, ramp_hold_s=1.0, outage_at_s=20.0, outage_s=1.5)
    np.testing.assert_array_equal(g.offset_w_m(4.99), 0.0)
    np.testing.assert_array_equal(g.offset_w_m(5.0), [10.0, 0, 0])
    np.testing.assert_array_equal(g.offset_w_m(7.0), 0.0)
    np.testing.assert_allclose(g.offset_w_m(11.0), [0, 1.0, 0])
    np.testing.assert_allclose(g.offset_w_m(14.5), [0, 4.0, 0])  # held
    np.testing.assert_array_equal(g.offset_w_m(15.0), 0.0)  # gone
    pos = np.zeros((3, 3))
    out, fix = g.apply(5.5, pos)
    np.testing.assert_array_equal(out[1], [10.0, 0, 0])
    np.testing.assert_array_equal(out[[0, 2]], 0.0)
    assert fix.tolist() == [True, True, True] and not np.shares_memory(out, pos)
    assert g.apply(20.5, pos)[1].tolist() == [True, False, True]
    assert GpsFault().apply(5.5, pos)[0] is pos


def test_impairment_is_seeded_and_loses_about_p():
    def run(seed):
        imp = Impairment(0.2, 0.01, 0.005, np.random.default_rng(seed))
        out = [imp.decide(float(k)) for k in range(5000)]
        return imp, out

    a, out_a = run(4)
    b, out_b = run(4)
    assert out_a == out_b  # same seed, same losses and delays
    assert a.dropped + a.forwarded == 5000 and 0.18 < a.dropped / 5000 < 0.22
    kept = [(k, r) for k, r in enumerate(out_a) if r is not None]
    assert all(0.01 <= r - k <= 0.015 for k, r in kept)
    assert MavlinkWireFault().active is False and MavlinkWireFault(jitter_ms=1.0).active


@contextmanager
def _running_wire(**proxy_kwargs):
    """A :class:`WireProxy` (``proxy_kwargs``) running in a thread between a vehicle's and a
    companion's socket on loopback; yields the proxy, both sockets and the ports (vehicle side,
    companion, the proxy's own)."""
    vside, comp_port, local = free_ports(3, udp=True)
    companion = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    companion.bind(("127.0.0.1", comp_port))
    vehicle = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    vehicle.bind(("127.0.0.1", 0))
    proxy = WireProxy([(vside, comp_port, local)], **proxy_kwargs)
    thread = threading.Thread(target=proxy.run, daemon=True)
    thread.start()
    try:
        yield proxy, vehicle, companion, (vside, comp_port, local)
    finally:
        proxy.stop()
        thread.join(2.0)
        proxy.close()
        companion.close()
        vehicle.close()


def test_wire_proxy_forwards_both_ways_drops_and_counts():
    with _running_wire(loss=0.3, delay_ms=5.0, jitter_ms=0.0, seed=1) as (proxy, vehicle, companion, ports):
        vside, comp_port, local = ports
        companion.settimeout(0.5)
        vehicle.settimeout(0.5)
        for k in range(200):
            vehicle.sendto(b"up%03d" % k, ("127.0.0.1", vside))
        got = []
        while True:
            try:
                data, addr = companion.recvfrom(100)
            except TimeoutError:
                break
            got.append(data)
            assert addr == ("127.0.0.1", local)  # the companion sees the proxy's port
        up = proxy.pairs[0].up
        assert len(got) == up.forwarded and up.forwarded + up.dropped == 200 and 40 < up.dropped < 80
        for k in range(100):  # the companion answers where it heard from: back to the vehicle
            companion.sendto(b"down%03d" % k, ("127.0.0.1", local))
        back = []
        while True:
            try:
                back.append(vehicle.recvfrom(100)[0])
            except TimeoutError:
                break
        down = proxy.pairs[0].down
        assert len(back) == down.forwarded and down.forwarded + down.dropped == 100 and down.dropped > 10
        stats = proxy.stats()
        assert stats[f"{vside}<->{comp_port}"]["vehicle_to_companion"]["dropped"] == up.dropped


def test_wire_proxy_on_simulated_time_holds_datagrams_until_that_clock_has_moved():
    """With the lockstep's clock (sim_time.SimTimeClock in a fleet) a datagram is held for its
    delay in that clock's time: frozen, it stays; moved by the delay, it leaves."""
    sim = [5.0]
    with _running_wire(loss=0.0, delay_ms=20.0, jitter_ms=0.0, seed=1, clock=lambda: sim[0],
                       poll_s=0.0005) as (proxy, vehicle, companion, (vside, _, _)):
        vehicle.sendto(b"state", ("127.0.0.1", vside))
        assert wait_for(lambda: proxy.pairs[0].up.forwarded == 1, 5.0)
        companion.settimeout(0.3)  # 15 wall-clock delays: still held, the simulated time stands still
        with pytest.raises(TimeoutError):
            companion.recvfrom(100)
        sim[0] += 0.019
        with pytest.raises(TimeoutError):
            companion.recvfrom(100)
        sim[0] += 0.002
        companion.settimeout(2.0)
        assert companion.recvfrom(100)[0] == b"state"


def test_wire_cli_writes_its_counters_and_stops_on_sigterm(tmp_path):
    vside, comp_port, local = free_ports(3, udp=True)
    stats = tmp_path / "wire.json"
    proc = subprocess.Popen([sys.executable, "-m", "sitl.fleet.wire", "--pair", f"{vside}:{comp_port}:{local}", "--loss", "0.5",
                             "--seed", "3", "--stats", str(stats)], stderr=subprocess.PIPE, text=True)
    def counted() -> int:  # the datagrams the wire has handled, as its counters file says (every second)
        try:
            c = json.loads(stats.read_text())[f"{vside}<->{comp_port}"]["vehicle_to_companion"]
        except (OSError, ValueError, KeyError):
            return -1
        return c["forwarded"] + c["dropped"]

    try:
        assert wait_for(lambda: counted() == 0, 20.0, poll_s=0.05), "the wire never started"
        s = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        for _ in range(100):
            s.sendto(b"x", ("127.0.0.1", vside))
        s.close()
        wait_for(lambda: counted() >= 100, 10.0, poll_s=0.05)
    finally:
        proc.terminate()
        proc.wait(10)
    assert proc.returncode == 0, proc.stderr.read()
    counts = json.loads(stats.read_text())[f"{vside}<->{comp_port}"]["vehicle_to_companion"]
    assert counts["forwarded"] + counts["dropped"] == 100 and 30 < counts["dropped"] < 70
    bad = subprocess.run([sys.executable, "-m", "sitl.fleet.wire", "--pair", "1:2", "--loss", "0.1"], capture_output=True,
                         text=True, timeout=60)
    assert bad.returncode == 2 and "VEHICLE_SIDE:COMPANION_PORT:LOCAL_PORT" in bad.stderr


def test_flag_windows_and_the_outage_split():
    t = np.arange(10) * 1.0
    out = np.zeros((10, 3), dtype=bool)
    out[2:4, 1] = True
    out[4:6, [1, 2]] = True
    assert flag_windows(t, out) == [{"start_s": 2.0, "end_s": 3.0, "links": [2]},
                                    {"start_s": 4.0, "end_s": 5.0, "links": [2, 3]}]
    n = 3
    log = {"t": t, "p_true": np.zeros((10, n, 3)), "p_target": np.zeros((10, n, 3)), "p_ctrl": np.zeros((10, n, 3)),
           "t_sckf": t, "con_pos_after": np.full((10, n - 1), 0.001)}
    log["p_true"][3:6, :, 0] = 0.5  # off while the outage lasts
    log["p_ctrl"][3:6, 1] = np.nan  # link 2 down: no estimate
    log["con_pos_after"][3:6] = 0.2
    res = outage_split(log, 1.0, [{"kind": "vehicle_down", "start_s": 3.0, "end_s": 5.0, "links": [2]}])
    assert res["during_outages"]["samples"] == 3 and res["outside_outages"]["samples"] == 6
    np.testing.assert_allclose(res["during_outages"]["rms_track_true_m"], 0.5)
    np.testing.assert_allclose(res["outside_outages"]["rms_track_true_m"], 0.0)
    assert np.isnan(res["during_outages"]["rms_track_est_m"][1])  # no estimate at all in there
    assert res["during_outages"]["constraint_pos_p95_m_after"] == pytest.approx(0.2)
    assert res["outside_outages"]["constraint_pos_p95_m_after"] == pytest.approx(0.001)
    corrected = np.ones((10, n), dtype=bool)
    corrected[3:6, 1] = False
    corrected[4, 2] = False  # link 3 missed one of the window's three steps
    res = outage_split({**log, "corrected_sckf": corrected}, 1.0,
                       [{"kind": "vehicle_down", "start_s": 3.0, "end_s": 5.0, "links": [2]}])
    assert res["windows"][0]["corrected_fraction"] == [1.0, None, pytest.approx(2 / 3, abs=1e-4)]


def _group_log(cycles, links, global_applied=True):
    k, m = len(cycles), len(links)
    q = np.zeros((k, m, 4))
    q[..., 0] = 1.0
    log = {key: np.zeros((k, m, 3)) for key in ("p_ekf_sckf", "v_ekf_sckf", "w_sckf", "p_local_sckf", "p_corr_sckf",
                                                "v_corr_sckf")}
    for j, i in enumerate(links):
        log["p_ekf_sckf"][:, j, 0] = log["p_corr_sckf"][:, j, 0] = float(i)  # a straight chain of 1 m links
    log.update(q_ekf_sckf=q, q_corr_sckf=q.copy(), t_sckf=np.asarray(cycles) * 1e-6, cycle_us=np.asarray(cycles),
               iterations=np.ones(k, dtype=int), global_applied=np.full(k, global_applied), leader=np.full(k, 2),
               corrected_sckf=np.ones((k, m), dtype=bool), nis_max_sckf=np.ones(k),
               P_ekf_sckf=np.tile(np.eye(3), (k, m, 3, 1, 1)), P_corr_sckf=np.tile(np.eye(3), (k, m, 3, 1, 1)),
               home_offset_sckf=np.tile([0.1, -0.2, 0.3], (k, 1)))
    assert set(STEP_LOG_KEYS) <= set(log)
    return log


def test_a_single_companions_step_log_keeps_its_home_per_group_like_a_distributed_one():
    d = np.array([[0.5, 0, 0]] * 3)
    merged = merge_step_logs([[_group_log([k * 50_000 for k in range(4)], [0, 1, 2])]], d, distributed=False)
    assert merged["home_offset_sckf"].shape == (4, 1, 3) and merged["global_applied"].shape == (4, 1)
    np.testing.assert_array_equal(merged["home_offset_sckf"][:, 0], np.tile([0.1, -0.2, 0.3], (4, 1)))


def test_merged_step_log_keeps_a_dead_companions_cycles_as_an_outage():
    d = np.array([[0.5, 0, 0]] * 3)
    all_cycles = [k * 50_000 for k in range(10)]
    alive = [c for c in all_cycles if not 150_000 <= c <= 300_000]  # group 2's companion down
    merged = merge_step_logs([[_group_log(all_cycles, [0, 1])], [_group_log(alive, [2])]], d, distributed=True)
    assert merged["t_sckf"].size == 10
    gone = (merged["cycle_us"] >= 150_000) & (merged["cycle_us"] <= 300_000)
    assert not merged["corrected_sckf"][gone, 2].any() and merged["corrected_sckf"][~gone].all()
    assert not merged["global_applied"][gone, 1].any() and np.all(merged["leader"][gone, 1] == -1)
    assert np.all(np.isnan(merged["p_corr_sckf"][gone, 2])) and np.all(np.isnan(merged["con_pos_after"][gone, 1]))
    assert merged["P_corr_sckf"].shape == (10, 3, 3, 3, 3) and np.all(np.isnan(merged["P_corr_sckf"][gone, 2]))
    assert merged["home_offset_sckf"].shape == (10, 2, 3) and np.all(np.isnan(merged["home_offset_sckf"][gone, 1]))
    np.testing.assert_array_equal(merged["home_offset_sckf"][~gone], np.tile([0.1, -0.2, 0.3], ((~gone).sum(), 2, 1)))
    np.testing.assert_allclose(merged["con_pos_after"][~gone], 0.0, atol=1e-12)
    np.testing.assert_allclose(merged["con_pos_after"][gone, 0], 0.0, atol=1e-12)
    # before every group has stepped once, the merged log does not start
    late = merge_step_logs([[_group_log(all_cycles, [0, 1])], [_group_log(all_cycles[4:], [2])]], d, True)
    assert late["cycle_us"][0] == all_cycles[4]


def test_merged_step_log_keeps_cycles_no_group_logged_as_an_outage():
    """Cycles every group skipped (a host too busy to run them) are rows without a step, not left out."""
    d = np.array([[0.5, 0, 0]] * 3)
    all_cycles = [k * 50_000 for k in range(12)]
    skipped = {200_000, 250_000, 300_000, 450_000}
    logged = [c for c in all_cycles if c not in skipped]
    merged = merge_step_logs([[_group_log(logged, [0, 1])], [_group_log(logged, [2])]], d, True, period_us=50_000)
    assert merged["cycle_us"].tolist() == all_cycles
    gone = np.isin(merged["cycle_us"], sorted(skipped))
    assert not merged["global_applied"][gone].any() and merged["global_applied"][~gone].all()
    assert not merged["corrected_sckf"][gone].any() and np.all(np.isnan(merged["p_corr_sckf"][gone]))
    assert np.mean(np.all(merged["global_applied"], axis=1)) == pytest.approx(8 / 12)
    # without the period the merged log holds the logged cycles only
    assert merge_step_logs([[_group_log(logged, [0, 1])], [_group_log(logged, [2])]], d, True)["cycle_us"].size == 8


def test_fault_sections_round_trip_through_the_run_folder_copy(tmp_path):
    from companion.configfile import dump_toml
    sc = load_scenario(f"{FAULTS}/gps_glitch.toml")
    sc = replace(sc, faults=replace(sc.faults, mavlink=MavlinkWireFault(loss=0.1, links=(1, 3))))
    path = tmp_path / "scenario.toml"
    path.write_text(dump_toml(sc))
    again = load_scenario(path)
    assert again.faults == sc.faults


def _reboot_flight(tmp_path, restart_after_s, **companion):
    sc = load_scenario("configs/sitl/chain/three_link.toml", duration_s=12.0)
    sc = replace(sc, faults=replace(sc.faults, link=LinkRebootFault(kill=2, kill_at_s=9.0, restart_after_s=restart_after_s)),
                 companion=replace(sc.companion, **companion))
    m = fly(sc, tmp_path, plots=False)
    log = np.load(tmp_path / "log.npz")
    tilt = np.degrees(np.linalg.norm(attitude_error(log["q_true"], log["q_target"]), axis=-1))  # NaN: no target
    return m, log, tilt


@pytest.mark.parametrize("restart_after_s", [0.5])  # the fleet's scripted-faults test: 1 s
def test_batch_link_reboot_its_neighbours_carry_it_and_the_chain_recovers(tmp_path, restart_after_s):
    """Batch mode's [faults.link]: link 2's firmware off at 9 s (rotors stopped, silent), a new one
    powered on restart_after_s later, its EKF started in flight, re-armed and re-admitted. Its
    neighbours carry it meanwhile (the feed-forward takes its weight): they stay within 20 deg of
    their attitude targets and the chain within 0.35 m of its own (they were 60 deg off, a crash
    by batch mode's rule, before the companion carried a link without rotors)."""
    m, log, tilt = _reboot_flight(tmp_path, restart_after_s)
    reboot = m["faults"]["link_reboot"]
    assert not m["crashed"], m["crash_reason"]
    assert reboot["killed_at_s"] == 9.0 and reboot["restarted_at_s"] == reboot["rejoined_at_s"] == 9.0 + restart_after_s
    assert 9.0 + restart_after_s < reboot["rotors_on_at_s"] < 9.0 + restart_after_s + 0.1
    assert reboot["readmitted_at_s"] is not None and reboot["readmitted_at_s"] < 9.0 + restart_after_s + 1.0
    (down_window,) = [w for w in m["outages"]["windows"] if w["kind"] == "vehicle_down"]
    assert {k: down_window[k] for k in ("start_s", "end_s", "links")} == {"start_s": 9.0, "end_s": 9.0 + restart_after_s,
                                                                         "links": [2]}
    assert down_window["corrected_fraction"][1] is None  # its own link: not counted
    t = log["t"]
    down = (t >= 9.0) & (t < 9.0 + restart_after_s)
    assert np.all(np.isnan(log["p_ekf"][down, 1])) and np.all(np.isfinite(log["p_ekf"][~down, 1]))
    # the state words the view colours links by: link 2 down exactly then, carried by its neighbours
    state = log["link_state"]
    assert np.all(state[down, 1] & DOWN) and not np.any(state[~down, 1] & DOWN) and not np.any(state[:, [0, 2]] & DOWN)
    assert np.any(state[t >= 9.0, 1] & CARRIED) and not np.any(state[t < 9.0, 1] & CARRIED)
    after = t >= 9.0
    assert np.nanmax(tilt[after][:, [0, 2]]) < 20.0
    assert np.nanmax(np.linalg.norm(log["p_true"] - log["p_target"], axis=-1)[after]) < 0.35
    assert m["min_altitude_m"] > 2.0
    # carrying takes the neighbours to their rotors' limit (scaled onto it), link 2 never
    limit = m["rotor_limit_s_per_link"]
    assert limit[1] == 0.0 and max(limit[0], limit[2]) > 0.3 and max(limit) < 9.0 + restart_after_s, limit
    # ... and the neighbours' firmware counted the same time at the limit (link 2's new one none)
    reports = m["thrust_limit"]
    for i in (0, 2):
        assert abs(reports[i]["at_limit_s"] - limit[i]) < 0.05 and reports[i]["min_scale"] <= 1.0, (reports, limit)
    assert max(r["episodes"] for r in reports) >= 1 and reports[1] == {
        "at_limit_s": 0.0, "episodes": 0, "min_scale": 1.0, "at_limit_now": False}, reports
    # each episode's STATUSTEXTs (the fault and its recovery) in the log, from the neighbours only
    links = log["statustext_link"].tolist()
    assert set(links) <= {1, 3} and len(links) >= 2 * max(r["episodes"] for r in reports)
    assert np.all(np.diff(log["statustext_t"]) >= 0) and np.all(log["statustext_t"] >= 9.0)
    end = t >= 11.5  # recovered
    assert np.max(tilt[end]) < 5.0 and np.max(np.linalg.norm(log["p_true"] - log["p_target"], axis=-1)[end]) < 0.3


def test_batch_link_reboot_in_distributed_mode_the_next_groups_companion_carries_it_too(tmp_path):
    """The same reboot with one companion per group, link 2 the first of group 2 (groups [1], [2, 3]):
    link 1's companion hears nothing of link 2 and carries it on group 2's word (GroupPassiveLinks
    over the in-process bus): link 1 stays within 20 deg of its target (45 deg, and the chain 0.52 m
    off its targets, when only link 2's own group carried it)."""
    m, log, tilt = _reboot_flight(tmp_path, 0.5, distributed=True, groups=((1,), (2, 3)))
    assert not m["crashed"], m["crash_reason"]
    # carried by its own group's companion from the silence until its rotors run again, and by
    # group 1's for as long (a target period or two later); nothing else carried
    carrying = m["carrying"]
    assert 0.5 < carrying["carried_s"]["2"] < 1.0 and carrying["carried_s"]["1"] == carrying["carried_s"]["3"] == 0.0
    assert carrying["carried_by_other_groups_s"] == {
        "companion-g1": {"2": pytest.approx(carrying["carried_s"]["2"], abs=0.05)}}
    after = log["t"] >= 9.0
    assert np.nanmax(tilt[after][:, [0, 2]]) < 20.0
    assert np.nanmax(np.linalg.norm(log["p_true"] - log["p_target"], axis=-1)[after]) < 0.35
    assert m["min_altitude_m"] > 2.0


def test_batch_runner_leaves_out_only_engine_polls_that_change_nothing(tmp_path, monkeypatch):
    """The batch runner polls a companion engine only when it needs one (an input, an event on the
    in-process bus, a timer due: :meth:`~companion.engine.CompanionEngine.needs_poll`). The
    distributed reboot flight above (arm retries at the start and after the reboot, a link silent
    and carried across groups, heartbeats, health tables, the global step) flies the same, bit for
    bit, with every engine polled on every firmware tick; there, every poll ``needs_poll`` would
    have left out returns nothing; and most polls are left out."""
    from companion.engine import CompanionEngine
    from sitl.runner import BatchRunner

    poll = CompanionEngine.poll
    counts = {"polls": 0, "idle": 0, "idle_with_output": 0}

    def counted(self, now_s):
        idle = not self.needs_poll(now_s)
        out = poll(self, now_s)
        counts["polls"] += 1
        counts["idle"] += idle
        counts["idle_with_output"] += idle and bool(out)
        return out

    monkeypatch.setattr(CompanionEngine, "poll", counted)
    runs = {}
    for skip in (True, False):
        monkeypatch.setattr(BatchRunner, "skip_idle_polls", skip)
        counts.update(polls=0, idle=0, idle_with_output=0)
        m, _, _ = _reboot_flight(tmp_path / str(skip), 0.5, distributed=True, groups=((1,), (2, 3)))
        runs[skip] = dict(counts), m, np.load(tmp_path / str(skip) / "log.npz")
    (skipped, m_skip, log_skip), (every, m_every, log_every) = runs[True], runs[False]
    assert every["idle_with_output"] == 0 and every["idle"] > 0.8 * every["polls"], every
    assert skipped["idle"] == 0 and skipped["polls"] == every["polls"] - every["idle"], (skipped, every)
    assert sorted(log_skip.files) == sorted(log_every.files)
    for key in log_every.files:
        np.testing.assert_array_equal(log_skip[key], log_every[key], err_msg=key)
    assert seeded_metrics(m_skip) == seeded_metrics(m_every)  # (all but the real-time factor)


@pytest.mark.slow  # the counterfactual of the test above (7 s), out of the default run for the suite's time
def test_batch_link_reboot_without_carrying_tips_its_neighbours_over(tmp_path):
    """The same reboot with the carrying off (a silence taken as one only after 100 s, no spin-up
    wait): the neighbours hold the unpowered link on feedback alone and tip past 60 deg."""
    m, _, tilt = _reboot_flight(tmp_path, 0.5, carry_silence_s=100.0, carry_spinup_s=0.0)
    assert m["crashed"] and "attitude error" in m["crash_reason"], m["crash_reason"]
    assert np.nanmax(tilt[:, [0, 2]]) > 55.0


@pytest.mark.slow  # the counterfactual of regression_end_motor_off (3 s), out of the default run for the suite's time
def test_a_stopped_motor_left_in_the_allocation_flips_its_end_link(tmp_path):
    """regression_end_motor_off with SKL_CA_FAIL = 0: the firmware reports the failed motor but
    allocates as if it turned, and the end link tips past 60 deg; with it (the seeded test) it flies."""
    sc = load_scenario(f"{FAULTS}/regression_end_motor_off.toml")
    allocation = replace(sc.firmware.allocation, remove_failed_rotor=False)
    sc = replace(sc, firmware=replace(sc.firmware, allocation=allocation))
    m = fly(sc, tmp_path, plots=False)
    assert m["crashed"] and "on link 3" in m["crash_reason"], m["crash_reason"]


@pytest.mark.parametrize("unit, ftype, instance, changed", [
    ("gps", "off", 0, 10),         # 10 Hz fixes for 1 s
    ("gyro", "garbage", 0, 500),   # every 500 Hz IMU sample
    ("motor", "off", 3, 500),      # every rotor command of the tick
    ("mavlink_signal", "off", 0, 50),  # every 50 Hz state report to the companion
])
def test_batch_injected_failures_go_through_the_vehicles_failure_filter(tmp_path, unit, ftype, instance, changed):
    """[faults.inject] in batch mode: link 2's samples or rotor commands changed by the vehicle's
    own failure filter for exactly the scripted second, announced as the vehicle announces a
    MAV_CMD_INJECT_FAILURE, and the chain flies through it."""
    sc = load_scenario("configs/sitl/chain/three_link.toml", duration_s=11.0)
    sc = replace(sc, faults=replace(sc.faults, inject=InjectFault(link=2, unit=unit, type=ftype, instance=instance,
                                                                  at_s=8.0, duration_s=1.0)))
    m = fly(sc, tmp_path, plots=False)
    inj = m["faults"]["inject"]
    assert (inj["injected_at_s"], inj["cleared_at_s"], inj["active"]) == (8.0, 9.0, [])
    assert inj["changed"] == {unit: changed}
    log = np.load(tmp_path / "log.npz")
    texts = [(float(t), int(i), str(s)) for t, i, s in zip(log["statustext_t"], log["statustext_link"],
                                                            log["statustext_text"]) if "Failure injection" in str(s)]
    name = unit + (f" {instance}" if unit == "motor" else "")
    assert texts == [(8.0, 2, f"Failure injection: {name} {ftype}"), (9.0, 2, f"Failure injection: {name} ok")]
    assert not m["crashed"] and m["min_altitude_m"] > 1.8


def test_an_injected_failure_the_unit_cannot_have_is_a_config_error():
    with pytest.raises(ValueError, match="type 'garbage' is not a failure of the gps"):
        InjectFault(link=1, unit="gps", type="garbage")
    with pytest.raises(ValueError, match="instance 9: the motor instances are 1-8"):
        InjectFault(link=1, unit="motor", type="off", instance=9)


#: the crashes the random fault campaign found (python -m sitl campaign faults), each a seeded
#: scenario configs/sitl/faults/regression_*.toml. Those that still crash are here with the reason:
#: the test expects their crash and fails once the chain survives one (strict), so that the
#: expectation goes; the others must fly through.
REGRESSIONS = {
    "regression_end_link_reboot": ("no level chain of these links holds a dead end link: 122 % of the rotors' thrust with the "
                                   "whole chain sharing, 152 % for its neighbour alone (python -m link_firmware_sim.design "
                                   "carry)"),
    "regression_end_motor_off_bend": ("with motor 1 out of end link 3, tilted about 18 deg in the bend, its side has "
                                      "no null space: the wrench needs 9.7 N of rotor 3 (8 N at most) and a reversal "
                                      "of rotor 2"),
}
SEEDED = sorted(p.stem for p in (ROOT / FAULTS).glob("regression_*.toml"))
#: what else a seeded scenario must show: the fix that made it fly (metrics.json -> why it failed)
FIXED_BY = {
    "regression_seven_inner_link_reboot": lambda m: (
        None if m.get("carrying", {}).get("carried_s", {}).get("6", 0.0) > 1.0
        else f"link 6 not carried: {m.get('carrying')}"),
    "regression_inner_link_reboot_gps_outage": lambda m: (
        None if m.get("carrying", {}).get("bridged_steps", 0) > 20 else f"link 2 bridged nothing: {m.get('carrying')}"),
    "regression_gps_stuck_bend": lambda m: (
        None if m["faults"]["gps"]["firmware"][0]["stuck"]["episodes"] == 1
        else f"link 1's stuck GPS not found: {m['faults']['gps']['firmware'][0]}"),
}


@pytest.mark.parametrize("name", SEEDED)
def test_the_crashes_the_fault_campaign_found_are_kept_as_seeded_scenarios(tmp_path, name):
    sc = load_scenario(f"{FAULTS}/{name}.toml")
    m = fly(sc, tmp_path, plots=False)
    if name in REGRESSIONS:
        if m["crashed"]:
            pytest.xfail(f"{name}: {m['crash_reason']}: {REGRESSIONS[name]}")
        pytest.fail(f"{name} flies through now: drop its expected crash from REGRESSIONS and keep it as a regression")
    assert not m["crashed"], f"{name}: {m['crash_reason']}"
    why = FIXED_BY[name](m) if name in FIXED_BY else None
    assert why is None, f"{name}: {why}"
