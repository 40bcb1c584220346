"""Parameters of a simulated Pixhawk (the MAVLink parameter protocol's table).

Names follow PX4's style (at most 16 characters). Controller gains, failsafe timeouts,
allocation settings and stream rates are parameters; changing one through PARAM_SET applies it
at once and persists it in the instance's parameter file (JSON), which is read back at start.

Values travel in PARAM_VALUE's float field as PX4 sends them (bytewise: an integer's 32 bits;
MAV_PROTOCOL_CAPABILITY_PARAM_ENCODE_BYTEWISE and MAV_AUTOPILOT_PX4 declare it, which is what
MAVProxy, QGroundControl and MAVSDK look at). A PARAM_SET of an integer is also understood
C-cast when the bytewise reading is out of range (integer ranges stay within 2**24, so the two
readings never both fit). The shared local origin is not a parameter: as on PX4 it is set with
SET_GPS_GLOBAL_ORIGIN, answered with GPS_GLOBAL_ORIGIN, and persisted in the same file (key
``origin``).
"""

from __future__ import annotations

import dataclasses
import json
import logging
import math
from dataclasses import dataclass, replace
from pathlib import Path

from ..geo import GeoOrigin

from ..firmware_config import FirmwareConfig

__all__ = ["ParamSpec", "PARAMS", "ParamTable", "StreamRates"]

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class ParamSpec:
    name: str
    kind: str  # "float" | "int"
    minimum: float
    maximum: float
    description: str
    read_only: bool = False


