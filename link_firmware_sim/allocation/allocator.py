"""The stateful allocator of one link (thesis ch. 2, sec. 2.4; the equations: :mod:`.mapping`).

:class:`Allocator` precomputes every matrix once, keeps the modulation state ``xi''_pre`` of (2.15)
between calls and runs the whole pipeline per wrench: by its kernel
(:func:`link_firmware_sim.kernels.allocation.allocate_kernel`) or by the specification (the
functional core), the one dispatch in :meth:`Allocator.allocate` and :meth:`Allocator.command`.
"""

from __future__ import annotations

import math

import numpy as np

from companion.kernels.jit import ENABLED
from companion.skeleton.rotors import N_ROTORS, N_SIDE, NU, SIDES, WRENCH_DIM, RotorGeometry, _frozen

from ..kernels.allocation import ALLOC_META, allocate_kernel
from ..kernels.layouts import (ALLOC_EPS0, ALLOC_EPS1, ALLOC_FAILED, ALLOC_NU, ALLOC_SCALE_TO_LIMIT, ALLOC_SELECTIVE,
                               ALLOC_SIZE, ALLOC_TEST, ALLOC_TEST_WRENCH, ALLOC_TMAX, ALLOC_TOL, ALLOC_XI_PRE)
from .mapping import (MARGIN_TOL_N, AllocationParams, AllocationResult, _fade_within_limit, gradual_selective_mapping,
                      infinity_norm_allocation, pseudo_inverse, reduced_pseudo_inverses, scaled_to_limit,
                      selective_mapping_weights, selective_modulation)

__all__ = ["Allocator"]


def _checked_keep(keep) -> np.ndarray:
    """The wrench :func:`scaled_to_limit` keeps: zeros for ``None``; 6 finite numbers."""
    if keep is None:
        return np.zeros(WRENCH_DIM)
    keep = np.asarray(keep, dtype=float)
    if keep.shape != (WRENCH_DIM,) or not math.isfinite(keep.sum()):
        raise ValueError(f"keep must be 6 finite numbers [force (N); torque (Nm)]; got {keep!r}")
    return keep


