"""``eonav run``: the whole pipeline on one machine, with an embedded zenoh router.

:func:`run_pipeline` (the function under the command) starts ``python -m eonav.bus.router`` on a loopback port, then
every service of a pipeline spec as its own OS process (``sys.executable -P -m eonav.services.<module>``: spawned, never
forked from a process holding a zenoh session), all connected to the router with the same ``--vehicle``. It
supervises them (exit 0 = finished, exit 2 = configuration error: neither restarted; anything else restarted with
back-off), the router too (:class:`EmbeddedRouter`: restarted on the same port with the same back-off; the services
reconnect by themselves), shows a status line from the health topic and stops everything cleanly on Ctrl-C or SIGTERM
(SIGINT to each service, then SIGKILL after a grace period; the router last). The spec format and the exit codes:
docs/bus.md, "Running".
"""
from __future__ import annotations

import argparse
import importlib.util
import json
import logging
import os
import signal
import socket
import subprocess
import sys
import threading
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable

from eonav import EonavError, InputError
from eonav.app.processes import SAFE_PATH, free_port, start_router, stop_processes

log = logging.getLogger("eonav.app.launcher")

BACKOFF_INITIAL_S = 0.5
BACKOFF_MAX_S = 10.0
STABLE_RESET_S = 30.0
DEFAULT_MAX_RESTARTS = 5
AFTER_TIMEOUT_S = 90.0           # a service with "after" starts anyway once its dependencies took this long
EXIT_CONFIG = 2
STATUS_DETAIL_CHARS = 40

# The default pipeline. Services whose modules do not exist yet are reported as missing.
DEFAULT_SERVICES = [
    {"name": "mavlink", "module": "mavlink_ingest"},
    {"name": "sync", "module": "sync"},
    {"name": "locator", "module": "locator"},
    {"name": "obstacles", "module": "obstacles"},
]


# --------------------------------------------------------------------------------------------------
# spec

@dataclass
class ServiceSpec:
    name: str
    module: str
    args: list = field(default_factory=list)
    env: dict = field(default_factory=dict)
    restart: bool = True
    max_restarts: int = DEFAULT_MAX_RESTARTS
    enabled: bool = True
    after: list = field(default_factory=list)


def _module_path(m: str) -> str:
    return m if "." in m else f"eonav.services.{m}"


def parse_spec(spec, spec_dir: str | None = None) -> list[ServiceSpec]:
    """Validate a pipeline spec (dict with "services", or a bare list) -> ServiceSpec list."""
    from eonav.bus.keys import check_chunk
    if isinstance(spec, (str, Path)):
        p = Path(spec)
        try:
            doc = json.loads(p.read_text())
        except FileNotFoundError:
            raise InputError(f"--pipeline {p}: no such file") from None
        except json.JSONDecodeError as e:
            raise InputError(f"--pipeline {p}: not valid JSON ({e})") from None
        return parse_spec(doc, spec_dir or str(p.resolve().parent))
    items = spec.get("services") if isinstance(spec, dict) else spec
    if not isinstance(items, list):
        raise InputError('pipeline spec: expected {"services": [ {...}, ... ]}')
    out, seen = [], set()
    for i, it in enumerate(items):
        if not isinstance(it, dict) or "name" not in it:
            raise InputError(f"pipeline spec services[{i}]: expected an object with at least a name")
        unknown = set(it) - {"name", "module", "args", "env", "restart", "max_restarts", "enabled", "after"}
        if unknown:
            raise InputError(f"pipeline spec services[{i}] ({it['name']}): unknown key(s) {sorted(unknown)}")
        name = check_chunk(str(it["name"]), f"pipeline spec services[{i}].name")
        if name in seen:
            raise InputError(f"pipeline spec: service name {name!r} used twice; give instances distinct names")
        if name == ROUTER_NAME:
            raise InputError(f"pipeline spec services[{i}]: the name {ROUTER_NAME!r} is the launcher's own (the zenoh "
                             "router's status entry); name the service otherwise")
        seen.add(name)
        args = it.get("args", [])
        if not isinstance(args, list) or not all(isinstance(a, (str, int, float)) for a in args):
            raise InputError(f"pipeline spec {name}.args: expected a list of strings")
        env = it.get("env", {})
        if not isinstance(env, dict):
            raise InputError(f"pipeline spec {name}.env: expected a map of strings")
        mr = it.get("max_restarts", DEFAULT_MAX_RESTARTS)
        if not isinstance(mr, int) or mr < 0:
            raise InputError(f"pipeline spec {name}.max_restarts: expected an integer >= 0")
        after = it.get("after", [])
        if not isinstance(after, list) or not all(isinstance(a, str) for a in after):
            raise InputError(f"pipeline spec {name}.after: expected a list of service names")
        out.append(ServiceSpec(name=name, module=_module_path(str(it.get("module", name))),
                               args=[str(a) for a in args], env={str(k): str(v) for k, v in env.items()},
                               restart=bool(it.get("restart", True)), max_restarts=mr,
                               enabled=bool(it.get("enabled", True)), after=list(after)))
    names = {s.name for s in out}
    for s in out:
        bad = [a for a in s.after if a not in names or a == s.name]
        if bad:
            raise InputError(f"pipeline spec {s.name}.after: {bad} not other services of the pipeline "
                             f"({', '.join(sorted(names))})")
    if spec_dir is not None:
        for s in out:
            s.env.setdefault("EONAV_SPEC_DIR", spec_dir)
    return out


