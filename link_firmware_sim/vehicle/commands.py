"""COMMAND_LONG and COMMAND_INT, each answered with a COMMAND_ACK:

* MAV_CMD_COMPONENT_ARM_DISARM: arm (refused while the EKF is not running), disarm (refused in
  flight unless param2 is PX4's force value :data:`FORCE_DISARM`); a param1 that does not round
  to 0 or 1 is DENIED;
* MAV_CMD_SET_MESSAGE_INTERVAL: a stream's interval on the link it came from (0: the default,
  -1: off);
* MAV_CMD_REQUEST_MESSAGE, MAV_CMD_REQUEST_AUTOPILOT_CAPABILITIES, MAV_CMD_GET_HOME_POSITION:
  one message now;
* MAV_CMD_DO_SET_HOME: the home position (:mod:`.home`; arming sets it too);
* the dialect's MAV_CMD_SKELETON_SET_CONTACT: the hybrid controller's contact, or its release;
* MAV_CMD_INJECT_FAILURE: a failure injected into the vehicle's sensors or motors
  (:mod:`.failures`), acknowledged as PX4 does: DENIED while ``SYS_FAILURE_EN`` is 0 or for a
  param that is not a number in range, UNSUPPORTED for a unit, type or instance not simulated;
* anything else: MAV_RESULT_UNSUPPORTED.

A parameter read as a number (a message id, an interval, the force value) that is not finite
makes the command a bad message (:class:`MessageError`: counted, not acted on).
"""

from __future__ import annotations

import logging
import math

import numpy as np

from companion.mavlink.codec import MessageError, decode_contact_command
from companion.mavlink.dialect import load_dialect

from .failures import OK, parse_failure
from .home import on_set_home
from .links import Endpoint, statustext
from .streams.schedule import BUILDERS

__all__ = ["FORCE_DISARM", "on_command", "ack"]

log = logging.getLogger(__name__)
D = load_dialect()

#: MAV_CMD_COMPONENT_ARM_DISARM param2 that disarms a vehicle in flight (PX4, ArduPilot)
FORCE_DISARM = 21196


def _finite(msg, name: str) -> float:
    """Command parameter ``name`` of ``msg``; :class:`MessageError` when it is NaN or infinite."""
    value = getattr(msg, name)
    if not math.isfinite(value):
        raise MessageError(f"{msg.get_type()}.{name}: not finite ({value!r})")
    return value


def ack(ep: Endpoint, msg, result: int) -> None:
    ep.port.send(D.MAVLink_command_ack_message(msg.command, result, 255, 0, msg.get_srcSystem(),
                                               msg.get_srcComponent()))


def on_command(v, ep: Endpoint, msg) -> None:
    """A COMMAND_LONG or COMMAND_INT ``msg`` to vehicle ``v`` from link ``ep``."""
    cmd = msg.command
    if cmd == D.MAV_CMD_COMPONENT_ARM_DISARM:
        _arm_disarm(v, ep, msg)
    elif cmd == D.MAV_CMD_SET_MESSAGE_INTERVAL:
        accepted = v.streams.set_interval(ep, int(_finite(msg, "param1")), _finite(msg, "param2"))
        ack(ep, msg, D.MAV_RESULT_ACCEPTED if accepted else D.MAV_RESULT_UNSUPPORTED)
    elif cmd in (D.MAV_CMD_REQUEST_MESSAGE, D.MAV_CMD_REQUEST_AUTOPILOT_CAPABILITIES, D.MAV_CMD_GET_HOME_POSITION):
        _request_message(v, ep, msg)
    elif cmd == D.MAV_CMD_DO_SET_HOME:
        on_set_home(v, ep, msg, ack)
    elif cmd == D.MAV_CMD_SKELETON_SET_CONTACT:
        _set_contact(v, ep, msg)
    elif cmd == D.MAV_CMD_INJECT_FAILURE:
        _inject_failure(v, ep, msg)
    else:
        ack(ep, msg, D.MAV_RESULT_UNSUPPORTED)


def _arm_disarm(v, ep: Endpoint, msg) -> None:
    fw = v.fw
    action = _finite(msg, "param1")
    if not -0.5 <= action < 1.5:  # PX4 rounds it: 1 arms, 0 disarms, anything else is refused
        log.warning("link %d: ARM_DISARM param1 %g is neither 0 nor 1", v.system_id, action)
        statustext(ep, D.MAV_SEVERITY_ERROR, f"Unsupported ARM_DISARM param: {action:.3g}")
        ack(ep, msg, D.MAV_RESULT_DENIED)
        return
    if action >= 0.5:
        was_armed = fw.armed
        result = D.MAV_RESULT_ACCEPTED if fw.arm(v.fc_time_s) else D.MAV_RESULT_TEMPORARILY_REJECTED
        if fw.armed and not was_armed:
            v.home.on_armed(v)
    elif fw.armed and not fw.landed(v.fc_time_s) and int(round(_finite(msg, "param2"))) != FORCE_DISARM:
        # PX4: disarming in flight needs the force value (the link would fall)
        v.errors["disarm_refused"] += 1
        log.warning("link %d: disarm refused in flight (param2 %g, force is %d)", v.system_id, msg.param2,
                    FORCE_DISARM)
        statustext(ep, D.MAV_SEVERITY_CRITICAL, f"Disarm refused: in flight (force {FORCE_DISARM})")
        result = D.MAV_RESULT_DENIED
    else:
        fw.disarm()
        result = D.MAV_RESULT_ACCEPTED
    ack(ep, msg, result)


