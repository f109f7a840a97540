"""MCAP recordings (eonav.recording): record -> replay over a real zenoh bus, the Foxglove channels read back with
the ``mcap`` reader and decoded from the schemas stored in the file, rotation by size and time, the replay's wait
for subscribers, ``eonav run --record``, and bad input."""
from __future__ import annotations

import json
import math
import threading
import time

import numpy as np
import pytest

zenoh = pytest.importorskip("zenoh")

from mcap.reader import make_reader  # noqa: E402
from mcap_protobuf.decoder import DecoderFactory  # noqa: E402

from eonav.bus import keys as K  # noqa: E402
from eonav.bus import schema  # noqa: E402
from eonav.bus.session import client_session  # noqa: E402
from eonav.app.processes import router_process, start_service, stop_service, wait_until  # noqa: E402
from eonav.geometry.frames import T_PAPERCAM_OPTICAL, rotation_from_quat_wxyz  # noqa: E402
from eonav.ranging.rangemap import AT_INFINITY, FILLED, VALID  # noqa: E402
from eonav.recording.foxglove import FoxgloveConverter, point_stride  # noqa: E402
from eonav.recording.recorder import Recorder, parse_size  # noqa: E402
from eonav.recording.replayer import read_records, rewrite_vehicle  # noqa: E402
from eonav.recording.writer import RecordingWriter, part_path  # noqa: E402

MSGPACK = "application/msgpack"


def raw_messages(path):
    """(key, zenoh encoding, payload) of the raw channels of a recording, in file order."""
    return [(r.key, r.encoding, r.payload, r.attachment) for r in read_records([path], exclude=["eonav/*/health/*"])]


def bus_messages(vehicle: str, rng) -> list:
    """(key, zenoh encoding, payload, attachment): the project's messages and two foreign encodings, one with an
    attachment."""
    out = []
    for i in range(6):
        img = rng.integers(0, 256, (48, 64), dtype=np.uint8)
        out.append((K.frame(vehicle, "nose"), MSGPACK,
                    schema.encode("frame", camera_id="nose", seq=i, stamp_us=1_000_000 + 100_000 * i, image=img), None))
        out.append((K.nav_state(vehicle), MSGPACK,
                    schema.encode("nav_state", stamp_us=1_000_000 + 100_000 * i + 50_000,
                                  position_ned_m=[float(i), 0.0, -10.0], q_wxyz=[1.0, 0.0, 0.0, 0.0]), None))
    out.append((f"eonav/{vehicle}/custom/raw", "application/octet-stream;bgr8", rng.bytes(3000), b"attachment-1"))
    out.append((f"eonav/{vehicle}/custom/json", "application/json", b'{"a": 1}', None))
    return out


def wait_recorded(health_sub, n: int, timeout: float = 20.0):
    """Wait until the recorder's health says it wrote ``n`` messages."""
    def done():
        for s in iter(health_sub.try_recv, None):
            m = schema.decode(s.payload.to_bytes(), expect="health")
            if m["service"] == "recorder" and m["counters"].get("messages", 0) >= n:
                return True
        return False
    wait_until(done, timeout, what=f"recorder to write {n} messages")


# --------------------------------------------------------------------------------------------------
# round trip over the bus

def test_record_then_replay_gives_identical_payloads_in_order(tmp_path):
    veh = "rt"
    sent = bus_messages(veh, np.random.default_rng(0))
    out = tmp_path / "rt.mcap"
    with router_process() as ep, client_session(ep) as s:
        health = s.declare_subscriber(K.health(veh, "recorder"), zenoh.handlers.FifoChannel(256))
        rec = start_service(["-m", "eonav.recording.recorder", str(out), "--vehicle", veh, "--connect", ep,
                             "--images", "raw", "--health-period-s", "0.2", "--exclude", f"eonav/{veh}/excluded/**"])
        pubs = {k: s.declare_publisher(k, congestion_control=zenoh.CongestionControl.BLOCK) for k, *_ in sent}
        wait_until(lambda: all(p.matching_status.matching for p in pubs.values()), 30, what="recorder subscribed")
        time.sleep(0.1)
        t_put0 = time.time_ns()
        for i, (key, enc, payload, att) in enumerate(sent):
            pubs[key].put(payload, encoding=zenoh.Encoding(enc), attachment=att)
            if i == 3:
                s.put(f"eonav/{veh}/excluded/x", b"not recorded")          # --exclude: left out
        t_put1 = time.time_ns()
        wait_recorded(health, len(sent))
        code, err = stop_service(rec)
        assert code == 0, err

        # the file: one raw channel per key with its zenoh encoding, log and publish times, a Foxglove image channel
        with open(out, "rb") as f:
            reader = make_reader(f)
            summary = reader.get_summary()
            assert summary is not None                           # finished (summary and index written) on SIGINT
            raw = {c.topic: c for c in summary.channels.values() if c.metadata.get("eonav.role") == "raw"}
            assert raw[K.frame(veh, "nose")].message_encoding == "msgpack"
            assert raw[K.frame(veh, "nose")].metadata["eonav.kind"] == "frame"
            assert raw[f"eonav/{veh}/custom/raw"].metadata["zenoh.encoding"] == "application/octet-stream;bgr8"
            assert raw[f"eonav/{veh}/custom/json"].message_encoding == "json"
            images = [c for c in summary.channels.values() if c.topic == "/camera/nose/image"]
            assert len(images) == 1 and summary.schemas[images[0].schema_id].name == "foxglove.RawImage"
            times = [(m.log_time, m.publish_time) for _, c, m in reader.iter_messages(log_time_order=False)
                     if c.metadata.get("eonav.role") == "raw" and "/health/" not in c.topic]
        logs = [t for t, _ in times]
        assert logs == sorted(logs) and t_put0 <= logs[0] and logs[-1] <= t_put1 + 5e9
        # publish time: the router's timestamp (HLC, set when the sample passed it), before the recorder got it
        assert all(-1e6 <= lt - pt < 1e9 for lt, pt in times), times[:3]
        assert raw_messages(out) == sent

        # replay onto the bus: the same keys, encodings, payloads and attachments, in the same order
        got = s.declare_subscriber(f"eonav/{veh}/**", zenoh.handlers.FifoChannel(1024))
        # the stopped recorder's last health can still be on its way through a loaded router: not the replay's
        time.sleep(0.3)
        late = [str(x.key_expr) for x in iter(got.try_recv, None)]
        assert all(k == K.health(veh, "recorder") for k in late), late
        rp = start_service(["-m", "eonav.recording.replayer", str(out), "--vehicle", "replayer", "--connect", ep,
                            "--as-fast-as-possible"])
        rc, err = rp.wait(30), rp.stderr.read()
        assert rc == 0, err
        received = []
        wait_until(lambda: received.extend(iter(got.try_recv, None)) or len(received) >= len(sent), 10,
                   what="replayed samples")
        time.sleep(0.3)
        received.extend(iter(got.try_recv, None))
        replayed = [(str(x.key_expr), str(x.encoding), x.payload.to_bytes(),
                     x.attachment.to_bytes() if x.attachment is not None else None) for x in received]
        assert replayed == sent


