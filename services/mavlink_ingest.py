"""MAVLink ingest: an autopilot link, live or recorded -> ``nav_state`` and ``clock_offset`` on the bus.

Live or recorded is one flag: ``--source`` takes any pymavlink connection string (``udpin:0.0.0.0:14550``,
``tcp:127.0.0.1:5760``, ``/dev/ttyACM0`` with ``--baud``), a ``.tlog`` path, or an ArduPilot dataflash log
(``.BIN``, known by its first bytes; its ATT, XKQ, XKF1 and POS messages go in as the MAVLink messages that carry
the same quantities, ``eonav.nav.dataflash``). Out: one schema ``nav_state`` on
``keys.nav_state(vehicle)`` per accepted navigation message (each message type its own stream, absent quantities
NaN), and ``clock_offset`` on ``keys.nav_clock(vehicle)``. Every ``stamp_us`` is autopilot time mapped onto the
companion clock by the estimated offset; decoding, validation and the clock estimators are ``eonav.nav.mavlink_in``
(docs/mavlink.md). A log replays at real time or a speed factor with its times (tlog record headers, dataflash
GPS-based times) moved onto the current clock (exit 0 at its end); a live link also gets a companion HEARTBEAT and TIMESYNC requests. A live link that is not up yet or drops
(serial device absent, TCP refused, UDP peer silent) is re-opened with back-off (``eonav.nav.links``) and the
health says ``degraded`` until the autopilot is heard; only a malformed connection string is a configuration
error (exit 2).
"""
from __future__ import annotations

import logging
import threading
import time
from collections import Counter
from pathlib import Path

from eonav import InputError
from eonav.bus import keys as K
from eonav.bus.node import Node, add_flag, restart_count, service_main
from eonav.nav.dataflash import DataflashReader, is_dataflash
from eonav.nav.links import MavLink
from eonav.nav.mavlink_in import (ClockMapper, NavDecoder, NavIngest, TlogReader, mavutil_v2)

log = logging.getLogger(__name__)

COMPANION_COMPONENT = 191          # MAV_COMP_ID_ONBOARD_COMPUTER
STREAM_IDS = {"ATTITUDE": 30, "ATTITUDE_QUATERNION": 31, "LOCAL_POSITION_NED": 32, "GLOBAL_POSITION_INT": 33,
              "SYSTEM_TIME": 2}
CLOCK_PUBLISH_PERIOD_US = 1_000_000
RESUME_LATE_US = 100_000     # a joint replay (re)starts at its first record due no more than this long ago
MAX_UNKNOWN_IDS = 1024       # distinct unknown message ids told apart (unknown_msg_ids stops growing there)


def now_us() -> int:
    return time.time_ns() // 1000


def is_tlog(source: str) -> bool:
    """A recorded log (tlog or dataflash) rather than a live link."""
    return source.lower().endswith((".tlog", ".tlog.raw", ".bin")) or (Path(source).is_file()
                                                                       and not source.startswith("/dev/"))


def open_log(path):
    """The reader of a recorded log: ``DataflashReader`` for a dataflash log (first bytes A3 95), else
    ``TlogReader``; both yield ``(stamp_us, message)`` and keep ``stats``."""
    if is_dataflash(path):
        return DataflashReader(path)
    if str(path).lower().endswith(".bin"):
        raise InputError(f"--source {path}: a .bin that is not a dataflash log (its first bytes are not A3 95)")
    return TlogReader(path)


def parse_origin(s: str | None):
    if not s:
        return None
    try:
        vals = [float(x) for x in s.split(",")]
    except ValueError:
        vals = []
    if len(vals) != 3:
        raise InputError(f"--origin {s!r}: expected LAT_DEG,LON_DEG,ALT_M")
    return tuple(vals)


def parse_clock(s: str, tlog: bool):
    if s == "auto":
        return ("receive",) if tlog else ("timesync", "system_time", "receive")
    methods = tuple(x.strip() for x in s.split(",") if x.strip())
    bad = set(methods) - {"timesync", "system_time", "receive"}
    if bad or not methods:
        raise InputError(f"--clock {s!r}: expected auto or a comma list of timesync, system_time, receive")
    return methods


