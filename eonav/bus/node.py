"""The one node skeleton every eonav service uses.

A service module looks like this::

    from eonav.bus.node import Node, add_flag, service_main

    def add_arguments(p):                  # service-specific flags, each with an EONAV_... env default
        add_flag(p, "--camera-id", env="EONAV_CAMERA_ID", default="nose", help="...")

    def body(node: Node, args) -> None:    # declare pubs/subs, start workers; return
        pub = node.publisher(keys.frame(node.vehicle, args.camera_id), image=True)
        node.worker(loop, node, pub, args, name="capture")

    if __name__ == "__main__":
        service_main("camera", add_arguments, body)

``service_main`` runs the lifecycle (configure, open the session, declare the config queryable and health
publisher, call ``body``, declare the liveliness token, wait for a stop, shut down) and maps the outcome to the exit code: 0 clean
stop, 1 a worker or ``body`` raised, 2 a configuration error. Subscribers are channels (``RingChannel`` for images,
``FifoChannel`` for small must-not-lose streams) read by worker threads that are joined before the session closes:
nothing runs in a zenoh callback (docs/bus.md, docs/zenoh.md "Pitfalls").
"""
from __future__ import annotations

import argparse
import collections
import json
import logging
import os
import signal
import sys
import threading
import time
from typing import Callable

from eonav import EonavError
from eonav.bus import schema
from eonav.bus import keys as K
from eonav.bus.session import RouterWatch, add_flag, add_session_arguments, env_default, open_session

__all__ = ["Node", "service_main", "add_common_arguments", "add_flag", "env_default",
           "RateMeter", "LatencyWindow", "STATES", "EXIT_OK", "EXIT_ERROR", "EXIT_CONFIG", "DEFAULT_INPUT_GRACE_S",
           "restart_count"]

STATES = ("ok", "degraded", "error")
EXIT_OK, EXIT_ERROR, EXIT_CONFIG = 0, 1, 2
JOIN_TIMEOUT_S = 5.0
INPUT_CHECK_S = 0.1           # the health timer looks at the watched inputs this often
DEFAULT_INPUT_GRACE_S = 15.0  # budget of a watched input before its first sample (start-up, replay leads)


MAX_COUNTERS = 512            # distinct health counter names per service
COUNTER_LIMIT = 2 ** 53       # counter values are clamped here (exact in JSON and float64, fits msgpack int64)


def now_us() -> int:
    """The project time base: UNIX-epoch microseconds on this host's realtime clock."""
    return time.time_ns() // 1000


# --------------------------------------------------------------------------------------------------
# meters (pure, thread-safe, injectable clock for tests)

class RateMeter:
    """Events per second over a sliding window (default 5 s)."""

    def __init__(self, window_s: float = 5.0, clock: Callable[[], float] = time.monotonic):
        self.window_s, self._clock = window_s, clock
        self._t = collections.deque()
        self._first = None
        self._lock = threading.Lock()

    def tick(self, n: int = 1) -> None:
        t = self._clock()
        with self._lock:
            if self._first is None:
                self._first = t
            for _ in range(n):
                self._t.append(t)
            self._trim(t)

    def _trim(self, t):
        while self._t and self._t[0] < t - self.window_s:
            self._t.popleft()

    def rate_hz(self) -> float:
        t = self._clock()
        with self._lock:
            self._trim(t)
            if not self._t or self._first is None:
                return 0.0
            span = min(self.window_s, t - self._first)
            if span <= 0:
                return 0.0
            return len(self._t) / span


class LatencyWindow:
    """p50 / p99 / max of durations (seconds) seen in the last ``window_s`` seconds, reported in ms."""

    def __init__(self, window_s: float = 10.0, maxlen: int = 2000, clock: Callable[[], float] = time.monotonic):
        self.window_s, self._clock = window_s, clock
        self._v = collections.deque(maxlen=maxlen)
        self._lock = threading.Lock()

    def add(self, seconds: float) -> None:
        with self._lock:
            self._v.append((self._clock(), float(seconds)))

    def summary_ms(self) -> dict:
        t = self._clock()
        with self._lock:
            while self._v and self._v[0][0] < t - self.window_s:
                self._v.popleft()
            vals = sorted(s for _, s in self._v)
        if not vals:
            return {"n": 0}

        def q(p):
            return round(1e3 * vals[min(len(vals) - 1, int(p * (len(vals) - 1) + 0.5))], 3)
        return {"p50": q(0.50), "p99": q(0.99), "max": round(1e3 * vals[-1], 3), "n": len(vals)}


