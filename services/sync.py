"""Time-sync pairing: frames + navigation states -> posed frames.

In: schema ``frame`` on ``keys.frames_all(vehicle)`` (RingChannel: the newest frames win) and ``nav_state`` on
``keys.nav_state(vehicle)`` (FifoChannel: must not be lost). Out: schema ``posed_frame`` on
``keys.posed_frame(vehicle, camera_id)``: the frame, its camera (``--cameras``: the pair file's "cameras" section,
or a whole pair file) and the vehicle pose interpolated at the capture stamp by ``eonav.nav.timesync.NavBuffer``,
with ``nav_gap_us`` and ``quality_flags``.

A frame is posed as soon as navigation brackets its stamp, dropped at once when it never can be, and posed by
bounded extrapolation (flagged) when navigation is still late after a wall-time limit; every drop is counted by
reason (docs/bus.md, "Sync"). The logic is :class:`Pairer`, a pure object over injected times.
"""
from __future__ import annotations

import logging
import threading
import time
from collections import Counter


from eonav import InputError
from eonav.bus import schema
from eonav.bus import keys as K
from eonav.bus.freshness import FreshnessGate, screen
from eonav.bus.node import Node, add_flag, now_us, service_main
from eonav.io import pairfile
from eonav.nav.timesync import NavBuffer

log = logging.getLogger(__name__)


def load_cameras(path) -> dict:
    """The --cameras file (eonav.pairfile.load_cameras); camera names must be plain key chunks."""
    cams = pairfile.load_cameras(path, "--cameras")
    for name in cams:
        K.check_chunk(name, "camera id")
    return cams


class Pairer:
    """Pending frames against a NavBuffer. ``add_frame``/``add_nav`` then ``poll(now_s)`` -> list of
    posed_frame field dicts; drops and counts in ``counts``. Not thread-safe (the service locks)."""

    def __init__(self, cameras: dict, nav: NavBuffer, max_wait_s: float = 0.3, max_pending: int = 32,
                 position_lead_s: float = 0.0):
        self.position_lead_us = int(round(position_lead_s * 1e6))
        self.cameras = cameras
        self.cam_msgs = {n: schema.camera_to_msg(c) for n, c in cameras.items()}
        self.nav = nav
        self.max_wait_s, self.max_pending = max_wait_s, max_pending
        self.pending: list = []          # (stamp_us, arrival_s, frame dict)
        self.counts: Counter = Counter()

    def add_nav(self, msg: dict) -> None:
        self.nav.add_state(msg)

    def add_frame(self, msg: dict, now_s: float) -> None:
        cam = self.cameras.get(msg["camera_id"])
        if cam is None:
            self.counts["unknown_camera"] += 1
            return
        img = msg["image"]
        if img.shape[:2] != (cam.height, cam.width):
            self.counts["dropped.wrong_size"] += 1
            return
        self.pending.append((int(msg["stamp_us"]), now_s, msg))
        self.pending.sort(key=lambda x: x[0])
        while len(self.pending) > self.max_pending:
            self.pending.pop(0)
            self.counts["dropped.pending_overflow"] += 1

    def _position_lead_ok(self, stamp: int, d) -> bool:
        """Attitude brackets the stamp, only position is behind, by at most the lead, and its newest sample has a
        velocity (a moving vehicle): NavBuffer extrapolates the last position bracket linearly, off by about
        0.5 a t_ex (t_ex + dt) = 3 mm at 5 m/s^2 for t_ex 20 ms, dt 40 ms."""
        if not self.position_lead_us or d.reason != "waiting_for_position":
            return False
        pos = self.nav.pos
        if not len(pos) or pos.vel[-1] is None or stamp - pos.newest_us > self.position_lead_us:
            return False
        return self.nav.att.decide(stamp, self.nav.max_extrapolation_us, self.nav.max_gap_us).state == "ready"

    def poll(self, now_s: float) -> list:
        out, keep = [], []
        for stamp, arrived, msg in self.pending:
            d = self.nav.decide(stamp)
            if d.state == "never":
                self.counts[f"dropped.{d.reason}"] += 1
                continue
            if d.state == "wait" and self._position_lead_ok(stamp, d):
                r = self.nav.pose_at(stamp, allow_extrapolation=True)     # flagged QF_EXTRAPOLATED
            elif d.state == "wait":
                if now_s - arrived < self.max_wait_s:
                    keep.append((stamp, arrived, msg))
                    continue
                r = self.nav.pose_at(stamp, allow_extrapolation=True)
            else:
                r = self.nav.pose_at(stamp)
            if not r.ok:
                self.counts[f"dropped.{r.reason}"] += 1
                continue
            self.counts["posed"] += 1
            out.append({"camera_id": msg["camera_id"], "seq": msg["seq"], "stamp_us": stamp,
                        "stamp_source": msg["stamp_source"], "encoding": msg["encoding"], "image": msg["image"],
                        "camera": self.cam_msgs[msg["camera_id"]], "position_ned_m": r.position_ned_m,
                        "q_wxyz": r.q_wxyz, "velocity_ned_mps": r.velocity_ned_mps,
                        "nav_gap_us": int(r.nav_gap_us), "quality_flags": int(r.quality_flags)})
        self.pending = keep
        return out


