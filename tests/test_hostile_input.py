"""No payload stops or blinds a service: every field is checked at decode (both sides of each limit), a message that
still raises in a service is counted and dropped, counters stay bounded, and a far-future nav stamp cannot blind
the time sync. The process tests put the malformed payloads that once killed the locator and the obstacle service
on a real bus, then check that the services still range and analyse good input."""
import contextlib
import math
import signal
import time

import msgpack
import numpy as np
import pytest

from eonav.bus import keys as K
from eonav.bus import schema
from eonav.bus.node import COUNTER_LIMIT, MAX_COUNTERS, Node
from eonav.nav.timesync import NavBuffer

CAM = {"name": "nose", "width": 4, "height": 3, "fx": 4.0, "fy": 4.0, "cx": 1.5, "cy": 1.0, "l_m": [0, 0, 0],
       "eps_deg": [0, 0, 0]}


def arr(a):
    a = np.ascontiguousarray(a)
    return {"dtype": a.dtype.name, "shape": list(a.shape), "data": a.tobytes()}


def posed(**over):
    doc = {"kind": "posed_frame", "v": 1, "camera_id": "nose", "seq": 1, "stamp_us": 1_700_000_000_000_000,
           "encoding": "mono8", "image": arr(np.zeros((3, 4), np.uint8)), "camera": dict(CAM),
           "position_ned_m": [0.0, 0.0, -10.0], "q_wxyz": [1.0, 0.0, 0.0, 0.0]}
    doc.update(over)
    return msgpack.packb(doc, use_bin_type=True)


def range_map(**over):
    z = np.ones((3, 4), np.float32)
    doc = {"kind": "range_map", "v": 1, "camera_id": "nose", "seq": 1, "stamp_us": 1_700_000_000_000_000,
           "method": "dense", "range_m": arr(z), "confidence": arr(z), "flags": arr(np.ones((3, 4), np.uint8)),
           "camera": dict(CAM), "position_ned_m": [0.0, 0.0, -10.0], "q_wxyz": [1.0, 0.0, 0.0, 0.0]}
    doc.update(over)
    return msgpack.packb(doc, use_bin_type=True)


def nav(**over):
    doc = {"kind": "nav_state", "v": 1, "stamp_us": 1_700_000_000_000_000, "position_ned_m": [0.0, 0.0, -10.0],
           "q_wxyz": [1.0, 0.0, 0.0, 0.0]}
    doc.update(over)
    return msgpack.packb(doc, use_bin_type=True)


def rejected(payload, match, reason="range"):
    with pytest.raises(schema.SchemaError, match=match) as e:
        schema.decode(payload)
    assert e.value.reason == reason


# -- images that once crashed the locator (cv2.cvtColor on a float64 / int32 'bgr8' image) ------------------------
@pytest.mark.parametrize("image,encoding", [
    (np.zeros((3, 4, 3), np.float64), "bgr8"), (np.zeros((3, 4, 3), np.int32), "bgr8"),
    (np.zeros((3, 4), np.float32), "mono8"), (np.zeros((3, 4, 3), np.uint8), "mono8"),
    (np.zeros((3, 4), np.uint8), "bgr8"), (np.zeros((3, 4, 4), np.uint8), "rgb8"),
])
def test_posed_frame_image_must_match_its_encoding(image, encoding):
    rejected(posed(image=arr(image), encoding=encoding), "posed_frame.image")


def test_posed_frame_image_must_match_its_camera_and_known_encodings():
    rejected(posed(image=arr(np.zeros((4, 3), np.uint8))), "camera's size 4 x 3")
    rejected(posed(encoding="yuv9"), "posed_frame.encoding")
    ok = schema.decode(posed(image=arr(np.zeros((3, 4, 3), np.uint8)), encoding="bgr8"))
    assert ok["image"].shape == (3, 4, 3)
    assert schema.decode(posed(image=arr(np.zeros((3, 4), np.uint16)), encoding="mono16"))["image"].dtype == np.uint16


