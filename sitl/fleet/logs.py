"""What a fleet run leaves: every process's log merged with the harness's truth on
flight-controller time, the MAVLink counters of every process, the scripted faults' report and
the distributed companions' figures (all from the run folder's files).
"""

from __future__ import annotations

import json
import logging
from pathlib import Path

import numpy as np

from companion.linkstate import word as state_word
from companion.logstream import read_log_stream
from link_firmware_sim.events import statustext_arrays
from link_firmware_sim.vehicle.hil import SITL_GPS_EPOCH_US
from link_firmware_sim.vehicle.simlink import is_simlink_url
from sitl.metrics import reboot_timeline
from sitl.scenario import Scenario
from sitl.steplog import attach_truth, merge_step_logs

from .faults import restart_folder
from .layout import FleetError

__all__ = ["load_run_log", "merge_logs", "vehicle_log", "companion_log", "companion_summaries", "mavlink_counters",
           "fault_windows", "fault_report", "distributed_metrics"]

log = logging.getLogger(__name__)


def load_run_log(folder: Path, stem: str) -> dict[str, np.ndarray] | None:
    """A process's log in a fleet run folder: ``<stem>.npz`` (written at a clean exit), else what
    its ``<stem>.stream`` holds (a killed process: up to its last flush), else ``None``."""
    npz, stream = folder / f"{stem}.npz", folder / f"{stem}.stream"
    if npz.exists():
        return dict(np.load(npz))
    if stream.exists():
        return read_log_stream(stream) or None
    return None


def merge_logs(sc: Scenario, truth: dict[str, np.ndarray],
                out_dir: Path) -> tuple[dict[str, np.ndarray], np.ndarray, list[int]]:
    """Align the vehicles', the companion's and the harness's logs on flight-controller time;
    returns the merged log, the correction latencies and the links (1-based) without a flight log."""
    n = sc.skeleton.n_links
    t_us = np.round(truth["t"] * 1e6).astype(np.int64)
    index = {int(x): i for i, x in enumerate(t_us)}
    fw = [vehicle_log(out_dir, i) for i in range(n)]
    missing = [i + 1 for i, f in enumerate(fw) if f is None]
    if len(missing) == n:
        raise FleetError("no vehicle wrote its flight log")
    if missing:
        log.warning("no flight log from link(s) %s (killed): their estimates are NaN in the metrics", missing)
    # Every simulator row that some vehicle logged: a link that was not flying its firmware then
    # (not started yet, killed, rebooting) has NaN estimates in that row.
    logged: set[int] = set()
    for f in fw:
        if f is not None:
            logged |= set(np.round(f["t"] * 1e6).astype(np.int64).tolist())
    times = np.array(sorted(set(t_us.tolist()) & logged), dtype=np.int64)
    if times.size == 0:
        raise FleetError("the vehicles' flight logs and the simulator log share no time stamps")
    rows = [index[int(x)] for x in times]
    merged = {
        "t": times * 1e-6,
        "p_true": truth["p_true"][rows],
        "v_true": truth["v_true"][rows],
        "q_true": truth["q_true"][rows],
        "thrust": truth["thrust"][rows],
        "joint_force_true": truth["joint_force_true"][rows],
        "tension_true": truth["tension_true"][rows],
    }
    fw_rows = []  # per link: the row of its log at each merged time (-1: none)
    for f in fw:
        if f is None:
            fw_rows.append(None)
            continue
        ft = {int(x): i for i, x in enumerate(np.round(f["t"] * 1e6).astype(np.int64))}
        fw_rows.append(np.array([ft.get(int(x), -1) for x in times], dtype=np.int64))
    present = next(f for f in fw if f is not None)
    for key in ("p_ekf", "q_ekf", "p_ctrl", "q_ctrl", "p_target", "q_target"):
        columns = []
        for f, r in zip(fw, fw_rows):
            col = np.full((times.size,) + present[key].shape[1:], np.nan)
            if f is not None:
                col[r >= 0] = f[key][r[r >= 0]]
            columns.append(col)
        merged[key] = np.stack(columns, axis=1)
    comp = companion_log(sc, out_dir)
    if comp is not None:
        if sc.companion.time_base == "gps":  # a companion on GPS time: the simulated GPS clock
            comp["t_sckf"] = (np.round(comp["t_sckf"] * 1e6).astype(np.int64) - SITL_GPS_EPOCH_US) * 1e-6
        merged.update(attach_truth(comp, truth["t"], truth["p_true"], truth["v_true"], truth["q_true"]))
    homes = [s["home_offset_m"] for s in companion_summaries(out_dir).values() if s.get("home_offset_m") is not None]
    if homes:  # where the companions flew the trajectory from (:func:`companion.trajectory.planned_positions`)
        merged["home_offset_w_m"] = np.array(homes[0], dtype=float)
    merged.update(_link_states(merged, fw, fw_rows))
    merged.update(statustext_arrays([(t, i + 1, sev, text) for i, f in enumerate(fw) if f is not None
                                     for t, sev, text in zip(f["statustext_t"].tolist(), f["statustext_severity"].tolist(),
                                                             f["statustext_text"].tolist())]))
    logs = [f["correction_latency"] for f in fw if f is not None]
    latency = np.concatenate(logs) if logs else np.zeros((0, 2))
    return merged, latency, missing