def add_arguments(p) -> None:
    g = p.add_argument_group("sync")
    add_flag(g, "--cameras", env="EONAV_SYNC_CAMERAS", default=None,
             help="JSON with the cameras (pair-file 'cameras' section or a whole pair file)")
    add_flag(g, "--max-extrapolation-ms", env="EONAV_SYNC_MAX_EXTRAPOLATION_MS", default=20.0, type=float,
             help="farthest a pose may be extrapolated beyond the nav samples")
    add_flag(g, "--max-gap-ms", env="EONAV_SYNC_MAX_GAP_MS", default=250.0, type=float,
             help="largest gap between bracketing nav samples accepted")
    add_flag(g, "--max-nav-ahead-ms", env="EONAV_SYNC_MAX_NAV_AHEAD_MS", default=5000.0, type=float,
             help="refuse nav samples stamped further than this ahead of the host clock (0: accept any)")
    add_flag(g, "--gap-warn-ms", env="EONAV_SYNC_GAP_WARN_MS", default=60.0, type=float,
             help="bracket gaps above this set the QF_GAP flag")
    add_flag(g, "--max-wait-ms", env="EONAV_SYNC_MAX_WAIT_MS", default=300.0, type=float,
             help="wall time a frame may wait for bracketing nav before extrapolation or drop")
    add_flag(g, "--position-lead-ms", env="EONAV_SYNC_POSITION_LEAD_MS", default=0.0, type=float,
             help="release a frame whose attitude is bracketed when position lags its stamp by at most this "
                  "(extrapolated, flagged QF_EXTRAPOLATED; <= --max-extrapolation-ms); 0: wait")
    add_flag(g, "--nav-buffer", env="EONAV_SYNC_NAV_BUFFER", default=4096, type=int,
             help="nav samples kept per stream (attitude, position)")
    add_flag(g, "--frame-ring", env="EONAV_SYNC_FRAME_RING", default=4, type=int,
             help="frame subscriber ring size (the newest frames win)")
    add_flag(g, "--nav-fifo", env="EONAV_SYNC_NAV_FIFO", default=2000, type=int,
             help="nav_state subscriber FIFO size")
    add_flag(g, "--max-input-age-ms", env="EONAV_SYNC_MAX_INPUT_AGE_MS", default=500.0, type=float,
             help="drop (count dropped.too_old) a frame older than this on arrival or when its posed frame would be "
                  "published (--max-wait-ms plus transport: docs/bus.md, Staleness)")
    add_flag(g, "--input-timeout-ms", env="EONAV_SYNC_INPUT_TIMEOUT_MS", default=1000.0, type=float,
             help="no usable frame for this long: state degraded (5 periods of a 5 fps camera)")
    add_flag(g, "--nav-timeout-ms", env="EONAV_SYNC_NAV_TIMEOUT_MS", default=500.0, type=float,
             help="no nav_state for this long: state degraded (2 x the default --max-gap-ms)")
    add_flag(g, "--attitude-only", env="EONAV_SYNC_ATTITUDE_ONLY", default=False, action="store_true",
             help="pose frames without a position stream (position NaN)")