@pytest.mark.parametrize("shape", [(0, 4), (3, 0), (0, 0)])
def test_frame_image_must_have_pixels(shape):
    """A frame message has no camera to check its image against: an image with no rows or no columns is refused
    at decode, not handed to the locator; 1 x 1 is an image."""
    doc = {"kind": "frame", "v": 1, "camera_id": "nose", "seq": 1, "stamp_us": 1, "encoding": "mono8",
           "image": arr(np.zeros(shape, np.uint8))}
    rejected(msgpack.packb(doc, use_bin_type=True), "frame.image")
    doc["image"] = arr(np.zeros((1, 1), np.uint8))
    assert schema.decode(msgpack.packb(doc, use_bin_type=True))["image"].shape == (1, 1)


def test_range_map_arrays_are_checked():
    rejected(range_map(flags=arr(np.ones((3, 4), np.float32))), "range_map.flags")      # crashed bitwise_and
    rejected(range_map(range_m=arr(np.ones((3, 4), np.int32))), "range_map.range_m")
    rejected(range_map(confidence=arr(np.ones((4, 3), np.float32))), "range_map.confidence")
    rejected(range_map(frame_width=10 ** 9, frame_height=10 ** 9), "range_map.frame_width")
    rejected(range_map(frame_width=3, frame_height=3), "range_map.frame_width")          # smaller than the map
    assert schema.decode(range_map(frame_width=16384, frame_height=3))["frame_width"] == 16384
    rejected(range_map(frame_width=16385, frame_height=3), "range_map.frame_width")
    assert schema.decode(range_map(range_m=arr(np.ones((3, 4), np.float16))))["range_m"].dtype == np.float16


@pytest.mark.parametrize("field,ok,bad", [
    ("stamp_us", 2 ** 62 - 1, 2 ** 62), ("stamp_us", 0, -1), ("stamp_us", 1, 2 ** 63), ("stamp_us", 1, 2 ** 64 - 1),
])
def test_stamps_both_sides_of_the_limit(field, ok, bad):
    assert schema.decode(nav(**{field: ok}))[field] == ok
    rejected(nav(**{field: bad}), f"nav_state.{field}")


def test_seq_both_sides_of_the_limit():
    assert schema.decode(posed(seq=2 ** 62 - 1))["seq"] == 2 ** 62 - 1
    for bad in (2 ** 62, 2 ** 64 - 1, -1):
        rejected(posed(seq=bad), "posed_frame.seq")


def test_positions_speeds_and_quaternions_both_sides():
    assert schema.decode(nav(position_ned_m=[1e7, -1e7, 0.0]))["position_ned_m"][0] == 1e7
    for bad in ([1e300, 0, 0], [0, 0, 1.0000001e7], [float("inf"), 0, 0]):
        rejected(nav(position_ned_m=bad), "nav_state.position_ned_m")
    assert np.isnan(schema.decode(nav(position_ned_m=[float("nan")] * 3))["position_ned_m"]).all()   # unknown
    rejected(posed(position_ned_m=[float("nan"), 0, 0]), "posed_frame.position_ned_m")            # required there
    rejected(nav(velocity_ned_mps=[1e5, 0, 0]), "nav_state.velocity_ned_mps")
    assert schema.decode(nav(q_wxyz=[1.0099, 0, 0, 0]))["q_wxyz"][0] == pytest.approx(1.0099)
    rejected(nav(q_wxyz=[1.0101, 0, 0, 0]), "nav_state.q_wxyz")
    rejected(posed(q_wxyz=[0.0, 0, 0, 0]), "posed_frame.q_wxyz")


