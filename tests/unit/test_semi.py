from dataclasses import replace

import numpy as np
import pytest

from companion.estimation.chain import CON_POS, CON_VEL, ERR_PV
from companion.estimation.constraints import constraint_residual, left_tip, right_tip
from companion.corrections import compute_corrections
from companion.estimation.neighbour import NeighbourMeasurement, NeighbourView, marker_in_camera, neighbour_updates
from companion.estimation.sckf import CAParams, constraint_apply
from companion.estimation.semi import (
    GroupBoundary,
    format_groups,
    global_solution,
    global_step,
    group_boundary,
    make_groups,
    parse_groups,
    semi_distributed_apply,
    validate_groups,
)

from companion.estimation.so3 import attitude_error, retract
from companion.messages import LinkState

from ..chains import consistent_chain, perturbed_chain, random_covariances

LAYOUTS = {
    "paper-7": ("1,2/3,4,5/6,7", 7),
    "pairs-6": ("1,2/3,4/5,6", 6),
    "singletons-4": ("1/2/3/4", 4),
    "uneven-9": ("1/2,3,4,5/6,7/8,9", 9),
    "one-group-5": ("1,2,3,4,5", 5),
}


def _brute_force_shifts(p, v, q, w, d, P, groups):
    """Eq. 6 solved as a KKT system over per-link shifts tied within groups."""
    n = p.shape[0]
    info = np.linalg.inv(P[:, ERR_PV, ERR_PV])
    H = np.zeros((6 * n, 6 * n))
    for i in range(n):
        H[6 * i : 6 * i + 6, 6 * i : 6 * i + 6] = 2.0 * info[i]
    rows, rhs = [], []
    rt, lt = right_tip(p, v, q, w, d), left_tip(p, v, q, w, d)
    group_of = {i: k for k, g in enumerate(groups) for i in g}
    for i in range(n - 1):
        A = np.zeros((6, 6 * n))
        A[:, 6 * i : 6 * i + 6] = np.eye(6)
        A[:, 6 * i + 6 : 6 * i + 12] = -np.eye(6)
        rows.append(A)
        # Same group: equal shifts. Across groups: the shifted tips coincide.
        rhs.append(np.zeros(6) if group_of[i] == group_of[i + 1] else -(rt[i] - lt[i + 1]))
    A = np.vstack(rows)
    kkt = np.block([[H, A.T], [A, np.zeros((A.shape[0], A.shape[0]))]])
    sol = np.linalg.solve(kkt, np.concatenate((np.zeros(6 * n), np.concatenate(rhs))))
    per_link = sol[: 6 * n].reshape(n, 6)
    return np.array([per_link[g[0]] for g in groups])


@pytest.mark.parametrize("layout", LAYOUTS.values(), ids=LAYOUTS.keys())
@pytest.mark.parametrize("seed", range(3))
def test_global_step_closes_group_joints_and_equals_kkt(layout, seed):
    spec, n = layout
    groups = parse_groups(spec, n)
    p, v, q, w, d, P = perturbed_chain(np.random.default_rng(seed), n)
    boundaries = [
        group_boundary(p[g[0] : g[-1] + 1], v[g[0] : g[-1] + 1], q[g[0] : g[-1] + 1], w[g[0] : g[-1] + 1],
                       d[g[0] : g[-1] + 1], P[g[0] : g[-1] + 1])
        for g in groups
    ]
    shifts = global_step(boundaries)
    np.testing.assert_allclose(shifts, _brute_force_shifts(p, v, q, w, d, P, groups), atol=1e-9)
    # Apply and check every inter-group joint closes to 1e-9.
    p2, v2 = p.copy(), v.copy()
    for k, g in enumerate(groups):
        p2[list(g)] += shifts[k, CON_POS]
        v2[list(g)] += shifts[k, CON_VEL]
    c = constraint_residual(p2, v2, q, w, d).reshape(n - 1, 6)
    for k in range(len(groups) - 1):
        joint = groups[k][-1]
        np.testing.assert_allclose(c[joint], 0.0, atol=1e-9)


