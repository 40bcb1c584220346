"""The companion's target source: every link's pose target for take-off, hover, the paper's bending motion, CPG motion
and a formation carrying a slung load.

A chain posture is a set of link attitudes plus the position of the chain's middle point;
link centres follow from the joints (``p_{i+1} = p_i + R_i d + R_{i+1} d``), so the targets
themselves satisfy the constraint of eq. 3. Phases:

* before ``takeoff_start_s``: hold the start pose;
* take-off: the middle point rises to ``takeoff_altitude_m`` along a quintic (continuous
  acceleration) over ``takeoff_duration_s``;
* ``kind = "hover"``: hold; ``kind = "bend"``: from ``bend_start_s`` the chain bends forwards
  and backwards (paper sec. V): link ``i`` pitches by ``theta(t) * s_i`` with ``s_i`` running
  linearly from -1 (first link) to +1 (last link), ``theta(t) = A r(t) sin(2 pi (t - t_b) / T)``
  with a quintic amplitude ramp ``r``. Positive ``theta`` lowers both ends.

``kind = "figure8"``: hover, then from ``figure8_start_s`` the chain's middle point draws a
horizontal figure eight (Gerono's lemniscate: ``A [sin(w s), sin(2 w s) / 2, 0]`` in the yaw frame,
``w = 2 pi / figure8_period_s``, the amplitude ramped in over one period by the quintic) at the
fixed attitude (``pitch_deg``, ``yaw_deg``): the SE(3) tracking test of thesis sec. 2.5.2 (there a
circle) with a 45 deg pitch.

``kind = "rest"``: the chain lies where it starts and is never armed (thesis sec. 3.5.2, the
static estimation test); the metrics window opens at ``takeoff_start_s`` (EKF settling).

``kind = "cpg"``: take-off and hover as above, then from ``motion.start_s`` the leader's CPG
motion generation (thesis ch. 4, :class:`CpgChainTrajectory`): the commands of the scenario's
``[motion]`` section through the inverse model, the CPG and the expected physics, whose body
starts at the hovering chain's centre with its yaw.

``kind = "formation"``: unjoined vehicles (one per link) carry the ``[load]`` box on cables
around the ``[load.formation]`` circle (:class:`~companion.load.formation.FormationTrajectory`:
the formation's own start pose, hold, ramp and yaw, each target with its cable's feed-forward
force). There is no take-off: the targets hold the formation's start pose from the first
targets on, so the vehicles start there, hovering. The chain's settings here do not apply
(``feedforward`` must be false), but the end of the take-off (``takeoff_start_s +
takeoff_duration_s``) still opens the metrics window.

``anchor_w_m``: where the chain's middle point starts (the trajectory's origin, in the links'
frame). Distributed companions need one anchor they all share (the SITL gives every companion
where the simulated chain starts).

``home``: where the companions fly the trajectory. ``"estimate"`` (the default): from where the
chain's own estimate puts its middle while it rests before its take-off (measured at every target
until ``takeoff_start_s`` less 0.2 s, the estimate settling), as a flight controller flies from
its home: the trajectory is shifted by that point less ``anchor_w_m`` (the anchor names where the
chain was set down), so a position error that every receiver shares at the start (``m8``'s
metres) shifts the targets with it instead of flying the chain that far off them, into the ground
when it is vertical; without an anchor the trajectory starts at that point (measured once). ``"anchor"``: at
``anchor_w_m`` in the links' frame, as it is given (a surveyed point; ``"estimate"`` without an
anchor). Distributed companions each see only their own links: the group that holds the middle
link measures the home and the others fly the one it publishes (:mod:`companion.engine.home`).
``kind = "formation"`` flies its own start pose.

All links share the chain's yaw and base pitch (``yaw_deg``, ``pitch_deg``). Velocities,
accelerations and body rates are central differences of the smooth pose function.

``feedforward = true``: every target also carries the whole-chain feed-forward wrench of the
chain's multibody model (:meth:`companion.skeleton.dynamics.ChainModel.inverse_dynamics`:
cable forces shared for the smallest rotor wrenches, the joints' passive torques); it needs
pinocchio (``pip install .[dynamics]``).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace
from typing import Literal

import numpy as np

from .kernels.jit import ENABLED as _COMPILED
from .kernels.trajectory import trajectory_kernel
from .configfile import require_nonnegative, require_positive
from .estimation.so3 import quat_from_euler_zyx, quat_mul, quat_to_rotmat, rotmat_to_quat, rotmat_tuple
from .load.config import LoadConfig
from .load.formation import FormationTrajectory
from .messages import PoseTarget
from .motion.expected_physics import BodyState
from .motion.generator import LinkTargets, MotionGenerator
from .motion.inverse import InverseModel
from .motion.schedule import MotionCommand, MotionConfig, desired_motion
from .skeleton.body import SkeletonConfig
from .skeleton.kinematics import chain_offsets, middle_offset

__all__ = ["TrajectoryConfig", "ChainTrajectory", "CpgChainTrajectory", "make_trajectory", "planned_positions",
           "in_truth_frame", "smoothstep5"]


def smoothstep5(s: float) -> float:
    """Quintic 0 -> 1 on [0, 1] with zero first and second derivatives at both ends."""
    s = min(max(s, 0.0), 1.0)
    return s * s * s * (10.0 + s * (-15.0 + 6.0 * s))


@dataclass(frozen=True)
class TrajectoryConfig:
    kind: Literal["hover", "bend", "rest", "cpg", "figure8", "formation"] = "hover"
    takeoff_start_s: float = 1.0
    takeoff_duration_s: float = 5.0
    takeoff_altitude_m: float = 2.0
    yaw_deg: float = 0.0
    pitch_deg: float = 0.0
    bend_start_s: float = 15.0
    bend_amplitude_deg: float = 25.0
    bend_period_s: float = 10.0
    bend_ramp_s: float = 5.0
    anchor_w_m: tuple[float, float, float] | None = None
    home: Literal["estimate", "anchor"] = "estimate"
    feedforward: bool = False
    figure8_start_s: float = 10.0
    figure8_amplitude_m: float = 0.5
    figure8_period_s: float = 10.0

    def __post_init__(self) -> None:
        require_nonnegative(self, "takeoff_start_s", "takeoff_duration_s", "bend_start_s", "bend_ramp_s",
                            "figure8_start_s", "figure8_amplitude_m")
        require_positive(self, "bend_period_s", "figure8_period_s")
        if not 0 <= self.bend_amplitude_deg < 90:
            raise ValueError(f"bend_amplitude_deg must be in [0, 90), got {self.bend_amplitude_deg}")
        if self.kind == "formation" and self.feedforward:
            raise ValueError("feedforward must be false with kind 'formation': the chain's feed-forward does not "
                             "apply to unjoined vehicles (the formation's targets carry their cables' own)")

    @property
    def takeoff_end_s(self) -> float:
        return self.takeoff_start_s + (0.0 if self.kind == "rest" else self.takeoff_duration_s)


def with_feedforward(targets: list[PoseTarget], model, passive=frozenset(), arrays=None) -> list[PoseTarget]:
    """``targets`` with the whole-chain feed-forward of ``model`` (a
    :class:`~companion.skeleton.dynamics.ChainModel`; ``None``: unchanged); ``passive``: links
    (0-based) whose rotors are off, carried by their neighbours. A carried link's own target
    keeps the feed-forward of the chain with every link flying: when its rotors come back it is
    to lift itself (a feed-forward that cancelled its weight would keep its rotors stopped, and
    they would restart from standstill once more when it ends). ``arrays``: the targets' ``(p, R,
    v, w, acc, wd)`` stacked over the links, when the caller has them (else
    :meth:`~companion.skeleton.dynamics.ChainModel.stack` forms them)."""
    if model is None:
        return targets
    arrays = model.stack(targets) if arrays is None else arrays
    return feedforward_targets([(t.p_w_m, t.q_wxyz, t.v_w_m_s, t.a_w_m_s2, t.omega_d_rad_s, t.omega_dot_d_rad_s2)
                                for t in targets], model, passive, arrays)


def feedforward_targets(motion, model, passive, arrays) -> list[PoseTarget]:
    """Each link's :class:`PoseTarget` with the whole-chain feed-forward of ``model`` (see
    :func:`with_feedforward`), built once from ``motion``: per link ``(p, q, v, a, w, w_dot)``,
    and ``arrays``: the same ``(p, R, v, w, acc, wd)`` stacked over the links."""
    flying = model.solve(*arrays) if passive else None
    dyn = model.solve(*arrays, passive=passive)
    out = []
    for i, (p, q, v, a, w, w_dot) in enumerate(motion):
        d = flying if i in passive else dyn
        R_tuple = rotmat_tuple(q.tolist())
        R_d = np.array(R_tuple).reshape(3, 3)
        target = PoseTarget(p, q, v, a, w, w_dot, force_ff_w_n=d.force_ff_w_n[i],
                            torque_ff_b_nm=R_d.T @ d.torque_ff_w_nm[i])
        target.__dict__.update(R_d=R_d, R_tuple=R_tuple)  # (its cached properties, computed here anyway)
        out.append(target)
    return out


def planned_positions(log: dict[str, np.ndarray]) -> np.ndarray:
    """The targets of a run's log (``p_target``, (..., n, 3)) in the frame of its truth: the
    companion flies the trajectory from its home, in the links' frame (the trajectory shifted by
    ``home_offset_w_m``, where the links' estimate put the chain at the start less its anchor,
    which in SITL is where the chain stands); less that offset, it is the trajectory from the true
    start, what the truth is judged against and shown beside. A log without the offset is taken
    as logged."""
    return in_truth_frame(log, log["p_target"])


def in_truth_frame(log: dict[str, np.ndarray], p_w_m: np.ndarray) -> np.ndarray:
    """Positions ``p_w_m`` (..., 3) of the links' frame (an estimate, a target) in the frame of the
    truth of the run whose log is ``log``: less its ``home_offset_w_m`` (taken as zero when the
    log has none)."""
    home = log.get("home_offset_w_m")
    return p_w_m if home is None else p_w_m - np.asarray(home, dtype=float)


class ChainTrajectory:
    """Per-link :class:`PoseTarget` of an ``n``-link chain as a function of time (``dynamics``: the
    chain model whose feed-forward the targets carry, or ``None``)."""

    def __init__(self, cfg: TrajectoryConfig, n_links: int, link_length_m: float, start_center_w_m, h_s: float = 1e-3,
                 dynamics=None):
        self.cfg = cfg
        self.n = n_links
        self.d = np.array([0.5 * link_length_m, 0.0, 0.0])
        self.start = np.asarray(start_center_w_m, dtype=float)
        self.h = h_s
        self.dynamics = dynamics
        self._base_q = quat_from_euler_zyx(math.radians(cfg.yaw_deg), math.radians(cfg.pitch_deg), 0.0)
        self._share = np.linspace(-1.0, 1.0, n_links) if n_links > 1 else np.zeros(1)

    def bend_angle_rad(self, t: float) -> float:
        c = self.cfg
        if c.kind != "bend" or t <= c.bend_start_s:
            return 0.0
        ramp = smoothstep5((t - c.bend_start_s) / c.bend_ramp_s) if c.bend_ramp_s > 0 else 1.0
        return math.radians(c.bend_amplitude_deg) * ramp * math.sin(2.0 * math.pi * (t - c.bend_start_s) / c.bend_period_s)

    def center_w_m(self, t: float) -> np.ndarray:
        c = self.cfg
        if c.kind == "rest":
            return self.start.copy()
        s = smoothstep5((t - c.takeoff_start_s) / c.takeoff_duration_s) if c.takeoff_duration_s > 0 else float(t >= c.takeoff_start_s)
        target = self.start.copy()
        target[2] = self.start[2] + s * (c.takeoff_altitude_m - self.start[2])
        if c.kind == "figure8" and t > c.figure8_start_s:
            tau = t - c.figure8_start_s
            w = 2.0 * math.pi / c.figure8_period_s
            amp = c.figure8_amplitude_m * smoothstep5(tau / c.figure8_period_s)
            x, y = amp * math.sin(w * tau), 0.5 * amp * math.sin(2.0 * w * tau)
            cy, sy = math.cos(math.radians(c.yaw_deg)), math.sin(math.radians(c.yaw_deg))
            target[0] += cy * x - sy * y
            target[1] += sy * x + cy * y
        return target

    def pose(self, t: float) -> tuple[np.ndarray, np.ndarray]:
        """Link centres (n, 3) and attitudes (n, 4) at ``t``."""
        p, q, _ = self.poses((t,))
        return p[0], q[0]

    def poses(self, times) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """:meth:`pose` at several times at once: centres (k, n, 3), attitudes (k, n, 4) and their
        rotation matrices (k, n, 3, 3) (one vectorised evaluation: :meth:`targets` needs five)."""
        zeros = np.zeros((len(times), self.n))
        theta = np.array([self.bend_angle_rad(t) for t in times])
        bends = quat_from_euler_zyx(zeros, theta[:, None] * self._share, zeros)
        q = quat_mul(self._base_q, bends)
        R = quat_to_rotmat(q)
        r, _ = chain_offsets(R, None, self.d)
        # Anchor the chain's middle point (middle link centre, or middle joint) at the centre.
        center = np.array([self.center_w_m(t) for t in times])
        return r + (center - middle_offset(r, R, self.d))[:, None, :], q, R

    def target_arrays(self, t: float, compiled: bool | None = None) -> tuple[np.ndarray, ...]:
        """Every link's ``(p, q, R, v, a, w, w_dot)`` at ``t`` ((n, 3), (n, 4), (n, 3, 3), then (n, 3)
        each): the poses at ``t + k h``, ``k = -2..2``, and their central differences (``w``: ``(R^T
        dR/dt)^v``). ``compiled`` (default: :data:`companion.kernels.jit.ENABLED`): by
        :func:`companion.kernels.trajectory.trajectory_kernel` (the same numbers to 1e-12, ``a`` and
        ``w_dot`` to 1e-8 and 1e-9, the rounding of the poses over ``h^2``:
        ``tests/unit/test_companion_kernels.py``), else in numpy, the specification below."""
        h = self.h
        times = [t + k * h for k in (-2, -1, 0, 1, 2)]
        if _COMPILED if compiled is None else compiled:
            n = self.n
            out = (np.empty((n, 3)), np.empty((n, 4)), np.empty((n, 3, 3)), np.empty((n, 3)), np.empty((n, 3)),
                   np.empty((n, 3)), np.empty((n, 3)))
            trajectory_kernel(np.array([self.bend_angle_rad(x) for x in times]),
                              np.array([self.center_w_m(x) for x in times]), (self._share, self._base_q, self.d),
                              float(h), out)
            return out
        p, qs, R = self.poses(times)
        v = (p[3] - p[1]) / (2 * h)
        a = (p[3] - 2 * p[2] + p[1]) / (h * h)
        # (R^T dR/dt)^v of every link at the offsets -1, 0, 1 at once
        W = np.einsum("snji,snjk->snik", R[1:4], (R[2:5] - R[0:3]) / (2 * h))
        rates = np.stack((W[..., 2, 1], W[..., 0, 2], W[..., 1, 0]), axis=-1)
        return p[2], qs[2], R[2], v, a, rates[1], (rates[2] - rates[0]) / (2 * h)

    def targets(self, t: float, passive=frozenset()) -> list[PoseTarget]:
        """Targets with velocity, acceleration, body rate and its derivative (``passive``: see
        :func:`with_feedforward`)."""
        p, q, R, v, a, w, w_dot = self.target_arrays(t)
        motion = [(p[i], q[i], v[i], a[i], w[i], w_dot[i]) for i in range(self.n)]
        if self.dynamics is None:
            return [PoseTarget(*m) for m in motion]
        return feedforward_targets(motion, self.dynamics, passive, (p, R, v, w, a, w_dot))


class CpgChainTrajectory:
    """``kind = "cpg"``: hover (:class:`ChainTrajectory`) until ``motion.start_s``, then the
    :class:`~companion.motion.generator.MotionGenerator` of the scenario's ``[motion]`` commands.

    The generator steps on its own grid ``start_s + k dt`` (``motion.dt_s``), always one step
    ahead of the latest query, so a target at ``t`` takes sample ``k = round((t - start_s)/dt)``
    with its acceleration and angular acceleration as central differences of the generator's
    exact velocities. Queries must not go back more than one step. The heading and altitude
    controllers (:func:`~companion.motion.schedule.desired_motion`) are sampled when the command
    changes and once per undulation period; ``altitude_m`` is the hover altitude they hold.
    """

    def __init__(self, cfg: TrajectoryConfig, motion: MotionConfig, model: InverseModel, n_links: int,
                 link_length_m: float, start_center_w_m, dynamics=None):
        try:
            if model.steady is None:
                raise ValueError("is not a flying chain's model (it records no expected physics)")
            model.steady.check_chain(n_links, link_length_m)
        except ValueError as exc:
            raise ValueError(f"the inverse model {exc}") from None
        self.cfg = cfg
        self.motion = motion
        self.n = n_links
        self.hover = ChainTrajectory(replace(cfg, kind="hover"), n_links, link_length_m, start_center_w_m,
                                     dynamics=dynamics)
        self.dynamics = dynamics
        self.start_s = motion.start_s
        self.dt = motion.dt_s
        center = self.hover.center_w_m(self.start_s)
        self.altitude_m = float(center[2])
        body = BodyState.at_rest(center, math.radians(cfg.yaw_deg))
        self.generator = MotionGenerator(model, body=body, adapt=motion.adapt)
        self._period_steps = max(1, int(round(self.generator.period_s / self.dt)))
        self._samples: dict[int, LinkTargets] = {0: self.generator.targets()}
        self._k = 0  # the generator's step
        self._command: MotionCommand | None = None
        self._since_control = 0
        self.xi_desired = np.zeros(7)

    def _advance(self) -> None:
        gen = self.generator
        command = self.motion.active(self._k * self.dt)
        new = command is not self._command
        if new or self._since_control >= self._period_steps:
            self.xi_desired = desired_motion(self.motion, command, gen.body.R_wb,
                                             float(gen.body.p_w_m[2]) - self.altitude_m)
            self._since_control = 0
        self._command = command
        self._since_control += 1
        self._k += 1
        self._samples[self._k] = gen.step(self.xi_desired, self.dt, new_command=new)
        self._samples.pop(self._k - 3, None)

    @property
    def eta(self) -> np.ndarray:
        """The CPG parameters ``[A_x, A_y, B_x, B_y]`` in use."""
        return self.generator.eta

    def targets(self, t: float, passive=frozenset()) -> list[PoseTarget]:
        if t < self.start_s:
            return self.hover.targets(t, passive)
        k = int(round((t - self.start_s) / self.dt))
        if k < self._k - 1:
            raise ValueError(f"targets at {t:.3f} s: the generator is already at {self.start_s + self._k * self.dt:.3f} s")
        while self._k < k + 1:
            self._advance()
        now, after = self._samples[k], self._samples[k + 1]
        before = self._samples.get(k - 1, now)
        span = (2 if k - 1 in self._samples else 1) * self.dt
        a = (after.v_w_m_s - before.v_w_m_s) / span
        w_dot = (after.omega_l_rad_s - before.omega_l_rad_s) / span
        q = rotmat_to_quat(now.R_wl)
        motion = [(now.p_w_m[i], q[i], now.v_w_m_s[i], a[i], now.omega_l_rad_s[i], w_dot[i]) for i in range(self.n)]
        if self.dynamics is None:
            return [PoseTarget(*m) for m in motion]
        return feedforward_targets(motion, self.dynamics, passive,
                                   (now.p_w_m, quat_to_rotmat(q), now.v_w_m_s, now.omega_l_rad_s, a, w_dot))


def chain_model(skeleton: SkeletonConfig):
    """The chain's multibody model for the feed-forward (``ValueError`` without pinocchio)."""
    try:
        from .skeleton.dynamics import ChainModel  # pinocchio: only the feed-forward needs it
    except ImportError as exc:
        raise ValueError(f"trajectory.feedforward needs pinocchio ({exc}): pip install "
                         "'aerial-skeleton-stack[dynamics]'") from None
    return ChainModel(skeleton)


def make_trajectory(cfg: TrajectoryConfig, motion: MotionConfig, skeleton: SkeletonConfig, start_center_w_m,
                    load: LoadConfig | None = None) -> ChainTrajectory | CpgChainTrajectory | FormationTrajectory:
    """The target source of a configuration: :class:`~companion.load.formation.FormationTrajectory`
    of ``load`` (the ``[load]`` table; ``ValueError`` without it) for ``kind = "formation"``,
    :class:`CpgChainTrajectory` for ``kind = "cpg"`` (its inverse model loaded from
    ``motion.model``), else :class:`ChainTrajectory`; with ``feedforward`` the chain model of
    ``skeleton`` computes the targets' feed-forward."""
    if cfg.kind == "formation":
        if load is None:
            raise ValueError("trajectory.kind 'formation' needs a [load] table")
        return FormationTrajectory(load)
    dynamics = chain_model(skeleton) if cfg.feedforward else None
    n, L = skeleton.n_links, skeleton.link_length_m
    if cfg.kind == "cpg":
        model = InverseModel.load(motion.model)
        return CpgChainTrajectory(cfg, motion, model, n, L, start_center_w_m, dynamics)
    return ChainTrajectory(cfg, n, L, start_center_w_m, dynamics=dynamics)
