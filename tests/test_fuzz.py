"""Fuzzing (hypothesis) of what eonav reads from outside: the bus message decoder, the pair-file reader, the tlog
reader and the dataflash reader. Each may refuse its input only with its documented error (SchemaError,
InputError; the tlog reader never raises), and what it accepts meets its invariants.

The default profile is short and deterministic (``derandomize``: the same examples on every run, so CI is stable);
``EONAV_FUZZ=long`` runs many more random examples (``EONAV_FUZZ_EXAMPLES`` sets how many)."""
from __future__ import annotations

import copy
import json
import math
import os
import struct
from pathlib import Path

import cv2
import msgpack
import numpy as np
import pytest
from hypothesis import HealthCheck, example, given, settings
from hypothesis import strategies as st

from eonav import InputError
from eonav.bus import schema
from eonav.io import pairfile
from eonav.nav.dataflash import DataflashReader
from eonav.nav.mavlink_in import TlogReader, mavlink2_dialect

settings.register_profile("default", max_examples=200, deadline=None, derandomize=True, database=None,
                          suppress_health_check=[HealthCheck.too_slow, HealthCheck.data_too_large,
                                                 HealthCheck.function_scoped_fixture])
settings.register_profile("long", max_examples=int(os.environ.get("EONAV_FUZZ_EXAMPLES", "20000")), deadline=None,
                          suppress_health_check=[HealthCheck.too_slow, HealthCheck.data_too_large,
                                                 HealthCheck.function_scoped_fixture])
settings.load_profile("long" if os.environ.get("EONAV_FUZZ") == "long" else "default")

DATA = Path(__file__).resolve().parent / "data"
TLOGS = Path(__file__).resolve().parents[1].parent / "shared" / "data" / "tlogs"

# -- values msgpack and JSON carry ---------------------------------------------------------------------------------
INT64 = st.integers(-2 ** 63, 2 ** 64 - 1)
SCALARS = st.one_of(st.none(), st.booleans(), INT64, st.floats(allow_nan=True, allow_infinity=True),
                    st.text(max_size=12), st.binary(max_size=24))
MSGPACK_VALUES = st.recursive(SCALARS, lambda kids: st.one_of(st.lists(kids, max_size=5),
                                                            st.dictionaries(st.text(max_size=8), kids, max_size=5)),
                              max_leaves=10)
JSON_VALUES = st.recursive(st.one_of(st.none(), st.booleans(), st.integers(-10 ** 30, 10 ** 30),
                                     st.floats(allow_nan=True, allow_infinity=True), st.text(max_size=12)),
                           lambda kids: st.one_of(st.lists(kids, max_size=5),
                                                  st.dictionaries(st.text(max_size=8), kids, max_size=5)),
                           max_leaves=10)
# values that sit on the edges of the checks: the limits, their neighbours, wrong types of the right look
EDGES = st.sampled_from([0, -1, 1, 2 ** 62 - 1, 2 ** 62, 2 ** 63, 2 ** 64 - 1, -2 ** 63, 1e7, 1.0000001e7, 1e300,
                         math.nan, math.inf, -math.inf, 0.5, True, "", "nose", [], {}, [0, 0], [0, 0, 0],
                         [1, 0, 0, 0], [math.nan] * 3, 16384, 16385, "x" * 300, b"\x00", None])
JSON_EDGES = st.one_of(EDGES.filter(lambda v: not isinstance(v, bytes)), st.just(10 ** 40), st.just(-10 ** 400))


def arr(a):
    return schema.pack_array(np.asarray(a))


CAM = {"name": "nose", "width": 4, "height": 3, "fx": 4.0, "fy": 4.0, "cx": 1.5, "cy": 1.0,
       "l_m": [0.0, 0.0, 0.0], "eps_deg": [0.0, 0.0, 0.0]}
