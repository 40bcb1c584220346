"""The Allocator (thesis sec. 2.4) step by step: every call exact and consistent with Props. 1-2,
(2.15) and (2.17); the rotors' limit (scale_to_limit: the wrench scaled, what is kept whole);
selective mapping off; saturation and clipping."""

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from companion.skeleton.rotors import L_SIDE, NU, SIDES
from link_firmware_sim.allocation import AllocationParams, Allocator, infinity_norm_allocation, scaled_to_limit

from ..allocation_cases import (
    B,
    B_PINV,
    B_RED,
    GEOM,
    G,
    MASS_KG,
    TMAX,
    below_margin_per_side,
    check_allocator_step,
    hover_wrench,
    near_zero_wrenches,
    random_wrenches,
    ry,
    rz,
    wrench,
)


# ------------------------------------------------------------------------------------------
# Allocator steps against Props. 1-2, (2.15), (2.17) and the limit
# ------------------------------------------------------------------------------------------


@settings(max_examples=60, deadline=None)
@given(st.lists(wrench, min_size=1, max_size=8))
def test_allocator_exact_and_consistent_hypothesis(Us):
    alloc = Allocator(GEOM)
    for U in Us:
        check_allocator_step(alloc, U)


@settings(max_examples=60, deadline=None)
@given(st.lists(st.tuples(wrench, st.floats(-3.2, 3.2), st.floats(-1.5, 1.5), st.floats(-3.2, 3.2)),
                min_size=1, max_size=8))
def test_allocator_keeping_the_weight_hypothesis(steps):
    """The firmware's call: the link's weight at its attitude kept whole at the limit."""
    alloc = Allocator(GEOM)
    for U, yaw, pitch, roll in steps:
        R = rz(yaw) @ ry(pitch) @ np.array([[1.0, 0, 0], [0, np.cos(roll), -np.sin(roll)], [0, np.sin(roll), np.cos(roll)]])
        keep = hover_wrench(R)
        r = check_allocator_step(alloc, hover_wrench(R) + 4.0 * U, keep)
        hover = np.max(np.abs(infinity_norm_allocation(B_PINV, keep, NU)[2])) <= TMAX  # (not past 50-60 deg of roll)
        if r.scale < 1.0 and hover:  # the weight is carried: B command = keep + s (U - keep)
            np.testing.assert_allclose(B @ r.command_n - keep, r.scale * 4.0 * U, atol=1e-9)


def test_a_far_target_gives_way_above_the_weight():
    """A target 30 m off asks eq. 1 for 300 N sideways (it has no limit of its own): clipped rotor
    by rotor that came out as 43 N sideways and no lift; the whole wrench scaled, 2.4 N of lift
    for 17.7 N of weight. With the weight kept (the firmware's call) the link holds its height and
    pushes sideways with what is left (25.8 N)."""
    weight = hover_wrench(np.eye(3))
    U = weight + np.array([300.0, 0, 0, 0, 0, 0])
    clipped = Allocator(GEOM, AllocationParams(scale_to_limit=False)).allocate(U).command_n
    whole = Allocator(GEOM).allocate(U).command_n
    kept = Allocator(GEOM).allocate(U, weight)
    assert (B @ clipped)[2] < 0.1 and (B @ whole)[2] < 0.2 * weight[2]
    np.testing.assert_allclose(B @ kept.command_n, weight + kept.scale * (U - weight), atol=1e-9)
    assert (B @ kept.command_n)[2] == pytest.approx(weight[2], abs=1e-9) and (B @ kept.command_n)[0] > 25.0
    assert np.max(np.abs(kept.command_n)) == pytest.approx(TMAX, abs=1e-9)
    with pytest.raises(ValueError, match="keep"):
        Allocator(GEOM).allocate(U, [1.0, 2.0])


