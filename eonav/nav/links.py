"""Autopilot links that may not be up yet: a pymavlink connection opened, and re-opened, with exponential back-off.

At boot the serial device may not exist yet (USB enumeration, udev), the autopilot's or mavlink-router's TCP
server may refuse for a while, and a UDP peer may stay silent; later a link can drop. ``MavLink`` keeps trying
(0.5 s, 1 s, 2 s ... up to 8 s between attempts by default) and reports its state for the service's health:

- ``down``: not open (the last error and the time of the next attempt in the detail);
- ``silent``: open, but no MAVLink message in the last ``silent_s`` seconds (or none yet): a UDP peer that is not
  there, a serial line with nothing on it;
- ``up``: a message arrived within ``silent_s``.

``down`` and ``silent`` are ``degraded`` in the health, never a configuration error: only a malformed connection
string (``parse_connection``) or a missing pyserial is one. TCP connects with a timeout (pymavlink's own connect
has none, so an unreachable host would block a service's shutdown for minutes). The receiving thread calls
``recv`` (which opens the link when an attempt is due); any thread may call ``send``. No zenoh here.
"""
from __future__ import annotations

import logging
import re
import socket
import threading
import time
from typing import Callable

from eonav import InputError

log = logging.getLogger(__name__)

NET_KINDS = ("tcp", "tcpin", "udp", "udpin", "udpout", "udpbcast")
STATES = ("down", "silent", "up")
_FORMS = ("tcp:HOST:PORT, tcpin:HOST:PORT, udpin:HOST:PORT, udpout:HOST:PORT, udp:HOST:PORT, udpbcast:HOST:PORT, "
          "HOST:PORT (UDP in) or a serial device (/dev/ttyACM0, /dev/serial/by-id/..., COM3) with an optional ,BAUD")


def parse_connection(connection: str, what: str = "connection") -> tuple:
    """(kind, address, baud or None) of a pymavlink connection string; InputError naming ``what`` if malformed."""
    s = str(connection or "").strip()
    m = re.fullmatch(r"(?:(tcp|tcpin|udp|udpin|udpout|udpbcast):)?([^:,/\s]+):(\d+)", s)
    if m and (m.group(1) or not s.startswith("/")):
        port = int(m.group(3))
        if not 1 <= port <= 65535:
            raise InputError(f"{what} {s!r}: port {port} is not 1..65535")
        return (m.group(1) or "udpin"), f"{m.group(2)}:{port}", None
    m = re.fullmatch(r"(/[^,\s]+|COM\d+)(?:,(\d+))?", s)
    if m:
        baud = int(m.group(2)) if m.group(2) else None
        if baud is not None and baud <= 0:
            raise InputError(f"{what} {s!r}: baud rate must be positive")
        return "serial", m.group(1), baud
    raise InputError(f"{what} {s!r}: not a MAVLink connection string; expected {_FORMS}")


def _tcp_with_timeout(mavutil, address: str, timeout_s: float, **kw):
    """pymavlink's TCP client whose (re)connect gives up after ``timeout_s`` instead of the kernel's ~2 minutes."""
    class TcpLink(mavutil.mavtcp):
        def do_connect(self):
            self.port = socket.create_connection(self.destination_addr, timeout=timeout_s)
            self.port.setblocking(False)
            mavutil.set_close_on_exec(self.port.fileno())
            self.port.setsockopt(socket.SOL_TCP, socket.TCP_NODELAY, 1)
    return TcpLink(address, autoreconnect=True, **kw)


