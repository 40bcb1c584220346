"""Plausibility before use: the stamp gate (replays, future stamps, reboots) and the joint gate."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from companion.estimation.gate import CHI2_6_1E6, GateParams, gate_chain, joint_nis, segments
from companion.estimation.neighbour import NEIGHBOUR_GATE_CHI2
from companion.estimation.constraints import constraint_jacobian_blocks, constraint_residual
from companion.plausibility import StampGate, StampVerdict, StampWindow

from ..chains import consistent_chain, perturbed_chain, random_covariances

V = StampVerdict


@pytest.mark.parametrize("value, tail, dof", [(CHI2_6_1E6, 1e-6, 6), (NEIGHBOUR_GATE_CHI2, 1e-3, 6)])
def test_gate_thresholds_are_the_chi_square_quantiles_they_name(value, tail, dof):
    from scipy.stats import chi2

    assert value == pytest.approx(chi2.isf(tail, dof), abs=0.005)


def test_stamps_must_increase_within_the_clock_window():
    gate = StampGate(StampWindow(margin_s=0.25, clock_rate_max=1.1))
    assert gate.check(1_000_000, 10.0) is V.ACCEPTED
    assert gate.check(1_000_000, 10.01) is V.REPLAY  # the same stamp again
    assert gate.check(990_000, 10.02) is V.REPLAY  # older
    assert gate.check(1_000_000 + 1000 * 1_000_000, 10.03) is V.FUTURE  # 1000 s ahead
    assert gate.last_us == 1_000_000  # a rejected stamp never moves the gate
    assert gate.check(1_020_000, 10.04) is V.ACCEPTED
    # after 2 s of silence the clock may have run 2.2 s (+ margin), not 3 s
    assert gate.check(1_020_000 + 2_400_000, 12.04) is V.ACCEPTED
    assert gate.check(1_020_000 + 2_400_000 + 3_000_000, 14.04) is V.FUTURE


def test_a_reboot_rebases_after_the_silence_and_a_consistent_new_clock():
    w = StampWindow(reboot_silence_s=1.0, reboot_frames=10)
    gate = StampGate(w)
    for k in range(50):
        assert gate.check(500_000_000 + 20_000 * k, 0.02 * k) is V.ACCEPTED
    t0 = 0.02 * 49
    # the link reboots: its clock restarts at 0.3 s; within the silence nothing is rebased
    verdicts = [gate.check(300_000 + 20_000 * k, t0 + 0.5 + 0.02 * k) for k in range(20)]
    assert set(verdicts) == {V.REPLAY}
    # once silent for 1 s, ten consistent stamps make the new clock
    verdicts = [gate.check(800_000 + 20_000 * k, t0 + 1.0 + 0.02 * k) for k in range(12)]
    assert verdicts[:9] == [V.REPLAY] * 9 and verdicts[9] is V.REBASED and verdicts[10:] == [V.ACCEPTED] * 2


def test_a_forged_future_stamp_cannot_wedge_a_link():
    """A forged stamp inside the window is accepted: the honest stream is rejected only until it
    passes that stamp (at most the margin). Further ahead it is rejected outright."""
    gate = StampGate(StampWindow(margin_s=0.25, reboot_silence_s=1.0, reboot_frames=10))
    gate.check(1_000_000, 0.0)
    assert gate.check(1_000_000 + 1_000_000, 0.001) is V.FUTURE
    assert gate.check(1_000_000 + 240_000, 0.001) is V.ACCEPTED  # forged, 0.24 s ahead
    honest = [gate.check(1_000_000 + 20_000 * k, 0.02 * k) for k in range(1, 80)]
    assert honest[:12] == [V.REPLAY] * 12 and set(honest[12:]) == {V.ACCEPTED}


def test_a_stream_rebases_after_a_wedge_further_than_the_margin():
    """Should a stamp far ahead ever be accepted (the first frame a link sends, forged), the honest
    stream re-bases once nothing has been accepted for the silence."""
    gate = StampGate(StampWindow(margin_s=0.25, reboot_silence_s=1.0, reboot_frames=10))
    assert gate.check(1_000_000_000, 0.0) is V.ACCEPTED  # forged first frame, 1000 s ahead
    honest = [gate.check(1_000_000 + 20_000 * k, 0.02 * k) for k in range(1, 80)]
    first = honest.index(V.REBASED)
    assert set(honest[:first]) == {V.REPLAY} and set(honest[first + 1:]) == {V.ACCEPTED}
    assert 0.02 * (first + 1) == pytest.approx(1.0 + 9 * 0.02)  # the silence, then ten frames


def test_interleaved_garbage_keeps_a_silent_link_out():
    gate = StampGate(StampWindow(reboot_silence_s=0.5, reboot_frames=5))
    gate.check(10_000_000, 0.0)
    out = []
    for k in range(40):
        out.append(gate.check(20_000 * k + 1, 1.0 + 0.02 * k))
        out.append(gate.check(9_000_000 - 20_000 * k, 1.01 + 0.02 * k))  # going backwards: never a clock
    assert V.REBASED not in out


@settings(max_examples=200, deadline=None)
@given(st.lists(st.tuples(st.integers(-10**9, 10**9), st.floats(0.0, 2.0)), min_size=1, max_size=60))
def test_accepted_stamps_always_increase(steps):
    """Between re-bases (a new clock after a silence) accepted stamps strictly increase, and a
    re-base only ever follows a silence of reboot_silence_s."""
    gate = StampGate(StampWindow(reboot_silence_s=0.5, reboot_frames=3))
    now, last, last_accept_s = 0.0, None, None
    for stamp, dt in steps:
        now += dt
        verdict = gate.check(stamp, now)
        if verdict is V.ACCEPTED:
            assert last is None or stamp > last
        elif verdict is V.REBASED:
            assert now - last_accept_s >= 0.5
        if verdict in (V.ACCEPTED, V.REBASED):
            last, last_accept_s = stamp, now
        else:
            assert gate.last_us == last


def test_window_rejects_bad_parameters():
    with pytest.raises(ValueError, match="margin_s"):
        StampWindow(margin_s=0.0)
    with pytest.raises(ValueError):
        GateParams(threshold=float("nan"))


# -- the joint gate --------------------------------------------------------------------------------------


def _nis_reference(p, v, q, w, d, P, params):
    """Per joint, from the dense eq. 4 Jacobian of the two links alone."""
    out = []
    for i in range(p.shape[0] - 1):
        sl = slice(i, i + 2)
        c = constraint_residual(p[sl], v[sl], q[sl], w[sl], d[sl])
        L, R = constraint_jacobian_blocks(q[sl], w[sl], d[sl])
        C = np.hstack([L[0], R[0]])
        Pj = np.zeros((18, 18))
        Pj[:9, :9], Pj[9:, 9:] = P[i], P[i + 1]
        S = C @ Pj @ C.T + np.diag([params.gate_pos_m ** 2] * 3 + [params.gate_vel_m_s ** 2] * 3)
        out.append(float(c @ np.linalg.solve(S, c)))
    return np.array(out)


@pytest.mark.parametrize("n", [2, 3, 7])
def test_joint_nis_matches_the_dense_form(n):
    rng = np.random.default_rng(n)
    p, v, q, w, d, P = perturbed_chain(rng, n)
    params = GateParams()
    np.testing.assert_allclose(joint_nis(p, v, q, w, d, P, params), _nis_reference(p, v, q, w, d, P, params),
                               rtol=1e-9)


def test_nis_of_consistent_errors_follows_chi_square_6():
    """States drawn from their covariances around an exact chain: mean NIS = 6 (no slack)."""
    rng = np.random.default_rng(3)
    p, v, q, w, d = consistent_chain(rng, 3)
    P = np.stack([np.diag([0.02 ** 2] * 3 + [0.05 ** 2] * 3 + [0.01 ** 2] * 3)] * 3)
    params = GateParams(gate_pos_m=1e-9, gate_vel_m_s=1e-9)
    values = []
    for _ in range(400):
        dp = rng.normal(0, 0.02, (3, 3))
        dv = rng.normal(0, 0.05, (3, 3))
        values.append(joint_nis(p + dp, v + dv, q, w, d, P, params))
    values = np.concatenate(values)
    # attitude errors not drawn: S over-counts them a little, the mean sits just under 6
    assert 4.5 < values.mean() < 6.5 and (values > CHI2_6_1E6).sum() == 0


@pytest.mark.parametrize("n", [3, 5, 7])
@pytest.mark.parametrize("bad", ["first", "inner", "last"])
def test_a_3_m_state_with_a_tiny_covariance_is_the_one_excluded(n, bad):
    rng = np.random.default_rng(7)
    p, v, q, w, d = consistent_chain(rng, n)
    P = random_covariances(rng, n, 0.01)
    k = {"first": 0, "inner": n // 2, "last": n - 1}[bad]
    p = p.copy()
    P = P.copy()
    p[k] += [0.0, 3.0, 0.0]
    P[k] = np.eye(9) * 1e-6
    res = gate_chain(p, v, q, w, d, P)
    assert res.excluded == (k,)
    assert list(np.flatnonzero(res.cut)) == [j for j in (k - 1, k) if 0 <= j < n - 1]
    usable = [i not in res.excluded for i in range(n)]
    segs = segments(usable, res.cut)
    assert all(k not in s for s in segs)
    # the healthy links stay corrected, except one cut off alone at an end (nothing to constrain)
    alone = sum(1 for run in ((0, k), (k + 1, n)) if run[1] - run[0] == 1)
    assert sum(len(s) for s in segs) == n - 1 - alone


def test_a_healthy_chain_passes_the_gate():
    rng = np.random.default_rng(11)
    p, v, q, w, d, P = perturbed_chain(rng, 7, pos_sigma=0.05, att_sigma=0.02)
    res = gate_chain(p, v, q, w, d, P)
    assert not res.cut.any() and res.excluded == ()


def test_a_two_link_chain_cuts_without_blaming():
    rng = np.random.default_rng(5)
    p, v, q, w, d = consistent_chain(rng, 2)
    P = random_covariances(rng, 2, 0.01)
    p[1] += [0.0, 0.0, 3.0]
    res = gate_chain(p, v, q, w, d, P)
    assert res.cut.tolist() == [True] and res.excluded == ()
    assert segments([True, True], res.cut) == []


def test_a_nan_residual_cuts():
    rng = np.random.default_rng(5)
    p, v, q, w, d, P = perturbed_chain(rng, 3)
    p = p.copy()
    p[2, 0] = np.nan
    assert gate_chain(p, v, q, w, d, P).cut.tolist() == [False, True]


@pytest.mark.parametrize("usable, cut, want", [
    ([True] * 5, None, [(0, 1, 2, 3, 4)]),
    ([True, True, False, True, True], None, [(0, 1), (3, 4)]),
    ([True, False, True, True, True], [False, False, True, False], [(3, 4)]),
    ([False, True, False, True, False], None, []),
    ([True] * 4, [False, True, False], [(0, 1), (2, 3)]),
])
def test_segments(usable, cut, want):
    assert segments(usable, cut) == want
