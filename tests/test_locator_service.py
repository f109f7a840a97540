"""The locator and obstacle services as real processes on a real zenoh bus (loopback, multicast off):
posed frames of a simulated flight go in, range maps are checked against the renderer's ground-truth range,
the obstacle list and the MAVLink OBSTACLE_DISTANCE bytes against the boxes' true distances, health against
what was sent (including malformed input), and both processes must exit 0 on SIGINT."""
import contextlib
import math
import os
import signal
import time

os.environ["MAVLINK20"] = "1"

import numpy as np
import pytest

from eonav.bus import keys as K
from eonav.bus import schema
from eonav.geometry.camera import on_grid
from eonav.bus.session import client_session
from eonav.app.processes import drain, free_port, router_process, start_service, stop_service, wait_until
from eonav.geometry.frames import quat_wxyz_from_rotation
from eonav.ranging.rangemap import VALID

VEHICLE = "loctest"
N_FRAMES = 6
RATE_HZ = 10.0
T0_S = 3.0                  # approach flight: 0 m north at t = 3 s, truck ahead at ~57 m


@pytest.fixture(scope="module")
def flight_frames():
    from eonav.sim.flight import flight, render_flight
    frames = list(render_flight("approach", n_frames=N_FRAMES, rate_hz=RATE_HZ, size=256, t0_s=T0_S, seed=1))
    return frames, flight("approach")


def posed_frame_payload(seq, stamp_us, view, image=None):
    return schema.encode("posed_frame", camera_id="nose", seq=seq, stamp_us=stamp_us, encoding="mono8",
                         image=np.clip(np.round(view.image if image is None else image), 0, 255).astype(np.uint8),
                         camera=schema.camera_to_msg(view.camera), position_ned_m=view.state.position_ned_m,
                         q_wxyz=quat_wxyz_from_rotation(view.state.T_body_ned.T))


def box_distance(box, p_ned):
    local = box.R_ned_local.T @ (np.asarray(p_ned) - np.asarray(box.center_ned_m))
    return float(np.linalg.norm(local - np.clip(local, -box.half_m, box.half_m)))


def latest_health(samples):
    out = {}
    for s in samples:
        m = schema.decode(s.payload.to_bytes(), expect="health")
        out[m["service"]] = m
    return out


def frame_publisher_when_up(s, health_sub, health: list, **options):
    """A posed-frame publisher for camera "nose" (zenoh publisher ``options``; CongestionControl.BLOCK unless given:
    these tests score what the services make of every frame, and a frame put with DROP was seen lost on a loaded
    machine), once both services sent health and the locator subscribed."""
    import zenoh
    options.setdefault("congestion_control", zenoh.CongestionControl.BLOCK)
    pub = s.declare_publisher(K.posed_frame(VEHICLE, "nose"), **options)
    wait_until(lambda: {"locator", "obstacles"} <= set(latest_health(drain(health_sub, health))),
               timeout=30, what="both services' first health message")
    wait_until(lambda: pub.matching_status.matching, timeout=30, what="locator subscribed")
    time.sleep(0.3)
    return pub


@contextlib.contextmanager
def locator_and_obstacles(locator_args=(), obstacles_args=()):
    """A router; a client session subscribed to range maps, obstacle lists and health; the locator and the obstacle
    service started against it (one OpenCV thread, no ground plane). Yields (session, procs, maps_sub, obs_sub,
    health_sub). On an exception the services are asked to stop and their stderr is printed (pytest shows it with
    the failure); on exit every service still running is killed."""
    import zenoh
    procs = {}
    try:
        with router_process() as ep, client_session(ep) as s:
            subs = [s.declare_subscriber(key, zenoh.handlers.FifoChannel(n)) for key, n in
                    ((K.range_maps_all(VEHICLE), 64), (K.obstacles(VEHICLE), 64), (K.health_all(VEHICLE), 1024))]
            common = ["--vehicle", VEHICLE, "--connect", ep, "--health-period-s", "0.2"]
            procs["locator"] = start_service(["-m", "eonav.services.locator", *common, "--cv-threads", "1",
                                              *locator_args])
            procs["obstacles"] = start_service(["-m", "eonav.services.obstacles", *common, "--ground-down-m", "0",
                                                *obstacles_args])
            yield (s, procs, *subs)
    except BaseException:
        for name, p in procs.items():
            if p.poll() is None:
                p.send_signal(signal.SIGINT)
            try:
                err = p.communicate(timeout=10)[1]
            except Exception:
                p.kill()
                err = p.communicate()[1]
            print(f"---- {name} (exit {p.returncode}) stderr:\n{err[-4000:]}")
        raise
    finally:
        for p in procs.values():
            if p.poll() is None:
                p.kill()
                p.communicate()


