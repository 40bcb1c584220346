"""The vision consumer's command line.

    python -m companion.vision --config FILE [--out DIR] [--duration S]

Reads camera frames from Zenoh (``<prefix>/camera/<vehicle>/image``: the SITL harness in fleet
mode, or a camera process on the onboard computer) or from a ``cv2.VideoCapture`` source (a camera
device, a video file or a stream URL), runs the marker pipeline on each (ArUco detection, PnP, the
pose's covariance) and writes ``vision_frames.jsonl`` (per frame: stamps, detections, detection and
PnP times, every marker pose with its covariance), ``vision_summary.json`` and ``vision.log`` into
its run folder. Stops on SIGTERM / Ctrl-C (after draining the frames in flight), after
``--duration`` seconds of wall time, at the end of a video, or after ``idle_timeout_s`` without
frames. Needs the ``vision`` extra (OpenCV) and, for Zenoh, the ``distributed`` extra.
Exit codes: 0 success, 2 bad input (the message names the file, key and reason), 3 the source
could not be opened.
"""

from __future__ import annotations

import argparse
import logging
import signal
import sys

from companion.cli import LOG_FORMAT, make_run_dir, setup_logging, single_thread_blas

EXIT_BAD_INPUT = 2
EXIT_SOURCE = 3

log = logging.getLogger("companion.vision")


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(
        prog="python -m companion.vision",
        description=("Camera frames (Zenoh <prefix>/camera/<vehicle>/image, or a cv2.VideoCapture device, file or "
                     "URL) through the marker pipeline (ArUco + PnP + covariance); writes vision_frames.jsonl, "
                     "vision_summary.json and vision.log to the run folder. Config: a TOML file with source = "
                     "\"zenoh\" ([zenoh] prefix, connect/listen; in a secured fleet fleet = its config and group = "
                     "whose credentials) or \"video\" ([video] device or url, camera, "
                     "vehicle, width_px, height_px, fx_px.. or fovy_deg, dist_coeffs) and [pipeline] (marker "
                     "sizes, dictionary, PnP method); see companion/vision/node_config.py."),
    )
    p.add_argument("--config", required=True, metavar="FILE", help="the consumer's config (TOML)")
    p.add_argument("--out", metavar="DIR", help="run folder (default: runs/vision-<name>-<UTC time>)")
    p.add_argument("--duration", type=float, metavar="S", help="stop after S seconds of wall time")
    p.add_argument("-v", "--verbose", action="store_true", help="debug logging")
    return p


def main(argv=None) -> int:
    args = build_parser().parse_args(argv)
    setup_logging(args.verbose)
    from companion.configfile import ConfigError

    from .node_config import load_vision_setup

    try:
        setup = load_vision_setup(args.config)
    except ConfigError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return EXIT_BAD_INPUT
    if args.duration is not None and not args.duration > 0:
        print("error: --duration must be positive", file=sys.stderr)
        return EXIT_BAD_INPUT
    out_dir = make_run_dir(f"vision-{setup.name}", args.out)
    handler = logging.FileHandler(out_dir / "vision.log")
    handler.setFormatter(logging.Formatter(LOG_FORMAT))
    logging.getLogger().addHandler(handler)
    stopping = []

    def on_signal(_signum, _frame):
        stopping.append(True)

    signal.signal(signal.SIGTERM, on_signal)
    signal.signal(signal.SIGINT, on_signal)
    from .node import open_source, run_node

    try:
        source = open_source(setup, args.config)
    except ConfigError as exc:  # the fleet's credential files changed since the config was read
        print(f"error: {exc}", file=sys.stderr)
        return EXIT_BAD_INPUT
    except ImportError as exc:
        print(f"error: {exc} (pip install '.[vision]'; the Zenoh source also needs '.[distributed]')", file=sys.stderr)
        return EXIT_SOURCE
    except Exception as exc:  # noqa: BLE001 - zenoh and OpenCV raise their own types
        print(f"error: cannot open the {setup.source} source: {exc}", file=sys.stderr)
        return EXIT_SOURCE
    log.info("run folder %s (vision_frames.jsonl, vision_summary.json)", out_dir)
    with single_thread_blas():
        run_node(setup, out_dir, stop=lambda: bool(stopping), duration_s=args.duration, source=source)
    return 0


if __name__ == "__main__":
    sys.exit(main())
