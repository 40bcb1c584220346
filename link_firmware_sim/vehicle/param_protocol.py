"""The MAVLink parameter protocol over the vehicle's table (:mod:`.params`): PARAM_REQUEST_LIST,
PARAM_REQUEST_READ (by index or by name) and PARAM_SET, each answered with PARAM_VALUE.

Values travel as PX4 sends them: an integer's 32 bits in PARAM_VALUE's float field (bytewise). A
PARAM_SET of an integer is read bytewise, or C-cast when that reading is out of the parameter's
range (:func:`decode_int_param`). A refused PARAM_SET (unknown, read-only, out of range, not an
integer) is answered with a STATUSTEXT giving the reason and, as PX4 does, the unchanged
PARAM_VALUE. A change applies at once (:func:`apply_param`) and persists in the parameter file.
"""

from __future__ import annotations

import logging
import math
import struct

from companion.mavlink.dialect import load_dialect

from .links import Endpoint, statustext
from .params import ParamSpec, ParamTable
from .streams.schedule import RATE_PARAMS

__all__ = ["on_param", "param_value", "apply_param", "decode_int_param"]

log = logging.getLogger(__name__)
D = load_dialect()


def param_value(params: ParamTable, name: str):
    """PARAM_VALUE, PX4's bytewise encoding: an integer's 32 bits in the float field."""
    spec = params.spec(name)
    value = params.values[name]
    if spec.kind == "int":
        raw, ptype = _int_as_float_bits(int(value)), D.MAV_PARAM_TYPE_INT32
    else:
        raw, ptype = float(value), D.MAV_PARAM_TYPE_REAL32
    return D.MAVLink_param_value_message(name.encode(), raw, ptype, len(params.names), params.names.index(name))


def apply_param(v, name: str) -> None:
    """Vehicle ``v`` after its parameter ``name`` changed: the firmware reconfigured, and a stream
    rate's stream restarted at the new rate."""
    v.fw.reconfigure(v.params.firmware_config())
    if name in RATE_PARAMS:
        v.streams.reset_onboard_rates()


def on_param(v, ep: Endpoint, msg) -> None:
    """A PARAM_* ``msg`` to vehicle ``v`` from link ``ep``."""
    kind = msg.get_type()
    params = v.params
    names = params.names
    if kind == "PARAM_REQUEST_LIST":
        for name in names:
            ep.port.send(param_value(params, name))
        return
    if kind == "PARAM_REQUEST_READ":
        if msg.param_index >= 0:
            if msg.param_index < len(names):
                ep.port.send(param_value(params, names[msg.param_index]))
            return
        name = _param_id(msg)
        if name in params.values:
            ep.port.send(param_value(params, name))
        return
    if kind == "PARAM_SET":
        if msg.target_system not in (0, v.system_id):
            return
        name = _param_id(msg)
        spec = params.spec(name)
        if spec is None:
            log.warning("link %d: PARAM_SET of unknown parameter %r", v.system_id, name)
            statustext(ep, D.MAV_SEVERITY_ERROR, f"Param {name[:16]} unknown")
            return
        value = msg.param_value
        if spec.kind == "int":
            value = decode_int_param(value, spec)
        try:
            params.set(name, value)
        except ValueError as exc:
            log.warning("link %d: PARAM_SET refused: %s", v.system_id, exc)
            statustext(ep, D.MAV_SEVERITY_ERROR, _refusal_text(name, spec, value, str(exc)))
        else:
            apply_param(v, name)
        ep.port.send(param_value(params, name))  # the current value either way (PX4 behaviour)


def _param_id(msg) -> str:
    return msg.param_id.rstrip("\x00") if isinstance(msg.param_id, str) else msg.param_id.decode().rstrip("\x00")


def _refusal_text(name: str, spec: ParamSpec, value: float, reason: str) -> str:
    """The STATUSTEXT of a refused PARAM_SET (50 characters, as PX4 words them)."""
    if spec.read_only:
        return f"Param {name} is read-only"
    if not (spec.minimum <= value <= spec.maximum):
        return f"Param {name}: {value:g} out of [{spec.minimum:g}, {spec.maximum:g}]"
    return f"Param {name} refused: {reason.split(': ', 1)[-1]}"[:50]


def _int_as_float_bits(value: int) -> float:
    return struct.unpack("<f", struct.pack("<i", value))[0]


def decode_int_param(raw: float, spec: ParamSpec) -> float:
    """An integer PARAM_SET value: PX4's bytewise encoding (what this vehicle declares), or, when
    that is out of the parameter's range and the float is a whole number in it, a C-cast value (a
    client that did not know the parameter's type, e.g. MAVProxy before its first download). The
    two never both fit: integer ranges here stay within 2**24, where bytewise values are denormal."""
    bits = struct.unpack("<i", struct.pack("<f", raw))[0]
    if spec.minimum <= bits <= spec.maximum:
        return bits
    if math.isfinite(raw) and abs(raw) >= 1.1754944e-38:
        return raw  # a normal float: sent C-cast (the range and integer checks report what is wrong)
    return bits
