"""A distributed chain's home (companion.engine.home), pure: who measures it, who waits, what is
taken from the other groups and what is refused."""

from __future__ import annotations

import numpy as np
import pytest

from companion.engine.home import HOME_AGREE_M, HOME_REPEAT_US, NetHome
from companion.engine.links import LinkTrack
from companion.estimation.so3 import quat_from_euler_zyx, quat_to_rotmat
from companion.messages import STATE_FLAG_ARMED, STATE_FLAG_EKF_OK, ChainHome

ANCHOR = np.array([1.0, -2.0, 0.3])
UNIT = np.array([1.0, 0.0, 0.0, 0.0])


class Net:
    """A group link that keeps what is published."""

    def __init__(self):
        self.sent: list[ChainHome] = []

    def publish_home(self, home: ChainHome) -> None:
        self.sent.append(home)


def planned(n_links):
    """The trajectory's link centres at its start: a straight chain along x about the anchor."""
    return ANCHOR + np.outer(np.arange(n_links) - (n_links - 1) / 2, [1.0, 0.0, 0.0])


def home_of(indices, n_links, group=0, n_groups=2, armed=False, wait_s=5.0):
    links = [LinkTrack(i, row, i + 1, flags=STATE_FLAG_EKF_OK | (STATE_FLAG_ARMED if armed else 0))
             for row, i in enumerate(indices)]
    d = np.tile([0.5, 0.0, 0.0], (len(indices), 1))
    net = Net()
    return NetHome(group, n_groups, net, links, d, n_links, ANCHOR, wait_s=wait_s), net


def resting(indices, n_links, shift=(0.0, 0.0, 0.0)):
    """``(p, q)`` of links at the trajectory's start, all moved by ``shift`` (a shared error)."""
    return planned(n_links)[list(indices)] + np.asarray(shift), np.tile(UNIT, (len(indices), 1))


@pytest.mark.parametrize("n_links, indices, expected", [
    (5, (2, 3, 4), "centre"),  # odd: the middle link's centre
    (4, (2, 3), "left tip"),  # even: the middle joint, the left tip of link n / 2
])
def test_the_group_with_the_middle_link_measures_the_home_from_its_first_step(n_links, indices, expected):
    home, net = home_of(indices, n_links)
    assert home.offset(0.0, None, planned(n_links)) is None  # before the first step: waiting
    q = quat_from_euler_zyx(0.4, 0.1, -0.2)
    p = np.array([[1.2, -1.7, 0.4], [2.0, -1.0, 0.5], [2.5, -0.5, 0.6]])[:len(indices)]
    offset = home.offset(0.05, (p, np.tile(q, (len(indices), 1))), planned(n_links))
    middle = p[0] if expected == "centre" else p[0] - quat_to_rotmat(q) @ np.array([0.5, 0.0, 0.0])
    np.testing.assert_allclose(offset, middle - ANCHOR, atol=1e-12)
    assert home.source == "measured"
    home.publish(50_000)
    home.publish(50_000 + HOME_REPEAT_US - 1)  # (not again within the repeat)
    home.publish(50_000 + HOME_REPEAT_US)
    assert [m.time_us for m in net.sent] == [50_000, 50_000 + HOME_REPEAT_US] and net.sent[0].group == 0
    np.testing.assert_array_equal(net.sent[1].offset_w_m, offset)


def test_a_group_without_the_middle_link_takes_the_home_it_receives_and_keeps_it():
    home, net = home_of((0, 1), 5, group=0)
    shift = np.array([0.3, -0.2, 1.5])
    assert home.offset(0.0, resting((0, 1), 5, shift), planned(5)) is None  # not its to measure
    home.on_remote(ChainHome(1, 60_000, shift + 0.4))  # (what the middle link measured: within its bias)
    np.testing.assert_array_equal(home.offset(0.1, None, planned(5)), shift + 0.4)
    assert home.source == "group 2"
    home.on_remote(ChainHome(1, 1_060_000, shift + 0.4))  # the same, repeated
    home.on_remote(ChainHome(1, 2_060_000, shift + 1.0))  # another: counted, not used
    np.testing.assert_array_equal(home.offset(2.1, None, planned(5)), shift + 0.4)
    assert home.counts == {"published": 0, "received": 3, "conflicts": 1, "rejected": 0}


def test_a_home_that_comes_before_the_groups_first_step_is_judged_by_it():
    home, _ = home_of((0, 1), 5, group=0)
    home.on_remote(ChainHome(1, 0, np.array([0.0, 0.0, HOME_AGREE_M + 2.0])))  # a forgery, first
    home.on_remote(ChainHome(1, 0, np.array([0.2, 0.1, 2.0])))
    assert home.offset(0.0, None, planned(5)) is None and home.counts["received"] == 0  # held for the step
    np.testing.assert_array_equal(home.offset(0.05, resting((0, 1), 5, (0.0, 0.0, 1.8)), planned(5)), [0.2, 0.1, 2.0])
    assert home.counts == {"published": 0, "received": 1, "conflicts": 0, "rejected": 1}


@pytest.mark.parametrize("group, far", [(0, False), (2, False), (7, False), (1, True)])
def test_a_home_from_this_group_outside_the_layout_or_far_from_its_links_is_refused(group, far):
    home, _ = home_of((0, 1), 5, group=0, n_groups=2)
    home.offset(0.05, resting((0, 1), 5), planned(5))
    home.on_remote(ChainHome(group, 60_000, np.array([0.0, HOME_AGREE_M + 0.1, 0.0]) if far else np.zeros(3)))
    assert home.offset_w_m is None and home.counts["rejected"] == 1


def test_a_companion_started_in_flight_does_not_measure_and_takes_the_others_home():
    """Its links were armed when it first heard them: the chain flies, so its estimate is not
    where the chain was set down; it takes the home the other groups repeat, whatever its links
    say now (the trajectory has moved them)."""
    home, _ = home_of((2, 3, 4), 5, group=1, armed=True)
    estimate = resting((2, 3, 4), 5, (0.0, 0.0, 7.0))
    assert home.offset(30.0, estimate, planned(5)) is None and home.offset(30.5, estimate, planned(5)) is None
    home.on_remote(ChainHome(0, 30_600_000, np.array([0.3, -0.2, 1.5])))
    np.testing.assert_array_equal(home.offset(30.6, estimate, planned(5)), [0.3, -0.2, 1.5])


@pytest.mark.parametrize("armed", [False, True])
def test_without_a_home_within_the_wait_the_anchor_is_flown_as_given(armed):
    home, net = (home_of((2, 3, 4), 5, group=1, armed=True, wait_s=2.0) if armed
                 else home_of((0, 1), 5, group=0, wait_s=2.0))
    assert home.offset(10.0, None, planned(5)) is None and home.offset(11.99, None, planned(5)) is None
    np.testing.assert_array_equal(home.offset(12.0, None, planned(5)), np.zeros(3))
    assert home.source == "anchor"
    home.publish(12_000_000)
    assert len(net.sent) == 1 and not net.sent[0].offset_w_m.any()


def test_the_measuring_group_measures_once_its_middle_link_has_an_estimate():
    home, _ = home_of((2, 3, 4), 5, group=1)
    p, q = resting((2, 3, 4), 5, (0.0, 0.0, -1.0))
    p[0] = np.nan  # the middle link without an estimate in the first step
    assert home.offset(0.05, (p, q), planned(5)) is None
    np.testing.assert_allclose(home.offset(0.1, resting((2, 3, 4), 5, (0.0, 0.0, -1.0)), planned(5)), [0, 0, -1.0],
                               atol=1e-12)
