"""Oracle tests: the companion's compiled kernels (:mod:`companion.kernels`) against their numpy
specifications on random inputs (seeded), and the warm-up against the signatures their callers use.

Without numba (an onboard install) the compiled path is the numpy one and these tests are skipped.
"""

from __future__ import annotations

import numpy as np
import pytest

from companion.estimation.so3 import quat_from_rotvec, quat_normalize, quat_to_rotmat
from companion.kernels.jit import ENABLED

pytestmark = pytest.mark.skipif(not ENABLED, reason="numba not installed (or SKELETON_JIT=0)")

N_CASES = 40
CPG_MODEL = "companion/motion/models/inverse_cpg_7link.npz"


def test_cross_is_numpys():
    """so3.cross: np.cross's numbers (exactly) for single vectors, stacks and broadcasts."""
    from companion.estimation.so3 import cross

    rng = np.random.default_rng(29)
    for a_shape, b_shape in (((3,), (3,)), ((5, 3), (5, 3)), ((4, 3), (3,)), ((2, 1, 3), (1, 6, 3))):
        a, b = rng.normal(size=a_shape), rng.normal(size=b_shape)
        np.testing.assert_array_equal(cross(a, b), np.cross(a, b))


def test_trajectory_poses_batch_is_pose():
    """ChainTrajectory.poses (the five instants of a target in one evaluation) equals pose() per time."""
    from companion.trajectory import ChainTrajectory, TrajectoryConfig

    traj = ChainTrajectory(TrajectoryConfig(kind="bend", bend_start_s=1.0, bend_ramp_s=1.0), 4, 1.0, [0.0, 0.0, 0.3])
    times = [0.5, 1.2, 2.0, 3.7, 9.1]
    p, q, R = traj.poses(times)
    for i, t in enumerate(times):
        pi, qi = traj.pose(t)
        np.testing.assert_array_equal(p[i], pi)
        np.testing.assert_array_equal(q[i], qi)
    np.testing.assert_array_equal(R, quat_to_rotmat(q))


@pytest.mark.parametrize("n_links", [1, 2, 3, 4, 7])
@pytest.mark.parametrize("kind", ["bend", "figure8", "hover", "rest"])
def test_trajectory_kernel_matches_numpy(n_links, kind):
    """ChainTrajectory.target_arrays by the kernel equals its numpy specification: poses, attitudes
    and velocity to 1e-12, the body rate to 1e-12; the acceleration and the body rate's derivative
    to 1e-8 and 1e-9: second and nested central differences over h = 1 ms carry the rounding of
    the poses (an ulp of a position of metres, 1e-15, where the two sides' sine and cosine may
    round apart) and of R (1e-16 between the two forms of R(q)) as rounding / h^2; random headings,
    pitches, link lengths, start points and times before, during and after the take-off and the
    bend's ramp, ``targets`` on the kernel."""
    from companion.trajectory import ChainTrajectory, TrajectoryConfig

    rng = np.random.default_rng(n_links * 10 + len(kind))
    for _ in range(10):
        cfg = TrajectoryConfig(kind=kind, takeoff_start_s=rng.uniform(0, 2), takeoff_duration_s=rng.uniform(1, 6),
                               takeoff_altitude_m=rng.uniform(1, 4), yaw_deg=rng.uniform(-180, 180),
                               pitch_deg=rng.uniform(-30, 30), bend_start_s=rng.uniform(2, 8),
                               bend_amplitude_deg=rng.uniform(5, 40), bend_period_s=rng.uniform(4, 12),
                               bend_ramp_s=rng.uniform(0, 6), figure8_start_s=rng.uniform(2, 8))
        traj = ChainTrajectory(cfg, n_links, rng.uniform(0.3, 2.0), rng.normal(size=3))
        for t in rng.uniform(0, 30, size=8):
            got, want = traj.target_arrays(t, compiled=True), traj.target_arrays(t, compiled=False)
            for name, g, w, atol in zip(("p", "q", "R", "v", "a", "w", "w_dot"), got, want,
                                                [1e-12] * 4 + [1e-8, 1e-12, 1e-9]):
                assert g.shape == w.shape, name
                np.testing.assert_allclose(g, w, rtol=0, atol=atol, err_msg=name)
            targets = traj.targets(t)
            np.testing.assert_array_equal(np.array([x.omega_dot_d_rad_s2 for x in targets]), got[6])