# --------------------------------------------------------------------------------------------------

class Subscription:
    """A channel subscriber. ``for sample in sub:`` ends when the node shuts down (the subscriber is
    undeclared). ``recv(timeout)`` returns None on timeout or after shutdown; use it in loops that
    must also wake up on their own (e.g. to check ``node.stop_event`` or a deadline)."""

    def __init__(self, node: "Node", key: str, zsub):
        self.node, self.key, self._sub = node, key, zsub
        self.closed = False

    def __iter__(self):
        try:
            for s in self._sub:
                yield s
        except Exception:  # ZError after undeclare: the channel is closed
            if not self._shutting_down():
                raise

    def _shutting_down(self) -> bool:
        """A channel error is expected (and means "no more samples") once the subscriber or node is closing."""
        return self.closed or self.node.stop_event.is_set()

    def try_recv(self):
        if self.closed:
            return None
        try:
            return self._sub.try_recv()
        except Exception:
            if self._shutting_down():
                return None
            raise

    def recv(self, timeout: float | None = None, poll_s: float = 0.002):
        """Next sample, or None after ``timeout`` seconds or on shutdown."""
        if timeout is None:
            try:
                return self._sub.recv()
            except Exception:
                if self._shutting_down():
                    return None
                raise
        deadline = time.monotonic() + timeout
        while True:
            s = self.try_recv()
            if s is not None or self.closed:
                return s
            if time.monotonic() >= deadline:
                return None
            time.sleep(poll_s)

    def undeclare(self):
        if not self.closed:
            self.closed = True
            try:
                self._sub.undeclare()
            except Exception:  # already undeclared / session closed
                pass