def test_allocator_exact_and_consistent_on_seeded_sequences():
    alloc = Allocator(GEOM)
    near_zero_seen = set()
    for U in list(random_wrenches(100, seed=31)) + near_zero_wrenches(100, seed=32):
        r = check_allocator_step(alloc, U)
        near_zero_seen.update(r.near_zero)
    # The near-zero path of (2.17) was exercised on both sides.
    assert near_zero_seen & set(range(4)) and near_zero_seen & set(range(4, 8))


# ------------------------------------------------------------------------------------------
# Selective mapping off, the limit, saturation
# ------------------------------------------------------------------------------------------


def test_selective_mapping_off_sends_clipped_lambda_alpha():
    alloc = Allocator(GEOM, AllocationParams(selective_mapping=False, scale_to_limit=False))
    Us = list(random_wrenches(30, seed=61)) + [hover_wrench(ry(np.pi / 4)), np.array([80.0, 0, 0, 0, 0, 0])]
    for U in Us:
        r = alloc.allocate(U)
        _, _, lam_a = infinity_norm_allocation(B_PINV, U, NU)
        np.testing.assert_allclose(r.lambda_alpha, lam_a, atol=1e-12)
        np.testing.assert_array_equal(r.lambda_beta, r.lambda_alpha)
        np.testing.assert_array_equal(r.lambda_gamma, r.lambda_alpha)
        np.testing.assert_array_equal(r.command_n, np.clip(r.lambda_alpha, -TMAX, TMAX))
        assert r.e == (1.0, 1.0) and r.near_zero == (-1, -1)
        assert r.saturated == bool(np.any(np.abs(r.lambda_alpha) > TMAX))
    np.testing.assert_array_equal(alloc.xi_pre, [0.0, 0.0])
    assert r.saturated  # the 80 N wrench


def test_selective_mapping_off_with_the_limit():
    alloc = Allocator(GEOM, AllocationParams(selective_mapping=False))
    for U in list(random_wrenches(30, seed=61)) + [np.array([80.0, 0, 0, 0, 0, 0])]:
        r = alloc.allocate(U)
        V, scale = scaled_to_limit(B_PINV, U, TMAX)
        _, _, lam_a = infinity_norm_allocation(B_PINV, V, NU)
        np.testing.assert_allclose(r.lambda_alpha, lam_a, atol=1e-12)
        np.testing.assert_array_equal(r.lambda_gamma, r.lambda_alpha)
        assert np.max(np.abs(r.lambda_alpha)) <= TMAX + 1e-9
        np.testing.assert_array_equal(r.command_n, np.clip(r.lambda_alpha, -TMAX, TMAX))
        assert r.saturated == (r.scale != 1.0) and r.scale == pytest.approx(scale, abs=1e-12)
    assert r.saturated and r.scale == pytest.approx(TMAX / np.max(np.abs(infinity_norm_allocation(B_PINV, U, NU)[2])))
    np.testing.assert_allclose(B @ r.command_n, r.wrench, atol=1e-9)  # the 80 N wrench, scaled


def test_scaling_to_the_limit_keeps_the_wrench_a_link_carrying_a_neighbour_asks_for():
    """The case that made it (three_link, link 2 unpowered and carried): each neighbour holds its
    own weight plus half of link 2's (8.8 N) at its joint, 0.5 m from its centre (4.41 N m), with
    8 N rotors: 96 % of the limit when level. Tilted 20 deg, with the attitude loop asking 1.5 N m
    more, it is beyond the limit. Clipped rotor by rotor, the wrench produced loses 5 % of its
    pitch torque and gains a side force (5-15 % of the torque from 0 to 30 deg, the link tips
    further); scaled, force and torque give way alike and nothing else is produced."""
    carry = np.r_[0.0, 0.0, MASS_KG * G + 8.83]
    level = np.r_[carry, 0.0, 4.41, 0.0]
    assert np.max(np.abs(infinity_norm_allocation(B_PINV, level, NU)[2])) == pytest.approx(7.71, abs=0.01)
    U = np.r_[ry(np.radians(20.0)).T @ carry, 0.0, 4.41 + 1.5, 0.0]
    clipped = Allocator(GEOM, AllocationParams(scale_to_limit=False)).allocate(U)
    scaled = Allocator(GEOM).allocate(U)
    assert clipped.saturated and scaled.saturated
    produced_clipped, produced_scaled = B @ clipped.command_n, B @ scaled.command_n
    assert produced_clipped[4] < 0.96 * U[4] and abs(produced_clipped[1]) > 0.15  # torque lost, a side force
    assert 0.9 < scaled.scale < 1.0
    np.testing.assert_allclose(produced_scaled, scaled.scale * U, atol=1e-9)
    assert np.max(np.abs(scaled.command_n)) <= TMAX


