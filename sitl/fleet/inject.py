"""``[faults.inject]`` in fleet mode: the launcher commands the failure as a ground station would.

The injected link's parameter file gets ``SYS_FAILURE_EN = 1`` before its vehicle starts
(:func:`enable_failure_injection`, as a user sets it in QGroundControl); at ``at_s`` of simulated
time :class:`FailureCommander` sends MAV_CMD_INJECT_FAILURE to the vehicle's ground-station port
(signed when that link signs), and at ``at_s + duration_s`` the same command with
FAILURE_TYPE_OK. The vehicle acknowledges to its ground station and reports what the failure did
in ``linkN_ports.json`` (``failures``); the launcher keeps when it sent each command.
"""

from __future__ import annotations

import json
import logging
from pathlib import Path

from companion.mavlink.dialect import load_dialect
from companion.mavlink.port import MavlinkPort
from link_firmware_sim.vehicle.failures import OK

from ..scenario import Scenario

__all__ = ["GCS_SYSTEM_ID", "enable_failure_injection", "FailureCommander"]

log = logging.getLogger(__name__)

#: the system id the launcher's commands come from (a ground station's, as QGroundControl's)
GCS_SYSTEM_ID = 255


def enable_failure_injection(params_file: Path) -> None:
    """``SYS_FAILURE_EN = 1`` in a vehicle's parameter file (created, or its other values kept)."""
    stored = {}
    if params_file.exists():
        try:
            stored = json.loads(params_file.read_text())
        except (OSError, ValueError):
            stored = {}
    if not isinstance(stored, dict):
        stored = {}
    stored["SYS_FAILURE_EN"] = 1
    params_file.parent.mkdir(parents=True, exist_ok=True)
    params_file.write_text(json.dumps(stored, indent=1))


class FailureCommander:
    """Sends ``sc.faults.inject``'s two commands to the vehicle listening at ``vehicle_gcs_port``
    when they are due (:meth:`tick`); :attr:`sent` holds when (``injected_at_s``, ``cleared_at_s``)."""

    def __init__(self, sc: Scenario, vehicle_gcs_port: int):
        self.fault = sc.faults.inject
        mode = sc.signing.link_mode("gcs")
        self.port = MavlinkPort(f"udpout://127.0.0.1:{vehicle_gcs_port}", GCS_SYSTEM_ID, 190,
                                signing=mode, key=sc.signing.key() if mode != "off" else None)
        self.sent: dict = {}

    def tick(self, t: float) -> None:
        """The command due at simulated time ``t``, if one is."""
        f = self.fault
        ftype = f.due(t, self.sent)
        if ftype is None:
            return
        D = load_dialect()
        self.port.send(D.MAVLink_command_long_message(f.link, 1, D.MAV_CMD_INJECT_FAILURE, 0, f.unit_id, ftype,
                                                      f.instance, 0, 0, 0, 0))
        log.warning("fault: MAV_CMD_INJECT_FAILURE %s %s (instance %d) to link %d at t = %.2f s", f.unit,
                    "ok" if ftype == OK else f.type, f.instance, f.link, t)

    def close(self) -> None:
        self.port.close()
