"""A distributed chain's home (companion.engine.home), pure: who measures it, who waits, what is
taken from the other groups and what is refused."""

from __future__ import annotations

import numpy as np
import pytest

from companion.engine.home import HOME_AGREE_M, HOME_MARGIN_S, HOME_REPEAT_US, NetHome
from companion.engine.links import LinkTrack
from companion.estimation.so3 import quat_from_euler_zyx, quat_to_rotmat
from companion.messages import STATE_FLAG_ARMED, STATE_FLAG_EKF_OK, ChainHome

ANCHOR = np.array([1.0, -2.0, 0.3])
UNIT = np.array([1.0, 0.0, 0.0, 0.0])
REFINE_S = 0.8  # the take-off starts at 1 s
LATE_S = 30.0  # trajectory time long after the take-off (a companion started in flight)


class Net:
    """A group link that keeps what is published."""

    def __init__(self):
        self.sent: list[ChainHome] = []

    def publish_home(self, home: ChainHome) -> None:
        self.sent.append(home)


def planned(n_links):
    """The trajectory's link centres at its start: a straight chain along x about the anchor."""
    return ANCHOR + np.outer(np.arange(n_links) - (n_links - 1) / 2, [1.0, 0.0, 0.0])


def layout(n_links):
    """Two groups: the first two links, then the rest (link n // 2 in the second for n >= 4)."""
    return ((0, 1), tuple(range(2, n_links)))


def home_of(indices, n_links, group=0, armed=False, wait_s=5.0, groups=None):
    links = [LinkTrack(i, row, i + 1, flags=STATE_FLAG_EKF_OK | (STATE_FLAG_ARMED if armed else 0))
             for row, i in enumerate(indices)]
    d = np.tile([0.5, 0.0, 0.0], (len(indices), 1))
    net = Net()
    return NetHome(group, groups or layout(n_links), net, links, d, n_links, ANCHOR, wait_s=wait_s), net


def resting(indices, n_links, shift=(0.0, 0.0, 0.0)):
    """``(p, q)`` of links at the trajectory's start, all moved by ``shift`` (a shared error)."""
    return planned(n_links)[list(indices)] + np.asarray(shift), np.tile(UNIT, (len(indices), 1))


def at(home, t, estimate, n_links=5):
    """The home at trajectory (and companion) time ``t`` [s]."""
    return home.offset(t, estimate, planned(n_links), t, REFINE_S)


@pytest.mark.parametrize("n_links, indices, expected", [
    (5, (2, 3, 4), "centre"),  # odd: the middle link's centre
    (4, (2, 3), "left tip"),  # even: the middle joint, the left tip of link n / 2
])
def test_the_group_with_the_middle_link_measures_the_home_from_its_steps(n_links, indices, expected):
    home, net = home_of(indices, n_links, group=1)
    assert home.measurer == 1 and at(home, 0.0, None, n_links) is None  # before the first step: waiting
    q = quat_from_euler_zyx(0.4, 0.1, -0.2)
    p = np.array([[1.2, -1.7, 0.4], [2.0, -1.0, 0.5], [2.5, -0.5, 0.6]])[:len(indices)]
    offset = at(home, 0.05, (p, np.tile(q, (len(indices), 1))), n_links)
    middle = p[0] if expected == "centre" else p[0] - quat_to_rotmat(q) @ np.array([0.5, 0.0, 0.0])
    np.testing.assert_allclose(offset, middle - ANCHOR, atol=1e-12)
    assert home.source == "measured"


def test_the_home_is_measured_again_while_the_chain_rests_and_kept_from_then_on():
    """The measuring group's estimate settles after its start: the home follows it until the
    take-off is near, is published at every measurement, and is then kept and repeated each second."""
    home, net = home_of((2, 3, 4), 5, group=1)
    for k, t in enumerate(np.arange(0.0, 2.0, 0.05)):
        got = at(home, t, resting((2, 3, 4), 5, (0.0, 0.0, 0.3 - 0.01 * k)))
        home.publish(int(round(t * 1e6)))
        want = 0.3 - 0.01 * min(k, 15)  # (the last measurement at 0.75 s: trajectory time < 0.8 s)
        np.testing.assert_allclose(got, [0.0, 0.0, want], atol=1e-12)
    stamps = [m.time_us for m in net.sent]
    assert stamps[:16] == [50_000 * k for k in range(16)]  # every measurement
    assert stamps[16:] == [1_750_000]  # then each second after the last (0.75 s)
    home.publish(1_750_000 + HOME_REPEAT_US)
    assert net.sent[-1].time_us == 1_750_000 + HOME_REPEAT_US