def default_spec(cameras=(), mavlink: str | None = None, cameras_file: str | None = None,
                 replay_shift_us: int | None = None) -> dict:
    """The default pipeline: camera ingest per ``[ID=]SOURCE`` in ``cameras``, MAVLink ingest (with
    ``--source`` when given), sync, locator, obstacles. ``cameras_file`` goes to the sync and to every camera
    ingest (``--cameras``); ``replay_shift_us`` (a number or ``"{replay_shift_us}"``, substituted when the replays
    start) to every replay: camera ingests and MAVLink ingest then start after the other services are alive (and,
    restarted, resume where the clock says they are: docs/bus.md, "Staleness")."""
    replay = [] if replay_shift_us is None else ["--replay-shift-us", str(replay_shift_us)]
    cams = [] if cameras_file is None else ["--cameras", str(cameras_file)]
    services = []
    for cid, src in camera_sources(cameras):
        services.append({"name": f"camera_{cid}", "module": "camera_ingest",
                         "args": ["--source", src, "--camera-id", cid, *cams, *replay]})
    for s in DEFAULT_SERVICES:
        s = dict(s)
        if s["name"] == "mavlink" and mavlink:
            s["args"] = ["--source", mavlink, *replay]
        if s["name"] == "sync" and cams:
            s["args"] = list(cams)
        services.append(s)
    if replay:
        consumers = [s["name"] for s in services if "--replay-shift-us" not in s.get("args", [])]
        for s in services:
            if "--replay-shift-us" in s.get("args", []):
                s["after"] = consumers
    return {"services": services}


def camera_sources(cameras) -> list[tuple[str, str]]:
    """``[ID=]SOURCE`` strings -> (camera id, source); without an id the i-th camera is ``cam<i>``."""
    out = []
    for i, c in enumerate(cameras):
        cid, _, src = c.partition("=") if "=" in c and "://" not in c.split("=", 1)[0] else (f"cam{i}", "", c)
        out.append((cid, src))
    return out


def module_exists(module: str) -> bool:
    try:
        return importlib.util.find_spec(module) is not None
    except (ImportError, ValueError):
        return False


# --------------------------------------------------------------------------------------------------
# processes

@dataclass
class Proc:
    spec: ServiceSpec
    state: str = "pending"     # pending waiting missing running restarting done failed config_error stopped disabled
    popen: subprocess.Popen | None = None
    restarts: int = 0
    started_mono: float = 0.0
    next_start_mono: float = 0.0
    exit_code: int | None = None
    health: dict | None = None
    health_mono: float = 0.0
    alive: bool = False
    router: bool = False       # the zenoh router's entry (EmbeddedRouter, ExternalRouter), not a service

    @property
    def name(self):
        return self.spec.name

    def schedule_restart(self, now: float) -> float:
        """Count one more restart and set it due after the back-off (0.5 s doubling to 10 s); returns the delay."""
        delay = min(BACKOFF_MAX_S, BACKOFF_INITIAL_S * 2 ** self.restarts)
        self.restarts += 1
        self.state, self.next_start_mono = "restarting", now + delay
        return delay


