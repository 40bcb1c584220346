"""A run folder's ``log.npz`` as an MCAP file (``run.mcap``) that Foxglove and Lichtblick open.

Messages are JSON with Foxglove's schemas (:mod:`companion.recording.foxglove`), stamped (log and
publish time) with the simulated time in nanoseconds and written in time order. The channels,
each written only when the log holds its arrays (links numbered from 1):

- ``/link{i}/truth``, ``/link{i}/ekf``, ``/link{i}/target`` (``foxglove.PoseInFrame``, frame
  ``world``): ``p_true``/``q_true``, ``p_ekf``/``q_ekf``, ``p_target``/``q_target`` at ``t`` (the
  targets in the truth's frame: :func:`companion.trajectory.planned_positions`);
- ``/link{i}/state_in`` (``foxglove.PoseInFrame``): the link's state as the companion's step took
  it in, ``p_ekf_sckf``/``q_ekf_sckf`` at ``t_sckf``;
- ``/link{i}/corrected`` (``foxglove.PoseInFrame``): the companion's correction,
  ``p_corr_sckf``/``q_corr_sckf`` at ``t_sckf``;
- ``/tf`` (``foxglove.FrameTransforms``): ``world`` -> ``link{i}``, the truth, at ``t``;
- ``/scene`` (``foxglove.SceneUpdate``): a box per link (the link's length along its x axis,
  0.1 m across; a 0.4 m cube when the run folder's ``scenario.toml`` gives no
  ``skeleton.link_length_m``) and a line from each link's centre to the next one's, the truth,
  at ``t`` decimated to at most :data:`SCENE_MAX_HZ`;
- ``/link{i}/thrust`` (``skeleton.Series``): ``thrust_n``, the rotors' thrusts, at ``t``;
- ``/link{i}/state`` (``skeleton.Series``): the link's state word (:mod:`companion.linkstate`) and its
  bits as 0/1 (:data:`STATE_BITS`), and its newest correction latency, at ``t``;
- ``/link{i}/correction`` (``skeleton.Series``): per companion step, ``delta_p_m``, the corrected
  position minus the estimate the step used, and whether the step corrected the link;
- ``/companion/step`` (``skeleton.Series``): per companion step (``t_sckf``) the constraint
  errors per joint before and after the correction, the iterations, the global step's flag per
  group, the largest NIS, the corrected links and the step's cycle time (:data:`STEP_FIELDS`);
- ``/contact`` (``skeleton.Series``): the ODAR wall push's contact (:data:`CONTACT_FIELDS`);
- ``/load/truth``, ``/load/ekf``, ``/load/ukf`` (``foxglove.PoseInFrame``): the slung load's pose
  and its two filters' estimates, from the run folder's ``load.npz``;
- ``/statustext`` (``foxglove.Log``): every STATUSTEXT a link's firmware sent (GPS health, the
  rotors' thrust limit), named ``link <i>``, from ``statustext_t`` / ``_link`` / ``_severity`` /
  ``_text``;
- ``/camera/<name>/image`` (``foxglove.CompressedImage``, JPEG, frame ``camera_<name>``): every
  frame of each camera at its capture time, from the run folder's ``camera_frames.npz``.

A non-finite number is written as JSON ``null``. Chunks are zstd-compressed when the
``zstandard`` module is importable, else uncompressed.
"""

from __future__ import annotations

import base64
import importlib.util
import json
import logging
import math
import os
import re
import tomllib
from collections.abc import Iterator, Mapping
from pathlib import Path

import numpy as np

from ..linkstate import CARRIED, DOWN, EXCLUDED
from ..messages import STATE_FLAG_ARMED, STATE_FLAG_CORRECTION_ACTIVE, STATE_FLAG_EKF_OK, STATE_FLAG_GPS_FAULT
from ..trajectory import planned_positions
from .foxglove import (COMPRESSED_IMAGE, FRAME_TRANSFORMS, LOG, LOG_LEVEL_OF_SEVERITY, POSE_IN_FRAME, SCENE_UPDATE, SCHEMAS,
                       SERIES, pose, stamp)

__all__ = ["SCENE_MAX_HZ", "STEP_FIELDS", "STATE_BITS", "CONTACT_FIELDS", "LOAD_POSES", "MCAP_NAME", "channels", "image_channels", "statustext_channel", "export_log",
           "write_run_mcap", "write_beside_log"]

