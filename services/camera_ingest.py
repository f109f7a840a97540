"""Camera ingest: one camera, live or recorded -> schema ``frame`` messages on ``keys.frame(vehicle, camera_id)``.

Live or recorded is one flag: ``--source`` takes a video file or an image folder (each with an optional timestamps
file), a V4L2 device or an RTSP/HTTP URL (docs/bus.md, "Camera ingest", lists the forms, the pacing and the stamps).
Every frame carries ``stamp_us`` (UNIX microseconds of capture on this host's realtime clock) and ``stamp_source``,
which says where the stamp came from: a recorded stamp, the stream's PTS, the V4L2 buffer time, the file's frame
rate, or the host clock right after ``grab()`` (decode time kept out of the stamp). Replays of one recording given
the same ``--replay-shift-us`` stay aligned with each other. The publisher drops frames rather than queueing them.

With ``--cameras FILE`` (the cameras file the sync reads) a camera whose entry has a lens model is undistorted
to its pinhole camera (tables built once, one ``cv2.remap`` a frame; ``eonav.io.calibration``), and each stamp
moves by the entry's ``time_offset_s`` plus half of ``--exposure-us`` to the middle of the exposure
(docs/cameras.md).

:func:`capture_loop` runs over an injected source, sink and metrics object, testable without zenoh or a camera.
"""
from __future__ import annotations

import logging
import re
import threading
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable, Iterable, Iterator

import numpy as np

from eonav import EonavError, InputError
from eonav.bus import keys as K
from eonav.bus.node import Node, add_flag, restart_count, service_main

log = logging.getLogger("eonav.service.camera")

IMAGE_EXTS = (".png", ".jpg", ".jpeg", ".bmp", ".tif", ".tiff", ".pgm", ".ppm", ".pnm", ".webp")
TIMESTAMPS_FILE = "timestamps.txt"
ENCODINGS = ("mono8", "bgr8")
US_THRESHOLD = 1e11  # integer stamps at or above this are microseconds (1e11 us = 27.8 h; 1e11 s = year 5138)
LIVE_PLAUSIBLE_US = 2_000_000
RESUME_LATE_US = 100_000  # a joint replay (re)starts at its first frame due no more than this long ago


# --------------------------------------------------------------------------------------------------
# clock (injectable)

class Clock:
    """Realtime microseconds, monotonic seconds and sleep; tests substitute a fake."""

    def now_us(self) -> int:
        return time.time_ns() // 1000

    def monotonic(self) -> float:
        return time.monotonic()

    def sleep(self, s: float, stop: threading.Event | None = None) -> None:
        if s <= 0:
            return
        if stop is not None:
            stop.wait(s)
        else:
            time.sleep(s)

    def mono_to_realtime_us(self) -> int:
        """Offset to add to a CLOCK_MONOTONIC stamp (us) to get the realtime clock (us)."""
        return (time.time_ns() - time.monotonic_ns()) // 1000


@dataclass
class RawFrame:
    """One frame as a source delivers it. ``image`` None = unreadable (``error`` says why)."""
    index: int
    image: np.ndarray | None
    stamp_us: int
    stamp_source: str
    source_pts_us: int = -1
    grab_mono: float = field(default_factory=time.monotonic)
    error: str = ""
    name: str = ""
    skipped: int = 0          # frames of the recording passed over just before this one (a resumed replay)


class Pacer:
    """Sleeps so that frames go out at the recorded pace (``mode="auto"``: media time), at a fixed
    ``fps``, or not at all (``fps == 0``). Media time is seconds from any origin; laps are handled by
    the caller passing a continuously increasing media time."""

    def __init__(self, rate, clock: Clock, stop: threading.Event | None = None):
        self.clock, self.stop = clock, stop
        if rate in (None, "auto"):
            self.mode, self.fps = "auto", None
        else:
            self.fps = float(rate)
            if self.fps < 0 or not np.isfinite(self.fps):
                raise InputError(f"--rate-hz {rate!r}: expected 'auto', 0 (as fast as possible) "
                                 f"or frames per second > 0")
            self.mode = "none" if self.fps == 0 else "fixed"
        self._t0 = None
        self._m0 = None
        self._n = 0

    def wait(self, media_s: float | None) -> None:
        if self.mode == "none":
            return
        now = self.clock.monotonic()
        if self._t0 is None:
            self._t0, self._m0 = now, media_s
            self._n = 1
            return
        if self.mode == "fixed" or media_s is None or self._m0 is None:
            fps = self.fps if self.mode == "fixed" else None
            if fps is None:  # auto without media time: nothing to pace by
                return
            target = self._t0 + self._n / fps
        else:
            target = self._t0 + (media_s - self._m0)
        self._n += 1
        delay = target - now
        if delay > 0:
            self.clock.sleep(delay, self.stop)
        elif delay < -1.0:  # far behind (a stall): re-anchor rather than burst
            self._t0, self._m0 = now, media_s
            self._n = 1


