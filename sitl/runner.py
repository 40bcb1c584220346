"""Batch mode: physics, firmware and companion stepped in one process on one clock.

One physics tick (1 kHz by default) is::

    kinematics (mj_step1) -> truth
    every firmware tick (500 Hz): IMU sample, GPS / attitude (and, when the sensor profile fits
        them, barometer / magnetometer) samples queued (their rates), each
        link's firmware: EKF predict + updates + control + allocation; then the companion
        engine(s): link states at the stream rate (50 Hz), its 20 Hz step, corrections, targets
        (50 Hz) and arming, carried out on the firmware at once
    rotor/ESC dynamics -> thrusts, wind -> forces -> dynamics and integration (mj_step2)

On the firmware ticks that feed no measurement and log no row, the links whose tick is quiet
(:mod:`link_firmware_sim.kernels.quiet`) tick in one kernel call
(:class:`~link_firmware_sim.batch.LinkBatch`); the runner gives their state back to the firmware
objects before it next reads or changes them, so the flight is the same, bit for bit.

Everything random comes from ``numpy.random.default_rng(scenario.seed)``; MuJoCo is
deterministic, so the same scenario and seed give the same numbers.

The companion is the daemon's engine (:class:`~companion.engine.CompanionEngine`): batch flights
exercise its time alignment, withholding, time base, targets and distributed halves. Its outputs
reach the firmware in the same tick (no transport latency; the MAVLink fleet adds the wires).
"""

from __future__ import annotations

import logging
import math
import time
from dataclasses import dataclass, field

import numpy as np

from companion.linkstate import word as state_word
from companion.engine import Command, CommandOut, CompanionEngine, CorrectionOut, TargetOut
from companion.estimation.so3 import quat_to_rotmat
from companion.fleetnet.group import GroupLink
from companion.fleetnet.hub import LocalHub
from companion.fleetnet.leader import GlobalStepNode
from companion.skeleton.kinematics import tension
from companion.trajectory import CpgChainTrajectory, make_trajectory
from link_firmware_sim.batch import ENABLED as BATCH_ENABLED
from link_firmware_sim.batch import LinkBatch
from link_firmware_sim.events import SEVERITY, statustext_arrays
from link_firmware_sim.firmware import CorrectionRejected, LinkFirmware
from link_firmware_sim.vehicle.failures import OK, FailureInjector
from link_firmware_sim.vehicle.hil import sitl_gps_time_us

from .plant.plant import Plant
from .plant.schedule import Schedule
from .scenario import Scenario, with_options
from .steplog import attach_truth, merge_step_logs
from .task import Task
from .watch import announce
from .warm import warm_up_kernels

__all__ = ["BatchRunner", "RunLog", "warm_up_kernels"]

log = logging.getLogger(__name__)


@dataclass
class RunLog:
    """Time series recorded at the log rate (the companions' steps are in their step logs)."""

    t: list = field(default_factory=list)
    p_true: list = field(default_factory=list)
    v_true: list = field(default_factory=list)
    q_true: list = field(default_factory=list)
    p_ekf: list = field(default_factory=list)
    q_ekf: list = field(default_factory=list)
    p_ctrl: list = field(default_factory=list)
    q_ctrl: list = field(default_factory=list)
    p_target: list = field(default_factory=list)
    q_target: list = field(default_factory=list)
    thrust: list = field(default_factory=list)
    # the cable at every joint: the simulator's force (world), and the model's when the targets
    # carry the whole-chain feed-forward (NaN while a link is not live); their tensions are worked
    # out of them and the attitudes (true, target) for all rows at once (:meth:`arrays`)
    joint_force_true: list = field(default_factory=list)
    joint_force_model: list = field(default_factory=list)
    # CPG motion (log ticks): the parameters in use and the desired motion
    eta: list = field(default_factory=list)
    xi_desired: list = field(default_factory=list)
    #: each link's state word (:mod:`companion.linkstate`)
    link_state: list = field(default_factory=list)
    #: each link's newest correction latency (applied minus the state's time) [ms], NaN: none yet
    correction_latency_ms: list = field(default_factory=list)

    def arrays(self) -> dict[str, np.ndarray]:
        """Every series recorded, one row per log tick, and the cables' tensions at each joint
        (:func:`~companion.skeleton.kinematics.tension`): ``tension_true``, and ``tension_model``
        with the feed-forward. The trajectory's series (the model's joint forces, the CPG's) begin
        with its first targets: NaN rows before them."""
        out = {k: _from_first_tick(v, len(self.t)) for k, v in self.__dict__.items()
               if len(v) and k != "joint_force_model"}
        if len(self.joint_force_true):
            out["tension_true"] = tension(out["joint_force_true"], quat_to_rotmat(out["q_true"]))
        if len(self.joint_force_model):
            joint_force = _from_first_tick(self.joint_force_model, len(self.t))
            out["tension_model"] = tension(joint_force, quat_to_rotmat(out["q_target"]))
        return out


