"""A vehicle's side of the simulator link in lockstep (link_firmware_sim.vehicle.lockstep): behind
PX4's TCP link and behind the same-host link it answers the same ticks with the same thrusts; its
compiled lockstep loop flies as the record tick and the decoders it stands for, bit for bit, hands
cut frames and noise to the parser, finishes an answer its send cut, and hands MAVLink input over
at once."""

from __future__ import annotations

import json
import socket
import threading
import time

import numpy as np
import pytest

from companion.estimation.so3 import quat_from_euler_zyx
from companion.kernels.jit import ENABLED as COMPILED
from companion.mavlink.dialect import load_dialect
from companion.mavlink.port import MavlinkPort
from companion.mavlink.sockets import TcpClient
from companion.mavlink.transport import wait_readable
from companion.messages import Correction, PoseTarget
from link_firmware_sim.estimators.ekf_config import EkfConfig
from link_firmware_sim.geo import GeoOrigin
from link_firmware_sim.kernels import mavlink_frames as frames
from link_firmware_sim.kernels.layouts import CTL_POS_INT
from link_firmware_sim.kernels.lockstep import LOOP_PACKET, LOOP_TICKED
from link_firmware_sim.vehicle.hil import decode_actuators, encode_actuators, encode_ahrs, encode_hil_gps, encode_hil_sensor
from link_firmware_sim.vehicle.simlink import encode_packet

from ..vehicle_rig import LEVEL, Rig

#: the kernels compiled (or loaded) before a vehicle here runs against a deadline
pytestmark = pytest.mark.usefixtures("compiled_kernels")

D = load_dialect()


@pytest.mark.parametrize("jit", [True, False], ids=["compiled", "numpy"])
def test_a_vehicle_answers_alike_over_both_links(tmp_path, jit):
    """The same ticks into a vehicle behind TCP and one behind the same-host link: the same thrusts
    and the same EKF state and link counters, bit for bit. Over the same-host link the ticks without
    a GPS fix (IMU only, or an attitude reference and the IMU sample: 49 in 50) go from the packet's
    bytes to the answer's in compiled code: the lockstep loop's (Lockstep.run_loop: the wait, the
    packet, the tick and the answer's send in one call) or the record tick's
    (Lockstep.tick_record); the others through the decoders. Over TCP the lockstep loop takes the
    same ticks from their MAVLink 2 frames (the record tick is the same-host link's only); the
    others, and every tick without the compiled kernels, are decoded."""
    if jit and not COMPILED:
        pytest.skip("numba not installed (or SKELETON_JIT=0)")
    thrusts, states, taken, loops = {}, {}, {}, {}
    for link in ("tcp", "unix"):
        (tmp_path / link).mkdir()
        rig = Rig(tmp_path / link, sim_link=link)
        v = rig.vehicle
        v.fw.fused_tick = jit
        records = taken[link] = []
        plain = v.lockstep.tick_record
        v.lockstep.tick_record = lambda data: records.append(plain(data)) or records[-1]
        looped = loops[link] = []
        plain_loop = v.fw.on_hil_loop
        v.fw.on_hil_loop = lambda *a, **k: looped.append(plain_loop(*a, **k)) or looped[-1]
        try:
            _armed_with_a_target(rig)
            thrusts[link] = np.array([rig.tick(gps=k % 50 == 0, ahrs=k % 10 == 0) for k in range(100)])
            states[link] = (v.fw.ekf.x.copy(), v.fw.ekf.P.copy(), v.fc_time_us, dict(v.sim.stats.per_type),
                            v.sim.stats.rx_messages, v.sim.stats.tx_messages)
        finally:
            rig.close()
    assert np.abs(thrusts["tcp"]).sum(axis=1).min() > 10.0  # armed: carrying its weight
    np.testing.assert_array_equal(thrusts["unix"], thrusts["tcp"])
    for a, b in zip(states["unix"], states["tcp"]):
        np.testing.assert_array_equal(a, b)
    assert not taken["tcp"]
    # the 100 armed ticks with a target: 98 without a GPS record go by a compiled call, the lockstep
    # loop's (Lockstep.run_loop) or, when the loop leaves the packet, the record tick's; the AHRS
    # records among them (8 of 10) are counted on the link as the decoders count them (per_type above)
    by_loop = sum(r[1] for r in loops["unix"] if r is not None)
    assert sum(taken["unix"]) + by_loop == (98 if jit else 0), (sum(taken["unix"]), by_loop)
    assert (by_loop >= 88) if jit else not any(r is not None for r in loops["unix"]), by_loop
    # over TCP the loop takes those 98 from their frames (it never leaves a whole tick's frames)
    by_loop = sum(r[1] for r in loops["tcp"] if r is not None)
    assert by_loop == (98 if jit else 0), by_loop