# --------------------------------------------------------------------------------------------------
# sources

def parse_timestamps(path: Path, unit: str = "auto") -> list[int]:
    """Stamps in microseconds from a timestamps file (see module docstring for the format)."""
    if unit not in ("auto", "s", "us"):
        raise InputError(f"--timestamps-unit {unit!r}: expected auto, s or us")
    raw: list[str] = []
    for ln, line in enumerate(Path(path).read_text().splitlines(), 1):
        line = line.split("#", 1)[0].strip()
        if not line:
            continue
        tok = re.split(r"[\s,]+", line)[0]
        try:
            float(tok)
        except ValueError:
            raise InputError(f"{path}:{ln}: stamp {tok!r} is not a number") from None
        raw.append(tok)
    if unit == "auto":
        ints = all(re.fullmatch(r"[+-]?\d+", t) for t in raw)
        unit = "us" if raw and ints and all(abs(int(t)) >= US_THRESHOLD for t in raw) else "s"
    if unit == "us":
        try:
            out = [int(t) for t in raw]
        except ValueError:
            raise InputError(f"{path}: --timestamps-unit us needs integer microseconds") from None
    else:
        out = [int(round(float(t) * 1e6)) for t in raw]
    for i in range(1, len(out)):
        if out[i] < out[i - 1]:
            raise InputError(f"{path}: stamps must not decrease (entry {i + 1}: {out[i]} us < {out[i - 1]} us)")
    return out


def list_images(folder: Path) -> list[Path]:
    return sorted(p for p in Path(folder).iterdir() if p.is_file() and p.suffix.lower() in IMAGE_EXTS)


def _median_dt_us(stamps: list[int], fallback_us: int) -> int:
    if len(stamps) < 2:
        return fallback_us
    return int(np.median(np.diff(stamps))) or fallback_us


def folder_frames(folder, *, timestamps: str | None = None, unit: str = "auto", keep_stamps: bool = False,
                  loop: bool = False, pacer: Pacer | None = None, clock: Clock | None = None,
                  default_fps: float = 10.0, stop: threading.Event | None = None,
                  reader: Callable | None = None, replay_shift_us: int | None = None) -> Iterator[RawFrame]:
    """Frames of an image folder (sorted files), stamped from the timestamps file if there is one.
    With ``replay_shift_us``, each frame is stamped recorded + shift and released when the host clock
    reaches that stamp (joint replays; the pacer is then not used); frames already due more than
    ``RESUME_LATE_US`` when the replay starts are passed over unread (``RawFrame.skipped``), so a replay restarted
    mid-way resumes where the clock says it is and never publishes an old stamp."""
    import cv2
    clock = clock or Clock()
    folder = Path(folder)
    files = list_images(folder)
    if not files:
        raise InputError(f"--source {folder}: no image files ({', '.join(IMAGE_EXTS)})")
    tpath = Path(timestamps) if timestamps else folder / TIMESTAMPS_FILE
    rec = None
    if timestamps and not tpath.is_file():
        raise InputError(f"--timestamps {tpath}: no such file")
    if tpath.is_file():
        rec = parse_timestamps(tpath, unit)
    if replay_shift_us is not None and (rec is None or keep_stamps):
        raise InputError("--replay-shift-us needs recorded stamps (a timestamps file) and excludes --keep-stamps")
    if replay_shift_us is not None:
        pacer = None
    if tpath.is_file():
        if len(rec) != len(files):
            raise InputError(f"{tpath}: {len(rec)} stamps for {len(files)} image files in {folder}; "
                             "expected one stamp per line per sorted image file")
    read = reader or (lambda p: cv2.imread(str(p), cv2.IMREAD_UNCHANGED))
    period_us = int(round(1e6 / default_fps)) if default_fps > 0 else 100_000
    offset_us = None
    lap_shift_us = 0
    index = 0
    resume_us = None if replay_shift_us is None else clock.now_us() - RESUME_LATE_US
    skipped = 0
    while True:
        for i, path in enumerate(files):
            if stop is not None and stop.is_set():
                return
            if rec is not None:
                media_us = rec[i] + lap_shift_us
            else:
                media_us = (index * period_us)
            if resume_us is not None and media_us + replay_shift_us < resume_us:
                skipped += 1
                index += 1
                continue
            if pacer:
                pacer.wait(media_us / 1e6)
            if replay_shift_us is not None:
                clock.sleep((media_us + replay_shift_us - clock.now_us()) / 1e6, stop)
            t_grab = clock.monotonic()
            host_us = clock.now_us()
            if rec is not None:
                if keep_stamps:
                    stamp, src = media_us, "recorded_raw"
                elif replay_shift_us is not None:
                    stamp, src = media_us + replay_shift_us, "recorded"
                else:
                    if offset_us is None:
                        offset_us = host_us - rec[0]
                    stamp, src = media_us + offset_us, "recorded"
                pts = rec[i]
            else:
                stamp, src, pts = host_us, "host", -1
            try:
                img = read(path)
                err = "" if img is not None else "cannot decode (corrupt or unsupported)"
            except Exception as e:  # permission denied, truncated file, ...
                img, err = None, f"{type(e).__name__}: {e}"
            yield RawFrame(index=index, image=img, stamp_us=stamp, stamp_source=src, source_pts_us=pts,
                           grab_mono=t_grab, error=err, name=path.name, skipped=skipped)
            skipped = 0
            index += 1
        if not loop:
            return
        if rec is not None:
            lap_shift_us += rec[-1] - rec[0] + _median_dt_us(rec, period_us)