def make_ingest(args, tlog: bool) -> NavIngest:
    dec = NavDecoder(system_id=args.system_id, origin_lla=parse_origin(args.origin),
                     position_source=args.position_source)
    mapper = ClockMapper(prefer=parse_clock(args.clock, tlog), window_us=int(args.clock_window_s * 1e6),
                         max_rtt_us=int(args.max_rtt_ms * 1000))
    return NavIngest(dec, mapper)


class Publisher:
    """Turns NavIngest output into bus messages and health counters (thread-safe)."""

    def __init__(self, node: Node, ingest: NavIngest):
        self.node, self.ingest = node, ingest
        self.nav_pub = node.publisher(K.nav_state(node.vehicle))
        self.clock_pub = node.publisher(K.nav_clock(node.vehicle))
        self.lock = threading.Lock()
        self._last_clock = None
        self._last_clock_us = None
        self._reported: Counter = Counter()
        self._unknown_ids: set = set()

    def feed(self, msg, rx_us: int) -> None:
        t = msg.get_type()
        if t.startswith("UNKNOWN_"):
            # an id the dialect does not define (pymavlink cannot check its CRC): corrupt bytes, mostly. Two
            # counters, not one per id: messages (msg.unknown) and distinct ids (unknown_msg_ids, at most 1024)
            self.node.count("msg.unknown")
            if t not in self._unknown_ids and len(self._unknown_ids) < MAX_UNKNOWN_IDS:
                self._unknown_ids.add(t)
                self.node.count("unknown_msg_ids")
            return
        self.node.count(f"msg.{t}")
        if t == "BAD_DATA":
            self.node.count("bad_data")
            return
        with self.lock:
            states = self.ingest.feed(msg, rx_us)
        self.publish(states, rx_us)

    def fast_forward(self, msg, rx_us: int) -> None:
        """Feed a record the replay passes over (already due when it started): the decoder (origin, system id)
        and the clock estimator see it, nothing is published (``replay_skipped``), not even later: its sample does not
        wait in the ingest for the clock to lock."""
        self.node.count("replay_skipped")
        if msg.get_type() != "BAD_DATA":
            with self.lock:
                self.ingest.feed(msg, rx_us)
                self.ingest.discard_pending()

    def publish(self, states, now: int) -> None:
        for d in states:
            self.node.put(self.nav_pub, "nav_state", **d)
            self.node.count("nav_published")
        self.sync_counters()
        est = self.ingest.clock()
        if est is None:
            return
        key = (est.method, est.offset_us)
        if key != self._last_clock and (self._last_clock is None or est.method != self._last_clock[0]
                                        or self._last_clock_us is None
                                        or now - self._last_clock_us >= CLOCK_PUBLISH_PERIOD_US):
            self.node.put(self.clock_pub, "clock_offset", stamp_us=int(now), offset_us=int(est.offset_us),
                          rtt_us=int(est.rtt_us), method=est.method, samples=int(est.samples))
            if self._last_clock is None or est.method != self._last_clock[0]:
                self.node.log.info("clock offset: %s %+.6f s (%d samples)", est.method, est.offset_us / 1e6,
                                   est.samples)
            self._last_clock, self._last_clock_us = key, now
            self.node.set_state("ok", f"clock {est.method} offset_us {est.offset_us} rtt_us {est.rtt_us}")

    def sync_counters(self) -> None:
        """Mirror the ingest's rejection counters into the node's health counters."""
        cur = self.ingest.rejected
        cur["reboots"] = self.ingest.decoder.reboots
        for k, v in cur.items():
            d = v - self._reported[k]
            if d:
                self.node.count(k if k == "reboots" else f"rejected.{k}", d)
                self._reported[k] = v


