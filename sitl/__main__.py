"""SITL command line: one for every scenario kind (:mod:`sitl.scenarios`).

    python -m sitl fly --config configs/sitl/chain/three_link.toml [--duration S] [--set KEY=VALUE] [--no-sckf] [--out DIR]
    python -m sitl launch --config configs/sitl/chain/three_link.toml [--duration S] [--speed F] [--no-companion] [--out DIR]
    python -m sitl mcap RUN_DIR [--out FILE]
    python -m sitl view RUN_DIR [--view-port P] [--at S] [--screenshot PNG]
    python -m sitl campaign run --config FILE --set KEY=V1,V2 --seeds 0-9 [--scheduler tcp://HOST:PORT]
    python -m sitl fault vehicle-off RUN_DIR --link N [--restart-after S]

``fly`` is batch mode: MuJoCo physics at 1 kHz, link firmware at 500 Hz and the companion SCKF at
20 Hz, in one process on one clock; it flies every kind. ``launch`` is fleet mode: one MAVLink
vehicle process per link and the companion daemon, the harness in lockstep with them over
PX4-style simulator links; it flies the kinds that have a fleet form and refuses the others. Both
leave ``run.mcap`` (:mod:`companion.recording.mcap_log`) beside ``log.npz``; ``mcap`` writes it for an
existing run folder. ``view`` replays a run folder in the browser 3D view (:mod:`sitl.view`);
``fly --view`` and ``launch --view`` show the run as it flies. ``campaign`` flies a grid of
scenarios x settings x seeds on Dask (:mod:`sitl.campaign`). ``fault`` switches a vehicle or a
companion of a running fleet off (and on again), as the scenario's ``[faults]`` table does
(:mod:`sitl.fleet.fault_cli`).
Exit codes: 0 success, 1 the skeleton crashed, 2 bad configuration (the message names the file,
key and reason; also an option or a mode the scenario's kind does not have), 3 the fleet failed
(a process died), 130 interrupted (Ctrl-C or SIGTERM; fleet mode still writes the metrics when
the run got past the take-off).
"""

from __future__ import annotations

import argparse
import json
import signal
import sys
from contextlib import contextmanager
from pathlib import Path

from tqdm import tqdm
from tqdm.contrib.logging import logging_redirect_tqdm

from companion.configfile import ConfigError, parse_setting
from companion.cli import make_run_dir, pace, run_subcommand
from companion.recording.mcap_log import INSTALL_HINT, write_beside_log, write_run_mcap

from .campaign.cli import add_campaign_parser
from .fleet.fault_cli import add_fault_parser
from .cameras.rendering import RenderingUnavailable, choose_backend, require_rendering
from .scenario import Scenario, with_options
from .scenarios import load as load_scenario_file
from .view.cli import add_live_args, add_view_parser, live

# (the simulator's modules import MuJoCo, whose OpenGL backend is chosen first: _prepare_rendering)

EXIT_CRASH = 1
EXIT_BAD_CONFIG = 2
EXIT_FLEET = 3
EXIT_INTERRUPTED = 130
#: the vehicles' simulator links (``sitl.fleet.layout.SIM_LINKS``; here without importing the simulator)
SIM_LINKS = ("tcp", "unix")
#: the fleet companions' paths (``sitl.fleet.layout.COMPANION_KERNELS``; here without importing the simulator)
COMPANION_KERNELS = ("compiled", "numpy")


def _scenario(args):
    """``(kind, scenario)`` of the scenario file with ``--duration`` / ``--seed`` / ``--set`` applied
    (``ConfigError`` if invalid)."""
    overrides = {}
    if args.duration is not None:
        overrides["duration_s"] = args.duration
    if args.seed is not None:
        overrides["seed"] = args.seed
    try:
        settings = dict(parse_setting(s) for s in args.set)
    except ValueError as exc:
        raise ConfigError(args.config, "--set", str(exc)) from None
    return load_scenario_file(args.config, settings=settings, **overrides)