def test_locator_and_obstacles_services(flight_frames):
    from eonav.nav.mavlink_out import mavutil
    frames, fl = flight_frames
    mu = mavutil()
    udp = free_port()
    rx = mu.mavlink_connection(f"udpin:127.0.0.1:{udp}")
    try:
        with locator_and_obstacles(("--fusion", "off"), ("--mavlink-out", f"udpout:127.0.0.1:{udp}")) as (
                s, procs, maps_sub, obs_sub, health_sub):
            health = []
            pub = frame_publisher_when_up(s, health_sub, health)
            def locator_counters():
                return latest_health(drain(health_sub, health)).get("locator", {}).get("counters", {})

            # malformed input first: garbage, and a frame whose image does not match its camera. Each put waits for
            # its counter: back to back, the ring (2) could drop the garbage before the locator decodes it
            pub.put(b"\x93not msgpack at all")
            wait_until(lambda: locator_counters().get("decode_errors") == 1, timeout=10, what="decode_errors 1")
            pub.put(posed_frame_payload(100, time.time_ns() // 1000 - 10_000_000, frames[0][1],
                                        image=np.zeros((10, 10))))
            wait_until(lambda: locator_counters().get("rejected.range") == 1, timeout=10, what="rejected.range 1")
            sent = {}
            maps, obstacles = [], []
            for i, (t_s, view, truth) in enumerate(frames):
                stamp = time.time_ns() // 1000            # captured "now": latencies are the pipeline's own
                sent[i] = (stamp, view, truth)
                pub.put(posed_frame_payload(i, stamp, view))
                # one frame in flight at a time (whatever the machine's load, no frame is superseded), at most 5 Hz
                if i == 0:
                    wait_until(lambda: locator_counters().get("skipped.first_frame") == 1, timeout=10,
                               what="frame 0 taken as the first frame")
                else:
                    wait_until(lambda: len(drain(maps_sub, maps)) >= i, timeout=20, what=f"range map {i}")
                    wait_until(lambda: len(drain(obs_sub, obstacles)) >= i, timeout=20, what=f"obstacle list {i}")
                time.sleep(max(0.0, stamp / 1e6 + 1.0 / RATE_HZ * 2 - time.time()))
            t_last = time.monotonic()

            # -- range maps vs the renderer's ground truth ------------------------------------------
            errs, cover = [], []
            for smp in maps:
                m = schema.decode(smp.payload.to_bytes(), expect="range_map")
                assert str(smp.key_expr) == K.range_map(VEHICLE, "nose")
                stamp, view, truth = sent[m["seq"]]
                assert m["stamp_us"] == stamp and m["other_seq"] == m["seq"] - 1 and m["method"] == "dense"
                # --scale auto (default): 256 x 256 at <= 5 Hz fits the budget at full scale on any machine we know;
                # the figures below hold at 0.5 too, so the scale is only checked to be a rung of the ladder. The map
                # is on its own camera's grid (--publish-grid locate): the truth is sampled at its pixel centres
                assert m["scale"] in (1.0, 0.5)
                assert m["range_m"].shape == (m["camera"]["height"], m["camera"]["width"])
                assert m["range_m"].shape == (round(256 * m["scale"]),) * 2
                assert (m["frame_width"], m["frame_height"]) == ((0, 0) if m["scale"] == 1.0 else (256, 256))
                gt = on_grid(truth.range_m, m["range_m"].shape[1], m["range_m"].shape[0])
                assert m["baseline_m"] == pytest.approx(np.linalg.norm(
                    view.state.position_ned_m - sent[m["other_seq"]][1].state.position_ned_m), rel=0.05)
                ok = ((m["flags"] & VALID) != 0) & np.isfinite(m["range_m"]) & np.isfinite(gt)
                rel = np.abs(m["range_m"][ok] - gt[ok]) / gt[ok]
                errs.append(float(np.median(rel)))
                cover.append(float(ok.mean()))
            assert max(errs) < 0.05, errs
            assert min(cover) > 0.2, cover

            # -- obstacle list vs the boxes ---------------------------------------------------------
            boxes = {b.name: b for b in fl.scene.boxes}
            truck_ids = []
            for smp in obstacles:
                m = schema.decode(smp.payload.to_bytes(), expect="obstacle_list")
                view = next(v for st, v, _ in sent.values() if st == m["stamp_us"])
                pos = view.state.position_ned_m
                truck = box_distance(boxes["truck"], pos)
                c = np.asarray(boxes["truck"].center_ned_m) - pos
                bearing = math.degrees(math.atan2(c[1], c[0]))
                # the truck (nearest box) is in the list at its true distance and bearing
                match = [o for o in m["obstacles"] if abs(o["bearing_deg"] - bearing) < 3.0]
                assert match, (bearing, m["obstacles"])
                assert match[0]["distance_m"] == pytest.approx(truck, rel=0.08), (match[0], truck)
                truck_ids.append(match[0]["id"])
                assert len(m["sectors"]["distances_cm"]) == 72
            assert len(set(truck_ids)) == 1, truck_ids     # the tracker keeps the truck's id

            # -- MAVLink: fresh sectors with the truck, then one 'unknown' flush and silence once stale ------
            od = []
            while True:
                msg = rx.recv_match(type="OBSTACLE_DISTANCE", blocking=True, timeout=0.3)
                if msg is None:
                    break
                od.append((time.monotonic(), msg))
                if time.monotonic() - t_last > 2.0:
                    break
            fresh = [msg for _, msg in od if set(msg.distances) != {65535}]
            assert fresh, "no fresh OBSTACLE_DISTANCE received"
            last_fresh = fresh[-1]
            assert last_fresh.frame == 12 and last_fresh.get_srcComponent() == 191
            assert (last_fresh.increment_f, last_fresh.angle_offset) == (5.0, -20.0)
            last_pos = sent[N_FRAMES - 1][1].state.position_ned_m
            c = np.asarray(boxes["truck"].center_ned_m) - last_pos
            j = round((math.degrees(math.atan2(c[1], c[0])) + 20.0) / 5.0) % 72   # element j: -20 + 5 j deg
            near = min(last_fresh.distances[j - 1:j + 2])   # bins at the truck's centre bearing
            truck_h = box_distance(boxes["truck"], [*last_pos[:2], -1.5])
            assert near / 100 == pytest.approx(truck_h, rel=0.1)
            assert set(od[-1][1].distances) == {65535}       # stale: one explicit unknown ...
            assert sum(set(m.distances) == {65535} for _, m in od) == 1
            assert rx.recv_match(type="OBSTACLE_DISTANCE", blocking=True, timeout=0.7) is None   # ... then silence

            # -- health: degraded while the autopilot is not heard on the output link, ok once it is ----------
            time.sleep(0.5)
            obs = latest_health(drain(health_sub, health))["obstacles"]
            assert obs["state"] == "degraded" and "no MAVLink" in obs["detail"], obs
            rx.mav.heartbeat_send(2, 3, 0, 0, 4)                        # the autopilot's HEARTBEAT back
            # the link's own degraded goes once the autopilot is heard; the silent range maps keep the state degraded
            wait_until(lambda: "no MAVLink" not in latest_health(drain(health_sub, health))["obstacles"]["detail"],
                       timeout=5, what="obstacles' link no longer degraded once the autopilot is heard")
            h = latest_health(drain(health_sub, health))
            loc, obs = h["locator"], h["obstacles"]
            # the frames stopped over a second ago: both report their silent input (Node.expect_input)
            assert loc["state"] == "degraded" and "no posed frames for" in loc["detail"], loc["detail"]
            assert obs["state"] == "degraded" and "no range maps for" in obs["detail"], obs["detail"]
            c = loc["counters"]
            assert c["pairs_computed"] == N_FRAMES - 1 and c["decode_errors"] == 2
            assert c["rejected.msgpack"] == 1 and c["rejected.range"] == 1         # garbage; image vs camera
            assert c["skipped.first_frame"] == 1 and c.get("frames_superseded", 0) == 0
            assert c["scale_pct.nose"] in (100, 50)                    # the camera's current scale (gauge)
            assert c["scale_pct.nose"] == 100 - 50 * c.get("scale_changes.down", 0) + 50 * c.get("scale_changes.up", 0)
            assert loc["latency_ms"]["capture_to_published"]["n"] == N_FRAMES - 1
            assert obs["counters"]["maps_processed"] == N_FRAMES - 1
            assert obs["counters"]["mavlink.od_sent_fresh"] >= 1 and obs["counters"]["mavlink.od_sent_flush"] == 1
            assert obs["latency_ms"]["capture_to_obstacles"]["p99"] < 2000
            assert "warmup_errors" not in obs["counters"]

            for name in ("locator", "obstacles"):
                code, err = stop_service(procs.pop(name), signal.SIGINT, timeout=15)
                assert code == 0, f"{name} exit {code}:\n{err[-3000:]}"
    finally:
        rx.close()


def run_to_exit(argv, timeout=30):
    """Start a service, wait for it to exit by itself; returns (exit code, stderr)."""
    p = start_service(argv)
    try:
        p.wait(timeout)
    finally:
        if p.poll() is None:
            p.kill()
    return p.returncode, p.communicate()[1]


def test_locator_rejects_bad_configuration():
    with router_process() as ep:
        code, err = run_to_exit(["-m", "eonav.services.locator", "--vehicle", VEHICLE, "--connect", ep, "--method", "nonsense"])
        assert code == 2 and "unknown method 'nonsense'" in err
        for bad, text in ((["--scale", "fast"], "--scale must be 'auto' or a number"),
                          (["--scale", "1.5"], "--scale must be 'auto' or a number"),
                          (["--min-scale", "0"], "--min-scale must be in (0, 1]"),
                          (["--budget-ms", "-5"], "--budget-ms must be > 0")):
            code, err = run_to_exit(["-m", "eonav.services.locator", "--vehicle", VEHICLE, "--connect", ep, *bad])
            assert code == 2 and text in err, (bad, code, err[-2000:])
        code, err = run_to_exit(["-m", "eonav.services.obstacles", "--vehicle", VEHICLE, "--connect", ep,
                                 "--ground-down-m", "x"])
        assert code == 2 and "--ground-down-m 'x'" in err