class MavLink:
    """One pymavlink connection that opens when it can (see the module docstring)."""

    def __init__(self, connection: str, *, what: str = "connection", baud: int = 57600, source_system: int = 1,
                 source_component: int = 191, dialect: str | None = None, silent_s: float = 3.0,
                 backoff_s: tuple = (0.5, 8.0), connect_timeout_s: float = 2.0,
                 clock: Callable[[], float] = time.monotonic, count: Callable | None = None):
        self.kind, self.address, baud_in_string = parse_connection(connection, what)
        if self.kind == "serial":
            try:
                import serial  # noqa: F401  (pymavlink opens serial ports with pyserial)
            except ImportError:
                raise InputError(f"{what} {connection!r}: serial links need pyserial (pip install pyserial)") from None
        self.connection, self.what = connection, what
        self.baud = baud_in_string or baud
        self.source_system, self.source_component, self.dialect = source_system, source_component, dialect
        self.silent_s, self.backoff_s, self.connect_timeout_s = silent_s, backoff_s, connect_timeout_s
        self._clock, self._count = clock, count or (lambda name, n=1: None)
        self._lock = threading.Lock()
        self._conn = None
        self._failures = 0
        self._next_try = clock()
        self._opened_at = None
        self._last_rx = None
        self._error = "not opened yet"

    # ---- opening ------------------------------------------------------------------------------------------------
    def _open(self):
        from eonav.nav.mavlink_in import mavutil_v2
        mu = mavutil_v2()
        if self.dialect:
            mu.set_dialect(self.dialect)
        ids = dict(source_system=self.source_system, source_component=self.source_component)
        if self.kind == "tcp":
            return _tcp_with_timeout(mu, self.address, self.connect_timeout_s, **ids)
        if self.kind == "serial":
            return mu.mavserial(self.address, baud=self.baud, autoreconnect=False, **ids)
        return mu.mavlink_connection(f"{self.kind}:{self.address}", **ids)

    def poll(self):
        """The open connection, opening it first if it is closed and an attempt is due; None while down."""
        with self._lock:
            if self._conn is not None:
                return self._conn
            now = self._clock()
            if now < self._next_try:
                return None
            self._count("link.attempts")
            try:
                conn = self._open()
            except OSError as e:                 # absent device, refused, unreachable, address in use, DNS
                self._failures += 1
                delay = min(self.backoff_s[1], self.backoff_s[0] * 2 ** (self._failures - 1))
                self._next_try = now + delay
                msg = f"{type(e).__name__}: {e}"
                if msg != self._error or self._failures == 1:
                    log.warning("%s %s not up (%s); retrying every <= %.1f s", self.what, self.connection, msg,
                                self.backoff_s[1])
                self._error = msg
                return None
            self._conn, self._failures, self._opened_at, self._last_rx = conn, 0, now, None
            self._error = ""
            self._count("link.opened")
            log.info("%s %s open", self.what, self.connection)
            return conn

    def mark_lost(self, conn, e: Exception) -> None:
        """``conn`` failed (``e``): close it and re-open after the first back-off step (no-op if already replaced)."""
        with self._lock:
            if self._conn is not conn:
                return
            self._conn = None
            self._error = f"lost: {type(e).__name__}: {e}"
            self._next_try = self._clock() + self.backoff_s[0]
            self._count("link.lost")
        log.warning("%s %s %s; re-opening", self.what, self.connection, self._error)
        try:
            conn.close()
        except Exception:       # a half-closed pymavlink object (port already None) must not mask the loss
            pass

    # ---- traffic -------------------------------------------------------------------------------------------------
    def recv(self, timeout_s: float = 0.2, stop: threading.Event | None = None):
        """The next message within ``timeout_s`` (None if none, or while the link is down: then it waits until the
        next attempt, at most ``timeout_s``)."""
        conn = self.poll()
        if conn is None:
            wait = max(0.0, min(timeout_s, self._next_try - self._clock()))
            if stop is not None:
                stop.wait(wait)
            else:
                time.sleep(wait)
            return None
        try:
            m = conn.recv_match(blocking=timeout_s > 0, timeout=timeout_s if timeout_s > 0 else None)
        except Exception as e:          # OSError / SerialException, or pymavlink tripping over a closed port
            self.mark_lost(conn, e)
            return None
        if getattr(conn, "portdead", False):
            self.mark_lost(conn, OSError("serial port dead"))
            return None
        if m is not None:
            self._last_rx = self._clock()
        return m

    def send(self, fn: Callable) -> bool:
        """``fn(conn)`` on the open connection (e.g. ``lambda c: c.mav.heartbeat_send(...)``); False while down or
        when it failed (the link is then re-opened)."""
        conn = self._conn
        if conn is None:
            return False
        try:
            fn(conn)
        except OSError as e:
            self.mark_lost(conn, e)
            return False
        if getattr(conn, "portdead", False):        # pymavlink's serial write swallows the error and sets this
            self.mark_lost(conn, OSError("serial port dead"))
            return False
        return True

    @property
    def conn(self):
        return self._conn

    def status(self) -> tuple:
        """(state, detail): see the module docstring."""
        now = self._clock()
        with self._lock:
            conn, last, opened, err, nxt = self._conn, self._last_rx, self._opened_at, self._error, self._next_try
        if conn is None:
            return "down", f"{self.what} {self.connection} down ({err}); next attempt in {max(0.0, nxt - now):.1f} s"
        if last is None or now - last > self.silent_s:
            quiet = now - (last if last is not None else opened)
            return "silent", f"{self.what} {self.connection} open, no MAVLink for {quiet:.1f} s"
        return "up", f"{self.what} {self.connection} up"

    def close(self) -> None:
        with self._lock:
            conn, self._conn = self._conn, None
        if conn is not None:
            try:
                conn.close()
            except Exception:
                pass
