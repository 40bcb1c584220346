"""The silence after which a link is carried, on a lossy wire: the loss estimate from the stamps'
gaps, the threshold's rule (its chance runs once in FALSE_CARRY_PERIOD_S, the cap), and the
engine on a 20 % lossy stream: a live link is not carried by chance, a dead one is carried by the
cap."""

from __future__ import annotations

import math
from dataclasses import replace

import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st

from companion.engine import CompanionEngine, TargetOut
from companion.engine.silence import BASE_RUN, FALSE_CARRY_PERIOD_S, StreamLoss, silence_threshold_s
from companion.messages import STATE_FLAG_ARMED, STATE_FLAG_EKF_OK

from ..engine_cases import of, setup_for, straight_state

RATE_HZ = 50.0
BASE_S, MAX_S = 0.06, 0.2


def _runs_per_s(loss: float, n: int) -> float:
    """How often a live stream of RATE_HZ states starts a run of n or more lost states [1/s]."""
    return RATE_HZ * (1.0 - loss) * loss ** n


def test_a_clean_stream_keeps_the_configured_silence():
    assert silence_threshold_s(0.0, BASE_S, MAX_S, RATE_HZ) == BASE_S
    assert silence_threshold_s(1e-9, BASE_S, MAX_S, RATE_HZ) == BASE_S
    assert silence_threshold_s(1.0, BASE_S, MAX_S, RATE_HZ) == MAX_S


@pytest.mark.parametrize("loss", [0.01, 0.05, 0.1, 0.2, 0.3])
def test_the_threshold_is_the_shortest_whose_chance_runs_are_rare_enough(loss):
    """Uncapped, the threshold lets through the shortest run n whose chance rate is at most once
    in FALSE_CARRY_PERIOD_S; a state period less would let through a run that comes more often."""
    t = silence_threshold_s(loss, BASE_S, 10.0, RATE_HZ)
    n = round((t - BASE_S) * RATE_HZ) + BASE_RUN
    assert t == pytest.approx(BASE_S + max(0, n - BASE_RUN) / RATE_HZ)
    assert _runs_per_s(loss, n) <= 1.0 / FALSE_CARRY_PERIOD_S
    if n > BASE_RUN:
        assert _runs_per_s(loss, n - 1) > 1.0 / FALSE_CARRY_PERIOD_S


@given(st.floats(0.0, 1.0), st.floats(0.0, 1.0))
def test_the_threshold_grows_with_the_loss_between_its_bounds(a, b):
    lo, hi = sorted((a, b))
    t_lo, t_hi = (silence_threshold_s(x, BASE_S, MAX_S, RATE_HZ) for x in (lo, hi))
    assert BASE_S <= t_lo <= t_hi <= MAX_S


@pytest.mark.parametrize("loss", [0.0, 0.05, 0.2, 0.4])
@pytest.mark.parametrize("seed", [0, 1])
def test_the_loss_estimate_follows_the_stream(loss, seed):
    """Bernoulli losses of a 50 Hz stream: the estimate is within 0.05 of the loss (its window is
    about 500 states); an outage longer than the cap is not counted as loss; a reboot's new
    clock is no gap."""
    rng = np.random.default_rng(seed)
    est = StreamLoss.of_stream(RATE_HZ, MAX_S)
    period_us = 20_000
    for k in range(1, 3000):
        if rng.random() >= loss:
            est.on_stamp(k * period_us)
    assert est.fraction == pytest.approx(loss, abs=0.05)
    before = est.fraction
    est.on_stamp(3000 * period_us + 5_000_000)  # back after a 5 s outage
    assert est.fraction == pytest.approx(before, abs=0.01)
    est.restart()
    est.on_stamp(40_000)  # a new clock
    assert est.fraction == pytest.approx(before, abs=0.01)


def test_the_loss_estimate_refuses_nothing_it_cannot_use():
    est = StreamLoss.of_stream(RATE_HZ, MAX_S)
    assert est.fraction == 0.0
    est.on_stamp(100_000)
    est.on_stamp(100_000)  # no gap (the gate refuses such a stamp before; counted as nothing here)
    assert est.fraction == 0.0 and est.received == 0.0


def _lossy_hover(loss: float, seed: int, duration_s: float, dead_at_s: float = math.inf, **companion):
    """A three-link hover whose middle link's states are each lost with probability ``loss``
    (seeded) and stop at ``dead_at_s``: the engine's summary, and when its neighbours first took
    its weight after its last state."""
    pytest.importorskip("pinocchio")
    setup = setup_for(3)
    setup = replace(setup, trajectory=replace(setup.trajectory, kind="hover", feedforward=True),
                    companion=replace(setup.companion, **companion))
    engine = CompanionEngine(setup)
    weight = None
    flying = STATE_FLAG_EKF_OK | STATE_FLAG_ARMED
    rng = np.random.default_rng(seed)
    t, last_heard, carried_after = 0.0, 0.0, None
    for k in range(1, int(round(duration_s / 0.02)) + 1):
        t = round(k * 0.02, 6)
        for r in range(3):
            if r == 1 and (t >= dead_at_s or (t > 1.0 and rng.random() < loss)):
                continue
            engine.on_state(r, straight_state(r, 3, t), flying, t)
            last_heard = t if r == 1 else last_heard
        out = of(TargetOut, engine.poll(t))
        if not out:  # the first targets come with the first step
            continue
        weight = engine.trajectory.dynamics.inertia.mass_kg * 9.80665
        lift = out[0].target.force_ff_w_n[2] + out[2].target.force_ff_w_n[2]
        if carried_after is None and t >= dead_at_s and lift > 0.5 * weight:
            carried_after = t - last_heard
    return engine.summary()["links"]["2"], carried_after


def test_a_live_link_on_a_lossy_wire_is_not_carried_by_chance():
    """20 % of the middle link's states lost for 60 s: with the loss-aware threshold
    (carry_silence_max_s set) it is carried at most once (a chance run of the threshold's length:
    about once in ten minutes), where the fixed silence (the default) carries it many times."""
    aware, _ = _lossy_hover(0.2, seed=3, duration_s=60.0, carry_silence_max_s=MAX_S)
    fixed, _ = _lossy_hover(0.2, seed=3, duration_s=60.0)
    assert aware["state_loss"] == pytest.approx(0.2, abs=0.05)
    assert fixed["carried_stretches"] >= 10
    assert aware["carried_stretches"] <= 1


@pytest.mark.parametrize("loss", [0.0, 0.2, 0.5])
def test_a_dead_link_on_a_lossy_wire_is_carried_by_the_cap(loss):
    """The middle link dies after 20 s on a wire losing ``loss`` of its states (the threshold
    loss-aware): it is carried within its silence threshold after its last state (the configured
    silence on a clean wire), and never later than carry_silence_max_s, however lossy its stream
    was; with the default fixed silence, at carry_silence_s whatever the loss."""
    summary, after = _lossy_hover(loss, seed=1, duration_s=21.0, dead_at_s=20.0, carry_silence_max_s=MAX_S)
    expected = silence_threshold_s(loss, BASE_S, MAX_S, RATE_HZ)
    assert after is not None and after <= expected + 0.04 + 1e-9 and after <= MAX_S + 0.04 + 1e-9
    assert after >= (BASE_S if loss == 0.0 else expected - 0.04) - 1e-9
    assert summary["carried_stretches"] >= 1
    _, fixed_after = _lossy_hover(loss, seed=1, duration_s=21.0, dead_at_s=20.0)
    assert BASE_S - 1e-9 <= fixed_after <= BASE_S + 0.04 + 1e-9
