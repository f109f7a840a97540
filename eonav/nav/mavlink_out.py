"""MAVLink OBSTACLE_DISTANCE out to the autopilot, with pymavlink's own encoder (docs/mavlink.md, docs/autopilot.md).

- ``encode_obstacle_distance(sectors, time_usec)``: the wire bytes of one MAVLink 2 message in the autopilots' own
  layout (``MAV_FRAME_BODY_FRD``, 72 x 5 degrees, ``angle_offset`` 0 = element 0's centre on the nose), from
  component 191; layouts either autopilot misreads are refused (``check_sectors``).
- ``ObstacleDistanceSender``: one pymavlink connection (opened and re-opened with back-off by ``eonav.nav.links``
  while the autopilot is not up; ``link_status()`` for the health) with a companion HEARTBEAT at 1 Hz and OBSTACLE_DISTANCE on a
  fixed timer carrying the merge of every camera's fresh sectors (ArduPilot resets all sectors on each message).
  Once every source is stale it sends ONE all-unknown message and then none until a fresh map arrives: a stall must
  look like a dead sensor (No Data at the autopilot), not like an empty sky. ``tick()`` takes an injected clock.
"""
from __future__ import annotations

import logging
import math
import os
import threading
import time
from typing import Callable

import numpy as np

from eonav import InputError
from eonav.obstacles.detect import N_SECTORS, SECTOR_INCREMENT_DEG, UINT16_MAX, Sectors, merge_sectors

log = logging.getLogger(__name__)

COMPANION_COMPONENT_ID = 191          # MAV_COMP_ID_ONBOARD_COMPUTER
MAV_FRAME_BODY_FRD = 12
MAV_DISTANCE_SENSOR_UNKNOWN = 4

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


def _next_due(prev: float, period: float, now: float) -> float:
    """Keep a steady cadence; after a stall (or at start) restart it from now instead of bursting."""
    nxt = prev + period
    return nxt if nxt > now else now + period


class ObstacleDistanceSender:
    """Steady OBSTACLE_DISTANCE + HEARTBEAT on one pymavlink connection (see the module docstring)."""

    def __init__(self, connection: str, *, system_id: int = 1, component_id: int = COMPANION_COMPONENT_ID,
                 rate_hz: float = 10.0, heartbeat_hz: float = 1.0, stale_s: float = DEFAULT_STALE_S,
                 sensor_type: int = MAV_DISTANCE_SENSOR_UNKNOWN, clock: Callable[[], float] = time.monotonic,
                 wall_us: Callable[[], int] = lambda: time.time_ns() // 1000, conn=None):
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
        self._next_send = self._next_hb = 0.0
        self.counters = {"od_sent_fresh": 0, "od_sent_flush": 0, "heartbeats_sent": 0, "send_errors": 0}
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
            if fresh:
                merged = merge_sectors([f[0] for f in fresh])
                stamp_us = min(f[1] for f in fresh)           # the oldest capture the picture holds
                self._send(lambda: self.conn.mav.send(
                    obstacle_distance_message(self.conn.mav, merged, stamp_us, self.sensor_type)), "od_sent_fresh")
                self._flushed = False
            elif not self._flushed and last is not None:      # stalled: clear the autopilot's sectors once, then silence
                self._send(lambda: self.conn.mav.send(
                    obstacle_distance_message(self.conn.mav, Sectors.unknown(last[0]), self._wall_us(),
                                              self.sensor_type)), "od_sent_flush")
                self._flushed = True
            self._next_send = _next_due(self._next_send, 1.0 / self.rate_hz, now)
        return max(0.0, min(self._next_hb, self._next_send) - self._clock())

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