class Allocator:
    """Stateful allocation of one link: keeps ``xi''_pre`` of (2.15) between calls.

    Parameters
    ----------
    geometry : RotorGeometry
        Must satisfy (2.11) (:meth:`RotorGeometry.has_null_structure`): Prop. 1's closed form
        and the selective mapping both rely on it.
    params : AllocationParams
    compiled : bool, optional
        Run :meth:`allocate` and :meth:`command` by the kernel
        (:func:`link_firmware_sim.kernels.allocation.allocate_kernel`; default: when numba is
        installed and not turned off) instead of the specification (:meth:`_allocate_spec`, with
        the functional core of :mod:`.mapping`); the same numbers to rounding
        (``tests/unit/test_fast_paths.py``).

    Raises
    ------
    ValueError
        If (2.11) does not hold (with selective mapping requested or not: Prop. 1 needs it
        too), or ``B`` or any single-rotor reduction of it is not full row rank.
    """

    def __init__(self, geometry: RotorGeometry, params: AllocationParams = AllocationParams(), *,
                 compiled: bool | None = None) -> None:
        if not geometry.has_null_structure():
            if params.selective_mapping:
                raise ValueError(
                    "selective mapping (2.15)-(2.17) requires the null structure (2.11) with nu = [1, -1, -1, 1]; "
                    "this geometry does not have it (Table 2.1 as printed, sigma1=+1? use the modified sigma1=-1)"
                )
            raise ValueError(
                "the closed-form infinity-norm allocation (Prop. 1) requires the null structure (2.11) with "
                "nu = [1, -1, -1, 1]; this geometry does not have it (use the modified design sigma1=-1)"
            )
        self.geometry = geometry
        self.params = params
        B = geometry.mapping_matrix()
        self._B = _frozen(B)
        self._B_pinv = _frozen(pseudo_inverse(B))
        self._B_pinv_reduced = _frozen(reduced_pseudo_inverses(B))
        # _reduced_by_side[s, jl] = side-s rows of B^+_{\(s*4 + jl)} (4x6), by (2.18)-(2.19).
        red = np.empty((2, N_SIDE, N_SIDE, WRENCH_DIM))
        for s, side in enumerate(SIDES):
            for jl in range(N_SIDE):
                red[s, jl] = self._B_pinv_reduced[side.start + jl][side]
        self._reduced_by_side = _frozen(red)
        self._selective = bool(params.selective_mapping)
        self._eps0 = float(params.eps0_n)
        self._eps1 = float(params.eps1_n)
        self._tmax = float(params.thrust_max_n)
        self._scale_to_limit = bool(params.scale_to_limit)
        self._xi_limit = self._tmax if self._scale_to_limit else math.inf  # (2.15) within the limit
        self._compiled = ENABLED if compiled is None else bool(compiled)
        # the kernels' state (ALLOC_* of kernels.layouts): the thresholds, nu and xi''_pre of (2.15)
        state = np.zeros(ALLOC_SIZE)
        state[[ALLOC_EPS0, ALLOC_EPS1, ALLOC_TMAX, ALLOC_SELECTIVE, ALLOC_SCALE_TO_LIMIT, ALLOC_TOL]] = (
            self._eps0, self._eps1, self._tmax, self._selective, self._scale_to_limit, MARGIN_TOL_N)
        state[ALLOC_NU:ALLOC_NU + N_SIDE] = NU
        state[ALLOC_FAILED] = -1.0
        self._state = state
        #: what the kernels read and update: ``(B_pinv, reduced_by_side, state)``, ``state`` holding
        #: the thresholds, the null vector and ``xi''_pre`` (``ALLOC_*`` of
        #: :mod:`link_firmware_sim.kernels.layouts`); the firmware's fused tick passes it on
        self.tick_state = (np.array(self._B_pinv, order="C"), np.array(self._reduced_by_side, order="C"), state)
        #: of the last allocation: ``AllocationResult.scale`` and ``.saturated`` (the firmware's
        #: thrust-limit report reads them; the fused tick sets them for its own)
        self.scale, self.saturated = 1.0, False

    @property
    def mapping_matrix(self) -> np.ndarray:
        """``B`` (6, 8), read-only."""
        return self._B

    @property
    def pinv(self) -> np.ndarray:
        """``B^+`` (8, 6), read-only."""
        return self._B_pinv

    @property
    def reduced_pinvs(self) -> np.ndarray:
        """``B^+_{\\i}`` stacked (8, 8, 6), read-only."""
        return self._B_pinv_reduced

    @property
    def xi_pre(self) -> np.ndarray:
        """Copy of the stored ``[xi''_{r,pre}; xi''_{l,pre}]`` of (2.15)."""
        return self._state[ALLOC_XI_PRE:ALLOC_XI_PRE + 2].copy()

    def reset(self) -> None:
        """Clear the modulation state: ``xi''_pre = 0`` (a removed rotor stays removed)."""
        self._state[ALLOC_XI_PRE:ALLOC_XI_PRE + 2] = 0.0

    @property
    def removed_rotor(self) -> int | None:
        """The rotor (0-based) left out of the allocation as failed (:meth:`remove_rotor`), or ``None``."""
        f = int(self._state[ALLOC_FAILED])
        return None if f < 0 else f

    @property
    def test_thrust_n(self) -> float:
        """The thrust [N] the removed rotor is commanded (0 without one)."""
        return float(self._state[ALLOC_TEST])

    def remove_rotor(self, rotor: int, test_thrust_n: float = 0.0) -> bool:
        """Leave failed rotor ``rotor`` (0-based) out of the allocation from now on: its side runs
        the rows of ``B^+_{\\j}`` without it (exact with the other side's by (2.18)-(2.19) and Prop.
        2; every single-rotor reduction of ``B`` is full rank), the other side as before (PX4's
        ``CA_FAILURE_MODE = 1``). With no null space left on its side, that side's thrusts follow
        from the wrench alone (hovering, two of its rotors carry twice their share), so a wrench
        beyond the seven rotors is clipped rotor by rotor (the thesis's allocation) instead of
        scaled onto the limit with the weight kept (``scale_to_limit``): scaling left the attitude
        control no authority and the link sank and tipped, where clipping held it. ``test_thrust_n``: the removed rotor is still commanded
        this much (within the limit), its wrench taken off the one the others produce, so that its
        ESC's telemetry tells whether it turns again (:mod:`link_firmware_sim.motor_failure`);
        the others' exactness holds while it does. One rotor at most: False (nothing changed) if
        another is removed already."""
        if not 0 <= rotor < N_ROTORS:
            raise ValueError(f"rotor {rotor} is not one of 0..{N_ROTORS - 1}")
        if not abs(test_thrust_n) <= self._tmax:
            raise ValueError(f"test_thrust_n must be within +-{self._tmax} N; got {test_thrust_n!r}")
        if self.removed_rotor not in (None, rotor):
            return False
        state = self._state
        state[ALLOC_FAILED] = float(rotor)
        state[ALLOC_TEST] = float(test_thrust_n)
        state[ALLOC_TEST_WRENCH:ALLOC_TEST_WRENCH + WRENCH_DIM] = self._B[:, rotor] * test_thrust_n
        state[ALLOC_XI_PRE + rotor // N_SIDE] = 0.0
        return True

    def restore_rotors(self) -> None:
        """Every rotor in the allocation again."""
        self._state[ALLOC_FAILED] = -1.0
        self._state[ALLOC_TEST:ALLOC_TEST_WRENCH + WRENCH_DIM] = 0.0

    def allocate(self, U: np.ndarray, keep: np.ndarray | None = None) -> AllocationResult:
        """Allocate the body-frame wrench ``U = [R^T f; tau]`` (N, Nm) to the eight rotors.

        With ``scale_to_limit``, first the wrench the rotors can produce, ``keep`` kept whole
        (:func:`scaled_to_limit`). Runs Prop. 1 (2.12), then, if enabled, the modulation (2.15)
        (updating ``xi''_pre``; within the limit with ``scale_to_limit``) and the gradual
        selective mapping (2.17) (within the limit with ``scale_to_limit``:
        :func:`_fade_within_limit`); clips to ``+-thrust_max_n``.

        Raises
        ------
        ValueError
            If ``U`` is not 6 finite numbers (the state is left untouched).
        """
        U = np.asarray(U, dtype=float)
        if U.shape != (WRENCH_DIM,) or not math.isfinite(U.sum()):
            raise ValueError(f"U must be 6 finite numbers [force (N); torque (Nm)]; got {U!r}")
        keep = _checked_keep(keep)
        r = self._allocate_kernel(U, keep) if self._compiled else self._allocate_spec(U, keep)
        self.scale, self.saturated = r.scale, r.saturated
        return r

    def _allocate_spec(self, U: np.ndarray, keep: np.ndarray) -> AllocationResult:
        """:meth:`allocate` by the functional core of :mod:`.mapping` (``U`` checked): the
        specification of the kernel."""
        tmax, B_pinv = self._tmax, self._B_pinv
        f = self.removed_rotor
        failed = None if f is None else (f // N_SIDE, self._reduced_by_side[f // N_SIDE, f % N_SIDE])
        if failed is not None:  # what the others produce: the wrench less the removed rotor's test thrust's
            U = U - self._state[ALLOC_TEST_WRENCH:ALLOC_TEST_WRENCH + WRENCH_DIM]
        scale = 1.0
        if self._scale_to_limit and failed is None:  # (with a rotor out: clipped, see remove_rotor)
            U, scale = scaled_to_limit(B_pinv, U, tmax, keep=keep)
        lam_o, xi1, lam_alpha = infinity_norm_allocation(B_pinv, U)  # Prop. 1, (2.12)
        common = {"lambda_o": lam_o, "lambda_alpha": lam_alpha, "wrench": U, "scale": scale}
        if not self._selective:
            lam = lam_alpha.copy()
            e, near = [1.0, 1.0], [-1, -1]
            if failed is not None:  # the removed rotor's side without it, the rotor at its test thrust
                lam[SIDES[failed[0]]] = failed[1] @ U
                lam[f] = self.test_thrust_n
                e[failed[0]], near[failed[0]] = 0.0, f
            return AllocationResult(command_n=np.clip(lam, -tmax, tmax), lambda_beta=lam, lambda_gamma=lam,
                                    e=(e[0], e[1]), near_zero=(near[0], near[1]),
                                    saturated=scale != 1.0 or np.abs(lam).max() > tmax, **common)
        xi2 = selective_modulation(lam_o, xi1, self.xi_pre, NU, self._eps1, self._xi_limit)  # (2.15)
        if failed is not None:  # (no null space left on the removed rotor's side)
            xi2[failed[0]] = 0.0
        self._state[ALLOC_XI_PRE:ALLOC_XI_PRE + 2] = xi2
        xi = xi1 + xi2
        lam_beta = lam_o + (NU * xi[:, None]).ravel()
        e, near = selective_mapping_weights(lam_beta, self._eps0, self._eps1)  # (2.17)
        if failed is not None:  # the removed rotor faded out of its side for good
            e, near = list(e), list(near)
            e[failed[0]], near[failed[0]] = 0.0, f
            e, near = (e[0], e[1]), (near[0], near[1])
        lam_gamma = gradual_selective_mapping(B_pinv, self._B_pinv_reduced, U, NU, xi, e, near)
        if failed is not None:
            lam_gamma[f] = self.test_thrust_n
        faded = False
        if self._scale_to_limit:  # (2.17) within the limit: a side's fade held back as far as that needs
            e = list(e)
            for s, side in enumerate(SIDES):
                if near[s] >= 0 and (failed is None or s != failed[0]) and np.abs(lam_gamma[side]).max() > tmax:
                    red = self._B_pinv_reduced[near[s]][side] @ U
                    e[s] = _fade_within_limit(red.tolist(), lam_beta[side].tolist(), e[s], tmax)
                    lam_gamma[side] = red + e[s] * (lam_beta[side] - red)
                    faded = True
            e = (e[0], e[1])
        return AllocationResult(command_n=np.clip(lam_gamma, -tmax, tmax), lambda_beta=lam_beta, lambda_gamma=lam_gamma,
                                e=e, near_zero=near, saturated=scale != 1.0 or faded or np.abs(lam_gamma).max() > tmax,
                                **common)

    def command(self, U: np.ndarray, keep: np.ndarray | None = None) -> np.ndarray:
        """``allocate(U).command_n`` (the thrusts sent to the ESCs) without the intermediate
        allocations: what the firmware's fast loop needs of it."""
        if not self._compiled:
            return self.allocate(U, keep).command_n
        U = np.asarray(U, dtype=float)
        if U.shape != (WRENCH_DIM,) or not math.isfinite(U.sum()):
            raise ValueError(f"U must be 6 finite numbers [force (N); torque (Nm)]; got {U!r}")
        out, meta = np.empty((5, N_ROTORS)), np.empty(ALLOC_META)
        allocate_kernel(U, _checked_keep(keep), self.tick_state, out, meta)
        self.scale, self.saturated = float(meta[5]), bool(meta[4])
        return out[0]

    def _allocate_kernel(self, U: np.ndarray, keep: np.ndarray) -> AllocationResult:
        """:meth:`allocate` by the kernel (``U`` checked)."""
        out, meta = np.empty((5, N_ROTORS)), np.empty(ALLOC_META)
        allocate_kernel(U, keep, self.tick_state, out, meta)
        return AllocationResult(command_n=out[0], lambda_o=out[1], lambda_alpha=out[2], lambda_beta=out[3],
                                lambda_gamma=out[4], e=(float(meta[0]), float(meta[1])),
                                near_zero=(int(meta[2]), int(meta[3])), saturated=bool(meta[4]), wrench=meta[6:12],
                                scale=float(meta[5]))
