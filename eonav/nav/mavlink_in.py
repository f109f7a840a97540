"""MAVLink navigation messages -> navigation samples, and the autopilot -> companion clock offset.

In: pymavlink message objects (anything with ``get_type()``, ``get_srcSystem()``, ``get_srcComponent()`` and the
fields), from a live link or a tlog (``TlogReader``). Out: ``NavSample`` per accepted ATTITUDE,
ATTITUDE_QUATERNION, LOCAL_POSITION_NED, GLOBAL_POSITION_INT or ODOMETRY (SI units, ``q_wxyz``, local NED), each
message type its own stream with its own stamps, mapped onto the companion clock by ``ClockMapper`` (TIMESYNC, else
SYSTEM_TIME, else receive time). Rejected messages are counted by reason, never emitted. ``NavIngest`` is the
pipeline object the MAVLink ingest service drives; tests drive it with lists of messages and injected receive times.
The messages, units, clock estimators and pitfalls: docs/mavlink.md.
"""
from __future__ import annotations

import logging
import math
import os
import struct
from collections import Counter, deque
from dataclasses import dataclass

import numpy as np

from eonav import InputError
from eonav.geometry.frames import quat_wxyz_from_ypr, rotation_from_quat_wxyz

log = logging.getLogger(__name__)

NAV_TYPES = ("ATTITUDE", "ATTITUDE_QUATERNION", "LOCAL_POSITION_NED", "GLOBAL_POSITION_INT", "ODOMETRY")
CLOCK_TYPES = ("SYSTEM_TIME", "TIMESYNC")
POSITION_TYPES = ("LOCAL_POSITION_NED", "GLOBAL_POSITION_INT", "ODOMETRY")
MAV_FRAME_LOCAL_NED = 1
MAV_FRAME_BODY_FRD = 12
MAV_FRAME_BODY_NED = 8
UNIX_TIME_MIN_US = 10**15          # time_usec above this is UNIX epoch (after 2001-09), below: since boot

# WGS-84
WGS84_A_M = 6378137.0
WGS84_F = 1.0 / 298.257223563
WGS84_E2 = WGS84_F * (2.0 - WGS84_F)


def mavutil_v2():
    """pymavlink's mavutil with the MAVLink 2 parser (which also reads MAVLink 1 packets).

    ``MAVLINK20`` must be set before mavutil picks a dialect (docs/mavlink.md, pymavlink pitfalls)."""
    os.environ.setdefault("MAVLINK20", "1")
    from pymavlink import mavutil
    return mavutil


def mavlink2_dialect():
    """The ardupilotmega MAVLink 2 dialect module (encoders for tests and the recorder)."""
    from pymavlink.dialects.v20 import ardupilotmega
    return ardupilotmega


# ----------------------------------------------------------------------------- geodesy
def ecef_from_lla(lat_deg: float, lon_deg: float, alt_m: float) -> np.ndarray:
    lat, lon = math.radians(lat_deg), math.radians(lon_deg)
    n = WGS84_A_M / math.sqrt(1.0 - WGS84_E2 * math.sin(lat) ** 2)    # prime-vertical radius
    return np.array([(n + alt_m) * math.cos(lat) * math.cos(lon),
                     (n + alt_m) * math.cos(lat) * math.sin(lon),
                     (n * (1.0 - WGS84_E2) + alt_m) * math.sin(lat)])


def T_ned_ecef(lat_deg: float, lon_deg: float) -> np.ndarray:
    """Rotation ECEF -> local NED at (lat, lon)."""
    lat, lon = math.radians(lat_deg), math.radians(lon_deg)
    sl, cl, so, co = math.sin(lat), math.cos(lat), math.sin(lon), math.cos(lon)
    return np.array([[-sl * co, -sl * so, cl],
                     [-so, co, 0.0],
                     [-cl * co, -cl * so, -sl]])


def ned_from_lla(lat_deg: float, lon_deg: float, alt_m: float, origin_lla) -> np.ndarray:
    """Local NED (m) of a WGS-84 point about ``origin_lla`` = (lat deg, lon deg, alt m).

    North/east: tangent plane at the origin; down: ``-(alt - alt0)`` (see module docstring)."""
    lat0, lon0, alt0 = (float(x) for x in origin_lla)
    d = ecef_from_lla(lat_deg, lon_deg, alt0) - ecef_from_lla(lat0, lon0, alt0)
    ned = T_ned_ecef(lat0, lon0) @ d
    return np.array([ned[0], ned[1], -(alt_m - alt0)])