@pytest.mark.parametrize("layout", LAYOUTS.values(), ids=LAYOUTS.keys())
def test_semi_distributed_satisfies_all_joints(layout):
    spec, n = layout
    groups = parse_groups(spec, n)
    p, v, q, w, d, P = perturbed_chain(np.random.default_rng(21), n)
    params = CAParams(eps=0.01)
    res = semi_distributed_apply(p, v, q, w, d, P, groups, params)
    c = constraint_residual(res.p, res.v, res.q, w, d).reshape(n - 1, 6)
    for k, g in enumerate(groups):
        inner = c[g[0] : g[-1]]
        assert np.linalg.norm(inner) <= params.eps + 1e-12  # local CA (Alg. 2); shifts keep it
        if k < len(groups) - 1:
            np.testing.assert_allclose(c[g[-1]], 0.0, atol=1e-9)  # global step (eq. 6)
    assert res.shifts.shape == (len(groups), 6)
    np.testing.assert_allclose(np.linalg.norm(res.q, axis=1), 1.0, atol=1e-12)


def test_single_group_is_alg1():
    p, v, q, w, d, P = perturbed_chain(np.random.default_rng(22), 6)
    semi = semi_distributed_apply(p, v, q, w, d, P, make_groups(6, 6))
    full = constraint_apply(p, v, q, w, d, P)
    np.testing.assert_array_equal(semi.shifts, np.zeros((1, 6)))
    assert semi.boundaries == ()  # no joint between groups: eq. 6 is not solved
    np.testing.assert_allclose(semi.p, full.p, atol=1e-15)
    np.testing.assert_allclose(semi.q, full.q, atol=1e-15)
    np.testing.assert_allclose(semi.P, full.P, atol=1e-15)


def test_translation_does_not_change_semi_corrections():
    p, v, q, w, d, P = perturbed_chain(np.random.default_rng(23), 7)
    groups = parse_groups("1,2/3,4,5/6,7", 7)
    shift = np.array([-300.0, 12.0, 55.0])
    a = semi_distributed_apply(p, v, q, w, d, P, groups)
    b = semi_distributed_apply(p + shift, v, q, w, d, P, groups)
    np.testing.assert_allclose(b.p - (p + shift), a.p - p, atol=1e-9)
    np.testing.assert_allclose(b.v, a.v, atol=1e-10)
    np.testing.assert_allclose(b.q, a.q, atol=1e-12)
    np.testing.assert_allclose(b.shifts, a.shifts, atol=1e-9)


def test_global_step_only_needs_boundaries():
    """Eq. 6 depends on the groups only through end tips and summed information."""
    rng = np.random.default_rng(24)
    bounds = [
        GroupBoundary(rng.normal(size=6), rng.normal(size=6), np.eye(6) * (k + 1.0) + 0.1 * np.ones((6, 6)))
        for k in range(4)
    ]
    shifts = global_step(bounds)
    for k in range(3):
        closed = (bounds[k].right_tip + shifts[k]) - (bounds[k + 1].left_tip + shifts[k + 1])
        np.testing.assert_allclose(closed, 0.0, atol=1e-12)
    # Stationarity: the information-weighted shifts sum to zero (Lagrangian of eq. 6).
    np.testing.assert_allclose(sum(b.info_pv @ s for b, s in zip(bounds, shifts)), 0.0, atol=1e-10)


def test_make_groups_and_format():
    assert make_groups(7, 3) == ((0, 1, 2), (3, 4, 5), (6,))
    assert format_groups(parse_groups("1,2/3,4,5/6,7", 7)) == "1,2/3,4,5/6,7"


@pytest.mark.parametrize(
    "spec, n, match",
    [
        ("1,2/4,5", 5, "group 2"),
        ("1,2/3", 5, "chain has 5 links"),
        ("2,1/3", 3, "group 1"),
        ("0,1/2", 3, "1-based"),
        ("1,a/3", 3, "cannot read group 1"),
        ("1,2//3", 3, "group 2 is empty"),
    ],
)
def test_bad_group_layouts_are_rejected(spec, n, match):
    with pytest.raises(ValueError, match=match):
        parse_groups(spec, n)


def test_validate_groups_rejects_empty():
    with pytest.raises(ValueError, match="at least one group"):
        validate_groups([], 3)


