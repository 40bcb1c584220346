"""Companion command line.

    python -m companion --config FILE [--group G] [--out DIR] [--start-center X,Y,Z] [--duration S]
    python -m companion replay IN.npz OUT.npz [--groups 1,2/3,4,5/6,7] [--eps M] [--alpha A]
    python -m companion dialect
    python -m companion keys new FILE | keys check FILE | keys zenoh FILE --groups N
    python -m companion certs DIR --groups N [--hosts H1 .. HN] [--days D] [--overwrite]

The first form runs the daemon: it connects to the links of the config's ``[companion]``
section (SITL UDP ports by default; serial devices on hardware), applies the constraints at
20 Hz and sends corrections and targets until SIGTERM / Ctrl-C. With ``companion.distributed``
one daemon runs per group (``--group G``, 1-based) and the groups meet over Zenoh for the global
step (``[zenoh]``), the first live group of ``zenoh.leader_order`` leading. ``dialect`` prints what
MAVProxy, mavlogdump/MAVExplorer and MAVSDK each need to decode the project's messages; ``keys``
creates and checks MAVLink 2 signing key files (``[signing]``) and the companions' Zenoh
user-password file (``zenoh.users_file``); ``certs`` creates the fleet CA and each group's TLS
certificate for mutual TLS between the companions (``[zenoh.tls] certs_dir``).
Exit codes: 0 success, 2 bad input (the message names the file, key and reason).
"""

from __future__ import annotations

import argparse
import logging
import math
import sys
import time
from pathlib import Path

from .estimation.sckf import CAParams
from .estimation.semi import parse_groups, validate_groups
from .replay import ReplayInputError, load_replay_input, replay, save_replay_output
from .cli import LOG_FORMAT, make_run_dir, progress_bar, run_subcommand, seconds


EXIT_BAD_INPUT = 2
#: stopped with Ctrl-C before it ran (waiting for a Zenoh listen address to come up)
EXIT_INTERRUPTED = 130


def _cmd_replay(args) -> int:
    try:
        params = CAParams(alpha=args.alpha, eps=args.eps, max_iter=args.max_iter)
        data = load_replay_input(args.input)
        if args.groups:
            groups = parse_groups(args.groups, data.n_links)
        else:
            groups = validate_groups([range(data.n_links)], data.n_links)
    except (ReplayInputError, ValueError) as exc:
        print(f"error: {exc}", file=sys.stderr)
        return EXIT_BAD_INPUT
    with progress_bar(total=data.n_steps, desc="replay", unit="step", disable=args.quiet) as bar:
        out = replay(data, groups, params, progress=bar.update)
    try:
        save_replay_output(args.output, out)
    except OSError as exc:
        print(f"error: cannot write {args.output}: {exc}", file=sys.stderr)
        return EXIT_BAD_INPUT
    print(
        f"{data.n_steps} steps, {data.n_links} links, groups {out['groups']}: "
        f"constraint error |c| mean {out['residual_before'].mean():.4g} -> {out['residual_after'].mean():.4g} "
        f"(max after {out['residual_after'].max():.4g}), CA iterations mean {out['iterations'].mean():.2f} "
        f"max {out['iterations'].max()}; wrote {args.output}"
    )
    return 0


def _cmd_daemon(args) -> int:
    from .config import CompanionSetup, load_setup
    from .configfile import ConfigError
    from .daemon import CompanionDaemon
    from .mavlink.transport import PortError

    try:
        scenario = load_setup(CompanionSetup, args.config)
        center = None
        if args.start_center:
            try:
                center = [float(x) for x in args.start_center.split(",")]
            except ValueError:
                center = []
            if len(center) != 3 or not all(math.isfinite(x) for x in center):
                raise ValueError(f"--start-center {args.start_center}: expected X,Y,Z, three finite numbers [m]")
        group = None if args.group is None else args.group - 1
        out_dir = make_run_dir(f"companion-{scenario.name}" + (f"-group{args.group}" if args.group else ""), args.out)
        started = time.monotonic()  # (--duration counts the wait for a Zenoh address that is not up yet)
        daemon = CompanionDaemon(scenario, out_dir, center, group=group, config_file=str(args.config),
                                 bus_wait_s=args.duration)
    except ConfigError as exc:
        hint = ""
        if exc.key and "." not in exc.key and exc.reason.startswith("unknown key"):
            hint = ("\n(a SITL scenario holds the simulator's sections too: `python -m sitl launch` writes the "
                    "companion's own part to companion.toml in its run folder)")
        print(f"error: {exc}{hint}", file=sys.stderr)
        return EXIT_BAD_INPUT
    except (PortError, ValueError) as exc:
        print(f"error: {exc}", file=sys.stderr)
        return EXIT_BAD_INPUT
    except KeyboardInterrupt:
        print("interrupted before the companion started", file=sys.stderr)
        return EXIT_INTERRUPTED
    handler = logging.FileHandler(out_dir / "companion.log")
    handler.setFormatter(logging.Formatter(LOG_FORMAT))
    logging.getLogger().addHandler(handler)
    logging.getLogger(__name__).info("run folder %s (tlog, log, companion_summary.json)", out_dir)
    daemon.run(None if args.duration is None else max(args.duration - (time.monotonic() - started), 0.0))
    return 0


