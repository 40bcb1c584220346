"""Typed messages of the stack (one schema for every wire) and the checks every decoder applies.

Frames and units are in the field names: ``_w`` is the world frame of the estimation core
(z-up; MAVLink's NED appears only in the MAVLink codec), ``_b`` the link body frame (x along
the link towards its right tip). Times are the link's flight-controller clock [s], or [us] in
``*_us`` fields.

The same dataclasses cross both wires: :mod:`companion.mavlink.codec` carries
:class:`LinkState` and :class:`Correction` between links and companions;
:mod:`companion.fleetnet.codec` carries all four between companions over Zenoh. Both decoders
validate with :func:`check_finite`, :func:`check_unit_quat` and :func:`check_pd` and raise
:class:`MessageError` naming the field.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from functools import cached_property

import numpy as np

from .estimation.so3 import quat_to_rotmat

__all__ = [
    "STATE_FLAG_EKF_OK",
    "STATE_FLAG_ARMED",
    "STATE_FLAG_CORRECTION_ACTIVE",
    "STATE_FLAG_GPS_FAULT",
    "MessageError",
    "check_finite",
    "check_bounded",
    "check_unit_quat",
    "check_pd",
    "check_psd",
    "LinkState",
    "Correction",
    "GroupBoundaryReport",
    "GlobalShift",
    "ChainTargets",
    "GroupPassiveLinks",
    "ChainHome",
    "NeighbourPose",
    "PoseTarget",
    "ContactTarget",
    "ExternalWrench",
]


#: Bits of the flags a link reports with its state (the dialect's SKELETON_STATE_FLAGS).
STATE_FLAG_EKF_OK = 1  # the EKF is initialised and its estimate is usable
STATE_FLAG_ARMED = 2
STATE_FLAG_CORRECTION_ACTIVE = 4  # a companion correction is applied to the control estimate
#: the link's GPS position is rejected by its EKF's gate or missing (glitch, outage): its estimate
#: is dead-reckoned; the companion keeps its state out of the chain step (corrected one way)
STATE_FLAG_GPS_FAULT = 8


class MessageError(ValueError):
    """A received message whose content cannot be used (the message names the field)."""


def check_finite(name: str, values) -> np.ndarray:
    """``values`` as a float array; :class:`MessageError` on NaN or infinity."""
    a = np.asarray(values, dtype=float)
    if not np.isfinite(a).all():
        raise MessageError(f"{name}: non-finite value")
    return a


def check_bounded(name: str, values, limit: float) -> np.ndarray:
    """``values`` as a finite float array whose Euclidean norm is at most ``limit``;
    :class:`MessageError` naming ``name`` otherwise (a corrupt or mis-scaled field)."""
    a = check_finite(name, values)
    norm = float(np.linalg.norm(a))
    if norm > limit:
        raise MessageError(f"{name}: magnitude {norm:.4g} exceeds {limit:g}")
    return a


def check_unit_quat(name: str, values) -> np.ndarray:
    """A quaternion within 1e-3 of unit norm, renormalised."""
    q = check_finite(name, values)
    n = float(np.linalg.norm(q))
    if abs(n - 1.0) > 1e-3:
        raise MessageError(f"{name}: quaternion norm {n:.6g} is not 1")
    return q / n


def check_pd(name: str, matrix) -> np.ndarray:
    """A finite symmetric positive-definite matrix (symmetrised)."""
    m = check_finite(name, matrix)
    m = 0.5 * (m + m.T)
    try:
        np.linalg.cholesky(m)
    except np.linalg.LinAlgError:
        raise MessageError(f"{name}: not positive definite") from None
    return m


def check_psd(name: str, matrix) -> np.ndarray:
    """A finite symmetric positive-semidefinite matrix (symmetrised; eigenvalues down to
    ``-1e-9`` times the largest are rounding)."""
    m = check_finite(name, matrix)
    m = 0.5 * (m + m.T)
    try:  # positive definite, the common case: a Cholesky factor exists (a third of eigvalsh's cost)
        np.linalg.cholesky(m)
        return m
    except np.linalg.LinAlgError:
        pass
    eig = np.linalg.eigvalsh(m)
    if eig[0] < -1e-9 * max(float(np.abs(eig).max()), 1e-300):
        raise MessageError(f"{name}: not positive semidefinite (eigenvalue {eig[0]:.3g})")
    return m


@dataclass(frozen=True)
class LinkState:
    """A link's EKF output as reported to its companion (paper: state and 9x9 covariance).

    Attributes:
        link: 0-based link index in the chain.
        time_s: EKF time of the estimate.
        p_w_m, v_w_m_s: position and velocity of the link centre.
        q_wxyz: body-to-world attitude.
        omega_b_rad_s: bias-corrected body rate (input of eq. 3).
        P: (9, 9) covariance of ``[dp_w; dv_w; dtheta_w]``.
    """

    link: int
    time_s: float
    p_w_m: np.ndarray
    v_w_m_s: np.ndarray
    q_wxyz: np.ndarray
    omega_b_rad_s: np.ndarray
    P: np.ndarray


@dataclass(frozen=True)
class Correction:
    """Constraint correction for one link: corrected estimate minus EKF estimate.

    The link adds it to its EKF output for control only (never to the EKF itself: paper
    sec. III-A), holding it between companion cycles and fading it out when stale.

    Attributes:
        link: 0-based link index.
        ekf_time_s: the EKF time of the state it was computed against.
        dp_w_m, dv_w_m_s: position and velocity corrections.
        dtheta_w_rad: world-frame attitude correction, ``q_corr = dq(dtheta) (x) q_ekf``.
        seq: companion cycle counter.
    """

    link: int
    ekf_time_s: float
    dp_w_m: np.ndarray
    dv_w_m_s: np.ndarray
    dtheta_w_rad: np.ndarray
    seq: int = 0


@dataclass(frozen=True)
class PoseTarget:
    """Desired motion of a link (world frame z-up; body rates in the desired body frame).

    ``omega_d_rad_s`` and ``omega_dot_d_rad_s2`` are ``w_d`` and ``wdot_d`` of eq. 1:
    ``w_d = (R_d^T dR_d/dt)^v``. ``force_ff_w_n`` (world) and ``torque_ff_b_nm`` (desired body
    frame) are the whole-chain feed-forward: what this link's rotors add to its own rigid-body
    wrench for the cable forces and the joints' passive torques
    (:meth:`companion.skeleton.dynamics.ChainModel.inverse_dynamics`); zero without it.
    """

    p_w_m: np.ndarray
    q_wxyz: np.ndarray
    v_w_m_s: np.ndarray = field(default_factory=lambda: np.zeros(3))
    a_w_m_s2: np.ndarray = field(default_factory=lambda: np.zeros(3))
    omega_d_rad_s: np.ndarray = field(default_factory=lambda: np.zeros(3))
    omega_dot_d_rad_s2: np.ndarray = field(default_factory=lambda: np.zeros(3))
    force_ff_w_n: np.ndarray = field(default_factory=lambda: np.zeros(3))
    torque_ff_b_nm: np.ndarray = field(default_factory=lambda: np.zeros(3))

    @classmethod
    def hold(cls, p_w_m, q_wxyz) -> PoseTarget:
        """Hold a pose: zero velocity, acceleration and rates."""
        return cls(np.array(p_w_m, dtype=float), np.array(q_wxyz, dtype=float))

    @cached_property
    def R_d(self) -> np.ndarray:
        """Desired rotation matrix (computed once per target)."""
        return quat_to_rotmat(self.q_wxyz)

    @cached_property
    def R_tuple(self) -> tuple:
        """``R_d`` as a row-major 9-tuple (the controller's form)."""
        return tuple(self.R_d.ravel().tolist())


@dataclass(frozen=True)
class GroupBoundaryReport:
    """What a group companion publishes after its local step (Alg. 2) for the global step (eq. 6):
    one report per part of the group. A group whose links all take part is one part; a link down
    or left out, or a joint the gate cut, splits it, and each part takes part in the global step
    as a group of its own.

    Attributes:
        group: 0-based group index in chain order.
        cycle_us: the step time on the flight-controller clock (a multiple of the step period):
            the cycle this boundary belongs to.
        left_tip_pv_w: (6,) [position m; velocity m/s] of the left tip of the part's first link.
        right_tip_pv_w: (6,) the same for the right tip of its last link.
        info_pv: (6, 6) ``Lambda_g = sum_i Pbar_i^-1``, the summed inverse [p; v] covariance.
        round_trip_us: this group's round trip (boundary published -> shift received, wall
            clock) of its previous cycle with a shift, -1 if it had none; the leader reports them.
        network_round_trip_us: the same less the leader's hold time (waiting for the other
            groups, solving): what the wire and the two Zenoh stacks took; -1 if none.
        tip_cov_pv: (12, 12) covariance of the ``[left tip; right tip]`` errors after the local
            step, or ``None``: with it every group derives the covariance of its shifted estimate
            (:mod:`companion.estimation.semi`).
        part, parts: this part's index (chain order) and how many parts the group reports this
            cycle (0 and 1: the whole group).
        joins_left, joins_right: whether the part's first link is the group's first (its left
            tip meets the previous group's right tip) and its last link the group's last; the
            global step joins two parts only across such ends of neighbouring groups.
    """

    group: int
    cycle_us: int
    left_tip_pv_w: np.ndarray
    right_tip_pv_w: np.ndarray
    info_pv: np.ndarray
    round_trip_us: int = -1
    network_round_trip_us: int = -1
    tip_cov_pv: np.ndarray | None = None
    part: int = 0
    parts: int = 1
    joins_left: bool = True
    joins_right: bool = True

    @property
    def key(self) -> tuple[int, int]:
        """``(group, part)``: what the global step's entries are keyed by."""
        return self.group, self.part


@dataclass(frozen=True)
class GlobalShift:
    """The leader's solution of eq. 6 for one cycle: one [dp; dv] shift per part of a group
    (:class:`GroupBoundaryReport`).

    Attributes:
        leader_group: 0-based group index of the companion that solved it.
        cycle_us: the cycle (see :class:`GroupBoundaryReport`).
        groups: the 0-based group of each entry solved, in chain order (groups that did not
            report in time are absent; a group split into parts is listed once per part; each run
            of joined parts is solved on its own).
        shift_pv_w: (len(groups), 6) [dp m; dv m/s] per entry.
        handover_group: a group the leader hands leadership to (a returning preferred leader),
            -1 for none; it leads from ``handover_cycle_us`` on.
        handover_cycle_us: first cycle of the new leader.
        hold_us: per entry, how long the leader held its boundary (arrival to this shift's
            publication) [us]; the group subtracts it from its round trip.
        parts: the part of its group each entry is (``()``: all 0, whole groups).
    """

    leader_group: int
    cycle_us: int
    groups: tuple[int, ...]
    shift_pv_w: np.ndarray
    handover_group: int = -1
    handover_cycle_us: int = 0
    hold_us: tuple[int, ...] = ()
    parts: tuple[int, ...] = ()

    def __post_init__(self) -> None:
        if not self.parts:
            object.__setattr__(self, "parts", (0,) * len(self.groups))

    @property
    def keys(self) -> tuple[tuple[int, int], ...]:
        """``(group, part)`` of every entry."""
        return tuple(zip(self.groups, self.parts))

    def _index(self, group: int, part: int) -> int | None:
        try:
            return self.keys.index((group, part))
        except ValueError:
            return None

    def shift_for(self, group: int, part: int = 0) -> np.ndarray | None:
        """The shift of ``group``'s ``part``, or ``None`` if it was not solved this cycle."""
        k = self._index(group, part)
        return None if k is None else self.shift_pv_w[k]

    def hold_for(self, group: int, part: int = 0) -> int | None:
        """The leader's hold time of that part's boundary [us], if listed."""
        k = self._index(group, part)
        return None if k is None or k >= len(self.hold_us) else self.hold_us[k]


@dataclass(frozen=True)
class ChainTargets:
    """The leader's CPG targets of a cycle (thesis ch. 4): every listed link's desired motion.

    Attributes:
        leader_group: 0-based group index of the companion that generated them.
        time_us: the time they are for, on the companions' common time base [us].
        seq: the leader's counter of target messages.
        links: 0-based link indices, increasing.
        p_w_m, v_w_m_s, a_w_m_s2: (len(links), 3) position, velocity and acceleration of each
            link centre (world, z up).
        q_wxyz: (len(links), 4) body-to-world attitudes.
        omega_b_rad_s, omega_dot_b_rad_s2: (len(links), 3) body rates in the desired body frame
            and their derivatives (``w_d``, ``wdot_d`` of the impedance controller, eq. 1).
        force_ff_w_n, torque_ff_b_nm: (len(links), 3) the whole-chain feed-forward of
            :class:`PoseTarget` (zero without it).
    """

    leader_group: int
    time_us: int
    seq: int
    links: tuple[int, ...]
    p_w_m: np.ndarray
    q_wxyz: np.ndarray
    v_w_m_s: np.ndarray
    a_w_m_s2: np.ndarray
    omega_b_rad_s: np.ndarray
    omega_dot_b_rad_s2: np.ndarray
    force_ff_w_n: np.ndarray
    torque_ff_b_nm: np.ndarray

    @classmethod
    def of(cls, leader_group: int, time_us: int, seq: int, links, targets: list[PoseTarget]) -> ChainTargets:
        """The targets of ``links`` (one :class:`PoseTarget` each, in that order)."""
        def rows(name: str) -> np.ndarray:
            return np.array([getattr(t, name) for t in targets], dtype=float)

        return cls(leader_group, time_us, seq, tuple(links), rows("p_w_m"), rows("q_wxyz"), rows("v_w_m_s"),
                   rows("a_w_m_s2"), rows("omega_d_rad_s"), rows("omega_dot_d_rad_s2"), rows("force_ff_w_n"),
                   rows("torque_ff_b_nm"))

    def target(self, k: int) -> PoseTarget:
        """The :class:`PoseTarget` of the ``k``-th listed link."""
        return PoseTarget(self.p_w_m[k], self.q_wxyz[k], self.v_w_m_s[k], self.a_w_m_s2[k], self.omega_b_rad_s[k],
                          self.omega_dot_b_rad_s2[k], self.force_ff_w_n[k], self.torque_ff_b_nm[k])


@dataclass(frozen=True)
class GroupPassiveLinks:
    """Which of a group's links its companion takes to have their rotors off (carried: the
    whole-chain feed-forward gives their weight to their neighbours), so that the companion of a
    neighbouring group carries them too: a dead link at a group's end hangs on a link of the next
    group. Published when the set changes and each second.

    Attributes:
        group: 0-based group index of the companion that publishes it.
        time_us: when, on the companions' common time base [us] (the publisher's cycle clock).
        links: 0-based chain indices of the group's own links taken as passive, increasing (empty:
            none).
    """

    group: int
    time_us: int
    links: tuple[int, ...]


@dataclass(frozen=True)
class ChainHome:
    """Where a distributed chain flies its trajectory from: the chain's middle point in its links'
    frame at the start (the first step's estimate) less the anchor all groups share. The group
    that holds the chain's middle link measures it; every group that holds a home repeats it each
    second, so that a companion that starts later flies from the same home.

    Attributes:
        group: 0-based group index of the companion that publishes it.
        time_us: when, on the companions' common time base [us] (the publisher's cycle clock).
        offset_w_m: (3,) the chain's estimated middle at the start less the anchor [m, world].
    """

    group: int
    time_us: int
    offset_w_m: np.ndarray


@dataclass(frozen=True)
class NeighbourPose:
    """A camera on chain link ``observer`` sees the marker on the neighbouring link ``observed``:
    the marker's pose in the camera frame with its covariance, and where the camera and the
    marker sit on their links, so that the companion that takes it needs no camera configuration
    of its own (published by the vision consumer, :mod:`companion.vision`).

    Attributes:
        observer: 0-based chain index of the link that carries the camera.
        observed: 0-based chain index of the link that carries the marker (a neighbour: the
            indices differ by one).
        t_capture_s: when the frame was captured, on the observing link's flight-controller clock [s].
        seq: the camera's frame number.
        q_cm_wxyz: marker to camera rotation (unit quaternion).
        t_cm_m: the marker's centre in the camera frame [m].
        cov_c: (6, 6) covariance of ``[dtheta_c (rad); dt_c (m)]``, camera frame.
        camera_pos_b_m, q_bc_wxyz: the camera on the observer (its centre in the body frame [m],
            camera to body rotation).
        marker_pos_b_m, q_bm_wxyz: the marker on the observed link (its centre in the body frame
            [m], marker to body rotation).
    """

    observer: int
    observed: int
    t_capture_s: float
    seq: int
    q_cm_wxyz: np.ndarray
    t_cm_m: np.ndarray
    cov_c: np.ndarray
    camera_pos_b_m: np.ndarray
    q_bc_wxyz: np.ndarray
    marker_pos_b_m: np.ndarray
    q_bm_wxyz: np.ndarray


@dataclass(frozen=True)
class ContactTarget:
    """Commanded contact of the hybrid pose/wrench controller (thesis sec. 2.3.3): the body point
    ``contact_b_m`` pressed along the world unit normal ``normal_w`` (pointing into the surface)
    with ``force_n`` [N] (>= 0). Sent over MAVLink as MAV_CMD_SKELETON_SET_CONTACT
    (:func:`companion.mavlink.codec.encode_contact_command`)."""

    normal_w: np.ndarray
    contact_b_m: np.ndarray
    force_n: float

    def __post_init__(self) -> None:
        n = np.asarray(self.normal_w, dtype=float)
        if n.shape != (3,) or not np.isfinite(n).all() or abs(np.linalg.norm(n) - 1.0) > 1e-6:
            raise ValueError(f"normal_w must be a unit 3-vector, got {self.normal_w!r}")
        r = np.asarray(self.contact_b_m, dtype=float)
        if r.shape != (3,) or not np.isfinite(r).all():
            raise ValueError(f"contact_b_m must be a finite 3-vector, got {self.contact_b_m!r}")
        if not (np.isfinite(self.force_n) and self.force_n >= 0):
            raise ValueError(f"force_n must be finite and non-negative, got {self.force_n!r}")


@dataclass(frozen=True)
class ExternalWrench:
    """A link's momentum-observer estimate of the external wrench (thesis sec. 2.3.3), as streamed
    in SKELETON_EXTERNAL_WRENCH.

    Attributes:
        link: 0-based link index.
        time_s: flight-controller time of the estimate.
        force_w_n: external force at the link centre, world frame [N].
        torque_b_nm: external torque, body frame [N m].
        contact_force_n: the observer's force along the commanded contact normal ``lambda_c^``
            [N] (what the link applies to the surface); NaN without a commanded contact.
        contact_force_cmd_n: the commanded contact force ``lambda_d`` [N]; NaN without one.
    """

    link: int
    time_s: float
    force_w_n: np.ndarray
    torque_b_nm: np.ndarray
    contact_force_n: float = float("nan")
    contact_force_cmd_n: float = float("nan")
