"""zenoh configuration from the shared command-line flags (defined once, here), and session helpers.

Precedence, lowest first: zenoh's defaults; ``--zenoh-config FILE`` (``EONAV_ZENOH_CONFIG``, overrides only); the
flags ``--mode``, ``--connect``, ``--listen``, ``--multicast``, ``--shm``. Two decisions (docs/zenoh.md):

- multicast scouting is off unless ``--multicast``: every deployment names its endpoints, and a peer given
  ``--connect`` but no ``--listen`` (and no file) listens on ``tcp/127.0.0.1:0`` (the router-per-host pattern);
- shared memory is off unless ``--shm`` (with a config file and neither flag, the file decides): with it on, range
  maps were lost between same-host services;
- a lost connection is retried after 0.25 s, then every 0.5 s (``CONNECT_RETRY``, unless the file sets
  ``connect/retry``): with zenoh's own schedule (1 s, doubling to 4 s) a peer found a restarted router up to 3.5 s
  late. Clients and peers reconnect by themselves (docs/zenoh.md, "Router restarts").

``zenoh`` is imported inside the functions only.
"""
from __future__ import annotations

import argparse
import json
import os

from eonav import InputError

MODES = ("peer", "client", "router")
_TRUE = ("1", "true", "yes", "on")
CONNECT_RETRY = {"period_init_ms": 250, "period_max_ms": 500, "period_increase_factor": 2}


def env_default(var: str, default=None, old_env=()):
    """The value of environment variable ``var`` if set and non-empty, else of the first set one of ``old_env``
    (names a variable had before it was renamed), else ``default``."""
    for name in (var, *old_env):
        val = os.environ.get(name)
        if val is not None and val != "":
            return val
    return default


def env_flag(var: str, default: bool = False, old_env=()) -> bool:
    val = env_default(var, None, old_env)
    if val is None:
        return default
    return val.strip().lower() in _TRUE


def add_flag(p, *names, env: str, default=None, help: str = "", aliases=(), old_env=(), **kw):
    """``p.add_argument`` whose default comes from environment variable ``env`` (then ``default``).

    For ``action="store_true"`` the variable is read as a boolean (1/true/yes/on). argparse applies
    ``type`` to string defaults, so ``type=float`` works with an environment string too.
    ``aliases``: old spellings of the flag, still accepted (same destination) but not shown in ``--help``;
    ``old_env``: old names of the variable, read when ``env`` is not set. Both keep deployed env files and
    pipeline specs working after a rename."""
    aliases = (aliases,) if isinstance(aliases, str) else tuple(aliases)
    old_env = (old_env,) if isinstance(old_env, str) else tuple(old_env)
    if kw.get("action") == "store_true":
        dflt = env_flag(env, bool(default), old_env)
    else:
        dflt = env_default(env, default, old_env)
    suffix = f" (env {env}; default {dflt!r})"
    action = p.add_argument(*names, default=dflt, help=(help + suffix).strip(), **kw)
    action.env, action.old_env = env, old_env          # (for --help readers and tests)
    if aliases:
        kw = {k: v for k, v in kw.items() if k not in ("dest", "required")}
        p.add_argument(*aliases, dest=action.dest, default=argparse.SUPPRESS, help=argparse.SUPPRESS, **kw)
    return action


def consume_in_threads(session, subscriptions, *, name: str, on_error) -> tuple[list, list]:
    """For each ``(key, depth, fn)`` a FIFO subscriber and a thread calling ``fn(sample, t_monotonic_s)`` for every
    sample; whatever ``fn`` raises goes to ``on_error(sample, exc)`` and the thread keeps going. Returns
    ``(subscribers, threads)`` for ``close_subscribers``."""
    import threading
    import time

    import zenoh

    def run(sub, fn):
        try:
            for sample in sub:
                t = time.monotonic()
                try:
                    fn(sample, t)
                except Exception as e:  # noqa: BLE001  (a malformed message is that message's failure)
                    on_error(sample, e)
        except Exception:  # noqa: BLE001  (the channel closed at shutdown)
            pass

    subs, threads = [], []
    for key, depth, fn in subscriptions:
        sub = session.declare_subscriber(key, zenoh.handlers.FifoChannel(depth))
        t = threading.Thread(target=run, args=(sub, fn), name=f"{name}-{getattr(fn, '__name__', 'consume')}")
        subs.append(sub)
        threads.append(t)
        t.start()
    return subs, threads


def close_subscribers(subs, threads, session, join_timeout_s: float) -> None:
    """Shut down a session's consumer threads: undeclare every subscriber (which ends each thread's ``for sample
    in sub`` loop; an already-closed one is ignored), join the threads (at most ``join_timeout_s`` each), then close
    the session (None: nothing to close)."""
    for sub in subs:
        try:
            sub.undeclare()
        except Exception:
            pass
    for t in threads:
        t.join(join_timeout_s)
    if session is not None:
        session.close()


def split_endpoints(value) -> list[str]:
    """``"tcp/a:1,tcp/b:2"`` or a list of such strings -> ``["tcp/a:1", "tcp/b:2"]``."""
    if value is None:
        return []
    if isinstance(value, str):
        value = [value]
    out = []
    for v in value:
        out.extend(x.strip() for x in str(v).split(",") if x.strip())
    for e in out:
        if "/" not in e:
            raise InputError(f"zenoh endpoint {e!r}: expected <protocol>/<address>, e.g. tcp/127.0.0.1:7447")
    return out


