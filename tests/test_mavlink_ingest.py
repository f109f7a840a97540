"""MAVLink ingest service: replay logic, then the real process over a real zenoh session on loopback
(tlog replay; live TIMESYNC against a simulated autopilot over UDP, pymavlink on both ends)."""
from __future__ import annotations

import socket
import threading
import time

import numpy as np
import pytest

from eonav import InputError

from eonav.bus import keys as K
from eonav.bus import schema
from eonav.geometry.frames import T_body_ned_from_quat
from eonav.nav.mavlink_in import mavutil_v2
from eonav.sim.record import DEFAULT_START_UNIX_US, nav_truth, write_tlog
from eonav.services import mavlink_ingest as MI

BOOT_OFFSET_US = DEFAULT_START_UNIX_US - 123_456_000


def _angle(q_a, q_b):
    R = T_body_ned_from_quat(q_a) @ T_body_ned_from_quat(q_b).T
    return float(np.arccos(np.clip((np.trace(R) - 1) / 2, -1, 1)))


@pytest.fixture(scope="module")
def tlog(tmp_path_factory):
    p = tmp_path_factory.mktemp("tlog") / "flight.tlog"
    counts = write_tlog(p, "turning", 2.0, start_unix_us=DEFAULT_START_UNIX_US, boot_offset_us=BOOT_OFFSET_US,
                        latency_us=(1000, 3000), seed=2)
    return p, counts


def test_replay_tlog_maps_headers_onto_now_and_paces(tlog):
    path, counts = tlog
    got = []
    stop = threading.Event()
    t0 = time.monotonic()
    reader = MI.replay_tlog(path, lambda m, rx: got.append((m, rx)), speed=4.0, stop=stop, clock=lambda: 5_000_000)
    elapsed = time.monotonic() - t0
    assert len(got) == sum(counts.values()) == reader.stats.records
    hdr = np.array([int(round(m._timestamp * 1e6)) for m, _ in got])
    rx = np.array([r for _, r in got])
    assert rx[0] == 5_000_000 and np.all(rx - hdr == rx[0] - hdr[0])     # one shift for the whole file
    span_s = (hdr[-1] - hdr[0]) / 1e6
    assert span_s / 4.0 - 0.05 < elapsed < span_s / 4.0 + 0.5            # paced at 4x real time


def test_replay_tlog_joint_shift_releases_each_record_at_its_shifted_stamp(tlog):
    path, counts = tlog
    now = {"us": 7_000_000}
    slept = []

    def sleep(s):
        slept.append(s)
        now["us"] += int(round(s * 1e6))

    got = []
    with open(path, "rb") as f:
        first_hdr = int.from_bytes(f.read(8), "big")
    shift = now["us"] + 500_000 - first_hdr             # first record due 0.5 s from now
    MI.replay_tlog(path, lambda m, rx: got.append((m, rx, now["us"])), speed=1.0, stop=threading.Event(),
                   clock=lambda: now["us"], sleep=sleep, shift_us=shift)
    assert len(got) == sum(counts.values())
    hdr = np.array([int(round(m._timestamp * 1e6)) for m, _, _ in got])
    rx = np.array([r for _, r, _ in got])
    released = np.array([t for _, _, t in got])
    assert np.all(np.abs(rx - hdr - shift) <= 1)          # stamped header + shift
    assert np.all(released >= rx - 1000)                   # never released more than 1 ms before its stamp
    assert slept[0] == pytest.approx(0.5, abs=1e-3)
    with pytest.raises(InputError, match="excludes --keep-stamps"):
        MI.replay_tlog(path, lambda m, rx: None, speed=2.0, stop=threading.Event(), shift_us=shift)


def test_clock_flag_and_origin_parsing():
    assert MI.parse_clock("auto", tlog=True) == ("receive",)
    assert MI.parse_clock("auto", tlog=False) == ("timesync", "system_time", "receive")
    with pytest.raises(Exception, match="--clock"):
        MI.parse_clock("gps", tlog=False)
    assert MI.parse_origin("47.1,8.2,400") == (47.1, 8.2, 400.0)
    with pytest.raises(Exception, match="--origin"):
        MI.parse_origin("47.1,8.2")