def replay_tlog(path, feed, *, speed: float, stop: threading.Event, keep_stamps: bool = False,
                clock=now_us, sleep=None, shift_us: int | None = None, skip=None) -> TlogReader:
    """Replay a log (a path, or a reader from ``open_log``) into ``feed(msg, rx_us)``: its times shifted onto the
    current clock, paced at
    ``speed`` x real time (0 = as fast as possible). With ``shift_us`` (joint replays, see the camera
    ingest), each record is stamped header + shift_us and released when the clock reaches that stamp; records
    already due more than ``RESUME_LATE_US`` when the replay starts go to ``skip(msg, rx_us)`` instead (default:
    dropped), so a replay restarted mid-way resumes where the clock says it is. Returns the reader (its ``stats``)."""
    sleep = sleep or (lambda s: stop.wait(s))
    if shift_us is not None:
        if keep_stamps or speed != 1.0:
            raise InputError("--replay-shift-us replays at real time: it excludes --keep-stamps and --speed != 1")
        resume_us = clock() - RESUME_LATE_US
        with (open_log(path) if isinstance(path, (str, Path)) else path) as reader:
            for header_us, msg in reader:
                if stop.is_set():
                    break
                if header_us + shift_us < resume_us:
                    if skip is not None:
                        skip(msg, header_us + shift_us)
                    continue
                wait_s = (header_us + shift_us - clock()) / 1e6
                if wait_s > 0.001:
                    sleep(wait_s)
                feed(msg, header_us + shift_us)
        return reader
    reader = open_log(path) if isinstance(path, (str, Path)) else path
    shift = None
    t_start_mono = time.monotonic()
    first = None
    with reader:
        for header_us, msg in reader:
            if stop.is_set():
                break
            if first is None:
                first = header_us
                shift = 0 if keep_stamps else clock() - header_us
            if speed > 0:
                due = t_start_mono + (header_us - first) / 1e6 / speed
                wait = due - time.monotonic()
                if wait > 0.001:
                    sleep(wait)
            feed(msg, header_us + shift)
    return reader


def add_arguments(p) -> None:
    g = p.add_argument_group("mavlink ingest")
    add_flag(g, "--source", env="EONAV_MAVLINK_SOURCE", default=None, required=False,
             help="pymavlink connection string (udpin:0.0.0.0:14550, tcp:host:port, /dev/ttyACM0) or a .tlog path")
    add_flag(g, "--baud", env="EONAV_MAVLINK_BAUD", default=57600, type=int, help="serial baud rate")
    add_flag(g, "--speed", env="EONAV_MAVLINK_SPEED", default=1.0, type=float, metavar="FACTOR",
             help="tlog replay speed factor (1 = real time, 2 = twice as fast, 0 = as fast as possible)",
             aliases="--rate", old_env="EONAV_MAVLINK_RATE")
    add_flag(g, "--replay-shift-us", env="EONAV_REPLAY_SHIFT_US", default=None, type=int, metavar="D",
             help="tlog joint replay: stamp header + D and release at that host time (same D for every replay)")
    add_flag(g, "--keep-stamps", env="EONAV_MAVLINK_KEEP_STAMPS", default=False, action="store_true",
             help="tlog: keep the recorded header times instead of mapping them onto the current clock")
    add_flag(g, "--system-id", env="EONAV_MAVLINK_SYSTEM_ID", default=None, type=int,
             help="autopilot system id to follow (default: the first autopilot seen, component 1)")
    add_flag(g, "--source-system", env="EONAV_MAVLINK_SOURCE_SYSTEM", default=1, type=int,
             help="our MAVLink system id on live links (the vehicle's; component is 191)")
    add_flag(g, "--position-source", env="EONAV_MAVLINK_POSITION_SOURCE", default="auto",
             choices=("auto", "LOCAL_POSITION_NED", "GLOBAL_POSITION_INT", "ODOMETRY"),
             help="which message gives position (auto: the first seen)")
    add_flag(g, "--origin", env="EONAV_MAVLINK_ORIGIN", default=None, metavar="LAT,LON,ALT",
             help="local NED origin for GLOBAL_POSITION_INT (deg, deg, m AMSL; default: first fix)")
    add_flag(g, "--clock", env="EONAV_MAVLINK_CLOCK", default="auto",
             help="clock-offset methods in preference order: auto (tlog: receive; live: "
                  "timesync,system_time,receive) or a comma list")
    add_flag(g, "--clock-window-s", env="EONAV_MAVLINK_CLOCK_WINDOW_S", default=20.0, type=float, metavar="S",
             help="sliding window of the min-filter offset estimators (s of autopilot time)",
             aliases="--clock-window", old_env="EONAV_MAVLINK_CLOCK_WINDOW")
    add_flag(g, "--max-rtt-ms", env="EONAV_MAVLINK_MAX_RTT_MS", default=10.0, type=float, metavar="MS",
             help="TIMESYNC exchanges with a longer round trip are ignored")
    add_flag(g, "--timesync-hz", env="EONAV_MAVLINK_TIMESYNC_HZ", default=5.0, type=float, metavar="HZ",
             help="live links: TIMESYNC request rate (0 = off)")
    add_flag(g, "--request-streams", env="EONAV_MAVLINK_REQUEST_STREAMS", default=False, action="store_true",
             help="live links: MAV_CMD_SET_MESSAGE_INTERVAL for the nav messages")
    add_flag(g, "--stream-hz", env="EONAV_MAVLINK_STREAM_HZ", default=50.0, type=float, metavar="HZ",
             help="rate requested with --request-streams")
    add_flag(g, "--wait-subscribers-s", env="EONAV_MAVLINK_WAIT_SUBSCRIBERS_S", default=2.0, type=float, metavar="S",
             help="tlog: wait up to S s for a nav_state subscriber before replaying (declaration race)",
             aliases="--wait-subscribers", old_env="EONAV_MAVLINK_WAIT_SUBSCRIBERS")


