"""MAVLink OBSTACLE_DISTANCE out to the autopilot, with pymavlink's own encoder (docs/mavlink.md, docs/autopilot.md).

- ``encode_obstacle_distance(sectors, time_usec)``: the wire bytes of one MAVLink 2 message in the autopilots' own
  layout (``MAV_FRAME_BODY_FRD``, 72 x 5 degrees, ``angle_offset`` 0 = element 0's centre on the nose), from
  component 191; layouts either autopilot misreads are refused (``check_sectors``).
- ``ObstacleDistanceSender``: one pymavlink connection (opened and re-opened with back-off by ``eonav.nav.links``
  while the autopilot is not up; ``link_status()`` for the health) with a companion HEARTBEAT at 1 Hz and OBSTACLE_DISTANCE on a
  fixed timer carrying the merge of every camera's fresh sectors (ArduPilot resets all sectors on each message).
  Once every source is stale it sends ONE all-unknown message and then none until a fresh map arrives: a stall must
  look like a dead sensor (No Data at the autopilot), not like an empty sky. ``tick()`` takes an injected clock.
- OBSTACLE_DISTANCE_3D (ardupilotmega dialect; ArduPilot only, PX4 does not know it) of the confirmed tracks, when
  the sender is made with ``messages`` "obstacle_distance_3d" or "both": per cycle one message per track (the point of
  its NED extent box nearest the vehicle, in body FRD of the pose given with the tracks, ``obstacle_id`` the track
  id) stamped ``time_boot_ms`` = T, then one end message stamped T + 1 (a point beyond ``max_distance``, id 65535).
  ArduPilot gathers messages of one ``time_boot_ms`` arriving within 50 ms of each other and files them into its
  boundary when a message with another ``time_boot_ms`` arrives: the end message files the cycle at once (else it
  would wait for the next cycle), and alone it says "no tracked obstacle" while keeping the sensor healthy. With
  "both", OBSTACLE_DISTANCE goes first (ArduPilot rebuilds its whole boundary from each one), then the 3D cycle adds
  the tracks above or below ArduPilot's middle layer (|elevation| >= 15 deg; the middle layer stays
  OBSTACLE_DISTANCE's, which holds every obstacle, tracked or not). A stall: the OBSTACLE_DISTANCE flush (with
  "both"), then silence (docs/autopilot.md).
"""
from __future__ import annotations

import logging
import math
import os
import struct
import threading
import time
from dataclasses import dataclass
from typing import Callable

import numpy as np

from eonav import InputError
from eonav.obstacles.detect import N_SECTORS, SECTOR_INCREMENT_DEG, UINT16_MAX, Sectors, merge_sectors

log = logging.getLogger(__name__)

COMPANION_COMPONENT_ID = 191          # MAV_COMP_ID_ONBOARD_COMPUTER
MAV_FRAME_BODY_FRD = 12
MAV_DISTANCE_SENSOR_UNKNOWN = 4

MESSAGES = ("obstacle_distance", "obstacle_distance_3d", "both")
MAX_OBSTACLES_3D = 40         # ArduPilot's boundary has 40 faces (5 layers x 8 sectors); the nearest 40 tracks
MIDDLE_LAYER_HALF_DEG = 15.0  # ArduPilot's middle (horizontal) boundary layer: elevation -15..15 deg
NO_OBSTACLE_ID = 65535        # OBSTACLE_DISTANCE_3D obstacle_id "unknown" (the end message)

DEFAULT_STALE_S = 0.3   # + the autopilots' own 0.5 s timeout after the flush + one send period: No Data within 1 s


def mavutil():
    """pymavlink's mavutil with MAVLink 2 selected (docs/mavlink.md, pymavlink pitfalls)."""
    os.environ.setdefault("MAVLINK20", "1")
    if os.environ["MAVLINK20"] != "1":
        raise InputError("MAVLINK20 is set to something other than 1: OBSTACLE_DISTANCE needs MAVLink 2")
    from pymavlink import mavutil as mu
    return mu