class _StandInIngest:
    """What ``Publisher`` reads of a NavIngest: ``clock()`` (set ``est``), ``rejected`` and ``decoder.reboots``."""

    def __init__(self):
        from collections import Counter
        from types import SimpleNamespace
        self.est = None
        self.rejected = Counter()
        self.decoder = SimpleNamespace(reboots=0)

    def clock(self):
        return self.est


def _publisher(ingest=None):
    """A Publisher on an in-process Node whose session records every put as (key, decoded message); ``ingest``:
    a real NavIngest (default: the stand-in)."""
    import argparse
    import logging
    from types import SimpleNamespace

    from eonav.bus.node import Node
    puts = []
    session = SimpleNamespace(declare_publisher=lambda key, **kw: SimpleNamespace(
        put=lambda payload: puts.append((str(key), schema.decode(bytes(payload))))))
    node = Node("mavlink", argparse.Namespace(vehicle="v", input_grace_s=10.0, health_period_s=1.0), session,
                log=logging.getLogger("test.mavlink_ingest"))
    ingest = _StandInIngest() if ingest is None else ingest
    return MI.Publisher(node, ingest), ingest, node, puts


def test_clock_offset_put_on_a_change_at_most_once_a_second_and_at_once_on_a_new_method():
    """clock_offset messages: the first estimate at once; a changed offset no sooner than 1 s after the last put
    (CLOCK_PUBLISH_PERIOD_US, inclusive); an unchanged estimate never again; a change of method at once."""
    from eonav.nav.mavlink_in import ClockEstimate
    pub, ingest, node, puts = _publisher()
    t0 = 1_700_000_000_000_000
    steps = [(0, "receive", 5_000, True), (500_000, "receive", 5_100, False), (999_999, "receive", 5_200, False),
             (1_000_000, "receive", 5_300, True), (2_500_000, "receive", 5_300, False),
             (2_600_000, "timesync", 5_250, True), (2_700_000, "timesync", 5_260, False)]
    for dt, method, offset, put in steps:
        ingest.est = ClockEstimate(offset_us=offset, method=method, samples=3, rtt_us=400)
        n = len(puts)
        pub.publish([], t0 + dt)
        assert len(puts) == n + put, (dt, method, offset)
    clock = [m for k, m in puts if k == K.nav_clock("v")]
    assert [(m["stamp_us"] - t0, m["offset_us"], m["method"]) for m in clock] == [
        (0, 5_000, "receive"), (1_000_000, 5_300, "receive"), (2_600_000, 5_250, "timesync")]
    assert node.counters()["out.clock_offset"] == 3


def test_rejection_counters_mirror_the_ingests_running_totals():
    """The ingest keeps running totals of its rejections and of autopilot reboots; the health counters show the
    same totals (each publish adds only what is new), not a sum of the totals seen at every publish."""
    pub, ingest, node, puts = _publisher()
    ingest.rejected.update({"attitude_nonfinite": 2})
    pub.publish([], 1)
    ingest.rejected.update({"attitude_nonfinite": 3, "time_backwards": 1})
    ingest.decoder.reboots = 1
    pub.publish([], 2)
    pub.publish([], 3)
    c = node.counters()
    assert (c["rejected.attitude_nonfinite"], c["rejected.time_backwards"], c["reboots"]) == (5, 1, 1)
    assert puts == []                                    # no states, no clock estimate: nothing put

