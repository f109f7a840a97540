"""Camera ingest: the pure capture loop and sources (fake clock, fake capture), then the real service
replaying an image folder over a real zenoh session on loopback."""
from __future__ import annotations

import argparse
import threading

import cv2
import numpy as np
import pytest

from eonav import InputError
from eonav.services import camera_ingest as C


class FakeClock(C.Clock):
    """Realtime starts at 1_700_000_000 s; sleep advances both clocks."""

    def __init__(self, now_us=1_700_000_000_000_000):
        self.us = now_us
        self.slept = []

    def now_us(self):
        return self.us

    def monotonic(self):
        return self.us / 1e6

    def sleep(self, s, stop=None):
        self.slept.append(s)
        self.us += int(round(s * 1e6))

    def mono_to_realtime_us(self):
        return 0


def _img(v, w=64, h=48, colour=False):
    a = np.full((h, w), v, np.uint8)
    a[0, 0] = (v + 1) % 256
    return cv2.cvtColor(a, cv2.COLOR_GRAY2BGR) if colour else a


def _folder(tmp_path, stamps_s=None, n=6):
    d = tmp_path / "rec"
    d.mkdir()
    for i in range(n):
        cv2.imwrite(str(d / f"frame_{i:03d}.png"), _img(10 * i, colour=(i % 2 == 0)))
    if stamps_s is not None:
        (d / "timestamps.txt").write_text("# recorded stamps, seconds\n" + "".join(f"{t:.6f}\n" for t in stamps_s))
    return d


# ---- timestamps file ---------------------------------------------------------------------------------

def test_timestamps_units(tmp_path):
    f = tmp_path / "t.txt"
    f.write_text("100.5\n100.6 frame_001.png\n\n# comment\n101\n")
    assert C.parse_timestamps(f) == [100_500_000, 100_600_000, 101_000_000]          # auto -> seconds
    f.write_text("1700000000000000\n1700000000100000\n")
    assert C.parse_timestamps(f) == [1_700_000_000_000_000, 1_700_000_000_100_000]  # auto -> microseconds
    assert C.parse_timestamps(f, "s")[0] == 1_700_000_000_000_000 * 1_000_000
    f.write_text("5\n6\n")
    assert C.parse_timestamps(f, "us") == [5, 6]
    assert C.parse_timestamps(f) == [5_000_000, 6_000_000]                          # small ints are seconds
    f.write_text("2\n1\n")
    with pytest.raises(InputError, match="must not decrease"):
        C.parse_timestamps(f)
    f.write_text("1\nabc\n")
    with pytest.raises(InputError, match="not a number"):
        C.parse_timestamps(f)


def test_timestamps_may_repeat_but_not_go_back(tmp_path):
    """The stamps must not decrease; a repeated stamp (two frames logged in one clock tick, a camera that stamps at
    millisecond resolution) is allowed and kept as it is: 1.0, 1.0, 1.1 s -> 1 000 000, 1 000 000, 1 100 000 us."""
    f = tmp_path / "t.txt"
    f.write_text("1.0\n1.0\n1.1\n")
    assert C.parse_timestamps(f) == [1_000_000, 1_000_000, 1_100_000]
    f.write_text("1700000000000000\n1700000000000000\n")
    assert C.parse_timestamps(f) == [1_700_000_000_000_000] * 2


def test_folder_needs_one_stamp_per_image(tmp_path):
    d = _folder(tmp_path, stamps_s=[1.0, 2.0], n=3)
    with pytest.raises(InputError, match="2 stamps for 3 image files"):
        list(C.folder_frames(d))


# ---- folder source + capture loop ----------------------------------------------------------------------

def test_folder_replay_maps_recorded_stamps_onto_now(tmp_path):
    stamps = [50.0, 50.1, 50.25, 50.3, 50.4, 50.5]
    d = _folder(tmp_path, stamps)
    clock = FakeClock()
    start = clock.us
    frames = C.folder_frames(d, clock=clock, pacer=C.Pacer("auto", clock))
    out = []
    st = C.capture_loop(frames, out.append, camera_id="nose")
    assert st.published == 6
    got = [f["stamp_us"] for f in out]
    assert got[0] == start                                   # offset = now - first stamp
    assert np.diff(got).tolist() == [100_000, 150_000, 50_000, 100_000, 100_000]   # spacing preserved
    assert [f["stamp_source"] for f in out] == ["recorded"] * 6
    assert [f["source_pts_us"] for f in out] == [int(round(t * 1e6)) for t in stamps]
    assert [f["seq"] for f in out] == list(range(6))
    assert all(f["image"].shape == (48, 64) and f["image"].dtype == np.uint8 for f in out)   # mono8
    assert out[3]["image"][1, 1] == 30 and out[3]["encoding"] == "mono8"
    assert clock.slept == pytest.approx([0.1, 0.15, 0.05, 0.1, 0.1], abs=1e-5)                       # real-time pacing