class Node:
    """What ``body(node, args)`` gets: the session, declarations with bookkeeping, metrics, health.

    Attributes: ``name`` (service name, one key chunk), ``vehicle``, ``session`` (``zenoh.Session``),
    ``log`` (``logging.Logger``), ``stop_event`` (``threading.Event``), ``args`` (parsed flags)."""

    def __init__(self, name: str, args, session, log: logging.Logger | None = None):
        self.name = K.check_chunk(name, "service name")
        self.vehicle = K.check_chunk(args.vehicle, "vehicle")
        self.args = args
        self.session = session
        self.log = log or logging.getLogger(f"eonav.service.{name}")
        self.stop_event = threading.Event()
        self.failed = False
        self.stop_reason = ""
        self._lock = threading.Lock()
        self._counters: dict[str, int] = {}
        self._rates: dict[str, RateMeter] = {}
        self._lat: dict[str, LatencyWindow] = {}
        self._state, self._detail = "ok", ""
        self._subs: list[Subscription] = []
        self._pubs: list = []
        self._workers: list[threading.Thread] = []
        self._queryables: list = []
        self._token = None
        self._health_pub = None
        self._last_log: dict[str, float] = {}
        self._suppressed: dict[str, int] = {}
        self._gc_t0 = None
        self._gc_cb = None
        self._inputs: dict[str, dict] = {}      # expect_input: name -> timeout_s, grace_s, since, seen, silent
        self._silent: list[str] = []            # details of the inputs silent at the last check
        self._router = None                     # RouterWatch of the session (declared with the health timer)
        self._router_lost: str | None = None    # its detail while the router is lost

    # ---- garbage collector ------------------------------------------------------------------------
    def watch_gc(self) -> None:
        """Time every collection of the interpreter's cyclic garbage collector into the latencies ``gc.gen<N>``
        (collections of generation 1 and 2 only: generation 0 is frequent and short). A collection stops every
        thread of the service, so its pauses belong in the latency figures (docs/bus.md)."""
        import gc

        def cb(phase, info):
            if info.get("generation", 0) < 1:
                return
            if phase == "start":
                self._gc_t0 = time.perf_counter()
            elif self._gc_t0 is not None:
                self.latency(f"gc.gen{info['generation']}", time.perf_counter() - self._gc_t0)
                self._gc_t0 = None
        self._gc_cb = cb
        gc.callbacks.append(cb)

    def unwatch_gc(self) -> None:
        import gc
        if self._gc_cb is not None and self._gc_cb in gc.callbacks:
            gc.callbacks.remove(self._gc_cb)
        self._gc_cb = None

    # ---- declarations ---------------------------------------------------------------------------
    def publisher(self, key: str, image: bool = False, *, priority=None, express: bool | None = None):
        """A publisher on ``key``. ``image=True``: CongestionControl.DROP, priority DATA, not express
        (a slow link drops frames instead of queueing them). Otherwise: reliable small messages,
        CongestionControl.BLOCK, priority DATA_HIGH, express. ``priority``/``express`` override."""
        import zenoh
        if image:
            kw = dict(congestion_control=zenoh.CongestionControl.DROP,
                      priority=priority or zenoh.Priority.DATA, express=bool(express))
        else:
            kw = dict(congestion_control=zenoh.CongestionControl.BLOCK,
                      priority=priority or zenoh.Priority.DATA_HIGH,
                      express=True if express is None else express)
        pub = self.session.declare_publisher(key, encoding=zenoh.Encoding("application/msgpack"), **kw)
        self._pubs.append(pub)
        self.log.debug("publisher %s (%s)", key, "image" if image else "reliable")
        return pub

    def subscribe(self, key: str, ring: int | None = None, fifo: int | None = None) -> Subscription:
        """A channel subscriber: ``ring=N`` keeps the newest N samples (images: latest frame wins),
        ``fifo=N`` queues up to N and then back-pressures (small streams that must not be lost).
        Iterate it in a worker: ``for sample in sub: ...``; the loop ends on shutdown."""
        import zenoh
        if (ring is None) == (fifo is None):
            raise EonavError(f"subscribe({key!r}): give exactly one of ring=N or fifo=N")
        n = ring if ring is not None else fifo
        if not isinstance(n, int) or n < 1:
            raise EonavError(f"subscribe({key!r}): channel size must be a positive integer, got {n!r}")
        handler = zenoh.handlers.RingChannel(n) if ring is not None else zenoh.handlers.FifoChannel(n)
        sub = Subscription(self, key, self.session.declare_subscriber(key, handler))
        self._subs.append(sub)
        self.log.debug("subscriber %s (%s %d)", key, "ring" if ring is not None else "fifo", n)
        return sub

    def worker(self, fn: Callable, *args, name: str | None = None) -> threading.Thread:
        """Run ``fn(*args)`` in a thread that is joined on shutdown. Loops should check
        ``node.stop_event`` (or iterate a subscription, which ends on shutdown). An exception sets
        the state to "error" and stops the node with exit code 1."""
        wname = name or getattr(fn, "__name__", "worker")

        def run():
            try:
                fn(*args)
            except Exception as e:
                self.fail(f"worker {wname} raised {type(e).__name__}: {e}", exc=True)

        t = threading.Thread(target=run, name=f"{self.name}.{wname}", daemon=False)
        self._workers.append(t)
        t.start()
        return t

    # ---- messages -------------------------------------------------------------------------------
    def wait_matching(self, publisher, timeout_s: float) -> bool:
        """Wait up to ``timeout_s`` until ``publisher`` has a matching subscriber (then 50 ms more, so the route is
        set up on every hop): a put right after a declaration can miss subscribers whose route is not there yet
        (docs/zenoh.md, the declaration race). Returns whether one matched (False also on shutdown)."""
        deadline = time.monotonic() + timeout_s
        while time.monotonic() < deadline and not self.stop_event.is_set():
            try:
                if publisher.matching_status.matching:
                    time.sleep(0.05)
                    return True
            except Exception:     # (a zenoh build without matching status: nothing to wait for)
                return False
            self.stop_event.wait(0.02)
        return False

    def put(self, publisher, kind: str, **fields) -> int:
        """``schema.encode(kind, **fields)`` and put; counts ``out.<kind>`` and its rate. Returns bytes sent."""
        payload = schema.encode(kind, **fields)
        publisher.put(payload)
        self.count(f"out.{kind}")
        self.tick(f"out.{kind}")
        return len(payload)

    def decode(self, sample, expect: str | None = None) -> dict | None:
        """Decode a sample's payload; never raises. Malformed payloads count ``decode_errors``
        (plus ``unknown_version`` for a schema version this build does not read), are logged at
        most once per 5 s per key, and give None. Good ones count ``in.<kind>`` and its rate."""
        key = str(getattr(sample, "key_expr", "?"))
        try:
            payload = sample.payload.to_bytes() if hasattr(sample, "payload") else sample
            msg = schema.decode(payload, expect=expect)
        except Exception as e:  # SchemaError, or anything odd from a hostile payload
            self.count("decode_errors")
            reason = getattr(e, "reason", "payload")
            self.count(f"rejected.{reason}")
            if reason == "version":
                self.count("unknown_version")
            self.log_limited(f"decode:{key}", logging.WARNING, "dropped payload on %s: %s", key, e)
            return None
        self.count(f"in.{msg['kind']}")
        self.tick(f"in.{msg['kind']}")
        return msg

    def log_limited(self, tag: str, level: int, fmt: str, *args, period_s: float = 5.0) -> None:
        """Log at most once per ``period_s`` per ``tag``; says how many were suppressed."""
        t = time.monotonic()
        with self._lock:
            last = self._last_log.get(tag)
            if last is not None and t - last < period_s:
                self._suppressed[tag] = self._suppressed.get(tag, 0) + 1
                return
            self._last_log[tag] = t
            n = self._suppressed.pop(tag, 0)
        if n:
            fmt += " (%d similar suppressed)"
            args = (*args, n)
        self.log.log(level, fmt, *args)

    # ---- inputs ---------------------------------------------------------------------------------
    def expect_input(self, name: str, timeout_s: float, grace_s: float | None = None, now: float | None = None):
        """Watch input ``name``: silent for longer than ``timeout_s`` after a sample (``input_seen``), or for longer
        than ``grace_s`` from now before its first one (default ``--input-grace-s``: start-up, a replay's lead), the
        node reports ``degraded`` with a detail naming the input, and ``ok`` again as soon as it flows. The health
        timer checks every ``INPUT_CHECK_S`` and publishes a health message at once on a change. ``now``: a
        ``time.monotonic()`` value (tests)."""
        if not (isinstance(timeout_s, (int, float)) and timeout_s > 0):
            raise EonavError(f"expect_input({name!r}): timeout must be > 0 s, got {timeout_s!r}")
        if grace_s is None:
            grace_s = float(getattr(self.args, "input_grace_s", DEFAULT_INPUT_GRACE_S))
        t = time.monotonic() if now is None else now
        with self._lock:
            self._inputs[name] = {"timeout_s": float(timeout_s), "grace_s": max(float(grace_s), float(timeout_s)),
                                  "since": t, "seen": None, "silent": False}

    def input_seen(self, name: str, now: float | None = None) -> None:
        """A usable sample of watched input ``name`` arrived (call it after the checks that could drop it, so an
        input of nothing but stale or bad messages stays silent)."""
        inp = self._inputs.get(name)
        if inp is not None:
            inp["seen"] = time.monotonic() if now is None else now

    def check_inputs(self, now: float | None = None) -> bool:
        """Re-evaluate the watched inputs; logs each input that falls silent or flows again. Returns whether any
        input changed between silent and flowing."""
        t = time.monotonic() if now is None else now
        changed, details = False, []
        with self._lock:
            items = list(self._inputs.items())
        for name, inp in items:
            seen = inp["seen"]
            quiet_s = t - (inp["since"] if seen is None else seen)
            budget = inp["grace_s"] if seen is None else inp["timeout_s"]
            silent = quiet_s > budget
            if silent:
                details.append(f"no {name} yet after {quiet_s:.1f} s" if seen is None
                               else f"no {name} for {quiet_s:.1f} s (budget {budget:.2f} s)")
            if silent != inp["silent"]:
                inp["silent"] = silent
                changed = True
                if silent:
                    self.log.warning("input %s silent: %s", name, details[-1])
                else:
                    self.log.info("input %s flowing again", name)
        with self._lock:
            self._silent = details
        return changed

    def silent_inputs(self) -> list[str]:
        """Details of the inputs found silent at the last ``check_inputs``."""
        with self._lock:
            return list(self._silent)

    def check_router(self, now: float | None = None) -> bool:
        """Re-evaluate the link to the zenoh router (``RouterWatch``: lost once it was there); logs the loss and the
        return. Returns whether it changed."""
        if self._router is None:
            return False
        lost = self._router.check(now)
        changed = (lost is None) != (self._router_lost is None)
        if changed:
            if lost:
                self.log.warning("zenoh router lost; reconnecting")
            else:
                self.log.info("zenoh router back")
        with self._lock:
            self._router_lost = lost
        return changed

    def _reported_state(self) -> tuple[str, str]:
        """The state and detail to report: the service's own, made ``degraded`` while a watched input is silent or
        the router is lost."""
        with self._lock:
            state, detail = self._state, self._detail
            silent = list(self._silent) + ([self._router_lost] if self._router_lost else [])
        if not silent or state == "error":
            return state, detail
        return "degraded", "; ".join(silent + ([detail] if detail else []))

    # ---- metrics --------------------------------------------------------------------------------
    def count(self, name: str, n: int = 1) -> None:
        """Add ``n`` to a health counter. Bounded: at most ``MAX_COUNTERS`` names (later new names all count as
        ``counters_overflow``) and values clamped to +-2^53, so no input can make the health message unsendable."""
        with self._lock:
            if name not in self._counters and len(self._counters) >= MAX_COUNTERS:
                name = "counters_overflow"
            v = self._counters.get(name, 0) + int(n)
            self._counters[name] = max(-COUNTER_LIMIT, min(COUNTER_LIMIT, v))

    def guarded(self, what: str, fn: Callable, *args):
        """``fn(*args)`` for one message; whatever it raises is counted (``message_errors``, ``rejected.<what>``),
        logged at a limited rate and swallowed (returns None): a payload never stops a service."""
        try:
            return fn(*args)
        except Exception as e:  # noqa: BLE001  (the point: one message's failure is that message's)
            self.count("message_errors")
            self.count(f"rejected.{what}")
            self.log_limited(f"guard:{what}", logging.WARNING, "%s failed on one message, dropped: %s: %s", what,
                             type(e).__name__, e)
            return None

    def tick(self, name: str, n: int = 1) -> None:
        with self._lock:
            m = self._rates.get(name)
            if m is None:
                m = self._rates[name] = RateMeter()
        m.tick(n)

    def latency(self, name: str, seconds: float) -> None:
        with self._lock:
            w = self._lat.get(name)
            if w is None:
                w = self._lat[name] = LatencyWindow()
        w.add(seconds)

    def set_state(self, state: str, detail: str = "") -> None:
        if state not in STATES:
            raise EonavError(f"set_state: state {state!r} not one of {STATES}")
        with self._lock:
            changed = (state, detail) != (self._state, self._detail)
            self._state, self._detail = state, detail
        if changed:
            self.log.log(logging.INFO if state == "ok" else logging.WARNING, "state %s%s",
                         state, f": {detail}" if detail else "")

    @property
    def state(self) -> str:
        """The reported state: the one set by ``set_state``/``fail``, ``degraded`` while a watched input is silent."""
        return self._reported_state()[0]

    def counters(self) -> dict:
        with self._lock:
            return dict(self._counters)

    def health_fields(self, recheck: bool = True) -> dict:
        """The fields of this node's health message now. ``recheck=False``: the watched inputs as the last
        ``check_inputs`` found them (the health timer's own check), so an input that fell silent is reported even
        when a sample arrives between that check and the message."""
        if self._inputs and recheck:
            self.check_inputs()
        state, detail = self._reported_state()
        with self._lock:
            counters = dict(self._counters)
            rates = dict(self._rates)
            lats = dict(self._lat)
        return {"service": self.name, "stamp_us": now_us(), "state": state, "detail": detail,
                "counters": counters, "pid": os.getpid(),
                "rates_hz": {k: round(m.rate_hz(), 3) for k, m in rates.items()},
                "latency_ms": {k: w.summary_ms() for k, w in lats.items()}}

    # ---- lifecycle ------------------------------------------------------------------------------
    def stop(self, reason: str = "") -> None:
        """Ask the node to shut down cleanly (exit code 0 unless something failed)."""
        if not self.stop_event.is_set():
            self.stop_reason = reason or "stop requested"
            self.log.info("stopping: %s", self.stop_reason)
        self.stop_event.set()

    def fail(self, detail: str, exc: bool = False) -> None:
        """Record a fatal error: state "error", log, stop; the process exits 1."""
        self.failed = True
        with self._lock:
            self._state, self._detail = "error", detail
        if exc:
            self.log.exception("%s", detail)
        else:
            self.log.error("%s", detail)
        self.stop(detail)

    def config_json(self) -> str:
        cfg = {k: v for k, v in vars(self.args).items() if not k.startswith("_") and not callable(v)}
        return json.dumps({"service": self.name, "vehicle": self.vehicle, "pid": os.getpid(), "args": cfg},
                          default=str, sort_keys=True)

    def declare_alive(self) -> None:
        """The liveliness token, declared once ``body`` has returned: alive = subscribed and running (the launcher
        starts a pipeline's replays only when their consumers are alive)."""
        self._token = self.session.liveliness().declare_token(K.alive(self.vehicle, self.name))

    def _declare_infrastructure(self) -> None:
        import zenoh
        self._router = RouterWatch(self.session)
        self._health_pub = self.session.declare_publisher(
            K.health(self.vehicle, self.name), encoding=zenoh.Encoding("application/msgpack"),
            congestion_control=zenoh.CongestionControl.DROP, priority=zenoh.Priority.DATA_LOW)
        ckey = K.config(self.vehicle, self.name)
        q = self.session.declare_queryable(ckey, zenoh.handlers.FifoChannel(16))
        self._queryables.append(q)

        def serve_config():
            try:
                for query in q:
                    try:
                        query.reply(ckey, self.config_json(), encoding=zenoh.Encoding.APPLICATION_JSON)
                    except Exception as e:
                        self.log_limited("config", logging.WARNING, "config query reply failed: %s", e)
            except Exception:
                if not self.stop_event.is_set():
                    raise

        def publish_health():
            # every --health-period-s, and at once when a watched input or the router is lost or back
            period = float(self.args.health_period_s)
            due = time.monotonic()
            while True:
                now = time.monotonic()
                changed = bool(self._inputs) and self.check_inputs(now)
                if self.check_router(now) or changed or now >= due:
                    self.publish_health(recheck=False)      # the state just evaluated: a change is never lost
                    due = now + period
                wait = min(INPUT_CHECK_S, period)
                if self.stop_event.wait(wait):
                    return

        self.worker(serve_config, name="config")
        self.worker(publish_health, name="health")

    def publish_health(self, recheck: bool = True) -> None:
        if self._health_pub is None:
            return
        try:
            self._health_pub.put(schema.encode("health", **self.health_fields(recheck)))
        except Exception as e:  # session closing, or a bug in a user metric name
            self.log_limited("health", logging.WARNING, "health publish failed: %s", e)

    def _shutdown(self) -> None:
        self.stop_event.set()
        for s in self._subs:
            s.undeclare()
        for q in self._queryables:
            try:
                q.undeclare()
            except Exception:
                pass
        me = threading.current_thread()
        deadline = time.monotonic() + JOIN_TIMEOUT_S        # one deadline for all: N stuck workers cost 5 s, not 5 N
        for t in self._workers:
            if t is me:
                continue
            t.join(max(0.0, deadline - time.monotonic()))
            if t.is_alive():
                self.log.error("worker %s did not stop within %.0f s (does its loop check stop_event?)",
                               t.name, JOIN_TIMEOUT_S)
                self.failed = True
        self.publish_health()  # last word: final counters (state "error" if it failed)
        for p in self._pubs + [self._health_pub]:
            if p is not None:
                try:
                    p.undeclare()
                except Exception:
                    pass
        if self._token is not None:
            try:
                self._token.undeclare()
            except Exception:
                pass


