"""Autopilot links that are not up yet (eonav.nav.links): malformed strings are configuration errors, everything else
is retried with back-off. Real bytes: a TCP autopilot that starts late (and drops once), a serial link over a pty
whose device appears late, a silent UDP peer; then the MAVLink ingest as a real process over both, its health
degraded until the autopilot is heard."""
from __future__ import annotations

import contextlib
import os
import socket
import threading
import time
import tty

import pytest

from eonav import InputError
from eonav.nav.links import MavLink, parse_connection
from eonav.nav.mavlink_in import mavlink2_dialect


def free_tcp_port() -> int:
    s = socket.socket()
    s.bind(("127.0.0.1", 0))
    p = s.getsockname()[1]
    s.close()
    return p


def free_udp_port() -> int:
    s = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    s.bind(("127.0.0.1", 0))
    p = s.getsockname()[1]
    s.close()
    return p


class Autopilot:
    """An autopilot stand-in on a byte transport (``write(bytes)``, ``read() -> bytes``): HEARTBEAT at 5 Hz and
    ATTITUDE at 50 Hz on its boot clock, encoded by pymavlink; it parses what it receives (the companion's
    HEARTBEATs)."""

    def __init__(self, write, read):
        ap = mavlink2_dialect()
        self.mav = ap.MAVLink(None, srcSystem=1, srcComponent=1)
        self.parser = ap.MAVLink(None)
        self.write, self.read = write, read
        self.stop = threading.Event()
        self.received = []
        self.t0 = time.monotonic()
        self.thread = threading.Thread(target=self.run, daemon=True)

    def run(self):
        ap = mavlink2_dialect()
        next_hb = next_att = time.monotonic()
        while not self.stop.is_set():
            t = time.monotonic()
            try:
                if t >= next_hb:
                    self.write(self.mav.heartbeat_encode(ap.MAV_TYPE_QUADROTOR, ap.MAV_AUTOPILOT_ARDUPILOTMEGA,
                                                         0, 0, ap.MAV_STATE_ACTIVE).pack(self.mav))
                    next_hb = t + 0.2
                if t >= next_att:
                    boot_ms = int((t - self.t0) * 1000) + 1000
                    self.write(self.mav.attitude_encode(boot_ms, 0.01, 0.02, 0.5, 0, 0, 0).pack(self.mav))
                    next_att = t + 0.02
                data = self.read()
            except OSError:
                return
            if data:
                self.received += [m for m in (self.parser.parse_buffer(data) or []) if m.get_type() != "BAD_DATA"]
            time.sleep(0.005)

    def start(self):
        self.thread.start()
        return self

    def close(self):
        self.stop.set()
        self.thread.join(5)

    def companion_heartbeats(self):
        return [m for m in self.received if m.get_type() == "HEARTBEAT" and m.get_srcComponent() == 191]


class TcpAutopilot:
    """A TCP server (like SITL or mavlink-router) that accepts one client and runs an ``Autopilot`` on it."""

    def __init__(self, port: int):
        self.srv = socket.socket()
        self.srv.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        self.srv.bind(("127.0.0.1", port))
        self.srv.listen(1)
        self.srv.settimeout(10)
        self.ap = None
        self.client = None
        threading.Thread(target=self._accept, daemon=True).start()

    def _accept(self):
        try:
            self.client, _ = self.srv.accept()
        except OSError:
            return
        self.client.setblocking(False)

        def read():
            try:
                return self.client.recv(4096)
            except BlockingIOError:
                return b""
        self.ap = Autopilot(self.client.sendall, read).start()

    def companion_heartbeats(self):
        return self.ap.companion_heartbeats() if self.ap is not None else []

    def drop(self):
        """Close the client connection (autopilot reboot) and accept the next one."""
        self.ap.close()
        self.client.close()
        self.ap = self.client = None
        threading.Thread(target=self._accept, daemon=True).start()

    def close(self):
        if self.ap is not None:
            self.ap.close()
        for s in (self.client, self.srv):
            if s is not None:
                s.close()