_log = logging.getLogger(__name__)

MCAP_NAME = "run.mcap"
#: the ``/scene`` channel's highest rate (the log's samples are decimated to it)
SCENE_MAX_HZ = 50.0
#: ``/companion/step`` field -> the log's key (stamped ``t_sckf``)
STEP_FIELDS = {
    "con_pos_before": "con_pos_before",
    "con_pos_after": "con_pos_after",
    "con_vel_before": "con_vel_before",
    "con_vel_after": "con_vel_after",
    "iterations": "iterations",
    "global_applied": "global_applied",
    "nis_max": "nis_max_sckf",
    "corrected": "corrected_sckf",
    "cycle_us": "cycle_us",
}
#: ``/contact`` field -> the log's key (stamped ``contact_t``): the ODAR wall push's contact force
#: along the wall's normal (true, commanded, the observer's estimate), the wrenches and the flag
CONTACT_FIELDS = {
    "force_true_n": "contact_force_true_n",
    "force_cmd_n": "contact_force_cmd_n",
    "force_hat_n": "contact_force_hat_n",
    "wrench_true": "contact_wrench_true",
    "wrench_hat": "contact_wrench_hat",
    "engaged": "contact_engaged",
}
#: ``/link{i}/state``'s 0/1 fields: name -> the state word's bit
STATE_BITS = {"ekf_ok": STATE_FLAG_EKF_OK, "armed": STATE_FLAG_ARMED, "correction_active": STATE_FLAG_CORRECTION_ACTIVE,
              "gps_fault": STATE_FLAG_GPS_FAULT, "carried": CARRIED, "excluded": EXCLUDED, "down": DOWN}
#: the slung load's poses, ``/load/<name>`` from ``load.npz`` (stamped ``load_t``):
#: ``(name, position key, quaternion key)``
LOAD_POSES = (("truth", "load_p_true", "load_q_true"), ("ekf", "load_ekf_p", "load_ekf_q"),
              ("ukf", "load_ukf_p", "load_ukf_q"))
#: the cube's edge when the link's length is unknown (m)
DEFAULT_CUBE_M = 0.4
LINK_WIDTH_M = 0.1
#: log rows turned into Python lists at a time while the messages are made
_ROWS_AT_ONCE = 1024
INSTALL_HINT = "pip install 'aerial-skeleton-stack[view]' (or pip install 'mcap>=1.1')"

_LINK_COLOR = {"r": 0.2, "g": 0.45, "b": 0.9, "a": 0.6}
_CABLE_COLOR = {"r": 1.0, "g": 0.55, "b": 0.0, "a": 1.0}
_IDENTITY = {"position": {"x": 0.0, "y": 0.0, "z": 0.0}, "orientation": {"x": 0.0, "y": 0.0, "z": 0.0, "w": 1.0}}
_LINK_TOPIC = re.compile(r"^/link(\d+)/")
#: compact JSON as bytes (one encoder for every message)
_ENCODE = json.JSONEncoder(separators=(",", ":"), check_circular=False).encode


def _json(message: dict) -> bytes:
    return _ENCODE(message).encode()


def _plain(a: np.ndarray) -> list:
    """``a`` as nested Python lists, a non-finite number as ``None`` (JSON ``null``)."""
    if a.dtype.kind == "f" and not np.isfinite(a).all():
        return np.where(np.isfinite(a), a, None).tolist()
    return a.tolist()


def _rows(a: np.ndarray) -> Iterator:
    """The rows of ``a`` as :func:`_plain` gives them, converted :data:`_ROWS_AT_ONCE` at a time
    (a long log's messages are made as they are written, never all held at once)."""
    for start in range(0, len(a), _ROWS_AT_ONCE):
        yield from _plain(a[start:start + _ROWS_AT_ONCE])


def _nanoseconds(t: np.ndarray) -> np.ndarray:
    return np.round(np.asarray(t, dtype=float) * 1e9).astype(np.int64)