POSE = {"position_ned_m": [1.0, 2.0, -10.0], "q_wxyz": [1.0, 0.0, 0.0, 0.0]}
Z = np.ones((3, 4), np.float32)
VALID = {       # one valid message of every kind, as the plain map that goes on the wire
    "frame": {"camera_id": "nose", "seq": 3, "stamp_us": 1_700_000_000_000_000, "encoding": "mono8",
              "image": arr(np.zeros((3, 4), np.uint8))},
    "nav_state": {"stamp_us": 1_700_000_000_000_000, "velocity_ned_mps": [1.0, 0.0, 0.0], **POSE},
    "clock_offset": {"stamp_us": 1_700_000_000_000_000, "offset_us": -12, "method": "receive"},
    "posed_frame": {"camera_id": "nose", "seq": 3, "stamp_us": 1_700_000_000_000_000, "encoding": "bgr8",
                    "image": arr(np.zeros((3, 4, 3), np.uint8)), "camera": dict(CAM), **POSE},
    "range_map": {"camera_id": "nose", "seq": 3, "stamp_us": 1_700_000_000_000_000, "method": "dense",
                  "range_m": arr(Z), "confidence": arr(Z.astype(np.float16)), "flags": arr(np.ones((3, 4), np.uint8)),
                  "n_fused": arr(np.ones((3, 4), np.uint8)), "camera": dict(CAM), "frame_width": 8,
                  "frame_height": 6, **POSE},
    "obstacle_list": {"stamp_us": 1_700_000_000_000_000, "obstacles": [{"range_m": 12.0, "bearing_deg": 3.0}],
                      "sectors": {"n": 8}, **POSE},
    "health": {"service": "locator", "stamp_us": 1_700_000_000_000_000, "state": "ok", "counters": {"a": 1}},
}


def wire(kind, doc):
    return msgpack.packb({"kind": kind, "v": 1, **doc}, use_bin_type=True)


def test_the_seed_messages_are_valid():
    for kind, doc in VALID.items():
        assert schema.decode(wire(kind, doc))["kind"] == kind


def check_invariants(out: dict) -> None:
    """What every decoded message holds: its kind's fields with their types, stamps and seqs in range, vectors as
    finite-or-NaN float arrays within their limits, arrays of allowed dtypes and of their camera's size; and it
    encodes again to a message that decodes to the same values."""
    kind = out["kind"]
    assert kind in schema.KINDS and out["v"] in schema.SUPPORTED_VERSIONS and type(out["v"]) is int
    for name, (typ, default) in schema.FIELDS[kind].items():
        v = out.get(name)
        if typ == "array":
            assert v is None and default is None or isinstance(v, np.ndarray) and v.dtype.name in schema.ARRAY_DTYPES
        elif typ in ("vec3", "vec4"):
            assert isinstance(v, np.ndarray) and v.shape == (int(typ[-1]),) and v.dtype == float
            assert not np.isinf(v).any()
        elif not (v is None and default is None):
            assert isinstance(v, {"int": int, "float": float, "str": str, "dict": dict, "list": list}[typ]), name
            assert not isinstance(v, bool)
    assert 0 <= out["stamp_us"] < schema.MAX_STAMP_US
    if "seq" in out:
        assert 0 <= out["seq"] < schema.MAX_SEQ
    if "position_ned_m" in out:
        p = out["position_ned_m"]
        assert np.all(np.abs(p[np.isfinite(p)]) <= schema.MAX_POSITION_M)
    if "camera" in out:
        hw = (out["camera"]["height"], out["camera"]["width"])
        assert 1 <= min(hw) and max(hw) <= schema.MAX_IMAGE_SIDE_PX
        if kind == "posed_frame":
            assert out["image"].shape[:2] == hw
        if kind == "range_map":
            assert out["range_m"].shape == hw and out["confidence"].shape == hw
            assert np.isfinite(out["q_wxyz"]).all() and abs(np.linalg.norm(out["q_wxyz"]) - 1) <= 1e-2
    fields = {k: v for k, v in out.items() if k not in ("kind", "v")}
    again = schema.decode(schema.encode(kind, **fields))
    for k, v in out.items():
        w = again[k]
        if isinstance(v, np.ndarray):
            assert v.dtype == w.dtype and np.array_equal(v, w, equal_nan=True), k
        elif isinstance(v, float) and math.isnan(v):
            assert isinstance(w, float) and math.isnan(w), k
        else:
            assert _same(v, w), k


def _same(a, b):
    """Equality that treats NaN as equal to NaN, inside lists and maps too."""
    if isinstance(a, float) and isinstance(b, float) and math.isnan(a) and math.isnan(b):
        return True
    if isinstance(a, dict) and isinstance(b, dict):
        return a.keys() == b.keys() and all(_same(a[k], b[k]) for k in a)
    if isinstance(a, (list, tuple)) and isinstance(b, (list, tuple)):
        return len(a) == len(b) and all(_same(x, y) for x, y in zip(a, b))
    return a == b