def pump(link: MavLink, until, timeout: float, what: str):
    """Receive on ``link`` until ``until(link, msgs)`` is true; returns the messages."""
    msgs = []
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        m = link.recv(0.05)
        if m is not None:
            msgs.append(m)
        if until(link, msgs):
            return msgs
    raise AssertionError(f"timeout waiting for {what}: status {link.status()}")


# ---- connection strings -----------------------------------------------------------------------------------------

@pytest.mark.parametrize("s,expect", [
    ("tcp:127.0.0.1:5760", ("tcp", "127.0.0.1:5760", None)),
    ("udpin:0.0.0.0:14550", ("udpin", "0.0.0.0:14550", None)),
    ("udpout:10.0.0.1:14551", ("udpout", "10.0.0.1:14551", None)),
    ("localhost:14550", ("udpin", "localhost:14550", None)),
    ("/dev/ttyACM0", ("serial", "/dev/ttyACM0", None)),
    ("/dev/serial/by-id/usb-ArduPilot_fmuv3-if00,921600", ("serial", "/dev/serial/by-id/usb-ArduPilot_fmuv3-if00", 921600)),
    ("COM3,57600", ("serial", "COM3", 57600)),
])
def test_connection_strings_accepted(s, expect):
    assert parse_connection(s) == expect


@pytest.mark.parametrize("s", ["tcp:localhost", "tcp:host:port", "udpin:0.0.0.0:99999", "ttyACM0", "", "serial",
                               "tcp://127.0.0.1:5760", "/dev/ttyACM0,fast"])
def test_malformed_connection_strings_are_configuration_errors(s):
    with pytest.raises(InputError, match="--source .*(not a MAVLink connection string|port 99999)"):
        MavLink(s, what="--source")


@pytest.mark.parametrize("port,ok", [(0, False), (1, True), (65535, True), (65536, False)])
def test_port_must_be_1_to_65535(port, ok):
    """Port 0 is no port a peer can be reached on (a bind to it takes any free port, so the autopilot would never
    find the companion): like 65536, a configuration error; 1 and 65535 are the edges that are accepted."""
    for kind in ("tcp", "udpin", "udpout"):
        s = f"{kind}:127.0.0.1:{port}"
        if ok:
            assert parse_connection(s) == (kind, f"127.0.0.1:{port}", None)
        else:
            with pytest.raises(InputError, match=f"port {port} is not 1..65535"):
                parse_connection(s, "--source")


@pytest.mark.parametrize("s", ["/dev/ttyACM0,0", "COM3,0"])
def test_baud_rate_0_is_a_configuration_error(s):
    """Baud 0 is no speed (on POSIX, B0 means hang up the line): refused like a malformed string, while 1 is the
    smallest accepted."""
    with pytest.raises(InputError, match="baud rate must be positive"):
        parse_connection(s, "--source")
    assert parse_connection(s[:-1] + "1") == ("serial", s[:-2], 1)

# ---- back-off -----------------------------------------------------------------------------------------------------

def test_back_off_doubles_up_to_its_limit_and_says_down():
    t = {"now": 100.0}
    port = free_tcp_port()                                # nothing listens: refused at once
    counts = {}
    link = MavLink(f"tcp:127.0.0.1:{port}", clock=lambda: t["now"], backoff_s=(0.5, 4.0),
                   count=lambda k, n=1: counts.__setitem__(k, counts.get(k, 0) + n))
    tries = []
    while t["now"] < 120.0:
        before = counts.get("link.attempts", 0)
        assert link.poll() is None
        if counts.get("link.attempts", 0) > before:
            tries.append(t["now"])
        t["now"] = round(t["now"] + 0.25, 2)
    gaps = [round(b - a, 2) for a, b in zip(tries, tries[1:])]
    assert gaps[:5] == [0.5, 1.0, 2.0, 4.0, 4.0] and set(gaps[3:]) == {4.0}
    state, detail = link.status()
    assert state == "down" and "ConnectionRefusedError" in detail and "next attempt in" in detail


