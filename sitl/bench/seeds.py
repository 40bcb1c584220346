"""One SITL scenario flown over many seeds, and what only many seeds can show.

* :func:`seed_specs`: the runs of a scenario over seeds, flown by the campaign engine
  (:mod:`sitl.campaign`) each into its own folder ``<run>/seed-<S>`` (metrics.json, log.npz,
  scenario.toml, run.log); the seeds are the scenario's seed field, so every run is reproducible
  alone with ``python -m sitl fly --config <run>/seed-<S>/scenario.toml``.
* :func:`aggregate_nees`: the Monte Carlo consistency test (Bar-Shalom, Li & Kirubarajan,
  *Estimation with Applications to Tracking and Navigation*, sec. 5.4.2): per link and 3-dof
  block, the NEES averaged over the window and over the N seeds. For a consistent filter it is
  3 on average, and the average over N independent runs of ``K_eff`` effective samples each lies
  within the chi-square bounds of ``N K_eff`` samples. One flight has few independent position
  errors (the GPS errors stay correlated for about as long as the flight), so only the seeds
  make the position test sharp.
* :func:`aggregate_static`: the thesis's sec. 3.5.2 static test as a protocol: per link and
  axis the standard deviation of the estimated position over the window and its RMS error
  against the truth, for the EKF alone, the local constraint application and the
  semi-distributed one, mean and spread over the seeds, beside the thesis's figures.

Pure functions over metrics dicts; the CLI is ``python -m sitl.bench nees`` and
``python -m sitl.bench static``.
"""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np

from sitl.campaign.grid import RunSpec
from sitl.metrics import NEES_BLOCKS, STATIC_ESTIMATES, THESIS_STATIC_LINK4_STD_M, nees_bounds95

__all__ = ["seed_specs", "seed_folder", "aggregate_nees", "format_nees", "aggregate_static", "format_static",
           "independent_reduction", "markdown_nees", "markdown_static"]



def seed_specs(config: str | Path, seeds: list[int], duration_s: float | None = None,
               profile: str | None = None) -> list[RunSpec]:
    """The batch runs of ``config`` once per seed (``duration_s``: instead of the file's;
    ``profile``: the sensor data's profile, the file's EKF tuning kept)."""
    return [RunSpec(str(config), (), int(s), "batch", duration_s, profile) for s in seeds]


def seed_folder(spec: RunSpec) -> Path:
    """A seed's folder in a bench's run folder: ``seed-<S>``."""
    return Path(f"seed-{spec.seed}")


def aggregate_nees(runs: list[dict]) -> dict:
    """The Monte Carlo NEES test over the runs' ``nees`` metrics (one run per seed).

    Per estimate (``ekf``, ``corrected``), block and link: ``mean`` (over seeds of the
    time-averaged NEES), ``per_seed``, ``effective_samples`` (summed over seeds),
    ``bounds95`` for that many (:func:`sitl.metrics.nees_bounds95`) and ``inside95``.
    ``bounds95_independent``: the bounds if every step were independent (``N K`` samples)."""
    nees = [r["nees"] for r in runs if r.get("nees")]
    if not nees:
        raise ValueError("no run has NEES figures (a flight with the companion's steps and the truth)")
    out: dict = {"seeds": [r.get("seed") for r in runs if r.get("nees")], "scenario": runs[0].get("scenario"),
                 "samples_per_seed": [x["samples"] for x in nees]}
    out["bounds95_independent"] = nees_bounds95(sum(out["samples_per_seed"])).tolist()
    for which in ("ekf", "corrected"):
        out[which] = {}
        for block in NEES_BLOCKS:
            per_seed = np.array([x[which][block] for x in nees], dtype=float)  # (N, n)
            k_eff = np.sum([x["effective_samples"][which][block] for x in nees], axis=0)  # (n,)
            mean = np.nanmean(per_seed, axis=0)
            bounds = nees_bounds95(k_eff)
            out[which][block] = {
                "mean": mean.tolist(),
                "per_seed": per_seed.tolist(),
                "effective_samples": np.round(k_eff, 1).tolist(),
                "bounds95": bounds.tolist(),
                "inside95": ((bounds[:, 0] <= mean) & (mean <= bounds[:, 1])).tolist(),
            }
    return out


