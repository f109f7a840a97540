"""The obstacle-track topic, guidance's input: message layout, encode / decode.

One msgpack map per message, as every eonav message (``eonav.bus.schema``): ``kind`` "obstacle_tracks", ``v`` 1, units
and frames in the field names, NaN for unknown, new fields appended with defaults. ``FIELDS`` is the top level in
``eonav.schema.FIELDS`` form (``schema.FIELDS[KIND] = FIELDS`` registers it there); the tracks and the nearest threat
are lists / maps whose fields this module checks (``TRACK_FIELDS``, ``THREAT_FIELDS``). Every field's unit, frame,
sign and rate: docs/guidance.md.

What to publish and when is ``eonav.obstacles.guidance.GuidancePublisher``; the service puts ``encode`` of it.

No zenoh import here: the message is pure data.
"""
from __future__ import annotations

import math

import msgpack
import numpy as np

from eonav.bus.schema import REQUIRED, SCHEMA_VERSION, SUPPORTED_VERSIONS, SchemaError, _check, _plain

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
# nested fields appended after version 1's first release: (type, default when absent)
TRACK_OPTIONAL = {"expected_time_to_contact_s": ("float", math.nan)}
THREAT_OPTIONAL = {"expected_time_to_contact_s": ("float", math.nan)}


def _nested(where: str, d, spec: dict, optional: dict | None = None) -> dict:
    if not isinstance(d, dict):
        raise SchemaError(f"{where}: expected a map, got {type(d).__name__}")
    out = {}
    for name, (typ, default) in (optional or {}).items():
        out[name] = _check(where, name, typ, d[name]) if d.get(name) is not None else default
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
    if not out["map_age_s"] >= 0:                 # +inf (no map yet) passes; -inf and NaN do not
        raise SchemaError(f"{KIND}.map_age_s: expected >= 0 s, got {out['map_age_s']!r}")
    tracks = []
    for i, t in enumerate(out["tracks"]):
        tr = _nested(f"{KIND}.tracks[{i}]", t, TRACK_FIELDS, TRACK_OPTIONAL)
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
        th = _nested(f"{KIND}.nearest_threat", out["nearest_threat"], THREAT_FIELDS, THREAT_OPTIONAL)
        if th["id"] not in ids:
            raise SchemaError(f"{KIND}.nearest_threat.id {th['id']} is not one of the tracks {ids}")
        out["nearest_threat"] = th
    return out


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
