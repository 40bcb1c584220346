"""Fleet mode's cameras: rendered by the harness, published over Zenoh, measured by
the companion-side consumer, scored against the truth.

:class:`CameraStreamer` renders a scenario's ``[[cameras]]`` with :class:`~sitl.cameras.rig.CameraRig`
(the renderer of batch mode: same schedule on the simulation clock, latency, seeded noise) from
the fleet harness's lockstep (:meth:`on_tick` is a tick hook of
:class:`~sitl.fleet.harness.FleetHarness`), and publishes each frame when it becomes available with
:class:`~companion.vision.camera_wire.CameraPublisher` on ``<prefix>/camera/<vehicle>/image``
(``prefix``: the scenario's Zenoh prefix, ``zenoh.prefix`` or its name; ``vehicle`` 1-based) as
the camera's ``wire_format`` (PNG by default: lossless, the consumer sees the pixels batch mode
sees). It keeps each published frame's ground truth (every marker's pose in the camera at capture).

The Zenoh sessions: a camera runs on the onboard computer of its vehicle's group, so the harness
opens one peer session per group that carries a camera (:func:`open_camera_session`), beside the
companions' sessions, not in their mesh: it listens on a port of 127.0.0.1 the OS picks (parallel
runs do not collide) and connects nowhere, multicast scouting off. In a secured fleet (the
companions' ``[zenoh]`` has ``users_file``, ``[zenoh.tls]`` or ``access_control``) it takes the
group's credentials as the group's companion does (its user and password, the users file as the
dictionary it checks the consumer against, its certificate with mutual TLS, the access rules;
:func:`~companion.fleetnet.credentials.group_credentials`), over ``tls/`` on the host of the
group's endpoint when the fleet uses TLS; a session without the fleet's credentials neither
receives nor publishes camera frames. The harness writes the consumer's config (``vision.toml``:
the endpoints, the prefix, the scenario's marker sizes; in a secured fleet the companions' config
and the group whose credentials the consumer presents, the first camera's) into the run folder.
The consumer checks every payload (the codec).

:func:`fleet_vision_metrics` joins the consumer's frame log (``vision/vision_frames.jsonl``) with
the truths by ``(vehicle, camera, seq)``: ``metrics.json["vision"]`` with batch mode's keys
(frames, detection rate, detection and PnP ms, the method's RMS / p95 / max errors: eq. 2 and 3)
plus the wire's counts (published, received, lost, rejected).
"""

from __future__ import annotations

import json
import logging
import os
import socket
import time
from dataclasses import replace
from pathlib import Path

import numpy as np

from companion.estimation.so3 import quat_to_rotmat
from companion.fleetnet.config import ZenohConfig
from companion.vision.config import PipelineConfig
from companion.vision.geometry import geodesic_angle_rad
from companion.vision.node import FRAMES_FILE, SUMMARY_FILE, read_frame_log
from companion.vision.node_config import VisionNodeSetup, ZenohCameraSource

from .neighbours import neighbour_cameras
from .rig import CameraRig

__all__ = ["CameraStreamer", "camera_endpoint", "fleet_vision_metrics", "free_loopback_port", "open_camera_session"]

log = logging.getLogger(__name__)


def free_loopback_port() -> int:
    """A TCP port free on 127.0.0.1 now (the OS's choice)."""
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def camera_endpoint(fleet: ZenohConfig, group: int) -> str:
    """Where 0-based ``group``'s camera session listens: a free port of 127.0.0.1 over tcp or, when
    ``fleet`` uses TLS, over the transport of the group's endpoint on its host (the host the
    group's certificate names)."""
    port = free_loopback_port()
    if not fleet.tls.configured:
        return f"tcp/127.0.0.1:{port}"
    transport, address = fleet.group_endpoint(group).split("/", 1)
    return f"{transport}/{address.rsplit(':', 1)[0]}:{port}"


def open_camera_session(fleet: ZenohConfig, group: int, n_groups: int, file: str = "<config>"):
    """``(endpoint, session)`` of 0-based ``group``'s cameras: a Zenoh peer listening on
    :func:`camera_endpoint`, connecting nowhere, with the group's credentials of ``fleet`` (the
    companions' ``[zenoh]``; ``file`` holds it, for the errors)."""
    import zenoh

    from companion.fleetnet.bus import peer_config
    from companion.fleetnet.credentials import group_credentials

    endpoint = camera_endpoint(fleet, group)
    credentials = group_credentials(fleet, group, n_groups, file)
    return endpoint, zenoh.open(peer_config((endpoint,), (), credentials, file=file))