def _plain_and_looped(tmp_path, link: str, fly) -> tuple[dict, dict]:
    """``fly(rig, loop)`` on a new rig over ``link`` with the vehicle's lockstep loop off (the
    record tick, or the decoders over TCP), then on: both flights."""
    flights = {}
    for loop in (False, True):
        (tmp_path / str(loop)).mkdir()
        rig = Rig(tmp_path / str(loop), sim_link=link)
        try:
            flights[loop] = fly(rig, loop)
        finally:
            rig.close()
    return flights[False], flights[True]


def _armed_with_a_target(rig) -> None:
    """``rig``'s vehicle started, armed (as MAV_CMD_COMPONENT_ARM_DISARM would, at a fixed tick) and
    given a hold target 0.2 m east, 0.1 m south and 0.3 m above its control estimate."""
    v = rig.vehicle
    rig.start(0.3)
    assert v.fw.arm(rig.t)
    p, _, q = v.fw.control_estimate(rig.t)
    v.fw.set_target(rig.t, PoseTarget.hold(p + np.array([0.2, -0.1, 0.3]), q))


def _poll_in_thread(vehicle):
    """``vehicle`` polling in its own thread, as its process does; returns the call that stops it."""
    stop = threading.Event()

    def fly():
        while not stop.is_set():
            vehicle.poll(0.05)

    thread = threading.Thread(target=fly, daemon=True)
    thread.start()

    def stop_polling() -> None:
        stop.set()
        thread.join(2.0)

    return stop_polling


