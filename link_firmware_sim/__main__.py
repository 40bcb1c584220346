"""Run one simulated Pixhawk as a MAVLink vehicle.

    python -m link_firmware_sim --config runs/<fleet run>/link.toml --instance 0 [--out DIR]
        [--sim-url tcpin://127.0.0.1:4560] [--onboard-url udpout://127.0.0.1:14540?bind=14580]
        [--gcs-url udpout://127.0.0.1:14550?bind=18570 | none] [--params FILE]

Instance ``i`` is MAVLink system ``i + 1``; the default ports follow PX4 SITL (simulator TCP
4560+i, onboard UDP 14540+i from 14580+i, GCS UDP 14550 from 18570+i). The physical link
(mass, inertia, rotors) and the firmware defaults come from a vehicle config
(:class:`~link_firmware_sim.config.VehicleSetup`: name, [skeleton], [rotors], [firmware], [origin],
[companion], [signing]); ``python -m sitl launch`` writes one, ``link.toml``, in its run folder.
With ``[signing]`` the onboard and GCS links are signed with the key in ``signing.key_file``. Parameters
changed over MAVLink persist in the parameter file (default ``DIR/link<i+1>_params.json``).
Stops cleanly on SIGTERM / Ctrl-C. Exit code 2 on a bad configuration or a busy port.
"""

from __future__ import annotations

import argparse
import logging
import sys
from pathlib import Path

from companion.cli import single_thread_blas
from companion.config import load_setup
from companion.configfile import ConfigError
from companion.kernels.warm import compile_notice
from companion.mavlink.transport import PortError

from .config import VehicleSetup
from .kernels import warm
from .vehicle.core import Vehicle
from .vehicle.links import VehiclePorts

log = logging.getLogger("link_firmware_sim")


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="python -m link_firmware_sim", description=__doc__.split("\n\n")[0])
    p.add_argument("--config", required=True, metavar="FILE",
                   help="vehicle config (the link.toml a fleet run writes): skeleton, rotors, firmware, origin")
    p.add_argument("--instance", type=int, required=True, metavar="I", help="0-based link index (sysid I+1)")
    p.add_argument("--out", metavar="DIR", help="folder for the tlog, flight log and parameters")
    p.add_argument("--sim-url", metavar="URL", help="simulator link (default tcpin://127.0.0.1:4560+I)")
    p.add_argument("--onboard-url", metavar="URL", help="companion link (default udpout://127.0.0.1:14540+I?bind=14580+I)")
    p.add_argument("--gcs-url", metavar="URL", help="GCS link, or 'none' (default udpout://127.0.0.1:14550?bind=18570+I)")
    p.add_argument("--params", metavar="FILE", help="parameter file (default DIR/link<I+1>_params.json)")
    p.add_argument("--log-rate", type=float, default=50.0, metavar="HZ", help="flight log rate (default 50)")
    p.add_argument("--standby", action="store_true",
                   help="load everything (modules, compiled kernels), then wait for a line on stdin before "
                        "opening any port (the replacement of a scripted reboot, started ahead so that the "
                        "reboot's timing is the simulation's, not the host's; EOF: exit)")
    return p


def main(argv=None) -> int:
    args = build_parser().parse_args(argv)
    logging.basicConfig(level=logging.INFO, format=f"%(asctime)s link{args.instance + 1} %(levelname)s %(message)s")
    try:
        sc = load_setup(VehicleSetup, args.config)
    except ConfigError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    if not 0 <= args.instance < sc.skeleton.n_links:
        print(f"error: --instance {args.instance} outside 0..{sc.skeleton.n_links - 1}", file=sys.stderr)
        return 2
    # The compiled kernels loaded (or compiled) before the ports open, as firmware boots before the
    # simulator connects: not in the first ticks of the lockstep, where every link would wait for it.
    with compile_notice("the firmware's compiled kernels", log, report_done=False):
        seconds = warm.warm_up(batch=False)
    if warm.ENABLED:
        log.info("compiled kernels ready in %.1f s", seconds)
    if args.standby:
        log.info("standby: waiting for the start line on stdin")
        if not sys.stdin.readline():
            log.info("standby: stdin closed before the start: exiting")
            return 0
        log.info("standby: started")
    ports = VehiclePorts.for_instance(args.instance, sim=args.sim_url, onboard=args.onboard_url, gcs=args.gcs_url)
    out = Path(args.out) if args.out else None
    try:
        key = sc.signing.key()
    except ValueError as exc:
        print(f"error: {args.config}: {exc}", file=sys.stderr)
        return 2
    try:
        vehicle = Vehicle.from_setup(sc, args.instance, ports, out, Path(args.params) if args.params else None,
                                     args.log_rate, key=key)
    except PortError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    with single_thread_blas():
        vehicle.run()
    return 0


if __name__ == "__main__":
    sys.exit(main())