def decode_only_schema_error(payload):
    try:
        out = schema.decode(payload)
    except schema.SchemaError as e:
        assert e.reason in ("msgpack", "kind", "version", "field", "array", "range"), e.reason
        return None
    check_invariants(out)
    return out


# -- the message decoder -------------------------------------------------------------------------------------------
@given(st.binary(max_size=600))
def test_decode_arbitrary_bytes(payload):
    decode_only_schema_error(payload)


@given(MSGPACK_VALUES)
def test_decode_arbitrary_msgpack_structures(doc):
    decode_only_schema_error(msgpack.packb(doc, use_bin_type=True))


@given(st.sampled_from(sorted(schema.KINDS)), MSGPACK_VALUES)
def test_decode_arbitrary_fields_of_a_known_kind(kind, doc):
    if isinstance(doc, dict):
        decode_only_schema_error(msgpack.packb({**doc, "kind": kind, "v": 1}, use_bin_type=True))


def _paths(obj, prefix=()):
    """Every path to a value inside nested maps and lists (the value itself included)."""
    yield prefix
    if isinstance(obj, dict):
        for k, v in obj.items():
            yield from _paths(v, prefix + (k,))
    elif isinstance(obj, list):
        for i, v in enumerate(obj):
            yield from _paths(v, prefix + (i,))


def _mutate(doc, path, action, value):
    """A copy of ``doc`` with the value at ``path`` deleted, replaced, or (in a map) a new key added beside it."""
    doc = copy.deepcopy(doc)
    if not path:
        return value if action == "replace" else doc
    parent = doc
    for k in path[:-1]:
        parent = parent[k]
    key = path[-1]
    if action == "delete":
        del parent[key]
    elif action == "replace":
        parent[key] = value
    elif isinstance(parent, dict):
        parent[f"{key}_x" if isinstance(key, str) else "x"] = value
    return doc


@st.composite
def mutated_messages(draw):
    kind = draw(st.sampled_from(sorted(VALID)))
    doc = {"kind": kind, "v": 1, **copy.deepcopy(VALID[kind])}
    for _ in range(draw(st.integers(1, 3))):
        paths = list(_paths(doc))
        path = draw(st.sampled_from(paths))
        action = draw(st.sampled_from(["replace", "replace", "delete", "add"]))
        value = draw(st.one_of(EDGES, MSGPACK_VALUES))
        doc = _mutate(doc, path, action, value)
    return msgpack.packb(doc, use_bin_type=True)


@given(mutated_messages())
@example(wire("frame", {**VALID["frame"], "image": {"etype": "uint8", "shape": [3, 4], "data": bytes(12)}}))
def test_decode_mutated_valid_messages_of_every_kind(payload):       # (the example: an array map without dtype)
    decode_only_schema_error(payload)


@st.composite
def flipped_bytes(draw):
    kind = draw(st.sampled_from(sorted(VALID)))
    b = bytearray(wire(kind, VALID[kind]))
    for _ in range(draw(st.integers(1, 4))):
        op = draw(st.sampled_from(["flip", "insert", "delete", "cut"]))
        i = draw(st.integers(0, len(b) - 1))
        if op == "flip":
            b[i] ^= draw(st.integers(1, 255))
        elif op == "insert":
            b[i:i] = draw(st.binary(min_size=1, max_size=4))
        elif op == "delete" and len(b) > 1:
            del b[i]
        elif op == "cut":
            del b[i:]
        if not b:
            break
    return bytes(b)


@given(flipped_bytes())
def test_decode_valid_messages_with_damaged_bytes(payload):
    decode_only_schema_error(payload)


# -- the pair-file reader ------------------------------------------------------------------------------------------
PAIR = {"cameras": {"nose": {"width": 8, "height": 6, "fx": 10.0, "fy": 10.0, "cx": 3.5, "cy": 2.5,
                             "mount": {"l_m": [1.0, 0.0, 0.2], "eps_deg": [0.0, -2.0, 0.0]}}},
        "frames": [{"image": "f0.png", "camera": "nose", "t": 0.0, "position_ned_m": [0, 0, -3],
                    "ypr_deg": [0, 0, 0]},
                   {"image": "f1.png", "camera": "nose", "t": 0.1, "position_ned_m": [1, 0, -3],
                    "q_wxyz": [1, 0, 0, 0]}]}


