"""Every rate of a scenario as a whole number of physics ticks."""

from __future__ import annotations

from dataclasses import dataclass

__all__ = ["rate_divisor", "Schedule"]


def rate_divisor(base_hz: float, rate_hz: float, name: str) -> int:
    """Ticks of the base rate per event of ``rate_hz``; ``ValueError`` unless a whole multiple."""
    if not (rate_hz > 0 and base_hz > 0):
        raise ValueError(f"{name}: rates must be positive (base {base_hz} Hz, {name} {rate_hz} Hz)")
    ratio = base_hz / rate_hz
    div = round(ratio)
    if div < 1 or abs(ratio - div) > 1e-9 * ratio:
        raise ValueError(f"{name} rate {rate_hz} Hz is not a whole divisor of the base tick rate {base_hz} Hz")
    return int(div)


@dataclass(frozen=True)
class Schedule:
    """Every rate of a scenario as a whole number of physics ticks."""

    dt: float
    fw: int
    gps: int
    att: int
    log: int
    baro: int
    mag: int

    @classmethod
    def of(cls, sc) -> Schedule:
        """The schedule of a :class:`~sitl.scenario.Scenario` (its ``sim``, ``firmware`` and ``sensors`` rates)."""
        physics = sc.sim.physics_rate_hz
        fw = rate_divisor(physics, sc.firmware.rate_hz, "firmware.rate_hz")
        return cls(
            dt=1.0 / physics,
            fw=fw,
            gps=fw * rate_divisor(sc.firmware.rate_hz, sc.sensors.gps_rate_hz, "gps"),
            att=fw * rate_divisor(sc.firmware.rate_hz, sc.sensors.attitude_rate_hz, "attitude"),
            log=rate_divisor(physics, sc.sim.log_rate_hz, "log_rate_hz"),
            baro=fw * rate_divisor(sc.firmware.rate_hz, sc.sensors.baro_rate_hz, "baro"),
            mag=fw * rate_divisor(sc.firmware.rate_hz, sc.sensors.mag_rate_hz, "mag"),
        )
