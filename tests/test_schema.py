"""The bus schema: round trips, and hostile or malformed payloads rejected with a reason."""
import re
from pathlib import Path

import msgpack
import numpy as np
import pytest

from eonav.bus import keys
from eonav.bus import schema
from eonav.bus.schema import SchemaError


def frame_msg(**over):
    f = dict(camera_id="nose", seq=3, stamp_us=1_700_000_000_000_000, image=np.arange(12, dtype=np.uint8).reshape(3, 4))
    f.update(over)
    return schema.encode("frame", **f)


def test_round_trip_keeps_arrays_and_defaults():
    d = schema.decode(frame_msg(), expect="frame")
    assert d["v"] == schema.SCHEMA_VERSION and d["seq"] == 3
    assert d["image"].dtype == np.uint8 and d["image"].shape == (3, 4) and d["image"][2, 3] == 11
    assert d["stamp_source"] == "host"
    n = schema.decode(schema.encode("nav_state", stamp_us=5, q_wxyz=[1, 0, 0, 0]))
    assert np.isnan(n["position_ned_m"]).all() and n["q_wxyz"][0] == 1.0


CAM_2X3 = {"width": 3, "height": 2, "fx": 2.0, "fy": 2.0, "cx": 1.0, "cy": 0.5, "l_m": [0, 0, 0], "eps_deg": [0, 0, 0]}


def test_float_array_round_trip():
    r = np.linspace(0, 1, 6, dtype=np.float32).reshape(2, 3)
    r[0, 0] = np.nan
    d = schema.decode(schema.encode("range_map", camera_id="c", seq=1, stamp_us=1, method="dense", range_m=r,
                                    confidence=r, camera=CAM_2X3, position_ned_m=[0, 0, 0],
                                    q_wxyz=[1, 0, 0, 0]))
    assert np.isnan(d["range_m"][0, 0]) and np.allclose(d["range_m"][1], r[1])


def test_big_endian_arrays_go_on_the_wire_little_endian():
    """The wire is little endian (docs/bus.md): a big-endian array given to encode (as read from a FITS file or a
    network buffer) is converted, so the bytes sent are the little-endian ones (258 = 0x0102 -> 02 01) and the
    reader gets the same values, not byte-swapped ones."""
    img = np.array([[258, 1], [0, 65535]], dtype=">u2")
    payload = frame_msg(image=img, encoding="mono16")
    assert msgpack.unpackb(payload, raw=False)["image"]["data"] == bytes.fromhex("0201 0100 0000 ffff")
    np.testing.assert_array_equal(schema.decode(payload)["image"], [[258, 1], [0, 65535]])
    r = np.array([[1.5, -2.0, 1e30], [0.25, np.inf, 7.0]], dtype=">f4")
    d = schema.decode(schema.encode("range_map", camera_id="c", seq=1, stamp_us=1, method="dense", range_m=r,
                                    confidence=r.astype(">f8"), camera=CAM_2X3, position_ned_m=[0, 0, 0],
                                    q_wxyz=[1, 0, 0, 0]))
    np.testing.assert_array_equal(d["range_m"], [[1.5, -2.0, np.float32(1e30)], [0.25, np.inf, 7.0]])
    np.testing.assert_array_equal(d["confidence"], d["range_m"].astype(np.float64))


def raw(doc):
    return msgpack.packb(doc, use_bin_type=True)


@pytest.mark.parametrize("payload,match", [
    (b"\xc1\xc1garbage", "not msgpack"),
    (raw([1, 2, 3]), "not a msgpack map"),
    (raw({"kind": "teleport", "v": 1}), "unknown message kind"),
    (raw({"kind": "frame", "v": 99}), "unsupported schema version 99"),
    (raw({"kind": "frame", "v": 1, "camera_id": "c", "seq": 1}), r"frame.stamp_us: missing required field"),
    (raw({"kind": "frame", "v": 1, "camera_id": "c", "seq": "one", "stamp_us": 1}), r"frame.seq: expected an integer"),
    (raw({"kind": "frame", "v": 1, "camera_id": "c", "seq": 1, "stamp_us": 1,
          "image": {"dtype": "uint8", "shape": [100, 100], "data": b"\0" * 10}}), "10 bytes but dtype uint8"),
    (raw({"kind": "frame", "v": 1, "camera_id": "c", "seq": 1, "stamp_us": 1,
          "image": {"dtype": "object", "shape": [1], "data": b"\0"}}), "dtype 'object' not allowed"),
    (raw({"kind": "frame", "v": 1, "camera_id": "c", "seq": 1, "stamp_us": 1,
          "image": {"dtype": "uint8", "shape": [100000, 100000], "data": b""}}), "exceeds the limit"),
    (raw({"kind": "frame", "v": 1, "camera_id": "c", "seq": 1, "stamp_us": 1,
          "image": {"dtype": "uint8", "shape": [-1, 4], "data": b""}}), "non-negative integers"),
])
def test_malformed_payloads_are_rejected_with_a_reason(payload, match):
    with pytest.raises(SchemaError, match=match):
        schema.decode(payload)


