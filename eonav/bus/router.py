"""An embedded zenoh router: a Python zenoh session in ``mode: "router"`` that stays up until SIGINT/SIGTERM.

    python -m eonav.bus.router --listen tcp/127.0.0.1:7447

It is what ``eonav run`` starts for a newcomer on one machine, so no separate ``zenohd`` install is
needed. On a vehicle prefer ``zenohd`` under systemd (deploy/README.md); the configuration is the same
JSON5 (``--zenoh-config deploy/zenoh/router.json5``). A Python router enforces zenoh's access control
(docs/zenoh.md) but loads no plugins (no REST, no storages).

Once its listeners are bound it prints one line on stdout, ``EONAV_ROUTER READY <zid> <endpoint>...``,
and logs the same, so a parent process can wait for it. Multicast scouting is off unless ``--multicast``.
Exit code 0 after a clean stop, 2 on a configuration error (e.g. the port is taken).
"""
from __future__ import annotations

import argparse
import json
import logging
import os
import signal
import sys
import threading

from eonav import EonavError
from eonav.bus.session import add_flag, add_session_arguments, build_config, split_endpoints

log = logging.getLogger("eonav.router")
DEFAULT_LISTEN = "tcp/127.0.0.1:7447"
READY = "EONAV_ROUTER READY"


def add_arguments(p: argparse.ArgumentParser) -> None:
    add_session_arguments(p, modes=("router",), default_mode="router")
    add_flag(p, "--log-level", env="EONAV_LOG_LEVEL", default="info",
             choices=["debug", "info", "warning", "error"], help="logging level")


def router_args(args) -> argparse.Namespace:
    """Router defaults: mode router, listen on ``DEFAULT_LISTEN`` when neither a flag nor a file says."""
    a = argparse.Namespace(**vars(args))
    a.mode = "router"
    if not split_endpoints(a.listen) and not a.zenoh_config:
        a.listen = DEFAULT_LISTEN
    return a


def serve(args, stop: threading.Event, on_ready=None) -> int:
    """Run a router until ``stop`` is set. ``on_ready(zid, endpoints)`` is called once it listens."""
    import zenoh

    zenoh.init_log_from_env_or("error")
    try:
        cfg = build_config(router_args(args))
    except EonavError as e:
        log.error("configuration error: %s", e)
        return 2
    try:
        session = zenoh.open(cfg)
    except Exception as e:  # e.g. address already in use
        log.error("cannot open the router (%s): %s", split_endpoints(router_args(args).listen) or "config file", e)
        return 2
    with session:
        zid = str(session.zid())
        try:
            endpoints = json.loads(cfg.get_json("listen/endpoints"))
        except Exception:
            endpoints = split_endpoints(router_args(args).listen)
        if isinstance(endpoints, dict):  # per-mode form {router: [...], peer: [...]}
            endpoints = endpoints.get("router", [])
        endpoints = [str(e) for e in (endpoints or [])]
        log.info("router %s listening on %s", zid, ", ".join(endpoints) or "(config)")
        if on_ready:
            on_ready(zid, endpoints)
        parent = int(os.environ.get("EONAV_SUPERVISOR_PID", "0") or 0)
        while not stop.wait(0.25):
            if parent and os.getppid() != parent:
                log.warning("supervisor (pid %d) is gone; stopping", parent)
                break
        log.info("router stopping")
    return 0


def run(args) -> int:
    logging.basicConfig(level=getattr(logging, args.log_level.upper(), logging.INFO), stream=sys.stderr,
                        format="%(asctime)s router[%(process)d] %(levelname)s %(name)s: %(message)s")
    stop = threading.Event()

    def on_signal(signum, _frame):
        if stop.is_set():
            sys.exit(1)
        stop.set()

    signal.signal(signal.SIGINT, on_signal)
    signal.signal(signal.SIGTERM, on_signal)

    def ready(zid, endpoints):
        print(f"{READY} {zid} {' '.join(endpoints)}", flush=True)

    return serve(args, stop, ready)


def main(argv=None) -> int:
    p = argparse.ArgumentParser(prog="python -m eonav.bus.router", description=__doc__.splitlines()[0])
    add_arguments(p)
    return run(p.parse_args(argv))


if __name__ == "__main__":
    sys.exit(main())