def _link_states(merged: dict, fw: list, fw_rows: list) -> dict[str, np.ndarray]:
    """Each link's state word at the merged times (:mod:`companion.linkstate`: its reported flags, down
    where its vehicle logged nothing, left out where the companion's newest step did not correct
    it) and its newest correction latency [ms]."""
    t = merged["t"]
    n = len(fw)
    flags = np.zeros((t.size, n), dtype=np.int64)
    down = np.ones((t.size, n), dtype=bool)
    latency = np.full((t.size, n), np.nan)
    for i, (f, r) in enumerate(zip(fw, fw_rows)):
        if f is None:
            continue
        down[:, i] = r < 0
        if "flags" in f:
            flags[r >= 0, i] = f["flags"][r[r >= 0]]
        lat = np.asarray(f["correction_latency"], dtype=float).reshape(-1, 2)
        if lat.size:
            k = np.searchsorted(lat[:, 0], t, side="right") - 1
            latency[k >= 0, i] = 1e3 * lat[k[k >= 0], 1]
    excluded = np.zeros((t.size, n), dtype=bool)
    if "t_sckf" in merged and merged["t_sckf"].size and "corrected_sckf" in merged:
        j = np.searchsorted(merged["t_sckf"], t, side="right") - 1
        excluded[j >= 0] = ~merged["corrected_sckf"][j[j >= 0]]
    words = state_word(flags, excluded=excluded, down=down)
    return {"link_state": words, "correction_latency_ms": latency}


def process_folders(out_dir: Path, base: str) -> list[str]:
    """The run folders of the process in ``base`` and of its restarts that exist (``base-restart``,
    ``base-restart2``...: :func:`~sitl.fleet.faults.restart_folder`), in order."""
    out = [base]
    k = 1
    while (out_dir / restart_folder(base, k)).is_dir():
        out.append(restart_folder(base, k))
        k += 1
    return out


def newest_ports(out_dir: Path, i: int) -> dict:
    """0-based link ``i``'s ``linkN_ports.json`` of its newest process that wrote one (its
    firmware's account since that boot, as a batch run reports it); ``{}`` if none did."""
    name = f"link{i + 1}"
    for folder in reversed(process_folders(out_dir, name)):
        try:
            return json.loads((out_dir / folder / f"{name}_ports.json").read_text())
        except (OSError, ValueError):
            continue
    return {}


def vehicle_log(out_dir: Path, i: int) -> dict[str, np.ndarray] | None:
    """0-based link ``i``'s flight log: its first process's and, after reboots, its restarted
    processes' (:func:`process_folders`), one after the other."""
    parts = [lg for lg in (load_run_log(out_dir / folder, f"link{i + 1}_firmware")
                           for folder in process_folders(out_dir, f"link{i + 1}")) if lg is not None and "t" in lg]
    if not parts:
        return None
    for p in parts:  # a stream holds the latencies only once a correction arrived, the texts once one was sent
        p["correction_latency"] = np.asarray(p.get("correction_latency", np.zeros((0, 2)))).reshape(-1, 2)
        for key, dtype in (("statustext_t", float), ("statustext_severity", np.int64), ("statustext_text", np.str_)):
            p[key] = np.asarray(p.get(key, np.zeros(0, dtype)), dtype=dtype).reshape(-1)
    keys = set.intersection(*(set(p) for p in parts))
    return {k: np.concatenate([p[k] for p in parts], axis=0) for k in keys}