def _lockstep_flight(rig, n_ticks: int, loop: bool, on_tick=None, after=None, rough_every: int = 0,
                     ahrs_every: int = 10, ahrs_q=lambda k: LEVEL) -> dict:
    """``n_ticks`` lockstep ticks into ``rig``'s vehicle (armed, with a target and a correction that
    fades out and lifts the control estimate past the take-off height), the vehicle polling in its
    own thread as its process does, so that records arrive while it waits (the lockstep loop runs
    several ticks in one call); what the flight leaves, for a bit-for-bit comparison. ``on_tick(k)``
    runs after tick ``k``'s answer, ``after()`` after the last, the vehicle still polling.
    ``rough_every`` (TCP): every so many ticks the tick's frames are written in two pieces, cut
    inside a frame, with a pause between, and noise (bytes no parser takes for a frame) is written
    before the next tick's. An attitude reference ``ahrs_q(k)`` comes every ``ahrs_every`` ticks."""
    v = rig.vehicle
    v.fw.hil_loop = loop
    calls = []
    plain = v.fw.on_hil_loop
    v.fw.on_hil_loop = lambda *a, **k: calls.append(plain(*a, **k)) or calls[-1]
    _armed_with_a_target(rig)
    v.fw.on_correction(rig.t, Correction(0, rig.t, np.array([0.05, 0.0, 0.2]), np.zeros(3), np.zeros(3)))
    stop_polling = _poll_in_thread(v)
    thrusts = []
    try:
        for k in range(n_ticks):
            rig.t = round(rig.t + 0.002, 6)
            wave = np.sin(0.37 * k)
            msgs = [encode_hil_gps(rig.t, np.array([0.0, 0.0, rig.height_m]), rig.vel_m_s, GeoOrigin())] \
                if k % 50 == 0 else []
            if k % ahrs_every == 0:
                msgs.append(encode_ahrs(rig.t, ahrs_q(k)))
            msgs.append(encode_hil_sensor(rig.t, np.array([0.1 * wave, -0.05, 9.80665]),
                                          np.array([0.02 * wave, 0.01, -0.03 * wave])))
            if rough_every and k % rough_every == rough_every - 1:
                data = b"".join(rig.sim._pack(m) for m in msgs)
                cut = len(data) - 20  # inside the HIL_SENSOR frame
                rig.sim.transport.send(data[:cut])
                time.sleep(0.003)  # the vehicle reads the first piece alone
                rig.sim.transport.send(data[cut:])
            elif rough_every and k % rough_every == 0 and k:
                rig.sim.transport.send(b"\x00noise\x01")
                rig.sim.send_many(msgs)
            else:
                rig.sim.send_many(msgs)
            deadline = time.monotonic() + 2.0
            answer = None
            while answer is None:
                assert time.monotonic() < deadline, f"no answer at tick {k}"
                wait_readable([rig.sim], 0.05)
                for msg in rig.sim.read():
                    t_us, answer = decode_actuators(msg, 8.0)
                    assert t_us == int(round(rig.t * 1e6))
            thrusts.append(answer)
            if on_tick is not None:
                on_tick(k)
        if after is not None:
            after()
    finally:
        stop_polling()
    fw, st = v.fw, v.sim.stats
    return {"thrusts": np.array(thrusts), "x": fw.ekf.x, "P": fw.ekf.P, "pos_int": fw.integrals.pos,
            "att_int": fw.integrals.att, "xi_pre": fw.allocator.xi_pre, "time": (fw.time_s, v.fc_time_us),
            "airborne": fw.airborne, "thrust_n": fw.thrust_total_n, "log_t": v.flight_log()["t"],
            "log_p": v.flight_log()["p_ctrl"], "counts": (dict(st.per_type), st.rx_messages, st.tx_messages, st.rx_bytes),
            "dropped": (st.dropped_frames, st.dropped_bytes, st.seq_lost), "seq": _seq_numbers(v.sim, rig.sim),
            "calls": [c for c in calls if c is not None]}


def _seq_numbers(vehicle_port, sim_port) -> tuple:
    """A MAVLink link's sequence numbers both ways (the vehicle's next one, the last it heard, the
    simulator's record of the vehicle's); ``()`` on the same-host link, which has none."""
    if not isinstance(vehicle_port, MavlinkPort):
        return ()
    return vehicle_port.mav.seq, dict(vehicle_port._last_seq), dict(sim_port._last_seq), sim_port.stats.seq_lost


@pytest.mark.parametrize("link", ["unix", "tcp"])
def test_the_lockstep_loop_flies_as_the_record_tick(tmp_path, link):
    """The vehicle's lockstep loop (Lockstep.run_loop: the waits, the packets, the quiet ticks and
    their answers in one compiled call) against the record tick it stands for (over TCP: the
    decoders and pymavlink's frames), over 400 ticks with a fading correction, a take-off and AHRS
    and GPS ticks: the same answers, EKF state, integrals, allocation state, flight log and link
    counters (sequence numbers both ways included), bit for bit; and the loop did run many ticks in
    a call and handed back the ticks that need the vehicle (streams and log rows at 50 Hz, the
    take-off) and the packets that are not its (AHRS, GPS)."""
    if not COMPILED:
        pytest.skip("numba not installed (or SKELETON_JIT=0)")
    plain, looped = _plain_and_looped(tmp_path, link, lambda rig, loop: _lockstep_flight(rig, 400, loop))
    assert np.abs(plain["thrusts"]).sum(axis=1).min() > 10.0 and plain["airborne"]
    for key in plain:
        if key != "calls":
            np.testing.assert_equal(looped[key], plain[key], err_msg=key)
    assert not plain["calls"]
    calls = looped["calls"]
    ticks = sum(c[1] for c in calls)
    assert ticks >= 300 and max(c[1] for c in calls) >= 5, (ticks, max(c[1] for c in calls))
    statuses = {c[0] for c in calls}
    assert {LOOP_TICKED, LOOP_PACKET} <= statuses, statuses



