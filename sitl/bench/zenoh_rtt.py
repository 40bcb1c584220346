"""Global step over Zenoh on loopback: one process per group, the leader prints the round trip.

Each group process opens its own Zenoh peer session on ``tcp/127.0.0.1`` (the SITL layout: a
full mesh, multicast scouting off), runs a :class:`~companion.fleetnet.group.GroupLink` and every
``period`` publishes its boundary for the cycle (cycles on the shared monotonic clock, so the
groups step together as companions do whose links stream in phase). Boundaries come from one
seeded 7-link snapshot (Alg. 2 per group, :func:`~companion.estimation.semi.semi_distributed_apply`),
so every process can also check the shift it receives against the in-process eq. 6 result.
Optionally the leader's process is killed partway (``kill_leader_at_s``) to time the failover.
"""

from __future__ import annotations

import math
import multiprocessing as mp
import select
import time

import numpy as np

from companion.estimation.semi import Groups, semi_distributed_apply

__all__ = ["run_zenoh_rtt", "format_zenoh_rtt", "markdown_zenoh_rtt"]


def _snapshot(seed: int, n_links: int, groups):
    """A seeded EKF-like chain snapshot and its semi-distributed solution (same in every process)."""
    rng = np.random.default_rng(seed)
    q = np.tile([1.0, 0.0, 0.0, 0.0], (n_links, 1))
    p = np.stack([[i * 1.0, 0.0, 2.0] for i in range(n_links)]) + rng.normal(scale=0.3, size=(n_links, 3))
    v = rng.normal(scale=0.1, size=(n_links, 3))
    w = np.zeros((n_links, 3))
    d = np.tile([0.5, 0.0, 0.0], (n_links, 1))
    A = rng.normal(scale=0.1, size=(n_links, 9, 9))
    P = A @ np.swapaxes(A, 1, 2) * 0.1 + np.diag([0.1] * 6 + [0.01] * 3)
    return semi_distributed_apply(p, v, q, w, d, P, groups)


def _group_main(group: int, endpoints: tuple[str, ...], prefix: str, period_us: int, start_s: float, end_s: float,
                seed: int, groups: Groups, results) -> None:
    from companion.fleetnet.bus import FleetBus
    from companion.fleetnet.config import ZenohConfig
    from companion.fleetnet.group import GroupLink
    from companion.fleetnet.leader import GlobalStepNode

    ref = _snapshot(seed, groups[-1][-1] + 1, groups)
    b = ref.boundaries[group]
    cfg = ZenohConfig(endpoints=endpoints)
    s = len(groups)
    link = GroupLink(GlobalStepNode(group, s, cfg.order(s), period_us, shift_deadline_s=cfg.shift_deadline_ms * 1e-3,
                                    leader_wait_s=cfg.leader_wait_ms * 1e-3), FleetBus(cfg, prefix, group, s))
    max_err = 0.0
    next_cycle = int(math.ceil(start_s * 1e6 / period_us)) * period_us
    try:
        while (now := time.monotonic()) < end_s:
            due = min(next_cycle * 1e-6, link.next_deadline_s(now) or math.inf, end_s)
            select.select([link], [], [], max(due - now, 0.0))
            now = time.monotonic()
            resolved = link.pump(now)
            if now * 1e6 >= next_cycle:
                resolved += link.local_step(b.left_tip, b.right_tip, b.info_pv, next_cycle, time.monotonic())
                next_cycle += period_us * max(1, int((now * 1e6 - next_cycle) // period_us) + 1)
            for res in resolved:
                if res.shift is not None:
                    max_err = max(max_err, float(np.max(np.abs(res.shift - ref.shifts[group]))))
        results.put({"group": group + 1, **link.summary(), "max_shift_error_vs_in_process": max_err})
    finally:
        link.close()


def run_zenoh_rtt(groups: Groups, duration_s: float = 20.0, rate_hz: float = 20.0, seed: int = 0,
                  base_port: int = 17447, prefix: str = "bench_zenoh") -> dict:
    """Run one process per group (0-based ``groups``) for ``duration_s``; collect their summaries."""
    n_links = groups[-1][-1] + 1
    s = len(groups)
    endpoints = tuple(f"tcp/127.0.0.1:{base_port + g}" for g in range(s))
    ctx = mp.get_context("spawn")  # Zenoh runs threads: never fork a process that holds a session
    results = ctx.Queue()
    start = time.monotonic() + 3.0  # spawn + session set-up
    procs = [ctx.Process(target=_group_main, args=(g, endpoints, prefix, int(round(1e6 / rate_hz)), start,
                                                   start + duration_s, seed, groups, results))
             for g in range(s)]
    for p in procs:
        p.start()
    out = [results.get(timeout=duration_s + 60) for _ in procs]
    for p in procs:
        p.join(10)
    out.sort(key=lambda r: r["group"])
    leader = max(out, key=lambda r: r["global_step"]["led"])
    return {"n_links": n_links, "groups": [[i + 1 for i in g] for g in groups], "rate_hz": rate_hz,
            "duration_s": duration_s, "leader": leader["group"],
            "round_trip_ms": leader["round_trip_ms_as_leader"], "companions": out}


def format_zenoh_rtt(result: dict) -> str:
    rt = result["round_trip_ms"] or {}
    lines = [f"{result['n_links']} links, groups {result['groups']}, {result['rate_hz']:g} Hz, {result['duration_s']:g} s; "
             f"leader: group {result['leader']}"]
    for part in ("network", "end_to_end"):
        r = rt.get(part)
        if r:
            lines.append(f"  round trip ({part.replace('_', ' ')}): p50 {r['p50']:.3f} ms  p99 {r['p99']:.3f} ms  "
                         f"max {r['max']:.3f} ms  ({r['samples']} boundaries)")
    for c in result["companions"]:
        g = c["global_step"]
        lines.append(f"  group {c['group']}: cycles with global step {g['global']}, local-only {g['local_only']}, "
                     f"max |shift - in-process eq. 6| {c['max_shift_error_vs_in_process']:.2e}")
    return "\n".join(lines)


def markdown_zenoh_rtt(result: dict) -> str:
    """The Markdown tables of a :func:`run_zenoh_rtt` result (``zenoh.json``): :func:`format_zenoh_rtt`'s figures."""
    from .report import md_table

    rt = result["round_trip_ms"] or {}
    parts = [f"{result['n_links']} links, groups {result['groups']}, {result['rate_hz']:g} Hz, "
             f"{result['duration_s']:g} s on loopback; leader: group {result['leader']}.", "",
             "## Round trip as the leader saw it (boundary published -> shift received) [ms]", ""]
    rows = [(part.replace("_", " "), f"{r['p50']:.3f}", f"{r['p99']:.3f}", f"{r['max']:.3f}", r["samples"])
            for part in ("network", "end_to_end") if (r := rt.get(part))]
    parts.append(md_table(("round trip", "p50", "p99", "max", "boundaries"), rows) if rows
                 else "No round trip measured (no leader reported one).")
    rows = [(c["group"], ", ".join(str(i) for i in result["groups"][c["group"] - 1]), c["global_step"]["global"],
             c["global_step"]["local_only"], f"{c['max_shift_error_vs_in_process']:.2e}")
            for c in result["companions"]]
    parts += ["", "## Per group", "",
              md_table(("group", "links", "cycles with global step", "local-only cycles",
                        "max abs(shift - in-process eq. 6)"), rows)]
    return "\n".join(parts)
