"""``eonav run --camera ID=SOURCE --mavlink SOURCE --cameras FILE``: the cameras file reaches the sync and every
camera ingest, recorded sources (image folder / video file with stamps + tlog) share one replay shift, and a real
run of a simulated recording poses and ranges every frame, in step with the navigation (truth from the simulator)."""
from __future__ import annotations

import argparse
import json
import signal
import socket
import struct
import threading
import time

import cv2
import numpy as np
import pytest

from eonav import InputError
from eonav.app import sources as S
from eonav.app.cli import build_parser
from eonav.app.commands.run import default_pipeline
from eonav.nav.mavlink_in import ned_from_lla
from eonav.services import camera_ingest as C
from eonav.sim.record import record_flight

N_FRAMES = 16


@pytest.fixture(scope="module")
def rec(tmp_path_factory):
    """16 frames at 5 Hz, 128 x 128, starting 3 s into the approach flight (the MAVLink ingest's clock lock), plus
    the same frames as a lossless video with its stamps beside it."""
    d = record_flight(tmp_path_factory.mktemp("rec"), name="approach", n_frames=N_FRAMES, rate_hz=5.0,
                      size=(128, 128), seed=0, frames_start_s=3.0)
    files = C.list_images(d / "frames")
    w = cv2.VideoWriter(str(d / "nose.avi"), cv2.VideoWriter_fourcc(*"FFV1"), 5.0, (128, 128), False)
    for f in files:
        w.write(cv2.imread(str(f), cv2.IMREAD_GRAYSCALE))
    w.release()
    (d / "nose.timestamps.txt").write_text((d / "frames" / "timestamps.txt").read_text())
    return d


def _stamps_us(rec):
    return C.parse_timestamps(rec / "frames" / "timestamps.txt")


def _first_tlog_us(path):
    with open(path, "rb") as f:
        return struct.unpack(">Q", f.read(8))[0]


def _first_fix(tlog):
    from eonav.nav.mavlink_in import TlogReader
    with TlogReader(tlog) as reader:
        return next(m for _, m in reader if m.get_type() == "GLOBAL_POSITION_INT")


def _run_args(*argv):
    return build_parser().parse_args(["run", *map(str, argv)])


# ---- sources and the shared shift ------------------------------------------------------------------------

def test_sources_first_stamps_and_the_joint_shift(rec, tmp_path):
    stamps = _stamps_us(rec)
    folder = S.camera_start("cam", str(rec / "frames"))
    video = S.camera_start("cam", str(rec / "nose.avi"))
    tlog = S.mavlink_start("mav", str(rec / "flight.tlog"))
    assert (folder.kind, folder.first_us) == ("folder", stamps[0])
    assert (video.kind, video.first_us) == ("file", stamps[0])
    assert (tlog.kind, tlog.first_us) == ("tlog", _first_tlog_us(rec / "flight.tlog"))
    assert tlog.first_us < stamps[0] - 2_900_000        # navigation starts 3 s before the frames
    now = 1_800_000_000_000_000
    shift = S.joint_replay_shift_us([folder, tlog], 2.5, now_us=now)
    assert shift == now + 2_500_000 - tlog.first_us      # the earliest record (the tlog's) lands 2.5 s from now
    assert S.joint_replay_shift_us([video, tlog], 2.5, now_us=now) == shift
    # nothing to keep in step: one recording, or recordings mixed with live sources
    assert S.joint_replay_shift_us([tlog], now_us=now) is None
    live = S.mavlink_start("mav", "udpin:0.0.0.0:14550")
    assert live.kind == "link" and S.joint_replay_shift_us([folder, live], now_us=now) is None
    assert S.camera_start("cam", "/dev/video0").kind == "v4l2"
    # a recording without stamps cannot be put in step with the tlog
    bare = tmp_path / "bare"
    bare.mkdir()
    cv2.imwrite(str(bare / "f0.png"), np.zeros((8, 8), np.uint8))
    with pytest.raises(InputError, match="without recorded stamps.*timestamps.txt"):
        S.joint_replay_shift_us([S.camera_start("--camera nose=bare", str(bare)), tlog])


def test_recordings_beside_a_live_source_get_no_joint_shift(rec):
    """Two recordings and a live camera: a live stream cannot be shifted, so no joint shift (None: each replay maps
    onto the current clock by itself, docs/bus.md "Running"), although two sources are recorded; the same two
    recordings with a third one instead get the shift that puts the earliest first stamp (the tlog's) 2 s from now.
    Catches the "recordings mixed with live sources" rule dropped (the earlier test mixes one recording only)."""
    now = 1_800_000_000_000_000
    folder = S.camera_start("--camera nose", str(rec / "frames"))
    video = S.camera_start("--camera tail", str(rec / "nose.avi"))
    tlog = S.mavlink_start("--mavlink", str(rec / "flight.tlog"))
    live = S.camera_start("--camera belly", "/dev/video0")
    assert live.kind == "v4l2" and not live.recorded
    assert S.joint_replay_shift_us([folder, tlog, live], 2.0, now_us=now) is None
    assert S.joint_replay_shift_us([live, folder, video, tlog], 2.0, now_us=now) is None
    assert S.joint_replay_shift_us([folder, video, tlog], 2.0, now_us=now) == \
        now + 2_000_000 - _first_tlog_us(rec / "flight.tlog")