@pytest.mark.parametrize("link", ["unix", "tcp"])
def test_the_lockstep_loop_counts_rejected_attitude_references_as_the_record_tick(tmp_path, link):
    """Attitude references at 100 Hz (two in each 50 Hz stream period) that the gate rejects, from
    tick 100 on a heading 150 deg away: the loop hands back at each rejection (the rejections in a
    row decide when the next reference resets the attitude), so it resets at the same reference as
    the record tick, and flies on bit for bit."""
    if not COMPILED:
        pytest.skip("numba not installed (or SKELETON_JIT=0)")
    far = quat_from_euler_zyx(np.radians(150.0), 0.0, 0.0)

    def fly(rig, loop):
        out = _lockstep_flight(rig, 400, loop, ahrs_every=5, ahrs_q=lambda k: far if k >= 100 else LEVEL)
        ekf = rig.vehicle.fw.ekf
        return out | {"att": (ekf.resets, ekf.accepted["att"], ekf.rejected["att"], ekf.rejected_run["att"])}

    plain, looped = _plain_and_looped(tmp_path, link, fly)
    resets, _, rejected, _ = plain["att"]
    assert resets == 1 and rejected == EkfConfig().att_reset_rejections, plain["att"]
    for key in plain:
        if key != "calls":
            np.testing.assert_equal(looped[key], plain[key], err_msg=key)
    assert sum(c[1] for c in looped["calls"]) >= 300


@pytest.mark.parametrize("link", ["unix", "tcp"])
@pytest.mark.parametrize("loop", [True, False], ids=["loop", "record_tick"])
def test_a_wrench_that_is_not_finite_is_answered_with_the_held_commands(tmp_path, link, loop):
    """A controller integral turned NaN between two ticks (a numerical failure inside the
    firmware), on the compiled paths (the lockstep loop, the record tick or the decoders): that
    tick is answered all the same, with the previous tick's thrusts, the refusal is counted and
    reported, the vehicle flies on with finite thrusts and writes the count at the end."""
    if not COMPILED:
        pytest.skip("numba not installed (or SKELETON_JIT=0)")
    rig = Rig(tmp_path, sim_link=link)
    v = rig.vehicle

    def corrupt(k):
        if k == 150:
            v.fw.controller.state[CTL_POS_INT] = np.nan

    try:
        flight = _lockstep_flight(rig, 300, loop, on_tick=corrupt)
        texts = [str(t) for t in v.flight_log()["statustext_text"]]
    finally:
        rig.close()
    thrusts = flight["thrusts"]
    np.testing.assert_allclose(thrusts[151], thrusts[150], atol=1e-4)
    assert np.isfinite(thrusts).all() and np.abs(thrusts[152:]).sum(axis=1).min() > 10.0
    assert v.fw.wrench_guard.refused == 1 and "Wrench not finite: command held (1)" in texts
    ports = json.loads((tmp_path / "out" / "link2_ports.json").read_text())
    assert ports["wrench"] == {"refused": 1, "holding": False}