SETTLED = ("done", "failed", "config_error", "missing", "disabled", "stopped")


def _subst(s: str, ctx: dict) -> str:
    """``{name}`` -> ``ctx[name]``; a callable value is called at its first use and its result kept."""
    for k, v in list(ctx.items()):
        key = "{" + k + "}"
        if key in s:
            if callable(v):
                v = ctx[k] = v()
            s = s.replace(key, str(v))
    return s


class Supervisor:
    """Starts, watches, restarts and stops the router and service processes."""

    def __init__(self, services: list[ServiceSpec], *, vehicle: str, router: str, ctx: dict,
                 grace_s: float = 5.0, log_dir: str | None = None, extra_env: dict | None = None,
                 zenoh_configs: dict | None = None):
        self.vehicle, self.router, self.ctx, self.grace_s = vehicle, router, ctx, grace_s
        self.zenoh_configs = zenoh_configs or {}      # service name -> session config (its credentials)
        self.procs = [Proc(s) for s in services]
        self.log_dir = log_dir
        self.extra_env = extra_env or {}
        self._lock = threading.Lock()

    def argv(self, sp: ServiceSpec) -> list[str]:
        zc = self.zenoh_configs.get(sp.name)
        return [sys.executable, *SAFE_PATH, "-m", sp.module, "--name", sp.name, "--vehicle", self.vehicle,
                "--connect", self.router, *(["--zenoh-config", str(zc)] if zc else []),
                *[_subst(a, self.ctx) for a in sp.args]]

    def check_modules(self) -> None:
        for p in self.procs:
            if not p.spec.enabled:
                p.state = "disabled"
            elif not module_exists(p.spec.module):
                p.state = "missing"
                log.warning("service %s: module %s not found; not started", p.name, p.spec.module)

    def start(self, p: Proc) -> None:
        env = dict(os.environ)
        env.update(self.extra_env)
        env.update({k: _subst(v, self.ctx) for k, v in p.spec.env.items()})
        env.setdefault("PYTHONUNBUFFERED", "1")
        env["EONAV_SUPERVISOR_PID"] = str(os.getpid())
        env["EONAV_RESTART_COUNT"] = str(p.restarts)       # a replay resumes, or ends, rather than start over
        stdout = stderr = None
        if self.log_dir:
            f = open(Path(self.log_dir) / f"{p.name}.log", "ab")
            stdout = stderr = f
        argv = self.argv(p.spec)
        log.debug("start %s: %s", p.name, " ".join(argv))
        try:
            # own process group: a terminal Ctrl-C reaches only the launcher, which forwards one SIGINT
            p.popen = subprocess.Popen(argv, env=env, stdout=stdout, stderr=stderr, stdin=subprocess.DEVNULL,
                                       start_new_session=True)
        except OSError as e:
            p.state, p.exit_code = "failed", None
            log.error("service %s: cannot start (%s)", p.name, e)
            return
        finally:
            if stdout is not None:
                stdout.close()
        p.state, p.started_mono, p.exit_code = "running", time.monotonic(), None
        p.health, p.alive = None, False
        log.info("service %s started (pid %d)", p.name, p.popen.pid)

    def start_all(self) -> None:
        """Start every pending service; one with ``after`` waits (state "waiting") for :meth:`start_waiting`."""
        for p in self.procs:
            if p.state == "pending":
                if p.spec.after:
                    p.state, p.next_start_mono = "waiting", time.monotonic() + AFTER_TIMEOUT_S
                else:
                    self.start(p)

    def start_waiting(self, now: float | None = None) -> None:
        """Start each waiting service whose ``after`` services are all alive (their liveliness token: subscribed and
        running) or ended, or that has waited :data:`AFTER_TIMEOUT_S`."""
        now = time.monotonic() if now is None else now
        by = {p.name: p for p in self.procs}
        for p in self.procs:
            if p.state != "waiting":
                continue
            deps = [by[a] for a in p.spec.after]
            late = [d.name for d in deps if not (d.alive or d.state in SETTLED)]
            if not late:
                self.start(p)
            elif now >= p.next_start_mono:
                log.warning("service %s: %s not alive after %.0f s; starting anyway", p.name, ", ".join(late),
                            AFTER_TIMEOUT_S)
                self.start(p)

    def poll(self, now: float | None = None) -> list[Proc]:
        """Reap exited processes and (re)start due ones; returns the processes that exited now."""
        now = time.monotonic() if now is None else now
        exited = []
        for p in self.procs:
            if p.state == "running" and p.popen is not None:
                rc = p.popen.poll()
                if rc is None:
                    if p.restarts and now - p.started_mono > STABLE_RESET_S:
                        p.restarts = 0
                    continue
                p.exit_code = rc
                p.alive = False
                exited.append(p)
                if rc == 0:
                    p.state = "done"
                    log.info("service %s finished (exit 0)", p.name)
                elif rc == EXIT_CONFIG:
                    p.state = "config_error"
                    log.error("service %s: configuration error (exit 2); not restarted", p.name)
                elif not p.spec.restart or p.restarts >= p.spec.max_restarts:
                    p.state = "failed"
                    log.error("service %s exited %s; %s", p.name, rc,
                              "restart disabled" if not p.spec.restart else f"gave up after {p.restarts} restarts")
                else:
                    delay = p.schedule_restart(now)
                    log.warning("service %s exited %s; restart %d/%d in %.1f s", p.name, rc, p.restarts,
                                p.spec.max_restarts, delay)
            elif p.state == "restarting" and now >= p.next_start_mono:
                self.start(p)
        return exited

    def active(self) -> bool:
        return any(p.state in ("running", "restarting", "pending", "waiting") for p in self.procs)

    def stop_all(self) -> None:
        running = [p for p in self.procs if p.popen is not None and p.popen.poll() is None]
        for p in self.procs:
            if p.state in ("restarting", "waiting"):
                p.state = "stopped"
        stop_processes([p.popen for p in running], self.grace_s)
        for p in running:
            p.exit_code = p.popen.returncode
            if p.state == "running":
                p.state = "stopped"