def _prepare_rendering(scenario, video) -> str | None:
    """Choose MuJoCo's OpenGL backend before the simulator imports MuJoCo: none for a run that
    renders nothing, a headless one that renders for a run with cameras or a video. ``None``, or
    the error for a run that renders on a machine where nothing can (exit code 2)."""
    renders = bool(scenario.cameras) or video is not None
    choose_backend(renders)
    if renders:
        try:
            require_rendering()
        except RenderingUnavailable as exc:
            return f"{'--video' if video is not None and not scenario.cameras else 'the scenario has cameras'}: {exc}"
    return None


class _Progress(tqdm):
    """The flight's progress in simulated seconds; the last update stops at the total (a flight's
    ticks can sum to a hair over its duration). Its clock starts at the first update: the time
    left is the flight's, not a first run's compilation of the kernels before it."""

    def __init__(self, *args, **kwargs):
        super().__init__(*args, **kwargs)
        self._flying = False

    def update(self, n=1):
        if not self._flying:
            self._flying = True
            self.reset()
        return super().update(max(0.0, min(n, self.total - self.n)))


@contextmanager
def _progress(scenario, args, desc: str, runs: int = 1):
    """The flight's progress bar on stderr; the console's log lines meanwhile (a warm-up's
    notice, a fault's warning) are written above it instead of into it."""
    with _Progress(total=runs * scenario.duration_s, desc=desc, unit="sim s", disable=args.quiet, file=sys.stderr,
                   bar_format="{l_bar}{bar}| {n:.1f}/{total:.1f} sim s [{elapsed}<{remaining}]") as bar, \
            logging_redirect_tqdm(tqdm_class=_Progress):
        yield bar


def _report(metrics: dict, out_dir, summary) -> int:
    print(json.dumps({k: metrics[k] for k in summary if k in metrics}, indent=2))
    print(f"wrote {out_dir}")
    if metrics.get("crashed"):
        return EXIT_CRASH
    return EXIT_INTERRUPTED if metrics.get("interrupted") else 0


def _cmd_fly(args) -> int:
    try:
        kind, scenario = _scenario(args)
    except ConfigError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return EXIT_BAD_CONFIG
    if args.video is not None and not kind.video:
        print(f"error: {args.config}: --video: a {kind.name} scenario makes no video", file=sys.stderr)
        return EXIT_BAD_CONFIG
    faults = getattr(scenario, "faults", None)  # (a ground robot's scenario has none)
    if faults is not None and faults.fleet_only:
        print(f"error: {args.config}: {', '.join(faults.fleet_only)}: fleet mode only "
              f"(python -m sitl launch --config {args.config})", file=sys.stderr)
        return EXIT_BAD_CONFIG
    problem = _prepare_rendering(scenario, args.video)
    if problem:
        print(f"error: {args.config}: {problem}", file=sys.stderr)
        return EXIT_BAD_CONFIG
    if isinstance(scenario, Scenario):  # the flying chain's options
        scenario = with_options(scenario, sckf=False if args.no_sckf else None,
                                selective_mapping=False if args.no_selective_mapping else None)
    options = {"video": args.video} if kind.video else {}
    out_dir = make_run_dir(f"fly-{scenario.name}", args.out)
    with live(args, scenario.name, out_dir) as replay_after:
        try:
            with _progress(scenario, args, scenario.name, kind.runs) as bar:
                metrics = kind.fly(scenario, out_dir, progress=bar.update, plots=not args.no_plots, **options)
        except KeyboardInterrupt:
            print(f"interrupted: no metrics ({out_dir})", file=sys.stderr)
            return EXIT_INTERRUPTED
        if not args.no_mcap and (out_dir / "log.npz").exists():
            write_beside_log(out_dir)
        code = _report(metrics, out_dir, kind.summary)
        if not metrics.get("interrupted"):  # (a fleet stopped with Ctrl-C: the user wants out)
            replay_after(out_dir)
    return code


def _raise_interrupt(_signum, _frame):
    raise KeyboardInterrupt