@pytest.fixture(scope="module")
def pair_dir(tmp_path_factory):
    d = tmp_path_factory.mktemp("fuzzpair")
    for i in range(2):
        cv2.imwrite(str(d / f"f{i}.png"), np.full((6, 8), 40 * i, np.uint8))
    cv2.imwrite(str(d / "small.png"), np.zeros((3, 3), np.uint8))
    return d


def load_only_input_error(doc, base: Path):
    try:
        pf = pairfile.parse_pair(doc, base)
        views = pf.views()
    except InputError:
        return None
    assert len(views) == len(pf.frames) >= 2
    for v in views:
        assert v.image.shape == (v.camera.height, v.camera.width) and v.image.dtype == np.float32
        assert np.all(np.isfinite(v.state.position_ned_m)) and np.allclose(v.state.T_body_ned @ v.state.T_body_ned.T,
                                                                           np.eye(3), atol=1e-9)
    return pf


def test_the_seed_pair_file_is_valid(pair_dir):
    assert load_only_input_error(PAIR, pair_dir) is not None


@given(JSON_VALUES)
def test_pair_reader_arbitrary_json(pair_dir, doc):
    load_only_input_error(doc, pair_dir)


@st.composite
def mutated_pair_files(draw):
    doc = copy.deepcopy(PAIR)
    for _ in range(draw(st.integers(1, 3))):
        path = draw(st.sampled_from(list(_paths(doc))))
        action = draw(st.sampled_from(["replace", "replace", "delete", "add"]))
        value = draw(st.one_of(JSON_EDGES, JSON_VALUES,
                               st.sampled_from(["small.png", "none.png", "/dev/zero", ".", "a\x00b", "x" * 5000])))
        doc = _mutate(doc, path, action, value)
    return doc


@given(mutated_pair_files())
def test_pair_reader_mutated_valid_pair_files(pair_dir, doc):
    load_only_input_error(doc, pair_dir)


@given(st.binary(max_size=300) | mutated_pair_files().map(lambda d: json.dumps(d).encode()))
def test_pair_file_bytes(pair_dir, data):
    p = pair_dir / "fuzz.json"
    p.write_bytes(data)
    try:
        doc = pairfile.read_json(p)
    except InputError:
        return
    load_only_input_error(doc, pair_dir)


# -- the tlog reader -----------------------------------------------------------------------------------------------
def _record_len(buf, i):
    return 8 + (6 + buf[i + 9] + 2 if buf[i + 8] == 0xFE else 10 + buf[i + 9] + 2 + (13 if buf[i + 10] & 1 else 0))


def tlog_seed(path: Path, max_bytes: int = 12_000) -> bytes:
    """The first records of a tlog (cut at a record boundary), or a generated one when the real ones are absent."""
    if path.is_file():
        data = path.read_bytes()[:max_bytes * 2]
        i = 0
        while i + 11 <= len(data) and i + _record_len(data, i) <= max_bytes:
            i += _record_len(data, i)
        return data[:i]
    ML = mavlink2_dialect()
    mav = ML.MAVLink(None, srcSystem=1, srcComponent=1)
    return b"".join(struct.pack(">Q", 1_700_000_000_000_000 + k * 20_000)
                    + ML.MAVLink_attitude_message(k * 20, 0.1, 0.2, 0.3, 0, 0, 0).pack(mav) for k in range(150))


SEEDS = {name: tlog_seed(TLOGS / f) for name, f in (("copter", "arducopter_real_flight_dronekit.tlog"),
                                                     ("sub", "ardusub_real_dive_qgc_mavlink2_small.tlog"))}


def read_tlog(tmp_path, data: bytes):
    p = tmp_path / "fuzz.tlog"
    p.write_bytes(data)
    r = TlogReader(p)
    got = [(h, m.get_type(), bytes(m.get_msgbuf())) for h, m in r]      # never raises: that is the contract
    r.close()
    st_ = r.stats
    # every byte is accounted for: whole records, bytes skipped to resynchronise, a truncated tail
    assert sum(8 + len(b) for _, _, b in got) + st_.resync_bytes + st_.truncated_bytes == len(data)
    assert st_.records == len(got)
    return got, st_


@pytest.fixture(scope="module")
def clean_tlogs(tmp_path_factory):
    """name -> (records, stats, the byte offset where each record ends) of each seed."""
    d = tmp_path_factory.mktemp("tlogseed")
    out = {}
    for name, data in SEEDS.items():
        got, s = read_tlog(d, data)
        ends, pos = [], 0
        for h, _, b in got:
            pos = data.index(h.to_bytes(8, "big") + b, pos) + 8 + len(b)
            ends.append(pos)
        out[name] = (got, s, ends)
    return out


