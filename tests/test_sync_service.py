"""Sync service: the pure Pairer, then the real process over zenoh: frames + nav in, posed frames out,
poses matching the simulator's truth at each frame's capture time."""
from __future__ import annotations

import dataclasses
import json
import time

import numpy as np
import pytest

from eonav.bus import keys as K
from eonav.bus import schema
from eonav.geometry.frames import T_body_ned_from_quat
from eonav.io.pairfile import camera_to_dict
from eonav.sim.flight import flight
from eonav.sim.presets import scale_camera
from eonav.sim.record import nav_truth
from eonav.nav.timesync import QF_EXTRAPOLATED, QF_VELOCITY_AIDED, NavBuffer
from eonav.services import sync as S

W, H = 32, 24


def _angle(q_a, q_b):
    R = T_body_ned_from_quat(q_a) @ T_body_ned_from_quat(q_b).T
    return float(np.arccos(np.clip((np.trace(R) - 1) / 2, -1, 1)))


def _cameras_file(tmp_path):
    cam = scale_camera(flight("turning").camera, (W, H))
    p = tmp_path / "cameras.json"
    p.write_text(json.dumps({"nose": camera_to_dict(cam)}))
    return p, cam


def _nav_msgs(base_us, t_end_s):
    """ATTITUDE-like states at 50 Hz and position (with velocity) at 25 Hz of the turning flight."""
    out = []
    ta = np.arange(0, t_end_s, 0.02)
    tr = nav_truth("turning", ta)
    for k, t in enumerate(ta):
        out.append({"stamp_us": base_us + int(round(t * 1e6)), "q_wxyz": tr["q_wxyz"][k], "source": "ATTITUDE"})
        if k % 2 == 0:
            out.append({"stamp_us": base_us + int(round(t * 1e6)), "position_ned_m": tr["position_ned_m"][k],
                        "velocity_ned_mps": tr["velocity_ned_mps"][k], "source": "LOCAL_POSITION_NED"})
    return out


def _frame(base_us, t_s, seq, cam="nose"):
    img = np.full((H, W), seq % 256, np.uint8)
    return {"camera_id": cam, "seq": seq, "stamp_us": base_us + int(round(t_s * 1e6)), "stamp_source": "recorded",
            "encoding": "mono8", "image": img}


def test_load_cameras_accepts_section_or_pair_file(tmp_path):
    p, cam = _cameras_file(tmp_path)
    assert S.load_cameras(p)["nose"].fx == pytest.approx(cam.fx)
    p2 = tmp_path / "pair.json"
    p2.write_text(json.dumps({"cameras": json.loads(p.read_text()), "frames": []}))
    assert list(S.load_cameras(p2)) == ["nose"]
    p2.write_text("{")
    with pytest.raises(Exception, match="not valid JSON"):
        S.load_cameras(p2)


def test_pairer_waits_poses_and_drops_with_reasons(tmp_path):
    p, cam = _cameras_file(tmp_path)
    pr = S.Pairer(S.load_cameras(p), NavBuffer(), max_wait_s=0.1)
    for m in _nav_msgs(0, 0.5):
        pr.add_nav({"q_wxyz": [np.nan] * 4, "position_ned_m": [np.nan] * 3, "velocity_ned_mps": [np.nan] * 3, **m})
    pr.add_frame(schema.decode(schema.encode("frame", **_frame(0, 0.25, 1))), now_s=0.0)
    pr.add_frame(schema.decode(schema.encode("frame", **_frame(0, 0.49, 2))), now_s=0.0)   # past the nav
    pr.add_frame(schema.decode(schema.encode("frame", **_frame(0, 0.2, 3, cam="tail"))), now_s=0.0)
    out = pr.poll(now_s=0.0)
    assert [o["seq"] for o in out] == [1] and len(pr.pending) == 1       # frame 2 waits for nav
    assert pr.counts["unknown_camera"] == 1
    out = pr.poll(now_s=0.2)                                            # budget spent: extrapolate 11 ms
    assert [o["seq"] for o in out] == [2] and out[0]["quality_flags"] & QF_EXTRAPOLATED
    pr.add_frame(schema.decode(schema.encode("frame", **_frame(0, 0.6, 4))), now_s=0.3)
    assert pr.poll(now_s=0.5) == [] and pr.counts["dropped.extrapolation_limit"] == 1


