"""Typed, versioned binary payloads for the Zenoh wire (pure: struct and numpy).

Every payload is ``header | body``. The header is ``b"ASKZ"``, the format version
(:data:`VERSION`, one byte) and the message type (one byte). The body is the message's fields
in the order of its schema (:data:`SCHEMAS`), little-endian, floats as float64 so that the
leader's eq. 6 solution crosses the wire bit for bit. Symmetric matrices travel as their upper
triangle (row-major, the order of the MAVLink dialect's covariance).

:func:`decode` checks the magic, the version, the type, the exact length, and the content
(finite numbers, unit quaternions, positive-definite covariance and information matrices,
valid group lists) with the same checks as the MAVLink codec; anything else raises
:class:`~companion.messages.MessageError` naming the field. Frames and units are those of
:mod:`companion.messages` (world z-up, SI): no frame conversion happens on this wire.
"""

from __future__ import annotations

import functools
import math
import struct
from typing import Any

import numpy as np

from companion.load.model import LoadObservation
from companion.messages import (
    ChainTargets,
    Correction,
    GlobalShift,
    GroupBoundaryReport,
    GroupPassiveLinks,
    ChainHome,
    LinkState,
    MessageError,
    NeighbourPose,
    check_bounded,
    check_finite,
    check_pd,
    check_psd,
    check_unit_quat,
)

__all__ = ["MAGIC", "VERSION", "SCHEMAS", "encode", "decode", "MessageError", "MAX_NEIGHBOUR_RANGE_M",
           "MAX_MOUNT_OFFSET_M", "MAX_LOAD_RANGE_M", "MAX_HOME_OFFSET_M"]

MAGIC = b"ASKZ"
# 2: ChainTargets carry the whole-chain feed-forward wrench; 3: boundaries their tip covariance;
# 4: GroupPassiveLinks (a group's links carried by their neighbours); 5: a group split by a link
# down reports each part (boundaries: part, parts, joins_left / joins_right; shifts: each entry's part);
# 6: NeighbourPose (a chain camera's view of its neighbour's marker); 7: LoadObservation (a carrying
# vehicle's camera measurement of a slung load, eq. 4); 8: ChainHome (a distributed chain's home)
VERSION = 8
_HEADER = struct.Struct("<4sBB")

#: Field kinds: scalars (struct codes), ``("vec", n)`` float64 vectors, ``("sym", n)``
#: symmetric n x n matrices (upper triangle), ``"ids"`` a u8 count and that many u8 ids,
#: ``("rows", m)`` float64 rows of width m, one per entry of the preceding ``ids`` field,
#: ``"per_id"`` one int32 per entry of the preceding ``ids`` field, ``("optsym", n)`` a u8 flag
#: (0: ``None``, 1: present) and, if present, a ``("sym", n)``.
_SCALAR = {"u8": "B", "i8": "b", "u16": "H", "i32": "i", "u32": "I", "i64": "q", "f64": "d"}