def lla_from_ned(position_ned_m, origin_lla) -> tuple:
    """Inverse of ``ned_from_lla``: (lat deg, lon deg, alt m); Newton iterations on the tangent-plane
    north/east (sub-millimetre within tens of kilometres)."""
    lat0, lon0, alt0 = (float(x) for x in origin_lla)
    p = np.asarray(position_ned_m, float).reshape(3)
    lat, lon = lat0, lon0
    for _ in range(8):
        ne = ned_from_lla(lat, lon, alt0, origin_lla)[:2]
        err_n, err_e = p[0] - ne[0], p[1] - ne[1]
        sl = math.sin(math.radians(lat))
        m_rad = WGS84_A_M * (1 - WGS84_E2) / (1 - WGS84_E2 * sl * sl) ** 1.5     # meridian radius
        n_rad = WGS84_A_M / math.sqrt(1 - WGS84_E2 * sl * sl)                     # prime-vertical radius
        lat += math.degrees(err_n / (m_rad + alt0))
        lon += math.degrees(err_e / ((n_rad + alt0) * math.cos(math.radians(lat))))
        if abs(err_n) < 1e-6 and abs(err_e) < 1e-6:
            break
    return lat, lon, alt0 - p[2]


# ----------------------------------------------------------------------------- samples
@dataclass(frozen=True)
class NavSample:
    """One navigation message, decoded. Absent quantities are None.

    ``autopilot_time_us`` is in the autopilot boot clock of ``boot_epoch`` unless ``time_base`` is
    "unix" (ODOMETRY stamped in UNIX time)."""
    msg_type: str
    system_id: int
    component_id: int
    autopilot_time_us: int
    boot_epoch: int = 0
    time_base: str = "boot"
    q_wxyz: np.ndarray | None = None
    position_ned_m: np.ndarray | None = None
    velocity_ned_mps: np.ndarray | None = None
    rates_frd_radps: np.ndarray | None = None

    @property
    def has_attitude(self) -> bool:
        return self.q_wxyz is not None

    @property
    def has_position(self) -> bool:
        return self.position_ned_m is not None


def _finite(*xs) -> bool:
    return all(isinstance(x, (int, float)) and math.isfinite(x) for x in xs)


def boot_time_us(msg) -> int | None:
    """The autopilot time of a message in us, or None if it carries none we use."""
    t = msg.get_type()
    if t in ("ATTITUDE", "ATTITUDE_QUATERNION", "LOCAL_POSITION_NED", "GLOBAL_POSITION_INT", "SYSTEM_TIME"):
        return int(msg.time_boot_ms) * 1000
    if t == "ODOMETRY":
        tu = int(msg.time_usec)
        return tu if tu < UNIX_TIME_MIN_US else None
    return None