@contextlib.contextmanager
def tcp_link(now_s: float, listening: bool = True, backoff_s=(0.5, 8.0)):
    """A ``MavLink`` to a local TCP socket, listening (its backlog accepts the connection) or only bound (a connect
    is refused until ``srv.listen()``), on the test's clock ``t["now"]`` (exact instants) with its counters kept:
    yields (link, t, counts, srv); both closed after."""
    t = {"now": now_s}
    counts = {}
    srv = socket.socket()
    srv.bind(("127.0.0.1", 0))
    if listening:
        srv.listen(4)
    link = MavLink(f"tcp:127.0.0.1:{srv.getsockname()[1]}", clock=lambda: t["now"], backoff_s=backoff_s,
                   count=lambda k, n=1: counts.__setitem__(k, counts.get(k, 0) + n))
    try:
        yield link, t, counts, srv
    finally:
        link.close()
        srv.close()


def test_a_lost_link_is_reopened_after_the_first_back_off_step():
    """A link that was up and drops (autopilot reboot, cable) is re-opened after the first back-off step (0.5 s),
    not the longest (8 s): the obstacle messages must resume as soon as the autopilot is back. A real TCP server
    (its backlog accepts the connection); the clock is the test's, so the instants are exact."""
    with tcp_link(50.0) as (link, t, counts, srv):
        conn = link.poll()
        assert conn is not None and counts == {"link.attempts": 1, "link.opened": 1}
        t["now"] = 60.0
        link.mark_lost(conn, ConnectionResetError("connection reset by peer"))
        state, detail = link.status()
        assert state == "down" and "lost: ConnectionResetError" in detail and "next attempt in 0.5 s" in detail
        t["now"] = 60.49
        assert link.poll() is None and counts["link.attempts"] == 1            # not yet due
        t["now"] = 60.5
        assert link.poll() is not None and counts == {"link.attempts": 2, "link.opened": 2, "link.lost": 1}


def test_back_off_starts_again_from_its_first_step_after_the_link_was_up():
    """Three refusals (0.5, 1, 2 s apart), the link opens, later drops, and the autopilot refuses again: the next
    attempt is 0.5 s after that refusal (the failures before the link was up do not count), not 4 s."""
    with tcp_link(100.0, listening=False) as (link, t, counts, srv):
        for now in (100.0, 100.5, 101.5):
            t["now"] = now
            assert link.poll() is None
        assert counts == {"link.attempts": 3} and "next attempt in 2.0 s" in link.status()[1]
        srv.listen(4)
        t["now"] = 103.5
        conn = link.poll()
        assert conn is not None and counts["link.opened"] == 1
        t["now"] = 110.0
        link.mark_lost(conn, ConnectionResetError("connection reset by peer"))
        srv.close()                                                       # the autopilot is gone: refused again
        t["now"] = 110.5
        assert link.poll() is None and counts["link.attempts"] == 5
        state, detail = link.status()
        assert state == "down" and "ConnectionRefusedError" in detail and "next attempt in 0.5 s" in detail


def test_a_late_failure_report_of_the_old_connection_keeps_the_new_one():
    """The sending and the receiving thread can both see the same connection fail; the second report, arriving
    after the link was re-opened, is about the old connection and must not drop the new one."""
    with tcp_link(50.0) as (link, t, counts, srv):
        old = link.poll()
        link.mark_lost(old, ConnectionResetError("connection reset by peer"))
        t["now"] = 50.5
        new = link.poll()
        assert new is not None and new is not old
        link.mark_lost(old, BrokenPipeError("broken pipe"))             # the other thread, late
        assert link.conn is new and link.status()[0] == "silent" and counts["link.lost"] == 1
        assert link.poll() is new and counts["link.attempts"] == 2