def test_service_poses_frames_against_truth(tmp_path):
    zenoh = pytest.importorskip("zenoh")
    from eonav.bus.session import endpoint, listener_session
    from eonav.app.processes import drain, free_port, start_service, stop_service, wait_until
    cams_path, cam = _cameras_file(tmp_path)
    port = free_port()
    proc = None
    with listener_session(port) as s:
        posed_sub = s.declare_subscriber(K.posed_frame("t4", "nose"), zenoh.handlers.FifoChannel(1000))
        h_sub = s.declare_subscriber(K.health("t4", "sync"), zenoh.handlers.FifoChannel(1000))
        nav_pub = s.declare_publisher(K.nav_state("t4"))
        frame_pub = s.declare_publisher(K.frame("t4", "nose"))
        tail_pub = s.declare_publisher(K.frame("t4", "tail"))
        try:
            proc = start_service(["-m", "eonav.services.sync", "--cameras", str(cams_path), "--vehicle", "t4",
                                  "--connect", endpoint(port), "--health-period-s", "0.2", "--max-wait-ms", "300",
                                  "--max-input-age-ms", "5000"])      # the frames are stamped 1-2.5 s ago
            wait_until(lambda: nav_pub.matching_status.matching and frame_pub.matching_status.matching, 15,
                       what="the sync service's subscribers")
            time.sleep(0.2)
            base = time.time_ns() // 1000 - 2_000_000
            for m in _nav_msgs(base, 1.2):
                nav_pub.put(schema.encode("nav_state", **m))
            frame_t = [0.11, 0.333, 0.5, 0.777, 0.9, 1.1]
            frame_pub.put(schema.encode("frame", **_frame(base, -0.5, 100)))             # before the nav
            time.sleep(0.03)
            for i, t in enumerate(frame_t):
                frame_pub.put(schema.encode("frame", **_frame(base, t, i)))
                time.sleep(0.03)
            tail_pub.put(schema.encode("frame", **_frame(base, 0.5, 99, cam="tail")))    # unknown camera
            time.sleep(0.03)
            frame_pub.put(schema.encode("frame", **_frame(base, 1.3, 101)))              # nav never comes
            got = []
            wait_until(lambda: len(drain(posed_sub, got)) >= len(frame_t), 10, what="posed frames")
            time.sleep(0.6)                                                              # the late frame's budget
            drain(posed_sub, got)
            code, err = stop_service(proc)
            health = [schema.decode(m.payload.to_bytes()) for m in drain(h_sub)]
        finally:
            if proc is not None and proc.poll() is None:
                stop_service(proc)
    assert code == 0, err
    posed = [schema.decode(m.payload.to_bytes(), expect="posed_frame") for m in got]
    assert [p["seq"] for p in posed] == list(range(len(frame_t)))
    tr = nav_truth("turning", np.array(frame_t))
    for k, p in enumerate(posed):
        assert p["stamp_us"] == base + int(round(frame_t[k] * 1e6))
        # velocity-aided Hermite between 25 Hz samples: sub-millimetre; slerp between 50 Hz samples
        np.testing.assert_allclose(p["position_ned_m"], tr["position_ned_m"][k], atol=1e-3)
        np.testing.assert_allclose(p["velocity_ned_mps"], tr["velocity_ned_mps"][k], atol=0.02)
        assert _angle(p["q_wxyz"], tr["q_wxyz"][k]) < 1e-4
        assert p["quality_flags"] & QF_VELOCITY_AIDED and not p["quality_flags"] & QF_EXTRAPOLATED
        assert 0 < p["nav_gap_us"] <= 40_000
        assert p["camera"]["fx"] == pytest.approx(cam.fx) and p["camera"]["eps_deg"][1] == pytest.approx(-5.0)
        assert p["image"].shape == (H, W) and int(p["image"][0, 0]) == k
    c = health[-1]["counters"]
    assert c["unknown_camera"] == 1
    assert c["dropped.before_first_nav"] == 1
    assert c["dropped.extrapolation_limit"] == 1
    assert c["out.posed_frame"] == len(frame_t)
    assert c["posed"] == len(frame_t)        # the health counter is the total, not a sum of running totals


