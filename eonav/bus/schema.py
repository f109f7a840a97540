"""Every message on the bus: msgpack maps with a kind, a schema version, units and frames in field names.

    {"kind": "frame", "v": 1, "camera_id": "nose", "seq": 12, "stamp_us": ..., "image": {array}, ...}

Arrays travel as ``{"dtype": "float32", "shape": [h, w], "data": <raw bytes>}`` (C order, little endian); a range
map's ``confidence`` and ``inv_range_std_per_m`` are float16, so readers must not assume float32. ``encode`` builds a
message of a kind; ``decode`` rejects anything malformed or hostile with ``SchemaError`` naming the problem
(services count those and keep running). New fields are appended with defaults, so a version-1 reader accepts
version-1 messages with extra fields. The kinds and keys: docs/bus.md. Pure data: no zenoh import.
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
    """A bus payload that is not a valid eonav message. ``reason`` is a short slug for the health counter
    ``rejected.<reason>`` (``msgpack``, ``kind``, ``version``, ``field``, ``array``, ``range``)."""

    def __init__(self, message: str, reason: str = "field"):
        super().__init__(message)
        self.reason = reason


# Plausible ranges of every field (hostile or corrupt values are refused at decode, not deep in a service).
MAX_STAMP_US = 2 ** 62            # stamps and seqs are int64 on every path (msgpack would carry a uint64)
MAX_SEQ = 2 ** 62
MAX_POSITION_M = 1.0e7            # 10 000 km from the local origin
MAX_SPEED_MPS = 1.0e4
MAX_RATE_RADPS = 100.0
MAX_IMAGE_SIDE_PX = 16384
# the age of any stamp the schema accepts: a replayed recording's frames are as old as the recording (the services'
# freshness gates, not the schema, decide what is too old: docs/bus.md, "Staleness")
MAX_AGE_MS = MAX_STAMP_US / 1e3
MAX_DURATION_S = 3600.0           # a map's compute and overhead times
IMAGE_ENCODINGS = {"mono8": (np.uint8, 1), "mono16": (np.uint16, 1), "bgr8": (np.uint8, 3), "rgb8": (np.uint8, 3)}
FLOAT_DTYPES = ("float16", "float32", "float64")


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
        # appended: a fused map's number of measurements fused per pixel (uint8, saturating at 255); absent on a
        # single pair's map
        "n_fused": ("array", None),
        # appended: age of the frame (now - stamp_us on the publisher's clock) when the map was put; NaN = unknown
        # (older locators). A stage never puts a map older than its max age (eonav.bus.freshness)
        "frame_age_ms": ("float", math.nan),
    },
    "obstacle_list": {
        "stamp_us": ("int", REQUIRED), "camera_id": ("str", ""), "obstacles": ("list", REQUIRED),
        "sectors": ("dict", None), "position_ned_m": ("vec3", NAN3), "q_wxyz": ("vec4", NAN4),
        # appended: age of the map's frame when the list was put (as range_map.frame_age_ms)
        "frame_age_ms": ("float", math.nan),
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
    if not isinstance(d, dict) or not {"dtype", "shape", "data"} <= set(d):
        raise SchemaError(f"field {name}: expected an array map with dtype, shape, data", "array")
    dtype, shape, data = d["dtype"], d["shape"], d["data"]
    if dtype not in ARRAY_DTYPES:
        raise SchemaError(f"field {name}: dtype {dtype!r} not allowed; expected one of {ARRAY_DTYPES}", "array")
    if (not isinstance(shape, (list, tuple)) or not 1 <= len(shape) <= 4
            or not all(isinstance(s, int) and not isinstance(s, bool) and 0 <= s for s in shape)):
        raise SchemaError(f"field {name}: shape {shape!r} must be 1 to 4 non-negative integers", "array")
    n = math.prod(shape)
    if n > MAX_ARRAY_ELEMENTS:
        raise SchemaError(f"field {name}: {n} elements exceeds the limit {MAX_ARRAY_ELEMENTS}", "array")
    if not isinstance(data, (bytes, bytearray)):
        raise SchemaError(f"field {name}: data must be bytes", "array")
    dt = np.dtype(dtype).newbyteorder("<")
    if len(data) != n * dt.itemsize:
        raise SchemaError(f"field {name}: {len(data)} bytes but dtype {dtype} x shape {list(shape)} "
                          f"needs {n * dt.itemsize}", "array")
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


_SCALARS = (int, float, str, bool, type(None))


def _plain(v):
    if isinstance(v, np.ndarray):
        return v.tolist()
    if isinstance(v, np.generic):
        return v.item()
    if isinstance(v, dict):
        return {k: x if type(x) in _SCALARS else _plain(x) for k, x in v.items()}
    if isinstance(v, (list, tuple)):
        return [x if type(x) in _SCALARS else _plain(x) for x in v]    # no call per number (72 sector bins)
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
        raise SchemaError(f"payload is not msgpack ({type(e).__name__}: {e})", "msgpack") from None
    if not isinstance(doc, dict):
        raise SchemaError("payload is not a msgpack map", "msgpack")
    kind, v = doc.get("kind"), doc.get("v")
    if not isinstance(kind, str) or kind not in FIELDS:        # (a list or map here is unhashable)
        raise SchemaError(f"unknown message kind {kind!r}", "kind")
    if expect is not None and kind != expect:
        raise SchemaError(f"expected a {expect} message, got {kind}", "kind")
    if isinstance(v, bool) or not isinstance(v, int) or v not in SUPPORTED_VERSIONS:     # (True == 1, 1.0 == 1)
        raise SchemaError(f"{kind}: unsupported schema version {v!r}; this build reads {SUPPORTED_VERSIONS}",
                          "version")
    out = {"kind": kind, "v": v}
    for name, (typ, default) in FIELDS[kind].items():
        if name in doc:
            out[name] = _check(kind, name, typ, doc[name])
        elif default is REQUIRED:
            raise SchemaError(f"{kind}.{name}: missing required field")
        else:
            out[name] = np.asarray(default, float) if typ in ("vec3", "vec4") else default
    validate(out)
    return out


# -- the values: ranges, shapes, dtypes (after the types are right) ------------------------------------------
def _range(kind, name, ok, expected, val):
    if not ok:
        raise SchemaError(f"{kind}.{name}: expected {expected}, got {str(val)[:80]}", "range")


def _check_stamp(kind, name, v, allow_unset=False):
    _range(kind, name, (allow_unset and v == -1) or 0 <= v < MAX_STAMP_US,
           f"a stamp in 0 .. 2^62 us{' or -1' if allow_unset else ''}", v)


def _check_vec(kind, name, v, limit, nan_ok):
    finite = np.isfinite(v)
    ok = bool(np.all(np.abs(v[finite]) <= limit)) and (nan_ok and not np.any(np.isinf(v)) or bool(finite.all()))
    _range(kind, name, ok, f"{'finite ' if not nan_ok else ''}values within +-{limit:g}" +
           (" (NaN = unknown)" if nan_ok else ""), v.tolist())


def _check_quat(kind, name, q, nan_ok):
    if nan_ok and np.all(np.isnan(q)):
        return
    n = float(np.linalg.norm(q)) if np.all(np.isfinite(q)) else math.nan
    _range(kind, name, abs(n - 1.0) <= 1e-2, "a unit quaternion w, x, y, z (norm 1 +- 0.01)", q.tolist())


def _check_camera(kind, cam):
    where = f"{kind}.camera"
    for k in ("width", "height"):
        v = cam.get(k)
        _range(where, k, isinstance(v, int) and not isinstance(v, bool) and 1 <= v <= MAX_IMAGE_SIDE_PX,
               f"an integer 1 .. {MAX_IMAGE_SIDE_PX}", v)
    for k in ("fx", "fy", "cx", "cy"):
        v = cam.get(k)
        num = isinstance(v, (int, float)) and not isinstance(v, bool) and math.isfinite(v)
        _range(where, k, num and (v > 0 if k in ("fx", "fy") else abs(v) <= 4 * MAX_IMAGE_SIDE_PX),
               "a finite number" + (" > 0" if k in ("fx", "fy") else ""), v)
    for k, lim in (("l_m", 1e3), ("eps_deg", 360.0)):
        v = cam.get(k, [0, 0, 0])
        ok = (isinstance(v, (list, tuple)) and len(v) == 3
              and all(isinstance(x, (int, float)) and not isinstance(x, bool) and math.isfinite(x) and abs(x) <= lim
                      for x in v))
        _range(where, k, ok, f"3 finite numbers within +-{lim:g}", v)


def _check_image(kind, msg, cam=None):
    img, enc = msg["image"], msg["encoding"]
    if enc not in IMAGE_ENCODINGS:
        raise SchemaError(f"{kind}.encoding: {enc!r} not one of {sorted(IMAGE_ENCODINGS)}", "range")
    dtype, ch = IMAGE_ENCODINGS[enc]
    shape_ok = (img.ndim == 2 and ch == 1) or (img.ndim == 3 and img.shape[2] == ch)
    _range(kind, "image", img.dtype == dtype and shape_ok and 1 <= min(img.shape[:2])
           and max(img.shape[:2]) <= MAX_IMAGE_SIDE_PX,
           f"{np.dtype(dtype).name} {'H x W' if ch == 1 else f'H x W x {ch}'} for encoding {enc}",
           f"{img.dtype.name} {list(img.shape)}")
    if cam is not None:
        _range(kind, "image", img.shape[:2] == (cam["height"], cam["width"]),
               f"the camera's size {cam['width']} x {cam['height']}", f"{img.shape[1]} x {img.shape[0]}")


def _check_map_arrays(kind, msg):
    cam = msg["camera"]
    hw = (cam["height"], cam["width"])
    for name, dtypes in (("range_m", FLOAT_DTYPES), ("confidence", FLOAT_DTYPES),
                         ("inv_range_std_per_m", FLOAT_DTYPES), ("flags", ("uint8",)), ("n_fused", ("uint8",))):
        a = msg.get(name)
        if a is None:
            continue
        _range(kind, name, a.dtype.name in dtypes and a.shape == hw,
               f"{' or '.join(dtypes)} of the camera's shape {list(hw)}", f"{a.dtype.name} {list(a.shape)}")
    for name, side in (("frame_width", cam["width"]), ("frame_height", cam["height"])):
        v = msg[name]
        _range(kind, name, v == 0 or side <= v <= MAX_IMAGE_SIDE_PX, f"0 or {side} .. {MAX_IMAGE_SIDE_PX}", v)
    v = msg["scale"]
    _range(kind, "scale", math.isfinite(v) and 0 < v <= 1, "a finite number in (0, 1]", v)
    for name, limit in (("baseline_m", MAX_POSITION_M), ("compute_s", MAX_DURATION_S), ("overhead_s", MAX_DURATION_S)):
        v = msg[name]
        _range(kind, name, math.isnan(v) or 0 <= v <= limit, f"NaN or 0 .. {limit:g}", v)


def validate(msg: dict) -> None:
    """Refuse values no sensor or service produces: stamps and seqs outside int64 use, positions beyond 10 000 km,
    NaN where a value is required, images or maps whose dtype or shape do not match their encoding or camera."""
    kind = msg["kind"]
    for name in ("stamp_us", "other_stamp_us", "autopilot_time_us", "source_pts_us"):
        if name in msg:
            _check_stamp(kind, name, msg[name], allow_unset=name != "stamp_us")
    for name in ("seq", "other_seq"):
        if name in msg:
            _range(kind, name, (name == "other_seq" and msg[name] == -1) or 0 <= msg[name] < MAX_SEQ,
                   "a sequence number in 0 .. 2^62", msg[name])
    if "frame_age_ms" in msg:
        v = msg["frame_age_ms"]
        _range(kind, "frame_age_ms", math.isnan(v) or abs(v) <= MAX_AGE_MS, f"NaN or within +-{MAX_AGE_MS:g} ms", v)
    required_pose = kind in ("posed_frame", "range_map")
    if "position_ned_m" in msg:
        _check_vec(kind, "position_ned_m", msg["position_ned_m"], MAX_POSITION_M, nan_ok=not required_pose)
    if "q_wxyz" in msg:
        _check_quat(kind, "q_wxyz", msg["q_wxyz"], nan_ok=not required_pose)
    if "velocity_ned_mps" in msg:
        _check_vec(kind, "velocity_ned_mps", msg["velocity_ned_mps"], MAX_SPEED_MPS, nan_ok=True)
    if "rates_frd_radps" in msg:
        _check_vec(kind, "rates_frd_radps", msg["rates_frd_radps"], MAX_RATE_RADPS, nan_ok=True)
    if "camera" in msg:
        _check_camera(kind, msg["camera"])
    if kind == "frame":
        _check_image(kind, msg)
    elif kind == "posed_frame":
        _check_image(kind, msg, msg["camera"])
    elif kind == "range_map":
        _check_map_arrays(kind, msg)
    elif kind == "obstacle_list":
        obs = msg["obstacles"]
        _range(kind, "obstacles", len(obs) <= 1024 and all(isinstance(o, dict) for o in obs),
               "a list of at most 1024 maps", f"{len(obs)} items")
    elif kind == "health":
        c = msg["counters"]
        _range(kind, "counters", len(c) <= 4096 and all(isinstance(k, str) and isinstance(v, (int, float))
                                                        and not isinstance(v, bool) for k, v in c.items()),
               "at most 4096 name -> number entries", f"{len(c)} entries")


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