class RecordingEvent(threading.Event):
    """A stop event that records how long ``recv`` asks to wait on it (and returns at once)."""

    def __init__(self):
        super().__init__()
        self.waits = []

    def wait(self, timeout=None):
        self.waits.append(timeout)
        return False


def test_recv_while_down_waits_at_most_its_timeout():
    """While the link is down ``recv`` waits for the next attempt, but never longer than its own timeout: the
    receiving thread must come back to check its stop event and report health (the back-off can be 8 s)."""
    stop = RecordingEvent()
    with tcp_link(100.0, listening=False, backoff_s=(4.0, 8.0)) as (link, t, _, _):
        assert link.recv(0.2, stop) is None                   # refused: the next attempt at 104.0
        t["now"] = 103.9
        assert link.recv(0.2, stop) is None                   # 0.1 s to the next attempt
        assert stop.waits == [0.2, pytest.approx(0.1, abs=1e-9)]


# ---- real links ---------------------------------------------------------------------------------------------------

def test_tcp_autopilot_that_starts_late_and_drops_once():
    port = free_tcp_port()
    link = MavLink(f"tcp:127.0.0.1:{port}", backoff_s=(0.1, 0.4), silent_s=0.5)
    ap = None
    try:
        pump(link, lambda lk, m: lk.status()[0] == "down", 2, "refused")
        time.sleep(0.5)                                                 # still refused a while
        assert link.status()[0] == "down" and link.conn is None
        ap = TcpAutopilot(port)                                         # the autopilot comes up
        msgs = pump(link, lambda lk, m: lk.status()[0] == "up" and len(m) >= 10, 5, "messages over TCP")
        assert {m.get_type() for m in msgs} >= {"HEARTBEAT", "ATTITUDE"}
        assert link.send(lambda c: c.mav.heartbeat_send(18, 8, 0, 0, 4))
        deadline = time.monotonic() + 3
        while not ap.ap.companion_heartbeats() and time.monotonic() < deadline:
            time.sleep(0.02)
        assert ap.ap.companion_heartbeats()                              # and hears us
        ap.drop()                                                        # connection reset: lost, re-opened
        pump(link, lambda lk, m: lk.status()[0] == "up" and ap.ap is not None and len(m) >= 5, 8, "re-connect")
    finally:
        link.close()
        if ap is not None:
            ap.close()


def test_serial_device_that_appears_late_over_a_pty(tmp_path):
    master, slave = os.openpty()
    tty.setraw(slave)                            # no echo / line discipline before pyserial configures the port
    dev = tmp_path / "ttyAP"                     # like /dev/serial/by-id/...: a link udev creates later
    link = MavLink(f"{dev},921600", backoff_s=(0.1, 0.4), silent_s=0.5)
    os.set_blocking(master, False)

    def read():
        try:
            return os.read(master, 4096)
        except BlockingIOError:
            return b""
    ap = Autopilot(lambda b: os.write(master, b), read)
    try:
        pump(link, lambda lk, m: lk.status()[0] == "down", 2, "absent device")
        assert "No such file" in link.status()[1] or "could not open" in link.status()[1]
        os.symlink(os.ttyname(slave), dev)
        ap.start()
        msgs = pump(link, lambda lk, m: lk.status()[0] == "up" and len(m) >= 10, 5, "messages over the pty")
        assert {m.get_type() for m in msgs} >= {"HEARTBEAT", "ATTITUDE"} and link.baud == 921600
        assert link.send(lambda c: c.mav.heartbeat_send(18, 8, 0, 0, 4))
        deadline = time.monotonic() + 3
        while not ap.companion_heartbeats() and time.monotonic() < deadline:
            time.sleep(0.02)
        assert ap.companion_heartbeats()
    finally:
        ap.close()
        link.close()
        os.close(master)
        os.close(slave)