def test_range_map_scalars_within_their_ranges():
    """A range map's scale is in (0, 1] (the locator's working scale), its baseline and times NaN (unknown) or within
    0 .. their limit: the edges pass, a step beyond them, a negative value, inf and a NaN scale are refused."""
    ok = schema.decode(range_map(scale=1.0, baseline_m=0.0, compute_s=schema.MAX_DURATION_S, overhead_s=float("nan")))
    assert ok["scale"] == 1.0 and ok["compute_s"] == schema.MAX_DURATION_S
    assert schema.decode(range_map(scale=1e-3, baseline_m=schema.MAX_POSITION_M))["baseline_m"] == schema.MAX_POSITION_M
    for bad in (0.0, -0.5, 1.0000001, float("nan"), float("inf")):
        rejected(range_map(scale=bad), "range_map.scale")
    for name, limit in (("baseline_m", schema.MAX_POSITION_M), ("compute_s", schema.MAX_DURATION_S),
                        ("overhead_s", schema.MAX_DURATION_S)):
        for bad in (-1e-9, limit * 1.0001, float("inf"), -float("inf")):
            rejected(range_map(**{name: bad}), f"range_map.{name}")


def test_vectors_both_sides_of_the_negative_limit():
    """The limits hold on magnitude: -1e7 m is a position, a metre beyond it or -1e300 is not; speeds and rates as
    their positive side (1e4 m/s, 100 rad/s)."""
    assert schema.decode(nav(position_ned_m=[-1e7, 0.0, -1e7]))["position_ned_m"][2] == -1e7
    for bad in ([-1e300, 0, 0], [0, -1.0000001e7, 0], [0, 0, -float("inf")]):
        rejected(nav(position_ned_m=bad), "nav_state.position_ned_m")
    rejected(posed(position_ned_m=[0, 0, -1.0000001e7]), "posed_frame.position_ned_m")
    assert schema.decode(nav(velocity_ned_mps=[-1e4, 0, 0]))["velocity_ned_mps"][0] == -1e4
    rejected(nav(velocity_ned_mps=[0, -1.0001e4, 0]), "nav_state.velocity_ned_mps")
    assert schema.decode(nav(rates_frd_radps=[0, 0, -100.0]))["rates_frd_radps"][2] == -100.0
    rejected(nav(rates_frd_radps=[0, 0, -100.01]), "nav_state.rates_frd_radps")


def test_camera_fields_are_checked():
    for key, bad in (("width", 10 ** 9), ("width", 0), ("fx", -1.0), ("fx", float("nan")), ("cy", 1e300)):
        rejected(posed(camera=dict(CAM, **{key: bad})), f"posed_frame.camera.{key}")
    rejected(posed(camera=dict(CAM, l_m=[0, 0, 1e9])), "posed_frame.camera.l_m")


def test_camera_focal_lengths_must_be_positive():
    """fx and fy are divisors of every projection: 0 is refused at decode like a negative one; the smallest positive
    value passes."""
    for key in ("fx", "fy"):
        rejected(posed(camera=dict(CAM, **{key: 0.0})), f"posed_frame.camera.{key}")
        rejected(posed(camera=dict(CAM, **{key: 0})), f"posed_frame.camera.{key}")
        assert schema.decode(posed(camera=dict(CAM, **{key: 1e-3})))["camera"][key] == 1e-3


def frame(**over):
    doc = {"kind": "frame", "v": 1, "camera_id": "nose", "seq": 1, "stamp_us": 1_700_000_000_000_000,
           "encoding": "mono8", "image": arr(np.zeros((3, 4), np.uint8))}
    doc.update(over)
    return msgpack.packb(doc, use_bin_type=True)


def obstacle_list(**over):
    doc = {"kind": "obstacle_list", "v": 1, "stamp_us": 1_700_000_000_000_000,
           "obstacles": [{"range_m": 12.0, "bearing_deg": 3.0}], "position_ned_m": [0.0, 0.0, -10.0],
           "q_wxyz": [1.0, 0.0, 0.0, 0.0]}
    doc.update(over)
    return msgpack.packb(doc, use_bin_type=True)


NAN = float("nan")


@pytest.mark.parametrize("name,n", [("position_ned_m", 3), ("velocity_ned_mps", 3), ("rates_frd_radps", 3),
                                    ("q_wxyz", 4)])