class CameraStreamer:
    """The cameras of a fleet run, published over Zenoh (module docstring). ``model``, ``data``:
    the plant's MuJoCo model (built with the cameras and markers) and data; ``dt_s`` its step.
    ``fleet``: the companions' ``[zenoh]`` (default: the scenario's) and ``fleet_file`` the config
    file that holds it (the consumer reads the credentials there; needed when ``fleet`` is secured)."""

    def __init__(self, sc, model, data, dt_s: float, runtime_env: str | None = None,
                 fleet: ZenohConfig | None = None, fleet_file: str = "", companion_endpoints: tuple[str, ...] = (),
                 neighbours: bool = False):
        if runtime_env and "ZENOH_RUNTIME" not in os.environ:  # before this process's first session
            os.environ["ZENOH_RUNTIME"] = runtime_env
        from companion.vision.camera_wire import CameraPublisher

        from .video import pipeline_config

        self.prefix = sc.zenoh_prefix
        self.markers = sc.markers
        self.pipeline: PipelineConfig = pipeline_config(sc.markers)
        self.fleet = sc.zenoh if fleet is None else fleet
        if self.fleet.secured and not fleet_file:
            raise ValueError("fleet_file: a secured fleet's camera consumer reads the credentials from its config")
        self.fleet_file = fleet_file
        self.cameras = sc.cameras
        self.companion_endpoints = tuple(companion_endpoints)
        self.neighbours = neighbours
        layout = sc.companion.group_layout(sc.skeleton.n_links)
        group_of = {v: g for g, links in enumerate(layout) for v in links}  # 0-based vehicle -> its group
        self.endpoints: dict[int, str] = {}  # by 0-based group: where its camera session listens
        self.sessions: dict[int, object] = {}
        try:
            for g in sorted({group_of[cam.vehicle_index()] for cam in sc.cameras}):
                self.endpoints[g], self.sessions[g] = open_camera_session(self.fleet, g, len(layout), fleet_file)
        except BaseException:
            for session in self.sessions.values():
                session.close()
            raise
        self.rig = None
        self.publishers: dict[str, CameraPublisher] = {}  # by camera (cameras of one vehicle share its key)
        self.formats = {cam.name: cam.wire_format for cam in sc.cameras}
        self.published = 0
        self.publish_s = 0.0
        self.final_stats: dict | None = None
        try:
            self.rig = CameraRig(model, data, sc.cameras, sc.markers, dt_s, sc.seed, scene=sc.scene)
            for cam in sc.cameras:
                self.publishers[cam.name] = CameraPublisher(self.sessions[group_of[cam.vehicle_index()]], self.prefix,
                                                            cam.vehicle_index(),
                                                            fmt=cam.wire_format, quality=cam.wire_quality)
        except BaseException:
            self.close()
            raise
        # (vehicle, camera, seq) -> (t_capture, {marker id: (R_cm, t_cm_m)})
        self.truths: dict[tuple[int, str, int], tuple[float, dict]] = {}
        log.info("cameras: publishing %s on %s/camera/<vehicle>/image from %s", ", ".join(c.name for c in sc.cameras),
                 self.prefix, ", ".join(self.endpoints.values()))

    def consumer_setup(self) -> VisionNodeSetup:
        """The consumer's config: connect to these sessions (in a secured fleet with the
        credentials of the first camera's group), the scenario's markers; with
        ``companion_endpoints`` (the companions that take the consumer's measurements) connect to
        them as well, and with ``neighbours`` publish the chain cameras' views of their neighbours'
        markers to them."""
        pipe = self.pipeline
        if self.markers:
            pipe = replace(pipe, ids=tuple(m.id for m in self.markers))
        credentials = dict(fleet=self.fleet_file, group=min(self.endpoints) + 1) if self.fleet.secured else {}
        neighbours = neighbour_cameras(self.cameras, self.markers) if self.neighbours else ()
        source = ZenohCameraSource(prefix=self.prefix, connect=tuple(self.endpoints.values()) + self.companion_endpoints,
                                   **credentials)
        return VisionNodeSetup(name="fleet_cameras", source="zenoh", zenoh=source, pipeline=pipe, neighbours=neighbours)

    def wait_for_subscriber(self, timeout_s: float, check=lambda: None) -> None:
        """Until every publisher has a matching subscriber (the consumer connected and subscribed),
        at most ``timeout_s`` of wall time; ``check()`` may raise (a process died)."""
        deadline = time.monotonic() + timeout_s
        while not all(p.matched for p in self.publishers.values()):
            check()
            if time.monotonic() > deadline:
                raise TimeoutError(f"no subscriber on {self.prefix}/camera/*/image within {timeout_s:.0f} s")
            time.sleep(0.02)

    def on_tick(self, k: int, t: float) -> None:
        """A tick hook: render what is due; publish what became available."""
        self.rig.on_tick(k, t)
        for f in self.rig.poll(t):
            h = f.frame.header
            w0 = time.perf_counter()
            self.publishers[h.camera].publish(f.frame)
            self.publish_s += time.perf_counter() - w0
            self.published += 1
            self.truths[(h.vehicle, h.camera, h.seq)] = (
                h.t_capture_s, {i: f.truth.marker_in_camera(i) for i in f.truth.markers})

    def stats(self) -> dict:
        if self.final_stats is not None:  # closed
            return self.final_stats
        pubs = self.publishers.values()
        rig = self.rig
        return {
            "endpoints": list(self.endpoints.values()), "prefix": self.prefix, "wire_format": self.formats,
            "published": self.published, "bytes_published": sum(p.bytes_sent for p in pubs),
            "encode_publish_ms_per_frame": round(1e3 * self.publish_s / self.published, 3) if self.published else None,
            "render_ms_per_frame": round(1e3 * rig.render_s / rig.renders, 3) if rig is not None and rig.renders else None,
        }

    def close(self) -> None:
        if self.final_stats is None:
            self.final_stats = self.stats()
        for p in self.publishers.values():
            try:
                p.close()
            except Exception:  # noqa: BLE001 - the session may be closing already
                pass
        self.publishers = {}
        if self.rig is not None:
            self.rig.close()
            self.rig = None
        if self.sessions:
            from companion.fleetnet.bus import close_session  # (Zenoh: camera scenarios only)

            for g, session in self.sessions.items():
                close_session(session, f"group {g + 1}'s camera session")


