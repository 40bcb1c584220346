"""Foxglove's message schemas, JSON-encoded: the schema texts an MCAP file registers and the
messages' building blocks.

The schemas carry Foxglove's names (``foxglove.PoseInFrame``, ``foxglove.FrameTransforms``,
``foxglove.SceneUpdate``, ``foxglove.Log``, ``foxglove.CompressedImage``: its bytes base64 in JSON) and the layout of the fields written here, as in Foxglove's published
JSON schemas (``schemas/jsonschema/*.json`` of foxglove/foxglove-sdk); Foxglove and Lichtblick
choose a panel's decoder by the schema's name. ``skeleton.Series`` is this stack's own: a
timestamp and named numbers or arrays of numbers, for the Plot panel.
"""

from __future__ import annotations

import json

__all__ = ["SCHEMAS", "SERIES", "POSE_IN_FRAME", "FRAME_TRANSFORMS", "SCENE_UPDATE", "LOG", "COMPRESSED_IMAGE",
           "LOG_LEVEL_OF_SEVERITY",
           "stamp", "pose"]

POSE_IN_FRAME = "foxglove.PoseInFrame"
FRAME_TRANSFORMS = "foxglove.FrameTransforms"
SCENE_UPDATE = "foxglove.SceneUpdate"
SERIES = "skeleton.Series"
LOG = "foxglove.Log"
COMPRESSED_IMAGE = "foxglove.CompressedImage"
#: MAVLink STATUSTEXT severity (MAV_SEVERITY: 0 emergency ... 7 debug) -> foxglove.Log level
#: (1 debug, 2 info, 3 warning, 4 error, 5 fatal)
LOG_LEVEL_OF_SEVERITY = (5, 5, 5, 4, 3, 2, 2, 1)


def _obj(title: str | None = None, **properties) -> dict:
    out = {"type": "object", "properties": properties}
    if title:
        out["title"] = title
    return out


def _numbers(*names: str) -> dict:
    return {name: {"type": "number"} for name in names}


_TIME = _obj("time", sec={"type": "integer", "minimum": 0},
             nsec={"type": "integer", "minimum": 0, "maximum": 999999999})
_DURATION = _obj("duration", sec={"type": "integer"}, nsec={"type": "integer", "minimum": 0, "maximum": 999999999})
_VECTOR3 = _obj("foxglove.Vector3", **_numbers("x", "y", "z"))
_POINT3 = _obj("foxglove.Point3", **_numbers("x", "y", "z"))
_QUATERNION = _obj("foxglove.Quaternion", **_numbers("x", "y", "z", "w"))
_COLOR = _obj("foxglove.Color", **_numbers("r", "g", "b", "a"))
_POSE = _obj("foxglove.Pose", position=_VECTOR3, orientation=_QUATERNION)
_LINE_TYPE = {"title": "foxglove.LineType", "oneOf": [
    {"title": "LINE_STRIP", "const": 0}, {"title": "LINE_LOOP", "const": 1}, {"title": "LINE_LIST", "const": 2}]}

_CUBE = _obj("foxglove.CubePrimitive", pose=_POSE, size=_VECTOR3, color=_COLOR)
_LINE = _obj("foxglove.LinePrimitive", type=_LINE_TYPE, pose=_POSE, thickness={"type": "number"},
             scale_invariant={"type": "boolean"}, points={"type": "array", "items": _POINT3}, color=_COLOR,
             colors={"type": "array", "items": _COLOR},
             indices={"type": "array", "items": {"type": "integer", "minimum": 0}})
_ENTITY = _obj("foxglove.SceneEntity", timestamp=_TIME, frame_id={"type": "string"}, id={"type": "string"},
               lifetime=_DURATION, frame_locked={"type": "boolean"},
               cubes={"type": "array", "items": _CUBE}, lines={"type": "array", "items": _LINE})
_DELETION = _obj("foxglove.SceneEntityDeletion", timestamp=_TIME, type={"title": "foxglove.SceneEntityDeletionType",
                 "oneOf": [{"title": "MATCHING_ID", "const": 0}, {"title": "ALL", "const": 1}]}, id={"type": "string"})
_TRANSFORM = _obj("foxglove.FrameTransform", timestamp=_TIME, parent_frame_id={"type": "string"},
                  child_frame_id={"type": "string"}, translation=_VECTOR3, rotation=_QUATERNION)
_NUMBERS = {"oneOf": [{"type": ["number", "null"]}, {"type": "array", "items": {"type": ["number", "boolean", "null"]}}]}

#: schema name -> its JSON schema text (bytes, as an MCAP schema record holds it)
SCHEMAS: dict[str, bytes] = {
    name: json.dumps({**schema, "title": name}).encode()
    for name, schema in {
        POSE_IN_FRAME: _obj(timestamp=_TIME, frame_id={"type": "string"}, pose=_POSE),
        FRAME_TRANSFORMS: _obj(transforms={"type": "array", "items": _TRANSFORM}),
        SCENE_UPDATE: _obj(deletions={"type": "array", "items": _DELETION},
                           entities={"type": "array", "items": _ENTITY}),
        SERIES: {**_obj(timestamp=_TIME), "additionalProperties": _NUMBERS},
        COMPRESSED_IMAGE: _obj(timestamp=_TIME, frame_id={"type": "string"},
                               data={"type": "string", "contentEncoding": "base64"}, format={"type": "string"}),
        LOG: _obj(timestamp=_TIME, level={"title": "foxglove.LogLevel", "oneOf": [
            {"title": t, "const": i} for i, t in enumerate(("UNKNOWN", "DEBUG", "INFO", "WARNING", "ERROR", "FATAL"))]},
                  message={"type": "string"}, name={"type": "string"}, file={"type": "string"},
                  line={"type": "integer", "minimum": 0}),
    }.items()
}


def stamp(ns: int) -> dict:
    """A Foxglove ``time`` of ``ns`` nanoseconds."""
    return {"sec": ns // 1_000_000_000, "nsec": ns % 1_000_000_000}


def pose(p, q) -> dict:
    """A Foxglove pose of the position ``p`` (x, y, z) and the quaternion ``q`` (w, x, y, z)."""
    return {"position": {"x": p[0], "y": p[1], "z": p[2]}, "orientation": {"x": q[1], "y": q[2], "z": q[3], "w": q[0]}}
