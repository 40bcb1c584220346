"""Holding a dead neighbour (link_firmware_sim.design.carry): the minimum infinity-norm thrust
against a linear program, the torque arm's geometry, the whole chain's sharing, the command."""

from __future__ import annotations

import json

import numpy as np
import pytest
from scipy.optimize import linprog

from companion.skeleton.rotors import RotorGeometry
from link_firmware_sim.design.__main__ import main
from link_firmware_sim.design.carry import GRAVITY_M_S2, _pitch_matrix, carry_cases, chain_hold_thrust_n, tip_load_thrust_n

GEOMETRY = RotorGeometry.odar(drag_ratio=0.02)


def _lp_thrust(B: np.ndarray, U: np.ndarray) -> float:
    """min ||lambda||_inf subject to B lambda = U, as a linear program in (lambda, s)."""
    n = B.shape[1]
    A_ub = np.vstack([np.c_[np.eye(n), -np.ones(n)], np.c_[-np.eye(n), -np.ones(n)]])
    res = linprog(np.r_[np.zeros(n), 1.0], A_ub=A_ub, b_ub=np.zeros(2 * n), A_eq=np.c_[B, np.zeros(6)], b_eq=U,
                  bounds=[(None, None)] * n + [(0.0, None)])
    assert res.success
    return float(res.x[-1])


@pytest.mark.parametrize("pitch_deg", [0.0, 20.0, 45.0, 70.0, 90.0])
@pytest.mark.parametrize("load_n", [0.0, 8.8, 17.7])
def test_the_thrust_is_the_least_largest_that_holds_the_load(pitch_deg, load_n):
    """The closed form (eq. 2.12) equals the linear program's optimum for the wrench that holds
    the link's weight and the load at its -x tip with no net torque about its centre."""
    m, L = 1.8, 1.0
    R = _pitch_matrix(np.radians(pitch_deg))
    tip_w = R @ np.array([-0.5 * L, 0.0, 0.0])
    f_w = np.array([0.0, 0.0, m * GRAVITY_M_S2 + load_n])
    torque_w = np.cross(tip_w, np.array([0.0, 0.0, load_n]))
    U = np.r_[R.T @ f_w, R.T @ torque_w]
    assert tip_load_thrust_n(GEOMETRY, m, L, load_n, pitch_deg) == pytest.approx(
        _lp_thrust(GEOMETRY.mapping_matrix(), U), rel=1e-6, abs=1e-9)


@pytest.mark.parametrize("load_n", [4.0, 12.0])
def test_hanging_vertical_the_load_is_only_weight(load_n):
    """At 90 deg pitch the load hangs on the link's axis: no torque, the same as a heavier link."""
    need = tip_load_thrust_n(GEOMETRY, 1.8, 1.0, load_n, 90.0)
    assert need == pytest.approx(tip_load_thrust_n(GEOMETRY, 1.8 + load_n / GRAVITY_M_S2, 1.0, 0.0, 90.0), rel=1e-9)
    assert need < tip_load_thrust_n(GEOMETRY, 1.8, 1.0, load_n, 0.0)


def test_a_longer_link_needs_more_to_hold_the_same_load_level():
    assert tip_load_thrust_n(GEOMETRY, 1.8, 1.5, 8.0) > tip_load_thrust_n(GEOMETRY, 1.8, 1.0, 8.0)
    assert tip_load_thrust_n(GEOMETRY, 1.8, 1.5, 0.0) == pytest.approx(tip_load_thrust_n(GEOMETRY, 1.8, 1.0, 0.0))


def test_a_chain_of_two_holds_a_dead_end_link_as_one_neighbour_alone():
    """The linear program for two links with one dead is the single carrier's case: the closed
    form of eq. 2.12, level."""
    assert chain_hold_thrust_n(GEOMETRY, 2, 1.8, 1.0, (0,)) == pytest.approx(
        tip_load_thrust_n(GEOMETRY, 1.8, 1.0, 1.8 * GRAVITY_M_S2), rel=1e-6)


@pytest.mark.parametrize("n", [1, 3, 7])
def test_a_chain_with_none_dead_needs_what_one_link_needs(n):
    assert chain_hold_thrust_n(GEOMETRY, n, 1.8, 1.0) == pytest.approx(tip_load_thrust_n(GEOMETRY, 1.8, 1.0, 0.0),
                                                                        rel=1e-6)


@pytest.mark.parametrize("n, dead", [(3, (0,)), (7, (0,)), (7, (6,)), (5, (2,)), (7, (1, 5))])
def test_the_rest_of_the_chain_helps_and_never_hurts(n, dead):
    """With a dead link, the whole chain needs no more than its neighbours alone would, and the
    same with more live links around (a longer chain can only share more)."""
    W = 1.8 * GRAVITY_M_S2
    inner = all(0 < d < n - 1 for d in dead)
    alone = tip_load_thrust_n(GEOMETRY, 1.8, 1.0, 0.5 * W if inner else W)
    need = chain_hold_thrust_n(GEOMETRY, n, 1.8, 1.0, dead)
    assert need <= alone + 1e-9
    assert chain_hold_thrust_n(GEOMETRY, n + 2, 1.8, 1.0, dead) <= need + 1e-9


def test_bad_dead_links_are_refused():
    for dead in ((3,), (0, 1, 2), (-1,)):
        with pytest.raises(ValueError, match="dead links"):
            chain_hold_thrust_n(GEOMETRY, 3, 1.8, 1.0, dead)


def test_the_cases_of_a_chain_and_the_command(tmp_path, capsys):
    own, inner, end = carry_cases(GEOMETRY, 3, 1.8, 1.0, 8.0)
    assert own.level_thrust_n < inner.level_thrust_n < end.level_thrust_n
    assert end.level_ratio > end.chain_ratio > 1.0 and end.best_pitch_deg == 90.0
    assert inner.load_n == pytest.approx(0.5 * end.load_n) and inner.chain_ratio < 1.0
    assert [c.case for c in carry_cases(GEOMETRY, 2, 1.8, 1.0, 8.0)] == ["own weight", "dead end link (all its weight)"]
    out = tmp_path / "carry.json"
    assert main(["carry", "--config", "configs/sitl/chain/three_link.toml", "--json", str(out)]) == 0
    printed = json.loads(capsys.readouterr().out)
    assert printed == json.loads(out.read_text()) and printed["n_links"] == 3
    assert [c["chain_holds"] for c in printed["cases"]] == [True, True, False]
    bad = tmp_path / "bad.toml"
    bad.write_text("[skeleton]\nlink_mass_kg = -1.0\n")
    assert main(["carry", "--config", str(bad)]) == 2
