import numpy as np
import pytest

from companion.estimation.chain import ERR_DIM, ERR_TH
from companion.estimation.constraints import (
    constraint_jacobian,
    constraint_jacobian_blocks,
    constraint_residual,
    left_tip,
    right_tip,
)
from companion.estimation.so3 import retract

from ..chains import consistent_chain, perturbed_chain


@pytest.mark.parametrize("n", [1, 2, 5, 12])
def test_consistent_chain_has_zero_residual(n):
    p, v, q, w, d = consistent_chain(np.random.default_rng(n), n)
    c = constraint_residual(p, v, q, w, d)
    assert c.shape == (6 * (n - 1),)
    np.testing.assert_allclose(c, 0.0, atol=1e-12)


def test_residual_is_tip_difference():
    p, v, q, w, d, _ = perturbed_chain(np.random.default_rng(0), 4)
    c = constraint_residual(p, v, q, w, d).reshape(3, 6)
    np.testing.assert_allclose(c, right_tip(p, v, q, w, d)[:-1] - left_tip(p, v, q, w, d)[1:], atol=1e-15)


def _perturb(p, v, q, dx):
    n = p.shape[0]
    dx = dx.reshape(n, ERR_DIM)
    return p + dx[:, 0:3], v + dx[:, 3:6], retract(q, dx[:, ERR_TH])


@pytest.mark.parametrize("n", [2, 3, 4, 5, 6])
@pytest.mark.parametrize("seed", [0, 1, 2])
def test_jacobian_matches_finite_differences(n, seed):
    """Eq. 4 against central differences of eq. 3 under the world-frame retraction."""
    rng = np.random.default_rng(100 * n + seed)
    p, v, q, w, d, _ = perturbed_chain(rng, n, pos_sigma=1.0, att_sigma=0.5)
    C = constraint_jacobian(q, w, d)
    h = 1e-6
    C_fd = np.empty_like(C)
    for k in range(ERR_DIM * n):
        e = np.zeros(ERR_DIM * n)
        e[k] = h
        plus = constraint_residual(*_perturb(p, v, q, e), w, d)
        minus = constraint_residual(*_perturb(p, v, q, -e), w, d)
        C_fd[:, k] = (plus - minus) / (2 * h)
    np.testing.assert_allclose(C, C_fd, atol=1e-8)


def test_jacobian_blocks_only_couple_neighbours():
    p, v, q, w, d, _ = perturbed_chain(np.random.default_rng(3), 5)
    C = constraint_jacobian(q, w, d)
    L, R = constraint_jacobian_blocks(q, w, d)
    for i in range(4):
        rows = slice(6 * i, 6 * i + 6)
        for j in range(5):
            block = C[rows, 9 * j : 9 * j + 9]
            if j == i:
                np.testing.assert_array_equal(block, L[i])
            elif j == i + 1:
                np.testing.assert_array_equal(block, R[i])
            else:
                assert not block.any()