# --------------------------------------------------------------------------------------------------
# the router

ROUTER_NAME = "router"
ROUTER_START_TIMEOUT_S = 10.0


class EmbeddedRouter:
    """The embedded router as a supervised process: exited for any reason, it is restarted on the same port after the
    services' back-off (0.5 s, 1 s, 2 s ... 10 s; the count reset after 30 s of stable running), at most
    ``max_restarts`` times. ``proc`` (a :class:`Proc` named "router") carries its state and a health of its own for
    the status line and ``on_status``: ``ok`` while it runs, ``degraded`` with the outage while it is down. A start
    that fails (the port taken meanwhile) counts as an exit."""

    def __init__(self, port: int, zenoh_config: str | None = None, max_restarts: int = DEFAULT_MAX_RESTARTS):
        self.port, self.zenoh_config = port, zenoh_config
        self.proc = Proc(ServiceSpec(name=ROUTER_NAME, module="eonav.bus.router", max_restarts=max_restarts),
                         router=True)
        self.down_since: float | None = None

    @property
    def popen(self):
        return self.proc.popen

    def start(self) -> str:
        """Start it (raises EonavError if it does not come up); returns its endpoint."""
        p = self.proc
        p.popen, ep = start_router(self.port, zenoh_config=self.zenoh_config, timeout_s=ROUTER_START_TIMEOUT_S)
        p.state, p.started_mono, p.exit_code, p.alive = "running", time.monotonic(), None, True
        if self.down_since is not None:
            log.warning("embedded router back (pid %d) %.2f s after it went down", p.popen.pid,
                        time.monotonic() - self.down_since)
        self.down_since = None
        self._health("ok", "")
        return ep

    def stop(self, grace_s: float) -> None:
        """SIGINT, SIGKILL after ``grace_s`` (after the services: they stop through it)."""
        p = self.proc
        if p.popen is not None and p.popen.poll() is None:
            stop_processes([p.popen], grace_s)
            p.exit_code = p.popen.returncode
        if p.state in ("running", "restarting"):
            p.state = "stopped"

    def _health(self, state: str, detail: str) -> None:
        self.proc.health = {"service": ROUTER_NAME, "state": state, "detail": detail}
        self.proc.health_mono = time.monotonic()

    def poll(self, now: float | None = None) -> bool:
        """Reap and restart; returns whether its state changed (went down, came back or failed for good)."""
        now = time.monotonic() if now is None else now
        p = self.proc
        if p.state == "running":
            rc = p.popen.poll()
            if rc is None:
                if p.restarts and now - p.started_mono > STABLE_RESET_S:
                    p.restarts = 0
                self._health("ok", "")
                return False
            p.exit_code = rc
            self.down_since = now
            log.error("embedded router exited (%s)", rc)
            self._down(now)
            return True
        if p.state == "restarting":
            if now >= p.next_start_mono:
                try:
                    self.start()
                    return True
                except EonavError as e:
                    log.error("%s", e)
                    p.exit_code = None
                    self._down(time.monotonic())
                    return p.state == "failed"
            self._health("degraded", f"down {now - self.down_since:.1f} s; restart {p.restarts}/"
                                     f"{p.spec.max_restarts} in {max(0.0, p.next_start_mono - now):.1f} s")
        return False

    def _down(self, now: float) -> None:
        p = self.proc
        p.alive = False
        if p.restarts >= p.spec.max_restarts:
            p.state = "failed"
            self._health("error", f"router gave up after {p.restarts} restarts")
            log.error("embedded router: gave up after %d restarts", p.restarts)
            return
        delay = p.schedule_restart(now)
        self._health("degraded", f"down {now - self.down_since:.1f} s; restart {p.restarts}/"
                                 f"{p.spec.max_restarts} in {delay:.1f} s")
        log.warning("embedded router: restart %d/%d in %.1f s", p.restarts, p.spec.max_restarts, delay)


