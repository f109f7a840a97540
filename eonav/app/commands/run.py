"""``eonav run``: the whole pipeline with an embedded router (``eonav.app.launcher``), or with no pipeline and no
source the newcomer's demo (``eonav.app.demo``: a recorded simulated flight through every service)."""
from __future__ import annotations

import argparse
import json
import logging
from pathlib import Path


def add_arguments(p: argparse.ArgumentParser) -> None:
    from eonav.bus.session import add_flag
    add_flag(p, "--pipeline", env="EONAV_PIPELINE", default=None, metavar="FILE",
             help="pipeline spec JSON (default: cameras from --camera, mavlink, sync, locator, obstacles)")
    add_flag(p, "--vehicle", env="EONAV_VEHICLE", default="demo", help="vehicle name for every service")
    add_flag(p, "--port", env="EONAV_ROUTER_PORT", default=None, type=int,
             help="embedded router port on 127.0.0.1 (default: a free one)")
    add_flag(p, "--router", env="EONAV_ROUTER", default=None, metavar="ENDPOINT",
             help="use this running router (e.g. tcp/127.0.0.1:7447) instead of starting one")
    add_flag(p, "--router-config", env="EONAV_ROUTER_CONFIG", default=None, metavar="FILE",
             help="zenoh JSON5 config for the embedded router")
    p.add_argument("--camera", action="append", default=[], metavar="[ID=]SOURCE",
                   help="default pipeline: add a camera ingest for SOURCE (repeatable)")
    add_flag(p, "--mavlink", env="EONAV_MAVLINK_SOURCE", default=None, metavar="SOURCE",
             help="default pipeline: MAVLink ingest --source (udpin:..., file.tlog)")
    add_flag(p, "--duration-s", env="EONAV_DURATION_S", default=None, type=float, metavar="S", help="stop after S seconds",
             aliases="--duration", old_env="EONAV_DURATION")
    add_flag(p, "--exit-when-done", env="EONAV_EXIT_WHEN_DONE", default=None, metavar="SERVICE",
             help="stop when SERVICE exits 0 (e.g. a replay reached its end)")
    add_flag(p, "--grace-s", env="EONAV_GRACE_S", default=5.0, type=float, metavar="S",
             help="seconds between SIGINT and SIGKILL when stopping", aliases="--grace", old_env="EONAV_GRACE")
    add_flag(p, "--log-dir", env="EONAV_LOG_DIR", default=None, metavar="DIR",
             help="one log file per service here (default: services log to this terminal)")
    add_flag(p, "--quiet", env="EONAV_QUIET", action="store_true", help="no status line")
    p.add_argument("--watch", action="store_true",
                   help="start nothing: show the status of the services already on the bus (use with --router)")
    p.add_argument("--print-spec", action="store_true", help="print the effective pipeline spec as JSON and exit")
    add_flag(p, "--record", env="EONAV_RECORD", default=None, metavar="FILE.mcap",
             help="also record everything on the bus into this MCAP file (eonav record; the demo too)")


def run(args) -> int:
    if not logging.getLogger().handlers:
        logging.basicConfig(level=logging.INFO, format="%(asctime)s %(levelname)s %(name)s: %(message)s")
    if not (args.watch or args.pipeline or args.camera or args.mavlink or args.print_spec):
        # no pipeline and no source: the newcomer's demo (a recorded simulated flight through the whole pipeline)
        from eonav.app.demo import run as run_demo
        return run_demo(args)
    from eonav.app.launcher import default_spec, log, run_pipeline
    if logging.getLogger().level > logging.INFO:
        log.setLevel(logging.INFO)
    spec = {"services": []} if args.watch else (args.pipeline or default_spec(args.camera, args.mavlink))
    if args.print_spec:
        doc = json.loads(Path(spec).read_text()) if isinstance(spec, str) else spec
        print(json.dumps(doc, indent=2))
        return 0
    return run_pipeline(spec, vehicle=args.vehicle, port=args.port, duration=args.duration_s,
                        exit_when_done=args.exit_when_done, router=args.router, grace_s=args.grace_s,
                        quiet=args.quiet, log_dir=args.log_dir, router_config=args.router_config,
                        record=args.record)