@pytest.mark.parametrize("n_links", [1, 2, 3, 5, 7])
def test_feedforward_kernel_matches_numpy(n_links):
    """companion.kernels.dynamics.passive_torques_kernel and feedforward_kernel (the chain's inverse
    dynamics) against ChainModel.solve's numpy specification: random motions, every link flying and
    with an end or a middle link passive, to 1e-12 of the largest wrench."""
    pytest.importorskip("pinocchio")
    from companion.skeleton.body import SkeletonConfig
    from companion.skeleton.dynamics import ChainModel

    model = ChainModel(SkeletonConfig(n_links=n_links))
    rng = np.random.default_rng(31 + n_links)
    for _ in range(N_CASES // 2):
        q = quat_normalize(rng.normal(size=(n_links, 4)))
        motion = (rng.normal(size=(n_links, 3)) * 3, quat_to_rotmat(q), rng.normal(size=(n_links, 3)),
                  rng.normal(size=(n_links, 3)), rng.normal(size=(n_links, 3)) * 5, rng.normal(size=(n_links, 3)) * 5)
        for passive in {(), (0,), (n_links // 2,), (n_links - 1,)}:
            spec = model.solve(*motion, passive=passive, compiled=False)
            fast = model.solve(*motion, passive=passive, compiled=True)
            scale = max(1.0, float(np.abs(spec.rotor_wrench_w).max()))
            for name in ("force_ff_w_n", "torque_ff_w_nm", "joint_force_w_n", "joint_torque_w_nm", "rotor_wrench_w"):
                np.testing.assert_allclose(getattr(fast, name), getattr(spec, name), rtol=0, atol=1e-12 * scale,
                                           err_msg=f"{name}, passive {passive}")


@pytest.mark.parametrize("max_angle", [1e-9, 1e-4, 0.5, 3.1])
def test_rotmat_log_matches_pinocchio(max_angle):
    """companion.kernels.so3.rotmat_log against pin.log3 (the passive joint torques' log), at every
    Shepperd pivot: tiny angles, small, large and near pi, about random axes, to 1e-12 rad."""
    pin = pytest.importorskip("pinocchio")
    from companion.kernels.so3 import rotmat_log

    rng = np.random.default_rng(8)
    pivots = set()
    for _ in range(N_CASES):
        axis = rng.normal(size=3)
        rv = axis / np.linalg.norm(axis) * rng.uniform(0.0, max_angle)
        R = quat_to_rotmat(quat_from_rotvec(rv))
        np.testing.assert_allclose(rotmat_log(R), pin.log3(R), rtol=0, atol=1e-12)
        np.testing.assert_allclose(rotmat_log(R), rv, rtol=0, atol=1e-12)
        pivots.add(int(np.argmax([np.trace(R), R[0, 0], R[1, 1], R[2, 2]])))
    assert pivots == ({0} if max_angle < 2.0 else {0, 1, 2, 3})


def _ekf_like_covariances(rng, n: int) -> np.ndarray:
    """(n, 9, 9) random correlated covariances with an EKF's scales (position 0.1 m, velocity
    0.05 m/s, attitude 0.02 rad)."""
    sd = np.array([0.1] * 3 + [0.05] * 3 + [0.02] * 3)
    A = rng.normal(size=(n, 9, 9))
    corr = A @ np.swapaxes(A, 1, 2) + 9.0 * np.eye(9)
    inv_sd = 1.0 / np.sqrt(np.einsum("nii->ni", corr))
    return corr * inv_sd[:, :, None] * inv_sd[:, None, :] * sd[:, None] * sd[None, :]


@pytest.mark.parametrize("n_links", [1, 2, 3, 4, 7])
@pytest.mark.parametrize("omega_std", [0.0, 0.02])
def test_constraint_apply_kernel_matches_numpy(n_links, omega_std):
    """companion.kernels.sckf.constraint_apply_kernel (Alg. 1 on one chain, with the body-rate noise gain) and
    covariance_terms
    against constraint_apply_dense's numpy specification on random chains: the same iteration
    count and every output to 1e-12 of its largest entry."""
    from companion.estimation.sckf import CAParams, constraint_apply_dense
    from companion.estimation.semi import BATCH_DENSE_MAX_LINKS, local_constraint_apply

    rng = np.random.default_rng(37 + n_links)
    params = CAParams(omega_std_rad_s=omega_std)
    iterations = []
    for _ in range(N_CASES // 2):
        spread = rng.choice([0.001, 0.05, 0.3])  # consistent to far off: one to many iterations
        p = np.cumsum(np.tile([1.0, 0.0, 0.0], (n_links, 1)), axis=0) + rng.normal(size=(n_links, 3)) * spread
        v = rng.normal(size=(n_links, 3)) * 0.3
        q = quat_normalize(np.array([1.0, 0.0, 0.0, 0.0]) + rng.normal(size=(n_links, 4)) * spread)
        w = rng.normal(size=(n_links, 3)) * 0.2
        d = np.tile([0.5, 0.0, 0.0], (n_links, 1))
        P = _ekf_like_covariances(rng, n_links)
        spec = constraint_apply_dense(p, v, q, w, d, P, params, compiled=False)
        fast = constraint_apply_dense(p, v, q, w, d, P, params, compiled=True)
        assert fast.iterations == spec.iterations and fast.converged == spec.converged
        iterations.append(spec.iterations)
        for name in ("p", "v", "q", "P", "P_full", "P_ends", "W_ends", "residual_history"):
            a, b = getattr(fast, name), getattr(spec, name)
            if b is None:
                assert a is None, name
                continue
            scale = max(float(np.abs(b).max()), 1e-300) if b.size else 1.0
            np.testing.assert_allclose(a, b, rtol=0, atol=1e-12 * scale, err_msg=name)
        if n_links <= BATCH_DENSE_MAX_LINKS:  # the semi-distributed step's batched groups take the same path
            (batched,) = local_constraint_apply(p, v, q, w, d, P, [list(range(n_links))], params)
            np.testing.assert_array_equal(batched.P_full, fast.P_full)
    if n_links > 1:
        assert max(iterations) > 1  # the loop itself is exercised, not only the first iteration


def _random_chain(rng, n_links: int, spread: float):
    """A chain of ``n_links`` 1 m links along x, off its joints by about ``spread``: p, v, q, w, d, P."""
    p = np.cumsum(np.tile([1.0, 0.0, 0.0], (n_links, 1)), axis=0) + rng.normal(size=(n_links, 3)) * spread
    v = rng.normal(size=(n_links, 3)) * 0.3
    q = quat_normalize(np.array([1.0, 0.0, 0.0, 0.0]) + rng.normal(size=(n_links, 4)) * spread)
    w = rng.normal(size=(n_links, 3)) * 0.2
    d = np.tile([0.5, 0.0, 0.0], (n_links, 1)) + rng.normal(size=(n_links, 3)) * 0.01
    return p, v, q, w, d, _ekf_like_covariances(rng, n_links)


@pytest.mark.parametrize("n_links", [1, 2, 3, 4, 7])
def test_joint_nis_kernel_matches_numpy(n_links):
    """companion.kernels.gate.joint_nis_kernel against joint_nis's numpy specification on random chains,
    from consistent to far off (NIS from about 1 to thousands): to 1e-12 of each value; a NaN
    state gives NaN at its joints both ways, so the gate cuts them."""
    from companion.estimation.gate import CHI2_6_1E6, GateParams, joint_nis

    rng = np.random.default_rng(71 + n_links)
    values = []
    for k in range(N_CASES):
        params = GateParams(gate_pos_m=rng.choice([0.01, 0.05]), gate_vel_m_s=rng.choice([0.1, 0.25]))
        p, v, q, w, d, P = _random_chain(rng, n_links, rng.choice([0.001, 0.05, 0.3, 1.0]))
        spec = joint_nis(p, v, q, w, d, P, params, compiled=False)
        fast = joint_nis(p, v, q, w, d, P, params, compiled=True)
        assert fast.shape == spec.shape == (n_links - 1,)
        np.testing.assert_allclose(fast, spec, rtol=1e-12, atol=0)
        values.extend(spec)
    if n_links > 1:
        assert min(values) < CHI2_6_1E6 < 10 * CHI2_6_1E6 < max(values)  # the inputs reach both sides of the gate
        p[n_links // 2, 1] = np.nan
        spec = joint_nis(p, v, q, w, d, P, compiled=False)
        fast = joint_nis(p, v, q, w, d, P, compiled=True)
        np.testing.assert_array_equal(np.isnan(fast), np.isnan(spec))
        assert np.isnan(spec).any()


@pytest.mark.parametrize("n_links", [1, 2, 3, 5])
@pytest.mark.parametrize("omega_std", [0.0, 0.02])
def test_local_boundary_kernel_matches_numpy(n_links, omega_std):
    """companion.kernels.semi.group_terms_kernel against local_boundary's specification (group_tip_terms
    and group_boundary) after a local step on random groups, with and without the body-rate
    noise (its end columns): tips, information, tip covariance and Cov(tau, x~_i) to 1e-12 of
    their largest entry."""
    from companion.estimation.sckf import CAParams, constraint_apply
    from companion.estimation.semi import local_boundary

    rng = np.random.default_rng(83 + n_links)
    params = CAParams(omega_std_rad_s=omega_std)
    with_rate_columns = 0
    for _ in range(N_CASES // 2):
        p, v, q, w, d, P = _random_chain(rng, n_links, rng.choice([0.001, 0.05, 0.3]))
        local = constraint_apply(p, v, q, w, d, P, params)
        with_rate_columns += local.W_ends is not None
        spec_b, spec_y = local_boundary(local.p, local.v, local.q, w, d, local, compiled=False)
        fast_b, fast_y = local_boundary(local.p, local.v, local.q, w, d, local, compiled=True)
        names = ("left_tip", "right_tip", "info_pv", "tip_cov")
        pairs = [(name, getattr(fast_b, name), getattr(spec_b, name)) for name in names]
        for name, a, b in pairs + [("Y", fast_y, spec_y)]:
            assert a.shape == b.shape, name
            np.testing.assert_allclose(a, b, rtol=0, atol=1e-12 * float(np.abs(b).max()), err_msg=name)
        assert np.array_equal(fast_b.info_pv, fast_b.info_pv.T) and np.array_equal(fast_b.tip_cov, fast_b.tip_cov.T)
    assert (with_rate_columns > 0) == (omega_std > 0 and n_links > 1)


@pytest.mark.parametrize("n_links", [1, 2, 3, 7])
def test_align_kernel_matches_numpy(n_links):
    """companion.kernels.align.align_kernel against align_states' numpy specification: link states
    stamped up to 50 ms apart, body rates up to 8 rad/s and the tiny angles of the Taylor branch,
    aligned to the newest stamp or a given time: to 1e-15; equal stamps move nothing, bit for bit."""
    from companion.corrections import align_states
    from companion.messages import LinkState

    rng = np.random.default_rng(91 + n_links)
    for k in range(N_CASES):
        rate = rng.choice([1e-10, 0.2, 8.0])
        states = [LinkState(i, 10.0 + rng.uniform(-0.05, 0.0) * (k % 3 != 0), rng.normal(size=3), rng.normal(size=3),
                            quat_normalize(rng.normal(size=4)), rng.normal(size=3) * rate, np.eye(9))
                  for i in range(n_links)]
        t = None if k % 2 else 10.0 + rng.uniform(0.0, 0.02)
        spec = align_states(states, t, compiled=False)
        fast = align_states(states, t, compiled=True)
        assert spec[0] == fast[0]
        for a, b in zip(fast[1:], spec[1:]):
            assert a.shape == b.shape
            np.testing.assert_allclose(a, b, rtol=0, atol=1e-15 * max(1.0, float(np.abs(b).max())))
        if k % 3 == 0 and t is None:  # (every stamp 10.0: nothing to propagate)
            for a, b in zip(fast[1:], spec[1:]):
                np.testing.assert_array_equal(a, b)


def test_attitude_errors_kernel_matches_numpy():
    """companion.kernels.align.attitude_errors_kernel against so3.attitude_error of stacked
    quaternions, from equal attitudes to half turns and a sign-flipped twin: to 1e-14 rad."""
    from companion.estimation.so3 import attitude_error, quat_from_rotvec, quat_mul
    from companion.kernels.align import attitude_errors_kernel

    rng = np.random.default_rng(97)
    q_from = quat_normalize(rng.normal(size=(200, 4)))
    turn = rng.normal(size=(200, 3)) * rng.choice([0.0, 1e-9, 1e-3, 0.5, 3.1], size=(200, 1))
    q_to = quat_mul(quat_from_rotvec(turn), q_from)
    q_to[::7] *= -1.0  # (the same attitude)
    out = np.empty((200, 3))
    attitude_errors_kernel(q_to, q_from, out)
    np.testing.assert_allclose(out, attitude_error(q_to, q_from), rtol=0, atol=1e-14)
    inside = np.linalg.norm(turn, axis=1) < 3.0  # (the turn itself, where it is not wrapped past pi)
    inside[::7] = False
    np.testing.assert_allclose(out[inside], turn[inside], rtol=0, atol=1e-9)


def test_kernel_arrays_pass_through_or_copy_to_one_layout():
    """companion.kernels.jit.as_kernel_array: a C-contiguous writeable float64 array of the shape is
    passed as is; anything else (read-only, transposed, broadcast, integer) becomes one, so every
    kernel sees one array type (numba compiles again for a read-only array)."""
    from companion.kernels.jit import as_kernel_array

    x = np.zeros((2, 3))
    assert as_kernel_array(x, (2, 3)) is x
    ro = np.arange(6.0).reshape(2, 3)
    ro.setflags(write=False)
    for given, shape in ((ro, (2, 3)), (np.arange(6.0).reshape(3, 2).T, (2, 3)), ([0.5, 0, 0], (4, 3)),
                         (np.arange(6).reshape(2, 3), (2, 3))):
        out = as_kernel_array(given, shape)
        assert out.shape == shape and out.dtype == np.float64 and out.flags.c_contiguous and out.flags.writeable
        np.testing.assert_array_equal(out, np.broadcast_to(np.asarray(given, dtype=float), shape))
        assert not np.shares_memory(out, np.asarray(given))


def test_the_warm_up_loads_every_signature_the_callers_use():
    """companion.kernels.warm compiles each kernel for the argument types its callers pass: after
    it, the callers' paths (a target with its feed-forward, Alg. 1 with and without the rate noise,
    the gate, a group's boundary) compile nothing new."""
    pytest.importorskip("pinocchio")
    from companion.estimation.gate import joint_nis
    from companion.estimation.sckf import CAParams, constraint_apply
    from companion.estimation.semi import local_boundary
    from companion.corrections import align_states, compute_corrections
    from companion.kernels import align, cpg, dynamics, gate, sckf, semi, trajectory, warm
    from companion.motion.generator import MotionGenerator
    from companion.motion.inverse import InverseModel
    from companion.messages import LinkState
    from companion.skeleton.body import SkeletonConfig
    from companion.skeleton.dynamics import ChainModel
    from companion.trajectory import ChainTrajectory, TrajectoryConfig

    warm.warm_up()
    kernels = (dynamics.passive_torques_kernel, dynamics.feedforward_kernel, sckf.constraint_apply_batched_kernel,
               gate.joint_nis_kernel, semi.group_terms_kernel, trajectory.trajectory_kernel, align.align_kernel,
               align.attitude_errors_kernel, cpg.cpg_step_kernel, cpg.cpg_output_kernel, cpg.body_step_kernel,
               cpg.link_targets_kernel)
    before = [list(k.signatures) for k in kernels]
    rng = np.random.default_rng(5)
    traj = ChainTrajectory(TrajectoryConfig(kind="bend"), 3, 1.0, np.zeros(3))
    p, q, R, v, a, w, wd = traj.target_arrays(2.0)
    ChainModel(SkeletonConfig(n_links=3)).solve(p, R, v, w, a, wd, passive=(1,))
    for omega_std in (0.0, 0.02):
        p, v, q, w, d, P = _random_chain(rng, 3, 0.05)
        local = constraint_apply(p, v, q, w, d, P, CAParams(omega_std_rad_s=omega_std))
        local_boundary(local.p, local.v, local.q, w, d, local)
        joint_nis(p, v, q, w, d, P)
        states = [LinkState(i, 1.0, p[i], v[i], q[i], w[i], P[i]) for i in range(3)]
        align_states(states, 1.01)
        compute_corrections(states, d, [(0, 1, 2)], CAParams(omega_std_rad_s=omega_std))
    gen = MotionGenerator(InverseModel.load(CPG_MODEL), compiled=True)
    gen.step(np.array([0.2, 0.0, 0.0, 0.0, 0.0, 0.1, 0.0]), 0.02)
    for k, sigs in zip(kernels, before):
        assert list(k.signatures) == sigs, k.__name__


@pytest.mark.parametrize("n_links", [2, 3, 5])
@pytest.mark.parametrize("omega_std", [0.0, 0.02])
def test_constraint_apply_takes_a_whole_covariance(n_links, omega_std):
    """constraint_apply_dense with the whole (9n, 9n) prior: its block-diagonal form gives what the
    blocks give; with neighbours correlated (a measurement between them before the constraint)
    the compiled kernel agrees with the numpy specification to 1e-12, and the correlation changes
    the corrections."""
    from companion.estimation.sckf import CAParams, block_diag_covariance, constraint_apply, constraint_apply_dense

    rng = np.random.default_rng(91 + n_links)
    params = CAParams(omega_std_rad_s=omega_std)
    p = np.cumsum(np.tile([1.0, 0.0, 0.0], (n_links, 1)), axis=0) + rng.normal(size=(n_links, 3)) * 0.05
    v = rng.normal(size=(n_links, 3)) * 0.3
    q = quat_normalize(np.array([1.0, 0.0, 0.0, 0.0]) + rng.normal(size=(n_links, 4)) * 0.05)
    w = rng.normal(size=(n_links, 3)) * 0.2
    d = np.tile([0.5, 0.0, 0.0], (n_links, 1))
    P = _ekf_like_covariances(rng, n_links)
    blocks = constraint_apply_dense(p, v, q, w, d, P, params, compiled=False)
    whole = constraint_apply_dense(p, v, q, w, d, block_diag_covariance(P), params, compiled=False)
    np.testing.assert_allclose(whole.p, blocks.p, atol=1e-12)
    np.testing.assert_allclose(whole.P_full, blocks.P_full, atol=1e-12)
    # neighbours 1 and 2 correlated: a positive definite prior with a cross block between them
    PE = block_diag_covariance(P)
    L = np.linalg.cholesky(PE)
    mix = np.eye(9 * n_links)
    mix[9:18, 0:9] = 0.5 * np.eye(9)
    corr = L @ mix @ mix.T @ L.T
    spec = constraint_apply_dense(p, v, q, w, d, corr, params, compiled=False)
    fast = constraint_apply_dense(p, v, q, w, d, corr, params, compiled=True)
    assert fast.iterations == spec.iterations and np.abs(spec.p - blocks.p).max() > 1e-6
    for name in ("p", "v", "q", "P_full", "W_ends"):
        a, b = getattr(fast, name), getattr(spec, name)
        if b is None:
            assert a is None
            continue
        np.testing.assert_allclose(a, b, rtol=0, atol=1e-12 * max(float(np.abs(b).max()), 1e-300), err_msg=name)
    np.testing.assert_allclose(constraint_apply(p, v, q, w, d, corr, params).p, spec.p, atol=1e-12)
    with pytest.raises(ValueError, match="P must be"):
        constraint_apply_dense(p, v, q, w, d, corr[:-1, :-1], params, compiled=False)


def _cpg_case(rng, n: int, at_rest: bool):
    """A random CPG (shaping, gains, frequency, lag), its state (at rest: the small-angle branch),
    parameters ``A, B``, a body and water, as the numpy functions and the kernels take them."""
    from companion.motion.cpg import CpgParams, CpgState
    from companion.motion.expected_physics import BodyState, WaterParams

    params = CpgParams(n, frequency_hz=rng.uniform(0.1, 1.0), k_a=rng.uniform(0.5, 4.0), k_b=rng.uniform(0.5, 4.0),
                       k_phi=rng.uniform(0.5, 4.0), sigma_a=tuple(rng.uniform(0.1, 1.0, n)),
                       sigma_b=tuple(rng.uniform(-1.0, 1.0, n)), lag_rad=rng.uniform(0.1, 1.0))
    scale = 0.0 if at_rest else 0.4
    state = CpgState(*(rng.normal(size=(n, 2)) * scale for _ in range(4)), rng.uniform(-np.pi, np.pi, n))
    A, B = rng.normal(size=2) * 0.4, rng.normal(size=2) * 0.2
    body = BodyState(rng.normal(size=3), rng.normal(size=3) * 0.3, quat_to_rotmat(quat_normalize(rng.normal(size=4))),
                     rng.normal(size=3) * 0.2)
    water = WaterParams(mass_kg=rng.uniform(2.0, 20.0), inertia_kg_m2=tuple(rng.uniform(0.2, 6.0, 3)))
    sa, sb, _ = params.shaping
    shape = (np.array(sa), np.array(sb), params.frequency_hz, params.k_a, params.k_b, params.k_phi)
    pairs = params.coupled_pairs
    coupling = (np.array(pairs.i, dtype=np.int64), np.array(pairs.j, dtype=np.int64), np.array(pairs.phi_ij))
    k = (0.5 * water.density_kg_m3 * water.area_axial_m2 * water.cd_axial,
         0.5 * water.density_kg_m3 * water.area_normal_m2 * water.cd_normal, water.mass_kg,
         np.array(water.inertia_kg_m2))
    return params, state, A, B, body, water, shape, coupling, k


@pytest.mark.parametrize("n", [2, 7, 15])
@pytest.mark.parametrize("at_rest", [False, True])
def test_cpg_generator_kernels_match_numpy(n, at_rest):
    """companion.kernels.cpg against companion.motion.cpg and .expected_physics on random CPGs,
    states and bodies: the Runge-Kutta step, the output (attitudes and rates), the drag and body
    step, and the link targets, to 1e-12."""
    from companion.kernels.cpg import body_step_kernel, cpg_output_kernel, cpg_step_kernel, link_targets_kernel
    from companion.motion.cpg import cpg_output, cpg_step
    from companion.motion.expected_physics import body_step, body_wrench, link_targets

    rng = np.random.default_rng(300 + n + 7 * at_rest)
    for _ in range(10):
        params, state, A, B, body, water, shape, coupling, k = _cpg_case(rng, n, at_rest)
        dt, half = rng.uniform(0.005, 0.05), rng.uniform(0.2, 0.8)
        ref = cpg_step(state, params, A, B, dt)
        got = tuple(np.array(x) for x in (state.a, state.a_dot, state.b, state.b_dot, state.phi))
        cpg_step_kernel(got, shape, coupling, A, B, dt)
        for x, y in zip(got, (ref.a, ref.a_dot, ref.b, ref.b_dot, ref.phi)):
            np.testing.assert_allclose(x, y, rtol=1e-12, atol=1e-12)
        _, R_bl, om = cpg_output(state, params, A, B)
        out = (np.empty((n, 3, 3)), np.empty((n, 3)))
        cpg_output_kernel(tuple(np.array(x) for x in (state.a, state.a_dot, state.b, state.b_dot, state.phi)), shape,
                          coupling, A, B, out)
        np.testing.assert_allclose(out[0], R_bl, rtol=1e-12, atol=1e-12)
        np.testing.assert_allclose(out[1], om, rtol=1e-12, atol=1e-12)
        f, tau = body_wrench(body, R_bl, om, half, water)
        ref_body = body_step(body, f, tau, water, dt)
        b = (body.p_w_m, body.v_w_m_s, body.R_wb, body.omega_b_rad_s)
        got_body = (np.empty(3), np.empty(3), np.empty((3, 3)), np.empty(3))
        body_step_kernel(b, R_bl, om, half, k, dt, 4, got_body)
        for x, y in zip(got_body, (ref_body.p_w_m, ref_body.v_w_m_s, ref_body.R_wb, ref_body.omega_b_rad_s)):
            np.testing.assert_allclose(x, y, rtol=1e-12, atol=1e-12)
        targets = (np.empty((n, 3)), np.empty((n, 3)), np.empty((n, 3, 3)), np.empty((n, 3)))
        link_targets_kernel(b, R_bl, om, half, targets)
        for x, y in zip(targets, link_targets(body, R_bl, om, half)):
            np.testing.assert_allclose(x, y, rtol=1e-12, atol=1e-12)


def test_the_compiled_motion_generator_flies_the_numpy_ones_targets():
    """The seven-link model's generator, compiled and numpy, over 60 s of two commands (with the
    adaptation of eq. 4.3 once per period): the same CPG parameters and targets to rounding."""
    from companion.motion.generator import MotionGenerator
    from companion.motion.inverse import InverseModel

    model = InverseModel.load(CPG_MODEL)
    spec, fast = MotionGenerator(model, compiled=False), MotionGenerator(model, compiled=True)
    commands = (np.array([0.3, 0.05, 0.0, 0.0, 0.0, 0.1, 0.0]), np.array([0.1, 0.0, 0.05, 0.0, 0.0, -0.1, 0.0]))
    for k in range(3000):
        xi = commands[k // 1500]
        a, b = spec.step(xi, 0.02), fast.step(xi, 0.02)
        for x, y in zip((a.p_w_m, a.v_w_m_s, a.R_wl, a.omega_l_rad_s), (b.p_w_m, b.v_w_m_s, b.R_wl, b.omega_l_rad_s)):
            np.testing.assert_allclose(y, x, rtol=1e-9, atol=1e-9)
    np.testing.assert_allclose(fast.eta, spec.eta, rtol=1e-9, atol=1e-12)
    assert np.linalg.norm(spec.body.p_w_m - np.zeros(3)) > 1.0  # it swam