def check_sectors(sectors: Sectors):
    """Refuse what either autopilot misreads: PX4 reads a body-frame message with an increment below 5 deg past the
    end of its 72-element map (phantom obstacles) and keeps one element per 5-degree bin (so a finer or shifted grid
    loses obstacles); ArduPilot ignores 0 cm. Only the 72 x 5-degree layout on 5-degree centres is sent."""
    d = np.asarray(sectors.distances_cm)
    if d.shape != (N_SECTORS,):
        raise InputError(f"OBSTACLE_DISTANCE needs {N_SECTORS} distances, got shape {d.shape}")
    inc, off = float(sectors.increment_deg), float(sectors.angle_offset_deg)
    if not (inc == SECTOR_INCREMENT_DEG and math.isfinite(off) and -180.0 <= off <= 180.0
            and off % SECTOR_INCREMENT_DEG == 0.0):
        raise InputError(f"OBSTACLE_DISTANCE: increment_deg {inc} / angle_offset_deg {off}: only increment "
                         f"{SECTOR_INCREMENT_DEG} deg with an angle_offset on a multiple of it is read right by "
                         f"both ArduPilot and PX4")
    if not 1 <= sectors.min_distance_cm < sectors.max_distance_cm < UINT16_MAX - 1:
        raise InputError(f"OBSTACLE_DISTANCE: need 1 <= min_distance_cm < max_distance_cm < {UINT16_MAX - 1}, got "
                         f"{sectors.min_distance_cm}, {sectors.max_distance_cm}")


def obstacle_distance_message(mav, sectors: Sectors, time_usec: int, sensor_type: int = MAV_DISTANCE_SENSOR_UNKNOWN):
    """The pymavlink message object (encoded by ``mav``, a ``MAVLink`` instance)."""
    check_sectors(sectors)
    return mav.obstacle_distance_encode(
        time_usec=int(time_usec), sensor_type=int(sensor_type),
        distances=[int(x) for x in np.asarray(sectors.distances_cm, np.int64)],
        increment=0,                                       # ignored when increment_f is non-zero
        min_distance=int(sectors.min_distance_cm), max_distance=int(sectors.max_distance_cm),
        increment_f=float(sectors.increment_deg), angle_offset=float(sectors.angle_offset_deg),
        frame=MAV_FRAME_BODY_FRD)


def encode_obstacle_distance(sectors: Sectors, time_usec: int, *, system_id: int = 1,
                             component_id: int = COMPANION_COMPONENT_ID, seq: int = 0,
                             sensor_type: int = MAV_DISTANCE_SENSOR_UNKNOWN) -> bytes:
    """Wire bytes of one OBSTACLE_DISTANCE (MAVLink 2)."""
    mu = mavutil()
    mav = mu.mavlink.MAVLink(None, srcSystem=system_id, srcComponent=component_id)
    mav.seq = seq & 0xFF
    return bytes(obstacle_distance_message(mav, sectors, time_usec, sensor_type).pack(mav))


@dataclass(frozen=True)
class TrackBox:
    """One confirmed track for OBSTACLE_DISTANCE_3D: its id, NED centre, NED extent (full widths along N, E, D) and
    velocity (zero unless the tracker calls it moving)."""
    id: int
    position_ned_m: np.ndarray
    extent_ned_m: np.ndarray
    velocity_ned_mps: np.ndarray

    @classmethod
    def from_track_msg(cls, t: dict) -> "TrackBox":
        """From one entry of the obstacle-track message's ``tracks`` (eonav.obstacles.guidance.build)."""
        v = np.asarray(t["velocity_ned_mps"], float) if t.get("moving") else np.zeros(3)
        box = cls(int(t["id"]), np.asarray(t["position_ned_m"], float), np.abs(np.asarray(t["extent_ned_m"], float)),
                  v if np.all(np.isfinite(v)) else np.zeros(3))
        if not (box.position_ned_m.shape == box.extent_ned_m.shape == (3,)
                and np.all(np.isfinite(box.position_ned_m)) and np.all(np.isfinite(box.extent_ned_m))):
            raise InputError(f"track {t.get('id')}: position_ned_m and extent_ned_m must be 3 finite numbers")
        return box


def nearest_point_frd(box: TrackBox, vehicle_position_ned_m, T_body_ned, dt_s: float = 0.0) -> np.ndarray:
    """Body FRD vector (m) from the vehicle to the point of the track's NED box (centre +- extent / 2, carried
    ``dt_s`` along its velocity) nearest the vehicle; eq. (15) for NED -> body. Inside the box: the centre."""
    c = box.position_ned_m + box.velocity_ned_mps * dt_s
    pos = np.asarray(vehicle_position_ned_m, float)
    half = 0.5 * box.extent_ned_m
    rel = c + np.clip(pos - c, -half, half) - pos
    if not np.any(rel):
        rel = c - pos
    return np.asarray(T_body_ned, float) @ rel


def elevation_deg(xyz_frd_m) -> float:
    """Elevation of a body FRD point above the body's horizontal plane (positive up), as ArduPilot files it."""
    x, y, z = np.asarray(xyz_frd_m, float)
    return math.degrees(math.atan2(-z, math.hypot(x, y)))