def test_corrupt_and_unknown_packets_are_counted_and_never_decoded():
    """On a live link pymavlink hands over a packet whose CRC fails as BAD_DATA: it counts ``msg.BAD_DATA`` and
    ``bad_data`` (a noisy radio shows in the health there, as a tlog's corrupt records do) and never reaches the
    decoder (the stand-in ingest has no ``feed``); an id the dialect does not define counts ``msg.unknown`` and one
    ``unknown_msg_ids`` per distinct id. Real packets, parsed by pymavlink."""
    import struct
    from eonav.nav.mavlink_in import mavlink2_dialect
    ML = mavlink2_dialect()
    mav = ML.MAVLink(None, srcSystem=1, srcComponent=1)
    parser = ML.MAVLink(None)
    parser.robust_parsing = True
    corrupt = bytearray(ML.MAVLink_attitude_message(1000, 0.1, 0, 0, 0, 0, 0).pack(mav))
    corrupt[-1] ^= 0xFF                                              # its CRC fails
    unknown = [struct.pack("<BBBBBBB", 0xFD, 3, 0, 0, 0, 1, 1) + i.to_bytes(3, "little") + b"\x01\x07\x07\x00\x00"
               for i in (0x100000, 0x100001, 0x100000)]              # two distinct undefined ids, one twice
    msgs = [m for b in [bytes(corrupt), bytes(corrupt), *unknown] for m in parser.parse_buffer(b) or []]
    assert [m.get_type() for m in msgs] == ["BAD_DATA"] * 2 + ["UNKNOWN_1048576", "UNKNOWN_1048577",
                                                                 "UNKNOWN_1048576"]
    pub, ingest, node, puts = _publisher()
    for k, m in enumerate(msgs):
        pub.feed(m, 1_000 + k)
    assert node.counters() == {"msg.BAD_DATA": 2, "bad_data": 2, "msg.unknown": 3, "unknown_msg_ids": 2}
    assert puts == []


def _restarted_replay(path, skip_s: float):
    """A joint replay of ``path`` (re)started when its record ``skip_s`` after the first was due RESUME_LATE_US ago,
    through a Publisher and a real NavIngest (GLOBAL_POSITION_INT positions, origin: the first fix), on a fake
    clock. Returns the nav_state messages put, the messages fed (not passed over) and the node."""
    from types import SimpleNamespace
    args = SimpleNamespace(system_id=None, origin=None, position_source="GLOBAL_POSITION_INT", clock="auto",
                           clock_window_s=20.0, max_rtt_ms=10.0)
    pub, ingest, node, puts = _publisher(MI.make_ingest(args, tlog=True))
    now = {"us": 1_800_000_000_000_000}

    def sleep(s):
        now["us"] += int(round(s * 1e6))

    fed = []

    def feed(m, rx):
        fed.append(m)
        pub.feed(m, rx)

    with open(path, "rb") as f:
        first_hdr = int.from_bytes(f.read(8), "big")
    shift = now["us"] - MI.RESUME_LATE_US - first_hdr - int(skip_s * 1e6)
    MI.replay_tlog(path, feed, speed=1.0, stop=threading.Event(), clock=lambda: now["us"], sleep=sleep,
                   shift_us=shift, skip=pub.fast_forward)
    with pub.lock:
        rest = ingest.flush()
    pub.publish(rest, now["us"])                       # the end of the log, as _run_tlog does
    return [m for k, m in puts if k == K.nav_state("v")], fed, node


def test_replay_restarted_midway_publishes_only_the_records_it_feeds(tlog):
    """A joint replay restarted 1 s into the log (before its receive clock has the 2 s it needs to lock) passes the
    first second over: one nav_state per navigation record it feeds, none for the records it passed over, which
    went through the decoder and the clock estimator only (docs/bus.md: "unpublished"). They used to wait in the
    ingest's queue for the clock lock and come out with it, stamped more than RESUME_LATE_US in the past."""
    path, counts = tlog
    nav, fed, node = _restarted_replay(path, 1.0)
    assert node.counters()["replay_skipped"] > 100
    fed_nav = sorted((m.get_type(), m.time_boot_ms * 1000) for m in fed
                     if m.get_type() in ("ATTITUDE", "ATTITUDE_QUATERNION", "GLOBAL_POSITION_INT"))
    assert len(fed_nav) > 100
    assert sorted((m["source"], m["autopilot_time_us"]) for m in nav) == fed_nav