def test_vectors_have_exactly_their_length_of_numbers(name, n):
    """A position, velocity or rate is 3 numbers, an attitude 4: one more or one fewer is refused at decode (a
    4-vector position would reach the sync's interpolation), and so is True among them (a bool is no measurement,
    as for the integer fields); the exact length decodes to its numbers."""
    good = [1.0] + [0.0] * (n - 1)
    np.testing.assert_array_equal(schema.decode(nav(**{name: good}))[name], good)
    for bad in (good[:-1], good + [0.0], [True] + good[1:]):
        rejected(nav(**{name: bad}), rf"nav_state\.{name}: expected a list of {n} numbers", reason="field")


def test_a_quaternion_is_unknown_only_when_all_four_are_nan():
    """NaN = unknown holds for the whole attitude (all four NaN: a nav source without attitude): a quaternion with
    one or three NaN components is corrupt, not unknown, and is refused where NaN is allowed (nav_state,
    obstacle_list) as where it is not."""
    assert np.isnan(schema.decode(nav(q_wxyz=[NAN] * 4))["q_wxyz"]).all()
    assert np.isnan(schema.decode(obstacle_list(q_wxyz=[NAN] * 4))["q_wxyz"]).all()
    for q in ([NAN, 0.0, 0.0, 0.0], [1.0, 0.0, 0.0, NAN], [NAN, NAN, NAN, 1.0]):
        rejected(nav(q_wxyz=q), "nav_state.q_wxyz")
        rejected(obstacle_list(q_wxyz=q), "obstacle_list.q_wxyz")
        rejected(posed(q_wxyz=q), "posed_frame.q_wxyz")


def test_a_range_map_needs_its_pose():
    """The obstacle service places every pixel of a map in the world with the map's pose: NaN (unknown) is allowed
    in a nav state's or an obstacle list's pose, never in a map's, where a NaN position or attitude is refused as
    on a posed frame."""
    for p in ([NAN, 0.0, -10.0], [NAN] * 3):
        rejected(range_map(position_ned_m=p), "range_map.position_ned_m")
    rejected(range_map(q_wxyz=[NAN] * 4), "range_map.q_wxyz")
    out = schema.decode(obstacle_list(position_ned_m=[NAN] * 3, q_wxyz=[NAN] * 4))
    assert np.isnan(out["position_ned_m"]).all() and np.isnan(out["q_wxyz"]).all()


def test_frame_image_side_limit_is_inclusive():
    """16384 px (MAX_IMAGE_SIDE_PX) is the largest image side a frame may have, inclusive: a 1 x 16384 and a
    16384 x 1 mono8 image decode, one pixel more on either side is refused."""
    side = schema.MAX_IMAGE_SIDE_PX
    for shape in ((1, side), (side, 1)):
        assert schema.decode(frame(image=arr(np.zeros(shape, np.uint8))))["image"].shape == shape
    for shape in ((1, side + 1), (side + 1, 1)):
        rejected(frame(image=arr(np.zeros(shape, np.uint8))), "frame.image")


def test_camera_side_limit_is_inclusive():
    """A camera 16384 px wide or high (MAX_IMAGE_SIDE_PX) is valid: a range map on a 16384 x 1 and a 1 x 16384
    camera decodes (no image to check, only the camera and its arrays); 16385 is refused naming the side."""
    side = schema.MAX_IMAGE_SIDE_PX
    for w, h in ((side, 1), (1, side)):
        a = np.ones((h, w), np.float32)
        out = schema.decode(range_map(camera=dict(CAM, width=w, height=h, cx=0.0, cy=0.0), range_m=arr(a),
                                      confidence=arr(a), flags=arr(np.ones((h, w), np.uint8))))
        assert (out["camera"]["width"], out["camera"]["height"]) == (w, h)
    for key in ("width", "height"):
        rejected(range_map(camera=dict(CAM, **{key: side + 1})), f"range_map.camera.{key}")