def test_pairer_position_lead_releases_on_attitude(tmp_path):
    """With a position lead, a frame is posed as soon as attitude brackets it while position (25 Hz) is at most the
    lead behind: flagged extrapolated, still within millimetres of the truth; without it the frame waits."""
    p, cam = _cameras_file(tmp_path)
    msgs = _nav_msgs(0, 0.47)                 # attitude every 20 ms up to 0.46 s, position every 40 ms up to 0.44 s
    t_frame = 0.455                           # attitude brackets it; position is 15 ms behind
    tr = nav_truth("turning", np.array([t_frame]))
    for lead, want in ((0.0, []), (0.02, [1])):
        pr = S.Pairer(S.load_cameras(p), NavBuffer(), max_wait_s=0.3, position_lead_s=lead)
        for m in msgs:
            pr.add_nav({"q_wxyz": [np.nan] * 4, "position_ned_m": [np.nan] * 3, "velocity_ned_mps": [np.nan] * 3,
                        **m})
        pr.add_frame(schema.decode(schema.encode("frame", **_frame(0, t_frame, 1))), now_s=0.0)
        out = pr.poll(now_s=0.0)
        assert [o["seq"] for o in out] == want
        if out:
            assert out[0]["quality_flags"] & QF_EXTRAPOLATED
            np.testing.assert_allclose(out[0]["position_ned_m"], tr["position_ned_m"][0], atol=0.01)
            assert _angle(out[0]["q_wxyz"], tr["q_wxyz"][0]) < 1e-4


def test_pairer_overflow_drops_the_oldest_frames_and_the_newest_are_posed(tmp_path):
    """More frames pending than ``max_pending`` (navigation late): the oldest stamps go, counted as
    ``dropped.pending_overflow``, as the frame ring does (the newest frames win); a frame arriving late with a stamp
    older than every pending one is the one dropped. Once navigation comes the newest frames are posed."""
    p, cam = _cameras_file(tmp_path)
    pr = S.Pairer(S.load_cameras(p), NavBuffer(), max_wait_s=0.3, max_pending=3)
    for seq in range(1, 6):                                              # frames at 0.1 .. 0.5 s, no nav yet
        pr.add_frame(schema.decode(schema.encode("frame", **_frame(0, 0.1 * seq, seq))), now_s=0.0)
    assert [s for s, _, _ in pr.pending] == [300_000, 400_000, 500_000]
    assert pr.counts["dropped.pending_overflow"] == 2
    pr.add_frame(schema.decode(schema.encode("frame", **_frame(0, 0.05, 9))), now_s=0.0)    # late and oldest
    assert [m["seq"] for _, _, m in pr.pending] == [3, 4, 5] and pr.counts["dropped.pending_overflow"] == 3
    for m in _nav_msgs(0, 0.6):
        pr.add_nav({"q_wxyz": [np.nan] * 4, "position_ned_m": [np.nan] * 3, "velocity_ned_mps": [np.nan] * 3, **m})
    assert [o["seq"] for o in pr.poll(now_s=0.0)] == [3, 4, 5]


def test_pairer_position_lead_needs_a_velocity_on_the_newest_position(tmp_path):
    """The position lead releases a frame early only when the newest position sample carries a velocity (a moving
    vehicle's LOCAL_POSITION_NED); position samples without one: the frame waits for its bracket as without a lead,
    and is extrapolated only when ``max_wait_s`` is spent."""
    p, cam = _cameras_file(tmp_path)
    msgs = _nav_msgs(0, 0.47)                 # as in the test above: attitude brackets 0.455 s, position 15 ms behind
    pr = S.Pairer(S.load_cameras(p), NavBuffer(), max_wait_s=0.3, position_lead_s=0.02)
    for m in msgs:
        pr.add_nav({"q_wxyz": [np.nan] * 4, "position_ned_m": [np.nan] * 3, **m, "velocity_ned_mps": [np.nan] * 3})
    assert pr.nav.pos.vel[-1] is None
    pr.add_frame(schema.decode(schema.encode("frame", **_frame(0, 0.455, 1))), now_s=0.0)
    assert pr.poll(now_s=0.0) == [] and len(pr.pending) == 1
    out = pr.poll(now_s=0.3)
    assert [o["seq"] for o in out] == [1] and out[0]["quality_flags"] & QF_EXTRAPOLATED