def test_replay_restarted_midway_keeps_the_logs_first_fix_as_origin(tlog):
    """A joint replay restarted 1 s into the log still shows the decoder the second it passed over
    (``fast_forward``): GLOBAL_POSITION_INT positions stay about the log's first fix, so a restart does not move
    the NED origin under the vehicle. Truth: the flight's NED position minus the one at t = 0 (the first fix). The
    tolerance is the message's quantisation, 1e-7 deg (1.1 cm) on the sample and on the origin, 1 mm in alt."""
    path, counts = tlog
    nav, fed, node = _restarted_replay(path, 1.0)
    pos = [m for m in nav if m["source"] == "GLOBAL_POSITION_INT"]
    assert len(pos) >= 20
    t_s = np.array([(m["autopilot_time_us"] + BOOT_OFFSET_US - DEFAULT_START_UNIX_US) / 1e6 for m in pos])
    tr = nav_truth("turning", np.concatenate([[0.0], t_s]))["position_ned_m"]
    np.testing.assert_allclose(np.array([m["position_ned_m"] for m in pos]), tr[1:] - tr[0], atol=0.025)


def test_live_link_health_is_degraded_while_down_or_silent_and_ok_once_heard(monkeypatch):
    """The receive loop of a live link turns the link's state into the health: ``down`` (not open) and ``silent``
    (open, no MAVLink for 3 s: a UDP peer that is not there, a radio out of range) are ``degraded`` with the link's
    own detail, ``up`` is ``ok``; each change as it happens. A scripted link, no sockets."""
    from types import SimpleNamespace
    pub, ingest, node, puts = _publisher()
    steps = [("down", "--source tcp:a:1 down (ConnectionRefusedError)"), ("silent", "--source tcp:a:1 open, no "
             "MAVLink for 0.0 s"), ("up", "--source tcp:a:1 up"), ("silent", "--source tcp:a:1 open, no MAVLink "
             "for 3.1 s"), ("up", "--source tcp:a:1 up")]
    seen = []

    class ScriptedLink:
        conn = None

        def __init__(self, *a, **kw):
            self.i = 0

        def recv(self, timeout_s, stop):              # no message; the health as the last status left it
            if self.i:
                seen.append((steps[self.i - 1][0], node.state, node.health_fields()["detail"]))
            if self.i == len(steps):
                stop.set()
            else:
                self.i += 1
            return None

        def status(self):
            return steps[self.i - 1]

        def send(self, fn):
            return False

        def close(self):
            pass

    workers = {}
    monkeypatch.setattr(MI, "MavLink", ScriptedLink)
    monkeypatch.setattr(node, "worker", lambda fn, *a, name=None: workers.setdefault(name, fn))
    args = SimpleNamespace(source="tcp:a:1", baud=57600, source_system=1, timesync_hz=0.0, request_streams=False,
                           stream_hz=50.0)
    MI._start_live(node, args, pub)
    workers["receive"]()
    assert [(s, st) for s, st, _ in seen] == [("down", "degraded"), ("silent", "degraded"), ("up", "ok"),
                                            ("silent", "degraded"), ("up", "ok")]
    assert [d for _, _, d in seen] == [d for _, d in steps]


def _run(args, subs, timeout=30):
    from eonav.bus.session import endpoint, listener_session
    from eonav.app.processes import free_port, start_service, stop_service
    zenoh = pytest.importorskip("zenoh")
    port = free_port()
    with listener_session(port) as s:
        chans = {k: s.declare_subscriber(k, zenoh.handlers.FifoChannel(20000)) for k in subs}
        proc = start_service(["-m", "eonav.services.mavlink_ingest", "--vehicle", "t2", "--connect", endpoint(port),
                              "--health-period-s", "0.2", *args])
        return s, chans, proc, stop_service


def _drain_all(sub):
    from eonav.app.processes import drain
    return [schema.decode(m.payload.to_bytes()) for m in drain(sub)]