def test_scaled_view_matches_frame_info_at_that_scale(flight_frames):
    """The history keeps full-resolution frames; a pair at 0.5 resizes them on use, exactly as a fixed --scale 0.5
    frame_info does, and the resized image is made once per frame and scale."""
    from eonav.services.locator import CameraCache, frame_info, scaled_view
    frames, _ = flight_frames
    msg = schema.decode(posed_frame_payload(0, 1_000_000, frames[0][1]), expect="posed_frame")
    full = CameraCache(1.0)
    f = frame_info(msg, full)
    ref = frame_info(msg, CameraCache(0.5))
    v = scaled_view(f, 0.5, full)
    assert v.image.shape == (128, 128) and np.array_equal(v.image, ref.payload["image"])
    c, r = v.camera, ref.payload["camera"]
    assert (c.width, c.height, c.fx, c.fy, c.cx, c.cy) == (r.width, r.height, r.fx, r.fy, r.cx, r.cy)
    assert scaled_view(f, 0.5, full).image is v.image                 # cached in the frame's payload
    v1 = scaled_view(f, 1.0, full)
    assert v1.image is f.payload["image"] and v1.camera is f.camera


def test_to_full_grid_odd_sizes_match_the_nearest_pixel_centre_rule():
    """The upsampling of a map computed at a locate scale: pixel u of the full grid takes scaled pixel
    floor((u + 0.5) small / full), for sizes that are not a multiple of the scale, every dtype sent, NaN kept."""
    from types import SimpleNamespace

    from eonav.services.locator import to_full_grid
    cam = SimpleNamespace(width=15, height=11)
    small = np.random.default_rng(3).random((5, 7)) * 100
    small[2, 3] = np.nan
    rows = [int((v + 0.5) * 5 / 11) for v in range(11)]
    cols = [int((u + 0.5) * 7 / 15) for u in range(15)]
    for dt in (np.float32, np.float16, np.uint8):
        a = (np.nan_to_num(small) if dt is np.uint8 else small).astype(dt)
        want = np.array([[a[r, c] for c in cols] for r in rows], dt)
        got = to_full_grid(a, cam)
        assert got.dtype == dt and got.shape == (11, 15)
        assert np.array_equal(got, want, equal_nan=dt is not np.uint8)
    same = np.zeros((11, 15), np.float32)
    assert to_full_grid(same, cam) is same and to_full_grid(None, cam) is None


def test_warm_up_times_every_rung_on_a_synthetic_partner_and_calibrates(flight_frames):
    """The warm-up at a camera's first frame: one timing per rung of the ladder (both positive, no assertion on their
    size), the partner is the frame's own image from behind, and the controller is calibrated (scale_pct-style
    gauge untouched here: that is the loop's job)."""
    from types import SimpleNamespace

    from eonav.ranging.locate import locate
    from eonav.ranging.scale_control import ScaleController
    from eonav.services.locator import CameraCache, calibrate_camera, frame_info, synthetic_partner
    frames, _ = flight_frames
    cams = CameraCache(1.0)
    f = frame_info(schema.decode(posed_frame_payload(0, 1_000_000, frames[0][1]), expect="posed_frame"), cams)
    b = synthetic_partner(f)
    assert b.payload["image"] is f.payload["image"] and b.payload["scaled"] is not f.payload["scaled"]
    assert np.linalg.norm(b.state.position_ned_m - f.state.position_ned_m) == pytest.approx(2.0)
    assert b.stamp_us < f.stamp_us and b.camera is f.camera
    c = ScaleController()
    costs = calibrate_camera(f, c, "dense", {}, cams, locate)
    assert sorted(costs) == [0.5, 1.0] and all(t > 0 for t in costs.values())
    calls = []

    def failing(va, vb, method, **kw):
        calls.append(va.image.shape)
        raise ValueError("boom")
    from eonav.services.locator import warm_up_camera
    counted = {}
    node = SimpleNamespace(count=lambda k, n=1: counted.__setitem__(k, counted.get(k, 0) + n),
                           log_limited=lambda *a, **k: None, latency=lambda *a: None,
                           log=SimpleNamespace(info=lambda *a: None))
    c2 = ScaleController()
    warm_up_camera(node, f, c2, "dense", {}, cams, failing)
    assert counted == {"warmup_errors": 1} and c2.scale == 1.0 and len(calls) == 1


def test_warm_up_hands_its_timings_to_the_controller_which_starts_at_the_rung_that_fits(monkeypatch):
    """A successful warm-up calibrates the camera's controller: with a 40 ms budget and locate timed at 65 ms at
    full scale and 20 ms at 0.5 (a clock advanced by the stand-in locate: 5 ms a call and 0.25 us a pixel of the
    480 x 500 frame), the camera starts at 0.5 with the calibrated cost ratio 65 / 20 = 3.25 (not the area's 4), and
    the warm-up's time is recorded (health latency ``warmup``), no error counted."""
    from types import SimpleNamespace

    from eonav.bus.node import Node
    from eonav.geometry.camera import Camera
    from eonav.ranging.scale_control import ScaleController
    from eonav.services import locator
    clock = {"s": 100.0}
    monkeypatch.setattr(locator, "time", SimpleNamespace(perf_counter=lambda: clock["s"], thread_time=time.thread_time))
    timed = []

    def area_cost(va, vb, method, **kw):
        timed.append(va.image.shape)
        clock["s"] += 0.005 + 0.25e-6 * va.image.size
        return _range_result(va.image.shape)
    node = Node("locator", SimpleNamespace(vehicle="v", input_grace_s=10.0, health_period_s=1.0), RecordingSession())
    cams = locator.CameraCache(1.0)
    img = np.zeros((500, 480), np.uint8)
    f = locator.frame_info(schema.decode(schema.encode(
        "posed_frame", camera_id="nose", seq=1, stamp_us=1_000_000, encoding="mono8", image=img,
        camera=schema.camera_to_msg(Camera("nose", 480, 500, 400.0, 400.0, 239.5, 249.5)),
        position_ned_m=[0.0, 0.0, -5.0], q_wxyz=[1.0, 0.0, 0.0, 0.0]), expect="posed_frame"), cams)
    c = ScaleController(budget_s=0.04)
    locator.warm_up_camera(node, f, c, "dense", {}, cams, area_cost)
    assert timed == [(250, 240), (250, 240), (500, 480)]     # the untimed first call at the lowest rung, then each
    assert c.scale == 0.5 and c.ratio(1.0, 0.5) == pytest.approx(3.25)
    assert "warmup_errors" not in node.counters()
    assert node.health_fields()["latency_ms"]["warmup"]["n"] == 1