PARAMS: tuple[ParamSpec, ...] = (
    ParamSpec("MAV_SYS_ID", "int", 1, 250, "MAVLink system id (set by the instance number)", read_only=True),
    ParamSpec("IMP_KP_XY", "float", 0.0, 200.0, "Position stiffness, horizontal [N/m] (eq. 1 k_p)"),
    ParamSpec("IMP_KP_Z", "float", 0.0, 200.0, "Position stiffness, vertical [N/m]"),
    ParamSpec("IMP_KD_XY", "float", 0.0, 200.0, "Position damping, horizontal [N s/m] (eq. 1 k_d)"),
    ParamSpec("IMP_KD_Z", "float", 0.0, 200.0, "Position damping, vertical [N s/m]"),
    ParamSpec("IMP_KI_XY", "float", 0.0, 50.0, "Position integral, horizontal [N/(m s)]"),
    ParamSpec("IMP_KI_Z", "float", 0.0, 50.0, "Position integral, vertical [N/(m s)]"),
    ParamSpec("IMP_KR", "float", 0.0, 100.0, "Attitude stiffness [N m] (eq. 1 k_R)"),
    ParamSpec("IMP_KW", "float", 0.0, 50.0, "Angular rate damping [N m s] (eq. 1 k_omega)"),
    ParamSpec("IMP_KI_ATT", "float", 0.0, 50.0, "Attitude integral [N m] (eq. 1 k_I)"),
    ParamSpec("IMP_GAMMA_I", "float", 0.0, 10.0, "Attitude integral mixing (eq. 1 gamma_I)"),
    ParamSpec("IMP_PERR_MAX", "float", 0.1, 100.0, "Position error taken at most this long in eq. 1 [m]"),
    ParamSpec("SKL_CORR_HOLD", "float", 0.0, 10.0, "Correction held at full weight [s]"),
    ParamSpec("SKL_CORR_STALE", "float", 0.01, 60.0, "Correction stale after [s]: control on the raw EKF"),
    ParamSpec("COM_OF_LOSS_T", "float", 0.05, 60.0, "Target stale after [s]: hold position"),
    ParamSpec("SKL_CTRL", "int", 0, 2, "Pose controller: 0 impedance (eq. 1), 1 SE(3) PID (2.3.2), 2 hybrid (2.3.3)"),
    ParamSpec("SKL_PSPM_EN", "int", 0, 2, "PSPM teleoperation (2.3.4): 0 off, 1 on, 2 slave law unmodulated"),
    ParamSpec("SKL_SM_EN", "int", 0, 1, "Selective mapping (thesis sec. 2.4.2) enabled"),
    ParamSpec("SKL_SM_EPS0", "float", 0.0, 5.0, "Selective mapping: rotor off below [N]"),
    ParamSpec("SKL_SM_EPS1", "float", 0.0, 5.0, "Selective mapping: rotor fully used above [N]"),
    ParamSpec("SKL_SAT_SCALE", "int", 0, 1, "Beyond the rotors' limit: 1 weight kept, the rest scaled onto it; 0 clip each rotor"),
    ParamSpec("SKL_CA_FAIL", "int", 0, 1, "A failed motor (ESC telemetry): 1 left out, flying on 7; 0 report only"),
    ParamSpec("SKL_TLIM_WARN", "float", 0.01, 10.0, "Rotors at their thrust limit this long: STATUSTEXT warning [s]"),
    ParamSpec("SKL_TLIM_CLR", "float", 0.01, 10.0, "Rotors back within their limit this long: episode over [s]"),
    ParamSpec("SKL_STATE_HZ", "float", 0.0, 500.0, "SKELETON_LINK_STATE rate to the companion [Hz]"),
    ParamSpec("SKL_ODOM_HZ", "float", 0.0, 500.0, "ODOMETRY rate to the companion [Hz]"),
    ParamSpec("SKL_WRENCH_HZ", "float", 0.0, 500.0, "SKELETON_EXTERNAL_WRENCH rate to the companion [Hz] (hybrid)"),
    ParamSpec("SKL_CT_FMAX", "float", 0.1, 200.0, "Largest contact force a command may ask [N] (hybrid)"),
    ParamSpec("SKL_CORR_MAXP", "float", 0.01, 100.0, "Largest correction accepted, position [m]"),
    ParamSpec("SKL_CORR_MAXV", "float", 0.01, 100.0, "Largest correction accepted, velocity [m/s]"),
    ParamSpec("SKL_CORR_MAXR", "float", 0.01, 3.1416, "Largest correction accepted, attitude [rad]"),
    ParamSpec("SKL_GPS_TOUT", "float", 0.1, 60.0, "GPS fault when no fix arrived for [s]"),
    ParamSpec("SKL_GPS_RECOV", "float", 0.0, 60.0, "GPS fault cleared after fixes accepted for [s]"),
    ParamSpec("SKL_GPS_DRIFT", "float", 0.05, 50.0, "GPS fault when positions drift from velocity by [m/s]"),
    ParamSpec("SKL_GPS_RST_T", "float", 0.5, 120.0, "Position reset to GPS after rejected for [s] (no aiding)"),
    ParamSpec("SKL_GPS_AID", "float", 0.0, 10.0, "GPS fault: companion's position fused, std [m] (0 off)"),
    ParamSpec("SKL_GPS_AID_RST", "float", 0.1, 60.0, "GPS fault: reset to corrections refused for [s]"),
    ParamSpec("SKL_GPS_STUCK", "float", 0.0, 60.0, "GPS fault when a fix repeats in flight for [s] (0 off)"),
    ParamSpec("SYS_FAILURE_EN", "int", 0, 1, "Failure injection (MAV_CMD_INJECT_FAILURE): 0 off (denied), 1 on"),
)
#: SKL_CTRL's values, in order (FirmwareConfig.controller)
CONTROLLERS = ("impedance", "se3_pid", "hybrid")
#: SKL_PSPM_EN's values, in order (FirmwareConfig.pspm_mode)
PSPM_MODES = ("off", "on", "bypass")
#: Integer parameters stay within this magnitude (a C-cast PARAM_SET is exact and unambiguous).
FLOAT32_EXACT_INT = 1 << 24
_SPEC = {p.name: p for p in PARAMS}
_ORIGIN_KEY = "origin"  # the parameter file's entry for the origin (not a parameter)
assert all(max(abs(p.minimum), abs(p.maximum)) <= FLOAT32_EXACT_INT for p in PARAMS if p.kind == "int")


@dataclass(frozen=True)
class StreamRates:
    """Default telemetry rates [Hz] of the onboard (companion) link; 0 disables a stream."""

    state_hz: float = 50.0
    odometry_hz: float = 50.0
    #: the observer's SKELETON_EXTERNAL_WRENCH (hybrid controller only; off by default)
    wrench_hz: float = 0.0


