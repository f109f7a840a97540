"""``eonav run``: the whole pipeline with an embedded router (``eonav.app.launcher``), or with no pipeline and no
source the newcomer's demo (``eonav.app.demo``: a recorded simulated flight through every service)."""
from __future__ import annotations

import argparse
import json
import logging
from pathlib import Path


def add_arguments(p: argparse.ArgumentParser) -> None:
    from eonav.app.sources import DEFAULT_START_IN_S
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
    add_flag(p, "--cameras", env="EONAV_CAMERAS", default=None, metavar="FILE",
             help="default pipeline: the cameras file (intrinsics, lens, mount per camera id; e.g. "
                  "deploy/cameras.example.json) for the sync and every camera ingest")
    add_flag(p, "--replay-shift-us", env="EONAV_REPLAY_SHIFT_US", default="auto", type=_shift, metavar="D|auto",
             help="default pipeline: the shift every replay gets (recorded stamp + D); auto = when all sources are "
                  "recordings (image folder / video file with stamps + tlog), computed when the replays start")
    add_flag(p, "--replay-start-in-s", env="EONAV_REPLAY_START_IN_S", default=DEFAULT_START_IN_S, type=float,
             metavar="S",
             help="default pipeline: seconds from the replays' start (once the other services are alive) to the "
                  "recording's first record (--replay-shift-us auto)")
    add_flag(p, "--duration-s", env="EONAV_DURATION_S", default=None, type=float, metavar="S", help="stop after S seconds",
             aliases="--duration", old_env="EONAV_DURATION")
    add_flag(p, "--exit-when-done", env="EONAV_EXIT_WHEN_DONE", default=None, metavar="SERVICE",
             help="stop when SERVICE exits 0 (e.g. a replay reached its end)")
    add_flag(p, "--grace-s", env="EONAV_GRACE_S", default=5.0, type=float, metavar="S",
             help="seconds between SIGINT and SIGKILL when stopping", aliases="--grace", old_env="EONAV_GRACE")
    add_flag(p, "--log-dir", env="EONAV_LOG_DIR", default=None, metavar="DIR",
             help="one log file per service here (default: services log to this terminal)")
    add_flag(p, "--quiet", env="EONAV_QUIET", action="store_true", help="no status line")
    add_flag(p, "--acl", env="EONAV_ACL_DIR", default=None, metavar="DIR",
             help="access control (docs/zenoh.md): the router enforces the ACL and every service connects with its "
                  "own user; credentials written to DIR for this pipeline (kept passwords: the operator's "
                  "DIR/zenoh-operator.json5 works for other tools); with --router, read from DIR")
    p.add_argument("--secure", action="store_true",
                   help="access control with fresh credentials in a private temporary directory, removed at exit")
    p.add_argument("--watch", action="store_true",
                   help="start nothing: show the status of the services already on the bus (use with --router)")
    p.add_argument("--print-spec", action="store_true", help="print the effective pipeline spec as JSON and exit")
    add_flag(p, "--out", env="EONAV_DEMO_OUT", default=None, metavar="DIR",
             help="the demo (no pipeline, no source): where its run folder eonav-demo-<date>-<time> (picture, "
                  "summary, logs) goes; default the working directory")
    add_flag(p, "--record", env="EONAV_RECORD", default=None, metavar="FILE.mcap",
             help="also record everything on the bus into this MCAP file (eonav record; the demo too)")


def _shift(s):
    if str(s).lower() == "auto":
        return "auto"
    try:
        return int(s)
    except ValueError:
        raise ValueError(f"--replay-shift-us {s!r}: expected auto or an integer (microseconds)") from None


def default_pipeline(args) -> tuple[dict, dict]:
    """The default spec for ``--camera`` / ``--mavlink`` / ``--cameras`` and its substitutions: every camera id
    checked against the cameras file; recorded sources replayed in step (``{replay_shift_us}``, the one shift of
    every replay, computed when the replays start, i.e. once the other services are alive)."""
    from eonav import InputError
    from eonav.app.launcher import camera_sources, default_spec, log
    from eonav.app import sources as S
    from eonav.io.pairfile import load_camera_models
    if args.cameras is None:
        raise InputError("--cameras FILE is required with the default pipeline: the sync and each camera ingest need "
                         "every camera's intrinsics and mount (e.g. deploy/cameras.example.json; docs/pair-file.md)")
    models = load_camera_models(args.cameras, "--cameras")
    cams = camera_sources(args.camera)
    for cid, src in cams:
        if cid not in models:
            raise InputError(f"--camera {cid}={src}: no camera {cid!r} in --cameras {args.cameras} (has "
                             f"{', '.join(sorted(models))}); name each camera after its entry")
    shift, subs = args.replay_shift_us, {}
    if shift == "auto":
        starts = [S.camera_start(f"--camera {cid}={src}", src) for cid, src in cams]
        if args.mavlink:
            starts.append(S.mavlink_start(f"--mavlink {args.mavlink}", args.mavlink))
        shift = S.joint_replay_shift_us(starts, args.replay_start_in_s)      # None, or checks the recordings
        if shift is None and any(s.recorded for s in starts) and not all(s.recorded for s in starts):
            log.warning("recorded and live sources mixed (%s): each replay is mapped onto the current clock by "
                        "itself, not in step with the live ones",
                        ", ".join(f"{s.what}: {s.kind}" for s in starts))
        if shift is not None:
            def shift_now():
                d = S.joint_replay_shift_us(starts, args.replay_start_in_s)
                log.info("recorded sources replayed in step: --replay-shift-us %d (first record in %.1f s)", d,
                         args.replay_start_in_s)
                return d
            shift, subs = "{replay_shift_us}", {"replay_shift_us": shift_now}
    return default_spec(args.camera, args.mavlink, args.cameras, shift), subs


def run(args) -> int:
    import shutil
    import tempfile
    tmp = tempfile.mkdtemp(prefix="eonav-acl-") if args.secure and not args.acl else None
    args.acl_dir = tmp or args.acl
    try:
        return _run(args)
    finally:
        if tmp:
            shutil.rmtree(tmp, ignore_errors=True)


def _run(args) -> int:
    if not logging.getLogger().handlers:
        logging.basicConfig(level=logging.INFO, format="%(asctime)s %(levelname)s %(name)s: %(message)s")
    if not (args.watch or args.pipeline or args.camera or args.mavlink or args.cameras or args.print_spec):
        # no pipeline and no source: the newcomer's demo (a recorded simulated flight through the whole pipeline)
        from eonav.app.demo import run as run_demo
        return run_demo(args)
    from eonav.app.launcher import log, run_pipeline
    if logging.getLogger().level > logging.INFO:
        log.setLevel(logging.INFO)
    if args.pipeline and (args.camera or args.mavlink or args.cameras):
        from eonav import InputError
        raise InputError("--camera / --mavlink / --cameras build the default pipeline; a --pipeline file names its "
                         "own sources and cameras file")
    subs = {}
    if args.watch:
        spec = {"services": []}
    elif args.pipeline:
        spec = args.pipeline
    else:
        spec, subs = default_pipeline(args)
    if args.print_spec:
        doc = json.loads(Path(spec).read_text()) if isinstance(spec, str) else spec
        print(json.dumps(doc, indent=2))
        return 0
    return run_pipeline(spec, vehicle=args.vehicle, port=args.port, duration=args.duration_s,
                        exit_when_done=args.exit_when_done, router=args.router, grace_s=args.grace_s,
                        quiet=args.quiet, log_dir=args.log_dir, router_config=args.router_config,
                        record=args.record, acl_dir=args.acl_dir, substitutions=subs)