def test_half_scale_maps_on_the_locate_grid_feed_the_obstacle_service(flight_frames):
    """--scale 0.5 (default --publish-grid locate): the range map is 128 x 128 with the scaled camera in the message
    and the frame size beside it, accurate against the truth sampled at its pixel centres; the obstacle service
    ranges the truck from it (its own camera), counts a map whose arrays do not match its camera (bad_maps) and still
    takes an older locator's full-grid map without frame size."""
    from eonav.geometry.camera import scaled_camera
    frames, fl = flight_frames
    with locator_and_obstacles(("--scale", "0.5", "--fusion", "off")) as (s, procs, maps_sub, obs_sub, health_sub):
        import zenoh
        health = []
        pub = frame_publisher_when_up(s, health_sub, health)
        # BLOCK as the frames: with DROP (zenoh's default) a fragmented message was lost on a loaded machine
        map_pub = s.declare_publisher(K.range_map(VEHICLE, "test"), congestion_control=zenoh.CongestionControl.BLOCK)
        wait_until(lambda: map_pub.matching_status.matching, timeout=30, what="the obstacle service subscribed")
        time.sleep(0.3)
        maps, obstacles = [], []
        for i in range(3):
            t_s, view, truth = frames[i]
            pub.put(posed_frame_payload(i, time.time_ns() // 1000, view))
            # one frame in flight at a time, as in the full-scale test: frame 1 put right behind frame 0 (the
            # publisher drops under congestion, the ring holds 2) was lost now and then and no map came
            if i == 0:
                wait_until(lambda: latest_health(drain(health_sub, health)).get("locator", {}).get("counters", {})
                           .get("skipped.first_frame") == 1, timeout=10, what="frame 0 taken as the first frame")
            else:
                wait_until(lambda: len(drain(maps_sub, maps)) >= i, timeout=20, what=f"range map {i}")
                wait_until(lambda: len(drain(obs_sub, obstacles)) >= i, timeout=20, what=f"obstacle list {i}")
        boxes = {b.name: b for b in fl.scene.boxes}
        for smp, osmp in zip(maps, obstacles):
            m = schema.decode(smp.payload.to_bytes(), expect="range_map")
            _, view, truth = frames[m["seq"]]
            sc = scaled_camera(view.camera, 0.5)
            assert m["scale"] == 0.5 and m["range_m"].shape == (128, 128)
            assert m["confidence"].shape == m["flags"].shape == m["inv_range_std_per_m"].shape == (128, 128)
            assert (m["frame_width"], m["frame_height"]) == (256, 256)
            c = schema.camera_from_msg(m["camera"])
            assert (c.width, c.height) == (128, 128)
            assert (c.fx, c.fy, c.cx, c.cy) == pytest.approx((sc.fx, sc.fy, sc.cx, sc.cy))
            gt = on_grid(truth.range_m, 128, 128)
            ok = ((m["flags"] & VALID) != 0) & np.isfinite(m["range_m"]) & np.isfinite(gt)
            assert ok.mean() > 0.2
            assert np.median(np.abs(m["range_m"][ok] - gt[ok]) / gt[ok]) < 0.05
            o = schema.decode(osmp.payload.to_bytes(), expect="obstacle_list")
            assert o["stamp_us"] == m["stamp_us"]
            pos = view.state.position_ned_m
            cb = np.asarray(boxes["truck"].center_ned_m) - pos
            bearing = math.degrees(math.atan2(cb[1], cb[0]))
            match = [x for x in o["obstacles"] if abs(x["bearing_deg"] - bearing) < 3]
            assert match and match[0]["distance_m"] == pytest.approx(box_distance(boxes["truck"], pos), rel=0.08)
            assert all(0 <= x["bbox_px"][2] <= 255 and 0 <= x["bbox_px"][3] <= 255 for x in o["obstacles"])

        # a map whose arrays do not match its camera: rejected at decode by name and counted; then an older locator's map
        # (frame grid, no frame size) is still analysed
        _, view, truth = frames[2]
        old = dict(camera_id="test", seq=1, stamp_us=time.time_ns() // 1000, method="truth",
                   camera=schema.camera_to_msg(view.camera), position_ned_m=view.state.position_ned_m,
                   q_wxyz=quat_wxyz_from_rotation(view.state.T_body_ned.T))
        small = on_grid(truth.range_m, 128, 128).astype(np.float32)
        map_pub.put(schema.encode("range_map", **old, range_m=small, confidence=np.ones_like(small)))
        def obstacle_counters():
            return latest_health(drain(health_sub, health)).get("obstacles", {}).get("counters", {})
        wait_until(lambda: obstacle_counters().get("rejected.range") == 1, timeout=10, what="rejected.range 1")
        full = truth.range_m.astype(np.float32)
        map_pub.put(schema.encode("range_map", **dict(old, seq=2, stamp_us=time.time_ns() // 1000), range_m=full,
                                  confidence=np.ones_like(full)))
        wait_until(lambda: obstacle_counters().get("maps_processed") == 3, timeout=10, what="maps_processed 3")
        assert obstacle_counters()["rejected.range"] == 1 and obstacle_counters()["decode_errors"] == 1
        for name in ("locator", "obstacles"):
            code, err = stop_service(procs.pop(name), signal.SIGINT, timeout=15)
            assert code == 0, f"{name} exit {code}:\n{err[-3000:]}"


def test_map_fields_on_either_grid(flight_frames):
    """map_fields: ``locate`` keeps the computed maps with the scaled camera and the frame size; ``frame`` upsamples
    them (to_full_grid) with the frame's camera; at scale 1 both are the frame's grid without a frame size."""
    from types import SimpleNamespace

    from eonav.services.locator import CameraCache, frame_info, map_fields, scaled_view, to_full_grid
    frames, _ = flight_frames
    cams = CameraCache(1.0)
    f = frame_info(schema.decode(posed_frame_payload(0, 1_000_000, frames[0][1]), expect="posed_frame"), cams)
    rng = np.random.default_rng(0)
    res = SimpleNamespace(range_m=rng.random((128, 128)) * 50, confidence=rng.random((128, 128)),
                          inv_range_std_per_m=rng.random((128, 128)) * 1e-3, flags=rng.integers(0, 64, (128, 128)))
    loc = scaled_view(f, 0.5, cams).camera
    a = map_fields(res, f, loc, "f16", "locate")
    assert a["range_m"].dtype == np.float32 and a["range_m"].shape == (128, 128)
    assert a["confidence"].dtype == a["inv_range_std_per_m"].dtype == np.float16 and a["flags"].dtype == np.uint8
    assert a["camera"] == schema.camera_to_msg(loc) and (a["frame_width"], a["frame_height"]) == (256, 256)
    b = map_fields(res, f, loc, "off", "frame")
    assert b["camera"] is f.payload["camera_msg"] and "frame_width" not in b and b["inv_range_std_per_m"] is None
    assert np.array_equal(b["range_m"], to_full_grid(a["range_m"], f.camera))
    assert np.array_equal(b["flags"], to_full_grid(a["flags"], f.camera))
    res1 = SimpleNamespace(range_m=np.ones((256, 256)), confidence=np.ones((256, 256)), inv_range_std_per_m=None,
                           flags=None)
    for grid in ("locate", "frame"):
        c = map_fields(res1, f, f.camera, "f32", grid)
        assert c["camera"] is f.payload["camera_msg"] and "frame_width" not in c and c["flags"] is None
    encoded = schema.decode(schema.encode("range_map", camera_id="nose", seq=1, stamp_us=1, method="x",
                                          position_ned_m=[0, 0, 0], q_wxyz=[1, 0, 0, 0], **a), expect="range_map")
    assert encoded["frame_width"] == 256 and schema.camera_from_msg(encoded["camera"]).width == 128
    # float16 maps: a sigma or confidence beyond float16's range is +inf (no information), NaN stays NaN
    res2 = SimpleNamespace(range_m=np.ones((128, 128), np.float32), confidence=np.full((128, 128), 1e6, np.float32),
                           inv_range_std_per_m=np.full((128, 128), 3.0, np.float32), flags=None)
    res2.inv_range_std_per_m[0, :3] = [1e6, 65504.0, np.nan]
    d = map_fields(res2, f, loc, "f16", "locate")
    assert d["inv_range_std_per_m"][0, :4].tolist()[:2] == [np.inf, 65504.0]
    assert np.isnan(d["inv_range_std_per_m"][0, 2]) and d["inv_range_std_per_m"][0, 3] == 3.0
    assert np.all(d["confidence"] == np.inf)


def test_locator_publishes_fused_maps(flight_frames):
    """Fusion on (the default with the dense method): every frame after the first gets a fused map of its own camera,
    with the per-pixel count of measurements growing frame by frame, its VALID ranges close to the renderer's truth,
    and the obstacle service analysing it."""
    frames, _ = flight_frames
    # the first fused map pays the load of the fusion kernels (numba cache), past the default age limit on a loaded
    # machine: this test is about what fusion computes (the age limit has its own tests, test_staleness.py)
    with locator_and_obstacles(("--max-input-age-ms", "10000")) as (s, procs, maps_sub, obs_sub, health_sub):
        health = []
        pub = frame_publisher_when_up(s, health_sub, health)

        def counters():
            return latest_health(drain(health_sub, health)).get("locator", {}).get("counters", {})
        maps, obstacles, sent = [], [], {}
        for i, (t_s, view, truth) in enumerate(frames):
            stamp = time.time_ns() // 1000
            sent[i] = (stamp, view, truth)
            pub.put(posed_frame_payload(i, stamp, view))
            if i == 0:
                wait_until(lambda: counters().get("fusion.policy.first_frame") == 1, timeout=10,
                           what="frame 0 taken as the first frame")
            else:
                # the locator's own count (computed and put) apart from the delivery, so that a failure says which
                try:
                    wait_until(lambda: counters().get("maps_fused", 0) >= i, timeout=30,
                               what=f"the locator's health counting fused map {i}")
                    wait_until(lambda: len(drain(maps_sub, maps)) >= i, timeout=20, what=f"fused map {i} delivered")
                except AssertionError as e:
                    raise AssertionError(f"{e}; locator counters {counters()}") from None
                wait_until(lambda: len(drain(obs_sub, obstacles)) >= i, timeout=20, what=f"obstacle list {i}")
            time.sleep(max(0.0, stamp / 1e6 + 2.0 / RATE_HZ - time.time()))
        peaks, errs = [], []
        for smp in maps:
            m = schema.decode(smp.payload.to_bytes(), expect="range_map")
            stamp, view, truth = sent[m["seq"]]
            assert m["method"] == "fused" and m["stamp_us"] == stamp
            n = m["n_fused"]
            assert n is not None and n.dtype == np.uint8 and n.shape == m["range_m"].shape
            peaks.append(int(np.percentile(n[n > 0], 90)))
            gt = on_grid(truth.range_m, m["range_m"].shape[1], m["range_m"].shape[0])
            ok = ((m["flags"] & VALID) != 0) & np.isfinite(m["range_m"]) & np.isfinite(gt)
            errs.append(float(np.median(np.abs(m["range_m"][ok] - gt[ok]) / gt[ok])))
        assert peaks[0] == 1 and peaks[-1] >= 3 and peaks == sorted(peaks), peaks   # evidence accumulates
        assert max(errs) < 0.05, errs
        # health is published on its own period: the count may trail the last map by one period (seen under load)
        c = wait_until(lambda: (lambda x: x if x.get("maps_fused") == N_FRAMES - 1 else None)(counters()), timeout=5,
                       what="the health counting every fused map")
        assert c.get("locate_errors", 0) == 0
        # per-stage timing (what eonav bench pipeline prints): one sample per fused map, the ages in pipeline order,
        # the locate's CPU apart from the fusion's
        lat = wait_until(lambda: (lambda x: x if x.get("cpu.publish", {}).get("n") == N_FRAMES - 1 else None)(
            latest_health(drain(health_sub, health))["locator"]["latency_ms"]), timeout=5, what="stage latencies")
        for name in ("age.fused", "frame_time", "locate", "fusion", "publish", "cpu.locate", "cpu.fusion",
                     "cpu.publish"):
            assert lat[name]["n"] == N_FRAMES - 1, name
        # every frame is dequeued and pushed (the first one only starts the state: no map)
        assert lat["age.dequeued"]["n"] == lat["cpu.ingest"]["n"] == lat["age.locate_start"]["n"] == N_FRAMES
        for k in ("p50", "max"):                                  # the same frames: fused before put
            assert lat["age.fused"][k] <= lat["capture_to_published"][k], k
        assert lat["cpu.locate"]["p50"] > 0 and lat["cpu.fusion"]["p50"] > 0
        wait_until(lambda: latest_health(drain(health_sub, health))["obstacles"]["counters"].get("maps_processed")
                   == N_FRAMES - 1, timeout=5, what="the obstacle service's health counting every fused map")
        olat = wait_until(lambda: (lambda x: x if x.get("cpu.track_message", {}).get("n") == N_FRAMES - 1 else None)(
            latest_health(drain(health_sub, health))["obstacles"]["latency_ms"]), timeout=5, what="stage latencies")
        for name in ("age.dequeued", "analyse", "track", "publish", "cpu.decode", "cpu.analyse", "cpu.track",
                     "cpu.track_message"):
            assert olat[name]["n"] == N_FRAMES - 1, name
        assert olat["age.dequeued"]["max"] <= olat["capture_to_obstacles"]["max"]
        for name in ("locator", "obstacles"):
            code, err = stop_service(procs.pop(name), signal.SIGINT, timeout=15)
            assert code == 0, f"{name} exit {code}:\n{err[-3000:]}"


def test_a_backlog_is_skipped_to_the_newest_frame_and_counted():
    """Latest frame wins: frames put faster than the locator ranges them wait in its ring (2 deep, the newest kept);
    after each frame it ranges only the newest one waiting (the one before it becomes a partner only:
    ``frames_superseded``), and the ring's drops show as gaps in the camera's seq (``frames_skipped``). Every frame is
    counted once -- pushed into fusion, superseded or skipped -- the newest gets its map, and a burst does not
    queue."""
    import zenoh

    from eonav.sim.flight import render_flight
    # 256 px: a fused map takes several times a put on any load (at 128 px a loaded machine once ranged every other
    # frame as it arrived, the ring never full)
    frames = list(render_flight("approach", n_frames=13, rate_hz=RATE_HZ, size=256, t0_s=T0_S, seed=2))
    burst = len(frames) - 1
    with locator_and_obstacles(("--max-input-age-ms", "10000", "--scale", "1", "--no-warmup")) as (
            s, procs, maps_sub, obs_sub, health_sub):
        health = []
        # (blocking, not the default dropping publisher: every frame reaches the locator's ring, whose drops are
        # the ones counted)
        pub = frame_publisher_when_up(s, health_sub, health)

        def counters():
            return latest_health(drain(health_sub, health)).get("locator", {}).get("counters", {})
        pub.put(posed_frame_payload(0, time.time_ns() // 1000, frames[0][1]))
        wait_until(lambda: counters().get("fusion.policy.first_frame") == 1, timeout=20, what="frame 0 taken")
        for i in range(1, len(frames)):          # back to back: far faster than a fused map each
            pub.put(posed_frame_payload(i, time.time_ns() // 1000, frames[i][1]))
        def accounted(c):        # frames 1.. pushed into fusion (each push counts its pair policy reason) or not
            pushed = sum(v for k, v in c.items() if k.startswith("fusion.policy.")) - 1
            return pushed + c.get("frames_superseded", 0) + c.get("frames_skipped", 0)
        wait_until(lambda: accounted(counters()) >= burst, timeout=30, what="every frame of the burst accounted for")
        time.sleep(0.5)
        c = counters()
        seqs = [schema.decode(smp.payload.to_bytes(), expect="range_map")["seq"] for smp in drain(maps_sub, [])]
        assert accounted(c) == burst, c
        assert seqs == sorted(seqs) and seqs[-1] == burst and c["maps_fused"] == len(seqs), seqs   # the newest ranged
        # the backlog was not worked off: the ring dropped frames, and the frame before the newest one waiting was
        # a partner only (the burst is put within a few ms, one fused map takes longer on any machine)
        assert c.get("frames_skipped", 0) >= 1 and c.get("frames_superseded", 0) >= 1 and len(seqs) < burst, (c, seqs)
        assert c.get("seq_jumps", 0) == 0 and c.get("locate_errors", 0) == 0
        for name in ("locator", "obstacles"):
            code, err = stop_service(procs.pop(name), signal.SIGINT, timeout=15)
            assert code == 0, f"{name} exit {code}:\n{err[-3000:]}"


def test_a_rigs_partner_frames_go_before_its_references_in_a_drained_batch():
    """``rig_first``: the stereo rig's partner frames before its reference's (the stereo measurement then leads the
    motion one: eonav.fusion.update, "Stereo leads"), each camera's own order and the newest flags kept; other
    cameras keep their places; no rig or a single frame: unchanged."""
    from types import SimpleNamespace

    from services.locator import rig_first

    def item(cam, seq, newest):
        return (SimpleNamespace(key_expr=K.posed_frame("v1", cam), seq=seq), newest)
    batch = [item("left", 7, False), item("right", 7, False), item("left", 8, True), item("nose", 3, True),
             item("right", 8, True)]
    left = K.posed_frame("v1", "left")
    out = rig_first(batch, left)
    assert [(str(s.key_expr).split("/")[-2], s.seq, n) for s, n in out] == [
        ("right", 7, False), ("nose", 3, True), ("right", 8, True), ("left", 7, False), ("left", 8, True)]
    assert rig_first(batch, None) is batch and rig_first(batch[:1], left) == batch[:1]
    # a camera id that ends like another's is not taken for it
    b2 = [item("xleft", 1, True), item("right", 1, True)]
    assert [str(s.key_expr).split("/")[-2] for s, _ in rig_first(b2, left)] == ["xleft", "right"]


# ---- range_pair in process: a Node whose session records its puts, a stand-in locate -----------------------------

class RecordingSession:
    """Stands in for the zenoh session of an in-process Node: every put, in order, as (key, payload bytes)."""

    def __init__(self):
        self.puts = []

    def declare_publisher(self, key, **kw):
        from types import SimpleNamespace
        return SimpleNamespace(put=lambda payload: self.puts.append((str(key), bytes(payload))))


def _pair_harness(gate=None):
    """A locator Node (recording session), its range-map publisher for camera "nose", and ``pair(stamp_a_us)``: a
    pair decision of two 16 x 12 posed frames of "nose" (a stamped ``stamp_a_us``, b 100 ms before, 2 m behind)."""
    import argparse
    import logging
    from types import SimpleNamespace

    from eonav.bus.node import Node
    from eonav.geometry.camera import Camera
    from eonav.services.locator import CameraCache, frame_info
    session = RecordingSession()
    node = Node("locator", argparse.Namespace(vehicle="v", input_grace_s=10.0, health_period_s=1.0), session,
                log=logging.getLogger("test.locator"))
    pubs = {"nose": node.publisher(K.range_map("v", "nose"), image=True)}
    cam = Camera("nose", 16, 12, 16.0, 16.0, 7.5, 5.5)
    cams = CameraCache(1.0)
    img = (np.arange(12 * 16).reshape(12, 16) % 251).astype(np.uint8)

    def frame(seq, stamp_us, north_m):
        return frame_info(schema.decode(schema.encode(
            "posed_frame", camera_id="nose", seq=seq, stamp_us=stamp_us, encoding="mono8", image=img,
            camera=schema.camera_to_msg(cam), position_ned_m=[north_m, 0.0, -5.0], q_wxyz=[1.0, 0.0, 0.0, 0.0]),
            expect="posed_frame"), cams)

    def pair(stamp_a_us, seq=2):
        return SimpleNamespace(a=frame(seq, stamp_a_us, 2.0), b=frame(seq - 1, stamp_a_us - 100_000, 0.0),
                               baseline_m=2.0, reason="motion")
    return node, session, pubs, cams, pair


def _range_result(shape=(12, 16), range_m=25.0):
    from types import SimpleNamespace
    return SimpleNamespace(range_m=np.full(shape, range_m, np.float32), confidence=np.full(shape, 3.0, np.float32),
                           inv_range_std_per_m=None, flags=None, method="stand-in")


def test_locate_failing_three_times_in_a_row_degrades_the_locator_and_a_good_pair_restores_it():
    """One failing locate is a bad pair (counted, no map, state ok); the third failure in a row is a persistent one
    (state degraded); the next pair that locates puts its map, resets the run and brings the state back to ok."""
    from eonav.services.locator import range_pair
    node, session, pubs, cams, pair = _pair_harness()
    calls = []

    def failing(va, vb, **kw):
        calls.append(kw)
        raise ValueError("no texture")

    def working(va, vb, **kw):
        return _range_result()
    d = pair(time.time_ns() // 1000)
    errors = 0
    for k in (1, 2, 3):
        errors, compute_s = range_pair(node, d, pubs, "dense", {}, 1.0, "f16", errors, time.perf_counter(), cams,
                                       failing)
        assert (errors, compute_s) == (k, None)
        assert node.state == ("degraded" if k == 3 else "ok"), k
    assert node.counters()["locate_errors"] == 3 and session.puts == [] and calls[0] == {"method": "dense"}
    errors, compute_s = range_pair(node, d, pubs, "dense", {}, 1.0, "f16", errors, time.perf_counter(), cams, working)
    assert errors == 0 and compute_s >= 0 and node.state == "ok"
    (key, payload), = session.puts
    m = schema.decode(payload, expect="range_map")
    assert key == K.range_map("v", "nose") and (m["seq"], m["other_seq"]) == (2, 1)
    assert np.all(m["range_m"] == 25.0) and node.counters()["pairs_computed"] == 1


def test_range_pair_never_puts_a_map_older_than_the_last_one_put():
    """The publish-side gate: once a map of frame t is put, a later pair whose reference frame is older (a frame that
    waited behind the newer one) computes but is not put (``dropped.out_of_order``); a newer one is."""
    from eonav.bus.freshness import FreshnessGate
    from eonav.services.locator import range_pair
    t = time.time_ns() // 1000
    gate = FreshnessGate(1.0, clock_us=lambda: t)
    node, session, pubs, cams, pair = _pair_harness()

    def working(va, vb, **kw):
        return _range_result()
    for stamp, seq in ((t - 100_000, 5), (t - 200_000, 4), (t - 100_000, 6), (t - 50_000, 7)):
        errors, compute_s = range_pair(node, pair(stamp, seq), pubs, "dense", {}, 1.0, "f16", 0, time.perf_counter(),
                                       cams, working, "locate", gate)
        assert errors == 0 and compute_s is not None
    put = [schema.decode(p, expect="range_map") for _, p in session.puts]
    assert [(m["seq"], m["stamp_us"]) for m in put] == [(5, t - 100_000), (6, t - 100_000), (7, t - 50_000)]
    assert node.counters()["dropped.out_of_order"] == 1 and gate.last_published_us("nose") == t - 50_000


def test_range_pair_at_a_scale_publishes_the_reference_frames_pose_and_the_partners_stamp():
    """A pair located at --scale 0.75 of a 16 x 12 (non-square) camera: locate gets both frames at 12 x 9, and the
    map is put with the reference frame's pose (a, 2 m north: not the partner's, 2 m behind), the partner's seq and
    stamp (100 ms before a's), scale 0.75, the scaled camera (fx 16 x 0.75 = 12, pixel centres kept:
    cx (7.5 + 0.5) x 0.75 - 0.5 = 5.5, cy (5.5 + 0.5) x 0.75 - 0.5 = 4) and the frame's size as width 16, height 12
    (the obstacle service maps the map's pixels back to the frame with them)."""
    from eonav.services.locator import range_pair
    node, session, pubs, cams, pair = _pair_harness()
    shapes = []

    def working(va, vb, **kw):
        shapes.append((va.image.shape, vb.image.shape, va.camera.width, vb.camera.width))
        return _range_result(shape=(9, 12))
    t = time.time_ns() // 1000
    errors, compute_s = range_pair(node, pair(t, seq=7), pubs, "dense", {}, 0.75, "f16", 0, time.perf_counter(), cams,
                                   working)
    assert errors == 0 and compute_s is not None and shapes == [((9, 12), (9, 12), 12, 12)]
    (_, payload), = session.puts
    m = schema.decode(payload, expect="range_map")
    assert (m["seq"], m["stamp_us"], m["other_seq"], m["other_stamp_us"]) == (7, t, 6, t - 100_000)
    assert m["position_ned_m"].tolist() == [2.0, 0.0, -5.0] and m["baseline_m"] == 2.0
    assert m["scale"] == 0.75 and m["range_m"].shape == (9, 12)
    c = m["camera"]
    assert (c["width"], c["height"], c["fx"], c["fy"], c["cx"], c["cy"]) == (12, 9, 12.0, 12.0, 5.5, 4.0)
    assert (m["frame_width"], m["frame_height"]) == (16, 12)
    assert node.counters()["pairs_computed.scale_75"] == 1


def test_drain_latest_marks_only_each_cameras_last_frame_as_newest():
    """Latest frame wins: of a drained batch (the frame just received, then all waiting in the ring, in arrival
    order) only the last frame of each camera (key) is ranged; earlier ones of the same camera are partners only. The
    order is kept."""
    from types import SimpleNamespace

    from eonav.services.locator import drain_latest

    def smp(cam, seq):
        return SimpleNamespace(key_expr=K.posed_frame("v", cam), seq=seq)
    waiting = [smp("right", 1), smp("nose", 2), smp("nose", 3), smp("right", 2)]
    sub = SimpleNamespace(try_recv=lambda: waiting.pop(0) if waiting else None)
    out = drain_latest(smp("nose", 1), sub)
    assert [(str(s.key_expr).split("/")[-2], s.seq, n) for s, n in out] == [
        ("nose", 1, False), ("right", 1, False), ("nose", 2, False), ("nose", 3, True), ("right", 2, True)]
    assert waiting == []
    (s, n), = drain_latest(smp("nose", 9), sub)          # nothing waiting: the frame itself is the newest
    assert s.seq == 9 and n is True


def test_locate_loop_counts_skipped_frames_and_a_restarted_cameras_seq_jump(monkeypatch):
    """The single-pair loop (fusion off) in process with a stand-in locate, frames arriving one at a time: seq 0
    (first frame: no pair), 1 (pair with 0), 4 (pair with 1; the ring dropped 2 and 3: frames_skipped 2, not 3), then
    0 again with a newer stamp (a restarted camera: seq_jumps 1, a seq going back is no gap). Every decision of the
    pair policy is counted (pairs.<reason>, skipped.<reason>) and each pair's map is put with its partner's seq."""
    from types import SimpleNamespace

    import eonav.ranging.locate
    from eonav.geometry.camera import Camera
    from eonav.ranging.pair_policy import PairPolicy, PairPolicyConfig
    from eonav.services.locator import locate_loop
    node, session, pubs, cams, _ = _pair_harness()
    monkeypatch.setattr(eonav.ranging.locate, "locate", lambda va, vb, **kw: _range_result())
    img = (np.arange(12 * 16).reshape(12, 16) % 251).astype(np.uint8)
    cam = schema.camera_to_msg(Camera("nose", 16, 12, 16.0, 16.0, 7.5, 5.5))
    t = time.time_ns() // 1000
    samples = []
    for k, seq in enumerate((0, 1, 4, 0)):
        payload = schema.encode("posed_frame", camera_id="nose", seq=seq, stamp_us=t - 400_000 + 100_000 * k,
                                encoding="mono8", image=img, camera=cam, position_ned_m=[2.0 * k, 0.0, -5.0],
                                q_wxyz=[1.0, 0.0, 0.0, 0.0])
        samples.append(SimpleNamespace(key_expr=K.posed_frame("v", "nose"),
                                       payload=SimpleNamespace(to_bytes=lambda p=payload: p)))
    policy = PairPolicy(PairPolicyConfig(min_baseline_m=1.0))
    locate_loop(node, _OneAtATime(samples), policy, "dense", {})
    c = node.counters()
    assert c["frames_skipped"] == 2 and c["seq_jumps"] == 1
    assert c["pairs.first_frame"] == c["skipped.first_frame"] == 1 and c.get("frames_superseded", 0) == 0
    put = [schema.decode(p, expect="range_map") for _, p in session.puts]
    # (the restarted camera's frame pairs with the last one before the restart: 100 ms and 2 m apart)
    assert [(m["seq"], m["other_seq"]) for m in put] == [(1, 0), (4, 1), (0, 4)]
    assert c["pairs.motion"] == c["pairs_computed.motion"] == c["pairs_computed"] == 3 and c["skipped"] == 1


class _OneAtATime:
    """A subscriber whose samples arrive one at a time (nothing waits in the ring behind the one received)."""

    def __init__(self, samples):
        self.samples = list(samples)

    def __iter__(self):
        return iter(self.samples)

    def try_recv(self):
        return None


# ---- fuse_frame in process: the fused path's publish gate, its count, and the reset after a failed push ----------

class OneMapPerFrame:
    """Stands in for the fusion runner: each push gives one fused map of the pushed frame (25 m everywhere),
    ``n_fused`` measurements per pixel (default 1). A runner whose state was just reset gives such a map for a frame
    of any age."""

    def __init__(self, n_fused=None):
        self.n_fused, self.counts, self.measure = n_fused, {}, None

    def push(self, fr):
        from eonav.fusion.sequence import FusedMap
        shape = (fr.camera.height, fr.camera.width)
        n = np.ones(shape, np.uint16) if self.n_fused is None else self.n_fused
        ms = [{"kind": "motion", "other_camera_id": fr.camera_id, "other_seq": fr.seq - 1, "baseline_m": 2.0}]
        return [FusedMap(fr, _range_result(shape), n, ms, 0.01, 0.001)]


def _fuse_frames(node, runner, pubs, cams, frames, gate=None):
    """``fuse_frame`` for each posed frame in order, as the locate loop calls it (one scale controller, fixed
    scale 1; the runner's counts and the frames behind the maps kept across calls)."""
    from eonav.services.locator import fuse_frame, scale_controllers
    sc, reported, sources = scale_controllers(1.0)(), {}, {}
    for f in frames:
        fuse_frame(node, runner, f, sc, pubs, "f16", time.perf_counter(), cams, "locate", reported, sources, gate)


def test_fused_path_never_puts_a_map_older_than_the_last_one_put():
    """The publish-side gate on the fused path (``fuse_frame``, the default with the dense method), as on the single
    pair's: once the fused map of frame t is put, a fused map of an older frame is not put (``dropped.out_of_order``);
    one as new or newer is, and the camera's mark is the newest stamp put (the arrival side checks against it)."""
    from eonav.bus.freshness import FreshnessGate
    t = time.time_ns() // 1000
    gate = FreshnessGate(1.0, clock_us=lambda: t)
    node, session, pubs, cams, pair = _pair_harness()
    frames = [pair(stamp, seq).a for stamp, seq in ((t - 100_000, 5), (t - 200_000, 4), (t - 100_000, 6),
                                                    (t - 50_000, 7))]
    _fuse_frames(node, OneMapPerFrame(), pubs, cams, frames, gate)
    put = [schema.decode(p, expect="range_map") for _, p in session.puts]
    assert [(m["seq"], m["stamp_us"]) for m in put] == [(5, t - 100_000), (6, t - 100_000), (7, t - 50_000)]
    assert all(m["method"] == "stand-in" and np.all(m["range_m"] == 25.0) for m in put)
    c = node.counters()
    assert c["dropped.out_of_order"] == 1 and c["maps_fused"] == 3 and gate.last_published_us("nose") == t - 50_000


def test_fused_map_count_saturates_at_255():
    """``n_fused`` travels as uint8 and saturates at 255 (docs/bus.md, range_map); the state counts up to 65535, so
    a pixel fused 256, 300 or 1000 times reads 255, not the low byte (0, 44, 232: well measured shown as unmeasured
    or barely measured)."""
    node, session, pubs, cams, pair = _pair_harness()
    n = np.zeros((12, 16), np.uint16)
    n[0, :7] = [0, 1, 254, 255, 256, 300, 1000]
    n[5:, :] = 65535
    _fuse_frames(node, OneMapPerFrame(n), pubs, cams, [pair(time.time_ns() // 1000).a])
    (_, payload), = session.puts
    got = schema.decode(payload, expect="range_map")["n_fused"]
    assert got.dtype == np.uint8 and got.shape == (12, 16)
    assert got[0, :7].tolist() == [0, 1, 254, 255, 255, 255, 255]
    assert np.all(got[5:] == 255) and np.all(got[1:5] == 0)


def test_a_failed_fusion_push_resets_the_cameras_state_and_the_next_maps_start_afresh(flight_frames):
    """A push that raises (here: the measurement of frame 3) costs that frame's map, is counted (``locate_errors``,
    ``fusion.resets_on_error``) and forgets the camera's state: the maps after it are built on the frames after it
    only (per-pixel count 1, then 2), not on the state from before the failure (which would read 3, 4), and still
    match the renderer's truth. The real fusion runner of the locator's default flags."""
    import argparse

    from eonav.services import locator
    frames, _ = flight_frames
    p = argparse.ArgumentParser()
    locator.add_arguments(p)
    runner = locator.fusion_runner(p.parse_args([]), {})
    measure, failing = runner.measure, {"now": False}

    def measure_or_fail(va, vb, **kw):
        if failing["now"]:
            raise ValueError("singular system")
        return measure(va, vb, **kw)
    runner.measure = measure_or_fail
    node, session, pubs, cams, _ = _pair_harness()
    stamps = [1_000_000 + 100_000 * i for i in range(len(frames))]
    posed = [locator.frame_info(schema.decode(posed_frame_payload(i, stamps[i], view), expect="posed_frame"), cams)
             for i, (_, view, _) in enumerate(frames)]
    _fuse_frames(node, runner, pubs, cams, posed[:3])
    failing["now"] = True
    _fuse_frames(node, runner, pubs, cams, posed[3:4])
    failing["now"] = False
    _fuse_frames(node, runner, pubs, cams, posed[4:])
    put = [schema.decode(p, expect="range_map") for _, p in session.puts]
    assert [m["seq"] for m in put] == [1, 2, 4, 5]
    assert [int(m["n_fused"].max()) for m in put] == [1, 2, 1, 2]
    c = node.counters()
    assert c["locate_errors"] == 1 and c["fusion.resets_on_error"] == 1 and c["maps_fused"] == 4
    for m in put[2:]:
        truth = frames[m["seq"]][2]
        gt = on_grid(truth.range_m, m["range_m"].shape[1], m["range_m"].shape[0])
        ok = ((m["flags"] & VALID) != 0) & np.isfinite(m["range_m"]) & np.isfinite(gt)
        assert ok.mean() > 0.2 and np.median(np.abs(m["range_m"][ok] - gt[ok]) / gt[ok]) < 0.05


def test_a_rig_partners_push_publishes_the_reference_map_at_the_references_scale():
    """A stereo rig's reference map comes out of the partner camera's push (the reference's frame was held for the
    stereo measurement): it is published with the scale the reference's frame was located at (0.5 here), not the
    partner's (1.0), and its compute time goes to the reference camera's scale controller, whose map it is, as on
    the single-pair path (``scalers[ref]``)."""
    from eonav.fusion.sequence import FusedMap
    from eonav.geometry.camera import Camera
    from eonav.services.locator import fuse_frame, scale_controllers
    node, session, pubs, cams, _ = _pair_harness()
    pubs["right"] = node.publisher(K.range_map("v", "right"), image=True)
    img = (np.arange(24 * 32).reshape(24, 32) % 251).astype(np.uint8)
    t = time.time_ns() // 1000

    def posed(cid, east_m):
        from eonav.services.locator import frame_info
        cam = Camera(cid, 32, 24, 32.0, 32.0, 15.5, 11.5)
        return frame_info(schema.decode(schema.encode(
            "posed_frame", camera_id=cid, seq=3, stamp_us=t, encoding="mono8", image=img,
            camera=schema.camera_to_msg(cam), position_ned_m=[0.0, east_m, -5.0], q_wxyz=[1.0, 0.0, 0.0, 0.0]),
            expect="posed_frame"), cams)

    class HeldForStereo:
        """The reference's push gives no map (held); the partner's push gives the reference's map."""
        counts, measure, held = {}, None, None

        def push(self, fr):
            if fr.camera_id == "nose":
                self.held = fr
                return []
            shape = (self.held.camera.height, self.held.camera.width)
            ms = [{"kind": "stereo", "other_camera_id": "right", "other_seq": 3, "baseline_m": 0.8}]
            return [FusedMap(self.held, _range_result(shape), np.ones(shape, np.uint16), ms, 0.02, 0.003)]

    scalers = {"nose": scale_controllers(0.5)(), "right": scale_controllers(1.0)()}
    runner, reported, sources = HeldForStereo(), {}, {}
    for f in (posed("nose", 0.0), posed("right", 0.8)):
        fuse_frame(node, runner, f, scalers[f.camera_id], pubs, "f16", time.perf_counter(), cams, "locate",
                   reported, sources, None, scalers)
    (key, payload), = session.puts
    m = schema.decode(payload, expect="range_map")
    assert m["camera_id"] == "nose" and m["scale"] == 0.5 and m["range_m"].shape == (12, 16)
    assert scalers["nose"].measured_s(0.5) == pytest.approx(0.023)
    assert scalers["right"].measured_s(1.0) is None
