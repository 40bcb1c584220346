"""A MAVSDK ground station that injects a GPS failure, run as its own process by the fleet tests.

    python tests/mavsdk_failure.py URL SYSID [--off-s S] [--timeout S]

Connects to ``URL`` (e.g. ``udpin://127.0.0.1:14550``, where every vehicle of a fleet sends its
ground-station traffic), waits for the autopilot ``SYSID`` among the systems it discovers, sets
``SYS_FAILURE_EN`` to 1 with the Param plugin, then with the Failure plugin injects GPS off into
it, waits ``--off-s`` seconds and clears it (GPS ok). Prints one JSON object: the parameter's
read-back and each injection's result with its wall time. Exit code 0 when the system was
discovered, 1 otherwise.
"""

from __future__ import annotations

import argparse
import json
import sys
import time

from mavsdk.plugins.failure import Failure, FailureError, FailureType, FailureUnit
from mavsdk.plugins.param import Param
from mavsdk_client import find_autopilot, ground_station  # (this folder: the script's own)


def _inject(failure: Failure, ftype) -> dict:
    t = time.time()
    try:
        failure.inject(FailureUnit.SENSOR_GPS, ftype, 0)
        return {"result": "SUCCESS", "wall_s": t}
    except FailureError as exc:
        return {"result": exc.result.name, "wall_s": t}


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("url")
    ap.add_argument("sysid", type=int)
    ap.add_argument("--off-s", type=float, default=3.0)
    ap.add_argument("--timeout", type=float, default=20.0)
    args = ap.parse_args()

    mav = ground_station(args.url)
    out: dict = {"discovered": False}
    try:
        system = find_autopilot(mav, args.sysid, args.timeout, out)
        if system is None:
            return 1
        param = Param(system)
        param.set_param_int("SYS_FAILURE_EN", 1)  # before the Failure plugin starts: it reads it then
        out["SYS_FAILURE_EN"] = param.get_param_int("SYS_FAILURE_EN")
        failure = Failure(system)
        out["off"] = _inject(failure, FailureType.OFF)
        time.sleep(args.off_s)
        out["ok"] = _inject(failure, FailureType.OK)
        return 0
    finally:
        mav.destroy()
        print(json.dumps(out), flush=True)


if __name__ == "__main__":
    sys.exit(main())