def open_capture(source: str, kind: str, args=None):
    """A cv2.VideoCapture for a file, V4L2 device or network stream (raises InputError if it won't open)."""
    import cv2
    if kind == "v4l2":
        dev = int(source) if re.fullmatch(r"\d+", source) else source
        cap = cv2.VideoCapture(dev, cv2.CAP_V4L2)
        if args is not None and cap.isOpened():
            if getattr(args, "fourcc", None):
                cap.set(cv2.CAP_PROP_FOURCC, cv2.VideoWriter_fourcc(*args.fourcc[:4].ljust(4)))
            if getattr(args, "width", None):
                cap.set(cv2.CAP_PROP_FRAME_WIDTH, args.width)
            if getattr(args, "height", None):
                cap.set(cv2.CAP_PROP_FRAME_HEIGHT, args.height)
            if getattr(args, "device_fps", None):
                cap.set(cv2.CAP_PROP_FPS, args.device_fps)
            cap.set(cv2.CAP_PROP_BUFFERSIZE, int(getattr(args, "buffer_size", 2) or 2))
    else:
        if kind == "stream" and args is not None and getattr(args, "open_timeout", None):
            cap = cv2.VideoCapture(source, cv2.CAP_FFMPEG, [
                cv2.CAP_PROP_OPEN_TIMEOUT_MSEC, int(args.open_timeout_s * 1000),
                cv2.CAP_PROP_READ_TIMEOUT_MSEC, int(args.open_timeout_s * 1000)])
        else:
            cap = cv2.VideoCapture(source, cv2.CAP_FFMPEG)
    if not cap.isOpened():
        raise InputError(f"--source {source!r}: cannot open as {kind} (OpenCV build: FFMPEG and V4L2 only, no GStreamer)")
    return cap