def test_the_limit_bounds_the_modulation_and_the_fade():
    """(2.15) keeps xi'' where it is while three rotors are clear of eps1 (it is not pulled back to
    the infinity-norm optimum): after a modulation at light load, a heavier feasible wrench (Prop.
    1's norm 7.9 N of 8) puts a rotor past the limit, and the clip distorts the wrench (0.18 N
    (N m) on average, up to 0.46). With scale_to_limit the limit bounds xi'' too, and where (2.17)'s
    fade of the near-zero rotor would shift thrust past it (121 of these 200 cases), the fade's
    weight is raised just enough: the command is the wrench, exactly."""
    thesis = Allocator(GEOM, AllocationParams(scale_to_limit=False))
    bounded = Allocator(GEOM)
    rng = np.random.default_rng(5)
    beta_over, raised, err_thesis, err_bounded = 0, 0, [], []
    for _ in range(200):
        light = near_zero_wrenches(1, int(rng.integers(1 << 30)))[0]
        heavy = light * (7.9 / np.max(np.abs(infinity_norm_allocation(B_PINV, light, NU)[2])))
        for alloc in (thesis, bounded):
            alloc.reset()
            alloc.allocate(light)
        t, r = thesis.allocate(heavy), check_allocator_step(bounded, heavy)
        beta_over += np.max(np.abs(t.lambda_beta)) > TMAX
        raised += r.saturated
        assert np.max(np.abs(r.lambda_beta)) <= TMAX + 1e-9 and r.scale == 1.0
        err_thesis.append(np.max(np.abs(B @ t.command_n - heavy)))
        err_bounded.append(np.max(np.abs(B @ r.command_n - heavy)))
    assert beta_over > 180  # the thesis's modulation alone: past the limit
    assert raised > 100 and np.mean(err_thesis) > 0.1 and max(err_bounded) < 1e-9


def test_where_the_limit_leaves_no_room_for_the_margin():
    """Found by hypothesis: after a modulation to xi'' = -0.435, a wrench beyond the limit (scaled
    by 0.757) leaves the l side's xi'' in [-0.619, 0.619], where two rotors are always within eps1
    of zero. Kept at -0.435 they would be at 0.335 and 0.593 N; the second is taken to 0.776 N
    (xi'' at the limit's end), as far from zero as the limit allows."""
    alloc = Allocator(GEOM)
    for U in ([0.0] * 6, [0.0, 9.0, 0.0, 5.0, 0.0, 0.0], [26.0, 12.0, 1.0, 0.0, 0.0, 0.5]):
        r = check_allocator_step(alloc, np.array(U))
    assert r.scale == pytest.approx(0.7575, abs=1e-4)
    left = np.sort(np.abs(r.lambda_beta[L_SIDE]))
    assert below_margin_per_side(r.lambda_beta)[1] == 2 and left[1] == pytest.approx(0.776, abs=1e-3)
    assert np.max(np.abs(r.lambda_beta[L_SIDE])) == pytest.approx(TMAX, abs=1e-9)


