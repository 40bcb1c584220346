"""A link's clock over TIMESYNC (companion.mavlink.timesync): learnt from the answers to our
requests, used to answer the link's requests on its own clock; hostile and stale answers refused."""

from __future__ import annotations

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from companion.mavlink.timesync import LinkTimesync, TimesyncConfig

MS = 1_000_000  # nanoseconds


def exchange(sync: LinkTimesync, now_ns: int, offset_ns: int, up_ns: int, down_ns: int) -> bool | None:
    """One request of ours at ``now_ns`` to a link whose clock is ours plus ``offset_ns``, its legs
    ``up_ns`` there and ``down_ns`` back; whether the estimate took the answer (``None``: none due)."""
    ts1 = sync.request(now_ns)
    if ts1 is None:
        return None
    tc1 = ts1 + up_ns + offset_ns
    return sync.on_answer(tc1, ts1, now_ns + up_ns + down_ns)


def synced(offset_ns=123_456_789_000, rtt_ns=2 * MS) -> tuple[LinkTimesync, int]:
    sync, t = LinkTimesync(), 10**12
    while not sync.synchronised:
        exchange(sync, t, offset_ns, rtt_ns // 2, rtt_ns // 2)
        t += 100 * MS
    return sync, t


def test_the_link_clock_is_learnt_and_its_requests_answered_on_it():
    sync, t = LinkTimesync(), 10**12
    assert sync.answer(5, t) is None and sync.counts["unsynced"] == 1  # nothing learnt: PX4 stamps on arrival
    offset = 123_456_789_000
    taken = [exchange(sync, t + k * 100 * MS, offset, MS, MS) for k in range(sync.config.min_samples)]
    assert all(taken) and sync.synchronised and sync.offset_ns == offset and sync.rtt_ns == 2 * MS
    t += 10**9
    asked = t + offset - MS  # PX4's clock when it asked, a millisecond before
    tc1, ts1 = sync.answer(asked, t)
    assert (tc1, ts1) == (t + offset, asked)
    # what PX4 makes of the answer: its clock less ours at the middle of its round trip, zero here,
    # so a stamp on its own clock stays as it is (sync_stamp adds that offset)
    px4_sent, px4_back = t + offset - MS, t + offset + MS
    assert (px4_sent + px4_back - 2 * tc1) // 2 == 0
    assert sync.report()["synchronised"] and sync.report()["offset_ms"] == pytest.approx(offset * 1e-6)


@settings(max_examples=200, deadline=None)
@given(offset=st.integers(-(2**40), 2**62), up=st.integers(0, 5 * MS), down=st.integers(0, 5 * MS))
def test_the_estimate_is_the_offset_less_half_the_legs_difference(offset, up, down):
    sync, t = LinkTimesync(), 10**12
    for k in range(sync.config.min_samples):
        assert exchange(sync, t + k * 100 * MS, offset, up, down)
    assert abs(sync.offset_ns - (offset + (up - down) / 2)) <= 1


def test_requests_are_paced_faster_until_synchronised():
    sync, t = LinkTimesync(), 10**12
    assert sync.request(t) is not None and sync.request(t + 50 * MS) is None
    assert sync.request(t + 100 * MS) is not None
    sync, t = synced()
    assert sync.request(t) is not None and sync.request(t + 500 * MS) is None and sync.request(t + 1000 * MS)


def test_a_link_that_never_answers_is_asked_once_a_second():
    sync, t = LinkTimesync(), 10**12
    for _ in range(sync.config.outstanding):
        assert sync.request(t) is not None
        t += 100 * MS
    assert sync.request(t) is not None and sync.request(t + 500 * MS) is None and sync.request(t + 1000 * MS)
    assert exchange(sync, t + 2000 * MS, 0, MS, MS)  # an answer at last: quick again until synchronised
    assert sync.request(t + 2100 * MS) is not None


@pytest.mark.parametrize("case", ["unknown", "replayed", "slow", "backwards", "no_clock", "huge_clock"])
def test_answers_to_no_request_or_out_of_bounds_are_refused(case):
    sync, t = synced()
    before = sync.offset_ns
    ts1 = sync.request(t)
    good = ts1 + before + MS
    if case == "unknown":
        taken = sync.on_answer(good, ts1 + 1, t + 2 * MS)
    elif case == "replayed":
        assert sync.on_answer(good, ts1, t + 2 * MS)
        taken = sync.on_answer(good + 10**9, ts1, t + 3 * MS)
    elif case == "slow":
        taken = sync.on_answer(good, ts1, t + 11 * MS)
    elif case == "backwards":
        taken = sync.on_answer(good, ts1, t - MS)
    else:
        taken = sync.on_answer(0 if case == "no_clock" else 2**63, ts1, t + 2 * MS)
    assert not taken and sync.offset_ns == before
    key = {"replayed": "unknown", "backwards": "slow", "no_clock": "unknown", "huge_clock": "unknown"}.get(case, case)
    assert sync.counts[key] == 1


def test_outliers_are_dropped_and_a_run_of_them_is_a_new_clock():
    sync, t = synced(offset_ns=5 * 10**9)
    cfg = sync.config
    for k in range(cfg.restart_after - 1):  # a few far answers: dropped, the estimate holds
        assert exchange(sync, t + k * 10**9, 7 * 10**9, MS, MS) is False
    assert sync.offset_ns == 5 * 10**9 and sync.counts["outlier"] == cfg.restart_after - 1
    assert exchange(sync, t + 5 * 10**9, 5 * 10**9, MS, MS)  # a good one ends the run
    t += 6 * 10**9
    for k in range(cfg.restart_after):  # the link rebooted: its clock restarted 2 s later
        exchange(sync, t + k * 10**9, 7 * 10**9, MS, MS)
    assert sync.counts["restarts"] == 1 and not sync.synchronised and sync.answer(1, t + 10**10) is None
    t += 10 * 10**9
    while not sync.synchronised:
        exchange(sync, t, 7 * 10**9, MS, MS)
        t += 100 * MS
    assert sync.offset_ns == 7 * 10**9


def test_requests_are_answered_at_a_bounded_rate():
    sync, t = synced()
    link = t + sync.offset_ns  # (the link's clock now)
    assert sync.answer(link, t) is not None
    assert sync.answer(link + 5 * MS, t + 5 * MS) is None and sync.counts["too_soon"] == 1
    assert sync.answer(link + 10 * MS, t + 10 * MS) is not None and sync.counts["answered"] == 2


def test_the_estimate_follows_the_median():
    sync = LinkTimesync(TimesyncConfig(window=5, min_samples=1))
    t, offsets = 10**12, [10, 50, 20, 40, 30]
    for k, off in enumerate(offsets):
        exchange(sync, t + k * 10**9, off * MS, MS, MS)
    assert sync.offset_ns == 30 * MS


def test_a_request_stamped_on_a_restarted_clock_is_not_answered_and_the_clock_learnt_again():
    """PX4 rebooted: its requests' stamps count from its new boot. Answering on the old clock would
    feed its fresh filter a wrong offset for seconds (it checks no deviation before converging);
    the first such request restarts the estimate instead, and the next request goes out at once."""
    sync, t = synced(offset_ns=300 * 10**9)
    assert sync.answer(t + 300 * 10**9 - MS, t) is not None  # (a request a millisecond on its way)
    t += 10**9
    assert sync.answer(2 * 10**9, t) is None  # 2 s into its new boot
    assert sync.counts["restarts"] == 1 and not sync.synchronised and sync.offset_ns is None
    assert sync.request(t) is not None
    assert sync.waiting_s(t + 3 * 10**9) == pytest.approx(3.0)


def test_waiting_counts_from_the_first_unanswered_request():
    sync, t = LinkTimesync(), 10**12
    assert sync.waiting_s(t) == 0.0
    for k in range(30):
        sync.request(t + k * 100 * MS)
    assert sync.waiting_s(t + 20 * 10**9) == pytest.approx(20.0)
    sync, t = synced()
    assert sync.waiting_s(t + 60 * 10**9) == 0.0
