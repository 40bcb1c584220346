"""The rotors of one ODAR link (thesis ch. 2): geometry of thesis Table 2.1 and the rotor/ESC parameters.

Shared by the link firmware (allocation, eq. 2.8), the simulator (MuJoCo rotor sites and the
ESC model) and the companion's chain model: one description of the vehicle. Pure numpy.

Rotors 1-4 (0-based indices 0..3, :data:`R_SIDE`) form the r-side and rotors 5-8 (4..7,
:data:`L_SIDE`) the l-side, with ``u_{j+4} = u_j``, ``r_{j+4} = -r_j``, ``sigma_{j+4} = -sigma_j``
(sec. 2.2.2). Column ``i`` of the mapping matrix ``B = [B_f; B_tau]`` (6x8, eq. 2.8) is
``[u_i; t_i]`` with ``t_i = r_i x u_i + gamma sigma_i u_i`` (eq. 2.1). With the modified design
of sec. 2.4.1 (``sigma_1 = -1``) the null-vector structure (2.11) holds with ``nu = [1, -1, -1, 1]``.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from companion.configfile import require_nonnegative, require_positive

__all__ = [
    "N_ROTORS",
    "N_SIDE",
    "R_SIDE",
    "L_SIDE",
    "SIDES",
    "WRENCH_DIM",
    "W_FORCE",
    "W_TORQUE",
    "NU",
    "RotorGeometry",
    "RotorGeometryConfig",
    "RotorParams",
]

N_ROTORS = 8
"""Number of rotors of one ODAR link."""
N_SIDE = 4
"""Rotors per side."""
R_SIDE = slice(0, 4)
"""r-side rotors 1-4 (0-based 0..3) in ``lambda`` and in the columns of ``B``."""
L_SIDE = slice(4, 8)
"""l-side rotors 5-8 (0-based 4..7)."""
SIDES = (R_SIDE, L_SIDE)
"""Both sides, in the order of ``xi = [xi_r; xi_l]`` and ``e = (e_r, e_l)``."""
WRENCH_DIM = 6
W_FORCE = slice(0, 3)
"""Force rows of ``U`` and ``B`` (``B_f``), body frame."""
W_TORQUE = slice(3, 6)
"""Torque rows of ``U`` and ``B`` (``B_tau``), body frame."""


def _frozen(a: np.ndarray) -> np.ndarray:
    a = np.array(a, dtype=float)
    a.setflags(write=False)
    return a


NU = _frozen([1.0, -1.0, -1.0, 1.0])
"""Null vector ``nu`` of each side (2.11), (2.13); read-only."""

# Table 2.1 (rotors 1-4; rotors 5-8 follow by the pair symmetry of sec. 2.2.2).
_TABLE_2_1_U = ((0.68, 0.28, 0.68), (0.68, 0.28, -0.68), (0.68, -0.28, 0.68), (0.68, -0.28, -0.68))
_TABLE_2_1_R_M = ((0.40, -0.17, 0.17), (0.40, 0.17, 0.17), (0.40, -0.17, -0.17), (0.40, 0.17, -0.17))
_TABLE_2_1_SIGMA_2_4 = (-1, -1, -1)


@dataclass(frozen=True, eq=False)
class RotorGeometry:
    """Rotor directions, positions and spin types of one 8-rotor link (sec. 2.2, Table 2.1).

    Attributes
    ----------
    directions : ndarray, shape (8, 3)
        Unit thrust directions ``u_i`` in the body frame (columns of ``B_f``, eq. 2.8).
    positions_m : ndarray, shape (8, 3)
        Rotor positions ``r_i`` from the link centre, body frame [m].
    spin : ndarray, shape (8,)
        Rotor types ``sigma_i`` in ``{+1, -1}`` (sec. 2.2.2).
    drag_ratio : float
        Thrust-to-drag-torque ratio ``gamma`` [m] of eq. (2.1); ``>= 0``.

    Arrays are copied and made read-only on construction.
    """

    directions: np.ndarray
    positions_m: np.ndarray
    spin: np.ndarray
    drag_ratio: float

    def __post_init__(self) -> None:
        u = np.array(self.directions, dtype=float)
        r = np.array(self.positions_m, dtype=float)
        s = np.array(self.spin, dtype=float)
        if u.shape != (N_ROTORS, 3) or r.shape != (N_ROTORS, 3) or s.shape != (N_ROTORS,):
            raise ValueError(
                f"RotorGeometry needs directions (8, 3), positions_m (8, 3), spin (8,); "
                f"got {u.shape}, {r.shape}, {s.shape}"
            )
        if not (np.all(np.isfinite(u)) and np.all(np.isfinite(r))):
            raise ValueError("RotorGeometry directions and positions must be finite")
        norms = np.linalg.norm(u, axis=1)
        if np.any(np.abs(norms - 1.0) > 1e-9):
            raise ValueError(f"RotorGeometry directions must be unit vectors; norms {norms}")
        if not np.all(np.abs(s) == 1.0):
            raise ValueError(f"RotorGeometry spin must be +1 or -1 for every rotor; got {s}")
        gamma = float(self.drag_ratio)
        if not (np.isfinite(gamma) and gamma >= 0.0):
            raise ValueError(f"drag_ratio gamma must be finite and >= 0; got {self.drag_ratio}")
        for name, val in (("directions", u), ("positions_m", r), ("spin", s)):
            val.setflags(write=False)
            object.__setattr__(self, name, val)
        object.__setattr__(self, "drag_ratio", gamma)

    @classmethod
    def odar(cls, drag_ratio: float = 0.02, sigma1: int = -1, x_scale: float = 1.0) -> RotorGeometry:
        """Optimised ODAR design of Table 2.1, extended to 8 rotors by the pair symmetry.

        Parameters
        ----------
        drag_ratio : float
            ``gamma`` [m] of eq. (2.1) (``~0.02`` from experiments, sec. 2.2.2).
        sigma1 : {-1, +1}
            Type of rotor 1. ``-1`` (default) is the modified design of sec. 2.4.1, which
            satisfies (2.11); ``+1`` is Table 2.1 as printed, which does not.
        x_scale : float
            Factor on the x coordinates of the rotor positions (to fit links longer than the
            thesis's bar, ``|r_x| = 0.40 m``). Keeps (2.11): the x-offset contributes
            ``r_x e_1 x sum_j nu_j u_j = 0`` to ``B_tau nu``.

        Notes
        -----
        Directions of Table 2.1 are rounded to two digits and normalised here. Rotors 5-8:
        ``u_{j+4} = u_j``, ``r_{j+4} = -r_j``, ``sigma_{j+4} = -sigma_j`` (sec. 2.2.2).
        """
        if sigma1 not in (-1, 1):
            raise ValueError(f"sigma1 must be -1 (modified design, sec. 2.4.1) or +1 (Table 2.1); got {sigma1}")
        if not (np.isfinite(x_scale) and x_scale > 0.0):
            raise ValueError(f"x_scale must be finite and > 0; got {x_scale}")
        u = np.array(_TABLE_2_1_U, dtype=float)
        u /= np.linalg.norm(u, axis=1, keepdims=True)
        r = np.array(_TABLE_2_1_R_M, dtype=float)
        r[:, 0] *= x_scale
        s = np.array((sigma1, *_TABLE_2_1_SIGMA_2_4), dtype=float)
        return cls(
            directions=np.vstack((u, u)),
            positions_m=np.vstack((r, -r)),
            spin=np.concatenate((s, -s)),
            drag_ratio=drag_ratio,
        )

    @classmethod
    def from_pairs(
        cls,
        directions: np.ndarray,
        positions_m: np.ndarray,
        spin: np.ndarray,
        drag_ratio: float = 0.02,
        x_scale: float = 1.0,
    ) -> RotorGeometry:
        """The 8-rotor geometry from rotors 1-4 by the pair symmetry of sec. 2.2.2.

        ``u_{j+4} = u_j``, ``r_{j+4} = -r_j``, ``sigma_{j+4} = -sigma_j``. ``directions`` (4, 3)
        are normalised; ``x_scale`` multiplies the x coordinates of the positions (as in
        :meth:`odar`).
        """
        u = np.array(directions, dtype=float)
        r = np.array(positions_m, dtype=float)
        s = np.array(spin, dtype=float)
        if u.shape != (N_SIDE, 3) or r.shape != (N_SIDE, 3) or s.shape != (N_SIDE,):
            raise ValueError(
                f"from_pairs needs directions (4, 3), positions_m (4, 3), spin (4,); got {u.shape}, {r.shape}, {s.shape}"
            )
        if not (np.isfinite(x_scale) and x_scale > 0.0):
            raise ValueError(f"x_scale must be finite and > 0; got {x_scale}")
        norms = np.linalg.norm(u, axis=1, keepdims=True)
        if not np.all(np.isfinite(norms)) or np.any(norms == 0.0):
            raise ValueError(f"from_pairs directions must be finite and non-zero; got {u.tolist()}")
        u = u / norms
        r[:, 0] *= x_scale
        return cls(
            directions=np.vstack((u, u)),
            positions_m=np.vstack((r, -r)),
            spin=np.concatenate((s, -s)),
            drag_ratio=drag_ratio,
        )

    def rotor_inertia_offdiag_m2(self) -> float:
        """Largest off-diagonal entry of ``sum_i r_i r_i^T`` [m^2].

        Zero when the rotors' point masses keep the body axes principal, as the link model
        (:func:`companion.skeleton.body.link_inertia`, which keeps the diagonal) assumes.
        """
        S = self.positions_m.T @ self.positions_m
        return float(max(abs(S[0, 1]), abs(S[0, 2]), abs(S[1, 2])))

    def torque_per_thrust(self) -> np.ndarray:
        """``t_i = r_i x u_i + gamma sigma_i u_i`` (eq. 2.1), shape (8, 3), body frame [m]."""
        return np.cross(self.positions_m, self.directions) + self.drag_ratio * self.spin[:, None] * self.directions

    def mapping_matrix(self) -> np.ndarray:
        """Mapping matrix ``B = [B_f; B_tau]`` of eq. (2.8), shape (6, 8): column ``i`` is ``[u_i; t_i]``."""
        return np.vstack((self.directions.T, self.torque_per_thrust().T))

    def has_null_structure(self, tol: float = 1e-9) -> bool:
        """Whether (2.11) holds with ``nu = [1, -1, -1, 1]``, to absolute tolerance ``tol``.

        Checks ``B_{f,s} nu = 0`` and ``B_{tau,s} nu = 0`` for both sides, ``B_{f,r} = B_{f,l}``
        and ``B_{tau,r} = -B_{tau,l}``.
        """
        B = self.mapping_matrix()
        Bf, Bt = B[W_FORCE], B[W_TORQUE]
        residuals = (
            Bf[:, R_SIDE] @ NU,
            Bf[:, L_SIDE] @ NU,
            Bt[:, R_SIDE] @ NU,
            Bt[:, L_SIDE] @ NU,
            Bf[:, R_SIDE] - Bf[:, L_SIDE],
            Bt[:, R_SIDE] + Bt[:, L_SIDE],
        )
        return all(float(np.max(np.abs(x))) <= tol for x in residuals)


_Vec3 = tuple[float, float, float]

#: How far a configured direction's norm may be from 1 (it is normalised on use): Table 2.1
#: prints its directions to two digits, ``|[0.68, 0.28, 0.68]| = 1.0016``.
DIRECTION_NORM_TOL = 0.01


@dataclass(frozen=True)
class RotorGeometryConfig:
    """The ``[rotors.geometry]`` table: a designed rotor geometry (thesis sec. 2.2.2, Table 2.1 layout).

    One schema for SITL scenarios and firmware configs (both load ``[rotors]`` as
    :class:`RotorParams`); ``python -m link_firmware_sim.design search`` writes it. Rotors 1-4
    only: rotors 5-8 follow by the pair symmetry ``u_{j+4} = u_j``, ``r_{j+4} = -r_j``,
    ``sigma_{j+4} = -sigma_j``. Without the table a config flies Table 2.1 (modified
    ``sigma_1 = -1`` of sec. 2.4.1), bit-identical to before.

    Attributes:
        directions: thrust directions ``u_1..u_4`` (body frame, unit; norms within
            :data:`DIRECTION_NORM_TOL` of 1 are accepted and normalised).
        positions_m: rotor positions ``r_1..r_4`` from the link centre, body frame [m].
        spin: rotor types ``sigma_1..sigma_4`` in ``{+1, -1}``.
        source: free text: where the geometry comes from (e.g. the design run).

    The drag ratio ``gamma`` is :attr:`RotorParams.drag_ratio_m`; the skeleton's
    ``rotor_x_scale`` multiplies the x coordinates as it does for Table 2.1.
    """

    directions: tuple[_Vec3, _Vec3, _Vec3, _Vec3]
    positions_m: tuple[_Vec3, _Vec3, _Vec3, _Vec3]
    spin: tuple[int, int, int, int]
    source: str = ""

    def __post_init__(self) -> None:
        u = np.array(self.directions, dtype=float)
        r = np.array(self.positions_m, dtype=float)
        if u.shape != (N_SIDE, 3) or not np.all(np.isfinite(u)):
            raise ValueError(f"directions must be 4 finite 3-vectors (rotors 1-4), got {self.directions}")
        norms = np.linalg.norm(u, axis=1)
        bad = np.flatnonzero(np.abs(norms - 1.0) > DIRECTION_NORM_TOL)
        if bad.size:
            raise ValueError(
                f"directions must be unit vectors (norm within {DIRECTION_NORM_TOL} of 1); rotor {bad[0] + 1} has "
                f"norm {norms[bad[0]]:.4g}"
            )
        if r.shape != (N_SIDE, 3) or not np.all(np.isfinite(r)):
            raise ValueError(f"positions_m must be 4 finite 3-vectors (rotors 1-4), got {self.positions_m}")
        if any(s not in (-1, 1) for s in self.spin):
            raise ValueError(f"spin must be +1 or -1 for every rotor, got {self.spin}")

    def to_geometry(self, drag_ratio: float = 0.02, x_scale: float = 1.0) -> RotorGeometry:
        """The 8-rotor :class:`RotorGeometry` (:meth:`RotorGeometry.from_pairs`)."""
        return RotorGeometry.from_pairs(self.directions, self.positions_m, self.spin, drag_ratio, x_scale)

    @classmethod
    def from_geometry(cls, geometry: RotorGeometry, source: str = "") -> RotorGeometryConfig:
        """Rotors 1-4 of ``geometry``; ``ValueError`` if rotors 5-8 do not follow the pair symmetry."""
        u, r, s = geometry.directions, geometry.positions_m, geometry.spin
        if not (np.allclose(u[L_SIDE], u[R_SIDE], atol=1e-12) and np.allclose(r[L_SIDE], -r[R_SIDE], atol=1e-12)
                and np.array_equal(s[L_SIDE], -s[R_SIDE])):
            raise ValueError("geometry does not have the pair symmetry u_{j+4} = u_j, r_{j+4} = -r_j, "
                             "sigma_{j+4} = -sigma_j of sec. 2.2.2")
        return cls(
            directions=tuple(tuple(float(x) for x in row) for row in u[R_SIDE]),
            positions_m=tuple(tuple(float(x) for x in row) for row in r[R_SIDE]),
            spin=tuple(int(x) for x in s[R_SIDE]),
            source=source,
        )


@dataclass(frozen=True)
class RotorParams:
    """Rotor/ESC parameters.

    Attributes:
        thrust_max_n: bidirectional thrust limit per rotor [N] (LASDRA: about 8 N).
        time_constant_s: first-order spin-up/down time constant ``1/k`` [s].
        esc_epsilon_n: below this thrust magnitude the ESC may reverse [N].
        min_thrust_n: smallest sustainable thrust magnitude (0: the thesis law) [N].
        restart_dwell_s: time a stopped rotor stays at zero before spinning up [s].
        drag_ratio_m: drag torque per unit thrust ``gamma`` [m] (thesis: 0.02).
        geometry: the ``[rotors.geometry]`` table (:class:`RotorGeometryConfig`), a designed
            rotor geometry; ``None`` (default): thesis Table 2.1 with ``sigma_1 = -1``.
    """

    thrust_max_n: float = 8.0
    time_constant_s: float = 0.05
    esc_epsilon_n: float = 0.05
    min_thrust_n: float = 0.0
    restart_dwell_s: float = 0.0
    drag_ratio_m: float = 0.02
    geometry: RotorGeometryConfig | None = None

    def __post_init__(self) -> None:
        require_positive(self, "thrust_max_n", "time_constant_s")
        if not 0 < self.esc_epsilon_n < self.thrust_max_n:
            raise ValueError(f"esc_epsilon_n must be in (0, thrust_max_n), got {self.esc_epsilon_n}")
        if not 0 <= self.min_thrust_n < self.thrust_max_n:
            raise ValueError(f"min_thrust_n must be in [0, thrust_max_n), got {self.min_thrust_n}")
        require_nonnegative(self, "restart_dwell_s", "drag_ratio_m")