def test_saturation_flag_and_clipping():
    alloc = Allocator(GEOM, AllocationParams(thrust_max_n=5.0, scale_to_limit=False))
    r = alloc.allocate(np.array([60.0, 0.0, 20.0, 0.0, 0.0, 0.0]))
    assert r.saturated
    assert np.max(np.abs(r.lambda_gamma)) > 5.0
    assert np.max(np.abs(r.command_n)) == 5.0
    np.testing.assert_array_equal(r.command_n, np.clip(r.lambda_gamma, -5.0, 5.0))
    np.testing.assert_allclose(B @ r.lambda_gamma, [60.0, 0.0, 20.0, 0.0, 0.0, 0.0], atol=1e-9)
    r = alloc.allocate(hover_wrench(np.eye(3)))
    assert not r.saturated
    np.testing.assert_array_equal(r.command_n, r.lambda_gamma)


# ------------------------------------------------------------------------------------------
# A rotor left out as failed (Allocator.remove_rotor)
# ------------------------------------------------------------------------------------------


def _limit_ratio(W, rotor):
    """How far wrench ``W`` is from the seven rotors' limit (1: on it): the removed rotor's side
    runs the rows of ``B^+_{\\j}`` (no null space left), the other side Prop. 1's spread."""
    side = rotor // 4
    rows = B_RED[rotor][side * 4:side * 4 + 4]
    other = (B_PINV @ W).reshape(2, 4)[1 - side] * NU
    return max(np.abs(rows @ W).max() / TMAX, np.ptp(other) / (2 * TMAX))


@settings(max_examples=80, deadline=None)
@given(st.lists(wrench, min_size=1, max_size=8), st.integers(0, 7), st.booleans(), st.sampled_from([0.0, 0.8, -1.5]))
def test_a_removed_rotor_gets_its_test_thrust_and_the_rest_produce_the_wrench(Us, rotor, selective, test):
    """With a rotor removed, it gets its test thrust only and the other seven produce the rest of
    the wrench exactly, each within the limit, when they can; beyond that, its side's rows of
    ``B^+_{\\j}`` times that rest are clipped rotor by rotor (nothing scaled) and the other side's
    stay within the limit."""
    alloc = Allocator(GEOM, AllocationParams(selective_mapping=selective))
    assert alloc.remove_rotor(rotor, test) and alloc.removed_rotor == rotor and alloc.test_thrust_n == test
    side = SIDES[rotor // 4]
    for U in Us:
        r = alloc.allocate(U, hover_wrench(np.eye(3)))
        rest = U - B[:, rotor] * test
        assert r.command_n[rotor] == test and r.scale == 1.0
        np.testing.assert_allclose(r.wrench, rest, atol=1e-12)
        if _limit_ratio(rest, rotor) <= 1.0:
            assert not r.saturated and np.abs(r.command_n).max() <= TMAX + 1e-9
            np.testing.assert_allclose(B @ r.command_n, U, atol=1e-9)
        else:
            others = [i for i in range(side.start, side.stop) if i != rotor]
            np.testing.assert_allclose(r.command_n[others], np.clip(B_RED[rotor][others] @ rest, -TMAX, TMAX),
                                       atol=1e-9)


def test_one_rotor_at_most_is_removed_and_all_come_back():
    alloc = Allocator(GEOM)
    assert alloc.removed_rotor is None
    assert alloc.remove_rotor(3) and alloc.remove_rotor(3)  # (again: the same, accepted)
    assert not alloc.remove_rotor(6) and alloc.removed_rotor == 3
    alloc.reset()  # (the modulation's state only)
    assert alloc.removed_rotor == 3
    alloc.restore_rotors()
    assert alloc.removed_rotor is None and alloc.allocate(hover_wrench(np.eye(3))).command_n[3] != 0.0
    with pytest.raises(ValueError):
        alloc.remove_rotor(8)
    with pytest.raises(ValueError):
        alloc.remove_rotor(2, test_thrust_n=TMAX + 1.0)