class NavDecoder:
    """MAVLink messages -> ``NavSample`` (see module docstring for rules and rejection reasons).

    ``system_id=None`` locks onto the first system whose component ``autopilot_component`` (1) sends
    a navigation message or an autopilot HEARTBEAT."""

    def __init__(self, system_id: int | None = None, origin_lla=None, position_source: str = "auto",
                 autopilot_component: int = 1, quat_norm_tol: float = 1e-3,
                 reboot_jump_us: int = 2_000_000, reboot_confirm: int = 2,
                 alt_jump_m: float = 20.0, max_vertical_speed_mps: float = 100.0):
        if position_source not in ("auto", *POSITION_TYPES):
            raise InputError(f"position_source {position_source!r}: expected 'auto' or one of {POSITION_TYPES}")
        if origin_lla is not None:
            o = np.asarray(origin_lla, float).reshape(-1)
            if o.size != 3 or not np.all(np.isfinite(o)) or abs(o[0]) > 90 or abs(o[1]) > 180:
                raise InputError(f"origin_lla {origin_lla!r}: expected (lat deg, lon deg, alt m), finite")
            origin_lla = tuple(float(x) for x in o)
        self.system_id = system_id
        self.autopilot_component = autopilot_component
        self.origin_lla = origin_lla
        self.position_source = position_source
        self.quat_norm_tol = quat_norm_tol
        self.reboot_jump_us = reboot_jump_us
        self.reboot_confirm = reboot_confirm
        self.alt_jump_m, self.max_vertical_speed_mps = alt_jump_m, max_vertical_speed_mps
        self._last_global = None
        self.counts: Counter = Counter()       # accepted samples per message type
        self.seen: Counter = Counter()         # every message type seen (all systems)
        self.rejected: Counter = Counter()     # rejections by reason
        self.reboots = 0
        self.boot_epoch = 0
        self._last_boot_us: int | None = None
        self._reboot_candidates: list[int] = []
        self._last_time: dict = {}             # stream -> last autopilot time

    # -- source filter
    def is_autopilot(self, msg) -> bool:
        """True for messages of the selected autopilot (locks ``system_id`` on first sight)."""
        if self.system_id is None:
            t = msg.get_type()
            if msg.get_srcComponent() != self.autopilot_component or msg.get_srcSystem() in (0, 255):
                return False
            if t in NAV_TYPES or t in CLOCK_TYPES or (t == "HEARTBEAT" and getattr(msg, "autopilot", 8) != 8):
                self.system_id = msg.get_srcSystem()
                log.info("locked onto autopilot system %d", self.system_id)
            else:
                return False
        return msg.get_srcSystem() == self.system_id and msg.get_srcComponent() == self.autopilot_component

    # -- time checks
    def observe_boot_time(self, t_us: int) -> str:
        """Track the autopilot boot clock; returns "ok", "reboot" or "time_backwards"."""
        last = self._last_boot_us
        if last is None or t_us >= last - self.reboot_jump_us:
            self._reboot_candidates.clear()
            if last is None or t_us > last:
                self._last_boot_us = t_us
            return "ok"
        c = self._reboot_candidates
        if c and not (c[-1] - self.reboot_jump_us <= t_us <= c[-1] + self.reboot_jump_us):
            c.clear()
        c.append(t_us)
        if len(c) >= self.reboot_confirm:
            self.reboots += 1
            self.boot_epoch += 1
            self._last_boot_us = max(c)
            self._last_time.clear()
            c.clear()
            log.warning("autopilot reboot detected (time_boot jumped back from %.3f s to %.3f s)",
                        last / 1e6, t_us / 1e6)
            return "reboot"
        return "time_backwards"

    def _check_stream(self, msg, t_us: int) -> bool:
        key = (msg.get_srcSystem(), msg.get_srcComponent(), msg.get_type())
        last = self._last_time.get(key)
        if last is not None and t_us <= last:
            self.rejected["duplicate_time" if t_us == last else "time_backwards"] += 1
            return False
        self._last_time[key] = t_us
        return True

    # -- decode
    def decode(self, msg) -> NavSample | None:
        """A NavSample for a valid navigation message of the selected autopilot, else None."""
        t = msg.get_type()
        self.seen["UNKNOWN" if t.startswith("UNKNOWN_") else t] += 1      # one key for every undefined id
        if t not in NAV_TYPES:
            return None
        if not self.is_autopilot(msg):
            self.rejected["wrong_system"] += 1
            return None
        tb = boot_time_us(msg)
        if tb is not None:
            state = self.observe_boot_time(tb)
            if state == "time_backwards":
                self.rejected["time_backwards"] += 1
                return None
        fn = getattr(self, "_" + t.lower())
        fields = fn(msg)
        if fields is None:
            return None
        if "position_ned_m" in fields and not self._position_source_ok(t):
            fields.pop("position_ned_m")
            fields.pop("velocity_ned_mps", None)
            if "q_wxyz" not in fields:
                self.rejected["position_source_not_selected"] += 1
                return None
        time_us, base = (tb, "boot") if tb is not None else (int(msg.time_usec), "unix")
        if not self._check_stream(msg, time_us):
            return None
        self.counts[t] += 1
        return NavSample(t, msg.get_srcSystem(), msg.get_srcComponent(), time_us, self.boot_epoch, base, **fields)

    def _position_source_ok(self, t: str) -> bool:
        if self.position_source == "auto":
            self.position_source = t
            log.info("position source: %s", t)
        return self.position_source == t

    def _attitude_ok(self, q) -> np.ndarray | None:
        q = np.asarray(q, float)
        if not np.all(np.isfinite(q)):
            self.rejected["attitude_nonfinite"] += 1
            return None
        n = float(np.linalg.norm(q))
        if abs(n - 1.0) > self.quat_norm_tol:
            self.rejected["quat_not_unit"] += 1
            return None
        q = q / n
        return q if q[0] >= 0 else -q

    def _attitude(self, m):
        if not _finite(m.roll, m.pitch, m.yaw):
            self.rejected["attitude_nonfinite"] += 1
            return None
        eps = 1e-4
        if abs(m.roll) > math.pi + eps or abs(m.yaw) > math.pi + eps or abs(m.pitch) > math.pi / 2 + eps:
            self.rejected["attitude_out_of_range"] += 1
            return None
        out = {"q_wxyz": quat_wxyz_from_ypr(m.yaw, m.pitch, m.roll)}
        if _finite(m.rollspeed, m.pitchspeed, m.yawspeed):
            out["rates_frd_radps"] = np.array([m.rollspeed, m.pitchspeed, m.yawspeed], float)
        return out

    def _attitude_quaternion(self, m):
        q = self._attitude_ok([m.q1, m.q2, m.q3, m.q4])
        if q is None:
            return None
        out = {"q_wxyz": q}
        if _finite(m.rollspeed, m.pitchspeed, m.yawspeed):
            out["rates_frd_radps"] = np.array([m.rollspeed, m.pitchspeed, m.yawspeed], float)
        return out

    def _local_position_ned(self, m):
        if not _finite(m.x, m.y, m.z):
            self.rejected["position_nonfinite"] += 1
            return None
        out = {"position_ned_m": np.array([m.x, m.y, m.z], float)}
        if _finite(m.vx, m.vy, m.vz):
            out["velocity_ned_mps"] = np.array([m.vx, m.vy, m.vz], float)
        return out

    def _global_position_int(self, m):
        if m.lat == 0 and m.lon == 0:
            self.rejected["global_no_fix"] += 1
            return None
        lat, lon, alt = m.lat * 1e-7, m.lon * 1e-7, m.alt * 1e-3
        if abs(lat) > 90 or abs(lon) > 180:
            self.rejected["global_out_of_range"] += 1
            return None
        if self.position_source not in ("auto", "GLOBAL_POSITION_INT"):
            return {"position_ned_m": np.zeros(3)}          # dropped by the source filter anyway
        if self.origin_lla is None:
            self.origin_lla = (lat, lon, alt)
            log.info("GLOBAL_POSITION_INT origin: lat %.7f lon %.7f alt %.3f m", lat, lon, alt)
        t_us = int(m.time_boot_ms) * 1000
        prev = self._last_global
        if prev is not None:
            dt_s = (t_us - prev[1]) * 1e-6 if prev[2] == self.boot_epoch else 0.0
            jump_m = alt - prev[0]
            if abs(jump_m) > self.alt_jump_m + self.max_vertical_speed_mps * max(dt_s, 0.0):
                # ArduPilot reports alt = relative_alt until its EKF origin is set, then AMSL:
                # a datum change, not motion. Re-anchor alt0 so that down stays continuous.
                lat0, lon0, alt0 = self.origin_lla
                self.origin_lla = (lat0, lon0, alt0 + jump_m)
                self.rejected["global_alt_datum_jump"] += 1      # counted, the sample is kept
                log.warning("GLOBAL_POSITION_INT alt jumped %.1f m in %.2f s: datum change, origin alt "
                            "re-anchored", jump_m, dt_s)
        self._last_global = (alt, t_us, self.boot_epoch)
        return {"position_ned_m": ned_from_lla(lat, lon, alt, self.origin_lla),
                "velocity_ned_mps": np.array([m.vx, m.vy, m.vz], float) * 0.01}

    def _odometry(self, m):
        if int(m.frame_id) != MAV_FRAME_LOCAL_NED:
            self.rejected["odometry_frame_unsupported"] += 1
            return None
        q = self._attitude_ok(list(m.q))
        if q is None:
            return None
        out = {"q_wxyz": q}
        if _finite(m.x, m.y, m.z):
            out["position_ned_m"] = np.array([m.x, m.y, m.z], float)
        v = np.array([m.vx, m.vy, m.vz], float)
        if np.all(np.isfinite(v)):
            if int(m.child_frame_id) == MAV_FRAME_BODY_FRD:
                v = rotation_from_quat_wxyz(q) @ v          # body FRD -> NED
            if int(m.child_frame_id) in (MAV_FRAME_BODY_FRD, MAV_FRAME_LOCAL_NED):
                out["velocity_ned_mps"] = v
        if _finite(m.rollspeed, m.pitchspeed, m.yawspeed):
            out["rates_frd_radps"] = np.array([m.rollspeed, m.pitchspeed, m.yawspeed], float)
        return out


