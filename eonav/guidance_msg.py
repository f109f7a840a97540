"""The obstacle-track topic, guidance's input: message layout, encode / decode, and when to publish.

One msgpack map per message, as every eonav message (``eonav.schema``): ``kind`` "obstacle_tracks", ``v`` 1, units
and frames in the field names, NaN for unknown, new fields appended with defaults. ``FIELDS`` is the top level in
``eonav.schema.FIELDS`` form (``schema.FIELDS[KIND] = FIELDS`` registers it there); the tracks and the nearest threat
are lists / maps whose fields this module checks (``TRACK_FIELDS``, ``THREAT_FIELDS``). Every field's unit, frame,
sign and rate: docs/guidance.md.

``GuidancePublisher`` decides what to publish and when (a message on every tracker update and on a fixed timer
grid), from the tracker and the latest vehicle state; the service only calls it and puts the bytes.

No zenoh import here: the message is pure data.
"""
from __future__ import annotations

import math

import msgpack
import numpy as np

from . import InputError
from .schema import REQUIRED, SCHEMA_VERSION, SUPPORTED_VERSIONS, SchemaError, _check
from .geometry import quat_wxyz_from_rotation
from .tracking import ConeConfig, Ownship, Tracker, assess, nearest_threat, ownship_at

KIND = "obstacle_tracks"
NAN3 = [math.nan] * 3
NAN33 = [[math.nan] * 3 for _ in range(3)]
STATUSES = ("ok", "stale", "no_map")         # newest map: fresh, older than stale_after_s, none yet
TRIGGERS = ("map", "timer")
TRACK_STATES = ("confirmed", "coasting")     # tentative tracks are not published (only counted)

FIELDS = {
    "seq": ("int", REQUIRED),                 # per publisher, +1 per message
    "stamp_us": ("int", REQUIRED),            # the time every track and bearing refers to (tracks predicted to it)
    "trigger": ("str", REQUIRED),             # "map": right after a tracker update; "timer": the fixed-rate tick
    "status": ("str", REQUIRED),              # STATUSES
    "map_stamp_us": ("int", REQUIRED),        # capture stamp of the newest range map the tracker used (-1: none)
    "map_age_s": ("float", REQUIRED),         # (stamp_us - map_stamp_us) / 1e6; inf when there is none
    "stale_after_s": ("float", REQUIRED),
    "nav_stamp_us": ("int", -1),              # stamp of the vehicle state used (-1: the map's capture pose)
    "position_ned_m": ("vec3", REQUIRED),     # vehicle origin
    "q_wxyz": ("vec4", REQUIRED),             # vehicle attitude, body FRD -> NED (as nav_state)
    "velocity_ned_mps": ("vec3", NAN3),       # vehicle velocity (NaN: unknown, then no collision cone)
    "vehicle_radius_m": ("float", REQUIRED),  # the collision cone's definition (docs/guidance.md)
    "cone_k_sigma": ("float", REQUIRED),
    "horizon_s": ("float", REQUIRED),
    "tracks": ("list", REQUIRED),             # TRACK_FIELDS maps, confirmed and coasting tracks only
    "n_tentative": ("int", 0),
    "nearest_threat": ("dict", None),         # THREAT_FIELDS map, absent when nothing is in the cone
}

# nested fields: (type, required); "mat3" is a 3 x 3 list of lists, "bool" a msgpack boolean
TRACK_FIELDS = {
    "id": "int", "state": "str",
    "position_ned_m": "vec3", "position_cov_ned_m2": "mat3",
    "velocity_ned_mps": "vec3", "velocity_cov_ned_m2_per_s2": "mat3", "moving": "bool",
    "distance_m": "float", "surface_distance_m": "float", "azimuth_frd_rad": "float", "elevation_frd_rad": "float",
    "extent_ned_m": "vec3", "pixel_count": "int", "confidence": "float", "measurement_confidence": "float",
    "age_s": "float", "time_since_update_s": "float", "hits": "int", "misses": "int", "camera_id": "str",
    "in_cone": "bool", "time_to_contact_s": "float", "closing_speed_mps": "float",
}
THREAT_FIELDS = {
    "id": "int", "time_to_contact_s": "float", "distance_m": "float", "surface_distance_m": "float",
    "azimuth_frd_rad": "float", "elevation_frd_rad": "float", "closing_speed_mps": "float",
    "position_ned_m": "vec3",
}


def _nested(where: str, d, spec: dict) -> dict:
    if not isinstance(d, dict):
        raise SchemaError(f"{where}: expected a map, got {type(d).__name__}")
    out = {}
    for name, typ in spec.items():
        if name not in d:
            raise SchemaError(f"{where}.{name}: missing required field")
        val = d[name]
        if typ == "bool":
            if not isinstance(val, bool):
                raise SchemaError(f"{where}.{name}: expected true or false, got {type(val).__name__} {val!r}")
            out[name] = val
        elif typ == "mat3":
            a = np.asarray(val, dtype=object) if isinstance(val, (list, tuple)) else None
            if (a is None or a.shape != (3, 3)
                    or not all(isinstance(x, (int, float)) and not isinstance(x, bool) for x in a.ravel())):
                raise SchemaError(f"{where}.{name}: expected a 3 x 3 list of numbers")
            out[name] = a.astype(float)
        else:
            out[name] = _check(where, name, typ, val)
    return out