# --------------------------------------------------------------------------------------------------

def add_common_arguments(p: argparse.ArgumentParser, default_name: str) -> None:
    """Flags every service shares (defined once, here)."""
    g = p.add_argument_group("eonav service")
    add_flag(g, "--vehicle", env="EONAV_VEHICLE", default="demo", help="vehicle name (key prefix eonav/<vehicle>)")
    add_flag(g, "--name", env="EONAV_SERVICE_NAME", default=default_name,
             help="service instance name in health/alive/config keys (several instances need distinct names)")
    add_flag(g, "--health-period-s", env="EONAV_HEALTH_PERIOD_S", default=1.0, type=float, metavar="S",
             help="seconds between health messages", aliases="--health-period", old_env="EONAV_HEALTH_PERIOD")
    add_flag(g, "--input-grace-s", env="EONAV_INPUT_GRACE_S", default=DEFAULT_INPUT_GRACE_S, type=float,
             metavar="S", help="a watched input (Node.expect_input) with no sample yet is reported silent after "
                               "this long (start-up, a replay's lead)")
    add_flag(g, "--log-level", env="EONAV_LOG_LEVEL", default="info",
             choices=["debug", "info", "warning", "error"], help="logging level")
    add_session_arguments(p)


def build_parser(name: str, add_arguments: Callable | None, module: str | None = None) -> argparse.ArgumentParser:
    """The service's parser: its own flags, then the common ones. ``module``: the service's module name under
    eonav.services (what ``eonav service MODULE`` takes; default ``name``), for the usage line."""
    p = argparse.ArgumentParser(prog=f"eonav service {module or name}",
                                description=f"eonav {name} service")
    if add_arguments is not None:
        add_arguments(p)
    add_common_arguments(p, name)
    return p


