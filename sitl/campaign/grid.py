"""A campaign's grid: scenario files x parameter settings x seeds, one :class:`RunSpec` per run.

Pure functions over strings and frozen records (no simulator, no Dask): what ``--set`` and
``--seeds`` mean, what a run is called (its key in the results table) and where its folder is.
"""

from __future__ import annotations

import hashlib
import itertools
import math
import re
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Literal

from companion.configfile import parse_setting

__all__ = ["RunSpec", "Sweep", "format_value", "parse_sweep", "parse_seeds", "make_grid", "MODES"]

MODES = ("batch", "fleet")

#: characters kept in a folder name made from settings (the others become ``_``)
_FOLDER_SAFE = re.compile(r"[^A-Za-z0-9._=,+-]")
_FOLDER_MAX = 100


def format_value(value: Any) -> str:
    """A setting's value as written in keys, folder names and tables: TOML's spelling for
    numbers, booleans and arrays (``1e-05``, ``true``, ``[1.0, 0.0]``), strings bare."""
    if isinstance(value, bool):
        return "true" if value else "false"
    if isinstance(value, float):
        return repr(value) if math.isfinite(value) else str(value)
    if isinstance(value, (list, tuple)):
        return "[" + ", ".join(format_value(v) for v in value) + "]"
    return str(value)


@dataclass(frozen=True)
class Sweep:
    """One ``--set KEY=V1,V2,...``: a dotted scenario key and the values it takes in turn."""

    key: str
    values: tuple[Any, ...]


def _split_values(text: str) -> list[str]:
    """``text`` split at the commas outside brackets and quotes (``1,2`` -> two values,
    ``[1, 2],[3, 4]`` -> two arrays)."""
    out, depth, quote, start = [], 0, "", 0
    for i, ch in enumerate(text):
        if quote:
            quote = "" if ch == quote else quote
        elif ch in "\"'":
            quote = ch
        elif ch in "[{":
            depth += 1
        elif ch in "]}":
            depth -= 1
        elif ch == "," and depth == 0:
            out.append(text[start:i])
            start = i + 1
    out.append(text[start:])
    return [v.strip() for v in out]


def parse_sweep(text: str) -> Sweep:
    """``"firmware.ekf.gate_sigma=3,4"`` as a :class:`Sweep` of two values, each read as a TOML
    value (:func:`companion.configfile.parse_setting`). ``ValueError`` for a malformed one."""
    key, sep, values = text.partition("=")
    if not sep:
        raise ValueError(f"--set {text!r}: expected KEY=VALUE[,VALUE...], e.g. firmware.ekf.gate_sigma=3,4")
    pieces = _split_values(values)
    if any(not v for v in pieces):
        raise ValueError(f"--set {text!r}: an empty value")
    parsed = [parse_setting(f"{key}={v}") for v in pieces]
    vals = tuple(v for _, v in parsed)
    if len(set(map(format_value, vals))) != len(vals):
        raise ValueError(f"--set {text!r}: a value is given twice")
    return Sweep(parsed[0][0], vals)


def parse_seeds(text: str) -> list[int]:
    """``"0-49"``, ``"3"``, ``"0,5,10-12"``: the seeds (inclusive ranges, in the order given;
    each seed once). ``ValueError`` for anything else."""
    seeds: list[int] = []
    for part in (p.strip() for p in text.split(",")):
        m = re.fullmatch(r"(\d+)(?:-(\d+))?", part)
        if not m:
            raise ValueError(f"--seeds {text!r}: expected seeds and ranges such as 0-49 or 0,3,7-9")
        lo, hi = int(m[1]), int(m[2] or m[1])
        if hi < lo:
            raise ValueError(f"--seeds {text!r}: the range {part} is empty")
        seeds += [s for s in range(lo, hi + 1) if s not in seeds]
    return seeds


