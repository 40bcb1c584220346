"""What every ground robot's scenario has (:class:`GroundScenario`): the run's clock rates, the
metrics' settling time, and the commands over time (each kind's own command type, ``t_s`` its
start). No MuJoCo here."""

from __future__ import annotations

from dataclasses import dataclass, replace
from pathlib import Path

from companion.configfile import (ConfigError, build, load_toml, require_finite_positive, require_nonnegative,
                                  require_positive, with_settings)
from companion.motion.oscillators import PhaseMap

__all__ = ["GroundScenario", "GroundControl", "load_ground_scenario", "with_phase_map", "GROUND_SUMMARY",
           "GROUND_TABLES"]

#: the metrics ``python -m sitl fly`` prints of a ground robot's run
GROUND_SUMMARY = ("commands", "distance_m", "heading_change_deg", "servo_rms_deg", "realtime_factor")
#: the top-level tables of a ground robot's scenario file
GROUND_TABLES = ("body", "ground", "cpg", "control", "commands")


@dataclass(frozen=True)
class GroundScenario:
    """A ground robot's run: ``duration_s``, MuJoCo's step ``physics_dt_s``, the CPG's integration
    and output rate ``cpg_rate_hz`` (the thesis: 100 Hz), the log rate, ``settle_s`` (the start of
    each command's window in the metrics, after the CPG's filters and the body settle) and
    ``commands`` (each held from its ``t_s``; the kind's own type). Nothing in a run is random:
    ``seed`` is kept for the run's record and the campaign engine."""

    kind: str = ""
    name: str = "ground"
    description: str = ""
    duration_s: float = 20.0
    seed: int = 0
    physics_dt_s: float = 0.002
    cpg_rate_hz: float = 100.0
    log_rate_hz: float = 50.0
    settle_s: float = 3.0
    commands: tuple = ()

    def __post_init__(self) -> None:
        require_finite_positive(self, "duration_s")
        require_positive(self, "physics_dt_s", "cpg_rate_hz", "log_rate_hz")
        require_nonnegative(self, "settle_s", "seed")
        for name, rate in (("cpg_rate_hz", self.cpg_rate_hz), ("log_rate_hz", self.log_rate_hz)):
            ratio = 1.0 / (rate * self.physics_dt_s)
            if abs(ratio - round(ratio)) > 1e-6 or round(ratio) < 1:
                raise ValueError(f"{name}: a whole number of physics steps ({self.physics_dt_s} s) per period, "
                                 f"got {ratio:.3f}")
        if not self.commands or self.commands[0].t_s != 0.0:
            raise ValueError("commands: the first starts at t_s = 0")
        times = [c.t_s for c in self.commands]
        if any(b <= a for a, b in zip(times, times[1:])):
            raise ValueError(f"commands: t_s must increase, got {times}")

    @property
    def cameras(self) -> tuple:
        """No cameras (the command line's rendering check)."""
        return ()

    def command_at(self, t_s: float):
        """The command in force at ``t_s``."""
        out = self.commands[0]
        for c in self.commands:
            if c.t_s <= t_s + 1e-12:
                out = c
        return out

    def windows(self) -> list[tuple[int, float, float]]:
        """Per command, ``(index, start, end)`` of its metrics window: from ``settle_s`` after it
        starts to the next command (or the run's end); commands too short for one are left out."""
        ends = [c.t_s for c in self.commands[1:]] + [self.duration_s]
        return [(k, c.t_s + self.settle_s, e) for k, (c, e) in enumerate(zip(self.commands, ends))
                if e > c.t_s + self.settle_s]


@dataclass(frozen=True)
class GroundControl:
    """What every ground robot's motion control (``[control]``, thesis sec. 4.6) has: the
    adaptation (eq. 4.3) on or off with its gains ``k_p``, ``k_i`` and its gate
    (:class:`~companion.motion.inverse.SteadyGate`: ``settle_periods``, ``steady_tol``), and the
    line-holding law ``omega_d = -k_y_per_s y - k_heading_per_s psi`` (``y`` [m] the offset from the
    line, ``psi`` the heading off it), limited to ``omega_max_rad_s``. (The thesis gives none of
    these gains.)"""

    adapt: bool = False
    k_p: float = 0.2
    k_i: float = 0.1
    settle_periods: int = 2
    steady_tol: float = 0.05
    k_y_per_s: float = 0.2
    k_heading_per_s: float = 0.5
    omega_max_rad_s: float = 0.6

    def __post_init__(self) -> None:
        require_nonnegative(self, "k_p", "k_i", "settle_periods", "k_y_per_s", "k_heading_per_s")
        require_positive(self, "steady_tol", "omega_max_rad_s")


def load_ground_scenario(cls: type, path: str | Path, settings=None, **overrides):
    """Read a ground robot's scenario of class ``cls`` (:class:`~companion.configfile.ConfigError`
    naming the key); ``settings``: dotted keys set in the file's tables; ``overrides``: top-level
    fields (e.g. ``duration_s``), checked as if the file held them."""
    data = {**load_toml(path), **overrides}
    if settings:
        data = with_settings(data, settings, file=str(path))
    return build(cls, data, file=str(path))


def with_phase_map(sc, path: str | Path, table: str):
    """``sc`` with the phase map its ``phase_map_file`` names (relative to the scenario ``path``):
    the file's ``[table]`` replaces the CPG's field ``table`` (eq. 4.1's map from a sweep:
    :mod:`.phase_sweep`), the file's path made absolute; ``sc`` itself without a file.
    :class:`~companion.configfile.ConfigError` for a file that cannot be read or a map the CPG
    refuses (e.g. of the wrong inputs)."""
    if not sc.phase_map_file:
        return sc
    map_path = Path(path).resolve().parent / sc.phase_map_file
    try:
        data = load_toml(map_path)
    except (OSError, ConfigError) as exc:
        raise ConfigError(str(path), "phase_map_file", f"cannot read {map_path}: {exc}") from None
    phase = build(PhaseMap, data.get(table, {}), file=str(map_path), prefix=table)
    try:
        return replace(sc, phase_map_file=str(map_path), cpg=replace(sc.cpg, **{table: phase}))
    except ValueError as exc:
        raise ConfigError(str(path), "phase_map_file", f"{map_path}: {exc}") from None