class ExternalRouter:
    """A router this launcher did not start (``--router EP``, e.g. zenohd under systemd): not supervised here, but
    reported, from the status monitor's own session (:class:`eonav.bus.session.RouterWatch`), ``degraded`` while
    the monitor reaches no router."""

    def __init__(self, endpoint: str):
        self.endpoint = endpoint
        self.proc = Proc(ServiceSpec(name=ROUTER_NAME, module="", restart=False), state="external", router=True)
        self.watch = None
        self._lost = False

    popen = None

    def attach(self, session) -> None:
        from eonav.bus.session import RouterWatch
        self.watch = RouterWatch(session)

    def poll(self, now: float | None = None) -> bool:
        if self.watch is None:
            return False
        lost = self.watch.check(now)
        p = self.proc
        p.alive = bool(self.watch.seen and not lost)
        p.health = {"service": ROUTER_NAME, "state": "degraded" if lost else ("ok" if p.alive else "degraded"),
                    "detail": lost or ("" if p.alive else f"not connected to {self.endpoint} yet")}
        p.health_mono = time.monotonic()
        changed = bool(lost) != self._lost
        if changed:
            (log.warning if lost else log.info)("router %s %s", self.endpoint, "lost" if lost else "back")
        self._lost = bool(lost)
        return changed


# --------------------------------------------------------------------------------------------------
# status

class HealthMonitor:
    """A client session on the router: latest health message and liveliness per service."""

    def __init__(self, vehicle: str, router: str, procs: list[Proc], zenoh_config: str | None = None):
        self.vehicle, self.router, self.zenoh_config = vehicle, router, zenoh_config
        self.procs = procs
        self.by_name = {p.name: p for p in procs}
        self._lock = threading.Lock()
        self.session = None
        self._subs = []
        self._threads = []

    def __enter__(self):
        import zenoh
        from eonav.bus import keys as K
        from eonav.bus.session import build_config
        args = argparse.Namespace(mode="client", connect=self.router, listen=None,
                                  zenoh_config=str(self.zenoh_config) if self.zenoh_config else None, multicast=False)
        self.session = zenoh.open(build_config(args))
        hs = self.session.declare_subscriber(K.health_all(self.vehicle), zenoh.handlers.FifoChannel(256))
        al = self.session.liveliness().declare_subscriber(K.alive_all(self.vehicle), zenoh.handlers.FifoChannel(256),
                                                          history=True)
        self._subs = [hs, al]
        self._threads = [threading.Thread(target=self._health, args=(hs,), name="health", daemon=False),
                         threading.Thread(target=self._alive, args=(al,), name="alive", daemon=False)]
        for t in self._threads:
            t.start()
        return self

    def _health(self, sub):
        from eonav.bus import schema
        try:
            for s in sub:
                try:
                    msg = schema.decode(s.payload.to_bytes(), expect="health")
                except schema.SchemaError as e:
                    log.debug("bad health payload on %s: %s", s.key_expr, e)
                    continue
                p = self._proc(msg["service"])
                p.health, p.health_mono = msg, time.monotonic()
        except Exception:
            pass

    def _alive(self, sub):
        import zenoh
        try:
            for s in sub:
                name = str(s.key_expr).rsplit("/", 1)[-1]
                self._proc(name).alive = s.kind == zenoh.SampleKind.PUT
        except Exception:
            pass

    def _proc(self, name: str) -> Proc:
        """The Proc of ``name``; a service that is not ours (another host, another launcher) is added
        with state "remote" so the status line shows it too."""
        with self._lock:
            p = self.by_name.get(name)
            if p is None:
                p = self.by_name[name] = Proc(ServiceSpec(name=name, module="", restart=False), state="remote")
                self.procs.append(p)
            return p

    def __exit__(self, *exc):
        from eonav.bus.session import close_subscribers
        close_subscribers(self._subs, self._threads, self.session, 5.0)


