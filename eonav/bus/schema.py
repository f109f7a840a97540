"""Every message on the bus: msgpack maps with a kind, a schema version, units and frames in field names.

    {"kind": "frame", "v": 1, "camera_id": "nose", "seq": 12, "stamp_us": ..., "image": {array}, ...}

Arrays travel as ``{"dtype": "float32", "shape": [h, w], "data": <raw bytes>}`` (C order, little endian).
``range_map`` sends ``range_m`` as float32, ``confidence`` and ``inv_range_std_per_m`` as float16 (3 significant
digits: plenty for a gate; half the bytes) and ``flags`` as uint8 (``eonav.ranging.rangemap``: VALID = measured, FILLED =
inferred from the measured pixels around, both with a finite ``range_m``); readers must not assume float32 (numpy promotes
float16 in arithmetic; ``np.asarray(a, np.float32)`` where a float32 copy is wanted). float16 was added to the
allowed dtypes without a version bump: an older build rejects such a message (counted decode error), it never
misreads it.
``decode`` rejects anything malformed or hostile (wrong kind, unknown version, missing or mistyped
field, array whose byte count does not match dtype x shape, absurd sizes) with ``SchemaError`` naming
the problem; services count those and keep running. New fields are appended with defaults, so a
reader of version 1 accepts version-1 messages carrying extra fields.

No zenoh import here: the schema is pure data.
"""
from __future__ import annotations

import math

import msgpack
import numpy as np

from eonav import InputError

SCHEMA_VERSION = 1
SUPPORTED_VERSIONS = (1,)
MAX_ARRAY_ELEMENTS = 64 * 1024 * 1024
ARRAY_DTYPES = ("uint8", "uint16", "int16", "int32", "uint32", "float16", "float32", "float64")


class SchemaError(InputError):
    """A bus payload that is not a valid eonav message."""


# field -> (type, default). A default of REQUIRED means the field must be present.
REQUIRED = object()
NAN3 = [math.nan] * 3
NAN4 = [math.nan] * 4

_CAMERA_FIELDS = {"camera": ("dict", REQUIRED)}   # width, height, fx, fy, cx, cy, l_m, eps_deg

FIELDS = {
    "frame": {
        "camera_id": ("str", REQUIRED), "seq": ("int", REQUIRED), "stamp_us": ("int", REQUIRED),
        "stamp_source": ("str", "host"), "encoding": ("str", "mono8"), "image": ("array", REQUIRED),
        "source_pts_us": ("int", -1),
    },
    "nav_state": {
        "stamp_us": ("int", REQUIRED), "autopilot_time_us": ("int", -1),
        "position_ned_m": ("vec3", NAN3), "q_wxyz": ("vec4", NAN4), "velocity_ned_mps": ("vec3", NAN3),
        "rates_frd_radps": ("vec3", NAN3), "source": ("str", ""), "clock_offset_us": ("int", 0),
        "system_id": ("int", 1),
    },
    "clock_offset": {
        "stamp_us": ("int", REQUIRED), "offset_us": ("int", REQUIRED), "rtt_us": ("int", -1),
        "method": ("str", REQUIRED), "samples": ("int", 0),
    },
    "posed_frame": {
        "camera_id": ("str", REQUIRED), "seq": ("int", REQUIRED), "stamp_us": ("int", REQUIRED),
        "stamp_source": ("str", "host"), "encoding": ("str", "mono8"), "image": ("array", REQUIRED),
        **_CAMERA_FIELDS,
        "position_ned_m": ("vec3", REQUIRED), "q_wxyz": ("vec4", REQUIRED),
        "velocity_ned_mps": ("vec3", NAN3), "nav_gap_us": ("int", 0), "quality_flags": ("int", 0),
    },
    "range_map": {
        "camera_id": ("str", REQUIRED), "seq": ("int", REQUIRED), "stamp_us": ("int", REQUIRED),
        "other_camera_id": ("str", ""), "other_seq": ("int", -1), "other_stamp_us": ("int", -1),
        "method": ("str", REQUIRED), "range_m": ("array", REQUIRED), "confidence": ("array", REQUIRED),
        "inv_range_std_per_m": ("array", None), "flags": ("array", None),
        **_CAMERA_FIELDS,
        "position_ned_m": ("vec3", REQUIRED), "q_wxyz": ("vec4", REQUIRED),
        "baseline_m": ("float", math.nan), "compute_s": ("float", math.nan),
        # appended (v1 readers default them): the locator's working scale (0.5: ranges computed on half-resolution
        # images) and its own per-message overhead
        "scale": ("float", 1.0), "overhead_s": ("float", math.nan),
        # appended: the size of the frame the map was ranged from. The arrays are always on the grid of ``camera``
        # (H x W = camera height x width); 0 (the default, and what older locators send) means that grid IS the
        # frame's; a map published at the locate scale (services/locator.py --publish-grid locate) carries the
        # scaled camera (eonav.camera.scaled_camera) and the frame's size here, so readers can count in frame pixels
        "frame_width": ("int", 0), "frame_height": ("int", 0),
    },
    "obstacle_list": {
        "stamp_us": ("int", REQUIRED), "camera_id": ("str", ""), "obstacles": ("list", REQUIRED),
        "sectors": ("dict", None), "position_ned_m": ("vec3", NAN3), "q_wxyz": ("vec4", NAN4),
    },
    "health": {
        "service": ("str", REQUIRED), "stamp_us": ("int", REQUIRED), "state": ("str", REQUIRED),
        "counters": ("dict", {}), "rates_hz": ("dict", {}), "latency_ms": ("dict", {}), "detail": ("str", ""),
        "pid": ("int", -1),
    },
}
KINDS = tuple(FIELDS)


