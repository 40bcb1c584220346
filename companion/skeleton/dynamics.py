"""The chain's multibody model, built with pinocchio: forward kinematics and whole-chain inverse dynamics.

:class:`ChainModel` is the same tree as the simulator's MuJoCo model: link 1 on a free-flyer
joint at its centre, link ``i+1`` on a spherical joint at link ``i``'s right tip (the cable),
each link's mass and inertia from :func:`~companion.skeleton.body.link_inertia`, a frame at each
link's centre. Generalised coordinates (pinocchio's conventions): ``q`` = link 1's position and
attitude (xyzw) then each joint's relative attitude ``R_{i}^T R_{i+1}``; ``v`` = link 1's velocity
in its own frame and body rate, then each joint's relative rate in the child frame.

Inverse dynamics (thesis sec. 3.2's Newton-Euler chain, the feed-forward of the targets): every
link's rotors must produce its own rigid-body wrench (what eq. 1's feed-forward already gives)
plus what the joints take from or give to it: the cable force ``f_j`` at each joint and the
cable's passive torque (stiffness and damping of the compliant joint at the desired relative
motion). The joint forces are an internal-force redundancy (thesis sec. 6, "optimal wrench
allocation for a group of links"); :meth:`ChainModel.inverse_dynamics` chooses them to minimise
``sum_i |F_i|^2 + |M_i / l|^2`` over the links' rotor wrenches (``l`` the half link length), so a
link that needs more gets help from its neighbours through the cables. pinocchio's RNEA with
those rotor wrenches as external forces (``inverse_dynamics(..., check=True)``; the feed-forward
at the target rate skips it) gives the force each cable carries (its spatial force across the
joint) and checks the solution: the free-flyer's generalised force is zero and each joint's is
the passive torque.

pinocchio is an optional dependency (``pip install .[dynamics]``): importing this module needs it.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import pinocchio as pin

from companion.kernels.dynamics import feedforward_kernel, passive_torques_kernel
from companion.kernels.jit import ENABLED as _COMPILED
from companion.estimation.so3 import cross, quat_to_rotmat, rotmat_to_quat, skew
from companion.messages import PoseTarget

from .body import GRAVITY_M_S2, SkeletonConfig, link_inertia
from .rotors import RotorGeometry

__all__ = ["ChainModel", "ChainDynamics", "PASSIVE_WEIGHT"]

#: Weight of a passive link's rotor wrench in the joint-force least squares (relative to 1 for
#: the others): its wrench is then zero to about 1e-6 of the load wherever the joints can carry it.
PASSIVE_WEIGHT = 1e3


@dataclass(frozen=True)
class ChainDynamics:
    """Inverse dynamics of one chain motion (world frame unless noted).

    Attributes:
        force_ff_w_n, torque_ff_w_nm: (n, 3) what each link's rotors must add to its own
            rigid-body wrench (eq. 1's feed-forward) for the chosen cable forces and the joints'
            passive torques, at the link centre.
        joint_force_w_n: (n-1, 3) force on link ``j+1`` from link ``j`` at their joint.
        joint_torque_w_nm: (n-1, 3) passive torque of joint ``j`` on link ``j+1``.
        rotor_wrench_w: (n, 6) each link's whole rotor wrench [force; torque about its centre].
        rnea_tau: pinocchio's RNEA generalised force with those rotor wrenches (free flyer ~0,
            each joint its passive torque in the child frame); ``None`` unless asked for
            (``check=True``).
    """

    force_ff_w_n: np.ndarray
    torque_ff_w_nm: np.ndarray
    joint_force_w_n: np.ndarray
    joint_torque_w_nm: np.ndarray
    rotor_wrench_w: np.ndarray
    rnea_tau: np.ndarray | None


class ChainModel:
    """See the module docstring. ``skeleton``: the chain (links, masses, joint stiffness and damping)."""

    def __init__(self, skeleton: SkeletonConfig, geometry: RotorGeometry | None = None):
        geometry = geometry if geometry is not None else RotorGeometry.odar(x_scale=skeleton.rotor_x_scale)
        self.skeleton = skeleton
        self.n = n = skeleton.n_links
        self.d = np.array([0.5 * skeleton.link_length_m, 0.0, 0.0])
        self.inertia = link_inertia(skeleton, geometry)
        self.stiffness = skeleton.joint_stiffness_nm_rad
        self.damping = skeleton.joint_damping_nms_rad
        model = pin.Model()
        model.gravity = pin.Motion(np.array([0.0, 0.0, -GRAVITY_M_S2]), np.zeros(3))
        mass, J = self.inertia.mass_kg, np.diag(self.inertia.inertia_kgm2)
        parent = 0
        self.frames = []
        for i in range(n):
            if i == 0:
                joint = model.addJoint(0, pin.JointModelFreeFlyer(), pin.SE3.Identity(), "link1_root")
                com = np.zeros(3)
            else:
                # the joint sits at the parent's right tip: +d from the centre of link 1, +2d from a left tip
                offset = self.d if i == 1 else 2.0 * self.d
                joint = model.addJoint(parent, pin.JointModelSpherical(), pin.SE3(np.eye(3), offset),
                                       f"joint{i}_{i + 1}")
                com = self.d
            model.appendBodyToJoint(joint, pin.Inertia(mass, com, J), pin.SE3.Identity())
            self.frames.append(model.addFrame(pin.Frame(f"link{i + 1}", joint, 0, pin.SE3(np.eye(3), com),
                                                        pin.FrameType.OP_FRAME)))
            parent = joint
        self.model = model
        self.data = model.createData()
        self.joints = list(range(1, n + 1))  # pinocchio joint ids of links 1..n
        #: the last :meth:`inverse_dynamics` result (its cable forces are logged)
        self.last: ChainDynamics | None = None

    # -- coordinates -------------------------------------------------------------------------------------
    def coordinates(self, p_w, R_wl, v_w=None, omega_b=None, a_w=None, omega_dot_b=None):
        """``(q, v, a)`` of a chain whose links have centres ``p_w`` (n, 3) (only link 1's is used:
        the joints place the others), attitudes ``R_wl`` (n, 3, 3), centre velocities ``v_w`` and
        accelerations ``a_w`` (world; link 1's is used), body rates ``omega_b`` and their
        derivatives ``omega_dot_b``. Missing rates and accelerations are zero."""
        n = self.n
        R = np.asarray(R_wl, dtype=float)
        zeros = np.zeros((n, 3))
        w = zeros if omega_b is None else np.asarray(omega_b, dtype=float)
        wd = zeros if omega_dot_b is None else np.asarray(omega_dot_b, dtype=float)
        v0 = np.zeros(3) if v_w is None else np.asarray(v_w, dtype=float)[0]
        a0 = np.zeros(3) if a_w is None else np.asarray(a_w, dtype=float)[0]
        q = np.empty(self.model.nq)
        v = np.empty(self.model.nv)
        a = np.empty(self.model.nv)
        q[0:3] = np.asarray(p_w, dtype=float)[0]
        R_rel = [R[i - 1].T @ R[i] for i in range(1, n)]
        quats = rotmat_to_quat(np.stack([R[0], *R_rel]))  # link 1's attitude, then each joint's
        q[3:7] = _xyzw(quats[0])
        v_local = R[0].T @ v0
        v[0:3], v[3:6] = v_local, w[0]
        a[0:3], a[3:6] = R[0].T @ a0 - cross(w[0], v_local), wd[0]
        for i in range(1, n):
            Rrel = R_rel[i - 1]
            w_rel = w[i] - Rrel.T @ w[i - 1]
            qi, vi = 7 + 4 * (i - 1), 6 + 3 * (i - 1)
            q[qi:qi + 4] = _xyzw(quats[i])
            v[vi:vi + 3] = w_rel
            a[vi:vi + 3] = wd[i] + cross(w_rel, Rrel.T @ w[i - 1]) - Rrel.T @ wd[i - 1]
        return q, v, a

    def forward(self, q, v=None, a=None):
        """Every link centre's ``(p_w (n,3), R_wl (n,3,3), v_w (n,3), omega_b (n,3), a_w (n,3),
        omega_dot_b (n,3))`` for generalised ``q, v, a`` (pinocchio's forward kinematics)."""
        model, data = self.model, self.data
        v = np.zeros(model.nv) if v is None else v
        a = np.zeros(model.nv) if a is None else a
        pin.forwardKinematics(model, data, q, v, a)
        pin.updateFramePlacements(model, data)
        out = [np.empty((self.n, 3)), np.empty((self.n, 3, 3))] + [np.empty((self.n, 3)) for _ in range(4)]
        for i, f in enumerate(self.frames):
            M = data.oMf[f]
            out[0][i], out[1][i] = M.translation, M.rotation
            vel = pin.getFrameVelocity(model, data, f, pin.LOCAL)
            acc = pin.getFrameClassicalAcceleration(model, data, f, pin.LOCAL)
            out[2][i] = M.rotation @ vel.linear
            out[3][i] = vel.angular
            out[4][i] = M.rotation @ acc.linear
            out[5][i] = acc.angular
        return tuple(out)

    # -- inverse dynamics ------------------------------------------------------------------------------
    def inverse_dynamics(self, targets: list[PoseTarget], check: bool = False, passive=()) -> ChainDynamics:
        """The rotor wrenches and cable forces of the chain following ``targets`` (one per link,
        constraint-consistent; see the module docstring). ``check``: also pinocchio's RNEA with
        those rotor wrenches (``rnea_tau``, and :meth:`cable_forces_rnea` after it). ``passive``:
        0-based links whose rotors are off (a link that lost power or was disarmed in flight):
        their rotor wrench is held at zero (weighted :data:`PASSIVE_WEIGHT` times the others in
        the least squares), so the joints carry them and their neighbours' rotors carry the joints.
        Where the motion cannot be followed with such a link passive (an end link held level by
        one ball joint) the result is the least-squares compromise and ``rotor_wrench_w`` says
        what that link would still need."""
        return self.solve(*self.stack(targets), check=check, passive=passive)

    @staticmethod
    def stack(targets: list[PoseTarget]) -> tuple[np.ndarray, ...]:
        """``(p, R, v, w, acc, wd)`` of ``targets``, each stacked over the links, as :meth:`solve` takes them."""
        return (np.stack([t.p_w_m for t in targets]), quat_to_rotmat(np.stack([t.q_wxyz for t in targets])),
                np.stack([t.v_w_m_s for t in targets]), np.stack([t.omega_d_rad_s for t in targets]),
                np.stack([t.a_w_m_s2 for t in targets]), np.stack([t.omega_dot_d_rad_s2 for t in targets]))

    def solve(self, p, R, v, w, acc, wd, check: bool = False, passive=(),
              compiled: bool | None = None) -> ChainDynamics:
        """:meth:`inverse_dynamics` of the links' centres ``p``, attitudes ``R`` (n, 3, 3), centre
        velocities ``v`` and accelerations ``acc`` (world), body rates ``w`` and their derivatives
        ``wd`` (each (n, 3)). The numpy code below is the specification; ``compiled`` (default:
        when numba is installed) runs it as :func:`companion.kernels.dynamics.passive_torques_kernel`
        and :func:`~companion.kernels.dynamics.feedforward_kernel` (the same numbers to 1e-12:
        ``tests/unit/test_fast_paths.py``)."""
        n = self.n
        m = self.inertia.mass_kg
        compiled = _COMPILED if compiled is None else compiled
        # passive joint torques on the child (compliant cable: stiffness and damping) at the joint's
        # relative attitude R_j^T R_{j+1} and relative rate in the child frame (the generalised
        # coordinates of :meth:`coordinates`)
        tau_j = np.zeros((max(n - 1, 0), 3))
        if compiled:
            R = np.ascontiguousarray(R, dtype=float)
            passive_torques_kernel(R, np.ascontiguousarray(w, dtype=float), float(self.stiffness),
                                   float(self.damping), tau_j)
        else:
            for j in range(n - 1):
                Rrel = R[j].T @ R[j + 1]
                w_rel = w[j + 1] - Rrel.T @ w[j]
                tau_j[j] = R[j + 1] @ (-self.stiffness * pin.log3(Rrel) - self.damping * w_rel)
        if compiled:
            weights = np.ones(n)
            if len(passive):
                weights[list(passive)] = PASSIVE_WEIGHT
            force_ff, torque_ff, F, rotor = np.zeros((n, 3)), np.zeros((n, 3)), np.zeros((n - 1, 3)), np.empty((n, 6))
            motion = tuple(np.ascontiguousarray(x, dtype=float) for x in (p, w, wd, acc))
            link = (self.d, np.asarray(self.inertia.inertia_kgm2, dtype=float), float(m), GRAVITY_M_S2, 1.0 / self.d[0])
            feedforward_kernel(motion, np.ascontiguousarray(R, dtype=float), tau_j, link, weights,
                               (force_ff, torque_ff, F, rotor))
        else:
            J = np.diag(self.inertia.inertia_kgm2)
            # each link's own rigid-body wrench (what eq. 1's feed-forward produces), world, about its centre
            own_f = m * (acc + np.array([0.0, 0.0, GRAVITY_M_S2]))
            own_m = np.einsum("nij,nj->ni", R, np.einsum("ij,nj->ni", J, wd) + cross(w, np.einsum("ij,nj->ni", J, w)))
            # joint points and the moment arms to each centre
            x = p[:-1] + np.einsum("nij,j->ni", R[:-1], self.d)
            F = self._share(own_f, own_m, p, x, tau_j, passive)
            add_f, add_m = self._joint_wrench(F, tau_j, p, x)
            rotor = np.concatenate([own_f - add_f, own_m - add_m], axis=1)
            force_ff, torque_ff = -add_f, -add_m
        rnea = self._rnea(*self.coordinates(p, R, v, w, acc, wd), rotor, R, p) if check else None
        self.last = ChainDynamics(force_ff, torque_ff, F, tau_j, rotor, rnea)
        return self.last

    def _joint_wrench(self, F, tau_j, p, x):
        """The force and moment (about each centre) the joints exert on every link: joint ``j``
        pushes link ``j+1`` with ``F_j`` (and the passive torque) and link ``j`` with the opposite."""
        n = self.n
        f = np.zeros((n, 3))
        mom = np.zeros((n, 3))
        if n > 1:
            f[1:] += F
            f[:-1] -= F
            mom[1:] += cross(x - p[1:], F) + tau_j
            mom[:-1] -= cross(x - p[:-1], F) + tau_j
        return f, mom

    def _share(self, own_f, own_m, p, x, tau_j, passive=()) -> np.ndarray:
        """The joint forces minimising the links' rotor wrenches (weighted least squares; the
        rotor wrenches of ``passive`` links weigh :data:`PASSIVE_WEIGHT` times more)."""
        n = self.n
        if n < 2:
            return np.zeros((0, 3))
        scale = 1.0 / self.d[0]  # moments weighed per half link length, like forces
        A = np.zeros((n, 6, n - 1, 3))
        j = np.arange(n - 1)
        A[j + 1, 0:3, j] = np.eye(3)
        A[j + 1, 3:6, j] = scale * skew(x - p[1:])
        A[j, 0:3, j] = -np.eye(3)
        A[j, 3:6, j] = -scale * skew(x - p[:-1])
        A = A.reshape(6 * n, 3 * (n - 1))
        _, tau_m = self._joint_wrench(np.zeros((n - 1, 3)), tau_j, p, x)
        b = np.concatenate([own_f, scale * (own_m - tau_m)], axis=1).reshape(-1)
        if len(passive):
            w = np.ones((n, 6))
            w[list(passive)] = PASSIVE_WEIGHT
            A, b = A * w.reshape(-1, 1), b * w.reshape(-1)
        # rotor wrench = b - A F: the minimum-norm rotor wrenches are the least-squares F
        F, *_ = np.linalg.lstsq(A, b, rcond=None)
        return F.reshape(n - 1, 3)

    def _rnea(self, q, v, a, rotor_w, R, p) -> np.ndarray:
        """pinocchio's RNEA with the rotor wrenches as external forces (in each joint's frame)."""
        model, data = self.model, self.data
        pin.forwardKinematics(model, data, q)
        fext = pin.StdVec_Force()
        fext.append(pin.Force.Zero())
        for i, jid in enumerate(self.joints):
            M = data.oMi[jid]
            f_local = M.rotation.T @ rotor_w[i, :3]
            # moment about the joint origin: the force acts at the link centre
            m_w = rotor_w[i, 3:] + cross(p[i] - M.translation, rotor_w[i, :3])
            fext.append(pin.Force(f_local, M.rotation.T @ m_w))
        return np.array(pin.rnea(model, data, q, v, a, fext))

    def cable_forces_rnea(self) -> np.ndarray:
        """(n-1, 3) world force across each joint from the last RNEA, that of the last
        ``inverse_dynamics(..., check=True)`` (pinocchio's ``data.f``: the parent's force on the
        child's subtree)."""
        out = np.empty((self.n - 1, 3))
        for j, jid in enumerate(self.joints[1:]):
            out[j] = self.data.oMi[jid].rotation @ self.data.f[jid].linear
        return out


def _xyzw(q_wxyz: np.ndarray) -> np.ndarray:
    return np.array([q_wxyz[1], q_wxyz[2], q_wxyz[3], q_wxyz[0]])