def test_the_tlog_seeds_read_cleanly(clean_tlogs):
    for name, (got, s, ends) in clean_tlogs.items():
        assert len(got) > 50 and s.truncated_bytes == 0 and ends[-1] == len(SEEDS[name]), name
        assert s.bad_data <= 5, name                  # (the copter's radio log has corrupt packets of its own)


@given(st.sampled_from(sorted(SEEDS)), st.data())
def test_truncated_tlog_is_a_prefix(tmp_path_factory, clean_tlogs, name, data):
    seed = SEEDS[name]
    cut = data.draw(st.integers(0, len(seed)))
    got, s = read_tlog(tmp_path_factory.mktemp("t"), seed[:cut])
    full, full_stats, ends = clean_tlogs[name]
    # exactly the records that end before the cut, as read from the whole seed
    assert got == full[:sum(1 for e in ends if e <= cut)]
    assert s.bad_data <= full_stats.bad_data


@given(st.sampled_from(sorted(SEEDS)), st.data())
def test_mutated_tlog_loses_only_the_damaged_records(tmp_path_factory, clean_tlogs, name, data):
    seed = bytearray(SEEDS[name])
    n = data.draw(st.integers(1, 6))
    spots = sorted(data.draw(st.lists(st.integers(0, len(seed) - 1), min_size=n, max_size=n, unique=True)))
    for i in spots:
        seed[i] ^= data.draw(st.integers(1, 255))
    got, s = read_tlog(tmp_path_factory.mktemp("m"), bytes(seed))
    full, full_stats, ends = clean_tlogs[name]
    # every record with no damaged byte comes out unchanged (a damaged header time is only kept in order)
    starts = [0] + ends[:-1]
    undamaged = [rec for rec, a, e in zip(full, starts, ends) if not any(a <= i < e for i in spots)]
    got_bytes = {b for _, _, b in got}
    lost = [rec for rec in undamaged if rec[2] not in got_bytes]
    assert not lost, (len(lost), n, s)
    assert s.bad_data <= full_stats.bad_data + 2 * n


# -- the dataflash reader ------------------------------------------------------------------------------------------
BIN = (DATA / "arducopter_sitl_short.bin").read_bytes()[:24_000]


@given(st.data())
def test_damaged_dataflash_log_gives_only_input_error(tmp_path_factory, data):
    b = bytearray(BIN)
    for _ in range(data.draw(st.integers(1, 8))):
        op = data.draw(st.sampled_from(["flip", "flip", "cut", "zero"]))
        i = data.draw(st.integers(0, len(b) - 1))
        if op == "flip":
            b[i] ^= data.draw(st.integers(1, 255))
        elif op == "cut":
            del b[i:]
        else:
            b[i:i + 64] = bytes(len(b[i:i + 64]))
        if not b:
            break
    p = tmp_path_factory.mktemp("df") / "fuzz.bin"
    p.write_bytes(bytes(b))
    try:
        r = DataflashReader(p)
        got = list(r)
    except InputError:
        return
    for stamp, m in got:
        assert isinstance(stamp, int) and m.get_type() in ("ATTITUDE", "ATTITUDE_QUATERNION", "LOCAL_POSITION_NED",
                                                           "GLOBAL_POSITION_INT")


# -- what the fuzzing found, kept as plain regression tests --------------------------------------------------------
def test_a_corrupt_first_tlog_header_does_not_lose_the_file(tmp_path):
    """One flipped byte in the first record's header time made every later record 'implausible' (too far from it):
    the whole file was skipped as garbage. Now a record whose packet decodes resynchronises, and the first header is
    checked against the next two."""
    ML = mavlink2_dialect()
    mav = ML.MAVLink(None, srcSystem=1, srcComponent=1)
    t0 = 1_700_000_000_000_000
    data = bytearray(b"".join(struct.pack(">Q", t0 + k * 20_000)
                              + ML.MAVLink_attitude_message(k * 20, 0, 0, 0, 0, 0, 0).pack(mav) for k in range(20)))
    data[0] ^= 0x40                                        # the first header is now years away
    got, s = read_tlog(tmp_path, bytes(data))
    assert [m for _, m, _ in got] == ["ATTITUDE"] * 20
    assert [h for h, _, _ in got] == [t0 + 20_000] + [t0 + k * 20_000 for k in range(1, 20)]
    assert s.header_jumps == 1 and s.resync_bytes == 0