def _request_message(v, ep: Endpoint, msg) -> None:
    """The message now (AUTOPILOT_VERSION at any time, the others once the EKF runs); DENIED when
    there is nothing to send (a report of a controller that is not running)."""
    if msg.command == D.MAV_CMD_REQUEST_MESSAGE:
        mid = int(_finite(msg, "param1"))
    elif msg.command == D.MAV_CMD_GET_HOME_POSITION:  # (deprecated by REQUEST_MESSAGE; QGroundControl sends it)
        mid = D.MAVLINK_MSG_ID_HOME_POSITION
    else:
        mid = D.MAVLINK_MSG_ID_AUTOPILOT_VERSION
    builder = BUILDERS.get(mid)
    if builder is None or (mid != D.MAVLINK_MSG_ID_AUTOPILOT_VERSION and not v.fw.initialized):
        ack(ep, msg, D.MAV_RESULT_UNSUPPORTED if builder is None else D.MAV_RESULT_TEMPORARILY_REJECTED)
        return
    out = builder(v)
    ack(ep, msg, D.MAV_RESULT_ACCEPTED if out is not None else D.MAV_RESULT_DENIED)
    if out is not None:
        ep.port.send(out)


def _set_contact(v, ep: Endpoint, msg) -> None:
    """MAV_CMD_SKELETON_SET_CONTACT: the hybrid controller's contact (or its release), validated;
    refused with MAV_RESULT_DENIED and a STATUSTEXT saying why."""
    fw = v.fw
    if msg.get_type() != "COMMAND_LONG":
        reason = "Contact refused: send it as COMMAND_LONG"
    elif fw.config.controller != "hybrid":
        reason = f"Contact refused: controller {fw.config.controller} (SKL_CTRL 2)"
    else:
        try:
            contact = decode_contact_command(msg)
            fw.set_contact(v.fc_time_s, contact)
        except ValueError as exc:  # MessageError too
            reason = f"Contact refused: {exc}"
        else:
            log.info("link %d: contact %s", v.system_id, "released" if contact is None else
                     f"{contact.force_n:g} N along {np.round(contact.normal_w, 3).tolist()} (world)")
            ack(ep, msg, D.MAV_RESULT_ACCEPTED)
            return
    log.warning("link %d: %s", v.system_id, reason)
    statustext(ep, D.MAV_SEVERITY_WARNING, reason)
    ack(ep, msg, D.MAV_RESULT_DENIED)


def _inject_failure(v, ep: Endpoint, msg) -> None:
    """MAV_CMD_INJECT_FAILURE (param1 FAILURE_UNIT, param2 FAILURE_TYPE, param3 instance, 0: all):
    applied to the vehicle's :class:`~.failures.FailureInjector`, reported to every link as a
    STATUSTEXT and in the log; refused with a STATUSTEXT to the sender when ``SYS_FAILURE_EN`` is 0
    or a param is not a number in range (DENIED), or when it is not simulated (UNSUPPORTED)."""
    if not v.params.values["SYS_FAILURE_EN"]:
        reason, result = "Failure injection disabled (SYS_FAILURE_EN 0)", D.MAV_RESULT_DENIED
    else:
        try:
            unit, ftype, instance = parse_failure(msg.param1, msg.param2, msg.param3)
        except ValueError as exc:
            reason, result = f"Failure injection refused: {exc}", D.MAV_RESULT_DENIED
        else:
            what = v.failures.inject(unit, ftype, instance)
            if what is not None:
                text = f"Failure injection: {what}"
                log.warning("link %d at %.2f s: %s", v.system_id, v.fc_time_s, text)
                severity = D.MAV_SEVERITY_INFO if ftype == OK else D.MAV_SEVERITY_WARNING
                v.recorder.statustext(v.fc_time_s, severity, text)
                v.status_all(severity, text)
                ack(ep, msg, D.MAV_RESULT_ACCEPTED)
                v.apply_link_failure()  # (after the acknowledgement: it may have come on that link)
                return
            reason = f"Failure unsupported: unit {unit} type {ftype} inst {instance}"
            result = D.MAV_RESULT_UNSUPPORTED
    log.warning("link %d: %s", v.system_id, reason)
    statustext(ep, D.MAV_SEVERITY_WARNING, reason)
    ack(ep, msg, result)