def format_nees(result: dict) -> str:
    """The Monte Carlo NEES table: per estimate and block, each link's mean with its bounds."""
    lines = [f"NEES over {len(result['seeds'])} seed(s) of {result['scenario']} "
             f"(3: consistent; below the band: the covariance is larger than the error, above: smaller)",
             f"bounds if every step were independent: {result['bounds95_independent'][0]:.2f}-"
             f"{result['bounds95_independent'][1]:.2f}", ""]
    for which in ("ekf", "corrected"):
        for block in NEES_BLOCKS:
            row = result[which][block]
            cells = [f"{m:5.2f} [{lo:.2f}-{hi:.2f}]{'' if ok else ' OUT'}"
                     for m, (lo, hi), ok in zip(row["mean"], row["bounds95"], row["inside95"])]
            lines.append(f"{which:>9} {block:>3}: " + "  ".join(cells))
    return "\n".join(lines)


def independent_reduction(n_links: int) -> float:
    """How much kinematic constraints can shrink one link's error at most when all ``n`` links
    err independently and alike: the constraints fix every link relative to the others, so
    what remains is the chain's common error, the mean of ``n`` independent errors (std / sqrt(n))."""
    return math.sqrt(n_links)


def aggregate_static(runs: list[dict]) -> dict:
    """The static protocol over the runs' ``static`` metrics (one run per seed): per estimate,
    link and axis the ``std_m`` and ``rms_err_m`` mean and spread (``*_spread``: the standard
    deviation over seeds), link 4's row beside the thesis, and the reduction the constraints
    achieved (EKF / semi-distributed, per axis, of the mean RMS error) against
    :func:`independent_reduction`."""
    static = [r["static"] for r in runs if r.get("static")]
    if not static:
        raise ValueError("no run has static figures (a resting chain with the companion's steps)")
    n = len(static[0]["std_m"]["ekf"])
    out: dict = {"seeds": [r.get("seed") for r in runs if r.get("static")], "scenario": runs[0].get("scenario"),
                 "n_links": n, "thesis_link4_std_m": THESIS_STATIC_LINK4_STD_M,
                 "independent_reduction": independent_reduction(n)}
    for figure in ("std_m", "rms_err_m"):
        out[figure] = {}
        for name in [e for e, _ in STATIC_ESTIMATES] + ["truth"]:
            vals = [s[figure][name] for s in static if name in s[figure]]
            if not vals:
                continue
            arr = np.array(vals, dtype=float)  # (N, n, 3)
            out[figure][name] = {"mean": arr.mean(axis=0).tolist(),
                                 "spread": (arr.std(axis=0, ddof=1) if len(arr) > 1 else 0 * arr[0]).tolist()}
    rms = out["rms_err_m"]
    if "semi_distributed" in rms:
        ekf, semi = np.array(rms["ekf"]["mean"]), np.array(rms["semi_distributed"]["mean"])
        out["reduction_rms"] = {"per_link": (ekf / semi).tolist(),
                                "chain": (np.sqrt(np.mean(ekf ** 2, axis=0)) / np.sqrt(np.mean(semi ** 2, axis=0))).tolist()}
    return out


def format_static(result: dict) -> str:
    """Link 4 beside the thesis, then every link's RMS error; mean +- spread over seeds."""
    n = result["n_links"]
    link = min(3, n - 1)

    def cell(entry, i, j):
        return f"{entry['mean'][i][j]:.3f}+-{entry['spread'][i][j]:.3f}"

    lines = [f"static protocol: {result['scenario']}, {len(result['seeds'])} seed(s) {result['seeds']}, "
             "mean +- spread over seeds [m]", "",
             f"link {link + 1} std of the estimate over the window, x / y / z (the thesis's figure)"]
    for name in ("ekf", "local", "semi_distributed", "truth"):
        entry = result["std_m"].get(name)
        if entry is None:
            continue
        thesis = result["thesis_link4_std_m"].get(name) if n == 7 else None
        ttxt = f"   thesis {' / '.join(f'{x:.3f}' for x in thesis)}" if thesis else ""
        lines.append(f"  {name:>16}: " + " / ".join(cell(entry, link, j) for j in range(3)) + ttxt)
    lines += ["", "RMS error against the truth per link, x / y / z"]
    for name in ("ekf", "local", "semi_distributed"):
        entry = result["rms_err_m"].get(name)
        if entry is None:
            continue
        lines.append(f"  {name}:")
        for i in range(n):
            lines.append(f"    link {i + 1}: " + " / ".join(cell(entry, i, j) for j in range(3)))
    red = result.get("reduction_rms")
    if red:
        lines += ["", "RMS error EKF / semi-distributed, x / y / z: chain "
                  + " / ".join(f"{x:.2f}" for x in red["chain"])
                  + f", link {link + 1} " + " / ".join(f"{x:.2f}" for x in red["per_link"][link])
                  + f"; at most sqrt({n}) = {result['independent_reduction']:.2f} for independent equal errors"]
    return "\n".join(lines)