def body(node: Node, args) -> None:
    if not args.cameras:
        raise InputError("--cameras is required (JSON with the camera intrinsics and mounts)")
    cams = load_cameras(args.cameras)
    nav = NavBuffer(max_samples=args.nav_buffer, max_extrapolation_us=int(args.max_extrapolation_ms * 1000),
                    max_gap_us=int(args.max_gap_ms * 1000), gap_warn_us=int(args.gap_warn_ms * 1000),
                    require_position=not args.attitude_only, clock_us=now_us if args.max_nav_ahead_ms > 0 else None,
                    max_future_us=int(args.max_nav_ahead_ms * 1000))
    if not 0 <= args.position_lead_ms <= args.max_extrapolation_ms:
        raise InputError(f"--position-lead-ms must be in [0, --max-extrapolation-ms], got {args.position_lead_ms}")
    pairer = Pairer(cams, nav, max_wait_s=args.max_wait_ms / 1000.0, position_lead_s=args.position_lead_ms / 1000.0)
    gate = FreshnessGate(args.max_input_age_ms / 1000.0)
    lock = threading.Lock()
    pubs = {name: node.publisher(K.posed_frame(node.vehicle, name), image=True) for name in cams}
    frame_sub = node.subscribe(K.frames_all(node.vehicle), ring=args.frame_ring)
    nav_sub = node.subscribe(K.nav_state(node.vehicle), fifo=args.nav_fifo)
    reported: Counter = Counter()
    node.log.info("sync: cameras %s; frames %s + nav %s -> %s", sorted(cams), K.frames_all(node.vehicle),
                  K.nav_state(node.vehicle), K.posed_frame(node.vehicle, "CAMERA"))

    put_lock = threading.Lock()     # the nav, frame and tick threads all release frames: one at a time, in order

    def process():
        with put_lock:
            put_released()

    def put_released():
        with lock:
            out = pairer.poll(time.monotonic())
            counts = Counter(pairer.counts)
        for d in out:
            if not screen(node, gate, d["camera_id"], d["stamp_us"], "publish"):
                continue
            node.put(pubs[d["camera_id"]], "posed_frame", **d)
            gate.commit(d["camera_id"], d["stamp_us"])
            node.latency("frame_to_posed", time.time() - d["stamp_us"] / 1e6)
        for k, v in counts.items():
            if v != reported[k]:
                if k.startswith("dropped.") and v > reported[k]:
                    node.log_limited(k, logging.WARNING, "frame %s", k.replace(".", ": ", 1))
                node.count(k, v - reported[k])
                reported[k] = v

    def on_nav(s):
        msg = node.decode(s, "nav_state")
        if msg is None:
            return
        node.input_seen("nav")
        with lock:
            pairer.add_nav(msg)
        process()

    def on_frame(s):
        msg = node.decode(s, "frame")
        if msg is None or not screen(node, gate, msg["camera_id"], msg["stamp_us"], "arrival"):
            return
        node.input_seen("frames")
        with lock:
            pairer.add_frame(msg, time.monotonic())
        process()

    def nav_loop():
        for s in nav_sub:
            node.guarded("nav_state", on_nav, s)

    def frame_loop():
        for s in frame_sub:
            node.guarded("frame", on_frame, s)

    def tick():
        while not node.stop_event.wait(0.02):
            process()
            with lock:
                nav_counts = Counter(nav.counts)
            for k in ("duplicate_stamp", "out_of_order", "too_old", "bad_attitude", "bad_position", "future_stamp"):
                d = nav_counts[k] - reported[f"nav.{k}"]
                if d:
                    node.count(f"nav.{k}", d)
                    reported[f"nav.{k}"] = nav_counts[k]

    node.expect_input("frames", args.input_timeout_ms / 1000.0)
    node.expect_input("nav", args.nav_timeout_ms / 1000.0)
    node.worker(nav_loop, name="nav")
    node.worker(frame_loop, name="frames")
    node.worker(tick, name="tick")


if __name__ == "__main__":
    service_main("sync", add_arguments, body)