def test_udp_peer_silent_then_heard():
    port = free_udp_port()
    link = MavLink(f"udpin:127.0.0.1:{port}", silent_s=0.3)
    tx = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    try:
        pump(link, lambda lk, m: lk.conn is not None, 2, "bound")
        time.sleep(0.4)
        link.recv(0.05)
        state, detail = link.status()
        assert state == "silent" and "no MAVLink for" in detail
        ap = Autopilot(lambda b: tx.sendto(b, ("127.0.0.1", port)), lambda: b"").start()
        try:
            pump(link, lambda lk, m: lk.status()[0] == "up", 3, "the peer")
        finally:
            ap.close()
        while link.recv(0.05) is not None:                               # what the peer sent before it stopped
            pass
        time.sleep(0.4)
        assert link.status()[0] == "silent"                              # and silent again once it stops
    finally:
        tx.close()
        link.close()


# ---- the MAVLink ingest service, real processes ------------------------------------------------------------------

def _service(source, vehicle, port):
    from eonav.app.processes import start_service
    from eonav.bus.session import endpoint
    return start_service(["-m", "eonav.services.mavlink_ingest", "--source", source, "--vehicle", vehicle,
                          "--connect", endpoint(port), "--health-period-s", "0.1", "--clock", "receive",
                          "--timesync-hz", "0"])


def _ingest_recovers(source, vehicle, bring_up):
    """Start the ingest on a link that is not up; check its health says degraded and nothing is published; bring
    the autopilot up; check nav states flow, the health says ok and the companion HEARTBEAT reaches the autopilot."""
    zenoh = pytest.importorskip("zenoh")
    from eonav.app.processes import drain, free_port, stop_service, wait_until
    from eonav.bus import keys as K
    from eonav.bus import schema
    from eonav.bus.session import listener_session
    port = free_port()
    health, nav = [], []
    with listener_session(port) as s:
        hsub = s.declare_subscriber(K.health(vehicle, "mavlink"), zenoh.handlers.FifoChannel(10000))
        nsub = s.declare_subscriber(K.nav_state(vehicle), zenoh.handlers.FifoChannel(10000))
        proc = _service(source, vehicle, port)
        ap = None
        try:
            def seen(pred):
                health.extend(schema.decode(m.payload.to_bytes()) for m in drain(hsub))
                return any(pred(h) for h in health)
            wait_until(lambda: seen(lambda h: h["state"] == "degraded" and "down" in h["detail"]), 20,
                       what="degraded health while the link is down")
            time.sleep(1.0)
            assert proc.poll() is None and not drain(nsub)                # still running, nothing published
            ap = bring_up()
            wait_until(lambda: seen(lambda h: h["state"] == "ok" and h["counters"].get("nav_published", 0) >= 10),
                       10, what="ok health and nav states once the autopilot is up")
            nav = [schema.decode(m.payload.to_bytes()) for m in drain(nsub)]
            wait_until(lambda: ap.companion_heartbeats(), 3, what="the companion HEARTBEAT at the autopilot")
        finally:
            code, err = stop_service(proc)
            if ap is not None:
                ap.close()
    assert code == 0, err
    assert len(nav) >= 10 and all(m["source"] == "ATTITUDE" for m in nav)
    last = health[-1]["counters"]
    assert last["link.attempts"] >= 2 and last["link.opened"] >= 1


def test_ingest_waits_for_a_late_tcp_autopilot():
    port = free_tcp_port()
    _ingest_recovers(f"tcp:127.0.0.1:{port}", "lk1", lambda: TcpAutopilot(port))


def test_ingest_waits_for_a_late_serial_device(tmp_path):
    master, slave = os.openpty()
    tty.setraw(slave)
    os.set_blocking(master, False)
    dev = tmp_path / "ttyACM0"

    def read():
        try:
            return os.read(master, 4096)
        except BlockingIOError:
            return b""
    ap = Autopilot(lambda b: os.write(master, b), read)

    def up():
        os.symlink(os.ttyname(slave), dev)
        return ap.start()
    try:
        _ingest_recovers(f"{dev},115200", "lk2", up)
    finally:
        ap.close()
        os.close(master)
        os.close(slave)