def _cmd_dialect(args) -> int:
    from .mavlink.dialect import DIALECT_XML, export_definitions, tool_environment

    env = tool_environment()
    name = env["MAVLINK_DIALECT"]
    xml = export_definitions() / "v1.0" / DIALECT_XML.name
    print("# pymavlink tools read the dialect from MDEF; eval \"$(python -m companion dialect)\" sets it:")
    for key, value in env.items():
        print(f"export {key}={value}")
    print(f"# MAVProxy:    mavproxy.py --master udpin:127.0.0.1:14550 --dialect {name}")
    print(f"# mavlogdump:  mavlogdump.py --dialect {name} --types SKELETON_LINK_STATE RUN/link1/link1.tlog")
    print(f"# MAVExplorer: MAVExplorer.py --dialect {name} RUN/link1/link1.tlog")
    print(f"# MAVSDK (Python): await drone.mavlink_direct.load_custom_xml(open({str(xml)!r}).read())")
    return 0


def _cmd_keys(args) -> int:
    import hashlib
    import shlex

    from .fleetnet.config import new_users_file, read_users_file
    from .mavlink.signing import load_key, new_key_file

    if args.action == "zenoh":
        if not args.groups or args.groups < 1:
            print("error: keys zenoh needs --groups N (the number of companion groups)", file=sys.stderr)
            return EXIT_BAD_INPUT
        try:
            new_users_file(args.file, args.groups, overwrite=args.force)
            users = read_users_file(args.file)
        except ValueError as exc:
            print(f"error: {exc}", file=sys.stderr)
            return EXIT_BAD_INPUT
        print(f"{args.file}: Zenoh users {', '.join(users)} (copy to every companion computer, mode 600)")
        print(f"name it in the config: [zenoh] users_file = \"{Path(args.file).resolve()}\"")
        return 0
    try:
        if args.action == "new":
            new_key_file(args.file, overwrite=args.force)
        key = load_key(args.file)
    except ValueError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return EXIT_BAD_INPUT
    fingerprint = hashlib.sha256(key).hexdigest()[:16]
    print(f"{args.file}: MAVLink 2 signing key, fingerprint {fingerprint} (compare, never share the file)")
    if args.action == "new":
        # key_file is read relative to the config file's folder: the absolute path is right anywhere
        print(f"name it in the config: [signing] mode = \"required\", key_file = \"{Path(args.file).resolve()}\"")
        # MAVProxy's prompt does no shell expansion: the shell expands $(...) on its command line
        print(f"MAVProxy: mavproxy.py --master=udpin:127.0.0.1:14550 --cmd=\"signing key $(cat {shlex.quote(str(args.file))})\"  "
              f"(or at its prompt: signing key, then the passphrase in {args.file})")
    return 0