def _from_first_tick(rows: list, n_ticks: int) -> np.ndarray:
    """``rows``, the last ``len(rows)`` of ``n_ticks`` log ticks, as an array of ``n_ticks`` rows
    (NaN before the first)."""
    a = np.asarray(rows)
    if len(a) >= n_ticks:
        return a
    return np.concatenate([np.full((n_ticks - len(a),) + a.shape[1:], np.nan), a.astype(float)])


class _SharedTargets:
    """A target source shared by a batch flight's group engines: the targets of the last time asked,
    computed once (every other attribute is the wrapped source's)."""

    def __init__(self, source):
        self.source = source
        self._last: tuple[float, list] | None = None

    def targets(self, t: float, passive=frozenset()):
        if self._last is None or self._last[0] != (t, passive):
            self._last = ((t, passive), self.source.targets(t, passive))
        return self._last[1]

    def __getattr__(self, name):
        return getattr(self.source, name)


class BatchRunner:
    """Batch mode: a :class:`~sitl.plant.plant.Plant`, every link's firmware and the companion
    engine(s), in one process; a scenario kind's :class:`~sitl.task.Task` hooks into its ticks.

    The companion is :class:`~companion.engine.CompanionEngine`, the daemon's own logic: each link's
    state reaches it at the state stream's rate on the flight-controller clock (as the vehicles
    stream SKELETON_LINK_STATE in fleet mode), with heartbeats and SYSTEM_TIME at 1 Hz; its
    corrections, targets and arm commands go to the firmware in the same tick (no transport
    latency). A distributed scenario runs one engine per group, joined by an in-process bus
    (:class:`~companion.fleetnet.hub.LocalHub`) on the simulation clock: the same election,
    boundaries and eq. 6 shifts as over Zenoh, deterministic.
    """

    #: poll an engine only when :meth:`~companion.engine.CompanionEngine.needs_poll` says it has
    #: something to do (an input, a bus event, a timer); ``False`` on an instance: every engine on
    #: every firmware tick (the two give the same flight, bit for bit: ``tests/integration/test_faults.py``)
    skip_idle_polls: bool = True
    #: run the quiet ticks of all links in one kernel call (:class:`~link_firmware_sim.batch.LinkBatch`);
    #: ``False`` on an instance: every link's tick through its firmware (the two give the same
    #: flight, bit for bit: ``tests/integration/test_batch_tick.py``)
    batch_ticks: bool = True

    def __init__(self, scenario: Scenario, sckf: bool | None = None, selective_mapping: bool | None = None,
                 task: Task | None = None):
        sc = with_options(scenario, sckf=sckf, selective_mapping=selective_mapping)
        self.scenario = sc
        #: the scenario kind's hooks (:mod:`sitl.task`)
        self.task = task if task is not None else Task()
        self.plant = Plant(sc)
        plant = self.plant
        self.n = plant.n
        self.dt = plant.dt
        self.schedule = Schedule.of(sc)
        self.d = plant.d
        self.rotors = plant.rotors
        # The compiled kernels loaded (from numba's cache) now, before the flight: a real-time factor is
        # the flight's, not the process's start-up.
        warm_up_kernels("batch", cpg=sc.trajectory.kind == "cpg")
        self.firmware = [LinkFirmware(i, sc.firmware, plant.inertia, plant.geometry) for i in range(self.n)]
        self.corrections_rejected = [0] * self.n  # out of the firmware's bounds (SKL_CORR_MAX*)
        self.groups = sc.companion.group_layout(self.n)
        self.now_s = 0.0  # the companions' clock: simulation time
        self.engines, self.hub = self._engines(sc, plant.start_center())
        self.start_firmware()
        if sc.faults.fleet_only:
            raise ValueError(f"{', '.join(sc.faults.fleet_only)}: fleet mode only (python -m sitl launch)")
        self.gps_fault = sc.faults.gps
        self.reboot = sc.faults.link
        self.inject = sc.faults.inject
        #: ``[faults.inject]``: the injected link's failure filter, as its vehicle runs one
        self.failures = FailureInjector(seed=sc.seed) if self.inject.link else None
        #: what the injection did (metrics ``faults.inject``): when it started and ended, the filter's report
        self.inject_log: dict = {}
        #: the link reboot's timeline (metrics ``faults.link_reboot``), as the fleet reports it
        self.link_fault: dict = {}
        self._down: set[int] = set()  # links whose firmware is off (killed, not yet powered on)
        self.log = RunLog()
        #: the firmware's STATUSTEXTs: (time [s], link from 1, MAV_SEVERITY, text)
        self.statustext: list[tuple] = []
        self.state_interval_us = int(round(1e6 / sc.companion.state_rate_hz))
        self.wall_s = 0.0
        self.sim_s = 0.0
        #: observers called as hook(k, t) at every physics tick after the kinematics and the log
        #: (cameras, video, an estimator beside the flight)
        self.tick_hooks: list = []
        self._batch: LinkBatch | None = None  # the quiet ticks' batch of the current run
        self.task.initialize(self)
        announce(self)

    @property
    def model(self):
        """The plant's MuJoCo model (:class:`~sitl.plant.model.SkeletonModel` or a scenario's own)."""
        return self.plant.model

    def start_firmware(self) -> None:
        """Every link's firmware started as a vehicle starts: its EKF from the first GPS fix and
        attitude reference the next tick delivers (at t = 0; the companion arms it later), the
        samples a fleet's vehicles start from with the same seed; an in-air start has the rotors
        already spinning at the thrusts that carry each link."""
        plant = self.plant
        truth = plant.model.truth()
        # a firmware's newest [GPS fix, attitude] before its EKF starts (:meth:`_boot`)
        self._boot_fix: dict[int, list] = {i: [None, None] for i in range(self.n)}
        if not self.scenario.start.on_ground:
            self.rotors.prime(np.concatenate([fw.hover_command(truth.q_wxyz[i]) for i, fw in enumerate(self.firmware)]))

    def _engines(self, sc: Scenario, center: np.ndarray):
        clock = lambda: self.now_s  # noqa: E731 - the engines' and the hub's clock
        if not sc.companion.distributed:
            return [CompanionEngine(sc, start_center=center)], None
        zc = sc.zenoh
        n_groups = len(self.groups)
        hub = LocalHub(n_groups, clock, sc.zenoh_prefix)
        # The group engines would each compute the same targets from the same deterministic source
        # (fleet companions do, in their own processes): here they share one, computed once per time.
        shared = _SharedTargets(make_trajectory(sc.trajectory, sc.motion, sc.skeleton, center, load=sc.load))
        engines = []
        for g in range(n_groups):
            node = GlobalStepNode(g, n_groups, zc.order(n_groups), int(round(1e6 / sc.companion.rate_hz)),
                                  shift_deadline_s=zc.shift_deadline_ms * 1e-3, leader_wait_s=zc.leader_wait_ms * 1e-3,
                                  handover_cycles=zc.handover_cycles)
            engines.append(CompanionEngine(sc, group=g, start_center=center, net=GroupLink(node, hub.join(g), clock),
                                           trajectory=shared))
        return engines, hub

    @property
    def trajectory(self):
        """The companion's target source (``None`` before its first target)."""
        source = self.engines[0].trajectory
        return source.source if isinstance(source, _SharedTargets) else source

    @property
    def crashed(self) -> bool:
        return self.plant.crashed

    @property
    def crash_reason(self) -> str:
        return self.plant.crash_reason

    def _inject_failure(self, t: float) -> None:
        """``[faults.inject]`` in batch mode: the failure set and cleared at its times, announced as
        the vehicle does (STATUSTEXT "Failure injection: ...")."""
        inj = self.inject
        ftype = inj.due(t, self.inject_log)
        if ftype is None:
            return
        self._sync()
        text = f"Failure injection: {self.failures.inject(inj.unit_id, ftype, inj.instance)}"
        log.warning("link %d at %.2f s: %s", inj.link, t, text)
        self.statustext.append((t, inj.link, SEVERITY["recovered" if ftype == OK else "fault"], text))

    def _link_reboot(self, t: float, commands: np.ndarray) -> None:
        """``[faults.link]`` in batch mode: link ``kill``'s firmware loses power at ``kill_at_s`` (its
        rotors stop, it is silent) and a new one powers on ``restart_after_s`` later. The new
        firmware starts its EKF in flight at its first GPS fix with an attitude reference (as a
        vehicle does) and waits for the companion to re-admit and re-arm it. Its clock is the
        simulation's, as a restarted vehicle's is in the lockstep."""
        rb, lf = self.reboot, self.link_fault
        i = rb.kill - 1
        if "killed_at_s" not in lf and t >= rb.kill_at_s:
            self._sync()
            self._down.add(i)
            commands[i] = 0.0
            lf.update(link=rb.kill, killed_at_s=round(t, 3))
            log.warning("fault: link %d's firmware off at t = %.2f s (rotors stopped)", rb.kill, t)
        if (rb.restart_after_s and "killed_at_s" in lf and "restarted_at_s" not in lf
                and t >= rb.kill_at_s + rb.restart_after_s):
            self._sync()
            self.firmware[i] = LinkFirmware(i, self.scenario.firmware, self.plant.inertia, self.plant.geometry)
            self._down.discard(i)
            self._boot_fix[i] = [None, None]
            lf.update(restarted_at_s=round(t, 3), rejoined_at_s=round(t, 3))
            log.warning("fault: link %d's firmware powered on again at t = %.2f s", rb.kill, t)
        if "restarted_at_s" in lf and "rotors_on_at_s" not in lf and np.any(commands[i] != 0):
            lf.update(rotors_on_at_s=round(t, 3))

    def _boot(self, i: int, t: float, fix=None, att=None) -> bool:
        """A starting (or restarted) firmware's sensor sample before its EKF runs: the EKF starts
        once it has a GPS fix and an attitude reference (the newest of each). True if the sample
        was taken here (the firmware was booting), False if the firmware takes it itself."""
        pending = self._boot_fix.get(i)
        if pending is None:
            return False
        if fix is not None:
            pending[0] = fix
        if att is not None:
            pending[1] = att
        if pending[0] is not None and pending[1] is not None:
            self.firmware[i].initialize(t, pending[0][0], pending[0][1], pending[1])
            del self._boot_fix[i]
        return True

    def _unheard(self, i: int) -> bool:
        """0-based link ``i`` exchanges nothing with the companion: powered off, or its MAVLink
        signal failed (``[faults.inject] unit = "mavlink_signal"``)."""
        return i in self._down or (self.failures is not None and self.failures.link_off and i == self.inject.link - 1)

    def _companion_exchange(self, t: float, t_us: int) -> None:
        """Link states (at the stream rate), heartbeats and SYSTEM_TIME (1 Hz) to the engines; their
        outputs to the firmware; repeated while the in-process bus carries messages."""
        self.now_s = t
        second = t_us % 1_000_000 == 0
        states = t_us % self.state_interval_us == 0
        if second or states:
            self._sync()
        for engine in self.engines if second or states else ():
            for lk in engine.links:
                fw = self.firmware[lk.index]
                if self._unheard(lk.index):
                    if lk.index not in self._down and states:
                        self.failures.changed["mavlink_signal"] += 1  # (a state report not sent)
                    continue  # no power, or its MAVLink signal off: silent
                if second:
                    engine.on_heartbeat(lk.row, t)
                    engine.on_system_time(lk.row, sitl_gps_time_us(t_us) if fw.initialized else 0, t_us // 1000)
                if states and fw.initialized:
                    engine.on_state(lk.row, fw.state_report(), fw.flags(t), t, fw.correction_seq,
                                    fw.correction_latency_us)
        for _ in range(4 * len(self.engines) + 4):
            for engine in self.engines:
                if not self.skip_idle_polls or engine.needs_poll(t):  # (most ticks bring an engine nothing)
                    self.apply(engine, engine.poll(t), t)
            if self.hub is None or not self.hub.pending():
                break

    def apply(self, engine: CompanionEngine, outputs: list, t: float) -> None:
        """An engine's outputs at ``t`` to the firmware, between the task's
        :meth:`~sitl.task.Task.before_outputs` and :meth:`~sitl.task.Task.after_outputs`."""
        self._sync()
        task = self.task
        self._apply(engine, task.before_outputs(self, engine, outputs, t), t)
        task.after_outputs(self, engine, outputs, t)

    def _apply(self, engine: CompanionEngine, outputs, t: float) -> None:
        standard = self.scenario.companion.mode == "standard"
        for out in outputs:
            if hasattr(out, "row") and self._unheard(engine.links[out.row].index):
                continue  # a firmware without power (or signal) hears nothing (and acknowledges nothing)
            if isinstance(out, CorrectionOut):
                fw = self.firmware[engine.links[out.row].index]
                if standard:
                    c = out.corrected
                    fw.on_external_pose(t, c.p_w_m, c.v_w_m_s, c.q_wxyz)
                else:
                    try:
                        fw.on_correction(t, out.correction)
                    except CorrectionRejected as exc:  # as the vehicle does: counted, not applied
                        self.corrections_rejected[fw.link] += 1
                        log.warning("t=%.2f s link %d: %s", t, fw.link + 1, exc)
            elif isinstance(out, TargetOut):
                self.firmware[engine.links[out.row].index].set_target(t, out.target)
            elif isinstance(out, CommandOut):
                ok = out.command is not Command.ARM or self.firmware[engine.links[out.row].index].arm(t)
                engine.on_command_ack(out.row, out.command, ok)

    def step_log(self) -> dict[str, np.ndarray] | None:
        """The companions' steps over the whole chain (:func:`~sitl.steplog.merge_step_logs`)."""
        return merge_step_logs([[e.log_arrays()] for e in self.engines], self.d, self.hub is not None)

    def arrays(self) -> dict[str, np.ndarray]:
        """The run's log: the log-rate series plus the companions' step log with the truth at every step."""
        out = self.log.arrays()
        out["home_offset_w_m"] = np.array(self.engines[0].targets.home_offset_w_m)  # (trajectory.planned_positions)
        if self.statustext:
            out.update(statustext_arrays(self.statustext))
        steps = self.step_log()
        if steps is not None and "t" in out:
            out.update(attach_truth(steps, out["t"], out["p_true"], out["v_true"], out["q_true"]))
        return out

    def _log_tick(self, t: float, truth) -> None:
        lg = self.log
        lg.t.append(t)
        lg.p_true.append(truth.p_w_m.copy())
        lg.v_true.append(truth.v_w_m_s.copy())
        lg.q_true.append(truth.q_wxyz.copy())
        # a link without power or still booting logs no estimate (NaN), as a vehicle logs nothing
        n = self.n
        p_ctrl, p_ekf, p_target = np.full((n, 3), np.nan), np.full((n, 3), np.nan), np.full((n, 3), np.nan)
        q_ctrl, q_ekf, q_target = np.full((n, 4), np.nan), np.full((n, 4), np.nan), np.full((n, 4), np.nan)
        all_live = True
        for i, fw in enumerate(self.firmware):
            if i in self._down or not fw.initialized:
                all_live = False
                continue
            ctrl = fw.control_estimate(t)
            p_ctrl[i], q_ctrl[i] = ctrl[0], ctrl[2]
            p_ekf[i], q_ekf[i] = fw.ekf.p_w_m, fw.ekf.q_wxyz
            target = fw.active_target(t, ctrl)
            p_target[i], q_target[i] = target.p_w_m, target.q_wxyz  # q: logged, and the model's tension
        lg.p_ctrl.append(p_ctrl)
        lg.q_ctrl.append(q_ctrl)
        lg.p_ekf.append(p_ekf)
        lg.q_ekf.append(q_ekf)
        lg.p_target.append(p_target)
        lg.q_target.append(q_target)
        lg.thrust.append(self.rotors.thrust_n.reshape(self.n, -1).copy())
        lg.joint_force_true.append(truth.joint_force_w_n)
        dynamics = getattr(self.trajectory, "dynamics", None) if self.trajectory is not None else None
        if dynamics is not None:
            last = dynamics.last
            lg.joint_force_model.append(np.full((self.n - 1, 3), np.nan) if last is None or not all_live
                                        else last.joint_force_w_n)
        if isinstance(self.trajectory, CpgChainTrajectory):
            lg.eta.append(self.trajectory.eta.copy())
            lg.xi_desired.append(self.trajectory.xi_desired.copy())
        lg.link_state.append(self.link_states(t))
        if self.scenario.companion.enabled:
            lg.correction_latency_ms.append([fw.correction_latency_us * 1e-3 if fw.latency_log else np.nan
                                             for fw in self.firmware])

    def link_states(self, t: float) -> np.ndarray:
        """Every link's state word at ``t`` (:mod:`companion.linkstate`): its firmware's flags, the
        companion's carried and left-out links, and the links without power."""
        tracks = {lk.index: lk for engine in self.engines for lk in engine.links}
        n = self.n
        flags, carried, excluded, down = [0] * n, [False] * n, [False] * n, [False] * n
        for i, fw in enumerate(self.firmware):
            down[i] = i in self._down
            flags[i] = 0 if down[i] else fw.flags(t)
            lk = tracks.get(i)
            if lk is not None:
                carried[i], excluded[i] = lk.carried.on, bool(lk.status)
        return state_word(np.array(flags), carried=np.array(carried), excluded=np.array(excluded), down=np.array(down))

    def _sync(self) -> None:
        """The firmware made current before the runner reads or changes it (:class:`~link_firmware_sim.batch.LinkBatch`)."""
        if self._batch is not None:
            self._batch.sync()

    def _link_batch(self) -> LinkBatch | None:
        """The batch of every link's quiet ticks for a run, or ``None``: switched off
        (:attr:`batch_ticks`), no compiled kernels, or an observer that may read the firmware at any
        physics tick (a tick hook, a task's :meth:`~sitl.task.Task.after_step`)."""
        if not (self.batch_ticks and BATCH_ENABLED) or self.tick_hooks or self._task_after_step() is not None:
            return None
        if self._batch is None or self._batch.firmware is not self.firmware:
            self._batch = LinkBatch(self.firmware)
        return self._batch

    def _task_after_step(self):
        """The task's :meth:`~sitl.task.Task.after_step`, or ``None`` when the task keeps
        :class:`~sitl.task.Task`'s, which does nothing."""
        return self.task.after_step if type(self.task).after_step is not Task.after_step else None

    def _batch_skip(self, j: int) -> set[int]:
        """The links the batch leaves to their firmware's own tick: without power, booting, the
        injected link while its IMU or motors fail, a link flying with a rotor left out (its ESCs'
        telemetry is judged each tick)."""
        failing = self.failures is not None and self.failures.imu_or_motor
        out = {i for i, fw in enumerate(self.firmware) if fw.rotor_out} if self.failures is not None else set()
        if not self._boot_fix and not failing and not out:
            return self._down
        return self._down | set(self._boot_fix) | ({j} if failing else set()) | out

    def run(self, duration_s: float, progress=None) -> RunLog:
        """Advance the simulation by ``duration_s``; ``progress(s)`` is called every 100 ms."""
        plant, sch, task = self.plant, self.schedule, self.task
        sensors, rotors = plant.sensors, plant.rotors
        n_ticks = int(round(duration_s / self.dt))
        fw_dt = sch.fw * self.dt
        commands = np.zeros((self.n, 8))
        self._batch = batch = self._link_batch()
        wall0 = time.perf_counter()
        tick0 = int(round(plant.time_s / self.dt))
        hooks = self.tick_hooks
        after_step = self._task_after_step()
        try:
            for k in range(tick0, tick0 + n_ticks):
                t = k * self.dt
                fw_due, log_due = k % sch.fw == 0, k % sch.log == 0
                truth = plant.begin_tick(truth=fw_due or log_due)  # (the other ticks: nobody reads it)
                if fw_due:
                    if not math.isfinite(truth.p_w_m.sum()):  # (a NaN or an infinity anywhere; one call)
                        plant.check_crash(t, truth, None)
                        break
                    self._firmware_tick(k, t, truth, commands, fw_dt, batch)
                    rotors.set_command(commands.reshape(-1))
                    self._companion_exchange(t, int(round(k * self.dt * 1e6)))
                if log_due:
                    self._sync()
                    self._log_tick(t, truth)
                    task.after_log(self, t, truth)
                    plant.check_crash(t, truth, self.log.q_target[-1])
                for hook in hooks:
                    hook(k, t)
                plant.end_tick()
                if after_step is not None:
                    after_step(self, k, t)
                if progress is not None and (k - tick0) % 100 == 99:
                    progress(100 * self.dt)
        finally:
            self._sync()
        self.wall_s += time.perf_counter() - wall0
        self.sim_s += n_ticks * self.dt
        return self.log

    def _firmware_tick(self, k: int, t: float, truth, commands: np.ndarray, fw_dt: float, batch) -> None:
        """A firmware tick at physics tick ``k``: the faults due, the measurements due fed, the IMU
        sample to every link's firmware (the quiet ones' in one call of ``batch``, when given, with
        the attitude reference when it is the only measurement due) and their thrust commands
        written to ``commands``, their events reported."""
        plant, sch, sensors = self.plant, self.schedule, self.plant.sensors
        if self.reboot.kill:
            self._link_reboot(t, commands)
        failures = self.failures
        if failures is not None:
            self._inject_failure(t)
        j = self.inject.link - 1  # the injected link (-1: none)
        down, booting = self._down, self._boot_fix  # no power; powered, no EKF yet
        log_row = k % sch.log == 0
        att_due = k % sch.att == 0
        fed = (k % sch.gps == 0 or (sensors.has_baro and k % sch.baro == 0)
               or (sensors.has_mag and k % sch.mag == 0))  # (measurements the firmware takes itself)
        batched = batch is not None and not fed
        if fed or (not batched and (att_due or log_row)):
            self._sync()
        if k % sch.gps == 0:
            pos, vel = sensors.gps(t, truth.p_w_m, truth.v_w_m_s)
            pos, has_fix = self.gps_fault.apply(t, pos)
            if failures is not None:
                fix = failures.gps(pos[j], vel[j])
                has_fix[j] = has_fix[j] and fix is not None
                if fix is not None:
                    pos, vel = pos.copy(), vel.copy()
                    pos[j], vel[j] = fix
            for i, fw in enumerate(self.firmware):
                if has_fix[i] and i not in down and not self._boot(i, t, fix=(pos[i], vel[i])):
                    fw.on_gps(t, pos[i], vel[i])
        att, att_links = None, ()
        if att_due:
            att = sensors.attitude(t, truth.q_wxyz)
            att_links = [i for i in range(self.n) if i not in down and not self._boot(i, t, att=att[i])]
            if not batched:
                for i in att_links:
                    self.firmware[i].on_attitude(t, att[i])
        baro, mag = plant.baro_mag(k, sch, truth)
        if baro is not None:
            for i, fw in enumerate(self.firmware):
                if i not in down and i not in booting:
                    fw.on_baro(t, float(baro[i]))
        if mag is not None:
            for i, fw in enumerate(self.firmware):
                if i not in down and i not in booting:
                    fw.on_mag(t, mag[i])
        gyro, accel = sensors.imu(truth.specific_force_b_m_s2, truth.omega_b_rad_s, fw_dt)
        if failures is not None and failures.imu_or_motor:
            gyro, accel = gyro.copy(), accel.copy()
            gyro[j], accel[j] = failures.imu(gyro[j], accel[j])
        if batched:
            links = batch.tick(t, gyro, accel, commands, self._batch_skip(j), att)
            if att_due:  # (the links the batch left to their firmware take the reference there)
                for i in set(links).intersection(att_links):
                    self.firmware[i].on_attitude(t, att[i])
        else:
            links = range(self.n)
        for i in links:
            fw = self.firmware[i]
            commands[i] = 0.0 if i in down else fw.on_imu(t, gyro[i], accel[i])
            if i == j and failures.imu_or_motor or fw.rotor_out:
                # what the motors apply: the ESCs' telemetry
                thrust = failures.thrust(commands[i]) if i == j else commands[i]
                fw.on_esc_telemetry(t, commands[i], thrust)
                commands[i] = thrust
        if log_row:  # the newest samples to the stuck-sensor watch (a vehicle: on its stream and log rows)
            if batched:
                self._sync()
            for i, fw in enumerate(self.firmware):
                if i not in down:
                    fw.watch_imu(t)
        for i, fw in enumerate(self.firmware):
            if fw.events:  # GPS health, thrust limit (a vehicle sends them as STATUSTEXT)
                for ev in fw.events:
                    log.warning("link %d at %.2f s: %s", i + 1, t, ev.text)
                    self.statustext.append((t, i + 1, SEVERITY[ev.kind], ev.text))
                fw.events.clear()