def pack_array(a: np.ndarray) -> dict:
    a = np.ascontiguousarray(a)
    if a.dtype.name not in ARRAY_DTYPES:
        raise SchemaError(f"array dtype {a.dtype.name} not allowed; expected one of {ARRAY_DTYPES}")
    if a.dtype.byteorder == ">":
        a = a.astype(a.dtype.newbyteorder("<"))
    return {"dtype": a.dtype.name, "shape": list(a.shape), "data": a.tobytes()}


def unpack_array(d, name: str) -> np.ndarray:
    if not isinstance(d, dict) or set(d) < {"dtype", "shape", "data"}:
        raise SchemaError(f"field {name}: expected an array map with dtype, shape, data")
    dtype, shape, data = d["dtype"], d["shape"], d["data"]
    if dtype not in ARRAY_DTYPES:
        raise SchemaError(f"field {name}: dtype {dtype!r} not allowed; expected one of {ARRAY_DTYPES}")
    if (not isinstance(shape, (list, tuple)) or not 1 <= len(shape) <= 4
            or not all(isinstance(s, int) and not isinstance(s, bool) and 0 <= s for s in shape)):
        raise SchemaError(f"field {name}: shape {shape!r} must be 1 to 4 non-negative integers")
    n = math.prod(shape)
    if n > MAX_ARRAY_ELEMENTS:
        raise SchemaError(f"field {name}: {n} elements exceeds the limit {MAX_ARRAY_ELEMENTS}")
    if not isinstance(data, (bytes, bytearray)):
        raise SchemaError(f"field {name}: data must be bytes")
    dt = np.dtype(dtype).newbyteorder("<")
    if len(data) != n * dt.itemsize:
        raise SchemaError(f"field {name}: {len(data)} bytes but dtype {dtype} x shape {list(shape)} "
                          f"needs {n * dt.itemsize}")
    return np.frombuffer(data, dtype=dt).reshape(shape)


def _check(kind: str, name: str, typ: str, val):
    def bad(expected):
        return SchemaError(f"{kind}.{name}: expected {expected}, got {type(val).__name__} {str(val)[:60]!r}")
    if typ == "int":
        if isinstance(val, bool) or not isinstance(val, int):
            raise bad("an integer")
        return val
    if typ == "float":
        if isinstance(val, bool) or not isinstance(val, (int, float)):
            raise bad("a number")
        return float(val)
    if typ == "str":
        if not isinstance(val, str):
            raise bad("a string")
        return val
    if typ in ("vec3", "vec4"):
        n = int(typ[-1])
        if (not isinstance(val, (list, tuple)) or len(val) != n
                or not all(isinstance(x, (int, float)) and not isinstance(x, bool) for x in val)):
            raise bad(f"a list of {n} numbers")
        return np.asarray(val, dtype=float)
    if typ == "dict":
        if not isinstance(val, dict):
            raise bad("a map")
        return val
    if typ == "list":
        if not isinstance(val, (list, tuple)):
            raise bad("a list")
        return list(val)
    if typ == "array":
        return unpack_array(val, f"{kind}.{name}")
    raise AssertionError(typ)