def test_rewrite_vehicle():
    assert rewrite_vehicle("eonav/a/camera/nose/frame", "b") == "eonav/b/camera/nose/frame"
    assert rewrite_vehicle("other/a/x", "b") == "other/a/x"


def test_publish_time_is_the_log_time_when_the_sample_has_none(tmp_path):
    """MCAP publish_time: the sample's zenoh timestamp when it has one, else its log time (docs: never 0, which a
    reader would show as 1970 and sort before everything)."""
    path = tmp_path / "pt.mcap"
    rec = Recorder(RecordingWriter(path))
    rec.record("eonav/pt/a", "text/plain", b"stamped", 5_000_000_000, publish_time_ns=4_990_000_000)
    rec.record("eonav/pt/a", "text/plain", b"unstamped", 6_000_000_000)
    rec.liveliness("eonav/pt/alive/x", True, 7_000_000_000)
    rec.close()
    with open(path, "rb") as f:
        got = [(m.data, m.log_time, m.publish_time) for _, _, m in make_reader(f).iter_messages(log_time_order=False)]
    assert got == [(b"stamped", 5_000_000_000, 4_990_000_000), (b"unstamped", 6_000_000_000, 6_000_000_000),
                   (b'{"alive": true}', 7_000_000_000, 7_000_000_000)]


def test_a_recording_cut_short_replays_the_messages_before_the_cut(tmp_path):
    """A recorder killed mid-write (SIGKILL, power lost) leaves a file with no summary and a torn last chunk: the
    replay reads it front to back and gives every message of the chunks written whole, in order, and its keys (so
    the service starts instead of failing). Which messages those are comes from the intact file's chunk index (a
    message every 1 ms of log time, 16 KiB chunks of 2 kB messages)."""
    from eonav.recording.replayer import recorded_keys
    rng = np.random.default_rng(3)
    full = tmp_path / "full.mcap"
    rec = Recorder(RecordingWriter(full, chunk_bytes=16 * 1024))
    sent = []
    for i in range(50):
        payload = rng.bytes(2000)
        rec.record("eonav/cut/k", "application/octet-stream", payload, i * 1_000_000)
        sent.append(("eonav/cut/k", "application/octet-stream", payload, None))
    rec.close()
    data = full.read_bytes()
    cut = len(data) // 2
    with open(full, "rb") as f:
        chunks = make_reader(f).get_summary().chunk_indexes
    whole = [c for c in chunks if c.chunk_start_offset + c.chunk_length <= cut]
    n_whole = max(c.message_end_time for c in whole) // 1_000_000 + 1          # messages 0 .. end time in ms
    assert 5 <= n_whole < 50
    short = tmp_path / "short.mcap"
    short.write_bytes(data[:cut])
    got = raw_from(short)
    assert len(got) >= n_whole and got == sent[:len(got)]
    assert recorded_keys([short]) == [("eonav/cut/k", "application/octet-stream")]


def test_replay_reads_in_file_order_when_the_clock_stepped_back(tmp_path):
    """The replay puts messages in the order the recorder received them (file order), not sorted by log time: the
    host clock stepped back 0.9 s mid-recording (NTP or GPS time set after boot) must not move the later messages
    before the earlier ones."""
    path = tmp_path / "step.mcap"
    rec = Recorder(RecordingWriter(path))
    log_s = [10.0, 10.1, 10.2, 9.3, 9.4]
    for i, t in enumerate(log_s):
        rec.record("eonav/step/k", "text/plain", b"msg-%d" % i, int(t * 1e9))
    rec.close()
    assert [r.payload for r in read_records([path])] == [b"msg-0", b"msg-1", b"msg-2", b"msg-3", b"msg-4"]