@pytest.mark.parametrize("spec, n", [("1,2/3,4/5,6/7,8", 8), ("1,2,3/4,5,6/7,8/9", 9), ("1/2/3", 3)])
def test_batched_local_step_equals_one_call_per_group(spec, n):
    from companion.estimation.semi import local_constraint_apply

    groups = parse_groups(spec, n)
    p, v, q, w, d, P = perturbed_chain(np.random.default_rng(31), n)
    params = CAParams(eps=1e-4)
    batched = local_constraint_apply(p, v, q, w, d, P, groups, params, "auto")
    for g, res in zip(groups, batched):
        sl = slice(g[0], g[-1] + 1)
        ref = constraint_apply(p[sl], v[sl], q[sl], w[sl], d[sl], P[sl], params, "structured")
        assert res.iterations == ref.iterations
        np.testing.assert_allclose(res.residual_history, ref.residual_history, rtol=1e-9, atol=1e-13)
        np.testing.assert_allclose(res.p, ref.p, atol=1e-11)
        np.testing.assert_allclose(res.q, ref.q, atol=1e-11)
        np.testing.assert_allclose(res.P, ref.P, atol=1e-9)


# -- the global step's covariance ----------------------------------------------------------------------------
@pytest.mark.parametrize("layout", [LAYOUTS["paper-7"], LAYOUTS["uneven-9"]], ids=["paper-7", "uneven-9"])
def test_global_solution_gains_are_the_shifts_derivative(layout):
    """Gamma_g is d(shift of g)/d(tips of g): finite differences on every tip coordinate; and
    V_g is the covariance of the shifts under the reported tip covariances (linear propagation
    written out with the full Jacobian, by finite differences)."""
    spec, n = layout
    groups = parse_groups(spec, n)
    res = semi_distributed_apply(*perturbed_chain(np.random.default_rng(4), n), groups)
    bounds = list(res.boundaries)
    sol = global_solution(bounds)
    np.testing.assert_array_equal(sol.shifts, global_step(bounds))
    s, h = len(bounds), 1e-6
    G = np.zeros((s, 6, s, 12))
    for k in range(s):
        for j in range(12):
            plus, minus = list(bounds), list(bounds)
            for sign, lst in ((1.0, plus), (-1.0, minus)):
                tips = np.concatenate([bounds[k].left_tip, bounds[k].right_tip])
                tips[j] += sign * h
                lst[k] = replace(bounds[k], left_tip=tips[:6], right_tip=tips[6:])
            G[:, :, k, j] = (global_step(plus) - global_step(minus)) / (2 * h)
    for g in range(s):
        np.testing.assert_allclose(sol.gains[g], G[g, :, g, :], atol=1e-7)
        V = sum(G[g, :, k, :] @ bounds[k].tip_cov @ G[g, :, k, :].T for k in range(s))
        np.testing.assert_allclose(sol.shift_cov[g], V, atol=1e-9)


def test_global_solution_without_tip_covariances_shifts_the_mean_only():
    groups = parse_groups("1,2/3,4", 4)
    res = semi_distributed_apply(*perturbed_chain(np.random.default_rng(5), 4), groups)
    bounds = [replace(b, tip_cov=None) for b in res.boundaries]
    sol = global_solution(bounds)
    assert sol.gains is None and sol.shift_cov is None
    np.testing.assert_array_equal(sol.shifts, global_step(bounds))


def _monte_carlo_nees(groups, n: int, samples: int, seed: int):
    """Average NEES per link and block of the semi-distributed estimate against a true chain,
    with EKF errors drawn from the reported covariances: with the covariance carried through the
    global step (``SemiResult.P``) and with the local step's alone."""
    rng = np.random.default_rng(seed)
    p0, v0, q0, w, d = consistent_chain(rng, n)
    P = random_covariances(rng, n, scale=0.1)
    L = np.linalg.cholesky(P)
    nees = np.zeros((2, n, 3))
    for _ in range(samples):
        e = (L @ rng.normal(size=(n, 9, 1)))[..., 0]
        res = semi_distributed_apply(p0 + e[:, :3], v0 + e[:, 3:6], retract(q0, e[:, 6:]), w, d, P, groups)
        err = np.concatenate([res.p - p0, res.v - v0, attitude_error(res.q, q0)], axis=1)
        for k, cov in enumerate((res.P, np.concatenate([r.P for r in res.local]))):
            for b, sl in enumerate((slice(0, 3), slice(3, 6), slice(6, 9))):
                x = err[:, sl]
                nees[k, :, b] += np.einsum("ni,ni->n", x, np.linalg.solve(cov[:, sl, sl], x[..., None])[..., 0])
    return nees / samples


