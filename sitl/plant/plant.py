"""The plant: the physical side of a run, shared by batch mode (firmware called in-process) and
fleet mode (firmware behind the vehicles' simulator links)."""

from __future__ import annotations

import numpy as np

from companion.skeleton.body import link_inertia
from companion.skeleton.kinematics import chain_middle

from sitl.scenario import Scenario

from .crash import CrashWatch
from .model import SkeletonModel
from .rotor import RotorBank
from .rotor import warm_up as warm_up_rotors
from .schedule import Schedule
from .sensors import LinkSensors, downwash_fraction
from .sensors import warm_up as warm_up_sensors
from .wind import Wind

__all__ = ["Plant"]


class Plant:
    """The physical side of a run: MuJoCo skeleton, rotors and ESCs, sensors and wind.

    Shared by batch mode (firmware called in-process) and fleet mode (firmware behind the HIL
    link). One ``numpy.random.Generator`` seeded from the scenario drives every sensor and gust.
    A physics tick is :meth:`begin_tick` (kinematics, truth) then :meth:`end_tick` (rotor
    dynamics, wind, integration).
    """

    def __init__(self, sc: Scenario):
        self.scenario = sc
        self.n = sc.skeleton.n_links
        self.dt = 1.0 / sc.sim.physics_rate_hz
        self.geometry = sc.geometry()
        self.inertia = link_inertia(sc.skeleton, self.geometry)
        self.model = SkeletonModel(sc.skeleton, self.geometry, sc.rotors, self.dt, cameras=sc.cameras,
                                   markers=sc.markers, scene=sc.scene, seed=sc.seed)
        self.model.reset(sc.start)
        self.d = sc.skeleton.d_b_m
        self.rng = np.random.default_rng(sc.seed)
        self.sensors = LinkSensors(sc.sensors.suite(), self.n, self.rng)
        self.rotors = RotorBank(8 * self.n, sc.rotors, rotors_per_link=8)
        warm_up_rotors()  # the compiled rotor and IMU kernels loaded now, not in the first ticks of the flight
        warm_up_sensors()
        self.wind = Wind(sc.wind, self.n, sc.skeleton.drag_area_m2, sc.skeleton.drag_coefficient, self.rng)
        self.model.begin_step()
        self._fresh = True  # begin_step already done for the current instant
        #: the crash rule, and whether and when the flight crashed
        self.crash = CrashWatch(sc)

    def use_model(self, model) -> None:
        """Fly ``model`` from now on, in place of the chain's (a scenario's own MuJoCo model: a wall
        beside the link, vehicles carrying a load), before the first tick. ``model`` answers to
        :class:`~sitl.plant.model.SkeletonModel`'s interface and has been reset to its start."""
        model.begin_step()
        self.model = model
        self._fresh = True

    @property
    def time_s(self) -> float:
        return self.model.time_s

    def start_center(self) -> np.ndarray:
        """Middle point of the chain (middle link centre or middle joint) at the start."""
        truth = self.model.truth()
        return chain_middle(truth.p_w_m, truth.q_wxyz, self.d).copy()

    def begin_tick(self, truth: bool = True):
        """Kinematics of the current instant; returns the truth (``truth=False``: ``None``, for a
        tick nobody reads)."""
        if not self._fresh:
            self.model.begin_step()
        self._fresh = False
        return self.model.truth() if truth else None

    def baro_mag(self, k: int, schedule: Schedule, truth) -> tuple[np.ndarray | None, np.ndarray | None]:
        """The barometric heights (n,) and magnetometer fields (n, 3) due at physics tick ``k``
        (``None``: not due, or the profile has no such sensor); the ground effect scales with
        each link's rotor thrust."""
        sensors = self.sensors
        baro = mag = None
        if sensors.has_baro and k % schedule.baro == 0:
            downwash = downwash_fraction(self.rotors.thrust_n.reshape(self.n, -1), self.inertia.mass_kg)
            baro = sensors.baro(k * self.dt, truth.p_w_m, downwash)
        if sensors.has_mag and k % schedule.mag == 0:
            mag = sensors.mag(truth.q_wxyz)
        return baro, mag

    def end_tick(self) -> None:
        thrust = self.rotors.step(self.dt)
        wind = self.wind.force(self.model.link_velocities(), self.dt) if self.wind.active else None
        self.model.end_step(thrust.reshape(self.n, -1), wind)

    def check_crash(self, t: float, truth, target_q: np.ndarray | None) -> None:
        """Judge the instant ``t`` by the crash rule (:class:`~.crash.CrashWatch`): ``truth`` the
        tick's, ``target_q`` (n, 4) every link's target attitude (``None``: not known here)."""
        self.crash.check(t, truth.p_w_m, truth.q_wxyz, target_q)

    @property
    def crashed(self) -> bool:
        return self.crash.crashed

    @property
    def crash_reason(self) -> str:
        return self.crash.crash_reason

    @property
    def crash_time_s(self) -> float | None:
        return self.crash.crash_time_s

    @property
    def took_off(self) -> bool:
        return self.crash.took_off