def test_principal_point_limits_hold_on_both_signs():
    """cx, cy may lie outside the image (a crop of a wider sensor), within +-4 x 16384 = 65536 px: both edges
    decode, a pixel beyond either edge is refused, and -1e300 like 1e300."""
    lim = 4 * schema.MAX_IMAGE_SIDE_PX
    assert lim == 65536
    for key in ("cx", "cy"):
        for ok in (lim, -lim):
            assert schema.decode(posed(camera=dict(CAM, **{key: float(ok)})))["camera"][key] == ok
        for bad in (lim + 1.0, -lim - 1.0, -1e300):
            rejected(posed(camera=dict(CAM, **{key: bad})), f"posed_frame.camera.{key}")


def test_fused_count_must_be_uint8_of_the_camera_shape():
    """n_fused (measurements per pixel of a fused map) masks the obstacle detector's pixels (min_fused): a float or
    a wider integer count, or one of another shape (a 1 x W row would broadcast over the whole map), is refused; a
    uint8 count of the camera's 3 x 4 shape decodes with its values."""
    ok = schema.decode(range_map(n_fused=arr(np.full((3, 4), 2, np.uint8))))["n_fused"]
    assert ok.dtype == np.uint8 and ok.shape == (3, 4) and (ok == 2).all()
    for bad in (np.full((3, 4), 2, np.float32), np.full((3, 4), 2, np.uint16), np.full((1, 4), 2, np.uint8),
                np.full((4, 3), 2, np.uint8)):
        rejected(range_map(n_fused=arr(bad)), "range_map.n_fused")


@pytest.mark.parametrize("make", [range_map, obstacle_list])
def test_frame_age_both_sides_of_the_limit(make):
    """frame_age_ms is NaN (unknown) or within +-MAX_AGE_MS (2^62 us in ms, a stamp's range): a small negative age
    (clock skew between hosts) and both edges decode; beyond either edge, -1e300 and +-inf are refused -- a reader
    comparing the age with its limit would take a huge negative age as fresh."""
    kind = "range_map" if make is range_map else "obstacle_list"
    lim = schema.MAX_AGE_MS
    assert lim == 2 ** 62 / 1000
    assert math.isnan(schema.decode(make(frame_age_ms=NAN))["frame_age_ms"])
    for ok in (-5.0, 0.0, lim, -lim):
        assert schema.decode(make(frame_age_ms=ok))["frame_age_ms"] == ok
    for bad in (lim * 1.0001, -lim * 1.0001, -1e300, float("inf"), -float("inf")):
        rejected(make(frame_age_ms=bad), f"{kind}.frame_age_ms")


def test_obstacle_list_holds_at_most_1024_maps():
    """Each obstacle of a list is a map (the MAVLink output and guidance subscribers read its fields by name): a
    list with a number, a string or a list among its items is refused; 1024 obstacles decode, 1025 are refused."""
    one = {"range_m": 12.0, "bearing_deg": 3.0}
    for stray in (7, "tree", [12.0, 3.0], None):
        rejected(obstacle_list(obstacles=[one, stray]), "obstacle_list.obstacles")
    assert len(schema.decode(obstacle_list(obstacles=[one] * 1024))["obstacles"]) == 1024
    rejected(obstacle_list(obstacles=[one] * 1025), "obstacle_list.obstacles")


@pytest.mark.parametrize("make,kind,field", [(range_map, "range_map", "other_stamp_us"),
                                             (nav, "nav_state", "autopilot_time_us"),
                                             (frame, "frame", "source_pts_us")])
def test_unset_stamps_are_minus_one_only(make, kind, field):
    """-1 is the one 'unset' value of the optional stamps: any other negative value is corrupt (a reader subtracting
    it from a stamp would get an interval beyond 2^62 us) and is refused; -1, 0 and 2^62 - 1 decode."""
    for ok in (-1, 0, 2 ** 62 - 1):
        assert schema.decode(make(**{field: ok}))[field] == ok
    for bad in (-2, -1_700_000_000_000_000, -2 ** 63):
        rejected(make(**{field: bad}), f"{kind}.{field}")


# -- the node: a message that still raises is that message's failure; counters bounded --------------------------
class _Quiet:
    def __init__(self):
        self.lines = []

    def log(self, level, fmt, *args):
        self.lines.append(fmt % args)

    def warning(self, fmt, *args):
        self.lines.append(fmt % args)