def body(node: Node, args) -> None:
    if not args.source:
        raise InputError("--source is required (a pymavlink connection string or a .tlog path)")
    tlog = is_tlog(args.source)
    if tlog and not Path(args.source).exists():
        raise InputError(f"--source {args.source}: no such log file")
    if tlog and not Path(args.source).is_file():
        raise InputError(f"--source {args.source}: not a regular file (expected a .tlog or dataflash .BIN log)")
    if tlog and args.replay_shift_us is None and restart_count():
        # no fixed time reference: it would start over with the recording's beginning presented as now
        node.log.warning("tlog replay of %s restarted without --replay-shift-us: it cannot resume where it was, so "
                         "it ends here instead of starting over (docs/bus.md, Staleness)", args.source)
        node.stop("restarted replay cannot resume")
        return
    if args.speed < 0:
        raise InputError(f"--speed {args.speed}: expected >= 0 (0 = as fast as possible)")
    if args.replay_shift_us is not None and (args.keep_stamps or args.speed != 1.0):
        raise InputError("--replay-shift-us replays at real time: it excludes --keep-stamps and --speed != 1")
    ingest = make_ingest(args, tlog)
    pub = Publisher(node, ingest)
    node.log.info("mavlink %s source %s -> %s", "tlog" if tlog else "live", args.source,
                  K.nav_state(node.vehicle))
    if tlog:
        reader = open_log(args.source)        # a dataflash log is indexed here: an unreadable one fails now
        node.log.info("%s log %s", "dataflash" if isinstance(reader, DataflashReader) else "tlog", args.source)
        node.worker(_run_tlog, node, args, pub, reader, name="replay")
    else:
        _start_live(node, args, pub)