def _setup_logging(level: str, name: str) -> None:
    root = logging.getLogger()
    for h in list(root.handlers):
        root.removeHandler(h)
    h = logging.StreamHandler(sys.stderr)
    h.setFormatter(logging.Formatter(f"%(asctime)s {name}[%(process)d] %(levelname)s %(name)s: %(message)s"))
    root.addHandler(h)
    root.setLevel(getattr(logging, level.upper(), logging.INFO))


def _supervisor_pid() -> int:
    """``EONAV_SUPERVISOR_PID``: set by ``eonav run`` for its children, which stop cleanly when their
    parent is gone (e.g. the launcher was SIGKILLed) instead of lingering as orphans."""
    try:
        return int(os.environ.get("EONAV_SUPERVISOR_PID", "0"))
    except ValueError:
        return 0


def restart_count() -> int:
    """``EONAV_RESTART_COUNT``: how often ``eonav run`` has restarted this service (0 at the first start, and when
    not run by it). A replay without a fixed time reference uses it to end rather than start over."""
    try:
        return max(0, int(os.environ.get("EONAV_RESTART_COUNT", "0") or 0))
    except ValueError:
        return 0


def run_node(name: str, args, body: Callable, freeze_gc: bool = False) -> int:
    """Open the session, run ``body``, wait for a stop, shut down. Returns the exit code.
    Installs SIGINT/SIGTERM handlers when called from the main thread. ``freeze_gc``: ``freeze_startup_objects``
    after ``body`` (a service process of its own; not in a test process that runs several nodes)."""
    log = logging.getLogger(f"eonav.service.{getattr(args, 'name', name)}")
    node_ref: list[Node] = []
    signals = {"n": 0}

    def on_signal(signum, _frame):
        signals["n"] += 1
        if signals["n"] > 1:
            log.error("second %s while stopping: forcing exit", signal.Signals(signum).name)
            logging.shutdown()
            os._exit(EXIT_ERROR)
        if node_ref:
            node_ref[0].stop(f"{signal.Signals(signum).name}")
        else:
            raise KeyboardInterrupt

    old = {}
    if threading.current_thread() is threading.main_thread():
        for sig in (signal.SIGINT, signal.SIGTERM):
            old[sig] = signal.signal(sig, on_signal)
    try:
        try:
            session_cm = open_session(args)
        except EonavError as e:
            log.error("configuration error: %s", e)
            return EXIT_CONFIG
        with session_cm as session:
            node = Node(args.name, args, session, log)
            node_ref.append(node)
            node.watch_gc()
            try:
                node._declare_infrastructure()
                body(node, args)
            except EonavError as e:
                node.fail(f"configuration error: {e}")
                node._shutdown()
                return EXIT_CONFIG
            except Exception as e:
                node.fail(f"body raised {type(e).__name__}: {e}", exc=True)
                node._shutdown()
                return EXIT_ERROR
            node.declare_alive()
            if freeze_gc:
                freeze_startup_objects()
            log.info("running (vehicle %s, pid %d)", node.vehicle, os.getpid())
            parent = _supervisor_pid()
            while not node.stop_event.wait(0.25):
                if parent and os.getppid() != parent:
                    node.stop(f"supervisor (pid {parent}) is gone")
            node._shutdown()
            code = EXIT_ERROR if node.failed else EXIT_OK
            log.info("stopped (%s), exit %d", node.stop_reason, code)
            return code
    except KeyboardInterrupt:
        log.info("interrupted before start")
        return EXIT_OK
    finally:
        if node_ref:
            node_ref[0].unwatch_gc()
        for sig, h in old.items():
            signal.signal(sig, h)