def test_service_replays_generated_tlog(tlog, tmp_path):
    from eonav.bus.session import endpoint, listener_session
    from eonav.app.processes import free_port, start_service, stop_service, wait_until
    zenoh = pytest.importorskip("zenoh")
    path, counts = tlog
    # a copy with a corrupt packet in the middle and a truncated last record
    data = bytearray(path.read_bytes())
    i = k = 0
    while k < 100:                                    # walk to record 100 (MAVLink 2: 8 + 10 + len + 2)
        i += 8 + 10 + data[i + 9] + 2
        k += 1
    data[i + 8 + 10 + 3] ^= 0xFF                      # a payload byte of record 100: its CRC fails
    bad = tmp_path / "bad.tlog"
    bad.write_bytes(bytes(data[:-7]))
    port = free_port()
    with listener_session(port) as s:
        nav_sub = s.declare_subscriber(K.nav_state("t2"), zenoh.handlers.FifoChannel(20000))
        clk_sub = s.declare_subscriber(K.nav_clock("t2"), zenoh.handlers.FifoChannel(1000))
        h_sub = s.declare_subscriber(K.health("t2", "mavlink"), zenoh.handlers.FifoChannel(1000))
        t_start_us = time.time_ns() // 1000
        proc = start_service(["-m", "eonav.services.mavlink_ingest", "--source", str(bad), "--speed", "0",
                              "--vehicle", "t2", "--connect", endpoint(port), "--health-period-s", "0.2",
                              "--position-source", "LOCAL_POSITION_NED", "--wait-subscribers-s", "10"])
        try:
            code = proc.wait(30)
        finally:
            if proc.poll() is None:
                stop_service(proc)
        err = proc.stderr.read()
        assert code == 0, err
        assert "end of tlog" in err
        nav, clk, health = [], [], []
        wait_until(lambda: len(nav.__iadd__(_drain_all(nav_sub))) >= 150, 5, what="nav states")
        time.sleep(0.2)
        nav += _drain_all(nav_sub)
        clk = _drain_all(clk_sub)
        health = _drain_all(h_sub)
    n_att = counts["ATTITUDE"] + counts["ATTITUDE_QUATERNION"]
    n_pos = counts["LOCAL_POSITION_NED"]
    assert n_att + n_pos - 3 <= len(nav) <= n_att + n_pos              # one corrupt, one truncated record
    t_s = np.array([(m["autopilot_time_us"] + BOOT_OFFSET_US - DEFAULT_START_UNIX_US) / 1e6 for m in nav])
    tr = nav_truth("turning", t_s)
    for k, m in enumerate(nav):
        assert m["kind"] == "nav_state" and m["system_id"] == 1
        if m["source"] == "LOCAL_POSITION_NED":
            np.testing.assert_allclose(m["position_ned_m"], tr["position_ned_m"][k], atol=1e-4)
            assert np.all(np.isnan(m["q_wxyz"]))
        else:
            assert _angle(m["q_wxyz"], tr["q_wxyz"][k]) < 1e-6
            assert np.all(np.isnan(m["position_ned_m"]))
    # stamps: recorded times mapped onto the current clock, spacing kept to within the latency spread
    st = np.array([m["stamp_us"] for m in nav])
    unix_rec = t_s * 1e6 + DEFAULT_START_UNIX_US
    shift = st - unix_rec
    assert np.ptp(shift) < 2500
    assert abs(np.median(shift) - (t_start_us - DEFAULT_START_UNIX_US)) < 5_000_000      # "now" at start
    for src in ("ATTITUDE", "ATTITUDE_QUATERNION", "LOCAL_POSITION_NED"):
        s_src = [m["stamp_us"] for m in nav if m["source"] == src]
        assert np.all(np.diff(s_src) > 0), src
    assert clk and clk[-1]["method"] == "receive"
    assert clk[-1]["offset_us"] == nav[-1]["clock_offset_us"]
    c = health[-1]["counters"]
    assert c["bad_data"] == 1 and c["truncated_bytes"] > 0
    assert c["msg.HEARTBEAT"] == counts["HEARTBEAT"]
    assert c["rejected.position_source_not_selected"] >= counts["GLOBAL_POSITION_INT"] - 2