def test_folder_joint_replay_shift_stamps_and_releases_at_the_shifted_time(tmp_path):
    # Two replays of one recording get the same shift D: each frame is stamped recorded + D and released when
    # the host clock reaches that stamp, whenever this process happened to start.
    stamps = [50.0, 50.1, 50.25]
    d = _folder(tmp_path, stamps, n=3)
    clock = FakeClock()
    shift = clock.us + 2_000_000 - 50_000_000        # first frame due 2 s from now
    out = []
    C.capture_loop(C.folder_frames(d, clock=clock, pacer=C.Pacer("auto", clock), replay_shift_us=shift),
                   out.append, camera_id="nose")
    assert [f["stamp_us"] for f in out] == [int(round(t * 1e6)) + shift for t in stamps]
    assert clock.slept == pytest.approx([2.0, 0.1, 0.15], abs=1e-5)   # released at the stamp, not at start
    assert clock.us == out[-1]["stamp_us"]
    with pytest.raises(InputError, match="replay-shift-us needs recorded stamps"):
        (tmp_path / "x").mkdir()
        next(C.folder_frames(_folder(tmp_path / "x", None, n=1), clock=clock, replay_shift_us=shift))


def test_folder_keep_stamps_loop_and_fixed_rate(tmp_path):
    d = _folder(tmp_path, [10.0, 10.2, 10.4], n=3)
    clock = FakeClock()
    stop = threading.Event()
    frames = C.folder_frames(d, clock=clock, keep_stamps=True, loop=True, pacer=C.Pacer(50.0, clock), stop=stop)
    out = []

    def sink(f):
        out.append(f)
        if len(out) == 7:
            stop.set()
    C.capture_loop(frames, sink, camera_id="nose", stop=stop)
    assert [f["stamp_us"] for f in out] == [10_000_000, 10_200_000, 10_400_000,
                                            10_600_000, 10_800_000, 11_000_000, 11_200_000]
    assert out[0]["stamp_source"] == "recorded_raw"
    assert clock.slept == pytest.approx([0.02] * 6, abs=1e-5)          # --rate-hz 50: fixed pacing


def test_folder_loop_continues_by_the_median_spacing_not_the_longest(tmp_path):
    """A looped folder with stamps 10.0, 10.1, 10.2, 10.6 s (spacings 0.1, 0.1, 0.4: one dropout): the second lap
    starts one median spacing (0.1 s) after the last stamp, at 10.7 s, not 0.4 s (the longest) or 0.2 s (the
    mean) after it, so the lap joint looks like an ordinary frame interval."""
    d = _folder(tmp_path, [10.0, 10.1, 10.2, 10.6], n=4)
    stop = threading.Event()
    out = []

    def sink(f):
        out.append(f)
        if len(out) == 6:
            stop.set()
    C.capture_loop(C.folder_frames(d, clock=FakeClock(), keep_stamps=True, loop=True, stop=stop), sink,
                   camera_id="nose", stop=stop)
    assert [f["stamp_us"] for f in out] == [10_000_000, 10_100_000, 10_200_000, 10_600_000, 10_700_000, 10_800_000]


def test_folder_without_timestamps_uses_host_clock(tmp_path):
    d = _folder(tmp_path, None, n=3)
    clock = FakeClock()
    out = []
    C.capture_loop(C.folder_frames(d, clock=clock, pacer=C.Pacer(0, clock)), out.append, camera_id="c",
                   encoding="bgr8")
    assert [f["stamp_source"] for f in out] == ["host"] * 3
    assert out[1]["image"].shape == (48, 64, 3) and out[1]["encoding"] == "bgr8"