def freeze_startup_objects() -> None:
    """``gc.freeze()`` once ``body`` has declared everything and imported its modules: the objects made so far
    (modules, functions, classes) move to the permanent generation, so later full collections scan only what the
    service allocated since (docs/bus.md). Nothing is leaked: frozen objects are the ones a service keeps for its
    life anyway."""
    import gc
    gc.collect()
    gc.freeze()


def service_main(name: str, add_arguments: Callable | None, body: Callable, argv=None, *,
                 module: str | None = None) -> None:
    """Parse flags, run the node, ``sys.exit`` with its code. ``name``: the default instance name (``--name``);
    ``module``: see :func:`build_parser`. ``argv`` defaults to ``sys.argv[1:]``. A worker still running after the
    shutdown (stuck in a call that ignores ``stop_event``; ``Node._shutdown`` has logged it and set exit code 1)
    would keep the interpreter waiting for it forever: the process then exits without waiting."""
    code = main(name, add_arguments, body, argv, freeze_gc=True, module=module)
    stuck = [t.name for t in threading.enumerate() if t.is_alive() and not t.daemon and t is not threading.main_thread()]
    if stuck:
        logging.getLogger(f"eonav.service.{name}").error("exiting without waiting for threads still running: %s",
                                                         ", ".join(stuck))
        logging.shutdown()
        sys.stdout.flush()
        sys.stderr.flush()
        os._exit(code or EXIT_ERROR)
    sys.exit(code)


def main(name: str, add_arguments: Callable | None, body: Callable, argv=None, freeze_gc: bool = False,
         module: str | None = None) -> int:
    """Like :func:`service_main` but returns the exit code (for ``eonav service`` and tests)."""
    parser = build_parser(name, add_arguments, module)
    args = parser.parse_args(argv)
    _setup_logging(args.log_level, args.name)
    try:
        K.check_chunk(args.name, "--name")
        K.check_chunk(args.vehicle, "--vehicle")
    except EonavError as e:
        parser.error(str(e))
    return run_node(name, args, body, freeze_gc=freeze_gc)
