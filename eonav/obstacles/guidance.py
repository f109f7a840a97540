"""What the obstacle service publishes on the obstacle-track topic, and when (docs/guidance.md).

``build`` makes the message map (``eonav.bus.guidance_msg`` layout) from the tracker's live tracks predicted to a
time and assessed from the vehicle state; ``GuidancePublisher`` calls it right after every tracker update and on a
fixed timer grid. Pure: no clock of its own, no transport.
"""
from __future__ import annotations

import math

from eonav import InputError
from eonav.geometry.frames import quat_wxyz_from_rotation
from eonav.obstacles.tracking import ConeConfig, Ownship, Tracker, assess, nearest_threat, ownship_at

TRIGGERS = ("map", "timer")


def _threat(tv) -> dict:
    return {"id": tv.track.id, "time_to_contact_s": tv.time_to_contact_s, "distance_m": tv.distance_m,
            "surface_distance_m": tv.surface_distance_m, "azimuth_frd_rad": tv.azimuth_frd_rad,
            "elevation_frd_rad": tv.elevation_frd_rad, "closing_speed_mps": tv.closing_speed_mps,
            "position_ned_m": tv.position_ned_m, "expected_time_to_contact_s": tv.expected_time_to_contact_s}


def build(tracker: Tracker, own: Ownship, now_us: int, *, seq: int, trigger: str, stale_after_s: float,
          cone: ConeConfig = ConeConfig()) -> dict:
    """The message at ``now_us``: the tracker's live tracks predicted to it and assessed from the vehicle state
    ``own`` (its position carried to ``now_us`` by its velocity, ``eonav.tracking.ownship_at``)."""
    if trigger not in TRIGGERS:
        raise InputError(f"trigger {trigger!r}: expected one of {TRIGGERS}")
    if not isinstance(own, Ownship):
        raise InputError(f"guidance message: expected an Ownship, got {type(own).__name__}")
    now = int(now_us)
    views = assess(tracker.snapshot(now), own, now, cone, tracker.cfg)
    threat = nearest_threat(views, confirmed_only=True)
    last = tracker.last_stamp_us
    if last is None:
        status, map_stamp, age = "no_map", -1, math.inf
    else:
        map_stamp, age = int(last), max(0, now - last) * 1e-6
        status = "ok" if age <= stale_after_s else "stale"
    tracks = []
    for tv in views:
        t = tv.track
        if not t.confirmed:
            continue
        tracks.append({
            "id": t.id, "state": t.state, "position_ned_m": tv.position_ned_m, "position_cov_ned_m2": tv.P[:3, :3],
            "velocity_ned_mps": tv.velocity_ned_mps, "velocity_cov_ned_m2_per_s2": tv.P[3:, 3:],
            "moving": bool(tv.moving), "distance_m": tv.distance_m, "surface_distance_m": tv.surface_distance_m,
            "azimuth_frd_rad": tv.azimuth_frd_rad, "elevation_frd_rad": tv.elevation_frd_rad,
            "extent_ned_m": t.extent_ned_m, "pixel_count": int(t.pixel_count), "confidence": t.confidence,
            "measurement_confidence": float(t.measurement_confidence), "age_s": tv.age_s,
            "time_since_update_s": tv.time_since_update_s, "hits": int(t.hits), "misses": int(t.misses),
            "camera_id": t.camera_id, "in_cone": bool(tv.in_cone), "time_to_contact_s": tv.time_to_contact_s,
            "closing_speed_mps": tv.closing_speed_mps, "expected_time_to_contact_s": tv.expected_time_to_contact_s})
    return {"seq": int(seq), "stamp_us": now, "trigger": trigger,
            "status": status, "map_stamp_us": map_stamp, "map_age_s": float(age),
            "stale_after_s": float(stale_after_s), "nav_stamp_us": int(own.stamp_us),
            "position_ned_m": ownship_at(own, now), "q_wxyz": quat_wxyz_from_rotation(own.T_body_ned.T),
            "velocity_ned_mps": own.velocity_ned_mps, "vehicle_radius_m": cone.vehicle_radius_m,
            "cone_k_sigma": cone.k_sigma, "horizon_s": cone.horizon_s, "tracks": tracks,
            "n_tentative": sum(1 for tv in views if not tv.track.confirmed),
            "nearest_threat": None if threat is None else _threat(threat)}


class GuidancePublisher:
    """What the obstacle service publishes on the track topic, and when: a message right after every tracker update
    (``on_map``) and one at every tick of a fixed grid of period 1 / ``rate_hz`` (``on_tick``), both built from the
    tracker and the caller's latest vehicle state at the caller's ``now_us``. Keeps no clock of its own."""

    def __init__(self, tracker: Tracker, rate_hz: float = 10.0, stale_after_s: float = 0.5,
                 cone: ConeConfig = ConeConfig()):
        if not (isinstance(rate_hz, (int, float)) and math.isfinite(rate_hz) and rate_hz > 0):
            raise InputError(f"guidance publisher: rate_hz must be > 0, got {rate_hz!r}")
        if not (isinstance(stale_after_s, (int, float)) and math.isfinite(stale_after_s) and stale_after_s > 0):
            raise InputError(f"guidance publisher: stale_after_s must be > 0, got {stale_after_s!r}")
        self.tracker, self.cone = tracker, cone
        self.period_us = int(round(1e6 / rate_hz))
        self.stale_after_s = float(stale_after_s)
        self.seq = 0
        self.next_tick_us: int | None = None

    def _build(self, now_us: int, own: Ownship, trigger: str) -> dict:
        msg = build(self.tracker, own, now_us, seq=self.seq, trigger=trigger, stale_after_s=self.stale_after_s,
                    cone=self.cone)
        self.seq += 1
        return msg

    def on_map(self, now_us: int, own: Ownship) -> dict:
        """Call right after ``tracker.update``: the message to publish now."""
        return self._build(now_us, own, "map")

    def on_tick(self, now_us: int, own: Ownship) -> dict | None:
        """Call often (at least at ``rate_hz``): the timer message when a grid tick has come, else None. The grid
        starts at the first call; ticks missed by a late caller are not made up (one message, next tick on the
        grid)."""
        now_us = int(now_us)
        if self.next_tick_us is None:
            self.next_tick_us = now_us
        if now_us < self.next_tick_us:
            return None
        behind = (now_us - self.next_tick_us) // self.period_us
        self.next_tick_us += (behind + 1) * self.period_us
        return self._build(now_us, own, "timer")

    def wait_s(self, now_us: int) -> float:
        """Seconds until the next tick is due (0 when due or never called)."""
        if self.next_tick_us is None:
            return 0.0
        return max(0.0, (self.next_tick_us - int(now_us)) * 1e-6)
