"""The lockstep's time shared through a file (sitl.fleet.sim_time): what the writer publishes the
clock reads, the clock runs on wall time only while the simulated time stands still, and it never
steps back."""

import multiprocessing

import pytest

from sitl.fleet.sim_time import SIM_TIME_BYTES, SimTimeClock, SimTimeWriter


class Wall:
    """An injected wall clock [s]."""

    def __init__(self):
        self.t = 100.0

    def __call__(self) -> float:
        return self.t


@pytest.fixture
def shared(tmp_path):
    writer = SimTimeWriter(tmp_path / "sim_time")
    wall = Wall()
    clock = SimTimeClock(writer.path, wall=wall, stall_s=0.25)
    yield writer, clock, wall
    clock.close()
    writer.close()


def test_the_clock_follows_the_simulated_time(shared):
    writer, clock, wall = shared
    assert writer.path.stat().st_size == SIM_TIME_BYTES
    readings = []
    for k in range(1, 50):
        writer.publish(k * 0.002)
        wall.t += 0.0004  # five times real time
        readings.append(clock())
    # the clock's steps are the simulated time's, whatever the pace
    steps = [b - a for a, b in zip(readings, readings[1:])]
    assert all(s == pytest.approx(0.002, abs=1e-9) for s in steps)


@pytest.mark.parametrize("stall_s", [0.1, 0.25, 1.0])
def test_a_stalled_lockstep_hands_over_to_wall_time_and_back_without_a_step_back(tmp_path, stall_s):
    writer, wall = SimTimeWriter(tmp_path / "t"), Wall()
    clock = SimTimeClock(writer.path, wall=wall, stall_s=stall_s)
    try:
        writer.publish(1.0)
        t0 = clock()
        wall.t += stall_s  # still within the grace: the clock waits for the lockstep
        assert clock() == t0
        wall.t += 2.0  # the lockstep is held up: wall time from the end of the grace
        assert clock() == pytest.approx(t0 + 2.0)
        before = clock()
        writer.publish(1.002)  # it moves again: followed from where the clock stood (the stall
        wall.t += 0.001  # counted until it was seen to end)
        after = clock()
        assert after == pytest.approx(before + 0.001 + 0.002)
        writer.publish(1.004)
        assert clock() == pytest.approx(after + 0.002)
    finally:
        clock.close()
        writer.close()


def test_a_missing_file_is_a_lockstep_not_yet_started(tmp_path):
    wall = Wall()
    clock = SimTimeClock(tmp_path / "none", wall=wall, stall_s=0.25)
    assert clock() == 0.0
    wall.t += 1.25
    assert clock() == pytest.approx(1.0)  # held datagrams still leave, on wall time
    writer = SimTimeWriter(tmp_path / "none")  # the launcher creates it later
    try:
        writer.publish(0.002)
        wall.t += 0.001
        assert clock() == pytest.approx(1.0 + 0.001 + 0.002)
    finally:
        clock.close()
        writer.close()


def _publish_many(path, n):
    writer = SimTimeWriter(path)
    for k in range(1, n + 1):
        writer.publish(k * 1e-3 + 1e3)  # large values: a torn read would show in the high bytes
    writer.close()


def test_another_process_never_reads_a_torn_or_backward_time(tmp_path):
    path = tmp_path / "t"
    clock = SimTimeClock(path, stall_s=1e9)  # (mapped once the writer has created the file)
    proc = multiprocessing.get_context("spawn").Process(target=_publish_many, args=(path, 200_000))
    proc.start()
    seen = []
    try:
        while proc.is_alive() or not seen:
            seen.append(clock())
            if len(seen) > 2_000_000:
                break
    finally:
        proc.join(30)
        clock.close()
    moved = [t for t in seen if t > 0]
    assert len(set(moved)) > 1, "the reader never saw the writer at work"
    assert all(b >= a for a, b in zip(seen, seen[1:]))
    # every value read is one the writer published: a whole number of ms above 1000 s
    assert all(abs(t * 1e3 - round(t * 1e3)) < 1e-6 and 1000.0 < t <= 1200.0 for t in moved)