#: message type -> (type id, [(field, kind)]): the one schema of every Zenoh payload.
SCHEMAS: dict[type, tuple[int, tuple[tuple[str, Any], ...]]] = {
    LinkState: (1, (("link", "u16"), ("time_s", "f64"), ("p_w_m", ("vec", 3)), ("v_w_m_s", ("vec", 3)),
                     ("q_wxyz", ("vec", 4)), ("omega_b_rad_s", ("vec", 3)), ("P", ("sym", 9)))),
    Correction: (2, (("link", "u16"), ("ekf_time_s", "f64"), ("dp_w_m", ("vec", 3)), ("dv_w_m_s", ("vec", 3)),
                      ("dtheta_w_rad", ("vec", 3)), ("seq", "u16"))),
    GroupBoundaryReport: (3, (("group", "u8"), ("cycle_us", "i64"), ("left_tip_pv_w", ("vec", 6)),
                              ("right_tip_pv_w", ("vec", 6)), ("info_pv", ("sym", 6)), ("round_trip_us", "i32"),
                              ("network_round_trip_us", "i32"), ("tip_cov_pv", ("optsym", 12)), ("part", "u8"),
                              ("parts", "u8"), ("joins_left", "u8"), ("joins_right", "u8"))),
    GlobalShift: (4, (("leader_group", "u8"), ("cycle_us", "i64"), ("groups", "ids"), ("parts", "per_id"),
                      ("shift_pv_w", ("rows", 6)), ("handover_group", "i8"), ("handover_cycle_us", "i64"),
                      ("hold_us", "per_id"))),
    ChainTargets: (5, (("leader_group", "u8"), ("time_us", "i64"), ("seq", "u32"), ("links", "ids"),
                       ("p_w_m", ("rows", 3)), ("q_wxyz", ("rows", 4)), ("v_w_m_s", ("rows", 3)),
                       ("a_w_m_s2", ("rows", 3)), ("omega_b_rad_s", ("rows", 3)), ("omega_dot_b_rad_s2", ("rows", 3)),
                       ("force_ff_w_n", ("rows", 3)), ("torque_ff_b_nm", ("rows", 3)))),
    GroupPassiveLinks: (6, (("group", "u8"), ("time_us", "i64"), ("links", "ids"))),
    ChainHome: (9, (("group", "u8"), ("time_us", "i64"), ("offset_w_m", ("vec", 3)))),
    NeighbourPose: (7, (("observer", "u16"), ("observed", "u16"), ("t_capture_s", "f64"), ("seq", "u32"),
                        ("q_cm_wxyz", ("vec", 4)), ("t_cm_m", ("vec", 3)), ("cov_c", ("sym", 6)),
                        ("camera_pos_b_m", ("vec", 3)), ("q_bc_wxyz", ("vec", 4)), ("marker_pos_b_m", ("vec", 3)),
                        ("q_bm_wxyz", ("vec", 4)))),
    # the position block of ``joint_cov`` is the observation's ``cov_m2`` (sent once); only an
    # observation with the load's attitude travels
    LoadObservation: (8, (("vehicle", "u16"), ("stamp_s", "f64"), ("vehicle_in_load_m", ("vec", 3)),
                          ("load_in_body_q_wxyz", ("vec", 4)), ("joint_cov", ("sym", 6)))),
}
#: Largest camera range and mount offset a :class:`NeighbourPose` may carry [m] (a chain link
#: is about a metre long; anything beyond is a corrupt or hostile payload).
MAX_NEIGHBOUR_RANGE_M = 20.0
MAX_MOUNT_OFFSET_M = 5.0
#: Farthest a carrying vehicle may be from the load it sees [m] (cables are metres long).
MAX_LOAD_RANGE_M = 50.0
#: Farthest a chain's home may be from its anchor [m] (a receiver's error is metres).
MAX_HOME_OFFSET_M = 50.0
_BY_ID = {type_id: (cls, fields) for cls, (type_id, fields) in SCHEMAS.items()}


def encode(msg) -> bytes:
    """The payload of one message of a type in :data:`SCHEMAS`."""
    try:
        type_id, fields = SCHEMAS[type(msg)]
    except KeyError:
        raise TypeError(f"no Zenoh schema for {type(msg).__name__}") from None
    if isinstance(msg, LoadObservation) and not msg.has_attitude:
        raise ValueError("LoadObservation: only an observation with the load's attitude (joint_cov) travels")
    out = [_HEADER.pack(MAGIC, VERSION, type_id)]
    count = 0
    for name, kind in fields:
        value = getattr(msg, name)
        if kind == "ids":
            count = len(value)
            out.append(struct.pack(f"<B{count}B", count, *value))
        elif kind == "per_id":
            if len(value) != count:
                raise ValueError(f"{type(msg).__name__}.{name}: {len(value)} values for {count} ids")
            out.append(struct.pack(f"<{count}i", *value))
        elif isinstance(kind, str):
            out.append(struct.pack("<" + _SCALAR[kind], value))
        elif kind[0] == "vec" or kind[0] == "rows":
            out.append(np.ascontiguousarray(value, dtype="<f8").tobytes())
        elif kind[0] == "optsym" and value is None:
            out.append(b"\x00")
        else:  # sym, optsym
            if kind[0] == "optsym":
                out.append(b"\x01")
            out.append(np.asarray(value, dtype="<f8")[_upper(kind[1])].tobytes())
    return b"".join(out)


