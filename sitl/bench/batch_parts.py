"""Where a batch flight's wall time goes, part by part, beside MuJoCo alone (the sitl bench's breakdown).

One batch flight of a scenario in this process, with a timer around each part of the runner's tick
(wrapped on the instances, the runner's code unchanged):

* ``physics``: the plant's tick (MuJoCo's two halves of the step, the truth read out, the rotors'
  and ESCs' model, wind);
* ``sensors``: the seeded sensor models (IMU, GPS, attitude reference, barometer, magnetometer);
* ``firmware``: every link's firmware on its ticks, the sensors' time left out; of which
  ``batch kernel``, the quiet ticks of all links in one call (:class:`~link_firmware_sim.batch.LinkBatch`),
  and ``gather and sync``, their state taken into the batch and given back, wherever the runner
  asks for it;
* ``companion``: the companion engine(s): link states in, the 20 Hz step, targets, outputs to the
  firmware;
* ``log``: the log rows (50 Hz);
* ``loop``: the rest (the tick loop itself, faults, the task's hooks).

The timers themselves cost about a microsecond per timed call (a few percent of the total).
"""

from __future__ import annotations

import time

__all__ = ["PARTS", "batch_parts", "markdown_batch_parts"]

#: the parts, in the report's order
PARTS = ("physics", "sensors", "firmware", "companion", "log", "loop")


def _timed(obj, name: str, acc: dict, key: str) -> None:
    """``obj.name`` replaced, on the instance, by the same call timed into ``acc[key]``."""
    fn = getattr(obj, name)
    clock = time.perf_counter

    def timed(*args, **kwargs):
        t0 = clock()
        try:
            return fn(*args, **kwargs)
        finally:
            acc[key] += clock() - t0

    setattr(obj, name, timed)


def batch_parts(config, duration_s: float, warm_s: float = 1.0) -> dict:
    """One batch flight of the scenario file ``config``: ``warm_s`` simulated seconds untimed, then
    ``duration_s`` timed part by part (see the module docstring). Returns the wall milliseconds
    per simulated second of each part (``ms_per_sim_s``), their total and the flight's real-time
    factor, and the batch's counts."""
    from sitl.runner import BatchRunner
    from sitl.scenario import load_scenario

    runner = BatchRunner(load_scenario(config))
    runner.run(warm_s)
    acc = dict.fromkeys(("physics", "sensors", "firmware_tick", "companion", "log", "batch_tick", "gather", "sync"),
                        0.0)
    plant, sensors = runner.plant, runner.plant.sensors
    _timed(plant, "begin_tick", acc, "physics")
    _timed(plant, "end_tick", acc, "physics")
    for name in ("imu", "gps", "attitude", "baro", "mag"):
        _timed(sensors, name, acc, "sensors")
    _timed(runner, "_firmware_tick", acc, "firmware_tick")
    _timed(runner, "_companion_exchange", acc, "companion")
    _timed(runner, "_log_tick", acc, "log")
    batch = runner._link_batch()
    if batch is not None:
        _timed(batch, "tick", acc, "batch_tick")
        _timed(batch, "_gather", acc, "gather")  # (inside tick)
        _timed(batch, "sync", acc, "sync")
    wall0 = time.perf_counter()
    runner.run(duration_s)
    wall = time.perf_counter() - wall0
    per = {k: 1e3 * v / duration_s for k, v in acc.items()}
    ms = {"physics": per["physics"], "sensors": per["sensors"],
          "firmware": per["firmware_tick"] - per["sensors"], "companion": per["companion"], "log": per["log"]}
    total = 1e3 * wall / duration_s
    ms["loop"] = total - sum(ms.values())
    return {"config": str(config), "sim_s": duration_s, "realtime_factor": duration_s / wall, "total_ms_per_sim_s": total,
            "ms_per_sim_s": ms, "batch_kernel_ms_per_sim_s": per["batch_tick"] - per["gather"] if batch else None,
            "gather_sync_ms_per_sim_s": per["gather"] + per["sync"] if batch else None,
            "batch_counts": dict(batch.counts) if batch is not None else None}


def markdown_batch_parts(parts: dict, ceilings: dict) -> str:
    """The breakdown of each scenario's :func:`batch_parts` (``parts``: by scenario name) as a
    Markdown table, beside MuJoCo alone on the same model (``ceilings``: the bench's
    :func:`~sitl.bench.speed.mujoco_ceiling` results, by name): wall milliseconds per simulated
    second, and each part's share of the flight."""
    from .report import md_table

    rows = []
    for name, p in parts.items():
        ceiling = ceilings.get(name)
        mujoco = None if ceiling is None else 1e3 / ceiling["realtime_factor"]
        total = p["total_ms_per_sim_s"]
        cells = [f"{p['ms_per_sim_s'][k]:.1f} ({100 * p['ms_per_sim_s'][k] / total:.0f} %)" for k in PARTS]
        kernel, gather = p.get("batch_kernel_ms_per_sim_s"), p.get("gather_sync_ms_per_sim_s")
        rows.append((name, f"{p['realtime_factor']:.1f}", f"{total:.1f}", "" if mujoco is None else f"{mujoco:.1f}",
                     *cells, "" if kernel is None else f"{kernel:.1f} / {gather:.1f}"))
    return md_table(("batch flight", "RTF (timed)", "total", "MuJoCo alone", *PARTS,
                     "of the firmware: batch kernel / gather and sync"), rows)