def test_an_unknown_id_found_while_resynchronising_is_no_record(tmp_path):
    """pymavlink does not check the CRC of an undefined message id, so while resynchronising (a header far from the
    last one, accepted only if its packet decodes) such a packet is no evidence: garbage read as one would swallow
    the records after it (the fuzzing found this in the first version of that fallback)."""
    ML = mavlink2_dialect()
    mav = ML.MAVLink(None, srcSystem=1, srcComponent=1)
    t0 = 1_700_000_000_000_000
    recs = [struct.pack(">Q", t0 + k * 20_000) + ML.MAVLink_attitude_message(k * 20, 0, 0, 0, 0, 0, 0).pack(mav)
            for k in range(6)]
    # garbage: a far header, then an 'unknown id' packet long enough to cover the next three records
    fake = struct.pack(">Q", 2 ** 62) + bytes([0xFD, 200, 0, 0, 0, 1, 1, 0xFF, 0xFF, 0xFE])
    data = recs[0] + recs[1][:-3] + fake + b"".join(recs[2:])
    got, s = read_tlog(tmp_path, data)
    assert [h for h, _, _ in got] == [t0] + [t0 + k * 20_000 for k in range(2, 6)]    # only record 1 is lost


def test_a_zeroed_fmt_record_is_refused_not_read_forever(tmp_path):
    """An FMT record zeroed (type 0, length 0, no format) and a message header A3 95 00 right after it: pymavlink's
    DFReader reads that message forever (its length 0 moves it back over its own header); such a log is refused."""
    import subprocess
    import sys
    b = bytearray(BIN)
    i = b.index(b"\xa3\x95\x80", 89)                       # the second FMT record
    b[i + 3:i + 89] = bytes(86)
    b[i + 89:i + 92] = b"\xa3\x95\x00"
    p = tmp_path / "zeroed.bin"
    p.write_bytes(bytes(b))
    code = ("import sys\nfrom eonav import InputError\nfrom eonav.nav.dataflash import DataflashReader\n"
            "try:\n    list(DataflashReader(sys.argv[1]))\nexcept InputError as e:\n    print(e)\n")
    r = subprocess.run([sys.executable, "-c", code, str(p)], capture_output=True, text=True, timeout=60)
    assert f"FMT record at byte {i} defines type 0 ('') with length 0, but its format '' needs 3" in r.stdout, r


def _attitude_records(n, t0=1_700_000_000_000_000):
    ML = mavlink2_dialect()
    mav = ML.MAVLink(None, srcSystem=1, srcComponent=1)
    return [bytearray(struct.pack(">Q", t0 + k * 20_000) + ML.MAVLink_attitude_message(k * 20, 0, 0, 0, 0, 0, 0)
                      .pack(mav)) for k in range(n)]


def test_a_corrupt_length_byte_near_the_end_does_not_end_the_file(tmp_path):
    """A length byte flipped so that its record runs past the end of the file: the reader ended there (the records
    after it counted as a truncated tail); now it resynchronises and reads them."""
    recs = _attitude_records(6)
    recs[4][9] = 0xF0                                      # record 4 now claims 240 payload bytes
    got, s = read_tlog(tmp_path, b"".join(recs))
    assert [int.from_bytes(r[:8], "big") for r in recs[:4] + recs[5:]] == [h for h, _, _ in got]
    assert s.truncated_bytes == 0


def test_an_unknown_id_is_believed_only_when_a_record_follows_it(tmp_path):
    """A flipped message id that the dialect does not define has no CRC check: with a flipped length too it
    swallowed the records after it. It is taken as a record only when the next record starts right after it."""
    recs = _attitude_records(8)
    recs[3][8 + 7] ^= 0x5A                                 # record 3's message id: undefined now
    recs[3][9] = 120                                        # and its length covers records 4 and 5
    got, s = read_tlog(tmp_path, b"".join(recs))
    assert [h for h, _, _ in got] == [int.from_bytes(r[:8], "big") for k, r in enumerate(recs) if k != 3]
    ok = _attitude_records(3)
    ok[1][8 + 7] ^= 0x5A                                   # an undefined id, framing intact: still a record
    got, _ = read_tlog(tmp_path, b"".join(ok))
    assert [t for _, t, _ in got] == ["ATTITUDE", f"UNKNOWN_{30 ^ 0x5A}", "ATTITUDE"]