def capture_frames(cap_factory: Callable[[], object], kind: str, *, loop: bool = False, pacer: Pacer | None = None,
                   clock: Clock | None = None, stop: threading.Event | None = None,
                   live_timeout_s: float = 5.0, default_fps: float = 30.0) -> Iterator[RawFrame]:
    """Frames from a cv2.VideoCapture-like object (``grab``, ``retrieve``, ``get``, ``release``).

    ``kind``: ``file`` (EOF ends, or loops; PTS mapped to a wall-clock origin), ``v4l2`` (kernel
    stamps) or ``stream`` (network; PTS mapped, re-anchored where it goes back or is implausible). The stamp is taken
    right after ``grab()``; ``retrieve()`` (decode) comes afterwards."""
    import cv2
    clock = clock or Clock()
    cap = cap_factory()
    fps = cap.get(cv2.CAP_PROP_FPS) if kind == "file" else 0.0
    if not fps or not np.isfinite(fps) or fps <= 0 or fps > 1000:
        fps = default_fps
    period_us = int(round(1e6 / fps))
    index = 0
    origin_us = None          # wall-clock us of PTS 0 (file/stream)
    lap_shift_us = 0          # file loops: media time keeps increasing
    last_pts_us = -1
    first_pts_us = None
    fails = 0
    last_ok = clock.monotonic()
    try:
        while stop is None or not stop.is_set():
            ok = cap.grab()
            t_grab = clock.monotonic()
            host_us = clock.now_us()
            if not ok:
                if kind == "file":
                    if not loop or index == 0:
                        return
                    cap.release()
                    cap = cap_factory()
                    if last_pts_us >= 0 and first_pts_us is not None:
                        lap_shift_us += last_pts_us - first_pts_us + period_us
                    last_pts_us = -1
                    continue
                fails += 1
                if clock.monotonic() - last_ok > live_timeout_s:
                    raise EonavError(f"{kind} source delivered no frame for {live_timeout_s:.1f} s "
                                     f"({fails} failed grabs)")
                clock.sleep(0.05, stop)
                continue
            fails, last_ok = 0, t_grab
            pos_ms = cap.get(cv2.CAP_PROP_POS_MSEC)
            pts_us = int(round(pos_ms * 1000)) if pos_ms is not None and np.isfinite(pos_ms) and pos_ms >= 0 else -1
            stamp, src = host_us, "host"
            if kind == "stream" and 0 <= pts_us < last_pts_us:
                origin_us = None      # a live stream's PTS went back (an encoder or stream restart): anchor again here
                last_pts_us = -1
            if kind in ("file", "stream") and pts_us >= 0 and (pts_us > last_pts_us or index == 0 or last_pts_us < 0):
                if first_pts_us is None:
                    first_pts_us = pts_us
                media_us = pts_us + lap_shift_us
                if origin_us is None:
                    origin_us = host_us - media_us
                stamp = origin_us + media_us
                if kind == "stream" and abs(stamp - host_us) > LIVE_PLAUSIBLE_US:
                    origin_us = host_us - media_us   # stream restarted / PTS jumped: re-anchor
                    stamp = host_us
                src = "pts"
            elif kind == "file" and pts_us < 0:
                # no PTS: synthesize from the frame rate so spacing is still right
                if origin_us is None:
                    origin_us = host_us
                stamp, src = origin_us + index * period_us, "fps"
            elif kind == "v4l2" and pts_us > 0:
                mono_cand = pts_us + clock.mono_to_realtime_us()
                if abs(mono_cand - host_us) <= LIVE_PLAUSIBLE_US:
                    stamp, src = mono_cand, "v4l2"
                elif abs(pts_us - host_us) <= LIVE_PLAUSIBLE_US:  # driver stamps on the realtime clock
                    stamp, src = pts_us, "v4l2"
            if pts_us >= 0:
                last_pts_us = pts_us
            elif kind == "file":
                last_pts_us = index * period_us
            if kind == "file" and pacer is not None:
                # after grab (only now is the PTS known); the stamp is PTS-based, so waiting here does not move it
                pacer.wait((last_pts_us + lap_shift_us) / 1e6)
            try:
                ok, img = cap.retrieve()
                err = "" if ok and img is not None else "retrieve() failed (corrupt frame)"
                if err:
                    img = None
            except Exception as e:
                img, err = None, f"{type(e).__name__}: {e}"
            yield RawFrame(index=index, image=img, stamp_us=stamp, stamp_source=src, source_pts_us=pts_us,
                           grab_mono=t_grab, error=err)
            index += 1
    finally:
        try:
            cap.release()
        except Exception:
            pass


def video_timestamps_file(video) -> Path:
    """Where a video file's recorded stamps are looked for: ``flight.mp4`` -> ``flight.timestamps.txt`` beside it."""
    p = Path(video)
    return p.with_name(p.stem + ".timestamps.txt")