def add_session_arguments(p: argparse.ArgumentParser, *, modes=("peer", "client"), default_mode=None) -> None:
    """The zenoh flags every eonav process shares."""
    g = p.add_argument_group("zenoh session")
    add_flag(g, "--connect", env="EONAV_CONNECT", default=None, metavar="ENDPOINTS",
             help="comma-separated zenoh endpoints to connect to, e.g. tcp/127.0.0.1:7447")
    add_flag(g, "--listen", env="EONAV_LISTEN", default=None, metavar="ENDPOINTS",
             help="comma-separated zenoh endpoints to listen on")
    add_flag(g, "--zenoh-config", env="EONAV_ZENOH_CONFIG", default=None, metavar="FILE",
             help="zenoh JSON5/YAML config file applied first; the flags override it")
    add_flag(g, "--mode", env="EONAV_ZENOH_MODE", default=default_mode, choices=modes,
             help="zenoh session mode (default: the config file's, else peer)")
    add_flag(g, "--multicast", env="EONAV_ZENOH_MULTICAST", default=False, action="store_true",
             help="enable multicast scouting (off by default: name endpoints instead)")
    shm = env_default("EONAV_ZENOH_SHM")
    g.add_argument("--shm", action=argparse.BooleanOptionalAction,
                   default=None if shm is None else shm.strip().lower() in _TRUE,
                   help="zenoh shared-memory transport for same-host payloads (default off, see "
                        "eonav.bus.session; with --zenoh-config the file decides) (env EONAV_ZENOH_SHM)")


def config_dict(args) -> dict:
    """The overrides the flags make, as a plain dict {json-path: value} (for logging and tests)."""
    zfile = getattr(args, "zenoh_config", None)
    mode = getattr(args, "mode", None) or (None if zfile else "peer")
    connect = split_endpoints(getattr(args, "connect", None))
    listen = split_endpoints(getattr(args, "listen", None))
    out: dict = {}
    if mode:
        out["mode"] = mode
    if connect:
        out["connect/endpoints"] = connect
    if listen:
        out["listen/endpoints"] = listen
    elif mode == "peer" and connect and not zfile:
        out["listen/endpoints"] = ["tcp/127.0.0.1:0"]
    out["scouting/multicast/enabled"] = bool(getattr(args, "multicast", False))
    shm = getattr(args, "shm", None)
    if shm is not None or not zfile:
        out["transport/shared_memory/enabled"] = bool(shm)
    return out


def build_config(args):
    """A ``zenoh.Config`` from the flags (see the module docstring for precedence)."""
    import zenoh

    zfile = getattr(args, "zenoh_config", None)
    if zfile:
        if not os.path.isfile(zfile):
            raise InputError(f"--zenoh-config {zfile!r}: no such file")
        try:
            cfg = zenoh.Config.from_file(zfile)
        except Exception as e:  # zenoh raises ZError with the parser's message
            raise InputError(f"--zenoh-config {zfile!r}: {e}") from None
    else:
        cfg = zenoh.Config()
    for path, value in config_dict(args).items():
        try:
            cfg.insert_json5(path, json.dumps(value))
        except Exception as e:
            raise InputError(f"zenoh config {path} = {value!r}: {e}") from None
    if json.loads(cfg.get_json("connect/retry")) is None:
        cfg.insert_json5("connect/retry", json.dumps(CONNECT_RETRY))
    return cfg


class RouterWatch:
    """Whether a session still reaches a zenoh router: ``check()`` gives None while it does (or before it ever did:
    a peer connected straight to another peer has no router to lose), else a detail such as ``"no zenoh router for
    1.2 s"``. It reads ``session.info.routers_zid()``, which empties as soon as the router's link closes and fills
    again when the session has reconnected. ``clock``: ``time.monotonic`` (tests inject one)."""

    def __init__(self, session, clock=None):
        import time
        self.session = session
        self._clock = clock or time.monotonic
        self.seen = False
        self.lost_since: float | None = None

    def routers(self) -> list[str]:
        try:
            return [str(z) for z in self.session.info.routers_zid()]
        except Exception:  # noqa: BLE001  (the session is closing)
            return []

    def check(self, now: float | None = None) -> str | None:
        t = self._clock() if now is None else now
        if self.routers():
            self.seen, self.lost_since = True, None
            return None
        if not self.seen:
            return None
        if self.lost_since is None:
            self.lost_since = t
        return f"no zenoh router for {t - self.lost_since:.1f} s"


def open_session(args):
    """``zenoh.open`` with the flags' config; use as a context manager."""
    import zenoh

    zenoh.init_log_from_env_or("error")
    return zenoh.open(build_config(args))


# -- sessions on loopback (tests, the demo, benchmarks) -------------------------------------------------

def endpoint(port: int) -> str:
    return f"tcp/127.0.0.1:{port}"


def _open(mode: str, connect=None, listen=None, zenoh_config=None):
    import zenoh
    args = argparse.Namespace(mode=mode, connect=connect, listen=listen, zenoh_config=zenoh_config, multicast=False)
    return zenoh.open(build_config(args))


def listener_session(port: int):
    """A peer session listening on tcp/127.0.0.1:<port> (use as a context manager)."""
    return _open("peer", listen=endpoint(port))


def client_session(ep: str, zenoh_config: str | None = None):
    """A client session connected to a router endpoint (use as a context manager); ``zenoh_config``: a session
    config file applied first (e.g. a user's credentials, ``eonav.bus.acl``)."""
    return _open("client", connect=ep, zenoh_config=zenoh_config)