def decode(payload: bytes):
    """The message of a payload; :class:`MessageError` if it is malformed or unusable."""
    data = bytes(payload)
    if len(data) < _HEADER.size:
        raise MessageError(f"payload: {len(data)} bytes, shorter than the {_HEADER.size}-byte header")
    magic, version, type_id = _HEADER.unpack_from(data)
    if magic != MAGIC:
        raise MessageError(f"payload: magic {magic!r}, expected {MAGIC!r} (not an aerial-skeleton payload)")
    if version != VERSION:
        raise MessageError(f"payload: format version {version}, this companion speaks version {VERSION}")
    if type_id not in _BY_ID:
        raise MessageError(f"payload: unknown message type {type_id}")
    cls, plan = _PLANS[type_id]
    values: dict[str, Any] = {}
    offset = _HEADER.size
    count = 0
    for name, kind, arg in plan:
        try:
            if kind == "scalar":
                (values[name],) = arg.unpack_from(data, offset)
                offset += arg.size
            elif kind == "ids":
                count = data[offset] if offset < len(data) else _truncated()
                values[name] = tuple(struct.unpack_from(f"<{count}B", data, offset + 1))
                offset += 1 + count
            elif kind == "per_id":
                values[name] = tuple(struct.unpack_from(f"<{count}i", data, offset))
                offset += 4 * count
            else:
                if kind == "optsym":
                    flag = data[offset] if offset < len(data) else _truncated()
                    offset += 1
                    if flag == 0:
                        values[name] = None
                        continue
                    if flag != 1:
                        raise MessageError(f"{cls.__name__}.{name}: presence flag {flag}, expected 0 or 1")
                size = count * arg if kind == "rows" else arg if kind == "vec" else arg * (arg + 1) // 2
                flat = np.frombuffer(data, dtype="<f8", count=size, offset=offset).astype(float)
                offset += 8 * size
                check_finite(f"{cls.__name__}.{name}", flat)
                values[name] = (flat if kind == "vec" else flat.reshape(count, arg) if kind == "rows"
                                else _sym(flat, arg))
        except MessageError:
            raise
        except (struct.error, ValueError):
            raise MessageError(f"{cls.__name__}.{name}: payload truncated ({len(data)} bytes)") from None
    if offset != len(data):
        raise MessageError(f"{cls.__name__}: {len(data) - offset} trailing bytes (payload of {len(data)} bytes)")
    return _VALIDATE[cls](values)


def _truncated():
    raise struct.error("truncated")


def _plan(fields) -> tuple[tuple[str, str, Any], ...]:
    """A schema's fields as :func:`decode` reads them: ``(name, kind, arg)``, ``arg`` a scalar's
    :class:`struct.Struct`, a vector's length, a row's width or a symmetric matrix's size."""
    out = []
    for name, kind in fields:
        if kind in ("ids", "per_id"):
            out.append((name, kind, None))
        elif isinstance(kind, str):
            out.append((name, "scalar", struct.Struct("<" + _SCALAR[kind])))
        else:
            out.append((name, kind[0], kind[1]))
    return tuple(out)


_PLANS = {type_id: (cls, _plan(fields)) for type_id, (cls, fields) in _BY_ID.items()}


@functools.cache
def _upper(n: int) -> tuple[np.ndarray, np.ndarray]:
    """``np.triu_indices(n)``, computed once per size (a global step's payloads carry dozens of
    covariance blocks per cycle)."""
    rows, cols = np.triu_indices(n)
    rows.setflags(write=False)
    cols.setflags(write=False)
    return rows, cols


def _sym(upper: np.ndarray, n: int) -> np.ndarray:
    rows, cols = _upper(n)
    m = np.empty((n, n))
    m[rows, cols] = upper
    m[cols, rows] = upper
    return m


def _finite_all(cls: type, values: dict[str, Any]) -> None:
    """The float fields finite (:func:`decode` checked every array field as it read it)."""
    for name, value in values.items():
        if isinstance(value, float) and not math.isfinite(value):
            raise MessageError(f"{cls.__name__}.{name}: non-finite value")


def _check_increasing(name: str, ids: tuple[int, ...], what: str) -> None:
    if not ids or list(ids) != sorted(set(ids)):
        raise MessageError(f"{name}: {list(ids)} is not a non-empty increasing list of {what}")


def _link_state(v: dict[str, Any]) -> LinkState:
    _finite_all(LinkState, v)
    v["q_wxyz"] = check_unit_quat("LinkState.q_wxyz", v["q_wxyz"])
    v["P"] = check_pd("LinkState.P", v["P"])
    return LinkState(**v)


def _correction(v: dict[str, Any]) -> Correction:
    _finite_all(Correction, v)
    return Correction(**v)


def _boundary(v: dict[str, Any]) -> GroupBoundaryReport:
    _finite_all(GroupBoundaryReport, v)
    if not 0 <= v["part"] < v["parts"]:
        raise MessageError(f"GroupBoundaryReport.part: part {v['part']} of {v['parts']}")
    for side, inner in (("joins_left", v["part"] > 0), ("joins_right", v["part"] < v["parts"] - 1)):
        if v[side] not in (0, 1) or (inner and v[side]):
            raise MessageError(f"GroupBoundaryReport.{side}: {v[side]} for part {v['part']} of {v['parts']} (an inner "
                               f"end of a split group joins no other group)")
        v[side] = bool(v[side])
    v["info_pv"] = check_pd("GroupBoundaryReport.info_pv", v["info_pv"])
    if v["tip_cov_pv"] is not None:
        v["tip_cov_pv"] = check_psd("GroupBoundaryReport.tip_cov_pv", v["tip_cov_pv"])
    return GroupBoundaryReport(**v)