def recorded_video_frames(frames: Iterable[RawFrame], stamps_us: list[int], *, keep_stamps: bool = False,
                          replay_shift_us: int | None = None, clock: Clock | None = None,
                          stop: threading.Event | None = None) -> Iterator[RawFrame]:
    """A video file's frames stamped from its recorded stamps (one per decoded frame, in order), as an image
    folder's are: moved onto the current clock with their spacing kept, kept as recorded (``keep_stamps``), or
    recorded + ``replay_shift_us`` and released when the host clock reaches that stamp (``frames`` then unpaced;
    frames due more than ``RESUME_LATE_US`` before the replay started are passed over, as a folder's)."""
    clock = clock or Clock()
    offset_us = None
    resume_us = None if replay_shift_us is None or keep_stamps else clock.now_us() - RESUME_LATE_US
    skipped = 0
    for f in frames:
        if f.index >= len(stamps_us):
            raise InputError(f"video frame {f.index + 1}: more frames than the {len(stamps_us)} recorded stamps")
        rec = stamps_us[f.index]
        grab_mono = f.grab_mono
        if keep_stamps:
            stamp, src = rec, "recorded_raw"
        elif replay_shift_us is not None:
            if rec + replay_shift_us < resume_us:
                skipped += 1
                continue
            clock.sleep((rec + replay_shift_us - clock.now_us()) / 1e6, stop)
            if stop is not None and stop.is_set():
                return
            stamp, src, grab_mono = rec + replay_shift_us, "recorded", clock.monotonic()
        else:
            if offset_us is None:
                offset_us = clock.now_us() - rec
            stamp, src = rec + offset_us, "recorded"
        yield RawFrame(index=f.index, image=f.image, stamp_us=stamp, stamp_source=src, source_pts_us=rec,
                       grab_mono=grab_mono, error=f.error, name=f.name, skipped=skipped)
        skipped = 0


def video_stamps(args) -> list[int] | None:
    """The recorded stamps of the video file ``args.source`` (``--timestamps`` or ``<name>.timestamps.txt``;
    None when it has none), checked against the video's frame count when the container states one."""
    import cv2
    tpath = Path(args.timestamps) if args.timestamps else video_timestamps_file(args.source)
    if args.timestamps and not tpath.is_file():
        raise InputError(f"--timestamps {tpath}: no such file")
    if not tpath.is_file():
        return None
    stamps = parse_timestamps(tpath, args.timestamps_unit)
    if args.loop:
        raise InputError(f"--loop: a video with recorded stamps ({tpath}) replays once; loop an image folder instead")
    cap = open_capture(args.source, "file", args)
    n = int(cap.get(cv2.CAP_PROP_FRAME_COUNT) or 0)
    cap.release()
    if n > 0 and n != len(stamps):
        raise InputError(f"{tpath}: {len(stamps)} stamps for {n} frames in {args.source}; "
                         "expected one stamp per line per frame")
    return stamps


def classify_source(source: str) -> str:
    """``folder``, ``file``, ``v4l2`` or ``stream`` for a ``--source`` string."""
    s = str(source)
    if re.match(r"^(rtsp|rtsps|rtmp|http|https|udp|tcp|srt)://", s, re.I):
        return "stream"
    if re.fullmatch(r"\d+", s) or s.startswith("/dev/video"):
        return "v4l2"
    p = Path(s)
    if p.is_dir():
        return "folder"
    if p.is_file():
        return "file"
    raise InputError(f"--source {s!r}: not a directory, file, V4L2 device (/dev/videoN or N) "
                     "or stream URL (rtsp://, http://)")


# --------------------------------------------------------------------------------------------------
# the capture loop (pure-ish: injected frames, sink, metrics)

class NullMetrics:
    def count(self, name, n=1): ...
    def tick(self, name, n=1): ...
    def latency(self, name, seconds): ...
    def log_limited(self, tag, level, fmt, *args, **kw):
        log.log(level, fmt, *args)