def test_ingest_malformed_connection_string_is_a_configuration_error():
    from eonav.app.processes import free_port
    proc = _service("tcp:localhost", "lk3", free_port())
    code = proc.wait(30)
    assert code == 2 and "not a MAVLink connection string" in proc.stderr.read()


# ---- OBSTACLE_DISTANCE out to an autopilot that starts late ---------------------------------------------------------

def test_obstacle_distance_sender_waits_for_a_late_tcp_autopilot():
    import numpy as np

    from eonav.nav.mavlink_out import ObstacleDistanceSender
    from eonav.obstacles.detect import N_SECTORS, Sectors
    port = free_tcp_port()
    tx = ObstacleDistanceSender(f"tcp:127.0.0.1:{port}", rate_hz=10.0)
    sectors = Sectors(np.full(N_SECTORS, 1234, np.int64), 5.0, 0.0, 50, 15000)
    ap = None
    try:
        t_end = time.monotonic() + 0.6
        while time.monotonic() < t_end:
            tx.update(sectors, time.time_ns() // 1000)
            time.sleep(min(tx.tick(), 0.05))
        state, detail = tx.link_status()
        assert state == "down" and "ConnectionRefusedError" in detail and tx.counters["od_sent_fresh"] == 0
        ap = TcpAutopilot(port)
        deadline = time.monotonic() + 8
        while time.monotonic() < deadline:
            tx.update(sectors, time.time_ns() // 1000)
            time.sleep(min(tx.tick(), 0.05))
            od = [m for m in (ap.ap.received if ap.ap else []) if m.get_type() == "OBSTACLE_DISTANCE"]
            if len(od) >= 3 and ap.companion_heartbeats() and tx.link_status()[0] == "up":
                break
        else:
            raise AssertionError(f"no OBSTACLE_DISTANCE after the autopilot came up: {tx.link_status()}")
        assert all(list(m.distances) == [1234] * N_SECTORS and m.get_srcComponent() == 191 for m in od)
    finally:
        tx.close()
        if ap is not None:
            ap.close()


def test_obstacles_service_degraded_until_its_tcp_autopilot_is_up():
    zenoh = pytest.importorskip("zenoh")
    from eonav.app.processes import drain, free_port, start_service, stop_service, wait_until
    from eonav.bus import keys as K
    from eonav.bus import schema
    from eonav.bus.session import endpoint, listener_session
    port, ap_port = free_port(), free_tcp_port()
    health = []
    with listener_session(port) as s:
        hsub = s.declare_subscriber(K.health("lk4", "obstacles"), zenoh.handlers.FifoChannel(10000))
        proc = start_service(["-m", "eonav.services.obstacles", "--vehicle", "lk4", "--connect", endpoint(port),
                              "--health-period-s", "0.1", "--mavlink-out", f"tcp:127.0.0.1:{ap_port}"])
        ap = None
        try:
            def seen(pred):
                health.extend(schema.decode(m.payload.to_bytes()) for m in drain(hsub))
                return any(pred(h) for h in health)
            wait_until(lambda: seen(lambda h: h["state"] == "degraded" and "down" in h["detail"]), 30,
                       what="degraded while the autopilot refuses")
            assert proc.poll() is None
            ap = TcpAutopilot(ap_port)
            wait_until(lambda: seen(lambda h: h["state"] == "ok"), 10, what="ok once the autopilot is heard")
            wait_until(lambda: ap.companion_heartbeats(), 5, what="the service's HEARTBEAT at the autopilot")
        finally:
            code, err = stop_service(proc)
            if ap is not None:
                ap.close()
    assert code == 0, err