def test_a_recording_without_stamps_is_told_where_its_stamps_go(rec, tmp_path):
    """The refusal names the stamps file the camera ingest would read for that kind of recording: an image folder's
    ``timestamps.txt`` in the folder, a video's ``<video name>.timestamps.txt`` beside it. Catches the two hints
    swapped (the earlier test's pattern matches either)."""
    tlog = S.mavlink_start("--mavlink", str(rec / "flight.tlog"))
    video = tmp_path / "clip.avi"
    video.write_bytes((rec / "nose.avi").read_bytes())          # no clip.timestamps.txt beside it
    folder = tmp_path / "frames"
    folder.mkdir()
    cv2.imwrite(str(folder / "f0.png"), np.zeros((8, 8), np.uint8))
    v, f = S.camera_start("--camera tail", str(video)), S.camera_start("--camera nose", str(folder))
    assert (v.kind, v.first_us, f.kind, f.first_us) == ("file", None, "folder", None)
    with pytest.raises(InputError, match=r"^--camera tail: .*expected <video name>\.timestamps\.txt beside the video"):
        S.joint_replay_shift_us([tlog, v])
    with pytest.raises(InputError, match=r"^--camera nose: .*expected timestamps\.txt in the folder"):
        S.joint_replay_shift_us([tlog, f])

def test_default_pipeline_gets_the_cameras_file_and_one_shift(rec):
    cams = rec / "cameras.json"
    args = _run_args("--camera", f"nose={rec / 'frames'}", "--mavlink", rec / "flight.tlog", "--cameras", cams,
                     "--replay-start-in-s", "3")
    spec, subs = default_pipeline(args)
    by = {s["name"]: s for s in spec["services"]}
    cam, mav, sync = by["camera_nose"]["args"], by["mavlink"]["args"], by["sync"]["args"]
    assert cam[cam.index("--cameras") + 1] == str(cams) and sync == ["--cameras", str(cams)]
    # the same shift for both replays, computed when they start: after every other service is alive
    assert cam[cam.index("--replay-shift-us") + 1] == mav[mav.index("--replay-shift-us") + 1] == "{replay_shift_us}"
    for name in ("camera_nose", "mavlink"):
        assert by[name]["after"] == ["sync", "locator", "obstacles"]
    t0 = time.time_ns() // 1000
    shift = subs["replay_shift_us"]()
    first_bus_us = _first_tlog_us(rec / "flight.tlog") + shift       # the tlog starts first (navigation lead)
    assert t0 + 3_000_000 <= first_bus_us <= time.time_ns() // 1000 + 3_000_000
    # a given shift is passed as it is; live sources get none
    spec, subs = default_pipeline(_run_args("--camera", f"nose={rec / 'frames'}", "--mavlink", rec / "flight.tlog",
                                            "--cameras", cams, "--replay-shift-us", "123"))
    assert not subs and all(s["args"][s["args"].index("--replay-shift-us") + 1] == "123"
                            for s in spec["services"] if s["name"] in ("camera_nose", "mavlink"))
    spec, subs = default_pipeline(_run_args("--camera", "nose=/dev/video0", "--mavlink", "udpin:0.0.0.0:14550",
                                            "--cameras", cams))
    assert not subs and not any("--replay-shift-us" in s.get("args", []) or s.get("after")
                                for s in spec["services"])
    # the cameras file is required and must name every camera
    with pytest.raises(InputError, match="--cameras FILE is required"):
        default_pipeline(_run_args("--camera", f"nose={rec / 'frames'}", "--mavlink", rec / "flight.tlog"))
    with pytest.raises(InputError, match="no camera 'tail'.*has nose"):
        default_pipeline(_run_args("--camera", f"tail={rec / 'frames'}", "--cameras", cams))


# ---- a video file with recorded stamps -------------------------------------------------------------------

class FakeClock(C.Clock):
    def __init__(self, now_us=1_800_000_000_000_000):
        self.us, self.slept = now_us, []

    def now_us(self):
        return self.us

    def monotonic(self):
        return self.us / 1e6

    def sleep(self, s, stop=None):
        if s > 0:
            self.slept.append(s)
            self.us += int(round(s * 1e6))