def test_one_key_with_two_encodings_is_two_channels(tmp_path):
    """A raw channel is one key AND one zenoh encoding: a key whose publisher switches from msgpack to JSON is
    recorded on two channels, each with its own ``zenoh.encoding``, and every sample is replayed with the encoding
    it was sent with."""
    path = tmp_path / "enc.mcap"
    rec = Recorder(RecordingWriter(path))
    nav = schema.encode("nav_state", stamp_us=1_000_000, position_ned_m=[1.0, 2.0, 3.0], q_wxyz=[1.0, 0.0, 0.0, 0.0])
    sent = [("eonav/enc/k", MSGPACK, nav, None), ("eonav/enc/k", "application/json", b'{"a": 1}', None),
            ("eonav/enc/k", MSGPACK, nav, None)]
    for i, (key, enc, payload, _) in enumerate(sent):
        rec.record(key, enc, payload, (i + 1) * 1_000_000_000)
    rec.close()
    assert raw_messages(path) == sent
    with open(path, "rb") as f:
        raw = [c for c in make_reader(f).get_summary().channels.values() if c.metadata.get("eonav.role") == "raw"]
    assert sorted((c.message_encoding, c.metadata["zenoh.encoding"]) for c in raw) == [
        ("json", "application/json"), ("msgpack", MSGPACK)]


# --------------------------------------------------------------------------------------------------
# Foxglove channels

CAM = {"name": "nose", "width": 40, "height": 30, "fx": 50.0, "fy": 50.0, "cx": 19.5, "cy": 14.5,
       "l_m": [1.0, 0.0, 0.0], "eps_deg": [0.0, 0.0, 0.0]}


def plane_range_map():
    """A 40 x 30 map of a wall at x_c = 20 m: rows 0-4 no estimate (NaN), 5-9 at infinity, 10-14 FILLED, the rest
    VALID."""
    r = np.full((30, 40), 20.0, np.float32)
    flags = np.full((30, 40), VALID, np.uint8)
    r[0:5], flags[0:5] = np.nan, 0
    r[5:10], flags[5:10] = np.inf, AT_INFINITY
    flags[10:15] = FILLED
    return r, flags


def fixture_messages():
    img = np.zeros((24, 32, 3), np.uint8)
    img[:, :, 2] = np.arange(32, dtype=np.uint8)[None, :] * 8            # red ramp left -> right
    r, flags = plane_range_map()
    q = [math.cos(0.25), 0.0, 0.0, math.sin(0.25)]                        # yaw 0.5 rad
    obstacles = [{"id": 3, "distance_m": 20.5, "bearing_deg": -5.0, "position_ned_m": [20.0, -2.0, -3.0],
                  "extent_ned_m": [0.1, 2.0, 4.0]},
                 {"id": 7, "distance_m": 60.0, "bearing_deg": 10.0, "position_ned_m": [55.0, 12.0, -1.0],
                  "extent_ned_m": [3.0, 3.0, 6.0]}]
    return [
        schema.encode("frame", camera_id="nose", seq=0, stamp_us=1_000_000, encoding="bgr8", image=img),
        schema.encode("nav_state", stamp_us=1_010_000, q_wxyz=q),                      # attitude only
        schema.encode("nav_state", stamp_us=1_020_000, position_ned_m=[5.0, 6.0, -7.0]),  # position only
        schema.encode("posed_frame", camera_id="nose", seq=0, stamp_us=1_000_000, encoding="mono8",
                      image=np.zeros((30, 40), np.uint8), camera=CAM, position_ned_m=[5.0, 6.0, -7.0], q_wxyz=q),
        schema.encode("range_map", camera_id="nose", seq=1, stamp_us=1_200_000, method="dense", range_m=r,
                      confidence=np.ones_like(r), flags=flags, camera=CAM, position_ned_m=[5.0, 6.0, -7.0],
                      q_wxyz=q),
        schema.encode("obstacle_list", stamp_us=1_200_000, camera_id="nose", obstacles=obstacles),
    ]


def record_fixture(path, image_format="raw", max_points=20000):
    w = RecordingWriter(path)
    rec = Recorder(w, FoxgloveConverter(image_format, near_m=5.0, far_m=150.0, max_points=max_points))
    keys = [K.frame("fx", "nose"), K.nav_state("fx"), K.nav_state("fx"), K.posed_frame("fx", "nose"),
            K.range_map("fx", "nose"), K.obstacles("fx")]
    for i, (key, payload) in enumerate(zip(keys, fixture_messages())):
        rec.record(key, MSGPACK, payload, 1_000_000_000 + i * 1_000_000)
    rec.close()


def decoded(path) -> dict:
    """topic -> [(schema name, schema encoding, message encoding, decoded protobuf)] of the Foxglove channels."""
    out = {}
    with open(path, "rb") as f:
        reader = make_reader(f, decoder_factories=[DecoderFactory()])
        topics = sorted({c.topic for c in reader.get_summary().channels.values()
                         if c.metadata.get("eonav.role") == "foxglove"})
        for sch, ch, _msg, dec in reader.iter_decoded_messages(topics=topics, log_time_order=False):
            out.setdefault(ch.topic, []).append((sch.name, sch.encoding, ch.message_encoding, dec))
    return out