def test_the_lockstep_loop_over_tcp_hands_cut_frames_and_noise_to_the_parser(tmp_path):
    """Over PX4's TCP link the lockstep loop takes only reads that are a tick's whole frames: with
    ticks written in two pieces (cut inside a frame) and noise between ticks, it hands those bytes
    to pymavlink's parser, which joins the frames and counts the noise, and takes the stream back
    once the parser holds no partial frame. The flight is the decoders' flight bit for bit, the
    noise counted alike, and the loop still took most ticks."""
    if not COMPILED:
        pytest.skip("numba not installed (or SKELETON_JIT=0)")
    plain, looped = _plain_and_looped(tmp_path, "tcp",
                                      lambda rig, loop: _lockstep_flight(rig, 300, loop, rough_every=7))
    for key in plain:
        if key != "calls":
            np.testing.assert_equal(looped[key], plain[key], err_msg=key)
    dropped_frames, dropped_bytes, seq_lost = plain["dropped"]
    assert dropped_frames == 42 and dropped_bytes == 42 * 7 and seq_lost == 0, plain["dropped"]
    ticks = sum(c[1] for c in looped["calls"])
    handed = sum(c[0] == LOOP_PACKET for c in looped["calls"])
    assert ticks >= 150 and handed >= 2 * 42, (ticks, handed)  # (each cut tick's first piece, the noise)


def _unread_flight(rig, n_ticks: int, loop: bool) -> dict:
    """``n_ticks`` ticks into ``rig``'s vehicle over TCP (armed, with a target; polling in its own
    thread), 2 ms apart, with the socket buffers as small as Linux allows and the simulator reading
    no answer until the last tick is sent: the vehicle's sends fill the buffers and are cut or
    refused (EAGAIN), and it waits in them until the simulator reads."""
    v = rig.vehicle
    v.fw.hil_loop = loop
    rests = []
    plain_rest = v.lockstep.answer_rest
    v.lockstep.answer_rest = lambda a: rests.append(int(v.lockstep.buffers.framing[frames.FRAMING["sent"]])) or plain_rest(a)
    # the simulator reconnects with the least receive buffer (set before connecting: TCP's window)
    rig.sim.close()
    while v.sim.connected:
        v.poll(0.01)
    sock = socket.socket()
    sock.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, 1)
    sock.connect(("127.0.0.1", v.sim.transport.local_port()))
    sock.setblocking(False)
    transport = TcpClient.__new__(TcpClient)  # (its constructor connects with the default buffers)
    transport.sock, transport.closed = sock, False
    rig.sim = MavlinkPort("tcpout://127.0.0.1", system_id=250, component_id=1, transport=transport)
    while not v.sim.connected:
        v.poll(0.01)
    v.sim.transport.conn.setsockopt(socket.SOL_SOCKET, socket.SO_SNDBUF, 1)
    _armed_with_a_target(rig)
    stop_polling = _poll_in_thread(v)
    want = []
    answers = []
    try:
        for k in range(n_ticks):
            rig.t = round(rig.t + 0.002, 6)
            want.append(int(round(rig.t * 1e6)))
            msgs = [encode_ahrs(rig.t, LEVEL)] if k % 10 == 0 else []
            msgs.append(encode_hil_sensor(rig.t, np.array([0.1 * np.sin(0.3 * k), -0.05, 9.80665]),
                                          np.array([0.01, 0.0, -0.02])))
            rig.sim.send_many(msgs)
            time.sleep(0.002)
        deadline = time.monotonic() + 10.0
        while len(answers) < n_ticks:
            assert time.monotonic() < deadline, len(answers)
            wait_readable([rig.sim], 0.05)
            answers += [decode_actuators(m, 8.0) for m in rig.sim.read()]
    finally:
        stop_polling()
    assert [t for t, _ in answers] == want
    st = rig.sim.stats
    return {"thrusts": np.array([a for _, a in answers]), "rests": rests,
            "harness": (st.rx_messages, st.seq_lost, st.dropped_frames, st.dropped_bytes),
            "vehicle": (v.sim.stats.tx_messages, v.sim.stats.tx_errors, v.sim.mav.seq)}