def _ingest_args(*argv):
    p = argparse.ArgumentParser()
    C.add_arguments(p)
    return p.parse_args([str(a) for a in argv])


def test_video_with_recorded_stamps_replays_at_the_shift(rec, tmp_path):
    stamps = _stamps_us(rec)
    clock = FakeClock()
    shift = clock.us + 1_000_000 - stamps[0]
    frames = C.make_frames(_ingest_args("--source", rec / "nose.avi", "--replay-shift-us", shift), clock=clock)
    out = list(frames)
    assert [f.stamp_us for f in out] == [s + shift for s in stamps]
    assert {f.stamp_source for f in out} == {"recorded"}
    assert clock.slept[0] == pytest.approx(1.0) and clock.us == stamps[-1] + shift     # released at each stamp
    first = cv2.imread(str(C.list_images(rec / "frames")[0]), cv2.IMREAD_GRAYSCALE)
    assert np.array_equal(out[0].image[..., 0], first)                                 # lossless, in order
    # restarted mid-way (frames 0..2 due more than 0.1 s ago): resumes at the first frame still due, never older
    clock = FakeClock()
    late = clock.us - (stamps[2] - stamps[0]) - 150_000 - stamps[0]
    out = list(C.make_frames(_ingest_args("--source", rec / "nose.avi", "--replay-shift-us", late), clock=clock))
    assert [f.stamp_us for f in out] == [s + late for s in stamps[3:]] and out[0].skipped == 3
    assert all(f.skipped == 0 for f in out[1:])
    # one stamp per frame; stamps are needed for a shift; a stamped video replays once
    bad = tmp_path / "v.avi"
    bad.write_bytes((rec / "nose.avi").read_bytes())
    (tmp_path / "v.timestamps.txt").write_text("\n".join(str(s) for s in stamps[:-1]))
    with pytest.raises(InputError, match=f"{N_FRAMES - 1} stamps for {N_FRAMES} frames"):
        C.make_frames(_ingest_args("--source", bad), clock=clock)
    (tmp_path / "v.timestamps.txt").unlink()
    with pytest.raises(InputError, match="replay-shift-us needs recorded stamps"):
        C.make_frames(_ingest_args("--source", bad, "--replay-shift-us", 5), clock=clock)
    with pytest.raises(InputError, match="replays once"):
        C.make_frames(_ingest_args("--source", rec / "nose.avi", "--loop"), clock=clock)


# ---- a real run ----------------------------------------------------------------------------------------------