def test_a_group_without_the_middle_link_follows_the_measurements_then_keeps_the_last():
    home, net = home_of((0, 1), 5, group=0)
    shift = np.array([0.3, -0.2, 1.5])
    assert at(home, 0.0, resting((0, 1), 5, shift)) is None  # not its to measure
    for k, t_us in enumerate((50_000, 100_000, 750_000)):
        home.on_remote(ChainHome(1, t_us, shift + 0.1 * k))
        home.publish(t_us)
    home.on_remote(ChainHome(1, 60_000, shift + 0.4))  # an older measurement, late: counted, not taken
    np.testing.assert_array_equal(at(home, 0.9, None), shift + 0.2)
    assert not net.sent  # (it publishes only the home it keeps)
    at(home, REFINE_S + HOME_MARGIN_S, None)  # kept from here on
    home.publish(1_000_000)
    assert [m.time_us for m in net.sent] == [1_000_000]
    home.on_remote(ChainHome(1, 1_050_000, shift + 0.2))  # the same, repeated
    home.on_remote(ChainHome(1, 2_050_000, shift + 1.0))  # another: counted, not flown
    np.testing.assert_array_equal(at(home, 2.1, None), shift + 0.2)
    assert home.source == "group 2"
    assert home.counts == {"published": 1, "received": 6, "stale": 1, "conflicts": 1, "rejected": 0}


def test_a_home_that_comes_before_the_groups_first_step_is_judged_by_it():
    home, _ = home_of((0, 1), 5, group=0)
    home.on_remote(ChainHome(1, 0, np.array([0.0, 0.0, HOME_AGREE_M + 2.0])))  # a forgery, first
    home.on_remote(ChainHome(1, 0, np.array([0.2, 0.1, 2.0])))
    assert at(home, 0.0, None) is None and home.counts["received"] == 0  # held for the step
    np.testing.assert_array_equal(at(home, 0.05, resting((0, 1), 5, (0.0, 0.0, 1.8))), [0.2, 0.1, 2.0])
    assert home.counts["received"] == 1 and home.counts["rejected"] == 1


@pytest.mark.parametrize("group, far", [(0, False), (2, False), (7, False), (1, True)])
def test_a_home_from_this_group_outside_the_layout_or_far_from_its_links_is_refused(group, far):
    home, _ = home_of((0, 1), 5, group=0)
    at(home, 0.05, resting((0, 1), 5))
    home.on_remote(ChainHome(group, 60_000, np.array([0.0, HOME_AGREE_M + 0.1, 0.0]) if far else np.zeros(3)))
    assert home.offset_w_m is None and home.counts["rejected"] == 1


def test_a_companion_started_in_flight_does_not_measure_and_takes_the_others_home():
    """Its links were armed when it first heard them: the chain flies, so its estimate is not
    where the chain was set down; it takes the home the other groups repeat, whatever its links
    say now (the trajectory has moved them)."""
    home, _ = home_of((2, 3, 4), 5, group=1, armed=True)
    estimate = resting((2, 3, 4), 5, (0.0, 0.0, 7.0))
    assert at(home, LATE_S, estimate) is None and at(home, LATE_S + 0.5, estimate) is None
    home.on_remote(ChainHome(0, 30_600_000, np.array([0.3, -0.2, 1.5])))
    np.testing.assert_array_equal(at(home, LATE_S + 0.6, estimate), [0.3, -0.2, 1.5])


@pytest.mark.parametrize("armed", [False, True])
def test_without_a_home_within_the_wait_the_anchor_is_flown_as_given(armed):
    home, net = (home_of((2, 3, 4), 5, group=1, armed=True, wait_s=2.0) if armed
                 else home_of((0, 1), 5, group=0, wait_s=2.0))
    assert at(home, 10.0, None) is None and at(home, 11.99, None) is None
    np.testing.assert_array_equal(at(home, 12.0, None), np.zeros(3))
    assert home.source == "anchor"
    home.publish(12_000_000)
    assert len(net.sent) == 1 and not net.sent[0].offset_w_m.any()


def test_the_measuring_group_measures_once_its_middle_link_has_an_estimate():
    home, _ = home_of((2, 3, 4), 5, group=1)
    p, q = resting((2, 3, 4), 5, (0.0, 0.0, -1.0))
    p[0] = np.nan  # the middle link without an estimate in the first step
    assert at(home, 0.05, (p, q)) is None
    np.testing.assert_allclose(at(home, 0.1, resting((2, 3, 4), 5, (0.0, 0.0, -1.0))), [0, 0, -1.0], atol=1e-12)