def _fmt_service(p: Proc, now: float) -> str:
    h = p.health
    if p.router and h is not None:
        state = h["state"] + (f"({h['detail'][:STATUS_DETAIL_CHARS]})" if h.get("detail") else "")
        return f"{p.name} {state}" + (f" r{p.restarts}" if p.restarts else "")
    if p.state == "remote":
        if h is None or not p.alive:
            return f"{p.name} remote {'alive' if p.alive else 'gone'}"
    elif p.state != "running" or h is None:
        extra = f"({p.exit_code})" if p.exit_code not in (None, 0) and p.state != "running" else ""
        r = f" r{p.restarts}" if p.restarts else ""
        return f"{p.name} {p.state if p.state != 'running' else 'starting'}{extra}{r}"
    state = h["state"] if now - p.health_mono < 5.0 else "stale"
    if state in ("degraded", "error") and h.get("detail"):
        state += f"({h['detail'].split(';')[0][:STATUS_DETAIL_CHARS]})"      # e.g. degraded(no frames for 1.2 s ...)
    parts = [p.name, state]
    rates = h.get("rates_hz") or {}
    if rates:
        k, v = max(rates.items(), key=lambda kv: kv[1])
        parts.append(f"{v:.1f}Hz")
    for k, v in (h.get("latency_ms") or {}).items():
        if isinstance(v, dict) and v.get("n"):
            parts.append(f"p50 {v['p50']:.1f}ms p99 {v['p99']:.1f}ms")
            break
    c = h.get("counters") or {}
    drops = sum(v for k, v in c.items() if isinstance(v, int)
                and any(w in k for w in ("drop", "corrupt", "decode_errors", "wrong_size", "error")))
    if drops:
        parts.append(f"drops {drops}")
    if p.restarts:
        parts.append(f"r{p.restarts}")
    return " ".join(parts)


def status_line(procs: list[Proc], vehicle: str, elapsed_s: float) -> str:
    now = time.monotonic()
    return f"[eonav {vehicle} {elapsed_s:5.0f}s] " + " | ".join(_fmt_service(p, now) for p in list(procs))


def status_dict(procs: list[Proc]) -> dict:
    return {p.name: {"state": p.state, "pid": p.popen.pid if p.popen else None, "restarts": p.restarts,
                     "exit_code": p.exit_code, "alive": p.alive, "health": p.health} for p in list(procs)}


class StatusPrinter:
    """One line on a terminal (rewritten in place), or a plain line every ``period_s`` otherwise."""

    def __init__(self, stream=None, period_s: float | None = None):
        self.stream = stream or sys.stderr
        self.tty = hasattr(self.stream, "isatty") and self.stream.isatty()
        self.period_s = period_s if period_s is not None else (1.0 if self.tty else 10.0)
        self._last = 0.0
        self._shown = False

    def __call__(self, line: str, force: bool = False) -> None:
        now = time.monotonic()
        if not force and now - self._last < self.period_s:
            return
        self._last = now
        if self.tty:
            try:
                width = os.get_terminal_size(self.stream.fileno()).columns
            except OSError:
                width = 160
            self.stream.write("\r\x1b[2K" + line[: max(20, width - 1)])
            self._shown = True
        else:
            self.stream.write(line + "\n")
        self.stream.flush()

    def end(self):
        if self.tty and self._shown:
            self.stream.write("\n")
            self.stream.flush()
            self._shown = False