def obstacle_points_frd(boxes, vehicle_position_ned_m, T_body_ned, min_distance_m: float, max_distance_m: float,
                        dt_s: float = 0.0, limit: int = MAX_OBSTACLES_3D, off_middle_layer: bool = False) -> list:
    """[(obstacle_id, xyz_frd_m)] of the tracks nearer than ``max_distance_m``, nearest first, at most ``limit``;
    a point nearer than ``min_distance_m`` is moved out to it along its direction (as OBSTACLE_DISTANCE reports
    nearer obstacles at min_distance). Ids are the track ids modulo 65535 (65535 means "unknown").
    ``off_middle_layer``: only points at least ``MIDDLE_LAYER_HALF_DEG`` above or below the body's horizontal plane
    (ArduPilot's middle layer is OBSTACLE_DISTANCE's when both are sent)."""
    out = []
    for b in boxes:
        p = nearest_point_frd(b, vehicle_position_ned_m, T_body_ned, dt_s)
        d = float(np.linalg.norm(p))
        if d > max_distance_m or (off_middle_layer and abs(elevation_deg(p)) < MIDDLE_LAYER_HALF_DEG):
            continue
        if d < min_distance_m:
            p = p * (min_distance_m / d) if d > 0 else np.array([min_distance_m, 0.0, 0.0])
        out.append((d, b.id % NO_OBSTACLE_ID, p))
    out.sort(key=lambda x: x[0])
    return [(i, p) for _, i, p in out[:limit]]


def _check_range_m(min_distance_m, max_distance_m):
    if not (math.isfinite(min_distance_m) and math.isfinite(max_distance_m) and 0 < min_distance_m < max_distance_m):
        raise InputError(f"OBSTACLE_DISTANCE_3D: need 0 < min_distance_m < max_distance_m, got {min_distance_m}, "
                         f"{max_distance_m}")


def obstacle_distance_3d_message(mav, obstacle_id: int, xyz_frd_m, time_boot_ms: int, min_distance_m: float,
                                 max_distance_m: float, sensor_type: int = MAV_DISTANCE_SENSOR_UNKNOWN):
    """The pymavlink OBSTACLE_DISTANCE_3D (x, y, z in metres, body FRD) encoded by ``mav``."""
    _check_range_m(min_distance_m, max_distance_m)
    x, y, z = (float(v) for v in np.asarray(xyz_frd_m, float).reshape(3))
    if not all(math.isfinite(v) for v in (x, y, z)):
        raise InputError(f"OBSTACLE_DISTANCE_3D: point must be finite, got {(x, y, z)}")
    if not 0 <= int(obstacle_id) <= NO_OBSTACLE_ID:
        raise InputError(f"OBSTACLE_DISTANCE_3D: obstacle_id {obstacle_id} outside 0..65535")
    return mav.obstacle_distance_3d_encode(
        time_boot_ms=int(time_boot_ms) & 0xFFFFFFFF, sensor_type=int(sensor_type), frame=MAV_FRAME_BODY_FRD,
        obstacle_id=int(obstacle_id), x=x, y=y, z=z, min_distance=float(min_distance_m),
        max_distance=float(max_distance_m))


def end_3d_message(mav, time_boot_ms: int, min_distance_m: float, max_distance_m: float,
                   sensor_type: int = MAV_DISTANCE_SENSOR_UNKNOWN):
    """The end of a cycle (and, alone, "no tracked obstacle"): a point 1 m beyond ``max_distance`` ahead with id
    65535 and its own ``time_boot_ms``. ArduPilot files the messages gathered before it into its boundary, counts it
    as data (the sensor stays healthy) and drops its point (farther than max_distance)."""
    return obstacle_distance_3d_message(mav, NO_OBSTACLE_ID, (max_distance_m + 1.0, 0.0, 0.0), time_boot_ms,
                                        min_distance_m, max_distance_m, sensor_type)


def encode_obstacle_distance_3d(obstacle_id: int, xyz_frd_m, time_boot_ms: int, min_distance_m: float,
                                max_distance_m: float, *, system_id: int = 1,
                                component_id: int = COMPANION_COMPONENT_ID, seq: int = 0,
                                sensor_type: int = MAV_DISTANCE_SENSOR_UNKNOWN) -> bytes:
    """Wire bytes of one OBSTACLE_DISTANCE_3D (MAVLink 2, ardupilotmega dialect)."""
    mu = mavutil()
    mav = mu.mavlink.MAVLink(None, srcSystem=system_id, srcComponent=component_id)
    mav.seq = seq & 0xFF
    return bytes(obstacle_distance_3d_message(mav, obstacle_id, xyz_frd_m, time_boot_ms, min_distance_m,
                                              max_distance_m, sensor_type).pack(mav))