@dataclass(frozen=True)
class RunSpec:
    """One run of a campaign: ``config`` (a scenario file) with ``settings`` (dotted keys and
    values set in it, :func:`companion.config.load_setup`), ``seed``, flown in ``mode`` (batch:
    ``python -m sitl fly``; fleet: ``python -m sitl launch --speed 0``). ``duration_s``: the
    scenario's length instead of the file's. ``profile``: the sensor data's profile swapped in
    after loading, the file's EKF tuning kept (what ``sitl.bench nees --profile`` has always
    done; a ``sensors.profile`` setting instead loads as the file would, tuning included)."""

    config: str
    settings: tuple[tuple[str, Any], ...] = ()
    seed: int = 0
    mode: Literal["batch", "fleet"] = "batch"
    duration_s: float | None = None
    profile: str | None = None
    speed: float = 0.0

    def __post_init__(self) -> None:
        if self.mode not in MODES:
            raise ValueError(f"mode must be one of {', '.join(MODES)}, got {self.mode!r}")
        if not (math.isfinite(self.speed) and self.speed >= 0.0):
            raise ValueError(f"speed must be >= 0 (0: unpaced), got {self.speed!r}")
        if self.speed and self.mode != "fleet":
            raise ValueError("speed paces fleet flights: batch mode has no pace")

    @property
    def scenario(self) -> str:
        """The scenario's name in keys and folders: its file's stem."""
        return Path(self.config).stem

    @property
    def settings_label(self) -> str:
        """``key=value,key=value`` in the order given; ``base`` without settings."""
        return ",".join(f"{k}={format_value(v)}" for k, v in self.settings) or "base"

    @property
    def key(self) -> str:
        """The run's key: scenario, mode, settings and seed (what makes two runs the same run)."""
        extra = [f"duration_s={format_value(float(self.duration_s))}"] if self.duration_s is not None else []
        extra += [f"profile={self.profile}"] if self.profile is not None else []
        extra += [f"speed={format_value(float(self.speed))}"] if self.speed else []
        return "|".join([self.scenario, self.mode, self.settings_label, *extra, f"seed={self.seed}"])

    @property
    def group(self) -> str:
        """The key without the seed: the runs a summary pools."""
        return self.key.rsplit("|", 1)[0]

    def folder(self) -> Path:
        """The run's folder inside the campaign's: ``<scenario>[-fleet[-x<speed>]]/<settings>/seed-<S>``
        (settings too long or odd for a folder name: a hash of them)."""
        label = _FOLDER_SAFE.sub("_", self.settings_label)
        if len(label) > _FOLDER_MAX or label.startswith("."):
            label = "settings-" + hashlib.sha256(self.settings_label.encode()).hexdigest()[:12]
        top = self.scenario + ("-fleet" if self.mode == "fleet" else "")
        top += f"-x{format_value(float(self.speed))}" if self.speed else ""
        return Path(top) / label / f"seed-{self.seed}"

    def columns(self) -> dict[str, Any]:
        """The run's key columns in the results table."""
        out: dict[str, Any] = {"scenario": self.scenario, "mode": self.mode}
        out.update({f"set:{k}": format_value(v) for k, v in self.settings})
        if self.duration_s is not None:
            out["duration_s"] = float(self.duration_s)
        if self.profile is not None:
            out["profile"] = self.profile
        if self.speed:
            out["speed"] = float(self.speed)
        out["seed"] = self.seed
        return out


def make_grid(configs: list[str], sweeps: list[Sweep], seeds: list[int], mode: str = "batch",
              duration_s: float | None = None, profile: str | None = None, speed: float = 0.0) -> list[RunSpec]:
    """Every combination of ``configs``, the sweeps' values and ``seeds`` (in that order of
    nesting). ``ValueError`` for a key swept twice or two files of the same name."""
    keys = [s.key for s in sweeps]
    if len(set(keys)) != len(keys):
        raise ValueError(f"--set: a key is swept twice ({', '.join(sorted(k for k in keys if keys.count(k) > 1))})")
    stems = [Path(c).stem for c in configs]
    if len(set(stems)) != len(stems):
        raise ValueError("two scenario files of the same name: their runs would share folders")
    if not seeds:
        raise ValueError("no seeds")
    combos = list(itertools.product(*[[(s.key, v) for v in s.values] for s in sweeps]))
    return [RunSpec(str(c), tuple(combo), int(seed), mode, duration_s, profile, speed)
            for c in configs for combo in combos for seed in seeds]