def fleet_vision_metrics(streamer: CameraStreamer, consumer_dir: Path, flight_start_s: float = 0.0
                         ) -> tuple[dict, dict[str, np.ndarray]]:
    """``metrics.json["vision"]`` of a fleet run and the per-pose arrays (``vision.npz``; batch
    mode's keys): the consumer's estimates against the truths the streamer kept."""
    records = read_frame_log(consumer_dir / FRAMES_FILE) if (consumer_dir / FRAMES_FILE).exists() else []
    try:
        summary = json.loads((consumer_dir / SUMMARY_FILE).read_text())
    except (OSError, ValueError):
        summary = {}
    frames: dict[str, int] = {}
    detected: dict[str, int] = {}
    cams = sorted({c for (_, c, _) in streamer.truths} | {r.get("camera", "") for r in records})
    rows = []  # t_capture, camera index, id, method index, pos err, att err, range, side, ambiguous
    detect_ms, pnp_ms, unmatched = [], [], 0
    for r in records:
        key = (r["vehicle"], r["camera"], r["seq"])
        truth = streamer.truths.get(key)
        if truth is None:
            unmatched += 1
            continue
        frames[r["camera"]] = frames.get(r["camera"], 0) + 1
        detected[r["camera"]] = detected.get(r["camera"], 0) + (r["detections"] > 0)
        detect_ms.append(r["detect_ms"])
        pnp_ms.append(r["pnp_ms"])
        for p in r["poses"]:
            if p["id"] not in truth[1]:
                continue
            R_true, t_true = truth[1][p["id"]]
            R = quat_to_rotmat(np.asarray(p["q_cm_wxyz"]))
            rows.append((r["t_capture_s"], cams.index(r["camera"]), p["id"], 0,
                         float(np.linalg.norm(np.asarray(p["t_cm_m"]) - t_true)),
                         float(np.degrees(geodesic_angle_rad(R, R_true))), float(np.linalg.norm(t_true)),
                         p["side_px"], p["ambiguous"]))
    a = np.array(rows, dtype=float).reshape(-1, 9)
    method = summary.get("method", streamer.pipeline.method)
    arrays = {"vision_t": a[:, 0], "vision_camera": a[:, 1].astype(int), "vision_marker": a[:, 2].astype(int),
              "vision_method": a[:, 3].astype(int), "vision_pos_err_m": a[:, 4], "vision_att_err_deg": a[:, 5],
              "vision_range_m": a[:, 6], "vision_side_px": a[:, 7], "vision_ambiguous": a[:, 8].astype(bool),
              "vision_methods": np.array([method]), "vision_cameras": np.array(cams)}
    pe, ae = a[:, 4], a[:, 5]

    def stat(x, f):
        return round(float(f(x)), 6) if len(x) else None

    received = summary.get("frames_total", len(records))
    out = {
        "frames": frames,
        "detection_rate": {c: detected.get(c, 0) / n for c, n in frames.items()},
        "detect_ms_per_frame": stat(detect_ms, np.mean),
        "pnp": {method: {
            "poses": int(len(pe)),
            "pos_rms_m": stat(pe, lambda x: np.sqrt(np.mean(x**2))),
            "pos_p95_m": stat(pe, lambda x: np.percentile(x, 95)),
            "pos_max_m": stat(pe, np.max),
            "att_rms_deg": stat(ae, lambda x: np.sqrt(np.mean(x**2))),
            "att_p95_deg": stat(ae, lambda x: np.percentile(x, 95)),
            "ambiguous_fraction": stat(a[:, 8], np.mean),
            "pnp_ms_per_frame": stat(pnp_ms, np.mean),
        }},
        "frames_total": sum(frames.values()),
        "render_ms_per_frame": streamer.stats()["render_ms_per_frame"],
        "mode": "fleet",
        "wire": {**streamer.stats(), "received": received, "lost": streamer.published - received,
                 "rejected_payloads": summary.get("rejected_payloads"), "unmatched_frames": unmatched},
        "consumer": {k: summary.get(k) for k in ("detect_pnp_ms", "detect_ms", "pnp_ms", "frames_per_s", "ended_by",
                                                   "wall_s")},
    }
    if flight_start_s > 0 and len(a):
        win = a[:, 0] >= flight_start_s
        out["pnp"][method]["pos_rms_m_in_flight"] = stat(pe[win], lambda x: np.sqrt(np.mean(x**2)))
    return out, arrays