def companion_log(sc: Scenario, out_dir: Path) -> dict[str, np.ndarray] | None:
    """The companions' step logs over the whole chain (a group's restarted companion continues
    its group's log; :func:`~sitl.steplog.merge_step_logs`)."""

    def parts(*folders: str) -> list[dict]:
        return [lg for lg in (load_run_log(out_dir / f, "companion_log") for f in folders) if lg is not None]

    if not sc.companion.distributed:
        logs = [parts(*process_folders(out_dir, "companion"))]
    else:
        logs = [parts(*process_folders(out_dir, f"companion-g{g + 1}"))
                for g in range(len(sc.companion.group_layout(sc.skeleton.n_links)))]
    return merge_step_logs(logs, sc.skeleton.d_b_m, sc.companion.distributed,
                           int(round(1e6 / sc.companion.rate_hz)))


def companion_summaries(out_dir: Path) -> dict[str, dict]:
    out = {}
    for path in sorted(out_dir.glob("companion*/companion_summary.json")):
        try:
            out[path.parent.name] = json.loads(path.read_text())
        except (OSError, ValueError):
            continue
    return out


_PORT_COUNTERS = ("signed", "unsigned", "rejected_unsigned", "rejected_signature", "rejected_replay", "peer_kept",
                  "dropped_frames", "dropped_unknown")


def _is_sim_url(url: str) -> bool:
    """A vehicle's simulator link: PX4's TCP, or the same-host link (its UDP ports are MAVLink's)."""
    return url.startswith("tcp") or is_simlink_url(url)


def mavlink_counters(out_dir: Path) -> dict:
    """Per process of a fleet run: its MAVLink ports' signing and rejection counters (from the
    vehicles' ``link<i>_ports.json`` and the companions' ``companion_summary.json``), the
    vehicles' refusals (out-of-bound corrections, disarms in flight, SETUP_SIGNING), and their
    simulator links' drops and refused peers (``sim_dropped_frames``, ``sim_rejected_peer``)."""
    out: dict = {}
    for path in sorted(out_dir.glob("link*/link*_ports.json")):
        try:
            ports = json.loads(path.read_text())
        except (OSError, ValueError):
            continue
        links = {url: p for url, p in ports.items() if url not in ("errors", "gps", "ekf", "thrust_limit")}
        sim = [p for url, p in links.items() if _is_sim_url(url)]
        mavlink = [p for url, p in links.items() if not _is_sim_url(url)]
        entry = {k: sum(p.get(k, 0) for p in mavlink) for k in _PORT_COUNTERS}
        entry.update(sim_dropped_frames=sum(p.get("dropped_frames", 0) for p in sim),
                     sim_rejected_peer=sum(p.get("rejected_peer", 0) for p in sim))
        entry.update(ports.get("errors", {}))
        out[path.parent.name] = entry
    for folder, summary in companion_summaries(out_dir).items():
        links = summary.get("links", {}).values()
        out[folder] = {k: sum(lk.get(k, 0) for lk in links) for k in _PORT_COUNTERS}
    return out