def _plain(v):
    if isinstance(v, np.ndarray):
        return v.tolist()
    if isinstance(v, np.generic):
        return v.item()
    if isinstance(v, dict):
        return {k: _plain(x) for k, x in v.items()}
    if isinstance(v, (list, tuple)):
        return [_plain(x) for x in v]
    return v


def encode(kind: str, **fields) -> bytes:
    """Encode one message of ``kind``. Array fields take numpy arrays; vectors take lists or arrays."""
    if kind not in FIELDS:
        raise SchemaError(f"unknown message kind {kind!r}; expected one of {KINDS}")
    spec = FIELDS[kind]
    out = {"kind": kind, "v": SCHEMA_VERSION}
    for name, (typ, default) in spec.items():
        if name in fields and fields[name] is not None:
            val = fields[name]
        elif default is REQUIRED:
            raise SchemaError(f"{kind}.{name}: missing required field")
        else:
            val = default
        if val is None:
            continue
        if typ == "array":
            out[name] = pack_array(np.asarray(val))
        else:
            out[name] = _plain(val)
            _check(kind, name, typ, out[name])
    extra = set(fields) - set(spec)
    if extra:
        raise SchemaError(f"{kind}: unknown field(s) {sorted(extra)}")
    return msgpack.packb(out, use_bin_type=True)


def decode(payload, expect: str | None = None) -> dict:
    """Decode and validate a payload; returns a dict with arrays as (read-only) numpy arrays and
    vec3/vec4 as float arrays. Raises SchemaError with the reason on anything malformed."""
    if not isinstance(payload, (bytes, bytearray, memoryview)):
        raise SchemaError(f"payload must be bytes, got {type(payload).__name__}")
    try:
        doc = msgpack.unpackb(payload, raw=False, strict_map_key=True, max_bin_len=MAX_ARRAY_ELEMENTS * 8)
    except Exception as e:  # msgpack raises several unrelated types on garbage
        raise SchemaError(f"payload is not msgpack ({type(e).__name__}: {e})") from None
    if not isinstance(doc, dict):
        raise SchemaError("payload is not a msgpack map")
    kind, v = doc.get("kind"), doc.get("v")
    if kind not in FIELDS:
        raise SchemaError(f"unknown message kind {kind!r}")
    if expect is not None and kind != expect:
        raise SchemaError(f"expected a {expect} message, got {kind}")
    if v not in SUPPORTED_VERSIONS:
        raise SchemaError(f"{kind}: unsupported schema version {v!r}; this build reads {SUPPORTED_VERSIONS}")
    out = {"kind": kind, "v": v}
    for name, (typ, default) in FIELDS[kind].items():
        if name in doc:
            out[name] = _check(kind, name, typ, doc[name])
        elif default is REQUIRED:
            raise SchemaError(f"{kind}.{name}: missing required field")
        else:
            out[name] = np.asarray(default, float) if typ in ("vec3", "vec4") else default
    return out


def camera_to_msg(cam) -> dict:
    """A Camera as the 'camera' map of posed_frame / range_map messages."""
    return {"name": cam.name, "width": cam.width, "height": cam.height, "fx": cam.fx, "fy": cam.fy,
            "cx": cam.cx, "cy": cam.cy, "l_m": [float(x) for x in cam.l_body_m],
            "eps_deg": [float(x) for x in np.rad2deg(cam.eps_rad)]}


def camera_from_msg(d: dict):
    """The 'camera' map back to a Camera (validated)."""
    from eonav.io.pairfile import parse_camera
    body = dict(d)
    name = str(body.pop("name", "camera"))
    body["mount"] = {"l_m": body.pop("l_m", [0, 0, 0]), "eps_deg": body.pop("eps_deg", [0, 0, 0])}
    return parse_camera(name, body)