def _defaults(system_id: int, config: FirmwareConfig, rates: StreamRates) -> dict[str, float]:
    g = config.gains
    a = config.allocation
    return {
        "MAV_SYS_ID": system_id,
        "IMP_KP_XY": g.kp_n_m[0],
        "IMP_KP_Z": g.kp_n_m[2],
        "IMP_KD_XY": g.kd_ns_m[0],
        "IMP_KD_Z": g.kd_ns_m[2],
        "IMP_KI_XY": g.ki_n_ms[0],
        "IMP_KI_Z": g.ki_n_ms[2],
        "IMP_KR": g.kR_nm,
        "IMP_KW": g.kw_nms,
        "IMP_KI_ATT": g.kI_nm_s,
        "IMP_GAMMA_I": g.gamma_I,
        "IMP_PERR_MAX": g.pos_error_limit_m,
        "SKL_CORR_HOLD": config.correction_hold_s,
        "SKL_CORR_STALE": config.correction_stale_s,
        "COM_OF_LOSS_T": config.target_stale_s,
        "SKL_CTRL": CONTROLLERS.index(config.controller),
        "SKL_PSPM_EN": PSPM_MODES.index(config.pspm_mode),
        "SKL_SM_EN": int(a.selective_mapping),
        "SKL_SM_EPS0": a.eps0_n,
        "SKL_SM_EPS1": a.eps1_n,
        "SKL_SAT_SCALE": int(a.scale_to_limit),
        "SKL_CA_FAIL": int(a.remove_failed_rotor),
        "SKL_TLIM_WARN": config.thrust_limit.warn_after_s,
        "SKL_TLIM_CLR": config.thrust_limit.clear_after_s,
        "SKL_STATE_HZ": rates.state_hz,
        "SKL_ODOM_HZ": rates.odometry_hz,
        "SKL_WRENCH_HZ": rates.wrench_hz,
        "SKL_CT_FMAX": config.contact_max_force_n,
        "SKL_CORR_MAXP": config.correction_max_dp_m,
        "SKL_CORR_MAXV": config.correction_max_dv_m_s,
        "SKL_CORR_MAXR": config.correction_max_dtheta_rad,
        "SKL_GPS_TOUT": config.gps.timeout_s,
        "SKL_GPS_RECOV": config.gps.recover_s,
        "SKL_GPS_DRIFT": config.gps.drift_max_m_s,
        "SKL_GPS_RST_T": config.gps.reset_s,
        "SKL_GPS_AID": config.gps.aid_std_m,
        "SKL_GPS_AID_RST": config.gps.aid_reset_s,
        "SKL_GPS_STUCK": config.gps.stuck_s,
        "SYS_FAILURE_EN": 0,
    }