def _series(log: Mapping[str, np.ndarray], stamp_key: str, *keys: str, width: int | None = None) -> list | None:
    """The arrays ``keys`` when the log holds them all with one row per ``stamp_key`` sample (and
    ``width`` links when given), else ``None``."""
    if stamp_key not in log or any(k not in log for k in keys):
        return None
    n = len(log[stamp_key])
    arrays = [np.asarray(log[k]) for k in keys]
    if any(a.ndim == 0 or a.shape[0] != n or (width is not None and (a.ndim < 2 or a.shape[1] != width))
           for a in arrays):
        _log.debug("%s: shapes do not match %s; skipped", ", ".join(keys), stamp_key)
        return None
    return arrays


def _pose_messages(ns: np.ndarray, p: np.ndarray, q: np.ndarray, link: int) -> Iterator[bytes]:
    return (_json({"timestamp": stamp(k), "frame_id": "world", "pose": pose(pk, qk)})
            for k, pk, qk in zip(ns.tolist(), _rows(p[:, link]), _rows(q[:, link])))


def _tf_messages(ns: np.ndarray, p: np.ndarray, q: np.ndarray) -> Iterator[bytes]:
    for k, pk, qk in zip(ns.tolist(), _rows(p), _rows(q)):
        ts = stamp(k)
        transforms = []
        for i, (pi, qi) in enumerate(zip(pk, qk)):
            f = pose(pi, qi)
            transforms.append({"timestamp": ts, "parent_frame_id": "world", "child_frame_id": f"link{i + 1}",
                               "translation": f["position"], "rotation": f["orientation"]})
        yield _json({"transforms": transforms})


def _scene_messages(ns: np.ndarray, p: np.ndarray, q: np.ndarray, link_length_m: float | None) -> Iterator[bytes]:
    if link_length_m:
        size = {"x": float(link_length_m), "y": LINK_WIDTH_M, "z": LINK_WIDTH_M}
    else:
        size = {"x": DEFAULT_CUBE_M, "y": DEFAULT_CUBE_M, "z": DEFAULT_CUBE_M}
    for k, pk, qk in zip(ns.tolist(), _rows(p), _rows(q)):
        ts = stamp(k)
        entities = [{"timestamp": ts, "frame_id": "world", "id": f"link{i + 1}", "frame_locked": False,
                     "cubes": [{"pose": pose(pi, qi), "size": size, "color": _LINK_COLOR}]}
                    for i, (pi, qi) in enumerate(zip(pk, qk))]
        entities += [{"timestamp": ts, "frame_id": "world", "id": f"cable{i + 1}", "frame_locked": False,
                      "lines": [{"type": 0, "pose": _IDENTITY, "thickness": 0.03, "scale_invariant": False,
                                 "points": [dict(zip("xyz", pk[i])), dict(zip("xyz", pk[i + 1]))],
                                 "color": _CABLE_COLOR}]}
                     for i in range(len(pk) - 1)]
        yield _json({"deletions": [], "entities": entities})


def _series_messages(ns: np.ndarray, fields: dict[str, np.ndarray]) -> Iterator[bytes]:
    names = list(fields)
    columns = [_rows(fields[name]) for name in names]
    return (_json({"timestamp": stamp(k), **dict(zip(names, row))})
            for k, *row in zip(ns.tolist(), *columns))


def _scene_stride(t: np.ndarray) -> int:
    """Every how many log samples ``/scene`` takes one (at most :data:`SCENE_MAX_HZ`)."""
    if len(t) < 2:
        return 1
    dt = float(np.median(np.diff(t)))
    return max(1, math.ceil(1.0 / (dt * SCENE_MAX_HZ) - 1e-9)) if dt > 0 else 1