def test_corrupt_and_wrong_size_frames_are_counted_and_skipped(tmp_path):
    d = _folder(tmp_path, None, n=3)
    (d / "frame_001.png").write_bytes(b"\x89PNG\r\n\x1a\n" + b"garbage" * 10)    # corrupt
    cv2.imwrite(str(d / "frame_002b.png"), np.zeros((32, 32), np.uint8))      # wrong size
    cv2.imwrite(str(d / "frame_003.png"), (np.ones((48, 64), np.uint16) * 65535))  # 16 bit -> 255

    class M(C.NullMetrics):
        def __init__(self):
            self.c = {}

        def count(self, name, n=1):
            self.c[name] = self.c.get(name, 0) + n
    m = M()
    out = []
    st = C.capture_loop(C.folder_frames(d, pacer=None), out.append, camera_id="c", width=64, height=48, metrics=m)
    assert (st.published, st.corrupt, st.wrong_size) == (3, 1, 1)
    assert m.c["corrupt_frames"] == 1 and m.c["wrong_size"] == 1 and m.c["frames_in"] == 5
    assert [f["seq"] for f in out] == [0, 1, 2]                # seq counts published frames
    assert out[-1]["image"].max() == 255


def test_undecodable_pixels_count_as_corrupt_not_wrong_size():
    """A frame that decodes to pixels ``convert`` cannot publish (float32, 5 channels) is counted as corrupt
    (``corrupt_frames``), not as a wrong size, even when its size is the expected one; the good frame still goes out
    as seq 0."""
    class M(C.NullMetrics):
        def __init__(self):
            self.c = {}

        def count(self, name, n=1):
            self.c[name] = self.c.get(name, 0) + n
    frames = [C.RawFrame(index=0, image=np.zeros((48, 64), np.float32), stamp_us=1, stamp_source="host"),
              C.RawFrame(index=1, image=np.zeros((48, 64, 5), np.uint8), stamp_us=2, stamp_source="host"),
              C.RawFrame(index=2, image=_img(7), stamp_us=3, stamp_source="host")]
    m = M()
    out = []
    st = C.capture_loop(frames, out.append, camera_id="c", width=64, height=48, metrics=m)
    assert (st.published, st.corrupt, st.wrong_size) == (1, 2, 0)
    assert m.c["corrupt_frames"] == 2 and "wrong_size" not in m.c
    assert [f["seq"] for f in out] == [0] and out[0]["stamp_us"] == 3


def test_sixteen_bit_pixels_are_scaled_not_truncated():
    """A 16-bit image goes to 8 bits by v * 255 // 65535 (full scale to full scale): 0, 257, 1000, 4095, 32896,
    65535 -> 0, 1, 3, 15, 128, 255 (hand values). Keeping the low byte instead would give 1000 -> 232 and a 12-bit
    sensor's white (4095) -> 255: bright where the scene is dark."""
    v = np.array([[0, 257, 1000, 4095, 32896, 65535]], np.uint16)
    assert C.convert(v, "mono8").tolist() == [[0, 1, 3, 15, 128, 255]]
    assert C.convert(v, "bgr8")[0, 2].tolist() == [3, 3, 3]


def test_colour_frames_are_read_as_bgr():
    """Decoded colour frames are BGR (OpenCV's order): mono8 is 0.114 B + 0.587 G + 0.299 R, so pure blue -> 29,
    pure green -> 150, pure red -> 76 (hand values, rounded); with the channels read as RGB blue and red would swap
    (76 and 29). The same with an alpha channel; bgr8 keeps the order."""
    bgr = np.zeros((1, 3, 3), np.uint8)
    bgr[0, 0, 0] = bgr[0, 1, 1] = bgr[0, 2, 2] = 255            # blue, green, red
    assert C.convert(bgr, "mono8").tolist() == [[29, 150, 76]]
    bgra = np.dstack([bgr, np.full((1, 3), 255, np.uint8)])
    assert C.convert(bgra, "mono8").tolist() == [[29, 150, 76]]
    assert C.convert(bgra, "bgr8").tolist() == bgr.tolist()


def test_repeated_and_backward_stamps_are_counted_as_nonincreasing():
    """Stamps 100, 200, 200, 150, 300 us: the repeated 200 and the 150 after it do not increase (two counts of
    ``nonincreasing_stamps``); all five frames are still published in order."""
    class M(C.NullMetrics):
        def __init__(self):
            self.c = {}

        def count(self, name, n=1):
            self.c[name] = self.c.get(name, 0) + n
    stamps = [100, 200, 200, 150, 300]
    frames = [C.RawFrame(index=i, image=_img(i), stamp_us=t, stamp_source="pts") for i, t in enumerate(stamps)]
    m = M()
    out = []
    C.capture_loop(frames, out.append, camera_id="c", metrics=m)
    assert [f["stamp_us"] for f in out] == stamps
    assert m.c["nonincreasing_stamps"] == 2