@pytest.mark.parametrize("extra", [-6, -1, 0, 1, 6])
def test_array_data_must_have_exactly_the_size_of_its_shape(extra):
    """A mono8 4 x 6 image needs 24 bytes: one byte or one row more or less is a SchemaError naming the sizes;
    exactly 24 decodes to the image."""
    a = np.arange(24, dtype=np.uint8).reshape(4, 6)
    data = a.tobytes() + b"\0" * max(extra, 0)
    data = data[:len(data) + extra] if extra < 0 else data
    payload = raw({"kind": "frame", "v": 1, "camera_id": "c", "seq": 1, "stamp_us": 1,
                   "image": {"dtype": "uint8", "shape": [4, 6], "data": data}})
    if extra == 0:
        np.testing.assert_array_equal(schema.decode(payload)["image"], a)
    else:
        with pytest.raises(SchemaError, match=rf"field frame\.image: {24 + extra} bytes but dtype uint8 x shape "
                                              rf"\[4, 6\] needs 24"):
            schema.decode(payload)


def test_wrong_kind_for_the_topic():
    with pytest.raises(SchemaError, match="expected a nav_state message, got frame"):
        schema.decode(frame_msg(), expect="nav_state")


@pytest.mark.parametrize("v", [True, 1.0, 0, 2, -1, "1", None])
def test_only_integer_schema_version_1_is_read(v):
    """This build reads version 1 only: True and 1.0 equal 1 in Python but are not the integer 1 a writer sends;
    they and unknown versions are refused with the reason "version"."""
    doc = msgpack.unpackb(frame_msg(), raw=False)
    doc["v"] = v
    with pytest.raises(SchemaError, match="unsupported schema version") as e:
        schema.decode(raw(doc))
    assert e.value.reason == "version"
    doc["v"] = 1
    assert schema.decode(raw(doc))["v"] == 1


def test_encode_refuses_unknown_fields_and_missing_required():
    with pytest.raises(SchemaError, match="unknown field"):
        schema.encode("health", service="x", stamp_us=1, state="ok", colour="red")
    with pytest.raises(SchemaError, match="health.state: missing"):
        schema.encode("health", service="x", stamp_us=1)


def test_extra_fields_from_a_newer_writer_are_ignored():
    doc = msgpack.unpackb(frame_msg(), raw=False)
    doc["future_field_m"] = 3.0
    assert schema.decode(raw(doc))["seq"] == 3


def test_keys_carry_the_vehicle_prefix_and_reject_wildcards():
    assert keys.frame("v1", "nose") == "eonav/v1/camera/nose/frame"
    assert keys.range_map("v1", "nose") == "eonav/v1/range/nose"
    with pytest.raises(ValueError, match="vehicle"):
        keys.nav_state("v1/*")
    with pytest.raises(ValueError, match="camera id"):
        keys.frame("v1", "**")


def _documented_keys():
    """The rows of the key table in docs/bus.md: (key pattern after ``eonav/<vehicle>/``, schema kind or '-')."""
    doc = (Path(__file__).resolve().parents[1] / "docs" / "bus.md").read_text()
    rows = re.findall(r"^\| `([^`]+)` \| [^|]+ \| (`(\w+)`|-) \|$", doc, flags=re.M)
    return {pattern: kind.strip("`") for pattern, kind, _ in rows}