def test_the_lockstep_loop_over_tcp_finishes_an_answer_its_send_cut(tmp_path):
    """Over TCP the lockstep loop's send of an answer frame may take part of it or nothing (a full
    socket buffer: the simulator not reading); the vehicle then writes the rest
    (Lockstep.answer_rest) and waits until it goes. With the buffers at their least and the simulator
    reading nothing for 300 ticks: every answer arrives whole and in order, no frame lost or
    broken, the same thrusts and counters as the decoding path's."""
    if not COMPILED:
        pytest.skip("numba not installed (or SKELETON_JIT=0)")
    plain, looped = _plain_and_looped(tmp_path, "tcp", lambda rig, loop: _unread_flight(rig, 300, loop))
    np.testing.assert_array_equal(looped["thrusts"], plain["thrusts"])
    assert looped["harness"] == plain["harness"] and plain["harness"][1:] == (0, 0, 0), plain["harness"]
    assert looped["vehicle"] == plain["vehicle"] and plain["vehicle"][1] == 0
    assert not plain["rests"] and looped["rests"], looped["rests"]  # the loop's sends were cut

    # ... and a send that took part of the frame (rare on loopback: the buffer has room for some
    # of its 93 bytes): the rest follows it and the simulator reads one whole answer
    rig = Rig(tmp_path / "cut", sim_link="tcp")
    try:
        v = rig.vehicle
        answer = np.frombuffer(encode_packet([encode_actuators(0.5, np.arange(8.0), 8.0, True)]), dtype=np.uint8)
        framing = v.lockstep.buffers.framing
        framing[:7] = (frames.FRAMES_TO_VEHICLE, 250, 1, 0, v.system_id, 1, v.sim.mav.seq)
        length = frames.record_to_frame(answer, v.lockstep.buffers.frame, framing)
        framing[frames.FRAMING["length"]], framing[frames.FRAMING["sent"]] = length, 40
        v.sim.transport.conn.send(v.lockstep.buffers.frame[:40].tobytes())
        v.lockstep.answer_rest(answer)
        deadline, got = time.monotonic() + 2.0, []
        while not got:
            assert time.monotonic() < deadline
            wait_readable([rig.sim], 0.05)
            got = rig.sim.read()
        assert decode_actuators(got[0], 8.0)[0] == 500_000 and rig.sim.stats.dropped_frames == 0
    finally:
        rig.close()


def test_the_lockstep_loop_hands_mavlink_input_over_at_once_and_while_the_simulator_is_silent(tmp_path):
    """In the lockstep loop a vehicle waits on its MAVLink ports too and hands a readable one to
    poll at once: a GCS request sent between two ticks is answered by the next tick; with the
    simulator silent (armed, flying, no tick coming) it is answered all the same."""
    if not COMPILED:
        pytest.skip("numba not installed (or SKELETON_JIT=0)")
    rig = Rig(tmp_path, sim_link="unix")
    request = D.MAVLink_param_request_read_message(2, 1, b"SKL_CORR_HOLD", -1)
    answered_at, asked = [], []

    def replies():
        return [m for m in rig.gcs.read() if m.get_type() == "PARAM_VALUE"]

    def on_tick(k):
        if replies() and asked and not answered_at:
            answered_at.append(k)
        if k == 150:
            assert rig.gcs.transport.connected  # the vehicle's streams reached it: it can reply
            rig.gcs.send(request)
            asked.append(k)

    def after():
        time.sleep(0.1)  # the simulator silent: no tick comes
        rig.gcs.read()
        rig.gcs.send(request)
        deadline = time.monotonic() + 1.0
        while not replies():
            assert time.monotonic() < deadline, "no PARAM_VALUE while the simulator is silent"
            time.sleep(0.005)

    try:
        flight = _lockstep_flight(rig, 200, True, on_tick, after)
    finally:
        rig.close()
    assert sum(c[1] for c in flight["calls"]) >= 100
    # replied while tick 151 is on its way: the feeder finds it after tick 151 (152: UDP's timing)
    assert answered_at and answered_at[0] <= 152, answered_at