def bare_node():
    node = Node.__new__(Node)          # the metrics part of a node, without a session
    import threading
    node._lock, node._counters, node._last_log, node._suppressed = threading.Lock(), {}, {}, {}
    node.log = _Quiet()
    return node


def test_guarded_counts_and_swallows():
    node = bare_node()
    assert node.guarded("range_map", lambda x: x + 1, 1) == 2
    assert node.guarded("range_map", lambda: np.bitwise_and(np.ones(2, np.float32), 1)) is None
    assert node.counters() == {"message_errors": 1, "rejected.range_map": 1}
    assert "TypeError" in node.log.lines[0]


def test_counters_are_bounded_in_names_and_values():
    node = bare_node()
    for i in range(MAX_COUNTERS + 10):
        node.count(f"unknown_msg_id.{i}")
    c = node.counters()
    assert len(c) == MAX_COUNTERS + 1 and c["counters_overflow"] == 10
    node.count("unknown_msg_id.3")                    # a known name still counts as itself
    assert node.counters()["unknown_msg_id.3"] == 2
    node = bare_node()
    node.count("frames_skipped", 2 ** 64)
    node.count("frames_skipped", 5)
    assert node.counters()["frames_skipped"] == COUNTER_LIMIT
    # the health message of such a node still encodes and decodes
    schema.decode(schema.encode("health", service="x", stamp_us=1, state="ok", counters=node.counters()))


def test_counters_are_bounded_below_too():
    """Counters also go down (the locator's scale_pct gauges are counted as deltas): a huge negative count is clamped
    at -2^53 like a positive one, so the health message still encodes (msgpack has no integer below -2^63) and a
    later count moves it by exactly its own amount."""
    node = bare_node()
    node.count("scale_pct.nose", -(2 ** 64))
    node.count("scale_pct.nose", -5)
    assert node.counters()["scale_pct.nose"] == -COUNTER_LIMIT == -(2 ** 53)
    node.count("scale_pct.nose", 50)
    assert node.counters()["scale_pct.nose"] == -(2 ** 53) + 50
    h = schema.decode(schema.encode("health", service="x", stamp_us=1, state="ok", counters=node.counters()))
    assert h["counters"]["scale_pct.nose"] == -(2 ** 53) + 50


# -- the time sync: a far-future stamp is refused, not kept for good ---------------------------------------------
def test_far_future_nav_stamp_is_refused_and_does_not_blind_the_sync():
    now = [1_700_000_000_000_000]
    q, p = [1.0, 0, 0, 0], [0.0, 0.0, -10.0]
    real = [now[0] - 1_000_000 + k * 50_000 for k in range(20)]
    frame_us = real[-1] + 25_000              # a frame just after the newest nav sample: its bracket is not there yet

    def filled(buf):
        for t in real:
            buf.add(t, q, p)
        return buf

    buf = filled(NavBuffer(clock_us=lambda: now[0], max_future_us=5_000_000))
    buf.add(now[0] + 5_000_000, q, p)         # exactly at the limit: kept
    assert buf.counts["future_stamp"] == 0
    buf = filled(NavBuffer(clock_us=lambda: now[0], max_future_us=5_000_000))
    buf.add(now[0] + 5_000_001, q, p)         # beyond: refused
    buf.add(2 ** 62 - 1, q, p)
    assert buf.counts["future_stamp"] == 2
    assert buf.decide(frame_us).state == "wait"           # waits for its bracket, as without the bogus samples
    buf.add(real[-1] + 50_000, q, p)
    assert buf.pose_at(frame_us).ok
    # without the limit the bogus sample is taken as the newest: the frame is bracketed with it and lost as a gap
    blind = filled(NavBuffer())
    blind.add(2 ** 62 - 1, q, p)
    assert blind.decide(frame_us).state != "wait" and not blind.pose_at(frame_us).ok