def test_keys_are_the_ones_docs_bus_md_documents():
    """Every key eonav builds is the one docs/bus.md gives its producers and consumers (an external guidance
    subscriber reads the table, not the code): a renamed key still matches its own producer but silently
    disconnects every reader that follows the document. Truth: the table, with vehicle ``v1``, camera ``nose``,
    service ``sync``."""
    table = _documented_keys()
    built = {
        "camera/<camera_id>/frame": keys.frame("v1", "nose"),
        "nav/state": keys.nav_state("v1"),
        "nav/clock": keys.nav_clock("v1"),
        "posed/<camera_id>/frame": keys.posed_frame("v1", "nose"),
        "range/<camera_id>": keys.range_map("v1", "nose"),
        "obstacles": keys.obstacles("v1"),
        "health/<service>": keys.health("v1", "sync"),
        "alive/<service>": keys.alive("v1", "sync"),
        "config/<service>": keys.config("v1", "sync"),
    }
    assert set(table) == set(built)
    for pattern, key in built.items():
        want = "eonav/v1/" + pattern.replace("<camera_id>", "nose").replace("<service>", "sync")
        assert key == want, pattern


def test_each_wildcard_matches_its_own_topic_and_no_other():
    """Subscribers use the wildcard forms (the sync takes every camera's frames, the obstacles service every range
    map, the launcher every health): by zenoh's own matching, each must include its concrete keys for any camera
    or service, and no concrete key may reach another topic's subscriber, e.g. obstacle tracks on the
    ``obstacles`` key would reach the MAVLink output as if they were the obstacle list."""
    zenoh = pytest.importorskip("zenoh")
    v = "v1"
    concrete = {
        "frame": [keys.frame(v, c) for c in ("nose", "left_wing")],
        "nav_state": [keys.nav_state(v)],
        "nav_clock": [keys.nav_clock(v)],
        "posed": [keys.posed_frame(v, c) for c in ("nose", "left_wing")],
        "range": [keys.range_map(v, c) for c in ("nose", "left_wing")],
        "obstacles": [keys.obstacles(v)],
        "tracks": [keys.obstacle_tracks(v)],
        "health": [keys.health(v, s) for s in ("sync", "locator")],
        "alive": [keys.alive(v, s) for s in ("sync", "locator")],
        "config": [keys.config(v, s) for s in ("sync", "locator")],
    }
    flat = [(topic, k) for topic, ks in concrete.items() for k in ks]
    assert len({k for _, k in flat}) == len(flat)                  # no two topics share a key
    subscribers = {"frame": keys.frames_all(v), "posed": keys.posed_frames_all(v), "range": keys.range_maps_all(v),
                   "health": keys.health_all(v), "alive": keys.alive_all(v),
                   "nav_state": keys.nav_state(v), "obstacles": keys.obstacles(v), "tracks": keys.obstacle_tracks(v)}
    for topic, sub in subscribers.items():
        got = {t for t, k in flat if zenoh.KeyExpr(sub).intersects(zenoh.KeyExpr(k))}
        assert got == {topic}, (sub, got)
    everything = zenoh.KeyExpr(keys.vehicle_all(v))
    assert all(everything.includes(zenoh.KeyExpr(k)) for _, k in flat)
    assert not any(everything.intersects(zenoh.KeyExpr(k.replace("eonav/v1/", "eonav/v2/"))) for _, k in flat)


def test_camera_message_round_trip():
    from eonav.geometry.camera import Camera
    cam = Camera("nose", 64, 48, 50.0, 51.0, 31.5, 23.5, [7.6, 0, 0.6], np.deg2rad([0, -2, 0]))
    back = schema.camera_from_msg(schema.camera_to_msg(cam))
    assert back.name == "nose" and back.fy == 51.0 and np.allclose(back.eps_rad, cam.eps_rad)


def test_range_map_frame_size_is_optional():
    """frame_width / frame_height were appended with defaults: a message without them (an older locator's) decodes
    with 0 x 0 (= the map is on the frame's grid), one with them carries them."""
    r = np.zeros((2, 3), np.float32)
    base = dict(camera_id="c", seq=1, stamp_us=1, method="dense", range_m=r, confidence=r, camera=CAM_2X3,
                position_ned_m=[0, 0, 0], q_wxyz=[1, 0, 0, 0])
    old = schema.decode(schema.encode("range_map", **base))
    assert (old["frame_width"], old["frame_height"], old["scale"]) == (0, 0, 1.0)
    new = schema.decode(schema.encode("range_map", **base, frame_width=6, frame_height=4, scale=0.5))
    assert (new["frame_width"], new["frame_height"], new["scale"]) == (6, 4, 0.5)
    with pytest.raises(schema.SchemaError, match="frame_width"):
        schema.encode("range_map", **base, frame_width=6.5)
