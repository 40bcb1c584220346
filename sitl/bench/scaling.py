"""Per-step cost of the constraint application vs. chain length (paper Fig. 3 analogue).

For each chain length the per-link EKFs run on the synthetic chain (short run, the first
seconds dropped as filter transient) and every 20 Hz tick is corrected by:

* ``full``: Alg. 1 on the whole chain (``constraint_apply``, structured solver);
* ``semi2``: Alg. 2 with groups of 2 links plus the global step of eq. 6;
* ``full_dense_reference``: Alg. 1 on the dense ``9n x 9n`` covariance, only up to
  :data:`DENSE_CAP_LINKS` links (it grows as ``n^3``).

Figures are wall-clock milliseconds per 20 Hz step (mean over the ticks), measured in one
process so that the ratios are comparable.
"""

from __future__ import annotations

import time
from dataclasses import replace

import numpy as np

from companion.kernels import warm as companion_kernels
from companion.estimation.sckf import CAParams, constraint_apply_dense, constraint_apply_structured
from companion.estimation.semi import make_groups, semi_distributed_apply
from sitl.synthetic import ChainMotion

from .ekf_chain import ChainRun, simulate_ekf_chain

__all__ = ["LINK_COUNTS", "DENSE_CAP_LINKS", "run_scaling", "format_scaling", "markdown_scaling"]

LINK_COUNTS = (3, 7, 12, 24, 48, 96)
DENSE_CAP_LINKS = 24


def _time_per_step(fn, stream, ticks) -> tuple[float, float]:
    times, iters = [], []
    for k in ticks:
        args = (stream.p[k], stream.v[k], stream.q[k], stream.w[k], stream.d, stream.P[k])
        t0 = time.perf_counter()
        res = fn(*args)
        times.append(time.perf_counter() - t0)
        iters.append(np.max(res.iterations) if np.ndim(res.iterations) else res.iterations)
    return 1e3 * float(np.mean(times)), float(np.mean(iters))


def run_scaling(
    seed: int = 0,
    link_counts=LINK_COUNTS,
    duration_s: float = 5.0,
    transient_s: float = 2.0,
    params: CAParams = CAParams(),
    progress=None,
) -> dict:
    result = {"full": {}, "semi2": {}, "full_dense_reference": {}, "iterations": {}, "protocol": {}}
    companion_kernels.warm_up()  # the compiled kernels loaded before anything is timed
    for n in link_counts:
        run = ChainRun(motion=replace(ChainMotion(), n_links=n), duration_s=duration_s)
        stream = simulate_ekf_chain(run, seed)
        ticks = [k for k in range(stream.t.size) if stream.t[k] > transient_s]
        groups = make_groups(n, 2)
        ms_full, it_full = _time_per_step(
            lambda *a: constraint_apply_structured(*a, params), stream, ticks
        )
        ms_semi, it_semi = _time_per_step(lambda *a: semi_distributed_apply(*a, groups, params), stream, ticks)
        result["full"][str(n)] = ms_full
        result["semi2"][str(n)] = ms_semi
        result["iterations"][str(n)] = {"full": it_full, "semi2_max_group": it_semi}
        if n <= DENSE_CAP_LINKS:
            ms_dense, _ = _time_per_step(lambda *a: constraint_apply_dense(*a, params, compiled=False), stream, ticks)
            result["full_dense_reference"][str(n)] = ms_dense
        if progress is not None:
            progress(1)
    result["protocol"] = {
        "seed": seed,
        "duration_s": duration_s,
        "transient_s": transient_s,
        "steps_per_n": len(ticks),
        "eps": params.eps,
        "alpha": params.alpha,
        "dense_cap_links": DENSE_CAP_LINKS,
    }
    return result


def format_scaling(result: dict) -> str:
    lines = [
        "Constraint application per 20 Hz step [ms] (mean over ticks; iterations = mean CA loops)",
        "",
        f"{'n links':>7} | {'full SCKF':>9} | {'semi (2)':>8} | {'dense ref':>9} | {'iters full':>10}",
        "-" * 56,
    ]
    for n, ms in result["full"].items():
        dense = result["full_dense_reference"].get(n)
        dtxt = f"{dense:9.3f}" if dense is not None else f"{'(capped)':>9}"
        lines.append(
            f"{n:>7} | {ms:9.3f} | {result['semi2'][n]:8.3f} | {dtxt} | {result['iterations'][n]['full']:10.2f}"
        )
    return "\n".join(lines)


def markdown_scaling(result: dict) -> str:
    """The Markdown table of a :func:`run_scaling` result (``scaling.json``): :func:`format_scaling`'s figures."""
    from .report import fmt, md_table

    proto = result.get("protocol", {})
    rows = []
    for n, ms in result["full"].items():
        it = result["iterations"][n]
        rows.append((n, f"{ms:.3f}", f"{result['semi2'][n]:.3f}",
                     fmt(result["full_dense_reference"].get(n), ".3f", "(capped)"), f"{it['full']:.2f}",
                     f"{it['semi2_max_group']:.2f}"))
    intro = ("Constraint application per 20 Hz step, wall-clock milliseconds (mean over "
             f"{proto.get('steps_per_n', '?')} steps per chain length after a {proto.get('transient_s', 0):g} s "
             f"transient of a {proto.get('duration_s', 0):g} s run; seed {proto.get('seed')}, eps "
             f"{proto.get('eps', 0):g}, alpha {proto.get('alpha', 0):g}). Dense reference only up to "
             f"{proto.get('dense_cap_links', DENSE_CAP_LINKS)} links. Iterations: mean CA loops (semi: the "
             "group with the most).")
    header = ("n links", "full SCKF [ms]", "semi, groups of 2 [ms]", "dense reference [ms]", "iterations full",
              "iterations semi")
    return "\n".join([intro, "", md_table(header, rows)])
