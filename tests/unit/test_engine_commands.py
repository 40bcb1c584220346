"""The companion engine's commands to the links, pure (a fake clock, no sockets): stream requests,
heartbeats and health rows on their periods, ARM retried until a link reports armed."""

from __future__ import annotations

import pytest

from companion.engine import ARM_FAST_TRIES, ARM_RETRY_S, RETRY_S, Command, CommandOut, CompanionEngine, HealthDue, Heartbeat
from companion.messages import STATE_FLAG_ARMED, STATE_FLAG_EKF_OK

from ..engine_cases import feed, of, setup_for


def test_stream_request_retries_each_second_until_acknowledged():
    engine = CompanionEngine(setup_for())
    engine.on_heartbeat(0, 10.0)
    req = of(CommandOut, engine.poll(10.0))
    assert [(r.row, r.command, r.system_id) for r in req] == [(0, Command.STREAM, 1)]
    assert req[0].interval_us == pytest.approx(1e6 / 50.0)
    engine.on_heartbeat(0, 10.0 + 0.5 * RETRY_S)
    assert not of(CommandOut, engine.poll(10.5))  # too soon
    engine.on_heartbeat(0, 10.0 + RETRY_S)
    assert of(CommandOut, engine.poll(11.0))  # retried
    engine.on_command_ack(0, Command.STREAM, True)
    engine.on_heartbeat(0, 20.0)
    assert not of(CommandOut, engine.poll(20.0))


def test_heartbeat_each_second_and_health_each_period():
    engine = CompanionEngine(setup_for(health_period_s=5.0))
    beats = health = 0
    for k in range(121):  # 12 s in 0.1 s
        out = engine.poll(100.0 + 0.1 * k)
        beats += len(of(Heartbeat, out))
        health += len(of(HealthDue, out))
    assert beats == 13 and health == 2


def test_a_link_disarmed_while_it_streams_is_not_armed_again_until_it_powers_on_again(caplog):
    """Its pilot or a failsafe disarmed it (its stream never broke off): the companion leaves it
    disarmed and says so once; silent as long as a carried link, then back disarmed, it may have
    powered off and on (a reboot in flight): armed again."""
    engine = CompanionEngine(setup_for())
    dt = 0.02  # the state stream's period

    def arms(t, flags=STATE_FLAG_EKF_OK):
        return [a.row for a in of(CommandOut, feed(engine, t, t, flags=flags)) if a.command is Command.ARM]

    assert arms(0.0) == [0, 1, 2]
    t = 0.0
    for _ in range(5):
        t += dt
        arms(t, flags=STATE_FLAG_EKF_OK | STATE_FLAG_ARMED)
    for _ in range(int(3 * RETRY_S / dt)):  # disarmed, streaming on: three seconds of no ARM
        t += dt
        assert arms(t) == []
    assert caplog.text.count("was disarmed (its pilot, a failsafe): not arming it again") == 3  # once a link
    t += 2 * engine.cfg.carry_silence_s  # a silence, then back disarmed
    assert arms(t) == [0, 1, 2]


def test_arm_retries_until_the_link_reports_armed():
    """A disarmed link with a usable EKF (e.g. rebooted in flight, rotors off) is asked again every
    ARM_RETRY_S for the first ARM_FAST_TRIES commands (a lost command costs 0.2 s, not 1 s), then
    every RETRY_S; a link that reports armed is left alone and its count starts over."""
    engine = CompanionEngine(setup_for())

    def arms(t, now, flags=STATE_FLAG_EKF_OK):
        return [a.row for a in of(CommandOut, feed(engine, t, now, flags=flags)) if a.command is Command.ARM]

    assert arms(0.0, 0.0) == [0, 1, 2]
    assert arms(0.02, 0.5 * ARM_RETRY_S) == []  # too soon
    sent = [0.0]
    now = 0.0
    while len(sent) < ARM_FAST_TRIES:
        now += ARM_RETRY_S + 1e-6
        assert arms(now, now) == [0, 1, 2]
        sent.append(now)
    assert arms(now + ARM_RETRY_S, now + ARM_RETRY_S) == []  # the fast tries are used up
    assert arms(now + 0.9 * RETRY_S, now + 0.9 * RETRY_S) == []
    assert arms(now + RETRY_S + 1e-6, now + RETRY_S + 1e-6) == [0, 1, 2]
    now += RETRY_S + 1e-6
    assert arms(now + 0.1, now + 5.0, flags=STATE_FLAG_EKF_OK | STATE_FLAG_ARMED) == []
    # disarmed again later (a reboot in flight): fast again
    assert arms(now + 0.2, now + 6.0) == [0, 1, 2]
    assert arms(now + 0.3, now + 6.0 + ARM_RETRY_S + 1e-6) == [0, 1, 2]
