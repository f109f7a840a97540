"""Starting, stopping and waiting for service processes on this machine (the launcher, the demo, benchmarks, tests).

Services run as their own OS processes (``sys.executable -m ...``, spawned, never forked from a process holding a
zenoh session). A service started with ``--connect tcp/127.0.0.1:<port>`` reaches a ``listener_session(port)``
directly (peer to peer); when two services must talk to each other, start ``router_process()`` (the embedded
router in a subprocess) and connect everything to it, as ``eonav run`` does.
"""
from __future__ import annotations

import contextlib
import logging
import os
import signal
import socket
import subprocess
import sys
import threading
import time

from eonav import EonavError

log = logging.getLogger("eonav.app.processes")

__all__ = ["free_port", "stop_processes", "start_router", "router_process", "start_service", "stop_service",
           "wait_until", "drain"]


def free_port(host: str = "127.0.0.1") -> int:
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as s:
        s.bind((host, 0))
        return s.getsockname()[1]


def stop_processes(popens: list, grace_s: float) -> None:
    """SIGINT each, wait up to ``grace_s`` in total, then SIGKILL the rest."""
    for pp in popens:
        try:
            pp.send_signal(signal.SIGINT)
        except ProcessLookupError:
            pass
    deadline = time.monotonic() + grace_s
    for pp in popens:
        try:
            pp.wait(max(0.0, deadline - time.monotonic()))
        except subprocess.TimeoutExpired:
            log.warning("pid %d did not stop within %.1f s after SIGINT; killing", pp.pid, grace_s)
            pp.kill()
            pp.wait()


# ``python -P``: the working directory is not put first on a child's import path, so a folder there named like a
# package (a checkout called ``eonav`` beside which one runs ``eonav run``) cannot shadow the installed one; the
# children import what the parent does (PYTHONPATH still applies)
SAFE_PATH = ("-P",)


def start_router(port: int, *, host: str = "127.0.0.1", timeout_s: float = 15.0, log_level: str = "warning",
                 zenoh_config: str | None = None) -> tuple[subprocess.Popen, str]:
    """Start ``python -m eonav.bus.router`` and wait for its READY line. Returns (process, endpoint)."""
    endpoint = f"tcp/{host}:{port}"
    argv = [sys.executable, *SAFE_PATH, "-m", "eonav.bus.router", "--listen", endpoint, "--log-level", log_level]
    if zenoh_config:
        argv += ["--zenoh-config", zenoh_config]
    env = dict(os.environ, EONAV_SUPERVISOR_PID=str(os.getpid()))
    pp = subprocess.Popen(argv, stdout=subprocess.PIPE, stdin=subprocess.DEVNULL, text=True,
                          start_new_session=True, env=env)
    ready = threading.Event()

    def reader():
        for line in pp.stdout:
            if line.startswith("EONAV_ROUTER READY"):
                ready.set()
        # keep draining until EOF so the router never blocks on a full pipe

    threading.Thread(target=reader, name="router-stdout", daemon=True).start()
    deadline = time.monotonic() + timeout_s
    while not ready.wait(0.05):
        if pp.poll() is not None:
            raise EonavError(f"embedded router on {endpoint} exited with code {pp.returncode} "
                             "(port taken? see its log above)")
        if time.monotonic() > deadline:
            stop_processes([pp], 2.0)
            raise EonavError(f"embedded router on {endpoint} not ready after {timeout_s:.0f} s")
    return pp, endpoint


@contextlib.contextmanager
def router_process(port: int | None = None):
    """The embedded router in a subprocess; yields its endpoint; stops it with SIGINT."""
    proc, ep = start_router(port or free_port())
    try:
        yield ep
    finally:
        stop_processes([proc], 5.0)


def start_service(argv: list[str], env: dict | None = None, **kw) -> subprocess.Popen:
    """``sys.executable -P *argv`` (``SAFE_PATH``) in its own process group, stderr captured (text)."""
    e = dict(os.environ)
    e.update(env or {})
    e.setdefault("PYTHONUNBUFFERED", "1")
    return subprocess.Popen([sys.executable, *SAFE_PATH, *argv], env=e, stdout=subprocess.PIPE, stderr=subprocess.PIPE,
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
