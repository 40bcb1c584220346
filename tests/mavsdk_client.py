"""A MAVSDK ground-station client, run as its own process by the fleet tests.

    python tests/mavsdk_client.py URL SYSID [--timeout S] [--set-int NAME=V] [--set-float NAME=V]

Connects to ``URL`` (e.g. ``udpin://127.0.0.1:14541``), waits for the autopilot ``SYSID``, reads
two parameters (a float and an int), sets the parameters named by ``--set-int``/``--set-float``
and reads each back, subscribes to position, attitude, odometry and home telemetry until 5
positions, 10 attitudes, a home and every health flag set came (at most ``--timeout`` seconds),
reads the health flags and prints one JSON object with what it got. Exit code 0 when the system
was discovered, 1 otherwise.
"""

from __future__ import annotations

import argparse
import json
import sys
import threading
import time
from collections import Counter

from mavsdk import ComponentType, Configuration, Mavsdk
from mavsdk.plugins.param import Param, ParamError
from mavsdk.plugins.telemetry import Telemetry


def ground_station(url: str) -> Mavsdk:
    """A MAVSDK instance as a ground station, listening on ``url``."""
    cfg = Configuration.create_with_component_type(ComponentType.GROUND_STATION)
    mav = Mavsdk(cfg)
    cfg.destroy()
    mav.add_any_connection(url)
    return mav


def find_autopilot(mav: Mavsdk, sysid: int, timeout_s: float, out: dict):
    """The system ``sysid`` among those ``mav`` discovers within ``timeout_s`` (several vehicles
    may send to one port), or ``None``; ``out["discovered"]`` says which, and without it
    ``out["seen"]`` lists the system ids heard."""
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        found = next((s for s in mav.get_systems() if s.get_system_id() == sysid), None)
        if found is not None:
            out["discovered"] = True
            return found
        time.sleep(0.1)
    out["discovered"] = False
    out["seen"] = [s.get_system_id() for s in mav.get_systems()]
    return None


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("url")
    ap.add_argument("sysid", type=int)
    ap.add_argument("--timeout", type=float, default=20.0)
    ap.add_argument("--set-int", action="append", default=[], metavar="NAME=V")
    ap.add_argument("--set-float", action="append", default=[], metavar="NAME=V")
    args = ap.parse_args()

    mav = ground_station(args.url)
    out: dict = {"discovered": False}
    try:
        system = find_autopilot(mav, args.sysid, args.timeout, out)
        if system is None:
            return 1
        out["sysid"] = system.get_system_id()
        param = Param(system)
        try:
            out["IMP_KP_Z"] = param.get_param_float("IMP_KP_Z")
            out["MAV_SYS_ID"] = param.get_param_int("MAV_SYS_ID")
        except ParamError as exc:
            out["param_error"] = exc.result.name
        out["set"] = {}
        for kind, items in (("int", args.set_int), ("float", args.set_float)):
            for item in items:
                name, value = item.split("=", 1)
                entry: dict = {}
                try:
                    if kind == "int":
                        param.set_param_int(name, int(value))
                    else:
                        param.set_param_float(name, float(value))
                    entry["result"] = "SUCCESS"
                except ParamError as exc:
                    entry["result"] = exc.result.name
                try:
                    entry["read_back"] = (param.get_param_int(name) if kind == "int"
                                          else param.get_param_float(name))
                except ParamError as exc:
                    entry["read_back_error"] = exc.result.name
                out["set"][name] = entry
        telemetry = Telemetry(system)
        counts: Counter = Counter()
        last: dict = {}
        lock = threading.Lock()

        def record(name):
            def callback(data, _user_data):  # runs on a MAVSDK thread: store only
                with lock:
                    counts[name] += 1
                    last[name] = data
            return callback

        telemetry.subscribe_position(record("position"))
        telemetry.subscribe_attitude_euler(record("attitude_euler"))
        telemetry.subscribe_odometry(record("odometry"))
        telemetry.subscribe_home(record("home"))
        telemetry.subscribe_health_all_ok(record("health_all_ok"))  # (from SYS_STATUS, once a second)
        until = time.monotonic() + args.timeout
        while time.monotonic() < until:
            with lock:
                if (counts["position"] >= 5 and counts["attitude_euler"] >= 10 and counts["home"]
                        and last.get("health_all_ok")):
                    break
            time.sleep(0.05)
        health = telemetry.health()
        out["health"] = {name: getattr(health, name) for name in dir(health) if name.startswith("is_")}
        out["health_all_ok"] = telemetry.health_all_ok()
        with lock:
            out["telemetry_counts"] = dict(counts)
            if "position" in last:
                pos = last["position"]
                out["position"] = [pos.latitude_deg, pos.longitude_deg, pos.relative_altitude_m]
            if "home" in last:
                home = last["home"]
                out["home"] = [home.latitude_deg, home.longitude_deg, home.absolute_altitude_m]
        return 0
    finally:
        mav.destroy()
        print(json.dumps(out), flush=True)


if __name__ == "__main__":
    sys.exit(main())