def channels(log: Mapping[str, np.ndarray],
             link_length_m: float | None = None) -> list[tuple[str, str, np.ndarray, Iterator[bytes]]]:
    """``(topic, schema name, times in ns, JSON messages)`` of every channel the log has arrays for
    (a SITL run's log, or a companion's step log alone); the messages are made as they are
    iterated, in the order of the times."""
    out = []
    truth = _series(log, "t", "p_true", "q_true")
    n = truth[0].shape[1] if truth else (np.shape(log["p_ekf_sckf"])[1] if np.ndim(log.get("p_ekf_sckf")) == 3 else None)
    if truth:
        ns = _nanoseconds(log["t"])
        out.append(("/tf", FRAME_TRANSFORMS, ns, _tf_messages(ns, *truth)))
        stride = _scene_stride(np.asarray(log["t"], dtype=float))
        out.append(("/scene", SCENE_UPDATE, ns[::stride],
                    _scene_messages(ns[::stride], truth[0][::stride], truth[1][::stride], link_length_m)))
    poses = [("truth", "t", "p_true", "q_true"), ("ekf", "t", "p_ekf", "q_ekf"),
             ("state_in", "t_sckf", "p_ekf_sckf", "q_ekf_sckf"), ("corrected", "t_sckf", "p_corr_sckf", "q_corr_sckf"),
             ("target", "t", "p_target", "q_target")]
    per_link = []
    # (the targets in the truth's frame: the companion flies them from its home, in the links' frame)
    shown = {**log, "p_target": planned_positions(log)} if "p_target" in log else log
    for name, stamp_key, p_key, q_key in poses:
        arrays = _series(shown, stamp_key, p_key, q_key, width=n)
        if arrays:
            ns = _nanoseconds(log[stamp_key])
            per_link += [(i, f"/link{i + 1}/{name}", POSE_IN_FRAME, ns, _pose_messages(ns, *arrays, i))
                         for i in range(arrays[0].shape[1])]
    thrust = _series(log, "t", "thrust", width=n)
    if thrust:
        ns = _nanoseconds(log["t"])
        per_link += [(i, f"/link{i + 1}/thrust", SERIES, ns, _series_messages(ns, {"thrust_n": thrust[0][:, i]}))
                     for i in range(thrust[0].shape[1])]
    state = _series(log, "t", "link_state", width=n)
    if state:
        ns = _nanoseconds(log["t"])
        words = np.asarray(state[0]).astype(np.int64)
        latency = _series(log, "t", "correction_latency_ms", width=n)
        for i in range(words.shape[1]):
            fields = {"state_word": words[:, i], **{name: (words[:, i] & bit != 0).astype(np.int64)
                                                    for name, bit in STATE_BITS.items()}}
            if latency:
                fields["correction_latency_ms"] = latency[0][:, i]
            per_link.append((i, f"/link{i + 1}/state", SERIES, ns, _series_messages(ns, fields)))
    moves = _series(log, "t_sckf", "p_corr_sckf", "p_ekf_sckf", width=n)
    corrected = _series(log, "t_sckf", "corrected_sckf", width=n)
    if moves:
        ns = _nanoseconds(log["t_sckf"])
        delta = moves[0] - moves[1]
        for i in range(delta.shape[1]):
            fields = {"delta_p_m": delta[:, i]}
            if corrected:
                fields["corrected"] = corrected[0][:, i].astype(np.int64)
            per_link.append((i, f"/link{i + 1}/correction", SERIES, ns, _series_messages(ns, fields)))
    out += [c[1:] for c in sorted(per_link, key=lambda c: c[0])]  # link by link, in the order above
    out += _series_channel(log, "/companion/step", "t_sckf", STEP_FIELDS)
    out += _series_channel(log, "/contact", "contact_t", CONTACT_FIELDS)
    out += _log_statustext(log)
    for name, p_key, q_key in LOAD_POSES:
        arrays = _series(log, "load_t", p_key, q_key)
        if arrays and arrays[0].shape[1:] == (3,) and arrays[1].shape[1:] == (4,):
            ns = _nanoseconds(log["load_t"])
            messages = _pose_messages(ns, arrays[0][:, None], arrays[1][:, None], 0)
            out.append((f"/load/{name}", POSE_IN_FRAME, ns, messages))
    return out


def statustext_channel(texts) -> list[tuple[str, str, np.ndarray, Iterator[bytes]]]:
    """``/statustext`` (``foxglove.Log``) of ``(time [s], link (from 1), MAV_SEVERITY, text)``, each
    named ``link <i>``; none without texts."""
    texts = sorted(texts, key=lambda x: x[0])
    if not texts:
        return []
    ns = _nanoseconds(np.array([x[0] for x in texts], dtype=float))
    messages = [_json({"timestamp": stamp(int(k)), "level": LOG_LEVEL_OF_SEVERITY[min(max(int(sev), 0), 7)],
                       "message": str(text), "name": f"link {link}", "file": "", "line": 0})
                for k, (_, link, sev, text) in zip(ns.tolist(), texts)]
    return [("/statustext", LOG, ns, iter(messages))]