def _run_line(result: dict) -> str:
    extra = []
    if result.get("profile") is not None:
        extra.append(f"sensor profile {result['profile']}")
    if result.get("duration_s") is not None:
        extra.append(f"{result['duration_s']:g} s per flight")
    return (f"{result['scenario']}, {len(result['seeds'])} seed(s) ({', '.join(str(s) for s in result['seeds'])})"
            + (f", {', '.join(extra)}" if extra else ""))


def markdown_nees(result: dict) -> str:
    """The Markdown tables of an :func:`aggregate_nees` result (``nees.json``): :func:`format_nees`'s
    figures, one table per estimate with a row per link."""
    from .report import md_table

    lo_i, hi_i = result["bounds95_independent"]
    parts = [f"Monte Carlo NEES: {_run_line(result)}. Per link and 3-dof block, the NEES averaged over the window "
             "and the seeds (3: consistent; below the bounds the covariance is larger than the error, above it "
             f"is smaller) with the 95 % bounds of that average; **out**: outside. Bounds if every step were "
             f"independent: {lo_i:.2f}-{hi_i:.2f}."]
    titles = {"ekf": "EKF (each link's own filter)", "corrected": "corrected (after the companion's SCKF)"}
    for which in ("ekf", "corrected"):
        n = len(result[which][NEES_BLOCKS[0]]["mean"])
        rows = []
        for i in range(n):
            cells = []
            for block in NEES_BLOCKS:
                row = result[which][block]
                lo, hi = row["bounds95"][i]
                cells.append(f"{row['mean'][i]:.2f} [{lo:.2f}-{hi:.2f}]" + ("" if row["inside95"][i] else " **out**"))
            rows.append((f"link {i + 1}", *cells))
        parts += ["", f"## {titles[which]}", "", md_table(("link", *NEES_BLOCKS), rows)]
    return "\n".join(parts)


def markdown_static(result: dict) -> str:
    """The Markdown tables of an :func:`aggregate_static` result (``static.json``): :func:`format_static`'s
    figures (mean ± spread over the seeds, metres)."""
    from .report import md_table

    n = result["n_links"]
    link = min(3, n - 1)

    def cell(entry, i, j):
        return f"{entry['mean'][i][j]:.3f} ± {entry['spread'][i][j]:.3f}"

    parts = [f"Static protocol (thesis sec. 3.5.2): {_run_line(result)}; mean ± spread over the seeds, metres."]
    rows = []
    for name in ("ekf", "local", "semi_distributed", "truth"):
        entry = result["std_m"].get(name)
        if entry is None:
            continue
        thesis = result["thesis_link4_std_m"].get(name) if n == 7 else None
        rows.append((name, *(cell(entry, link, j) for j in range(3)),
                     " / ".join(f"{x:.3f}" for x in thesis) if thesis else "-"))
    parts += ["", f"## Link {link + 1}: std of the estimate over the window (the thesis's figure)", "",
              md_table(("estimate", "x", "y", "z", "thesis x / y / z"), rows)]
    names = [name for name in ("ekf", "local", "semi_distributed") if name in result["rms_err_m"]]
    rows = [(f"link {i + 1}", *(cell(result["rms_err_m"][name], i, j) for name in names for j in range(3)))
            for i in range(n)]
    parts += ["", "## RMS error against the truth per link", "",
              md_table(("link", *(f"{name} {axis}" for name in names for axis in "xyz")), rows)]
    red = result.get("reduction_rms")
    if red:
        parts += ["", "RMS error EKF / semi-distributed, x / y / z: chain "
                  + " / ".join(f"{x:.2f}" for x in red["chain"])
                  + f", link {link + 1} " + " / ".join(f"{x:.2f}" for x in red["per_link"][link])
                  + f"; at most sqrt({n}) = {result['independent_reduction']:.2f} for independent equal errors."]
    return "\n".join(parts)