def _cmd_launch(args) -> int:
    try:
        kind, scenario = _scenario(args)
        if kind.launch is None:
            raise ValueError(f"a {kind.name} scenario has no fleet form: it flies in batch mode only "
                             f"(python -m sitl fly --config {args.config})")
        problem = _prepare_rendering(scenario, None)
        if problem:
            raise ValueError(problem)
        from .fleet.layout import check_fleet_scenario, check_instance_offset

        check_fleet_scenario(scenario)
        check_instance_offset(scenario, args.instance_offset, args.gcs_port)
    except ConfigError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return EXIT_BAD_CONFIG
    except ValueError as exc:
        print(f"error: {args.config}: {exc}", file=sys.stderr)
        return EXIT_BAD_CONFIG
    from .fleet.layout import FleetError

    out_dir = make_run_dir(f"launch-{scenario.name}", args.out)
    signal.signal(signal.SIGTERM, _raise_interrupt)  # `kill` / systemd stop: the same clean stop as Ctrl-C
    with live(args, f"{scenario.name} (fleet)", out_dir) as replay_after:
        try:
            with _progress(scenario, args, f"{scenario.name} (fleet)") as bar:
                metrics = kind.launch(scenario, out_dir, speed=args.speed, progress=bar.update,
                                      companion=not args.no_companion, plots=not args.no_plots,
                                      instance_offset=args.instance_offset, sim_link=args.sim_link,
                                      batch_scheduling=False if args.default_scheduling else None,
                                      gcs_port=args.gcs_port, companion_kernels=args.companion_kernels)
        except FleetError as exc:
            print(f"error: {exc} (logs in {out_dir})", file=sys.stderr)
            return EXIT_FLEET
        except KeyboardInterrupt:  # during start-up: the fleet is already stopped
            print(f"interrupted (logs in {out_dir})", file=sys.stderr)
            return EXIT_INTERRUPTED
        code = _report(metrics, out_dir, kind.summary)
        signal.signal(signal.SIGTERM, signal.SIG_DFL)
        if not metrics.get("interrupted"):  # (a fleet stopped with Ctrl-C: the user wants out)
            replay_after(out_dir)
    return code


def _cmd_mcap(args) -> int:
    try:
        path, counts = write_run_mcap(args.run_dir, args.out)
    except ImportError:
        print(f"error: the mcap package is missing; {INSTALL_HINT}", file=sys.stderr)
        return EXIT_BAD_CONFIG
    except (OSError, ValueError) as exc:
        print(f"error: {args.run_dir}: {exc}", file=sys.stderr)
        return EXIT_BAD_CONFIG
    print(f"wrote {path}: {len(counts)} channels, {sum(counts.values())} messages")
    return 0


