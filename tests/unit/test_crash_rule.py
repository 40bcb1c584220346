"""The crash rule (sitl/plant/crash.py): in the loop (batch mode) and over a logged flight (fleet
mode, whose harness does not see the targets while it flies)."""

import numpy as np
import pytest

from companion.estimation.so3 import quat_from_euler_zyx, quat_from_rotvec, quat_mul
from sitl.plant.crash import CRASH_TILT_DEG, CrashWatch
from sitl.scenario import load_scenario

CONFIG = "configs/sitl/chain/three_link.toml"
RESTING = "configs/sitl/chain/seven_link_static.toml"  # trajectory.kind = "rest"


@pytest.fixture(scope="module")
def scenario():
    return load_scenario(CONFIG)


def _tilted(deg: float, seed: int):
    """Targets of three links, and attitudes with link 2 ``deg`` off its target about a random
    axis and link 3 half as much about the vertical (its quaternion's sign flipped: the same
    attitude)."""
    rng = np.random.default_rng(seed)
    target = quat_from_euler_zyx(rng.uniform(-3, 3, 3), rng.uniform(-0.5, 0.5, 3), rng.uniform(-0.5, 0.5, 3))
    axis = rng.normal(size=3)
    q = target.copy()
    q[1] = quat_mul(quat_from_rotvec(np.radians(deg) * axis / np.linalg.norm(axis)), target[1])
    q[2] = -quat_mul(quat_from_rotvec(np.radians(0.5 * deg) * np.array([0.0, 0.0, 1.0])), target[2])
    return q, target


@pytest.mark.parametrize("deg, crashed", [(0.0, False), (54.9, False), (56.0, False), (59.5, False), (60.5, True),
                                          (120.0, True), (179.0, True)])
def test_the_crash_rule_at_the_tilt_limit(scenario, deg, crashed):
    """After the take-off a link more than CRASH_TILT_DEG off its target attitude is a crash (a
    link without a target, NaN, is not judged): on both sides of the limit and of the quick test
    that leaves out the rotation vectors far from it."""
    q, target = _tilted(deg, int(deg * 10))
    for without_target in (None, 0):
        q_target = target.copy()
        if without_target is not None:
            q_target[without_target] = np.nan
        watch = CrashWatch(scenario)
        watch.check(scenario.flight_start_s + 1.0, np.tile([0.0, 0.0, 2.0], (3, 1)), q, q_target)
        assert watch.crashed == crashed, (deg, watch.crash_reason)
        if crashed:
            assert watch.crash_reason.startswith(f"attitude error {deg:.0f} deg on link 2"), watch.crash_reason
    assert CRASH_TILT_DEG == 60.0


@pytest.mark.parametrize("heights_m, took_off, crashed", [
    ((0.05,), False, False),  # on the ground throughout (nobody armed it): never took off, no crash
    ((0.05, 2.0, 2.5), True, False),  # took off and flies
    ((0.05, 2.0, 0.05), True, True),  # took off, then hit the ground
])
def test_a_chain_that_never_took_off_has_not_crashed(scenario, heights_m, took_off, crashed):
    watch = CrashWatch(scenario)
    q = np.tile([1.0, 0.0, 0.0, 0.0], (3, 1))
    for k, z in enumerate(heights_m):
        watch.check(scenario.flight_start_s + k, np.tile([0.0, 0.0, z], (3, 1)), q, None)
    assert (watch.took_off, watch.crashed) == (took_off, crashed), watch.crash_reason


def _logged_flight(scenario, tilt_deg_at: dict[int, float], heights_m=None, k_rows: int = 40, n: int = 3):
    """A logged flight of ``n`` links over ``k_rows`` rows of 0.1 s from the start of the
    flight window less 1 s: level at 2 m (``heights_m``: the rows' heights), link 2 tilted
    ``tilt_deg_at[row]`` from its target at the given rows."""
    t = scenario.flight_start_s - 1.0 + 0.1 * np.arange(k_rows)
    z = np.full(k_rows, 2.0) if heights_m is None else np.asarray(heights_m, dtype=float)
    p = np.zeros((k_rows, n, 3))
    p[:, :, 2] = z[:, None]
    q_target = np.tile(quat_from_euler_zyx(np.zeros(n), np.zeros(n), np.zeros(n)), (k_rows, 1, 1))
    q = q_target.copy()
    for row, deg in tilt_deg_at.items():
        q[row, 1] = quat_from_rotvec(np.radians(deg) * np.array([0.0, 1.0, 0.0]))
    return t, p, q, q_target


def test_a_logged_flight_crashes_at_its_first_row_past_the_tilt_limit(scenario):
    t, p, q, q_target = _logged_flight(scenario, {25: 50.0, 28: 75.0, 33: 90.0})
    watch = CrashWatch(scenario)
    watch.check_logged(t, p, q, q_target)
    assert watch.crashed and watch.crash_time_s == pytest.approx(t[28])
    assert watch.crash_reason == f"attitude error 75 deg on link 2 at t = {t[28]:.2f} s"


@pytest.mark.parametrize("case", ["before_the_window", "never_flown", "no_target", "resting"])
def test_a_logged_tilt_is_not_judged_where_the_loop_would_not_judge_it(scenario, case):
    """Before the flight window, before the chain flew, without a target, in a resting scenario:
    no crash, as in the loop."""
    row = 5 if case == "before_the_window" else 25
    heights = np.full(40, 0.1) if case == "never_flown" else None
    sc = load_scenario(RESTING) if case == "resting" else scenario
    t, p, q, q_target = _logged_flight(sc, {row: 90.0}, heights, n=sc.skeleton.n_links)
    if case == "no_target":
        q_target[row, 1] = np.nan
    watch = CrashWatch(sc)
    watch.check_logged(t, p, q, q_target)
    assert not watch.crashed, watch.crash_reason


@pytest.mark.parametrize("floor_row, first", [(20, "floor"), (35, "attitude")])
def test_the_earlier_of_the_loops_crash_and_the_logs_stands(scenario, floor_row, first):
    """A fleet's harness finds a ground crash in the loop; the log's attitude crash replaces it
    only if it came first."""
    t, p, q, q_target = _logged_flight(scenario, {28: 90.0})
    watch = CrashWatch(scenario)
    for k in range(len(t)):
        z = 0.05 if k == floor_row else 2.0
        watch.check(float(t[k]), np.tile([0.0, 0.0, z], (3, 1)), q[k], None)
    assert watch.crashed and watch.crash_reason.startswith("link below")
    watch.check_logged(t, p, q, q_target)
    assert watch.crash_time_s == pytest.approx(t[min(floor_row, 28)])
    assert watch.crash_reason.startswith("link below" if first == "floor" else "attitude error 90 deg on link 2")