def convert(img: np.ndarray, encoding: str) -> np.ndarray:
    """A decoded image (grey / BGR / BGRA, 8 or 16 bit) as mono8 (H x W) or bgr8 (H x W x 3) uint8."""
    import cv2
    a = np.asarray(img)
    if a.ndim == 3 and a.shape[2] == 1:
        a = a[:, :, 0]
    if a.dtype == np.uint16:
        a = (a.astype(np.uint32) * 255 // 65535).astype(np.uint8)
    elif a.dtype != np.uint8:
        raise InputError(f"image dtype {a.dtype} not supported; expected uint8 or uint16")
    if a.ndim == 2:
        return a if encoding == "mono8" else cv2.cvtColor(a, cv2.COLOR_GRAY2BGR)
    if a.ndim != 3 or a.shape[2] not in (3, 4):
        raise InputError(f"image shape {a.shape}: expected H x W, H x W x 3 or H x W x 4")
    if encoding == "mono8":
        return cv2.cvtColor(a, cv2.COLOR_BGR2GRAY if a.shape[2] == 3 else cv2.COLOR_BGRA2GRAY)
    return a if a.shape[2] == 3 else cv2.cvtColor(a, cv2.COLOR_BGRA2BGR)


@dataclass
class CaptureStats:
    published: int = 0
    corrupt: int = 0
    wrong_size: int = 0
    skipped: int = 0
    last_stamp_us: int = -1


def capture_loop(frames: Iterable[RawFrame], sink: Callable[[dict], None], *, camera_id: str,
                 encoding: str = "mono8", width: int | None = None, height: int | None = None,
                 metrics=None, stop: threading.Event | None = None,
                 monotonic: Callable[[], float] = time.monotonic, correct: Callable | None = None) -> CaptureStats:
    """Turn source frames into schema "frame" fields and hand them to ``sink``.

    Skips (and counts) unreadable frames (``corrupt_frames``) and, when ``width``/``height`` are given,
    frames of another size (``wrong_size``). ``correct(image, stamp_us) -> (image, stamp_us)`` (a
    ``eonav.io.calibration.FrameCorrection``) undistorts and re-stamps each kept frame. ``seq`` numbers published
    frames from 0, plus the frames a resumed replay passed over (``replay_skipped``: downstream sees them as a gap,
    not a restart). Returns when ``frames`` is exhausted or ``stop`` is set."""
    if encoding not in ENCODINGS:
        raise InputError(f"--encoding {encoding!r}: expected one of {ENCODINGS}")
    m = metrics or NullMetrics()
    st = CaptureStats()
    for f in frames:
        if stop is not None and stop.is_set():
            break
        m.count("frames_in")
        if f.skipped:
            st.skipped += f.skipped
            m.count("replay_skipped", f.skipped)
        if f.image is None:
            st.corrupt += 1
            m.count("corrupt_frames")
            m.log_limited("corrupt", logging.WARNING, "skipped unreadable frame %d %s: %s",
                          f.index, f.name, f.error or "no image")
            continue
        try:
            img = convert(f.image, encoding)
        except InputError as e:
            st.corrupt += 1
            m.count("corrupt_frames")
            m.log_limited("corrupt", logging.WARNING, "skipped frame %d %s: %s", f.index, f.name, e)
            continue
        h, w = img.shape[:2]
        if (width and w != width) or (height and h != height):
            st.wrong_size += 1
            m.count("wrong_size")
            m.log_limited("size", logging.WARNING, "skipped frame %d %s: %dx%d, expected %sx%s",
                          f.index, f.name, w, h, width or "*", height or "*")
            continue
        stamp_us = int(f.stamp_us)
        if correct is not None:
            img, stamp_us = correct(img, stamp_us)
        sink({"camera_id": camera_id, "seq": st.published + st.skipped, "stamp_us": stamp_us,
              "stamp_source": f.stamp_source, "encoding": encoding, "image": img,
              "source_pts_us": int(f.source_pts_us)})
        m.latency("grab_to_put", monotonic() - f.grab_mono)
        m.tick("frames")
        if st.last_stamp_us >= 0 and stamp_us <= st.last_stamp_us:
            m.count("nonincreasing_stamps")
        st.published += 1
        st.last_stamp_us = stamp_us
    return st


# --------------------------------------------------------------------------------------------------
# the service

def _rate(s: str):
    if str(s).lower() == "auto":
        return "auto"
    try:
        v = float(s)
    except ValueError:
        raise ValueError(f"--rate-hz {s!r}: expected auto, 0 or frames per second") from None
    if v < 0:
        raise ValueError("--rate-hz must be >= 0")
    return v


def _opt_int(s):
    return None if s in (None, "", "0", 0) else int(s)


def add_arguments(p) -> None:
    g = p.add_argument_group("camera ingest")
    add_flag(g, "--source", env="EONAV_CAMERA_SOURCE", default=None,
             help="video file, image folder, V4L2 device (/dev/videoN or N), or rtsp:// / http:// URL")
    add_flag(g, "--camera-id", env="EONAV_CAMERA_ID", default="nose", help="camera id in the frame key and messages")
    add_flag(g, "--rate-hz", env="EONAV_CAMERA_RATE_HZ", default="auto", type=_rate, metavar="auto|HZ",
             help="file pacing: auto = real time from stamps/PTS/fps, N = N frames per second, 0 = as fast as possible",
             aliases="--rate", old_env="EONAV_CAMERA_RATE")
    add_flag(g, "--loop", env="EONAV_CAMERA_LOOP", action="store_true", help="replay a file source forever")
    add_flag(g, "--encoding", env="EONAV_CAMERA_ENCODING", default="mono8", choices=ENCODINGS,
             help="published pixel format")
    g.add_argument("--grey", dest="encoding", action="store_const", const="mono8", help="same as --encoding mono8")
    g.add_argument("--colour", dest="encoding", action="store_const", const="bgr8", help="same as --encoding bgr8")
    add_flag(g, "--width", env="EONAV_CAMERA_WIDTH", default=None, type=_opt_int,
             help="expected width in pixels (frames of another size are skipped; V4L2: requested)")
    add_flag(g, "--height", env="EONAV_CAMERA_HEIGHT", default=None, type=_opt_int,
             help="expected height in pixels (as --width)")
    add_flag(g, "--timestamps", env="EONAV_CAMERA_TIMESTAMPS", default=None,
             help=f"timestamps file for an image folder (default <folder>/{TIMESTAMPS_FILE} if present) or a video "
                  "file (default <name>.timestamps.txt beside it if present)")
    add_flag(g, "--timestamps-unit", env="EONAV_CAMERA_TIMESTAMPS_UNIT", default="auto", choices=("auto", "s", "us"),
             help="s = seconds, us = integer microseconds, auto = us if all integers >= 1e11 else s")
    add_flag(g, "--keep-stamps", env="EONAV_CAMERA_KEEP_STAMPS", action="store_true",
             help="publish recorded stamps as they are instead of mapping them onto the current clock")
    add_flag(g, "--replay-shift-us", env="EONAV_REPLAY_SHIFT_US", default=None, type=int, metavar="D",
             help="joint replay: stamp recorded + D and release at that host time (same D for every replay)")
    add_flag(g, "--default-fps", env="EONAV_CAMERA_DEFAULT_FPS", default=10.0, type=float, metavar="FPS",
             help="frame rate assumed for folders without timestamps / files without fps (pacing in auto mode)")
    add_flag(g, "--wait-subscribers-s", env="EONAV_CAMERA_WAIT_SUBSCRIBERS_S", default=2.0, type=float, metavar="S",
             help="file sources: wait up to S s for a subscriber before the first frame (declaration race)",
             aliases="--wait-subscribers", old_env="EONAV_CAMERA_WAIT_SUBSCRIBERS")
    add_flag(g, "--cameras", env="EONAV_CAMERA_CAMERAS", default=None, metavar="FILE",
             help="cameras file (as the sync's): this camera's lens model (frames undistorted) and time_offset_s")
    add_flag(g, "--exposure-us", env="EONAV_CAMERA_EXPOSURE_US", default=None, type=float, metavar="US",
             help="known exposure time: stamps move by half of it to the middle of the exposure")
    add_flag(g, "--fourcc", env="EONAV_CAMERA_FOURCC", default=None, help="V4L2 pixel format, e.g. MJPG")
    add_flag(g, "--device-fps", env="EONAV_CAMERA_DEVICE_FPS", default=None, type=float, metavar="FPS",
             help="V4L2 frame rate to request")
    add_flag(g, "--buffer-size", env="EONAV_CAMERA_BUFFER_SIZE", default=2, type=int, help="V4L2 buffers (small = low latency)")
    add_flag(g, "--live-timeout-s", env="EONAV_CAMERA_LIVE_TIMEOUT_S", default=5.0, type=float, metavar="S",
             help="live sources: exit 1 (for a restart) after S s without a frame",
             aliases="--live-timeout", old_env="EONAV_CAMERA_LIVE_TIMEOUT")
    add_flag(g, "--open-timeout-s", env="EONAV_CAMERA_OPEN_TIMEOUT_S", default=10.0, type=float, metavar="S",
             help="network streams: open/read timeout", aliases="--open-timeout", old_env="EONAV_CAMERA_OPEN_TIMEOUT")


def camera_correction(args):
    """The ``FrameCorrection`` of ``--cameras`` / ``--exposure-us`` (None when neither is given). The camera's
    calibrated size becomes ``--width``/``--height`` (requested from V4L2; other sizes are skipped)."""
    from eonav.io.calibration import frame_correction
    exposure_s = None if args.exposure_us is None else args.exposure_us / 1e6
    if not args.cameras:
        return None if exposure_s is None else frame_correction(None, 0.0, exposure_s)
    from eonav.io.pairfile import load_camera_models
    models = load_camera_models(args.cameras, "--cameras")
    if args.camera_id not in models:
        raise InputError(f"--cameras {args.cameras}: no camera {args.camera_id!r} (has {sorted(models)})")
    m = models[args.camera_id]
    for flag, want in (("width", m.camera.width), ("height", m.camera.height)):
        if getattr(args, flag) is None:
            setattr(args, flag, want)
        elif getattr(args, flag) != want:
            raise InputError(f"--{flag} {getattr(args, flag)}: camera {args.camera_id!r} in --cameras is "
                             f"{m.camera.width}x{m.camera.height}")
    return frame_correction(m.undistort, m.time_offset_s, exposure_s)


def make_frames(args, *, stop: threading.Event | None = None, clock: Clock | None = None) -> Iterator[RawFrame]:
    """The frame iterator for ``args.source`` (also usable without a bus)."""
    if not args.source:
        raise InputError("--source is required (or EONAV_CAMERA_SOURCE)")
    kind = classify_source(args.source)
    clock = clock or Clock()
    pacer = Pacer(args.rate_hz, clock, stop) if kind in ("folder", "file") else None
    if kind == "folder":
        return folder_frames(args.source, timestamps=args.timestamps, unit=args.timestamps_unit,
                             keep_stamps=args.keep_stamps, loop=args.loop, pacer=pacer, clock=clock,
                             default_fps=args.default_fps, stop=stop, replay_shift_us=args.replay_shift_us)
    stamps = video_stamps(args) if kind == "file" else None
    if args.replay_shift_us is not None and (stamps is None or args.keep_stamps):
        raise InputError("--replay-shift-us needs recorded stamps (an image folder's timestamps file, a video's "
                         "<name>.timestamps.txt or --timestamps) and excludes --keep-stamps")
    if args.timestamps and kind != "file":
        raise InputError("--timestamps applies to image folders and video files only")
    open_capture(args.source, kind, args).release()  # fail early, as a configuration error
    frames = capture_frames(lambda: open_capture(args.source, kind, args), kind, loop=args.loop,
                            pacer=None if args.replay_shift_us is not None else pacer, clock=clock, stop=stop,
                            live_timeout_s=args.live_timeout_s, default_fps=args.default_fps)
    if stamps is None:
        return frames
    return recorded_video_frames(frames, stamps, keep_stamps=args.keep_stamps, replay_shift_us=args.replay_shift_us,
                                 clock=clock, stop=stop)


def body(node: Node, args) -> None:
    K.check_chunk(args.camera_id, "--camera-id")
    kind = classify_source(args.source) if args.source else None
    if kind in ("folder", "file") and args.replay_shift_us is None and restart_count():
        # no fixed time reference: it would start over with the recording's beginning presented as now
        node.log.warning("replay of %s restarted without --replay-shift-us: it cannot resume where it was, so it "
                         "ends here instead of starting over (docs/bus.md, Staleness)", args.source)
        node.stop("restarted replay cannot resume")
        return
    correct = camera_correction(args)
    frames = make_frames(args, stop=node.stop_event)
    key = K.frame(node.vehicle, args.camera_id)
    pub = node.publisher(key, image=True)
    node.log.info("camera %s: %s source %s -> %s (%s, rate %s)", args.camera_id, kind, args.source, key,
                  args.encoding, args.rate_hz)
    if correct is not None:
        node.log.info("camera %s: %s, stamps %+d us", args.camera_id,
                      "undistorted" if correct.undistort is not None else "pinhole", correct.shift_us)

    def sink(fields):
        node.put(pub, "frame", **fields)

    def run():
        if kind in ("folder", "file") and args.wait_subscribers_s > 0:
            if not node.wait_matching(pub, args.wait_subscribers_s):
                node.log.info("no subscriber after %.1f s; publishing anyway", args.wait_subscribers_s)
        st = capture_loop(frames, sink, camera_id=args.camera_id, encoding=args.encoding, width=args.width,
                          height=args.height, metrics=node, stop=node.stop_event, correct=correct)
        if node.stop_event.is_set():
            return
        if st.published == 0 and st.corrupt + st.wrong_size > 0:
            node.set_state("degraded", f"no usable frame ({st.corrupt} corrupt, {st.wrong_size} wrong size)")
        node.log.info("end of source: %d frames published, %d corrupt, %d wrong size",
                      st.published, st.corrupt, st.wrong_size)
        node.stop_event.wait(0.3)  # let the last frames leave the TX queue
        node.stop("end of source")

    node.worker(run, name="capture")


def main(argv=None) -> int:
    from eonav.bus.node import main as node_main
    return node_main("camera", add_arguments, body, argv)


if __name__ == "__main__":
    service_main("camera", add_arguments, body, module="camera_ingest")