def test_bad_encoding_rejected():
    with pytest.raises(InputError, match="encoding"):
        C.capture_loop([], lambda f: None, camera_id="c", encoding="rgb16")


# ---- video-capture source (fake cv2.VideoCapture) ----------------------------------------------------

class FakeCap:
    def __init__(self, pts_ms, bad=(), fps=20.0):
        self.pts_ms, self.bad, self.fps = list(pts_ms), set(bad), fps
        self.i = -1
        self.released = False

    def grab(self):
        self.i += 1
        return self.i < len(self.pts_ms)

    def retrieve(self):
        if self.i in self.bad:
            return False, None
        return True, _img(self.i)

    def get(self, prop):
        if prop == cv2.CAP_PROP_FPS:
            return self.fps
        if prop == cv2.CAP_PROP_POS_MSEC:
            return self.pts_ms[self.i]
        return 0.0

    def release(self):
        self.released = True


def test_file_pts_mapped_to_wallclock_origin_and_corrupt_frames():
    clock = FakeClock()
    start = clock.us
    caps = []

    def factory():
        caps.append(FakeCap([0.0, 50.0, 100.0, 150.0], bad={2}))
        return caps[-1]
    out, stats = [], None
    frames = C.capture_frames(factory, "file", pacer=C.Pacer("auto", clock), clock=clock)
    stats = C.capture_loop(frames, out.append, camera_id="c")
    assert stats.published == 3 and stats.corrupt == 1
    assert [f["stamp_us"] - start for f in out] == [0, 50_000, 150_000]
    assert [f["stamp_source"] for f in out] == ["pts"] * 3
    assert [f["source_pts_us"] for f in out] == [0, 50_000, 150_000]
    assert caps[0].released


def test_file_loop_keeps_stamps_increasing():
    clock = FakeClock()
    frames = C.capture_frames(lambda: FakeCap([0.0, 50.0]), "file", loop=True, pacer=C.Pacer(0, clock), clock=clock)
    out = []
    stop = threading.Event()

    def sink(f):
        out.append(f)
        if len(out) == 5:
            stop.set()
    C.capture_loop(frames, sink, camera_id="c", stop=stop)
    d = np.diff([f["stamp_us"] for f in out])
    assert (d == 50_000).all(), d


def test_file_without_pts_is_stamped_and_paced_at_its_frame_rate():
    """A video whose container gives no PTS (POS_MSEC NaN) at 20 fps: frame n is stamped first grab + n * 50 ms
    (``fps``), the first one at the grab itself, and the auto pacer sleeps 50 ms before each later frame, whatever
    the decode pace. Hand values, us from the first grab."""
    clock = FakeClock()
    start = clock.us
    nan = float("nan")
    frames = C.capture_frames(lambda: FakeCap([nan] * 4, fps=20.0), "file", pacer=C.Pacer("auto", clock), clock=clock)
    got = list(frames)
    assert [(f.stamp_us - start, f.stamp_source) for f in got] == [(n * 50_000, "fps") for n in range(4)]
    assert clock.slept == pytest.approx([0.05] * 3, abs=1e-6)


def test_looped_file_with_no_frame_ends_instead_of_reopening_forever():
    """``--loop`` over a video that yields no frame at all (empty, or nothing decodable) ends at the first EOF: there
    is no lap to repeat, and re-opening it would spin the capture thread without end. One open, no frame."""
    opened = []
    stop = threading.Event()

    def factory():
        opened.append(1)
        if len(opened) >= 3:
            stop.set()           # the guard for a build that re-opens: it stops after 3 opens, and the test fails
        return FakeCap([])
    got = list(C.capture_frames(factory, "file", loop=True, clock=FakeClock(), stop=stop))
    assert got == [] and len(opened) == 1


class FlakyCap(FakeCap):
    """A live camera: grab n advances the host clock by steps_us[n] and succeeds or not as ok[n]; after the list
    every grab fails (the camera unplugged)."""

    def __init__(self, clock, steps_us, ok):
        super().__init__([-1.0] * len(ok), fps=0.0)
        self.clock, self.steps_us, self.ok = clock, list(steps_us), list(ok)

    def grab(self):
        self.i += 1
        if self.i >= len(self.ok):
            return False
        self.clock.us += self.steps_us[self.i]
        return self.ok[self.i]