def _free_udp_port():
    s = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    s.bind(("127.0.0.1", 0))
    p = s.getsockname()[1]
    s.close()
    return p


def test_service_timesync_against_simulated_autopilot():
    """The service is the companion (udpout); a pymavlink autopilot (udpin) answers TIMESYNC with its
    boot clock in ns, streams ATTITUDE on the same clock and records the companion's HEARTBEAT."""
    from eonav.bus.session import endpoint, listener_session
    from eonav.app.processes import free_port, start_service, stop_service, wait_until
    zenoh = pytest.importorskip("zenoh")
    mavutil = mavutil_v2()
    udp = _free_udp_port()
    boot_offset_ns = time.time_ns() - 987_654_321_000          # booted 987.65 s ago
    ap = mavutil.mavlink_connection(f"udpin:127.0.0.1:{udp}", source_system=1, source_component=1,
                                    dialect="ardupilotmega")
    stop = threading.Event()
    seen = {"hb": [], "ts": 0}

    def autopilot():
        next_att = time.monotonic()
        while not stop.is_set():
            m = ap.recv_match(blocking=True, timeout=0.01)
            if m is not None:
                if m.get_type() == "TIMESYNC" and m.tc1 == 0:
                    ap.mav.timesync_send(time.time_ns() - boot_offset_ns, m.ts1)
                    seen["ts"] += 1
                elif m.get_type() == "HEARTBEAT":
                    seen["hb"].append((m.type, m.autopilot, m.get_srcComponent()))
            if time.monotonic() >= next_att and seen["ts"]:
                boot_ms = (time.time_ns() - boot_offset_ns) // 1_000_000
                ap.mav.attitude_send(boot_ms, 0.01, 0.02, 0.5, 0, 0, 0)
                next_att += 0.02

    th = threading.Thread(target=autopilot)
    th.start()
    port = free_port()
    proc = None
    try:
        with listener_session(port) as s:
            nav_sub = s.declare_subscriber(K.nav_state("t3"), zenoh.handlers.FifoChannel(5000))
            clk_sub = s.declare_subscriber(K.nav_clock("t3"), zenoh.handlers.FifoChannel(1000))
            proc = start_service(["-m", "eonav.services.mavlink_ingest", "--source", f"udpout:127.0.0.1:{udp}",
                                  "--vehicle", "t3", "--connect", endpoint(port), "--timesync-hz", "10"])
            clk = []
            wait_until(lambda: any(c["method"] == "timesync" and c["samples"] >= 10
                                   for c in clk.__iadd__(_drain_all(clk_sub))) or None, 15,
                       what="a TIMESYNC clock estimate from 10 exchanges")
            time.sleep(0.3)
            nav = _drain_all(nav_sub)
            code, err = stop_service(proc)
            clk += _drain_all(clk_sub)
    finally:
        stop.set()
        th.join()
        ap.close()
        if proc is not None and proc.poll() is None:
            stop_service(proc)
    assert code == 0, err
    ts = [c for c in clk if c["method"] == "timesync"]
    best = ts[-1]
    assert abs(best["offset_us"] - boot_offset_ns / 1000) < 1000, (best, boot_offset_ns)    # within 1 ms
    assert 0 <= best["rtt_us"] < 10_000
    assert (18, 8, 191) in seen["hb"]        # MAV_TYPE_ONBOARD_CONTROLLER, MAV_AUTOPILOT_INVALID, comp 191
    assert nav, err
    late = [m for m in nav if m["clock_offset_us"] == best["offset_us"]]
    assert late
    for m in late:
        # stamp = autopilot time + offset: the autopilot's send time on our clock, to ~1 ms (ms truncation)
        assert abs(m["stamp_us"] - (m["autopilot_time_us"] + boot_offset_ns / 1000)) < 2000