def _log_statustext(log: Mapping[str, np.ndarray]) -> list:
    """:func:`statustext_channel` of a log's ``statustext_*`` arrays (none when they do not fit)."""
    keys = ("statustext_t", "statustext_link", "statustext_severity", "statustext_text")
    if any(k not in log for k in keys):
        return []
    arrays = [np.asarray(log[k]).reshape(-1) for k in keys]
    if len({len(a) for a in arrays}) != 1 or not np.isfinite(arrays[0].astype(float)).all():
        _log.debug("statustext arrays do not fit together; skipped")
        return []
    return statustext_channel(list(zip(*(a.tolist() for a in arrays))))


def _series_channel(log: Mapping[str, np.ndarray], topic: str, stamp_key: str,
                    fields: Mapping[str, str]) -> list[tuple[str, str, np.ndarray, Iterator[bytes]]]:
    """The ``skeleton.Series`` channel ``topic`` of the ``fields`` (message field -> log key) the
    log holds at ``stamp_key``; none when it holds none of them."""
    present = {}
    for name, key in fields.items():
        arrays = _series(log, stamp_key, key)
        if arrays:
            present[name] = arrays[0]
    if not present:
        return []
    ns = _nanoseconds(log[stamp_key])
    return [(topic, SERIES, ns, _series_messages(ns, present))]


def export_log(log: Mapping[str, np.ndarray], out: str | Path, link_length_m: float | None = None,
               extra: list | None = None, first_link: int = 1) -> dict[str, int]:
    """Write the log's channels (and ``extra`` ones, as :func:`channels` gives them) to the MCAP
    file ``out``; the log's links are numbered from ``first_link`` (a group's companion: its
    first link's place in the chain). Returns the message count per topic (``ImportError``
    without the ``mcap`` package, ``ValueError`` for a log with no channel)."""
    import mcap.writer  # noqa: F401 (ImportError before the messages are built)

    chans = channels(log, link_length_m)
    if first_link != 1:
        chans = [(_LINK_TOPIC.sub(lambda m: f"/link{int(m.group(1)) + first_link - 1}/", c[0], count=1), *c[1:])
                 for c in chans]
    chans += list(extra or ())
    if not chans:
        raise ValueError("the log holds none of the arrays a channel is made of (t, p_true, q_true, ...)")
    out = Path(out)
    tmp = out.with_name(out.name + ".tmp")
    try:
        _write(tmp, chans)
    except BaseException:
        tmp.unlink(missing_ok=True)
        raise
    os.replace(tmp, out)
    return {topic: len(ns) for topic, _, ns, _ in chans}


def _write(path: Path, chans: list) -> None:
    """The channels' messages in time order (ties in channel order) to the MCAP file ``path``."""
    from mcap.writer import CompressionType, Writer

    compression = CompressionType.ZSTD if importlib.util.find_spec("zstandard") else CompressionType.NONE
    times = np.concatenate([c[2] for c in chans])
    ids = np.concatenate([np.full(len(c[2]), j, dtype=np.int64) for j, c in enumerate(chans)])
    sequence = np.concatenate([np.arange(len(c[2]), dtype=np.int64) for c in chans])
    messages = [c[3] for c in chans]  # each channel's iterator, read in its own time order
    # a channel whose times go back (a hostile or damaged log) is made at once and read by sequence
    held = {j: list(c[3]) for j, c in enumerate(chans) if np.any(np.diff(c[2]) < 0)}
    order = np.argsort(times, kind="stable")
    with open(path, "wb") as stream:
        writer = Writer(stream, compression=compression)
        writer.start(profile="", library="aerial-skeleton-stack")
        schema_ids = {name: writer.register_schema(name=name, encoding="jsonschema", data=SCHEMAS[name])
                      for name in dict.fromkeys(c[1] for c in chans)}
        channel_ids = [writer.register_channel(topic=topic, message_encoding="json", schema_id=schema_ids[schema])
                       for topic, schema, _, _ in chans]
        add = writer.add_message
        for j, k, s in zip(ids[order].tolist(), times[order].tolist(), sequence[order].tolist()):
            data = held[j][s] if held and j in held else next(messages[j])
            add(channel_id=channel_ids[j], log_time=k, data=data, publish_time=k, sequence=s)
        writer.finish()