# -- real processes on a real bus ---------------------------------------------------------------------------------
@contextlib.contextmanager
def _services():
    from tests.test_locator_service import locator_and_obstacles
    # the health asserted at the end is about surviving the payloads, not about input silence or freshness: on a
    # loaded machine the waits for the map and the list can outlast the default 1 s input timeout (state degraded:
    # input silent), and the locator's first good frame (its kernels loaded then) or the map can be older than the
    # 0.8 / 1 s freshness limits by the time they are taken (dropped too_old: no map, no list)
    slow = ("--input-timeout-ms", "60000", "--max-input-age-ms", "60000")
    with locator_and_obstacles(("--fusion", "off", *slow), slow) as ctx:
        yield ctx


def test_locator_and_obstacles_survive_the_payloads_that_killed_them():
    import zenoh
    from eonav.app.processes import drain, stop_service, wait_until
    from eonav.sim.flight import render_flight
    from tests.test_locator_service import VEHICLE, latest_health, posed_frame_payload

    frames = list(render_flight("approach", n_frames=2, rate_hz=4.0, size=128, t0_s=3.0, seed=1))
    with _services() as (s, procs, maps_sub, obs_sub, health_sub):
        health = []
        # BLOCK: every payload here is counted by the services, and a put with DROP was seen lost on a loaded machine
        frame_pub = s.declare_publisher(K.posed_frame(VEHICLE, "nose"), congestion_control=zenoh.CongestionControl.BLOCK)
        map_pub = s.declare_publisher(K.range_map(VEHICLE, "nose"), congestion_control=zenoh.CongestionControl.BLOCK)
        wait_until(lambda: {"locator", "obstacles"} <= set(latest_health(drain(health_sub, health))), timeout=60,
                   what="both services up")
        wait_until(lambda: frame_pub.matching_status.matching and map_pub.matching_status.matching, timeout=30,
                   what="subscribers")
        time.sleep(0.3)

        def counters(name):
            return latest_health(drain(health_sub, health)).get(name, {}).get("counters", {})

        bad_frames = [posed(image=arr(np.zeros((3, 4, 3), t)), encoding="bgr8") for t in (np.float64, np.int32)]
        bad_frames += [posed(seq=2 ** 64 - 1), posed(stamp_us=2 ** 63), posed(position_ned_m=[1e300, 0, 0]),
                       posed(camera=dict(CAM, width=10 ** 9))]
        for i, p in enumerate(bad_frames):
            frame_pub.put(p)
            wait_until(lambda: counters("locator").get("decode_errors", 0) >= i + 1, timeout=20,
                       what=f"bad posed frame {i} counted")
        map_pub.put(range_map(flags=arr(np.ones((3, 4), np.float32))))
        wait_until(lambda: counters("obstacles").get("decode_errors", 0) >= 1, timeout=20, what="bad map counted")

        # still alive and still working: a good pair gives a range map, and the map an obstacle list
        drain(maps_sub)                       # (the bad map itself, put on the map key above)
        t_us = time.time_ns() // 1000
        for i, (t_s, view, _) in enumerate(frames):
            frame_pub.put(posed_frame_payload(i, t_us + i * 250_000, view))
            time.sleep(0.3)
        maps = []
        wait_until(lambda: any(schema.decode(m.payload.to_bytes())["method"] == "dense" for m in drain(maps_sub, maps)),
                   timeout=30, what="a range map after the bad frames")
        wait_until(lambda: drain(obs_sub), timeout=30, what="an obstacle list after the bad map")
        loc, obs = counters("locator"), counters("obstacles")
        assert loc["decode_errors"] == 6 and loc["rejected.range"] == 6 and loc.get("message_errors", 0) == 0
        assert obs["decode_errors"] == 1 and obs["rejected.range"] == 1
        h = latest_health(drain(health_sub, health))
        assert h["locator"]["state"] == "ok" and h["obstacles"]["state"] == "ok"
        for name in ("locator", "obstacles"):
            code, err = stop_service(procs.pop(name), signal.SIGINT, timeout=15)
            assert code == 0, f"{name} exit {code}:\n{err[-3000:]}"