def fault_report(sc: Scenario, merged: dict, out_dir: Path, faults, wired: list[int],
                 inject_sent: dict | None = None, requests: dict | None = None) -> dict:
    """What the faults did (metrics.json ``faults``): every harness fault's timeline (``harness``,
    scripted and asked for at run time, :class:`~sitl.fleet.faults.FleetFaults` ``faults``; a
    vehicle's: killed, restarted, back in the lockstep, rotors on, first corrected by the
    companion; the scripted reboot's also as ``link_reboot``) and the fault socket's ``requests``
    counts, the impaired wires' counters, every link's GPS health when a fault touches the GPS, and
    the injected failure (when the launcher sent its commands, ``inject_sent``, and what the vehicle's
    failure filter reported)."""
    out: dict = {}
    def public(tl: dict) -> dict:  # (the wall-clock stamps are the failover figures' own)
        tl = {k: v for k, v in tl.items() if not k.endswith("_monotonic")}
        return reboot_timeline(tl, merged) if tl["kind"] == "vehicle_off" else tl

    if faults.timelines:
        out["harness"] = [public(tl) for tl in faults.timelines]
    link_fault = faults.first("vehicle_off", "scenario")
    if requests:
        out["requests"] = requests
    if sc.faults.inject.link:
        i = sc.faults.inject.link
        entry = {"link": i, **(inject_sent or {})}
        try:
            entry.update(json.loads((out_dir / f"link{i}" / f"link{i}_ports.json").read_text()).get("failures", {}))
        except (OSError, ValueError):
            pass
        out["inject"] = entry
    if link_fault:
        out["link_reboot"] = public(link_fault)
    if wired:
        path = out_dir / "wire" / "wire_stats.json"
        try:
            stats = json.loads(path.read_text())
        except (OSError, ValueError):
            stats = {}
        m = sc.faults.mavlink
        out["mavlink"] = {"loss": m.loss, "delay_ms": m.delay_ms, "jitter_ms": m.jitter_ms,
                          "links": [i + 1 for i in wired], "wires": stats}
    if sc.faults.touches_gps:
        out["gps"] = {"link": sc.faults.gps.link,
                      "firmware": [newest_ports(out_dir, i).get("gps", {}) for i in range(sc.skeleton.n_links)]}
    return out


def neighbour_camera_metrics(out_dir: Path, summaries: dict[str, dict]) -> dict:
    """``metrics.json["neighbour_cameras"]`` of a fleet run: the neighbour poses the vision
    consumer published (and those of a camera on another vehicle than configured) and, per
    companion, what reached it over Zenoh (delivered, rejected by reason) and what its steps did
    with them (:meth:`companion.engine.CompanionEngine.on_neighbour_pose`)."""
    try:
        vision = json.loads((out_dir / "vision" / "vision_summary.json").read_text())
    except (OSError, ValueError):
        vision = {}
    return {"consumer": vision.get("neighbour_poses"),
            "companions": {name: {"wire": summ.get("neighbour_poses_wire"), "steps": summ.get("neighbour_measurements")}
                           for name, summ in summaries.items()}}


def distributed_metrics(sc: Scenario, merged: dict, summaries: dict[str, dict], faults: dict) -> dict:
    """Global-step figures of a distributed fleet run: per companion its counts, leaders and
    round trips; the leader failover after a scripted kill, measured by the surviving groups."""
    out: dict = {"companions": {}}
    rts = []
    for name, summ in summaries.items():
        out["companions"][name] = {k: summ.get(k) for k in ("global_step", "round_trip_ms_as_leader", "failovers",
                                                             "malformed_payloads", "cpg_targets")}
        if summ.get("round_trip_ms_as_leader"):
            rts.append(summ["round_trip_ms_as_leader"])
    for part in ("network", "end_to_end"):
        values = [r[part]["p99"] for r in rts if r.get(part)]
        if values:
            out[f"round_trip_{part}_ms_p99"] = max(values)
    win = merged.get("t_sckf", np.zeros(0)) >= sc.flight_start_s
    if "global_applied" in merged and np.any(win):
        out["cycles_with_global_step_fraction"] = float(np.mean(np.all(merged["global_applied"][win], axis=1)))
    if faults:
        out["fault"] = {k: v for k, v in faults.items() if not k.endswith("_monotonic")}
        takeovers = []
        for name, summ in summaries.items():
            for fo in summ.get("failovers") or []:
                if fo.get("from") == faults["group"] and "gone_at" in fo:
                    takeovers.append({"observed_by": name, "to_group": fo.get("to"),
                                      "leader_gone_after_kill_s": round(fo["gone_at"] - faults["killed_at_monotonic"], 4),
                                      "global_step_back_after_kill_s": round(
                                          fo["gone_at"] + fo["first_global_after_s"] - faults["killed_at_monotonic"], 4),
                                      "cycles_without_global_step": fo["cycles_without_global"]})
        out["fault"]["failover"] = takeovers
        if takeovers:
            out["fault"]["failover_s_max"] = max(t["global_step_back_after_kill_s"] for t in takeovers)
    return out