class ParamTable:
    """Current parameter values, their persistence, and their effect on the firmware config."""

    def __init__(self, system_id: int, config: FirmwareConfig, origin: GeoOrigin, rates: StreamRates,
                 path: Path | None = None):
        self.values = _defaults(system_id, config, rates)
        self._origin = origin
        self.path = path
        self._base = config
        if path is not None and path.exists():
            try:
                stored = json.loads(path.read_text())
                if not isinstance(stored, dict):
                    raise ValueError("not a JSON object")
            except (OSError, ValueError) as exc:
                log.warning("%s: ignoring unreadable parameter file (%s)", path, exc)
                stored = {}
            for name, value in stored.items():
                if name == _ORIGIN_KEY:
                    try:
                        self._origin = GeoOrigin(**value)
                    except (TypeError, ValueError) as exc:
                        log.warning("%s: ignoring the stored origin %r (%s)", path, value, exc)
                    continue
                try:
                    self._validate(name, value)
                except ValueError as exc:
                    log.warning("%s: ignoring %s", path, exc)
                    continue
                if not _SPEC[name].read_only:
                    self.values[name] = value
        self.values["MAV_SYS_ID"] = system_id
        # The table must describe a valid firmware configuration.
        self.firmware_config()

    @property
    def names(self) -> list[str]:
        return [p.name for p in PARAMS]

    def spec(self, name: str) -> ParamSpec | None:
        return _SPEC.get(name)

    def _validate(self, name: str, value) -> float:
        spec = _SPEC.get(name)
        if spec is None:
            raise ValueError(f"{name}: unknown parameter")
        if isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(value):
            raise ValueError(f"{name}: not a finite number ({value!r})")
        if spec.kind == "int" and float(value) != int(value):
            raise ValueError(f"{name}: integer parameter, got {value!r}")
        if not spec.minimum <= value <= spec.maximum:
            raise ValueError(f"{name}: {value} outside [{spec.minimum}, {spec.maximum}]")
        return int(value) if spec.kind == "int" else float(value)

    def set(self, name: str, value) -> None:
        """Validate, apply and persist; raises ``ValueError`` with the reason (nothing changes)."""
        spec = _SPEC.get(name)
        if spec is not None and spec.read_only:
            raise ValueError(f"{name}: read-only")
        value = self._validate(name, value)
        old = self.values[name]
        self.values[name] = value
        try:
            self.firmware_config()
        except ValueError:
            self.values[name] = old
            raise
        self.save()

    def save(self) -> None:
        if self.path is None:
            return
        self.path.parent.mkdir(parents=True, exist_ok=True)
        tmp = self.path.with_suffix(".tmp")
        stored: dict = {k: v for k, v in self.values.items() if not _SPEC[k].read_only}
        stored[_ORIGIN_KEY] = dataclasses.asdict(self._origin)
        tmp.write_text(json.dumps(stored, indent=1))
        tmp.replace(self.path)

    def firmware_config(self) -> FirmwareConfig:
        v = self.values
        gains = replace(
            self._base.gains,
            kp_n_m=(v["IMP_KP_XY"], v["IMP_KP_XY"], v["IMP_KP_Z"]),
            kd_ns_m=(v["IMP_KD_XY"], v["IMP_KD_XY"], v["IMP_KD_Z"]),
            ki_n_ms=(v["IMP_KI_XY"], v["IMP_KI_XY"], v["IMP_KI_Z"]),
            kR_nm=v["IMP_KR"],
            kw_nms=v["IMP_KW"],
            kI_nm_s=v["IMP_KI_ATT"],
            gamma_I=v["IMP_GAMMA_I"],
            pos_error_limit_m=v["IMP_PERR_MAX"],
        )
        allocation = replace(
            self._base.allocation, selective_mapping=bool(v["SKL_SM_EN"]), eps0_n=v["SKL_SM_EPS0"],
            eps1_n=v["SKL_SM_EPS1"], scale_to_limit=bool(v["SKL_SAT_SCALE"]),
            remove_failed_rotor=bool(v["SKL_CA_FAIL"])
        )
        return replace(
            self._base,
            gains=gains,
            allocation=allocation,
            correction_hold_s=v["SKL_CORR_HOLD"],
            correction_stale_s=v["SKL_CORR_STALE"],
            target_stale_s=v["COM_OF_LOSS_T"],
            correction_max_dp_m=v["SKL_CORR_MAXP"],
            correction_max_dv_m_s=v["SKL_CORR_MAXV"],
            correction_max_dtheta_rad=v["SKL_CORR_MAXR"],
            controller=CONTROLLERS[int(v["SKL_CTRL"])],
            contact_max_force_n=v["SKL_CT_FMAX"],
            pspm_mode=PSPM_MODES[int(v["SKL_PSPM_EN"])],
            gps=replace(self._base.gps, timeout_s=v["SKL_GPS_TOUT"], recover_s=v["SKL_GPS_RECOV"],
                        drift_max_m_s=v["SKL_GPS_DRIFT"],
                        reset_s=v["SKL_GPS_RST_T"], aid_std_m=v["SKL_GPS_AID"],
                        aid_reset_s=v["SKL_GPS_AID_RST"], stuck_s=v["SKL_GPS_STUCK"]),
            thrust_limit=replace(self._base.thrust_limit, warn_after_s=v["SKL_TLIM_WARN"],
                                 clear_after_s=v["SKL_TLIM_CLR"]),
        )

    def origin(self) -> GeoOrigin:
        return self._origin

    def set_origin(self, origin: GeoOrigin) -> None:
        """A new shared origin (SET_GPS_GLOBAL_ORIGIN), persisted."""
        self._origin = origin
        self.save()

    def rates(self) -> StreamRates:
        return StreamRates(state_hz=self.values["SKL_STATE_HZ"], odometry_hz=self.values["SKL_ODOM_HZ"],
                           wrench_hz=self.values["SKL_WRENCH_HZ"])