def validate(msg: dict) -> dict:
    """A message map (as unpacked) checked field by field; returns it with vectors / matrices as float arrays.
    Raises SchemaError naming the first bad field."""
    if not isinstance(msg, dict):
        raise SchemaError(f"{KIND}: expected a map, got {type(msg).__name__}")
    if msg.get("kind") != KIND:
        raise SchemaError(f"expected a {KIND} message, got {msg.get('kind')!r}")
    if msg.get("v") not in SUPPORTED_VERSIONS:
        raise SchemaError(f"{KIND}: unsupported schema version {msg.get('v')!r}; this build reads "
                          f"{SUPPORTED_VERSIONS}")
    out = {"kind": KIND, "v": msg["v"]}
    for name, (typ, default) in FIELDS.items():
        if name in msg and msg[name] is not None:
            out[name] = _check(KIND, name, typ, msg[name])
        elif default is REQUIRED:
            raise SchemaError(f"{KIND}.{name}: missing required field")
        else:
            out[name] = np.asarray(default, float) if typ in ("vec3", "vec4") else default
    if out["status"] not in STATUSES:
        raise SchemaError(f"{KIND}.status: expected one of {STATUSES}, got {out['status']!r}")
    if out["trigger"] not in TRIGGERS:
        raise SchemaError(f"{KIND}.trigger: expected one of {TRIGGERS}, got {out['trigger']!r}")
    if not (out["map_age_s"] >= 0 or math.isinf(out["map_age_s"])):
        raise SchemaError(f"{KIND}.map_age_s: expected >= 0 s, got {out['map_age_s']!r}")
    tracks = []
    for i, t in enumerate(out["tracks"]):
        tr = _nested(f"{KIND}.tracks[{i}]", t, TRACK_FIELDS)
        if tr["state"] not in TRACK_STATES:
            raise SchemaError(f"{KIND}.tracks[{i}].state: expected one of {TRACK_STATES}, got {tr['state']!r}")
        for name in ("position_ned_m", "position_cov_ned_m2", "velocity_ned_mps", "velocity_cov_ned_m2_per_s2"):
            if not np.all(np.isfinite(tr[name])):
                raise SchemaError(f"{KIND}.tracks[{i}].{name}: expected finite numbers")
        tracks.append(tr)
    ids = [t["id"] for t in tracks]
    if len(set(ids)) != len(ids):
        raise SchemaError(f"{KIND}.tracks: ids must be unique, got {ids}")
    out["tracks"] = tracks
    if out["nearest_threat"] is not None:
        th = _nested(f"{KIND}.nearest_threat", out["nearest_threat"], THREAT_FIELDS)
        if th["id"] not in ids:
            raise SchemaError(f"{KIND}.nearest_threat.id {th['id']} is not one of the tracks {ids}")
        out["nearest_threat"] = th
    return out


def _plain(v):
    if isinstance(v, np.ndarray):
        return v.tolist()
    if isinstance(v, np.bool_):
        return bool(v)
    if isinstance(v, np.generic):
        return v.item()
    if isinstance(v, dict):
        return {k: _plain(x) for k, x in v.items()}
    if isinstance(v, (list, tuple)):
        return [_plain(x) for x in v]
    return v


def encode(msg: dict) -> bytes:
    """A message map (``build`` output, or by hand with every required field) -> msgpack bytes; validated first,
    so a bad message is a SchemaError here, not at the reader."""
    body = _plain({k: v for k, v in msg.items() if v is not None})
    body.setdefault("kind", KIND)
    body.setdefault("v", SCHEMA_VERSION)
    unknown = set(body) - set(FIELDS) - {"kind", "v"}
    if unknown:
        raise SchemaError(f"{KIND}: unknown field(s) {sorted(unknown)}")
    validate(body)
    return msgpack.packb(body, use_bin_type=True)


def decode(payload) -> dict:
    """msgpack bytes (or an already unpacked map) -> validated message (see ``validate``). Raises SchemaError."""
    if isinstance(payload, dict):
        return validate(payload)
    if not isinstance(payload, (bytes, bytearray, memoryview)):
        raise SchemaError(f"payload must be bytes, got {type(payload).__name__}")
    try:
        doc = msgpack.unpackb(payload, raw=False, strict_map_key=True)
    except Exception as e:  # msgpack raises several unrelated types on garbage
        raise SchemaError(f"payload is not msgpack ({type(e).__name__}: {e})") from None
    return validate(doc)


def _threat(tv) -> dict:
    return {"id": tv.track.id, "time_to_contact_s": tv.time_to_contact_s, "distance_m": tv.distance_m,
            "surface_distance_m": tv.surface_distance_m, "azimuth_frd_rad": tv.azimuth_frd_rad,
            "elevation_frd_rad": tv.elevation_frd_rad, "closing_speed_mps": tv.closing_speed_mps,
            "position_ned_m": tv.position_ned_m}


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
            "closing_speed_mps": tv.closing_speed_mps})
    return {"kind": KIND, "v": SCHEMA_VERSION, "seq": int(seq), "stamp_us": now, "trigger": trigger,
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
