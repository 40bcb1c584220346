"""``python -m sitl fault KIND RUN_DIR ...``: a harness fault asked of a running fleet.

    python -m sitl fault vehicle-off RUN_DIR --link N [--restart-after S] [--at S]
    python -m sitl fault companion-off RUN_DIR --group G [--restart-after S] [--at S]

``vehicle-off``: link N's Pixhawk loses power (its process is killed, its rotors stop); with
``--restart-after S`` a new one powers on S simulated seconds later and rejoins the lockstep.
``companion-off``: group G's companion (1: a centralised fleet's one) is killed; with
``--restart-after S`` a new one starts S simulated seconds later. ``--at S``: at simulated time S
(default: at once). The fleet plays it as it plays the scenario's ``[faults]`` table
(:mod:`sitl.fleet.faults`); the reply (printed as JSON) says when, or why not. Exit codes: 0
accepted, 2 refused or a bad option, 3 no fleet running in RUN_DIR (or it did not answer).
"""

from __future__ import annotations

import json
import sys
from pathlib import Path

from companion.cli import nonnegative_seconds, seconds

from .fault_socket import send_request

__all__ = ["add_fault_parser"]


def _cmd_fault(args) -> int:
    request = {"kind": args.kind.replace("-", "_"), "target": args.link if args.kind == "vehicle-off" else args.group,
               "restart_after_s": args.restart_after}
    if args.at is not None:
        request["at_s"] = args.at
    try:
        reply = send_request(args.run_dir / "faults.sock", request, args.timeout)
    except (ConnectionError, TimeoutError, OSError, ValueError) as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 3
    print(json.dumps(reply, indent=2))
    return 0 if reply.get("accepted") else 2


def add_fault_parser(sub) -> None:
    """The ``fault`` command on the ``python -m sitl`` subparsers ``sub``."""
    fa = sub.add_parser("fault", help="switch a vehicle or companion of a running fleet off (and on again)",
                        description="Switch a vehicle (its Pixhawk loses power) or a companion of a running fleet "
                                    "off, and on again with --restart-after, as the scenario's [faults] table does. "
                                    "Prints the fleet's reply as JSON; exit code 0 accepted, 2 refused, 3 no fleet "
                                    "running in RUN_DIR.",
                        epilog="e.g. python -m sitl fault vehicle-off runs/launch-three_link-... --link 2 "
                               "--restart-after 3")
    kinds = fa.add_subparsers(dest="kind", metavar="KIND", required=True)
    for kind, target, what in (("vehicle-off", "--link", "link"), ("companion-off", "--group", "group")):
        k = kinds.add_parser(kind, help=f"switch a {what}'s {'Pixhawk' if what == 'link' else 'companion'} off")
        k.add_argument("run_dir", metavar="RUN_DIR", type=Path, help="the running fleet's run folder (launch --out)")
        k.add_argument(target, type=int, required=True, metavar="N", help=f"the {what} (from 1)")
        k.add_argument("--restart-after", type=nonnegative_seconds, default=0.0, metavar="S",
                       help="power on again S simulated seconds later (default 0: stays off)")
        k.add_argument("--at", type=nonnegative_seconds, metavar="S", help="at simulated time S (default: at once)")
        k.add_argument("--timeout", type=seconds, default=10.0, metavar="S", help="wait this long for the reply")
    fa.set_defaults(func=_cmd_fault)