def test_pairer_posed_frame_carries_the_bracket_gap_and_its_own_camera(tmp_path):
    """A frame at 0.25 s between attitude samples 0.24/0.26 s (gap 20 ms) and position samples 0.24/0.28 s (gap
    40 ms): ``nav_gap_us`` is the wider bracket, 40_000 us (not ms). With two cameras in the file each posed frame
    carries the intrinsics of the camera it came from."""
    cam = scale_camera(flight("turning").camera, (W, H))
    tail = dataclasses.replace(cam, name="tail", fx=2 * cam.fx, fy=2 * cam.fy)
    p = tmp_path / "cameras.json"
    p.write_text(json.dumps({"nose": camera_to_dict(cam), "tail": camera_to_dict(tail)}))
    pr = S.Pairer(S.load_cameras(p), NavBuffer(gap_warn_us=60_000), max_wait_s=0.3)
    for m in _nav_msgs(0, 0.5):
        pr.add_nav({"q_wxyz": [np.nan] * 4, "position_ned_m": [np.nan] * 3, "velocity_ned_mps": [np.nan] * 3, **m})
    pr.add_frame(schema.decode(schema.encode("frame", **_frame(0, 0.25, 1))), now_s=0.0)
    pr.add_frame(schema.decode(schema.encode("frame", **_frame(0, 0.25, 2, cam="tail"))), now_s=0.0)
    out = {o["camera_id"]: o for o in pr.poll(now_s=0.0)}
    assert sorted(out) == ["nose", "tail"]
    for o in out.values():
        assert o["nav_gap_us"] == 40_000 and o["stamp_us"] == 250_000
        assert o["quality_flags"] & QF_VELOCITY_AIDED and not o["quality_flags"] & QF_EXTRAPOLATED
    assert out["nose"]["camera"]["fx"] == pytest.approx(cam.fx)
    assert out["tail"]["camera"]["fx"] == pytest.approx(2 * cam.fx)


def test_pairer_counts_a_frame_that_never_got_a_position_under_its_own_reason(tmp_path):
    """Attitude only, no position stream yet: the frame waits, and when ``max_wait_s`` is spent it cannot be
    extrapolated either; it is dropped and counted as ``dropped.no_position_yet``, the reason the pose failed, not
    under another drop reason."""
    p, cam = _cameras_file(tmp_path)
    pr = S.Pairer(S.load_cameras(p), NavBuffer(), max_wait_s=0.1)
    for m in _nav_msgs(0, 0.5):
        if m["source"] == "ATTITUDE":
            pr.add_nav({"position_ned_m": [np.nan] * 3, "velocity_ned_mps": [np.nan] * 3, **m})
    pr.add_frame(schema.decode(schema.encode("frame", **_frame(0, 0.25, 1))), now_s=0.0)
    assert pr.poll(now_s=0.0) == [] and len(pr.pending) == 1
    assert pr.poll(now_s=0.2) == [] and pr.pending == []
    assert dict(pr.counts) == {"dropped.no_position_yet": 1}


def test_pairer_position_lead_is_inclusive(tmp_path):
    """``position_lead_s`` is the most position may lag the frame for an early release ("at most this"): position 15 ms
    behind a frame whose attitude is bracketed is released with a 15 ms lead, and waits with a 14.9 ms one."""
    p, cam = _cameras_file(tmp_path)
    msgs = _nav_msgs(0, 0.47)                 # attitude up to 0.46 s, position (with velocity) up to 0.44 s
    for lead, want in ((0.015, [1]), (0.0149, [])):
        pr = S.Pairer(S.load_cameras(p), NavBuffer(), max_wait_s=0.3, position_lead_s=lead)
        for m in msgs:
            pr.add_nav({"q_wxyz": [np.nan] * 4, "position_ned_m": [np.nan] * 3, "velocity_ned_mps": [np.nan] * 3,
                        **m})
        pr.add_frame(schema.decode(schema.encode("frame", **_frame(0, 0.455, 1))), now_s=0.0)
        out = pr.poll(now_s=0.0)
        assert [o["seq"] for o in out] == want and len(pr.pending) == 1 - len(want)