def test_live_timeout_counts_from_the_last_frame_not_the_start():
    """A V4L2 camera delivering a frame a second for 8 s, with one failed grab at 6.5 s, then unplugged: the one
    failure is tolerated (the last frame was 0.5 s before, not over 5 s; the retry 50 ms later moves the last two
    frames to 7.05 and 8.05 s), all 9 frames go out, and the source gives up (EonavError, for a restart) on the first
    failed grab more than 5 s (--live-timeout-s) after the last frame: 5.05 s, failed grabs being retried every 50 ms.
    Hand values, us from the first grab."""
    from eonav import EonavError
    clock = FakeClock()
    start = clock.us
    steps = [0] + [1_000_000] * 6 + [500_000, 500_000, 1_000_000]
    ok = [True] * 7 + [False] + [True] * 2
    frames = C.capture_frames(lambda: FlakyCap(clock, steps, ok), "v4l2", clock=clock, live_timeout_s=5.0)
    got = []
    with pytest.raises(EonavError, match="no frame for 5.0 s"):
        for f in frames:
            got.append(f)
    assert [f.stamp_us - start for f in got] == [s * 1_000_000 for s in range(7)] + [7_050_000, 8_050_000]
    assert clock.us - got[-1].stamp_us == pytest.approx(5_050_000, abs=1)


def test_v4l2_monotonic_stamps_converted_else_host():
    clock = FakeClock()   # its monotonic -> realtime offset is 0, so a plausible kernel stamp is close to now
    frames = C.capture_frames(lambda: FakeCap([clock.us / 1000.0 - 3.0, 12.0]), "v4l2", clock=clock)
    first = next(frames)
    assert first.stamp_source == "v4l2" and first.stamp_us == clock.us - 3000
    second = next(frames)
    assert second.stamp_source == "host" and second.stamp_us == clock.us   # implausible driver stamp
    frames.close()


def test_v4l2_monotonic_kernel_stamp_moves_to_the_realtime_clock():
    """uvcvideo stamps buffers on CLOCK_MONOTONIC; the stamp is that plus the monotonic -> realtime offset (here a
    host booted 10 000 s ago: monotonic = realtime - offset). A driver stamping on the realtime clock is taken
    as it is; a stamp plausible on neither clock (> 2 s off) gives the host clock."""
    now = FakeClock().us
    mono_to_rt = now - 10_000_000_000

    class BootedClock(FakeClock):
        def mono_to_realtime_us(self):
            return mono_to_rt
    clock = BootedClock(now)
    kernel_ms = (clock.us - mono_to_rt - 3000) / 1000.0          # exposed 3 ms ago, monotonic clock
    realtime_ms = (clock.us - 4000) / 1000.0                     # 4 ms ago, realtime clock
    frames = C.capture_frames(lambda: FakeCap([kernel_ms, realtime_ms, 12.0]), "v4l2", clock=clock)
    got = [(f.stamp_source, f.stamp_us - clock.us) for f in (next(frames) for _ in range(3))]
    frames.close()
    assert got == [("v4l2", -3000), ("v4l2", -4000), ("host", 0)]


class StreamCap(FakeCap):
    """A network stream: each grab advances the host clock by its step (frames arrive in real time)."""

    def __init__(self, clock, steps_us, pts_ms):
        super().__init__(pts_ms, fps=0.0)
        self.clock, self.steps_us = clock, list(steps_us)

    def grab(self):
        ok = super().grab()
        if ok:
            self.clock.us += self.steps_us[self.i]
        return ok


def test_stream_pts_reanchored_when_it_jumps_or_stalls():
    """A stream is stamped from its PTS on a wall-clock origin taken at the first frame; when the PTS stamp lands
    more than 2 s from the host clock (the PTS jumped 10 min ahead, an encoder restart; or 5 s of stall with the
    PTS only 50 ms on) the origin is taken again at that frame, so stamps stay within 2 s of the host clock and
    keep the PTS spacing after. Hand values, us from the first grab."""
    clock = FakeClock()
    start = clock.us
    steps = [0, 50_000, 50_000, 50_000, 5_000_000, 50_000]
    pts = [0.0, 50.0, 600_100.0, 600_150.0, 600_200.0, 600_250.0]
    frames = C.capture_frames(lambda: StreamCap(clock, steps, pts), "stream", clock=clock)
    got = [next(frames) for _ in range(6)]
    frames.close()
    assert [f.stamp_us - start for f in got] == [0, 50_000, 100_000, 150_000, 5_150_000, 5_200_000]
    assert [f.stamp_source for f in got] == ["pts"] * 6
    assert [f.source_pts_us for f in got] == [int(p * 1000) for p in pts]


