"""Run one simulated Pixhawk as a MAVLink vehicle.

    python -m link_firmware_sim --config configs/sitl/three_link.toml --instance 0 [--out DIR]
        [--sim-url tcpin://127.0.0.1:4560] [--onboard-url udpout://127.0.0.1:14540?bind=14580]
        [--gcs-url udpout://127.0.0.1:14550?bind=18570 | none] [--params FILE]

Instance ``i`` is MAVLink system ``i + 1``; the default ports follow PX4 SITL (simulator TCP
4560+i, onboard UDP 14540+i from 14580+i, GCS UDP 14550 from 18570+i). The physical link
(mass, inertia, rotors) and the firmware defaults come from the scenario file; parameters
changed over MAVLink persist in the parameter file (default ``DIR/link<i+1>_params.json``).
Stops cleanly on SIGTERM / Ctrl-C. Exit code 2 on a bad configuration or a busy port.
"""

from __future__ import annotations

import argparse
import logging
import sys
from pathlib import Path

from companion.configfile import ConfigError
from companion.mavlink.port import PortError
from companion.runtime import single_thread_blas

from sitl.skeleton import link_inertia  # the physical link is described by the scenario
from sitl.scenario import load_scenario

from .allocation import RotorGeometry
from .firmware import LinkFirmware
from .params import ParamTable, StreamRates
from .vehicle import Vehicle, VehiclePorts


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="python -m link_firmware_sim", description=__doc__.split("\n\n")[0])
    p.add_argument("--config", required=True, metavar="FILE", help="scenario file (physical link and firmware)")
    p.add_argument("--instance", type=int, required=True, metavar="I", help="0-based link index (sysid I+1)")
    p.add_argument("--out", metavar="DIR", help="folder for the tlog, flight log and parameters")
    p.add_argument("--sim-url", metavar="URL", help="simulator link (default tcpin://127.0.0.1:4560+I)")
    p.add_argument("--onboard-url", metavar="URL", help="companion link (default udpout://127.0.0.1:14540+I?bind=14580+I)")
    p.add_argument("--gcs-url", metavar="URL", help="GCS link, or 'none' (default udpout://127.0.0.1:14550?bind=18570+I)")
    p.add_argument("--params", metavar="FILE", help="parameter file (default DIR/link<I+1>_params.json)")
    return p


def main(argv=None) -> int:
    args = build_parser().parse_args(argv)
    logging.basicConfig(level=logging.INFO, format=f"%(asctime)s link{args.instance + 1} %(levelname)s %(message)s")
    try:
        sc = load_scenario(args.config)
    except ConfigError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    if not 0 <= args.instance < sc.skeleton.n_links:
        print(f"error: --instance {args.instance} outside 0..{sc.skeleton.n_links - 1}", file=sys.stderr)
        return 2
    defaults = VehiclePorts.px4_sitl(args.instance)
    gcs = defaults.gcs if args.gcs_url is None else (None if args.gcs_url == "none" else args.gcs_url)
    ports = VehiclePorts(sim=args.sim_url or defaults.sim, onboard=args.onboard_url or defaults.onboard, gcs=gcs)
    out = Path(args.out) if args.out else None
    params_path = Path(args.params) if args.params else (out / f"link{args.instance + 1}_params.json" if out else None)
    geometry = RotorGeometry.odar(drag_ratio=sc.rotors.drag_ratio_m, x_scale=sc.skeleton.rotor_x_scale)
    firmware = LinkFirmware(args.instance, sc.firmware, link_inertia(sc.skeleton, geometry), geometry)
    # The companion reads SKELETON_LINK_STATE (dialect mode) or ODOMETRY (standard mode): stream the one it uses.
    rate = sc.companion.state_rate_hz
    rates = StreamRates(state_hz=rate, odometry_hz=0.0) if sc.companion.mode == "dialect" else StreamRates(0.0, rate)
    params = ParamTable(args.instance + 1, sc.firmware, sc.origin, rates, params_path)
    try:
        vehicle = Vehicle(args.instance, firmware, params, ports, out, sc.sim.log_rate_hz, sc.rotors.thrust_max_n)
    except PortError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    with single_thread_blas():
        vehicle.run()
    return 0


if __name__ == "__main__":
    sys.exit(main())