def test_foxglove_channels_have_their_schemas_and_decode(tmp_path):
    path = tmp_path / "fx.mcap"
    record_fixture(path)
    d = decoded(path)
    names = {t: {(n, se, me) for n, se, me, _ in v} for t, v in d.items()}
    assert names == {
        "/camera/nose/image": {("foxglove.RawImage", "protobuf", "protobuf")},
        "/camera/nose/calibration": {("foxglove.CameraCalibration", "protobuf", "protobuf")},
        "/pose": {("foxglove.PoseInFrame", "protobuf", "protobuf")},
        "/tf": {("foxglove.FrameTransform", "protobuf", "protobuf")},
        "/range/nose/image": {("foxglove.RawImage", "protobuf", "protobuf")},
        "/range/nose/points": {("foxglove.PointCloud", "protobuf", "protobuf")},
        "/obstacles": {("foxglove.SceneUpdate", "protobuf", "protobuf")},
    }
    # the frame: same size and pixels
    img = d["/camera/nose/image"][0][3]
    assert (img.width, img.height, img.encoding, img.step) == (32, 24, "bgr8", 96)
    px = np.frombuffer(img.data, np.uint8).reshape(24, 32, 3)
    assert px[5, 10].tolist() == [0, 0, 80] and img.frame_id == "cam_nose_optical"
    assert (img.timestamp.seconds, img.timestamp.nanos) == (1, 0)
    # the pose: only once attitude AND position are known (the attitude-only state gives none)
    poses = d["/pose"]
    assert len(poses) == 1
    p = poses[0][3].pose
    assert [p.position.x, p.position.y, p.position.z] == [5.0, 6.0, -7.0]
    assert [p.orientation.w, p.orientation.z] == pytest.approx([math.cos(0.25), math.sin(0.25)])
    tf = {(t.parent_frame_id, t.child_frame_id): t for *_, t in d["/tf"]}
    assert set(tf) == {("ned", "body"), ("body", "cam_nose"), ("cam_nose", "cam_nose_optical")}
    mount = tf[("body", "cam_nose")]
    assert [mount.translation.x, mount.translation.y, mount.translation.z] == [1.0, 0.0, 0.0]
    opt = tf[("cam_nose", "cam_nose_optical")].rotation
    R = rotation_from_quat_wxyz([opt.w, opt.x, opt.y, opt.z])
    assert np.allclose(R, T_PAPERCAM_OPTICAL)
    assert np.allclose(R @ [0, 0, 1], [1, 0, 0])          # the optical z axis (into the image) is the paper's Xc
    cal = d["/camera/nose/calibration"][0][3]
    assert (cal.width, cal.height) == (40, 30) and list(cal.K) == [50.0, 0, 19.5, 0, 50.0, 14.5, 0, 0, 1]
    # the range picture: the map's size; no estimate and infinity black; FILLED at half the brightness of VALID
    rimg = d["/range/nose/image"][0][3]
    assert (rimg.width, rimg.height, rimg.encoding) == (40, 30, "bgr8")
    rp = np.frombuffer(rimg.data, np.uint8).reshape(30, 40, 3).astype(int)
    assert rp[0:10].max() == 0
    assert rp[20, 7].max() > 0 and (rp[12, 7] == rp[20, 7] // 2).all()
    # the point cloud: every VALID or FILLED finite pixel (30 x 40 minus 10 rows), in the camera frame
    cloud = d["/range/nose/points"][0][3]
    assert cloud.frame_id == "cam_nose" and cloud.point_stride == 16
    assert [f.name for f in cloud.fields] == ["x", "y", "z", "range"]
    pts = np.frombuffer(cloud.data, "<f4").reshape(-1, 4)
    assert len(pts) == 20 * 40
    assert np.all(pts[:, 0] == 20.0) and np.all(pts[:, 3] == 20.0)
    # pixel (u=0, v=29): y = 20 (0 - 19.5) / 50 = -7.8, z = 20 (29 - 14.5) / 50 = 5.8 (hand-derived)
    assert pts[-40, 1:3] == pytest.approx([-7.8, 5.8])
    assert pts[0, 1:3] == pytest.approx([-7.8, 20 * (10 - 14.5) / 50])   # first point: u=0 on row 10
    # the obstacles: one cube per obstacle at its NED point, extent (at least 0.3 m), all older entities deleted
    upd = d["/obstacles"][0][3]
    assert len(upd.deletions) == 1 and len(upd.entities) == 2
    e = {x.id: x for x in upd.entities}
    c = e["obstacle/3"].cubes[0]
    assert [c.pose.position.x, c.pose.position.y, c.pose.position.z] == [20.0, -2.0, -3.0]
    assert [c.size.x, c.size.y, c.size.z] == pytest.approx([0.3, 2.0, 4.0])
    assert e["obstacle/3"].frame_id == "ned" and "20.5 m" in e["obstacle/3"].texts[0].text


def test_foxglove_layout_shows_recorded_topics(tmp_path):
    # every topic docs/foxglove-layout.json shows is one a recording of camera "nose" has
    from pathlib import Path
    layout = json.loads((Path(__file__).parents[1] / "docs" / "foxglove-layout.json").read_text())
    shown = set()
    for cfg in layout["configById"].values():
        shown |= {v for k, v in cfg.get("imageMode", {}).items() if k.endswith("Topic")}
        shown |= set(cfg.get("topics", {}))
        shown |= {p["value"].split(".", 1)[0] for p in cfg.get("paths", [])}
    path = tmp_path / "fx.mcap"
    record_fixture(path)
    recorded = set(decoded(path))
    assert shown and shown <= recorded, shown - recorded
    assert layout["configById"]["3D!scene"]["followTf"] == "body"


def test_point_cloud_subsampling_and_compressed_images(tmp_path):
    # at most 100 points: stride 4 (ceil(30/4) x ceil(40/4) = 80 cells; stride 3 would be 140); the rows kept are
    # v = 0, 4, ..., 28, of which 12, 16, 20, 24, 28 have a range: 5 rows x 10 columns
    assert point_stride(30, 40, 100) == 4 and point_stride(30, 40, 1200) == 1 and point_stride(30, 40, 1199) == 2
    path = tmp_path / "fx.mcap"
    record_fixture(path, image_format="jpeg", max_points=100)
    d = decoded(path)
    cloud = d["/range/nose/points"][0][3]
    assert len(cloud.data) // 16 == 50
    import cv2
    name, *_, img = d["/camera/nose/image"][0]
    assert name == "foxglove.CompressedImage" and img.format == "jpeg"
    assert cv2.imdecode(np.frombuffer(img.data, np.uint8), cv2.IMREAD_COLOR).shape == (24, 32, 3)


def test_point_cloud_scales_columns_by_fx_and_rows_by_fy():
    """A camera with non-square pixels (fx = 40, fy = 20): a pixel (u, v) at range r is r [1, (u - cx)/fx,
    (v - cy)/fy]; hand-derived for the four corners of a 3 x 4 map at 10 m (cx = 1.5, cy = 1)."""
    from eonav.recording.foxglove import range_points
    cam = {"fx": 40.0, "fy": 20.0, "cx": 1.5, "cy": 1.0}
    pts = range_points(np.full((3, 4), 10.0, np.float32), None, cam)
    assert pts.shape == (12, 4)
    corners = pts.reshape(3, 4, 4)[[0, 0, 2, 2], [0, 3, 0, 3]]
    # y = 10 (u - 1.5) / 40 = -0.375 / +0.375; z = 10 (v - 1) / 20 = -0.5 / +0.5
    np.testing.assert_allclose(corners, [[10, -0.375, -0.5, 10], [10, 0.375, -0.5, 10],
                                         [10, -0.375, 0.5, 10], [10, 0.375, 0.5, 10]], rtol=1e-6)


def test_foxglove_stamps_keep_the_microseconds(tmp_path):
    """Foxglove timestamps are (seconds, nanoseconds) of the message's stamp_us: the pose of the fixture (stamp
    1_020_000 us) is at 1 s + 20 ms, the obstacles (1_200_000 us) at 1 s + 200 ms."""
    path = tmp_path / "fx.mcap"
    record_fixture(path)
    d = decoded(path)
    ts = d["/pose"][0][3].timestamp
    assert (ts.seconds, ts.nanos) == (1, 20_000_000)
    upd = d["/obstacles"][0][3]
    assert {(e.timestamp.seconds, e.timestamp.nanos) for e in upd.entities} == {(1, 200_000_000)}
    cloud = d["/range/nose/points"][0][3]
    assert (cloud.timestamp.seconds, cloud.timestamp.nanos) == (1, 200_000_000)


@pytest.mark.parametrize("eps_deg,axis_in_body", [
    ([90.0, 0.0, 0.0], [0.0, 1.0, 0.0]),                                  # turned right: looks along body +Y
    ([0.0, 30.0, 0.0], [math.cos(math.radians(30)), 0.0, -0.5]),          # tilted 30 deg up (FRD: up is -Z)
])
def test_camera_mount_transform_points_the_optical_axis_where_the_camera_looks(tmp_path, eps_deg, axis_in_body):
    """The /tf body -> cam_<id> transform is the camera's pose in the body (p_body = R p_cam + l): the paper's
    camera axis Xc of a camera mounted 90 deg to the right (eps1 about Zc, like a yaw) is the body's +Y, of a
    camera tilted up 30 deg (eps2 about Yc, like a pitch) it is (cos 30, 0, -sin 30). Hand-derived from the
    mounting; the translation is the lever arm."""
    cam = dict(CAM, eps_deg=eps_deg, l_m=[0.5, 0.2, -0.1])
    path = tmp_path / "mount.mcap"
    rec = Recorder(RecordingWriter(path), FoxgloveConverter("raw"))
    rec.record(K.posed_frame("mt", "nose"), MSGPACK,
               schema.encode("posed_frame", camera_id="nose", seq=0, stamp_us=1_000_000, encoding="mono8",
                             image=np.zeros((30, 40), np.uint8), camera=cam, position_ned_m=[0.0, 0.0, 0.0],
                             q_wxyz=[1.0, 0.0, 0.0, 0.0]), 1_000_000_000)
    rec.close()
    tf = {(t.parent_frame_id, t.child_frame_id): t for *_, t in decoded(path)["/tf"]}
    mount = tf[("body", "cam_nose")]
    R = rotation_from_quat_wxyz([mount.rotation.w, mount.rotation.x, mount.rotation.y, mount.rotation.z])
    assert R @ [1.0, 0.0, 0.0] == pytest.approx(axis_in_body, abs=1e-9)
    assert [mount.translation.x, mount.translation.y, mount.translation.z] == pytest.approx([0.5, 0.2, -0.1])


def record_messages(path, items, converter=None):
    """Record (key, payload, log_time_ns, publish_time_ns) with a Foxglove converter (raw images)."""
    rec = Recorder(RecordingWriter(path), converter or FoxgloveConverter("raw"))
    for key, payload, log_ns, pub_ns in items:
        rec.record(key, MSGPACK, payload, log_ns, publish_time_ns=pub_ns)
    rec.close()


def test_range_picture_and_frame_share_the_frame_of_their_calibration(tmp_path):
    """Foxglove projects an image with the CameraCalibration of the same frame_id: the range picture is on the
    camera's own pixel grid, so it (like the camera image) is in cam_<id>_optical, the calibration's frame, not in
    cam_<id> (whose x axis is the optical axis)."""
    path = tmp_path / "fx.mcap"
    record_fixture(path)
    d = decoded(path)
    cal = d["/camera/nose/calibration"][0][3]
    assert cal.frame_id == "cam_nose_optical"
    assert d["/range/nose/image"][0][3].frame_id == cal.frame_id
    assert d["/camera/nose/image"][0][3].frame_id == cal.frame_id


def test_calibration_projection_matrix_maps_a_point_to_its_pixel(tmp_path):
    """CameraCalibration.P (what Foxglove projects with) takes a point of the optical frame to its pixel: the point
    seen at pixel (u, v) = (3, 25) at x_c = 20 m of the fixture camera (fx = fy = 50, cx = 19.5, cy = 14.5) is
    (x, y, z)_optical = (20 (3 - 19.5) / 50, 20 (25 - 14.5) / 50, 20) = (-6.6, 4.2, 20); P [x y z 1] / w = (3, 25).
    Hand-derived from eqs. 8-9."""
    path = tmp_path / "fx.mcap"
    record_fixture(path)
    cal = decoded(path)["/camera/nose/calibration"][0][3]
    P = np.asarray(cal.P).reshape(3, 4)
    uvw = P @ [-6.6, 4.2, 20.0, 1.0]
    assert uvw[:2] / uvw[2] == pytest.approx([3.0, 25.0])
    assert np.asarray(cal.K).reshape(3, 3) @ [-6.6, 4.2, 20.0] / 20.0 == pytest.approx([3.0, 25.0, 1.0])


def test_obstacles_gone_from_the_list_are_gone_from_the_scene(tmp_path):
    """Each /obstacles SceneUpdate replaces the scene: an obstacle the tracker dropped must not stay drawn. Applying
    the updates as Foxglove does (a deletion of type ALL removes every entity of the topic up to its timestamp,
    MATCHING_ID only the one with its id; then the entities are added) leaves obstacle 7 after a list of 3 and 7
    followed by one of 7, and nothing after an empty list."""
    def obstacle(i, d):
        return {"id": i, "distance_m": d, "bearing_deg": 0.0, "position_ned_m": [d, 0.0, -2.0],
                "extent_ned_m": [1.0, 1.0, 1.0]}
    lists = [[obstacle(3, 20.0), obstacle(7, 40.0)], [obstacle(7, 38.0)], []]
    path = tmp_path / "obs.mcap"
    record_messages(path, [(K.obstacles("ob"), schema.encode("obstacle_list", stamp_us=1_000_000 + 100_000 * i,
                                                             camera_id="nose", obstacles=obs),
                            (i + 1) * 1_000_000_000, None) for i, obs in enumerate(lists)])
    scene, seen = {}, []
    for *_, upd in decoded(path)["/obstacles"]:
        for dl in upd.deletions:
            kind = dl.DESCRIPTOR.fields_by_name["type"].enum_type.values_by_number[dl.type].name
            t = (dl.timestamp.seconds, dl.timestamp.nanos)
            if kind == "ALL":
                scene = {k: e for k, e in scene.items() if (e.timestamp.seconds, e.timestamp.nanos) > t}
            else:
                scene.pop(dl.id, None)
        scene.update({e.id: e for e in upd.entities})
        seen.append(sorted(scene))
    assert seen == [["obstacle/3", "obstacle/7"], ["obstacle/7"], []]


def test_obstacle_cubes_are_red_when_near_and_yellow_when_far(tmp_path):
    """Cube colour (r, g, b) = (1, g, 0) with g = (d - near) / (far - near) clamped to 0..1, near 5 m and far 150 m:
    2 m -> 0 (red), 20.5 m -> 15.5 / 145, 60 m -> 55 / 145, 400 m -> 1 (yellow). Hand-derived."""
    obs = [{"id": i, "distance_m": d, "bearing_deg": 0.0, "position_ned_m": [d, 0.0, 0.0], "extent_ned_m": [1, 1, 1]}
           for i, d in enumerate([2.0, 20.5, 60.0, 400.0])]
    path = tmp_path / "col.mcap"
    record_messages(path, [(K.obstacles("co"), schema.encode("obstacle_list", stamp_us=1_000_000, camera_id="nose",
                                                             obstacles=obs), 1_000_000_000, None)],
                    FoxgloveConverter("raw", near_m=5.0, far_m=150.0))
    upd = decoded(path)["/obstacles"][0][3]
    col = {e.id: e.cubes[0].color for e in upd.entities}
    got = [[col[f"obstacle/{i}"].r, col[f"obstacle/{i}"].g, col[f"obstacle/{i}"].b] for i in range(4)]
    np.testing.assert_allclose(got, [[1, 0, 0], [1, 15.5 / 145, 0], [1, 55 / 145, 0], [1, 1, 0]], rtol=1e-6)


def test_foxglove_messages_keep_the_log_and_publish_time_of_their_sample(tmp_path):
    """A Foxglove message made from a sample has the sample's log time and publish time (its zenoh timestamp,
    10 ms before it was received here), not its log time twice."""
    path = tmp_path / "pt.mcap"
    nav = schema.encode("nav_state", stamp_us=1_000_000, position_ned_m=[1.0, 2.0, 3.0], q_wxyz=[1.0, 0.0, 0.0, 0.0])
    record_messages(path, [(K.nav_state("pt"), nav, 5_000_000_000, 4_990_000_000)])
    with open(path, "rb") as f:
        got = {(c.topic, m.log_time, m.publish_time) for _, c, m in make_reader(f).iter_messages(log_time_order=False)}
    assert got == {(K.nav_state("pt"), 5_000_000_000, 4_990_000_000), ("/pose", 5_000_000_000, 4_990_000_000),
                   ("/tf", 5_000_000_000, 4_990_000_000)}


# --------------------------------------------------------------------------------------------------
# rotation

def write_random(path, n, log_step_ns, **kw):
    rng = np.random.default_rng(1)
    w = RecordingWriter(path, **kw)
    rec = Recorder(w)
    sent = []
    for i in range(n):
        key = f"eonav/rot/k{i % 2}"
        payload, att = rng.bytes(4000), (b"a%d" % i if i % 7 == 0 else None)
        rec.record(key, "application/octet-stream", payload, i * log_step_ns, attachment=att)
        sent.append((key, "application/octet-stream", payload, att))
    rec.close()
    return w, sent


def test_rotation_by_size(tmp_path):
    split = 64 * 1024
    w, sent = write_random(tmp_path / "big.mcap", 300, 1_000_000, split_bytes=split)    # 1.2 MB, incompressible
    assert w.files == [part_path(tmp_path / "big.mcap", i) for i in range(len(w.files))]
    assert w.files[0].name == "big_000.mcap" and not (tmp_path / "big.mcap").exists()
    assert len(w.files) >= 12
    for p in w.files:
        with open(p, "rb") as f:
            s = make_reader(f).get_summary()
        assert s is not None and s.statistics.message_count > 0                # each part complete on its own
        assert p.stat().st_size <= split + w.chunk_bytes + 16 * 1024
    assert [m for p in w.files for m in raw_from(p)] == sent                  # nothing lost, same order
    # below the threshold: one part
    w2, _ = write_random(tmp_path / "small.mcap", 10, 1_000_000, split_bytes=split)
    assert [p.name for p in w2.files] == ["small_000.mcap"]


def test_an_attachment_stays_in_the_file_of_its_payload(tmp_path):
    """Rotation by size never separates a sample's attachment from its payload: the replay pairs them within one
    file. Attachments of 20 kB are larger than a chunk (16 kB for a 64 KiB split), so the file grows past the split
    size right after an attachment is written: the payload must still go into that file."""
    rng = np.random.default_rng(2)
    w = RecordingWriter(tmp_path / "att.mcap", split_bytes=64 * 1024)
    assert w.chunk_bytes == 16 * 1024
    rec = Recorder(w)
    sent = []
    for i in range(20):
        payload, att = rng.bytes(100), rng.bytes(20_000)
        rec.record("eonav/att/k", "application/octet-stream", payload, i * 1_000_000, attachment=att)
        sent.append(("eonav/att/k", "application/octet-stream", payload, att))
    rec.close()
    assert len(w.files) >= 4
    assert [m for p in w.files for m in raw_from(p)] == sent


def raw_from(path):
    return [(r.key, r.encoding, r.payload, r.attachment) for r in read_records([path])]


def test_rotation_by_time(tmp_path):
    # 100 messages 0.1 s apart (log time 0 .. 9.9 s), a new part every 3 s: [0, 3), [3, 6), [6, 9), [9, 9.9]
    w, sent = write_random(tmp_path / "t.mcap", 100, 100_000_000, split_s=3.0)
    firsts = []
    for p in w.files:
        with open(p, "rb") as f:
            st = make_reader(f).get_summary().statistics
        firsts += [st.message_start_time / 1e9, st.message_end_time / 1e9]
    assert firsts == pytest.approx([0.0, 2.9, 3.0, 5.9, 6.0, 8.9, 9.0, 9.9])
    assert [m for p in w.files for m in raw_from(p)] == sent
    w2, _ = write_random(tmp_path / "t2.mcap", 100, 100_000_000, split_s=10.0)
    assert len(w2.files) == 1


def test_parse_size_and_writer_input_errors(tmp_path):
    from eonav import InputError
    assert parse_size("64K") == 65536 and parse_size("2M") == 2 * 1024 ** 2 and parse_size("1000") == 1000
    assert parse_size(None) is None and parse_size("0") is None
    with pytest.raises(InputError, match="expected bytes"):
        parse_size("lots")
    (tmp_path / "x.mcap").write_bytes(b"old")
    with pytest.raises(InputError, match="already exists"):
        RecordingWriter(tmp_path / "x.mcap")
    with pytest.raises(InputError, match="ending in .mcap"):
        RecordingWriter(tmp_path / "x.bag")
    with pytest.raises(InputError, match="at least 64 KiB"):
        RecordingWriter(tmp_path / "y.mcap", split_bytes=1000)


# --------------------------------------------------------------------------------------------------
# replay: waiting for subscribers

def write_sequence(path, n=40, step_s=0.05, vehicle="w"):
    rec = Recorder(RecordingWriter(path))
    for i in range(n):
        rec.record(f"eonav/{vehicle}/data", "text/plain", b"msg-%03d" % i, int(i * step_s * 1e9))
    rec.close()
    return [b"msg-%03d" % i for i in range(n)]


def replay_with_late_subscriber(ep, path, wait_timeout: float, late_s: float) -> list:
    """Start a real-time replay; declare the data subscriber ``late_s`` after the replay's first health message
    (the process is up); return the payloads it got."""
    with client_session(ep) as s:
        health = s.declare_subscriber(K.health("w", "replay"), zenoh.handlers.FifoChannel(64))
        rp = start_service(["-m", "eonav.recording.replayer", str(path), "--vehicle", "w", "--connect", ep,
                            "--wait-timeout-s", str(wait_timeout)])
        try:
            wait_until(lambda: health.try_recv() is not None, 30, what="replay up")
            time.sleep(late_s)
            sub = s.declare_subscriber("eonav/w/data", zenoh.handlers.FifoChannel(256))
            assert rp.wait(30) == 0, rp.stderr.read()
            time.sleep(0.3)
            return [x.payload.to_bytes() for x in iter(sub.try_recv, None)]
        finally:
            if rp.poll() is None:
                stop_service(rp)


def test_replay_waits_for_subscribers_before_the_first_message(tmp_path):
    path = tmp_path / "seq.mcap"
    sent = write_sequence(path)                          # 40 messages over 2 s
    with router_process() as ep:
        # waiting: the subscriber joins 0.7 s after the replay came up and still gets every message from the first
        assert replay_with_late_subscriber(ep, path, wait_timeout=20, late_s=0.7) == sent
        # not waiting: the same late subscriber misses the first messages (the rest arrives, in order)
        got = replay_with_late_subscriber(ep, path, wait_timeout=0, late_s=0.7)
        assert 0 < len(got) < len(sent) and got == sent[len(sent) - len(got):]


def replay_in_process(path, vehicle: str, speed: float) -> tuple[list, str]:
    """Run the replay's own body on a Node of an in-process session (its subscriber in the same session) until it
    stops; returns [(monotonic arrival time, payload)] and the node's stop reason."""
    import argparse

    from eonav.app.processes import free_port
    from eonav.bus.node import Node
    from eonav.bus.session import listener_session
    from eonav.recording import replayer
    args = argparse.Namespace(inputs=[str(path)], speed=speed, as_fast_as_possible=False, include=None, exclude=None,
                              as_vehicle=None, wait_for=None, wait_timeout_s=5.0, vehicle=vehicle)
    arrivals = []
    with listener_session(free_port()) as s:
        s.declare_subscriber(f"eonav/{vehicle}/data",
                             lambda x: arrivals.append((time.monotonic(), x.payload.to_bytes())))
        node = Node("replay", args, s)
        replayer.body(node, args)
        assert node.stop_event.wait(30)
        for t in node._workers:
            t.join(5)
    return arrivals, node.stop_reason


def test_replay_speed_factor_paces_by_log_time(tmp_path):
    """``--speed 4``: a message recorded t seconds after the first is put t / 4 seconds after it (never earlier).
    11 messages over 4 s of log time arrive over 1 s (4 s if the factor were ignored, 16 s if it multiplied; the
    bound between leaves a loaded machine 1.5 s of lateness)."""
    path = tmp_path / "speed.mcap"
    sent = write_sequence(path, n=11, step_s=0.4, vehicle="sp")
    arrivals, reason = replay_in_process(path, "sp", 4.0)
    assert reason == "end of the recording (11 messages)"
    assert [p for _, p in arrivals] == sent
    offsets = [t - arrivals[0][0] for t, _ in arrivals]
    for i, off in enumerate(offsets):
        assert off >= i * 0.4 / 4 - 0.01, (i, offsets)
    assert offsets[-1] < 2.5, offsets


def test_replay_paces_by_log_time_not_publish_time(tmp_path):
    """Pacing follows the log times (when the recorder received each sample), not the publish times: 6 samples
    received 0.1 s apart that all carry one zenoh timestamp (stamped by a source that sent them in a burst, or by a
    clock that stood still) still arrive 0.1 s apart at --speed 1, the last 0.5 s after the first."""
    path = tmp_path / "pace.mcap"
    rec = Recorder(RecordingWriter(path))
    sent = [b"msg-%d" % i for i in range(6)]
    for i, payload in enumerate(sent):
        rec.record("eonav/pc/data", "text/plain", payload, 1_000_000_000 + i * 100_000_000, publish_time_ns=900_000_000)
    rec.close()
    arrivals, reason = replay_in_process(path, "pc", 1.0)
    assert reason == "end of the recording (6 messages)"
    assert [p for _, p in arrivals] == sent
    offsets = [t - arrivals[0][0] for t, _ in arrivals]
    for i, off in enumerate(offsets):
        assert off >= i * 0.1 - 0.01, (i, offsets)
    assert offsets[-1] < 2.0, offsets


# --------------------------------------------------------------------------------------------------
# eonav run --record, and bad input

def test_run_with_record_records_the_run(tmp_path):
    from eonav.app.launcher import run_pipeline
    src = tmp_path / "src.mcap"
    sent = write_sequence(src, n=20, step_s=0.02, vehicle="runrec")
    out = tmp_path / "run.mcap"
    spec = {"services": [{"name": "replay", "module": "eonav.recording.replayer", "restart": False,
                          "args": [str(src), "--as-fast-as-possible"]}]}
    code = run_pipeline(spec, vehicle="runrec", exit_when_done="replay", quiet=True, record=str(out),
                        log_dir=str(tmp_path / "logs"))
    assert code == 0, (tmp_path / "logs" / "recorder.log").read_text()
    # the replay waited for the recorder (its only subscriber), so nothing was lost; the file was finished on stop
    assert [p for k, _, p, _ in raw_messages(out) if k == "eonav/runrec/data"] == sent
    with open(out, "rb") as f:
        s = make_reader(f).get_summary()
    assert any(c.topic == "eonav/runrec/alive/replay" for c in s.channels.values())   # liveliness recorded too


def test_cli_bad_input_is_a_configuration_error(tmp_path):
    (tmp_path / "exists.mcap").write_bytes(b"")
    (tmp_path / "junk.mcap").write_bytes(b"not an mcap file at all")
    p = start_service(["-m", "eonav.app.cli", "record", str(tmp_path / "exists.mcap"), "--listen", "tcp/127.0.0.1:0"])
    code, err = p.wait(30), p.stderr.read()
    assert code == 2 and "already exists" in err, err
    p = start_service(["-m", "eonav.app.cli", "replay", str(tmp_path / "junk.mcap"), "--listen", "tcp/127.0.0.1:0"])
    code, err = p.wait(30), p.stderr.read()
    assert code == 2 and "not an MCAP file" in err, err