def test_stream_pts_going_back_is_anchored_again():
    """A stream whose PTS starts over (an encoder or stream restart) 1 s in: the frame where it goes back is stamped
    from the host clock and becomes the new origin, so the next frames keep the PTS spacing on the host timeline. Not
    caught by the 2 s plausibility rule alone: on the old origin they would be stamped 1.05 s early. Hand values, us
    from the first grab."""
    clock = FakeClock()
    start = clock.us
    steps = [0, 1_000_000, 50_000, 50_000]
    pts = [0.0, 1000.0, 0.0, 50.0]
    frames = C.capture_frames(lambda: StreamCap(clock, steps, pts), "stream", clock=clock)
    got = [next(frames) for _ in range(4)]
    frames.close()
    assert [f.stamp_us - start for f in got] == [0, 1_000_000, 1_050_000, 1_100_000]
    assert [f.stamp_source for f in got] == ["pts"] * 4


def test_recorded_video_keeps_the_recorded_spacing_not_the_decode_pace():
    """A video with a timestamps file, replayed without a shift: the first frame is stamped now and every later one
    now + (its recorded stamp - the first), whatever pace the decoder delivers at (here 40 ms a frame while the
    recording is 100/150/50 ms apart). With --keep-stamps the recorded stamps go out as they are."""
    rec = [50_000_000, 50_100_000, 50_250_000, 50_300_000]

    def decoded(clock):
        for i in range(len(rec)):
            yield C.RawFrame(index=i, image=_img(i), stamp_us=clock.us, stamp_source="pts", grab_mono=0.0)
            clock.us += 40_000
    clock = FakeClock()
    start = clock.us
    out = list(C.recorded_video_frames(decoded(clock), rec, clock=clock))
    assert [f.stamp_us - start for f in out] == [0, 100_000, 250_000, 300_000]
    assert [f.stamp_source for f in out] == ["recorded"] * 4 and [f.source_pts_us for f in out] == rec
    clock = FakeClock()
    out = list(C.recorded_video_frames(decoded(clock), rec, keep_stamps=True, clock=clock))
    assert [(f.stamp_us, f.stamp_source) for f in out] == [(r, "recorded_raw") for r in rec]


def test_recorded_video_resumed_replay_reports_the_frames_it_passed_over():
    """A video joint replay (re)started when its frame 2 was due exactly ``RESUME_LATE_US`` ago: frames 0 and 1 are
    passed over and reported on frame 2 (``skipped`` 2, then 0), so the published seq goes on from the recording's
    frame number (2, 3, 4: a gap downstream, not a restart); stamps are recorded + shift."""
    rec = [0, 100_000, 200_000, 300_000, 400_000]
    clock = FakeClock()
    shift = clock.us - C.RESUME_LATE_US - rec[2]
    frames = [C.RawFrame(index=i, image=_img(i), stamp_us=0, stamp_source="pts", grab_mono=0.0)
              for i in range(len(rec))]
    got = list(C.recorded_video_frames(iter(frames), rec, replay_shift_us=shift, clock=clock))
    assert [(f.index, f.skipped) for f in got] == [(2, 2), (3, 0), (4, 0)]
    assert [f.stamp_us for f in got] == [r + shift for r in rec[2:]]
    clock = FakeClock()
    out = []
    st = C.capture_loop(C.recorded_video_frames(iter(frames), rec, replay_shift_us=shift, clock=clock), out.append,
                        camera_id="nose")
    assert [f["seq"] for f in out] == [2, 3, 4] and st.skipped == 2


def test_classify_source(tmp_path):
    assert C.classify_source("rtsp://10.0.0.5/stream") == "stream"
    assert C.classify_source("http://cam.local/mjpg") == "stream"
    assert C.classify_source("0") == "v4l2" and C.classify_source("/dev/video2") == "v4l2"
    assert C.classify_source(str(tmp_path)) == "folder"
    f = tmp_path / "a.mp4"
    f.write_bytes(b"x")
    assert C.classify_source(str(f)) == "file"
    with pytest.raises(InputError, match="not a directory"):
        C.classify_source(str(tmp_path / "nope.mp4"))