# --------------------------------------------------------------------------------------------------
# the pipeline function

def secure_sessions(acl_dir, services: list[ServiceSpec], write: bool) -> tuple[dict, Path]:
    """Credentials of a pipeline under access control: (service name -> session config, the operator's config
    for the status monitor). ``write``: (re)write ``acl_dir`` for these services first (``eonav.bus.acl``)."""
    from eonav.bus import acl
    if write:
        acl.write_acl_dir(acl_dir, {s.name: s.module for s in services if s.enabled})
    configs = {s.name: acl.session_file(acl_dir, s.name) for s in services if s.enabled}
    monitor = acl.session_file(acl_dir, acl.OPERATOR_USER)
    missing = [str(p) for p in (*configs.values(), monitor) if not p.is_file()]
    if missing:
        raise InputError(f"access control: no credentials {', '.join(missing)} (eonav acl init {acl_dir} "
                         "--service NAME=MODULE ...)")
    return configs, monitor


def run_pipeline(spec, *, vehicle: str = "demo", port: int | None = None, duration: float | None = None,
                 on_status: Callable[[dict], None] | None = None, exit_when_done: str | None = None,
                 router: str | None = None, grace_s: float = 5.0, stop_event: threading.Event | None = None,
                 status_stream=None, quiet: bool = False, log_dir: str | None = None,
                 router_config: str | None = None, extra_env: dict | None = None, record: str | None = None,
                 acl_dir: str | None = None, substitutions: dict | None = None) -> int:
    """Run a pipeline until stopped; returns the exit code (see the module docstring).

    ``spec``: dict / list / JSON file path. ``port``: embedded router port (None = a free one).
    ``router``: connect to this existing router endpoint instead of starting one. ``duration``: stop
    after that many seconds. ``on_status(status_dict)``: called about once a second, and at once when the router
    goes down or comes back, with {service: {state, pid, restarts, exit_code, alive, health}}, the zenoh router under
    ``"router"`` (its health made here: ``degraded`` while it is down). ``stop_event``: set it to stop
    (SIGINT/SIGTERM also stop when called from the main thread). ``log_dir``: one log file per
    service instead of inheriting stderr. ``extra_env``: added to every service's environment. ``record``: also run
    the recorder (``eonav.recording.recorder``) writing this MCAP file. ``acl_dir``: run with access control
    (``eonav.bus.acl``): the embedded router enforces it and every service and the status monitor connect with
    their own credentials from ``acl_dir`` (written there for this pipeline, passwords already there kept; with
    ``router``, only read). ``substitutions``: more ``{name}`` values for args and env (a callable is called when
    a service first needs it)."""
    from eonav.bus.keys import check_chunk
    check_chunk(vehicle, "--vehicle")
    spec_dir = None
    if isinstance(spec, (str, Path)):
        spec_dir = str(Path(spec).resolve().parent)
    services = parse_spec(spec, spec_dir)
    if record:
        from eonav.recording.recorder import recorder_service
        rec = parse_spec([recorder_service(record)])
        for s in services:
            if s.after:                    # replays wait for the recorder too: it keeps their first records
                s.after.append(rec[0].name)
        services += rec
    if exit_when_done and exit_when_done not in {s.name for s in services}:
        raise InputError(f"--exit-when-done {exit_when_done!r}: no such service in the pipeline "
                         f"({', '.join(s.name for s in services)})")
    if log_dir:
        Path(log_dir).mkdir(parents=True, exist_ok=True)
    zenoh_configs, monitor_config = secure_sessions(acl_dir, services, write=router is None) if acl_dir \
        else ({}, None)
    if acl_dir and router is None:
        if router_config:
            raise InputError("--router-config and access control: the router config is written in the ACL "
                             "directory; give one of them")
        from eonav.bus.acl import ROUTER_FILE
        router_config = str(Path(acl_dir) / ROUTER_FILE)
    stop = stop_event or threading.Event()
    reason = {"why": ""}
    old = {}
    if threading.current_thread() is threading.main_thread():
        def on_signal(signum, _frame):
            if stop.is_set():
                return
            reason["why"] = signal.Signals(signum).name
            stop.set()
        for sig in (signal.SIGINT, signal.SIGTERM):
            old[sig] = signal.signal(sig, on_signal)

    rt = None
    printer = StatusPrinter(status_stream)
    t0 = time.monotonic()
    code = 0
    try:
        if router is None:
            tries = 1 if port else 3
            for attempt in range(tries):
                rt = EmbeddedRouter(port or free_port(), zenoh_config=router_config)
                try:
                    router = rt.start()
                    break
                except EonavError as e:
                    rt = None
                    if attempt == tries - 1:
                        log.error("%s", e)
                        return 2
            log.info("embedded router on %s (pid %d)", router, rt.popen.pid)
        else:
            rt = ExternalRouter(router)
        ctx = {"spec_dir": spec_dir or os.getcwd(), "vehicle": vehicle, "router": router,
               "port": router.rsplit(":", 1)[-1], **(substitutions or {})}
        sup = Supervisor(services, vehicle=vehicle, router=router, ctx=ctx, grace_s=grace_s, log_dir=log_dir,
                         extra_env=extra_env, zenoh_configs=zenoh_configs)
        sup.check_modules()
        missing = [p.name for p in sup.procs if p.state == "missing"]
        if missing:
            log.warning("not started (module not found): %s", ", ".join(missing))

        def report():
            if on_status:
                try:
                    on_status(status_dict([rt.proc, *sup.procs]))
                except Exception as e:  # a status consumer must not kill the pipeline
                    log.warning("on_status raised %s: %s", type(e).__name__, e)

        with HealthMonitor(vehicle, router, sup.procs, zenoh_config=monitor_config) as monitor:
            if isinstance(rt, ExternalRouter):
                rt.attach(monitor.session)
            sup.start_all()
            last_status = 0.0
            while not stop.wait(0.1):
                exited = sup.poll()
                sup.start_waiting()
                router_changed = rt.poll()
                if rt.proc.state == "failed":
                    reason["why"], code = "router failed", 1
                    break
                now = time.monotonic()
                if exit_when_done:
                    p = next(p for p in sup.procs if p.name == exit_when_done)
                    if p in exited and p.state == "done":
                        reason["why"] = f"{exit_when_done} done"
                        break
                    if p.state in ("failed", "config_error", "missing", "disabled"):
                        reason["why"], code = f"{exit_when_done} {p.state}", 1
                        break
                if duration is not None and now - t0 >= duration:
                    reason["why"] = f"duration {duration:g} s"
                    break
                if services and not sup.active():
                    if not any(p.popen is not None for p in sup.procs):
                        reason["why"], code = "no service could be started", 1
                    else:
                        reason["why"] = "no service left running"
                    break
                if router_changed or now - last_status >= 1.0:     # at once when the router went down or back
                    last_status = now
                    report()
                    if not quiet:
                        printer(status_line([rt.proc, *sup.procs], vehicle, now - t0), force=router_changed)
            if not quiet:
                printer(status_line([rt.proc, *sup.procs], vehicle, time.monotonic() - t0), force=True)
                printer.end()
            log.info("stopping (%s)", reason["why"] or "stop requested")
            sup.stop_all()
            if isinstance(rt, EmbeddedRouter):
                rt.stop(grace_s)
            report()
        bad = [p for p in sup.procs if p.state in ("failed", "config_error")]
        if bad:
            code = code or 1
        shown = [rt.proc, *sup.procs] if rt.proc.restarts or rt.proc.state == "failed" else sup.procs
        summary = ", ".join(f"{p.name}={p.state}" + (f"({p.exit_code})" if p.exit_code not in (None, 0) else "")
                            + (f" r{p.restarts}" if p.restarts else "") for p in shown)
        log.info("pipeline stopped: %s", summary)
        if not quiet:
            print(f"eonav run: {reason['why'] or 'stopped'}; {summary}", file=status_stream or sys.stderr)
        return code
    finally:
        if rt is not None and rt.popen is not None and rt.popen.poll() is None:
            stop_processes([rt.popen], grace_s)
        for sig, h in old.items():
            signal.signal(sig, h)