def _run_args(p: argparse.ArgumentParser, kind: str) -> None:
    """The options ``fly`` and ``launch`` share (read by :func:`_scenario`, :func:`_progress`)."""
    p.add_argument("--config", required=True, metavar="FILE", help="scenario file, e.g. configs/sitl/chain/three_link.toml")
    p.add_argument("--duration", type=float, metavar="S",
                   help="simulated seconds (default: the scenario's); must be longer than the scenario's take-off, "
                        "trajectory.takeoff_start_s + takeoff_duration_s, where the metrics window starts")
    p.add_argument("--seed", type=int, help="random seed (default: the scenario's)")
    p.add_argument("--set", action="append", default=[], metavar="KEY=VALUE",
                   help="set a key of the scenario file, e.g. firmware.ekf.gate_sigma=4 (a TOML value; repeat for more)")
    p.add_argument("--out", metavar="DIR", help=f"run folder (default: runs/{kind}-<scenario>-<UTC time>)")
    p.add_argument("--quiet", action="store_true", help="no progress bar")


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="python -m sitl", description="MuJoCo SITL of aerial skeletons.")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")
    fl = sub.add_parser(
        "fly",
        help="fly a scenario in batch mode (one process, deterministic)",
        description="Fly a scenario in batch mode: physics 1 kHz, firmware 500 Hz, companion SCKF 20 Hz, one clock.",
    )
    _run_args(fl, "fly")
    fl.add_argument("--no-sckf", action="store_true", help="fly on the EKF alone (no companion corrections)")
    fl.add_argument("--no-selective-mapping", action="store_true",
                    help="allocate with the infinity-norm solution only (Prop. 1), without selective mapping")
    fl.add_argument("--no-plots", action="store_true", help="skip the PNG plots")
    fl.add_argument("--video", metavar="PATH", type=Path,
                    help="write an MP4 of the flight (chase camera, 30 fps of simulated time; with the scenario's "
                         "first onboard camera and the detected markers' axes inset)")
    fl.add_argument("--no-mcap", action="store_true", help="skip run.mcap (the log for Foxglove and Lichtblick)")
    add_live_args(fl)
    fl.set_defaults(func=_cmd_fly)
    la = sub.add_parser(
        "launch",
        help="fly a scenario in fleet mode (vehicle processes, companion, MAVLink over sockets)",
        description="Fleet mode: n MAVLink vehicle processes, the companion daemon and the MuJoCo harness in lockstep.",
    )
    _run_args(la, "launch")
    la.add_argument("--speed", type=pace, default=1.0, metavar="F",
                    help="pace at F times real time; 0 = as fast as the lockstep allows (default 1)")
    la.add_argument("--no-companion", action="store_true",
                    help="do not start the companion daemon: UDP 14540+i is free for your own (MAVSDK, MAVProxy)")
    la.add_argument("--no-plots", action="store_true", help="skip the PNG plots")
    la.add_argument("--instance-offset", type=int, default=0, metavar="K",
                    help="link i takes PX4 SITL instance K+i's ports (simulator TCP 4560+K+i, onboard UDP 14540+K+i, "
                         "GCS from 18570+K+i; Zenoh base_port+K+g): a second fleet beside a first of n links "
                         "needs K >= n (default 0)")
    la.add_argument("--gcs-port", type=int, default=14550, metavar="P",
                    help="UDP port on 127.0.0.1 every vehicle sends its ground-station traffic to, where QGroundControl "
                         "or MAVProxy listens (default 14550, PX4's)")
    la.add_argument("--sim-link", choices=SIM_LINKS, default="tcp",
                    help="the vehicles' simulator links: tcp, PX4's simulator API on TCP 4560+K+i (default), or "
                         "unix, the same HIL messages as binary records over UNIX sockets (one host only; faster)")
    la.add_argument("--default-scheduling", action="store_true",
                    help="unpaced (--speed 0) too, keep Linux's default scheduling policy; without it an unpaced "
                         "fleet runs under SCHED_BATCH: no process preempts the one that woke it (faster lockstep)")
    la.add_argument("--companion-kernels", choices=COMPANION_KERNELS, default="compiled",
                    help="the companions run their compiled kernels (default, where numba is installed) or numpy, "
                         "the path an onboard computer without numba runs (SKELETON_JIT=0 for them alone)")
    add_live_args(la)
    la.set_defaults(func=_cmd_launch)
    mc = sub.add_parser(
        "mcap",
        help="write a run folder's log.npz as run.mcap (Foxglove, Lichtblick)",
        description="Convert a run folder's log.npz (batch or fleet) to an MCAP file of Foxglove-schema JSON messages.",
    )
    mc.add_argument("run_dir", metavar="RUN_DIR", type=Path, help="a run folder holding log.npz")
    mc.add_argument("--out", metavar="FILE", type=Path, help="the MCAP file (default: RUN_DIR/run.mcap)")
    mc.set_defaults(func=_cmd_mcap)
    add_view_parser(sub)
    add_campaign_parser(sub)
    add_fault_parser(sub)
    return parser


def main(argv=None) -> int:
    return run_subcommand(build_parser(), argv, usage_exit=EXIT_BAD_CONFIG)


if __name__ == "__main__":
    sys.exit(main())