def _shift(v: dict[str, Any]) -> GlobalShift:
    _finite_all(GlobalShift, v)
    keys = list(zip(v["groups"], v["parts"]))
    if not keys or keys != sorted(set(keys)) or min(v["parts"]) < 0:
        raise MessageError(f"GlobalShift.groups: (group, part) {keys} is not a non-empty increasing list of parts")
    if v["handover_group"] < -1:
        raise MessageError(f"GlobalShift.handover_group: {v['handover_group']}")
    return GlobalShift(**v)


def _targets(v: dict[str, Any]) -> ChainTargets:
    _finite_all(ChainTargets, v)
    _check_increasing("ChainTargets.links", v["links"], "links")
    # every attitude within 1e-3 of unit norm (as check_unit_quat, all rows at once: the decoding
    # loop found them finite), kept as sent (the targets cross bit for bit)
    norms = np.linalg.norm(v["q_wxyz"], axis=1)
    bad = np.flatnonzero(np.abs(norms - 1.0) > 1e-3)
    if bad.size:
        k = int(bad[0])
        raise MessageError(f"ChainTargets.q_wxyz[link {v['links'][k] + 1}]: quaternion norm {norms[k]:.6g} is not 1")
    return ChainTargets(**v)


def _home(v: dict[str, Any]) -> ChainHome:
    _finite_all(ChainHome, v)
    v["offset_w_m"] = check_bounded("ChainHome.offset_w_m", v["offset_w_m"], MAX_HOME_OFFSET_M)
    return ChainHome(**v)


def _passive(v: dict[str, Any]) -> GroupPassiveLinks:
    # empty: none of the group's links is carried; otherwise strictly increasing (whether they are
    # the group's own links is the receiver's check: it knows the layout)
    if v["links"] and list(v["links"]) != sorted(set(v["links"])):
        raise MessageError(f"GroupPassiveLinks.links: {list(v['links'])} is not an increasing list of links")
    return GroupPassiveLinks(**v)


def _neighbour_pose(v: dict[str, Any]) -> NeighbourPose:
    _finite_all(NeighbourPose, v)
    if abs(v["observer"] - v["observed"]) != 1:
        raise MessageError(f"NeighbourPose.observed: link {v['observed'] + 1} is not a neighbour of link "
                           f"{v['observer'] + 1}")
    if v["t_capture_s"] < 0.0:
        raise MessageError(f"NeighbourPose.t_capture_s: {v['t_capture_s']:g} s is before the clock's start")
    for name in ("q_cm_wxyz", "q_bc_wxyz", "q_bm_wxyz"):
        v[name] = check_unit_quat(f"NeighbourPose.{name}", v[name])
    check_bounded("NeighbourPose.t_cm_m", v["t_cm_m"], MAX_NEIGHBOUR_RANGE_M)
    for name in ("camera_pos_b_m", "marker_pos_b_m"):
        check_bounded(f"NeighbourPose.{name}", v[name], MAX_MOUNT_OFFSET_M)
    v["cov_c"] = check_pd("NeighbourPose.cov_c", v["cov_c"])
    return NeighbourPose(**v)


def _load_observation(v: dict[str, Any]) -> LoadObservation:
    _finite_all(LoadObservation, v)
    if v["stamp_s"] < 0.0:
        raise MessageError(f"LoadObservation.stamp_s: {v['stamp_s']:g} s is before the clock's start")
    v["load_in_body_q_wxyz"] = check_unit_quat("LoadObservation.load_in_body_q_wxyz", v["load_in_body_q_wxyz"])
    check_bounded("LoadObservation.vehicle_in_load_m", v["vehicle_in_load_m"], MAX_LOAD_RANGE_M)
    joint = check_pd("LoadObservation.joint_cov", v["joint_cov"])
    try:
        return LoadObservation(v["vehicle"], v["stamp_s"], v["vehicle_in_load_m"], joint[:3, :3],
                               v["load_in_body_q_wxyz"], joint)
    except ValueError as exc:
        raise MessageError(f"LoadObservation: {exc}") from None


_VALIDATE = {LinkState: _link_state, Correction: _correction, GroupBoundaryReport: _boundary, GlobalShift: _shift,
             ChainTargets: _targets, GroupPassiveLinks: _passive, ChainHome: _home, NeighbourPose: _neighbour_pose,
             LoadObservation: _load_observation}