def _run_tlog(node: Node, args, pub: Publisher, reader) -> None:
    if args.wait_subscribers_s > 0:
        node.wait_matching(pub.nav_pub, args.wait_subscribers_s)
    reader = replay_tlog(reader, pub.feed, speed=args.speed, stop=node.stop_event, keep_stamps=args.keep_stamps,
                         shift_us=args.replay_shift_us, skip=pub.fast_forward)
    if node.stop_event.is_set():
        return
    with pub.lock:
        rest = pub.ingest.flush()
    pub.publish(rest, now_us())
    st = reader.stats
    if isinstance(reader, DataflashReader):
        for k, v in vars(st).items():
            if v:
                node.count(f"dataflash_{k}", v)
        node.log.info("end of dataflash log: %d messages, %d navigation, published %s, rejected %s",
                      st.records, st.nav, dict(pub.ingest.published), dict(pub.ingest.rejected))
        node.stop_event.wait(0.3)
        node.stop("end of log")
        return
    node.count("tlog_records", st.records)
    if st.bad_data:
        node.count("bad_data", st.bad_data)
    if st.resync_bytes:
        node.count("resync_bytes", st.resync_bytes)
    if st.truncated_bytes:
        node.count("truncated_bytes", st.truncated_bytes)
        node.log.warning("tlog ends with %d bytes of a truncated record", st.truncated_bytes)
    node.log.info("end of tlog: %d records, %d bad packets, published %s, rejected %s, reboots %d",
                  st.records, st.bad_data, dict(pub.ingest.published), dict(pub.ingest.rejected),
                  pub.ingest.decoder.reboots)
    node.stop_event.wait(0.3)          # let the last messages leave the TX queue
    node.stop("end of tlog")


def _start_live(node: Node, args, pub: Publisher) -> None:
    mavutil = mavutil_v2()
    link = MavLink(args.source, what="--source", baud=args.baud, source_system=args.source_system,
                   source_component=COMPANION_COMPONENT, dialect="ardupilotmega", count=node.count)
    send_lock = threading.Lock()
    mav = mavutil.mavlink

    def receive():
        state = None
        while not node.stop_event.is_set():
            m = link.recv(0.2, node.stop_event)       # opens / re-opens the link with back-off (eonav.nav.links)
            if m is not None:
                pub.feed(m, now_us())
            now_state, detail = link.status()
            if now_state != state:                    # down / silent: degraded until the autopilot is heard
                node.set_state("ok" if now_state == "up" else "degraded", detail)
                state = now_state
        link.close()

    def send():
        next_hb = next_ts = next_req = time.monotonic()
        ts_period = 1.0 / args.timesync_hz if args.timesync_hz > 0 else None
        while not node.stop_event.is_set():
            t = time.monotonic()
            try:
                if t >= next_hb:
                    with send_lock:
                        link.send(lambda c: c.mav.heartbeat_send(mav.MAV_TYPE_ONBOARD_CONTROLLER,
                                                                 mav.MAV_AUTOPILOT_INVALID, 0, 0, mav.MAV_STATE_ACTIVE))
                    next_hb = t + 1.0
                if ts_period and t >= next_ts and link.conn is not None:
                    with pub.lock:
                        ts1 = pub.ingest.mapper.timesync.request(time.time_ns())
                    with send_lock:
                        if link.send(lambda c: c.mav.timesync_send(0, ts1)):
                            node.count("timesync_sent")
                    next_ts = t + ts_period
                sysid = pub.ingest.decoder.system_id
                if args.request_streams and sysid is not None and t >= next_req:
                    for name, msg_id in STREAM_IDS.items():
                        hz = 1.0 if name == "SYSTEM_TIME" else args.stream_hz
                        with send_lock:
                            link.send(lambda c: c.mav.command_long_send(sysid, 1, mav.MAV_CMD_SET_MESSAGE_INTERVAL,
                                                                        0, msg_id, int(1e6 / hz), 0, 0, 0, 0, 0))
                    node.count("stream_requests")
                    next_req = t + 30.0
            except Exception as e:
                node.count("send_errors")
                node.log_limited("send", logging.WARNING, "send failed: %s", e)
            node.stop_event.wait(0.01)

    node.worker(receive, name="receive")
    node.worker(send, name="send")


if __name__ == "__main__":
    service_main("mavlink", add_arguments, body, module="mavlink_ingest")