def test_semi_distributed_covariance_is_consistent_after_the_global_step():
    """Monte Carlo (seeded): the reported covariance of the semi-distributed estimate matches its
    error as well as Alg. 1's own on the whole chain does (NEES near 3 per block; the weakening
    makes Alg. 1 a little conservative), while the local step's covariance, which eq. 6 alone
    leaves unchanged, overstates the position and velocity error (NEES 1.7-2.4 on the inner
    links here; 0.9-1.6 in a 7-link flight)."""
    groups = parse_groups("1,2/3,4,5/6,7", 7)
    carried, local = _monte_carlo_nees(groups, 7, samples=300, seed=8)
    whole, _ = _monte_carlo_nees(parse_groups("1,2,3,4,5,6,7", 7), 7, samples=300, seed=8)
    # 300 samples of a 3-dof NEES: the mean's 95 % band is about 3 +- 0.28
    assert np.all((carried > 2.4) & (carried < 3.4)), carried
    assert abs(carried.mean() - whole.mean()) < 0.15, (carried.mean(), whole.mean())
    assert local[:, :2].mean() < 2.4 and np.all(local[1:-1, :2] < 2.5), local  # the old, conservative report
    np.testing.assert_allclose(local[:, 2], carried[:, 2])  # attitude: eq. 6 does not move it


def test_neighbour_measurements_go_into_their_groups_before_the_constraint():
    """A camera measurement inside a group is applied to that group before its constraint
    application (the same as the update and a dense CA on the whole covariance it leaves), one
    between two groups is left out and said so (NaN, not accepted), and with none the step is
    the plain one."""
    rng = np.random.default_rng(31)
    p, v, q, w, d, P = perturbed_chain(rng, 6)
    groups = parse_groups("1,2,3/4,5,6", 6)
    view = NeighbourView(np.array([0.45, 0.0, 0.05]), np.eye(3), np.array([0.0, 0.0, 0.08]), np.eye(3))
    R_cm, t_cm = marker_in_camera(p[1], q[1], p[2], q[2], view)
    inside = NeighbourMeasurement(1, 2, R_cm, t_cm + [0.05, 0.0, -0.03], np.eye(6) * 1e-3, view)
    across = NeighbourMeasurement(2, 3, R_cm, t_cm, np.eye(6) * 1e-3, view)
    res = semi_distributed_apply(p, v, q, w, d, P, groups, neighbours=[inside, across])
    assert res.neighbour_accepted.tolist() == [True, False] and np.isfinite(res.neighbour_nis[0])
    assert np.isnan(res.neighbour_nis[1])
    up = neighbour_updates(p[:3], v[:3], q[:3], P[:3], [inside])
    first = constraint_apply(up.p, up.v, up.q, w[:3], d[:3], up.P, method="dense")
    np.testing.assert_allclose(res.local[0].p, first.p, atol=1e-12)
    np.testing.assert_allclose(res.local[1].p, semi_distributed_apply(p, v, q, w, d, P, groups).local[1].p, atol=1e-15)
    plain = semi_distributed_apply(p, v, q, w, d, P, groups)
    assert plain.neighbour_nis.shape == (0,)
    assert not np.allclose(res.p[:3], plain.p[:3], atol=1e-6)


def test_the_companion_step_carries_the_neighbour_measurements_into_its_corrections():
    rng = np.random.default_rng(32)
    p, v, q, w, d, P = perturbed_chain(rng, 4)
    states = [LinkState(i, 1.0, p[i], v[i], q[i], w[i], P[i]) for i in range(4)]
    view = NeighbourView(np.array([0.45, 0.0, 0.05]), np.eye(3), np.array([0.0, 0.0, 0.08]), np.eye(3))
    R_cm, t_cm = marker_in_camera(p[0], q[0], p[1], q[1], view)
    m = NeighbourMeasurement(0, 1, R_cm, t_cm + [0.04, 0.02, 0.0], np.eye(6) * 1e-3, view)
    groups = make_groups(4, 4)
    result, corrections = compute_corrections(states, d, groups, neighbours=[m])
    want = semi_distributed_apply(p, v, q, w, d, P, groups, neighbours=[m])
    assert result.neighbour_accepted.tolist() == [True]
    np.testing.assert_allclose([c.dp_w_m for c in corrections], want.p - p, atol=1e-12)