def test_flags_have_env_defaults(monkeypatch):
    monkeypatch.setenv("EONAV_CAMERA_RATE_HZ", "0")
    monkeypatch.setenv("EONAV_CAMERA_LOOP", "1")
    monkeypatch.setenv("EONAV_CAMERA_WIDTH", "640")
    p = argparse.ArgumentParser()
    C.add_arguments(p)
    a = p.parse_args(["--colour"])
    assert a.rate_hz == 0.0 and a.loop is True and a.width == 640 and a.height is None and a.encoding == "bgr8"
    assert p.parse_args(["--rate-hz", "auto"]).rate_hz == "auto"
    assert p.parse_args(["--rate", "12.5"]).rate_hz == 12.5           # the old spelling (deployed specs)
    monkeypatch.delenv("EONAV_CAMERA_RATE_HZ")
    monkeypatch.setenv("EONAV_CAMERA_RATE", "7")                      # the old variable (deployed env files)
    p = argparse.ArgumentParser()
    C.add_arguments(p)
    assert p.parse_args([]).rate_hz == 7.0


# ---- the real service over zenoh -----------------------------------------------------------------------

def test_service_replays_folder_over_zenoh(tmp_path):
    zenoh = pytest.importorskip("zenoh")
    from eonav.bus import keys as K
    from eonav.bus import schema
    from eonav.bus.session import endpoint, listener_session
    from eonav.app.processes import drain, free_port, start_service, wait_until

    stamps = [200.0, 200.05, 200.15, 200.2, 200.3, 200.35, 200.45, 200.5]
    d = tmp_path / "rec"
    d.mkdir()
    for i in range(8):
        if i == 2:
            (d / f"f_{i:02d}.png").write_bytes(b"\x89PNG\r\n\x1a\nnot really a png")   # corrupt
        elif i == 5:
            cv2.imwrite(str(d / f"f_{i:02d}.png"), np.zeros((20, 30), np.uint8))      # wrong size
        else:
            cv2.imwrite(str(d / f"f_{i:02d}.png"), _img(20 * i, colour=True))
    (d / "timestamps.txt").write_text("".join(f"{t}\n" for t in stamps))
    port = free_port()
    with listener_session(port) as s:
        frames_sub = s.declare_subscriber(K.frame("t1", "nose"), zenoh.handlers.FifoChannel(100))
        health_sub = s.declare_subscriber(K.health("t1", "camera_nose"), zenoh.handlers.FifoChannel(1000))
        proc = start_service(["-m", "eonav.services.camera_ingest", "--source", str(d), "--camera-id", "nose",
                              "--vehicle", "t1", "--name", "camera_nose", "--connect", endpoint(port),
                              "--width", "64", "--height", "48", "--rate-hz", "20", "--health-period-s", "0.1",
                              "--wait-subscribers-s", "10"])
        try:
            code = proc.wait(30)
        finally:
            if proc.poll() is None:
                proc.kill()
        err = proc.stderr.read()
        assert code == 0, err
        msgs = []
        wait_until(lambda: len(drain(frames_sub, msgs)) >= 6, 5, what="6 frames")
        frames = [schema.decode(m.payload.to_bytes(), expect="frame") for m in msgs]
        health = [schema.decode(m.payload.to_bytes(), expect="health") for m in drain(health_sub)]
    assert [f["seq"] for f in frames] == list(range(6))
    good = [i for i in range(8) if i not in (2, 5)]
    rec_us = [int(round(stamps[i] * 1e6)) for i in good]
    got = [f["stamp_us"] for f in frames]
    assert np.diff(got).tolist() == np.diff(rec_us).tolist()       # recorded spacing preserved
    assert got[0] - rec_us[0] > 1_600_000_000_000_000 - 200_000_000  # mapped onto the current clock
    assert all(f["stamp_source"] == "recorded" for f in frames)
    assert [f["source_pts_us"] for f in frames] == rec_us
    assert all(f["image"].shape == (48, 64) and f["encoding"] == "mono8" for f in frames)
    assert [int(f["image"][10, 10]) for f in frames] == [20 * i for i in good]
    assert health, err
    last = health[-1]["counters"]
    assert last["corrupt_frames"] == 1 and last["wrong_size"] == 1 and last["out.frame"] == 6
    assert "end of source" in err