# ----------------------------------------------------------------------------- clock offset
class MinWindowOffset:
    """offset_us = min over a sliding window (by autopilot time) of (companion_us - autopilot_us).

    For receive-time and SYSTEM_TIME samples, where delays only add (monotonic-deque sliding minimum)."""

    def __init__(self, method: str, window_us: int = 20_000_000):
        self.method = method
        self.window_us = int(window_us)
        self.reset()

    def reset(self):
        self._q: deque = deque()      # (autopilot_us, offset_us), offsets increasing
        self.samples = 0
        self.first_us: int | None = None
        self.last_us: int | None = None

    def add(self, companion_us: int, autopilot_us: int) -> None:
        off = int(companion_us) - int(autopilot_us)
        q = self._q
        while q and q[-1][1] >= off:
            q.pop()
        q.append((int(autopilot_us), off))
        while q and q[0][0] < autopilot_us - self.window_us:
            q.popleft()
        self.samples += 1
        if self.first_us is None:
            self.first_us = int(autopilot_us)
        self.last_us = int(autopilot_us)

    @property
    def span_us(self) -> int:
        return 0 if self.first_us is None else self.last_us - self.first_us

    @property
    def offset_us(self) -> int | None:
        return self._q[0][1] if self._q else None


class TimesyncEstimator:
    """TIMESYNC exchanges -> offset (companion - autopilot), min-RTT + median filtered."""

    method = "timesync"

    def __init__(self, window: int = 20, max_rtt_us: int = 10_000, max_outstanding: int = 64):
        self.window, self.max_rtt_us = window, max_rtt_us
        self._pending: deque = deque(maxlen=max_outstanding)
        self.rejected: Counter = Counter()
        self.reset()

    def reset(self):
        self._ex: deque = deque(maxlen=self.window)     # (rtt_us, offset_us)
        self.samples = 0

    def request(self, now_ns: int) -> int:
        """Remember and return ts1 for a TIMESYNC(tc1=0, ts1) request sent at now_ns."""
        self._pending.append(int(now_ns))
        return int(now_ns)

    def on_reply(self, tc1_ns: int, ts1_ns: int, t_rx_ns: int) -> bool:
        if ts1_ns not in self._pending:
            self.rejected["timesync_not_ours"] += 1
            return False
        self._pending.remove(ts1_ns)
        rtt_us = (t_rx_ns - ts1_ns) // 1000
        if rtt_us < 0 or rtt_us > self.max_rtt_us:
            self.rejected["timesync_rtt_too_long"] += 1
            return False
        offset_us = ((ts1_ns + t_rx_ns) // 2 - tc1_ns) // 1000
        self._ex.append((rtt_us, offset_us))
        self.samples += 1
        return True

    @property
    def offset_us(self) -> int | None:
        if not self._ex:
            return None
        best = sorted(self._ex)[:max(1, len(self._ex) // 4)]
        return int(np.median([o for _, o in best]))

    @property
    def rtt_us(self) -> int:
        return min(r for r, _ in self._ex) if self._ex else -1


@dataclass
class ClockEstimate:
    offset_us: int
    method: str
    samples: int
    rtt_us: int = -1


class ClockMapper:
    """Chooses the best clock-offset estimate and maps autopilot time to companion stamps.

    Mapping keeps stamps monotonic: increases of the estimate step, decreases slew at ``slew`` s/s."""

    def __init__(self, prefer=("timesync", "system_time", "receive"), window_us: int = 20_000_000,
                 lock_span_us: int = 2_000_000, slew: float = 0.1, max_rtt_us: int = 10_000):
        bad = set(prefer) - {"timesync", "system_time", "receive"}
        if bad or not prefer:
            raise InputError(f"clock methods {sorted(bad)}: expected some of timesync, system_time, receive")
        self.prefer = tuple(prefer)
        self.timesync = TimesyncEstimator(max_rtt_us=max_rtt_us)
        self.system_time = MinWindowOffset("system_time", window_us)
        self.receive = MinWindowOffset("receive", window_us)
        self.lock_span_us, self.slew = lock_span_us, slew
        self._applied: int | None = None
        self._last_map_us: int | None = None

    def reset(self):
        self.timesync.reset()
        self.system_time.reset()
        self.receive.reset()
        self._applied = self._last_map_us = None

    def _ready(self, name) -> bool:
        if name == "timesync":
            return self.timesync.samples >= 3
        return getattr(self, name).span_us >= self.lock_span_us

    def best(self) -> ClockEstimate | None:
        """The preferred estimate that is locked, else the preferred one that has any sample."""
        for require_lock in (True, False):
            for name in self.prefer:
                est = getattr(self, name)
                if est.offset_us is not None and (not require_lock or self._ready(name)):
                    return ClockEstimate(est.offset_us, name, est.samples,
                                         self.timesync.rtt_us if name == "timesync" else -1)
        return None

    @property
    def locked(self) -> bool:
        return any(getattr(self, n).offset_us is not None and self._ready(n) for n in self.prefer)

    @property
    def applied_offset_us(self) -> int | None:
        return self._applied

    def map(self, autopilot_us: int) -> int | None:
        """Companion stamp of an autopilot time (None without any estimate)."""
        est = self.best()
        if est is None:
            return None
        if self._applied is None or est.offset_us >= self._applied:
            self._applied = est.offset_us
        else:
            dt = 0 if self._last_map_us is None else max(0, autopilot_us - self._last_map_us)
            self._applied = max(est.offset_us, self._applied - int(self.slew * dt))
        if self._last_map_us is None or autopilot_us > self._last_map_us:
            self._last_map_us = autopilot_us
        return int(autopilot_us) + self._applied


# ----------------------------------------------------------------------------- pipeline
class NavIngest:
    """MAVLink messages (+ their companion receive times) -> nav_state field dicts in the companion clock.

    ``feed(msg, rx_us)`` returns a list of dicts ready for ``schema.encode("nav_state", **d)``;
    ``clock()`` the current ``ClockEstimate``. Times are injected: live links pass
    ``time.time_ns()//1000`` at receipt, tlog replays the (remapped) record header time."""

    def __init__(self, decoder: NavDecoder | None = None, mapper: ClockMapper | None = None,
                 max_pending: int = 2000):
        self.decoder = decoder or NavDecoder()
        self.mapper = mapper or ClockMapper()
        self.max_pending = max_pending
        self._pending: deque = deque()
        self._last_stamp: dict = {}
        self.dropped: Counter = Counter()
        self.published: Counter = Counter()

    @property
    def rejected(self) -> Counter:
        out = Counter(self.decoder.rejected)
        out.update(self.mapper.timesync.rejected)
        out.update(self.dropped)
        return out

    def clock(self) -> ClockEstimate | None:
        return self.mapper.best()

    def _clock_samples(self, msg, rx_us: int | None):
        t = msg.get_type()
        if t == "SYSTEM_TIME":
            if msg.time_unix_usec > 0:
                self.mapper.system_time.add(int(msg.time_unix_usec), int(msg.time_boot_ms) * 1000)
            else:
                self.dropped["system_time_no_gps"] += 1
        elif t == "TIMESYNC":
            if msg.tc1 != 0:
                if rx_us is not None:
                    self.mapper.timesync.on_reply(int(msg.tc1), int(msg.ts1), int(rx_us) * 1000)
                return
            # the autopilot's own request: ts1 = its boot clock, usable as a receive-time sample
            if rx_us is not None and msg.ts1 > 0:
                self.mapper.receive.add(int(rx_us), int(msg.ts1) // 1000)
            return
        tb = boot_time_us(msg)
        if rx_us is not None and tb is not None:
            self.mapper.receive.add(int(rx_us), tb)

    def feed(self, msg, rx_us: int | None) -> list:
        """Decode one message received at companion time ``rx_us``; returns nav_state dicts ready now."""
        t = msg.get_type()
        out: list = []
        epoch = self.decoder.boot_epoch
        if t in CLOCK_TYPES:
            self.decoder.seen[t] += 1
            if not self.decoder.is_autopilot(msg):
                return out
            if t == "SYSTEM_TIME":
                st = self.decoder.observe_boot_time(int(msg.time_boot_ms) * 1000)
                if st == "time_backwards":
                    self.dropped["time_backwards"] += 1
                    return out
            if self.decoder.boot_epoch != epoch:
                out += self._on_reboot()
            self._clock_samples(msg, rx_us)
            return out + self._drain()
        s = self.decoder.decode(msg)
        if self.decoder.boot_epoch != epoch:
            out += self._on_reboot()
        if s is None:
            return out + self._drain()
        if s.time_base == "boot":
            self._clock_samples(msg, rx_us)
        self._pending.append(s)
        if len(self._pending) > self.max_pending:
            self._pending.popleft()
            self.dropped["clock_unlocked"] += 1
        return out + self._drain()

    def _on_reboot(self) -> list:
        """Map what is pending from the previous boot with the old estimate, then restart the clocks."""
        old = [s for s in self._pending if s.boot_epoch != self.decoder.boot_epoch]
        self._pending = deque(s for s in self._pending if s.boot_epoch == self.decoder.boot_epoch)
        out = [d for d in (self._state(s) for s in old) if d is not None]
        self.mapper.reset()
        self._last_stamp.clear()
        return out

    def _drain(self, force: bool = False) -> list:
        out: list = []
        if not (self.mapper.locked or force):
            return out
        while self._pending:
            d = self._state(self._pending.popleft())
            if d is not None:
                out.append(d)
        return out

    def flush(self) -> list:
        """At the end of a stream: map what is pending with the best estimate there is."""
        return self._drain(force=True)

    def discard_pending(self) -> int:
        """Drop the samples waiting for the clock to lock (a resumed replay's passed-over records, which must not
        come out with the lock later); returns how many."""
        n = len(self._pending)
        self._pending.clear()
        return n

    def _state(self, s: NavSample) -> dict | None:
        if s.time_base == "unix":
            stamp, off = s.autopilot_time_us, 0
        else:
            stamp = self.mapper.map(s.autopilot_time_us)
            if stamp is None:
                self.dropped["no_clock"] += 1
                return None
            off = self.mapper.applied_offset_us
        key = s.msg_type
        last = self._last_stamp.get(key)
        if last is not None and stamp <= last:
            self.dropped["stamp_backwards_after_offset"] += 1
            return None
        self._last_stamp[key] = stamp
        self.published[s.msg_type] += 1
        nan3 = [math.nan] * 3
        return {"stamp_us": int(stamp), "autopilot_time_us": int(s.autopilot_time_us),
                "position_ned_m": s.position_ned_m if s.position_ned_m is not None else nan3,
                "q_wxyz": s.q_wxyz if s.q_wxyz is not None else [math.nan] * 4,
                "velocity_ned_mps": s.velocity_ned_mps if s.velocity_ned_mps is not None else nan3,
                "rates_frd_radps": s.rates_frd_radps if s.rates_frd_radps is not None else nan3,
                "source": s.msg_type, "clock_offset_us": int(off), "system_id": int(s.system_id)}


# ----------------------------------------------------------------------------- tlogs
@dataclass
class TlogStats:
    records: int = 0          # whole records decoded into a message
    bad_data: int = 0         # records whose packet failed to decode (CRC, length, unknown layout)
    resync_bytes: int = 0     # bytes skipped looking for the next record after garbage
    truncated_bytes: int = 0  # bytes at the end of the file that do not form a whole record
    backwards_headers: int = 0  # headers earlier than the previous one: replaced by the previous
    header_jumps: int = 0       # headers > max_header_step_us from the previous, unconfirmed: replaced


class TlogReader:
    """Stream a .tlog (record = 8-byte big-endian UNIX us + one MAVLink 1/2 packet), decoding with pymavlink.

    Yields ``(header_us, message)``. Corrupt packets are counted (``stats.bad_data``) and skipped;
    after garbage the reader resynchronises on the next byte position that holds a plausible header
    (timestamp within ``max_header_jump_us`` of the last one, then a packet marker). A file cut
    mid-record ends cleanly with ``stats.truncated_bytes`` > 0."""

    def __init__(self, path, max_header_jump_us: int = 3 * 86400 * 10**6, chunk: int = 1 << 16,
                 max_header_step_us: int = 60_000_000):
        self.path = str(path)
        self.max_step = max_header_step_us
        self._jump_candidate: int | None = None
        self.stats = TlogStats()
        self.max_jump = max_header_jump_us
        self._f = open(self.path, "rb")
        self._buf = bytearray()
        self._eof = False
        self._chunk = chunk
        self._last_header: int | None = None
        self._resyncing = False      # after garbage or a bad packet, until the next good record
        dialect = mavlink2_dialect()
        self._mav = dialect.MAVLink(None)
        self._mav.robust_parsing = True
        self._MAVError = dialect.MAVError

    def close(self):
        self._f.close()

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()

    def _fill(self, n: int) -> bool:
        while len(self._buf) < n and not self._eof:
            b = self._f.read(self._chunk)
            if not b:
                self._eof = True
            self._buf += b
        return len(self._buf) >= n

    def _check_header(self, h: int) -> int:
        """Receive times only move forward: a header before the previous one (a corrupt byte, or a
        clock step on the recording host) is replaced by the previous one; a jump of more than
        ``max_header_step_us`` is accepted only when the next record confirms it (a real gap in the
        recording), else replaced. Keeps replay pacing and min-filter clock estimates sane."""
        st, last = self.stats, self._last_header
        if last is None:
            # the first record has no previous one to be checked against: the next two records (the buffer holds
            # what follows it) vote; one corrupt first header would otherwise become the time base of the replay
            nxt = self._next_headers(2)
            if len(nxt) == 2 and abs(nxt[0] - nxt[1]) <= self.max_step and abs(h - nxt[0]) > self.max_step:
                st.header_jumps += 1
                h = nxt[0]
            self._last_header = h
            return h
        if abs(h - last) > self.max_step:
            cand = self._jump_candidate
            if cand is not None and abs(h - cand) <= self.max_step and h >= cand:
                self._jump_candidate = None
                self._last_header = h
                return h
            self._jump_candidate = h
            st.header_jumps += 1
            return last
        self._jump_candidate = None
        if h < last:
            st.backwards_headers += 1
            return last
        self._last_header = h
        return h

    def _record_len(self, i: int) -> int | None:
        """Length of the record starting at buffer index i, or None if no packet marker there."""
        b = self._buf
        magic = b[i + 8]
        if magic == 0xFE:
            return 8 + 6 + b[i + 9] + 2
        if magic == 0xFD:
            return 8 + 10 + b[i + 9] + 2 + (13 if b[i + 10] & 1 else 0)
        return None

    def _next_headers(self, k: int) -> list:
        """Header times of the next ``k`` records in the buffer (from its start), while their packets decode."""
        out, i = [], 0
        while len(out) < k and self._fill(i + 11) and self._record_len(i) is not None and self._decodes(i):
            out.append(int.from_bytes(self._buf[i:i + 8], "big"))
            i += self._record_len(i)
        return out

    def _decodes(self, i: int) -> bool:
        """The record at buffer index i holds a packet that decodes and whose CRC checks out (pymavlink does not
        check the CRC of an id its dialect does not define: such a packet is no evidence)."""
        n = self._record_len(i)
        if n is None or not self._fill(i + n):
            return False
        try:
            msg = self._mav.decode(bytearray(self._buf[i + 8:i + n]))
        except (self._MAVError, struct.error, IndexError, ValueError, TypeError):
            return False
        return not msg.get_type().startswith("UNKNOWN_")

    def _plausible(self, i: int) -> bool:
        """A record may start at buffer index i: a packet marker, and a header time near the last one, or (a header
        far from it: corrupt, or a corrupt last one; or garbage before the file's first good record) a packet that
        decodes with its CRC."""
        if not self._fill(i + 11):
            return False
        h = int.from_bytes(self._buf[i:i + 8], "big")
        if self._buf[i + 8] not in (0xFE, 0xFD):
            return False
        if not self._fill(i + self._record_len(i)):
            return False                  # runs past the end: a truncated tail, or a corrupt length byte
        if self._last_header is None and not self._resyncing:
            return True                   # the file's first record
        if self._last_header is not None and abs(h - self._last_header) <= self.max_jump:
            return True
        return self._decodes(i)

    def __iter__(self):
        st = self.stats
        while True:
            if not self._fill(11):
                st.truncated_bytes += len(self._buf)
                self._buf.clear()
                return
            if not self._plausible(0):
                # garbage: skip to the next plausible record start
                self._resyncing = True
                j = 1
                while self._fill(j + 11) and not self._plausible(j):
                    j += 1
                    if j > 4096:
                        self._buf = self._buf[j:]
                        st.resync_bytes += j
                        j = 0
                        continue
                if not self._fill(j + 11):
                    st.truncated_bytes += len(self._buf)
                    self._buf.clear()
                    return
                st.resync_bytes += j
                del self._buf[:j]
                continue
            n = self._record_len(0)
            if not self._fill(n):
                st.truncated_bytes += len(self._buf)
                self._buf.clear()
                return
            header_us = int.from_bytes(self._buf[:8], "big")
            pkt = bytearray(self._buf[8:n])
            try:
                msg = self._mav.decode(pkt)
            except (self._MAVError, struct.error, IndexError, ValueError, TypeError) as e:
                st.bad_data += 1
                log.debug("tlog bad packet at header %d: %s", header_us, e)
                # the length byte may itself be corrupt: resync from the next byte
                del self._buf[:1]
                self._resyncing = True
                st.resync_bytes += 1
                continue
            if msg.get_type().startswith("UNKNOWN_") and self._fill(n + 11) and not self._plausible(n):
                # an id the dialect does not define has no CRC check: believed only when a record follows it
                # (a corrupt id or length byte would otherwise swallow the records after it)
                st.bad_data += 1
                del self._buf[:1]
                self._resyncing = True
                st.resync_bytes += 1
                continue
            del self._buf[:n]
            self._resyncing = False
            header_us = self._check_header(header_us)
            st.records += 1
            msg._timestamp = header_us / 1e6
            yield header_us, msg