@pytest.mark.parametrize("source", ["frames", "nose.avi"])
@pytest.mark.pipeline
def test_eonav_run_poses_and_ranges_every_frame_of_a_recording(rec, tmp_path, source):
    pytest.importorskip("zenoh")
    from eonav.app.processes import free_port, start_service, wait_until
    from eonav.bus import keys as K
    from eonav.bus import schema
    from eonav.bus.session import client_session
    from eonav.fusion.sequence import prepare_kernels
    prepare_kernels()                  # numba's cache, shared with the run's own preparation and the locator
    port, vehicle = free_port(), f"run{source[:3]}"
    proc = start_service(["-m", "eonav.app.cli", "run", "--camera", f"nose={rec / source}",
                          "--mavlink", str(rec / "flight.tlog"), "--cameras", str(rec / "cameras.json"),
                          "--port", str(port), "--vehicle", vehicle, "--quiet",
                          "--log-dir", str(tmp_path / "logs")])
    posed, ranged, lock = {}, set(), threading.Lock()
    try:
        def router_up():
            assert proc.poll() is None, proc.stderr.read()
            with socket.socket() as so:
                return so.connect_ex(("127.0.0.1", port)) == 0
        wait_until(router_up, timeout=90, period=0.2, what="the run's router")
        with client_session(f"tcp/127.0.0.1:{port}") as s:
            def on_posed(sample):
                m = schema.decode(sample.payload.to_bytes(), expect="posed_frame")
                with lock:
                    posed[int(m["stamp_us"])] = np.asarray(m["position_ned_m"], float)

            def on_range(sample):
                m = schema.decode(sample.payload.to_bytes(), expect="range_map")
                with lock:
                    ranged.add(int(m["stamp_us"]))
            health = {}

            def on_health(sample):
                m = schema.decode(sample.payload.to_bytes(), expect="health")
                health[m["service"]] = m["counters"]
            subs = [s.declare_subscriber(K.posed_frames_all(vehicle), on_posed),
                    s.declare_subscriber(K.range_maps_all(vehicle), on_range),
                    s.declare_subscriber(K.health_all(vehicle), on_health)]
            try:
                # the services' own counts: posed frames and range maps are CongestionControl.DROP channels (latest
                # wins), so a loaded machine may drop one on its way to this client; every frame posed is the sync's
                # claim, every frame ranged the locator's
                wait_until(lambda: health.get("locator", {}).get("out.range_map", 0) >= N_FRAMES - 1
                           and health.get("sync", {}).get("out.posed_frame", 0) >= N_FRAMES, timeout=30,
                           period=0.2, what="range maps")
            except AssertionError:
                raise AssertionError(f"{len(posed)} posed, {len(ranged)} ranged of {N_FRAMES}; "
                                     f"locator {health.get('locator')}") from None
            logs = tmp_path / "logs"
            wait_until(lambda: all("exit 0" in (logs / f"{n}.log").read_text() for n in ("camera_nose", "mavlink")),
                       timeout=10, period=0.2, what="both replays at their end")
            time.sleep(0.5)
            for sub in subs:
                sub.undeclare()
        proc.send_signal(signal.SIGINT)
        rc = proc.wait(30)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()
    err = proc.stderr.read()
    assert rc == 0, err
    assert "camera_nose=done" in err and "mavlink=done" in err and "config_error" not in err, err
    # every frame posed, every frame after the first (no earlier frame to pair with) ranged: the services' own counts
    # (posed frames, like range maps, go out with CongestionControl.DROP, latest wins: a loaded machine may drop one
    # on its way to this client, as seen once in CI with 15 of 16 delivered here and every frame ranged)
    assert health["sync"]["out.posed_frame"] == N_FRAMES and health["locator"]["out.range_map"] == N_FRAMES - 1
    assert len(posed) >= N_FRAMES - 1 and len(ranged) >= (N_FRAMES - 1) // 2   # delivered here (best effort)
    stamps = [int(t) for t in _stamps_us(rec)]
    bus = sorted(posed)
    # one shift puts every posed stamp on a recorded one: the recorded spacing, to the microsecond
    shifts = [bus[0] - t for t in stamps if {b - (bus[0] - t) for b in bus} <= set(stamps)]
    assert shifts
    # in step with the navigation: each frame posed where the simulated vehicle was when it was taken (the MAVLink
    # ingest's NED origin is the tlog's first GLOBAL_POSITION_INT fix; the truth's is the recording's origin)
    truth = np.load(rec / "truth.npz")
    origin = json.loads((rec / "manifest.json").read_text())["origin_lla"]
    fix = _first_fix(rec / "flight.tlog")
    first_fix_ned = ned_from_lla(fix.lat * 1e-7, fix.lon * 1e-7, fix.alt * 1e-3, origin)
    at = dict(zip(stamps, truth["position_ned_m"]))
    # in step with the navigation under exactly one of the shifts (with a frame missing here, the recorded spacing
    # also fits one frame period off: 4 m off in position at 20 m/s)
    errs = [max(np.linalg.norm(posed[b] - (at[b - sh] - first_fix_ned)) for b in bus) for sh in shifts]
    assert sum(e < 0.05 for e in errs) == 1, errs       # 20 m/s: 0.05 m = 2.5 ms out of step
    shift = shifts[int(np.argmin(errs))]
    assert ranged <= {t + shift for t in stamps[1:]}     # only frames after the first are ranged


# ---- the example pipeline in deploy/ -------------------------------------------------------------------------

def test_example_pipeline_parses_and_its_cameras_are_in_the_example_cameras_file():
    import importlib
    from pathlib import Path
    from eonav.app import launcher as L
    from eonav.bus.node import build_parser as service_parser
    from eonav.io.pairfile import load_camera_models
    deploy = Path(__file__).resolve().parents[1] / "deploy"
    services = L.parse_spec(str(deploy / "pipeline.example.json"))
    ctx = {"spec_dir": str(deploy), "vehicle": "uav1", "router": "tcp/127.0.0.1:7447", "port": "7447"}
    models = load_camera_models(deploy / "cameras.example.json")
    seen_cameras, by_module = set(), {}
    for sp in services:
        mod = importlib.import_module(sp.module)
        args = service_parser(sp.name, mod.add_arguments).parse_args([L._subst(a, ctx) for a in sp.args])
        by_module.setdefault(sp.module.rsplit(".", 1)[-1], []).append(args)
        if sp.module.endswith("camera_ingest"):
            assert args.camera_id in models and args.cameras == str(deploy / "cameras.example.json")
            corr = C.camera_correction(args)                 # the calibration loads; the size is the calibrated one
            cam = models[args.camera_id].camera
            assert (args.width, args.height) == (cam.width, cam.height)
            assert (corr.undistort is not None) == (args.camera_id in ("nose", "belly"))   # tail: plain pinhole
            seen_cameras.add(args.camera_id)
    assert seen_cameras == set(models)
    assert [a.cameras for a in by_module["sync"]] == [str(deploy / "cameras.example.json")]
    assert set(by_module) == {"camera_ingest", "mavlink_ingest", "sync", "locator", "obstacles"}