def _next_due(prev: float, period: float, now: float) -> float:
    """Keep a steady cadence; after a stall (or at start) restart it from now instead of bursting."""
    nxt = prev + period
    return nxt if nxt > now else now + period


class ObstacleDistanceSender:
    """Steady OBSTACLE_DISTANCE + HEARTBEAT on one pymavlink connection (see the module docstring)."""

    def __init__(self, connection: str, *, system_id: int = 1, component_id: int = COMPANION_COMPONENT_ID,
                 rate_hz: float = 10.0, heartbeat_hz: float = 1.0, stale_s: float = DEFAULT_STALE_S,
                 sensor_type: int = MAV_DISTANCE_SENSOR_UNKNOWN, clock: Callable[[], float] = time.monotonic,
                 wall_us: Callable[[], int] = lambda: time.time_ns() // 1000, conn=None,
                 messages: str = "obstacle_distance"):
        if messages not in MESSAGES:
            raise InputError(f"MAVLink output messages {messages!r}: expected one of {', '.join(MESSAGES)}")
        self.send_2d, self.send_3d = messages != "obstacle_distance_3d", messages != "obstacle_distance"
        if self.send_3d and not hasattr(mavutil().mavlink.MAVLink, "obstacle_distance_3d_encode"):
            raise InputError("OBSTACLE_DISTANCE_3D needs pymavlink's ardupilotmega (or all) dialect; MAVLINK_DIALECT "
                             f"is {os.environ.get('MAVLINK_DIALECT')!r}")
        if not (rate_hz >= 2.0):
            raise InputError(f"OBSTACLE_DISTANCE rate {rate_hz} Hz: the autopilots time out at 0.5 s; send >= 2 Hz")
        if not (0 < stale_s <= 5.0):
            raise InputError(f"stale_s must be in (0, 5] s, got {stale_s}")
        if not (1 <= system_id <= 255 and 1 <= component_id <= 255):
            raise InputError(f"MAVLink ids must be 1..255, got system {system_id} component {component_id}")
        self.connection, self.rate_hz, self.heartbeat_hz, self.stale_s = connection, rate_hz, heartbeat_hz, stale_s
        self.system_id, self.component_id, self.sensor_type = system_id, component_id, sensor_type
        self._clock, self._wall_us = clock, wall_us
        self._lock = threading.Lock()
        self._latest: dict = {}                 # source -> (sectors, stamp_us, received at clock())
        self._flushed = True                    # nothing to flush before the first sectors
        self._tracks = None                     # (boxes, stamp_us, position_ned_m, T_body_ned, received at clock())
        self._t0 = clock()                      # time_boot_ms counts from here
        self._next_send = self._next_hb = 0.0
        self.counters = {"od_sent_fresh": 0, "od_sent_flush": 0, "heartbeats_sent": 0, "send_errors": 0,
                         "encode_errors": 0}
        if self.send_3d:
            self.counters.update(od3d_sent=0, od3d_sent_end=0)
        self.link = None
        if conn is None:    # opened and re-opened with back-off (eonav.nav.links); a malformed string is an InputError
            from eonav.nav.links import MavLink
            self.link = MavLink(connection, what="MAVLink output", source_system=system_id,
                                source_component=component_id, clock=clock)
        self.conn = conn

    def update(self, sectors: Sectors, stamp_us: int, source: str = "") -> None:
        """New sectors of one ``source`` (a camera) measured at ``stamp_us`` (UNIX µs of the frame capture)."""
        check_sectors(sectors)
        with self._lock:
            self._latest[source] = (sectors, int(stamp_us), self._clock())

    def update_tracks(self, tracks, stamp_us: int, position_ned_m, T_body_ned, min_distance_m: float,
                      max_distance_m: float) -> None:
        """The confirmed tracks (entries of the obstacle-track message's ``tracks``) at ``stamp_us`` (UNIX µs), to be
        sent in body FRD of the pose (``position_ned_m``, ``T_body_ned``: the vehicle now), with the sensor's range
        (as the sectors' min / max distance)."""
        _check_range_m(min_distance_m, max_distance_m)
        boxes = [TrackBox.from_track_msg(t) for t in tracks]
        pos, T = np.asarray(position_ned_m, float).reshape(3), np.asarray(T_body_ned, float).reshape(3, 3)
        with self._lock:
            self._tracks = (boxes, int(stamp_us), pos, T, float(min_distance_m), float(max_distance_m),
                            self._clock())

    def _fresh(self, now: float) -> list:
        return [v for v in self._latest.values() if now - v[2] <= self.stale_s]

    def is_fresh(self) -> bool:
        with self._lock:
            return bool(self._fresh(self._clock()))

    def _send(self, fn, counter):
        try:
            fn()
            self.counters[counter] += 1
        except OSError as e:
            self.counters["send_errors"] += 1
            log.warning("MAVLink send on %s failed: %s", self.connection, e)
            if self.link is not None:
                self.link.mark_lost(self.conn, e)
        except (ValueError, OverflowError, struct.error) as e:    # a message that cannot be packed (a value outside
            self.counters["encode_errors"] += 1                     # its field): that one is skipped, the link and
            log.error("MAVLink %s not sent: %s", counter, e)        # the next messages are fine

    def link_status(self) -> tuple:
        """(state, detail) of the output link: ``up``, ``silent`` (open, the autopilot not heard) or ``down``."""
        return self.link.status() if self.link is not None else ("up", "")

    def tick(self) -> float:
        """Send whatever is due now; return the seconds until the next thing is due."""
        mu = mavutil()
        now = self._clock()
        if self.link is not None:
            for _ in range(200):            # read what the autopilot sends: its HEARTBEAT says the link is up
                if self.link.recv(0) is None:
                    break
            self.conn = self.link.conn
            if self.conn is None:           # not up yet: nothing to send on; the link retries with back-off
                return 0.1
        if now >= self._next_hb:
            self._send(lambda: self.conn.mav.heartbeat_send(mu.mavlink.MAV_TYPE_ONBOARD_CONTROLLER,
                                                            mu.mavlink.MAV_AUTOPILOT_INVALID, 0, 0, 0),
                       "heartbeats_sent")
            self._next_hb = _next_due(self._next_hb, 1.0 / self.heartbeat_hz, now)
        if now >= self._next_send:
            with self._lock:
                fresh = self._fresh(now)
                last = next(iter(self._latest.values()), None)
                tracks = self._tracks
            if self.send_2d and fresh:
                merged = merge_sectors([f[0] for f in fresh])
                stamp_us = min(f[1] for f in fresh)           # the oldest capture the picture holds
                self._send(lambda: self.conn.mav.send(
                    obstacle_distance_message(self.conn.mav, merged, stamp_us, self.sensor_type)), "od_sent_fresh")
                self._flushed = False
            elif self.send_2d and not self._flushed and last is not None:      # stalled: clear the autopilot's sectors once, then silence
                self._send(lambda: self.conn.mav.send(
                    obstacle_distance_message(self.conn.mav, Sectors.unknown(last[0]), self._wall_us(),
                                              self.sensor_type)), "od_sent_flush")
                self._flushed = True
            if self.send_3d:                  # after OBSTACLE_DISTANCE, which resets ArduPilot's whole boundary
                self._tick_3d(now, tracks)
            self._next_send = _next_due(self._next_send, 1.0 / self.rate_hz, now)
        return max(0.0, min(self._next_hb, self._next_send) - self._clock())

    def _tick_3d(self, now: float, tracks) -> None:
        """One cycle of OBSTACLE_DISTANCE_3D while the tracks are fresh: a message per track and the end message;
        nothing once they are stale (ArduPilot then times out, as for OBSTACLE_DISTANCE)."""
        if tracks is None:
            return
        boxes, stamp_us, pos, T, lo, hi, received = tracks
        if now - received > self.stale_s:
            return
        boot_ms = 2 * int((now - self._t0) * 500) + 2         # even; the end message's T + 1 is odd: never reused
        mav = self.conn.mav
        dt_s = max(0.0, (self._wall_us() - stamp_us) * 1e-6)
        for oid, p in obstacle_points_frd(boxes, pos, T, lo, hi, dt_s, off_middle_layer=self.send_2d):
            self._send(lambda: mav.send(obstacle_distance_3d_message(mav, oid, p, boot_ms, lo, hi, self.sensor_type)),
                       "od3d_sent")
        self._send(lambda: mav.send(end_3d_message(mav, boot_ms + 1, lo, hi, self.sensor_type)), "od3d_sent_end")

    def run(self, stop_event: threading.Event) -> None:
        while not stop_event.is_set():
            stop_event.wait(self.tick())

    def close(self) -> None:
        if self.link is not None:
            self.link.close()
            return
        try:
            self.conn.close()
        except Exception:  # closing a half-open link must not mask the real shutdown path
            pass