def _cmd_certs(args) -> int:
    from .fleetnet.certs import CA_KEY, new_fleet_certs

    try:
        written = new_fleet_certs(args.dir, args.groups, args.hosts, days=args.days, overwrite=args.overwrite)
    except ValueError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return EXIT_BAD_INPUT
    except OSError as exc:
        print(f"error: cannot write to {args.dir}: {exc.strerror or exc}", file=sys.stderr)
        return EXIT_BAD_INPUT
    hosts = args.hosts or ["127.0.0.1"] * args.groups
    print(f"{args.dir}: fleet CA ca.pem (its key {CA_KEY}, mode 600: keep it off the companions) and "
          f"{args.groups} group certificates, valid {args.days} days:")
    for g, host in enumerate(hosts):
        print(f"  companion-g{g + 1}.pem / .key  for {host}")
    print(f"copy ca.pem, companion-g<G>.pem and companion-g<G>.key (mode 600) to group G's computer, into the "
          f"folder [zenoh.tls] certs_dir names (relative to the config file), e.g. \"{Path(args.dir).resolve()}\"; "
          "the endpoints must be tls/HOST:PORT with these hosts")
    logging.getLogger(__name__).debug("wrote %s", ", ".join(map(str, written)))
    return 0


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="python -m companion",
        description="Companion computer of an aerial skeleton: SCKF constraint application and tools.",
    )
    parser.add_argument("--config", metavar="FILE", help="run the daemon with this config: a hardware file, or the "
                                                          "companion.toml a SITL fleet run writes")
    parser.add_argument("--out", metavar="DIR",
                        help="daemon: run folder for its tlog, log and summary "
                             "(default: runs/companion-<name>[-group<G>]-<UTC time>)")
    parser.add_argument("--group", type=int, metavar="G",
                        help="daemon, distributed configs: the group (1-based) this companion serves")
    parser.add_argument("--start-center", metavar="X,Y,Z", help="daemon: anchor of the target trajectory [m, ENU]")
    parser.add_argument("--duration", type=seconds, metavar="S", help="daemon: stop after S seconds of wall time")
    parser.set_defaults(func=_cmd_daemon)
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")
    rp = sub.add_parser(
        "replay",
        help="apply the constraints offline to a recorded state stream (.npz)",
        description=(
            "Run the constraint application (Alg. 1; with --groups, Alg. 2 and the global step eq. 6) "
            "on every step of a recorded stream. Input keys: t [K], p [K,n,3], v [K,n,3], q [K,n,4] (w,x,y,z), "
            "w [K,n,3], P [K,n,9,9], d [n,3]."
        ),
    )
    rp.add_argument("input", metavar="IN.npz", help="recorded link states")
    rp.add_argument("output", metavar="OUT.npz", help="corrected states and residuals are written here")
    rp.add_argument(
        "--groups",
        metavar="LAYOUT",
        help="group layout, 1-based links, groups separated by '/': e.g. 1,2/3,4,5/6,7 (default: one group)",
    )
    rp.add_argument("--eps", type=float, default=CAParams.eps, metavar="M", help="stop at ||c|| <= M (default 0.01)")
    rp.add_argument("--alpha", type=float, default=CAParams.alpha, metavar="A", help="weakening factor (default 0.01)")
    rp.add_argument("--max-iter", type=int, default=CAParams.max_iter, metavar="N", help="CA iteration cap (default 20)")
    rp.add_argument("--quiet", action="store_true", help="no progress bar")
    rp.set_defaults(func=_cmd_replay)
    dp = sub.add_parser(
        "dialect",
        help="print what MAVProxy, mavlogdump, MAVExplorer and MAVSDK need to decode the dialect",
        description=(
            "Prints export lines and, as comments, each tool's command: eval \"$(python -m companion dialect)\" "
            "then e.g. mavproxy.py --dialect aerial_skeleton, or "
            "mavlogdump.py --dialect aerial_skeleton --types SKELETON_LINK_STATE run/link2/link2.tlog; "
            "MAVSDK loads the dialect XML with mavlink_direct.load_custom_xml"
        ),
    )
    dp.set_defaults(func=_cmd_dialect)
    kp = sub.add_parser(
        "keys",
        help="create or check a MAVLink 2 signing key file, or create the companions' Zenoh user file",
        description=(
            "new FILE: a random 256-bit passphrase in FILE (mode 600); the key is its SHA-256, as MAVProxy's "
            "'signing key PASSPHRASE' and QGroundControl derive it. check FILE: load it and print its fingerprint. "
            "zenoh FILE --groups N: a Zenoh user-password file for N group companions (companion-g1..gN, random "
            "passwords, mode 600) for [zenoh] users_file."
        ),
    )
    kp.add_argument("action", choices=("new", "check", "zenoh"),
                    help="new: create FILE; check: validate FILE; zenoh: create a Zenoh user file")
    kp.add_argument("--groups", type=int, metavar="N", help="zenoh: the number of companion groups")
    kp.add_argument("file", metavar="FILE", help="key file")
    kp.add_argument("--force", action="store_true", help="new: replace an existing FILE")
    kp.set_defaults(func=_cmd_keys)
    cp = sub.add_parser(
        "certs",
        help="create the fleet CA and one TLS certificate per group companion (Zenoh mutual TLS)",
        description=(
            "Writes to DIR a fleet CA (ca.pem, ca.key) and per group G companion-gG.pem / companion-gG.key, "
            "signed by the CA, for group G's host (its Zenoh endpoint's IP address or DNS name) and usable as "
            "server and client certificate; private keys mode 600. [zenoh.tls] certs_dir = DIR picks each "
            "group's files."
        ),
    )
    cp.add_argument("dir", metavar="DIR", help="folder for the files (created if missing)")
    cp.add_argument("--groups", type=int, required=True, metavar="N", help="the number of companion groups")
    cp.add_argument("--hosts", nargs="+", metavar="HOST",
                    help="each group's host, in group order: an IP address or DNS name, several for one group "
                         "separated by commas (default: 127.0.0.1 for every group)")
    cp.add_argument("--days", type=int, default=1095, metavar="D", help="validity in days (default 1095)")
    cp.add_argument("--overwrite", action="store_true", help="replace existing files (a new CA: recopy every file)")
    cp.set_defaults(func=_cmd_certs)
    return parser


def main(argv=None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    if args.command is None and args.config:
        args.command = "daemon"  # the daemon is the top-level form
    return run_subcommand(parser, argv, usage_exit=EXIT_BAD_INPUT, args=args)


if __name__ == "__main__":
    sys.exit(main())
