"""Helpers for tests that run services over a real zenoh bus on loopback (no multicast, free ports).

    from eonav.bus.testing import free_port, listener_session, wait_until

    port = free_port()
    with listener_session(port) as s:                # a peer listening on tcp/127.0.0.1:<port>
        sub = s.declare_subscriber(keys.health_all("demo"), zenoh.handlers.FifoChannel(64))
        proc = start_service(["-m", "services.camera_ingest", "--connect", f"tcp/127.0.0.1:{port}", ...])

A service started with ``--connect tcp/127.0.0.1:<port>`` reaches the test's session directly
(peer to peer, no router). That is enough for ONE service talking to the test. Peers do not forward
for each other, so when two services must talk to each other, use ``router_process()`` (the
embedded router in a subprocess) plus ``client_session(ep)`` for the test, as ``eonav run`` does.
"""
from __future__ import annotations

import argparse
import contextlib
import os
import signal
import subprocess
import sys
import time

from ..launcher import free_port, start_router, stop_processes  # noqa: F401  (re-exported)
from .session import build_config

__all__ = ["free_port", "endpoint", "listener_session", "client_session", "router_process",
           "start_service", "wait_until", "stop_service", "drain"]


def endpoint(port: int) -> str:
    return f"tcp/127.0.0.1:{port}"


def _open(mode: str, connect=None, listen=None):
    import zenoh
    args = argparse.Namespace(mode=mode, connect=connect, listen=listen, zenoh_config=None, multicast=False)
    return zenoh.open(build_config(args))


def listener_session(port: int):
    """A peer session listening on tcp/127.0.0.1:<port> (use as a context manager)."""
    return _open("peer", listen=endpoint(port))


def client_session(ep: str):
    """A client session connected to a router endpoint (use as a context manager)."""
    return _open("client", connect=ep)


@contextlib.contextmanager
def router_process(port: int | None = None):
    """The embedded router in a subprocess; yields its endpoint; stops it with SIGINT."""
    proc, ep = start_router(port or free_port())
    try:
        yield ep
    finally:
        stop_processes([proc], 5.0)


def start_service(argv: list[str], env: dict | None = None, **kw) -> subprocess.Popen:
    """``sys.executable *argv`` in its own process group, stderr captured (text)."""
    e = dict(os.environ)
    e.update(env or {})
    e.setdefault("PYTHONUNBUFFERED", "1")
    return subprocess.Popen([sys.executable, *argv], env=e, stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                            stdin=subprocess.DEVNULL, text=True, start_new_session=True, **kw)


def stop_service(proc: subprocess.Popen, sig=signal.SIGINT, timeout: float = 15.0) -> tuple[int, str]:
    """Send ``sig``, wait; returns (exit code, stderr). Kills (and fails loudly) on timeout."""
    if proc.poll() is None:
        proc.send_signal(sig)
    try:
        _, err = proc.communicate(timeout=timeout)
    except subprocess.TimeoutExpired:
        proc.kill()
        _, err = proc.communicate()
        raise AssertionError(f"process {proc.args} did not stop within {timeout} s after {sig!r}:\n{err}")
    return proc.returncode, err


def wait_until(cond, timeout: float = 10.0, period: float = 0.02, what: str = "condition"):
    """Poll ``cond()`` until it returns a truthy value (returned) or fail after ``timeout`` seconds."""
    deadline = time.monotonic() + timeout
    while True:
        v = cond()
        if v:
            return v
        if time.monotonic() > deadline:
            raise AssertionError(f"timed out after {timeout} s waiting for {what}")
        time.sleep(period)


def drain(sub, into: list | None = None) -> list:
    """Everything currently queued in a channel subscriber (non-blocking)."""
    out = [] if into is None else into
    while True:
        s = sub.try_recv()
        if s is None:
            return out
        out.append(s)