def _link_length(run_dir: Path) -> float | None:
    """``skeleton.link_length_m`` of the run folder's ``scenario.toml``, if it has one."""
    try:
        value = tomllib.loads((run_dir / "scenario.toml").read_text()).get("skeleton", {}).get("link_length_m")
    except (OSError, tomllib.TOMLDecodeError, AttributeError):
        return None
    return float(value) if isinstance(value, (int, float)) and value > 0 else None


def image_channels(frames: Mapping[str, np.ndarray]) -> list[tuple[str, str, np.ndarray, Iterator[bytes]]]:
    """``/camera/<name>/image`` of a run's JPEG frames (``frame_t``, ``frame_camera``,
    ``frame_offsets``, ``frame_names``, ``frame_jpeg``: :mod:`sitl.cameras.frame_archive`), a
    channel per camera with frames; none when the arrays do not fit together."""
    try:
        t = np.asarray(frames["frame_t"], dtype=float)
        cam = np.asarray(frames["frame_camera"], dtype=np.int64)
        offsets = np.asarray(frames["frame_offsets"], dtype=np.int64)
        names = [str(x) for x in frames["frame_names"]]
        data = np.asarray(frames["frame_jpeg"], dtype=np.uint8)
    except (KeyError, ValueError, TypeError):
        return []
    if (t.ndim != 1 or cam.shape != t.shape or offsets.shape != (len(t) + 1,) or np.any(np.diff(offsets) < 0)
            or (len(t) and (offsets[0] != 0 or offsets[-1] != data.size)) or np.any((cam < 0) | (cam >= len(names)))
            or not np.isfinite(t).all()):
        _log.warning("camera frames: the arrays do not fit together; no image channels")
        return []
    out = []
    for j, name in enumerate(names):
        rows = np.flatnonzero(cam == j)
        rows = rows[np.argsort(t[rows], kind="stable")]
        if not rows.size:
            continue
        ns = _nanoseconds(t[rows])
        out.append((f"/camera/{name}/image", COMPRESSED_IMAGE, ns, _image_messages(ns, rows, f"camera_{name}", data,
                                                                                     offsets)))
    return out


def _image_messages(ns: np.ndarray, rows: np.ndarray, frame_id: str, data: np.ndarray,
                    offsets: np.ndarray) -> Iterator[bytes]:
    for k, r in zip(ns.tolist(), rows.tolist()):
        jpeg = base64.b64encode(data[offsets[r]:offsets[r + 1]].tobytes()).decode()
        yield _json({"timestamp": stamp(k), "frame_id": frame_id, "format": "jpeg", "data": jpeg})


def write_run_mcap(run_dir: str | Path, out: str | Path | None = None) -> tuple[Path, dict[str, int]]:
    """Convert ``run_dir/log.npz`` to ``out`` (default ``run_dir/run.mcap``); returns the path and
    the message count per topic (``FileNotFoundError`` without a log.npz; see :func:`export_log`)."""
    run_dir = Path(run_dir)
    out = Path(out) if out is not None else run_dir / MCAP_NAME
    with np.load(run_dir / "log.npz") as npz:
        arrays = {k: npz[k] for k in npz.files}
    if (run_dir / "load.npz").is_file():  # the slung load's estimates
        with np.load(run_dir / "load.npz") as npz:
            arrays.update({k: npz[k] for k in npz.files if k not in arrays})
    extra = []
    if (run_dir / "camera_frames.npz").is_file():  # the cameras' frames
        with np.load(run_dir / "camera_frames.npz", allow_pickle=False) as npz:
            extra = image_channels({k: npz[k] for k in npz.files})
    return out, export_log(arrays, out, _link_length(run_dir), extra=extra)


def write_beside_log(run_dir: str | Path) -> Path | None:
    """:func:`write_run_mcap` at the end of a run: one log line instead of an error when the
    ``mcap`` package is missing or the log cannot be converted; the path written, or ``None``."""
    try:
        path, _ = write_run_mcap(run_dir)
    except ImportError:
        _log.info("run.mcap not written: the mcap package is missing; %s", INSTALL_HINT)
        return None
    except Exception as exc:  # noqa: BLE001 (the run's other artefacts stand without it)
        _log.warning("run.mcap not written: %s", exc)
        return None
    return path
