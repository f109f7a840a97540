"""Obstacle publisher: range maps (+ navigation) -> obstacle list for guidance, and MAVLink OBSTACLE_DISTANCE.

In: schema ``range_map`` on ``keys.range_maps_all(vehicle)`` (RingChannel: the newest map of each camera wins) and
``nav_state`` (only the latest pose matters). Out: schema ``obstacle_list`` on ``keys.obstacles(vehicle)``
(``eonav.obstacles.detect.analyse``: 72 sectors and the obstacle list, referred to the map's capture stamp and
pose; a small, reliable, express message), and with ``--mavlink-out`` OBSTACLE_DISTANCE (and / or, with
``--mavlink-messages``, OBSTACLE_DISTANCE_3D of the confirmed tracks) plus a companion HEARTBEAT
(``eonav.nav.mavlink_out``, docs/mavlink.md, docs/autopilot.md).

Decisions: the sectors sent to the autopilot are re-referenced to the latest navigation pose newer than the map
(the autopilot applies them where it is on arrival); a stall sends one all-unknown message and then silence, so the
autopilot sees a dead sensor, not an empty sky. Each map is read on its own grid with its own ``camera``; a map
whose arrays or frame size do not fit that camera is rejected and counted. ``analyse`` is warmed up once on a
synthetic map before the first real one. An output link that is not up (refused, device absent) or whose
autopilot is not heard is retried with back-off and makes the health ``degraded`` (``eonav.nav.links``).
"""
from __future__ import annotations

import logging
import time

import numpy as np

from eonav import InputError
from eonav.bus import keys as K
from eonav.bus.freshness import FreshnessGate, age_ms, screen
from eonav.bus.node import Node, add_flag, now_us, service_main

log = logging.getLogger("eonav.service.obstacles")

NAV_MAX_AHEAD_S = 1.0        # a nav state newer than the map by more than this is from another timeline


def add_arguments(p):
    from eonav.obstacles.detect import ObstacleConfig
    d = ObstacleConfig()                         # the extraction defaults are the library's
    add_flag(p, "--mavlink-out", env="EONAV_OBSTACLES_MAVLINK_OUT", default=None, metavar="CONNECTION",
             help="send OBSTACLE_DISTANCE on this pymavlink connection, e.g. udpout:127.0.0.1:14560")
    add_flag(p, "--mavlink-messages", env="EONAV_OBSTACLES_MAVLINK_MESSAGES", default="obstacle_distance",
             choices=("obstacle_distance", "obstacle_distance_3d", "both"),
             help="what --mavlink-out sends: OBSTACLE_DISTANCE sectors, OBSTACLE_DISTANCE_3D of the confirmed tracks "
                  "(ArduPilot only), or both (docs/autopilot.md)")
    add_flag(p, "--mavlink-source-system", env="EONAV_OBSTACLES_MAVLINK_SOURCE_SYSTEM", default=1, type=int,
             help="our MAVLink system id (the vehicle's, as mavlink_ingest --source-system); component is 191 "
                  "(onboard computer)", aliases="--mavlink-sysid", old_env="EONAV_OBSTACLES_MAVLINK_SYSID")
    add_flag(p, "--mavlink-rate-hz", env="EONAV_OBSTACLES_MAVLINK_RATE_HZ", default=10.0, type=float, metavar="HZ",
             help="OBSTACLE_DISTANCE rate (ArduPilot/PX4 time out after 0.5 s)",
             aliases="--mavlink-rate", old_env="EONAV_OBSTACLES_MAVLINK_RATE")
    add_flag(p, "--stale-s", env="EONAV_OBSTACLES_STALE_S", default=0.3, type=float, metavar="S",
             help="after this long without a new range map, send one all-unknown OBSTACLE_DISTANCE and then none "
                  "until maps flow again (the autopilot then reports No Data)",
             aliases="--stale", old_env="EONAV_OBSTACLES_STALE")
    add_flag(p, "--tracks-rate-hz", env="EONAV_OBSTACLES_TRACKS_RATE_HZ", default=10.0, type=float, metavar="HZ",
             help="obstacle-track topic (guidance's input): a message on every map and on this fixed timer")
    add_flag(p, "--no-nav", env="EONAV_OBSTACLES_NO_NAV", default=False, action="store_true",
             help="do not re-reference MAVLink sectors to the latest navigation pose")
    add_flag(p, "--max-input-age-ms", env="EONAV_OBSTACLES_MAX_INPUT_AGE_MS", default=1000.0, type=float,
             help="drop (count dropped.too_old) a range map whose frame is older than this on arrival or when its "
                  "obstacle list would be published (docs/bus.md, Staleness)")
    add_flag(p, "--input-timeout-ms", env="EONAV_OBSTACLES_INPUT_TIMEOUT_MS", default=1000.0, type=float,
             help="no usable range map for this long: state degraded (5 periods of a 5 fps camera)")
    add_flag(p, "--nav-timeout-ms", env="EONAV_OBSTACLES_NAV_TIMEOUT_MS", default=500.0, type=float,
             help="no nav_state for this long: state degraded (not watched with --no-nav)")
    g = p.add_argument_group("obstacle extraction (eonav.obstacles.ObstacleConfig)")
    add_flag(g, "--min-distance-m", env="EONAV_OBST_MIN_DISTANCE_M", default=d.min_distance_m, type=float,
             metavar="M", help="OBSTACLE_DISTANCE min_distance (>= 0.01): nearer obstacles are reported at this "
                               "distance",
             aliases="--min-distance", old_env="EONAV_OBST_MIN_DISTANCE")
    add_flag(g, "--max-distance-m", env="EONAV_OBST_MAX_DISTANCE_M", default=d.max_distance_m, type=float,
             metavar="M", help="OBSTACLE_DISTANCE max_distance; farther is 'clear'",
             aliases="--max-distance", old_env="EONAV_OBST_MAX_DISTANCE")
    add_flag(g, "--max-obstacle-distance-m", env="EONAV_OBST_MAX_OBSTACLE_DISTANCE_M",
             default=d.max_obstacle_distance_m, type=float, metavar="M",
             help="obstacle list: only objects nearer than this",
             aliases="--max-obstacle-distance", old_env="EONAV_OBST_MAX_LIST_DISTANCE")
    add_flag(g, "--ground-down-m", env="EONAV_OBST_GROUND_DOWN_M", default="auto", metavar="M|auto",
             help="NED down coordinate of the ground (0 = home level), or auto (estimated from the points)",
             aliases="--ground-down", old_env="EONAV_OBST_GROUND_DOWN")
    add_flag(g, "--ground-clearance-m", env="EONAV_OBST_GROUND_CLEARANCE_M", default=d.ground_clearance_m, type=float,
             metavar="M", help=f"points less than this above the ground (plus {d.ground_sigma_k:g} sigma of their "
                               f"height) or below it are ground, not obstacles",
             aliases="--ground-clearance", old_env="EONAV_OBST_GROUND_CLEARANCE")
    add_flag(g, "--min-confidence", env="EONAV_OBST_MIN_CONFIDENCE", default=d.min_confidence, type=float,
             help="ignore pixels whose confidence (inverse range / its 1-sigma: the inverse of the relative range "
                  "error) is below this (0: off)")
    add_flag(g, "--max-rel-std", env="EONAV_OBST_MAX_REL_STD", default=d.max_rel_std, type=float,
             help="ignore pixels whose relative range 1-sigma exceeds this (the dense method's VALID threshold)")
    add_flag(g, "--min-obstacle-pixels", env="EONAV_OBST_MIN_OBSTACLE_PIXELS", default=d.min_obstacle_pixels, type=int,
             help="smallest connected component kept as an obstacle (list and sectors), in analysed pixels",
             old_env="EONAV_OBST_MIN_PIXELS")
    add_flag(g, "--max-width-px", env="EONAV_OBST_MAX_WIDTH_PX", default=d.max_width_px, type=int, metavar="PX",
             help="analyse the range map pooled to at most this many columns (robust minimum per block; "
                  "0: full resolution)", aliases="--max-width", old_env="EONAV_OBST_MAX_WIDTH")


def obstacle_config(args):
    from eonav.obstacles.detect import ObstacleConfig
    if str(args.ground_down_m).lower() == "auto":
        ground = None
    else:
        try:
            ground = float(args.ground_down_m)
        except ValueError:
            raise InputError(f"--ground-down-m {args.ground_down_m!r}: expected metres or 'auto'") from None
    return ObstacleConfig(min_confidence=args.min_confidence, max_rel_std=args.max_rel_std,
                          min_distance_m=args.min_distance_m, max_distance_m=args.max_distance_m,
                          ground_down_m=ground, ground_clearance_m=args.ground_clearance_m,
                          max_obstacle_distance_m=args.max_obstacle_distance_m,
                          min_obstacle_pixels=args.min_obstacle_pixels, max_width_px=args.max_width_px)


class LatestNav:
    """The vehicle's newest pose, filled by the nav worker, read by the obstacle loop and guidance.

    The MAVLink ingest publishes attitude and position as separate nav_state messages (one autopilot message each),
    so the newest attitude and the newest position are kept apart and joined when their stamps are within
    ``MAX_PART_SKEW_US``: the pose then carries the newer stamp."""

    MAX_PART_SKEW_US = 200_000

    def __init__(self):
        import threading
        self._lock = threading.Lock()
        self.state = None
        self.stamp_us = None
        self.velocity_ned_mps = np.full(3, np.nan)
        self._q = self._p = None             # (stamp_us, value) of the newest attitude / position (+ velocity)

    def add(self, stamp_us: int, q_wxyz=None, position_ned_m=None, velocity_ned_mps=None) -> bool:
        """One nav_state's known parts (None or NaN: absent). True when a whole pose could be formed."""
        from eonav.geometry.camera import VehicleState
        t = int(stamp_us)
        with self._lock:
            if q_wxyz is not None and np.all(np.isfinite(q_wxyz)) and abs(np.linalg.norm(q_wxyz) - 1) < 1e-3:
                if self._q is None or t >= self._q[0]:
                    self._q = (t, np.asarray(q_wxyz, float))
            if position_ned_m is not None and np.all(np.isfinite(position_ned_m)):
                if self._p is None or t >= self._p[0]:
                    v = np.asarray(velocity_ned_mps if velocity_ned_mps is not None else [np.nan] * 3, float)
                    self._p = (t, np.asarray(position_ned_m, float), v if np.all(np.isfinite(v)) else None)
            if self._q is None or self._p is None or abs(self._q[0] - self._p[0]) > self.MAX_PART_SKEW_US:
                return False
            stamp = max(self._q[0], self._p[0])
            if self.stamp_us is None or stamp >= self.stamp_us:
                self.state = VehicleState.from_quat(self._p[1], self._q[1])
                self.stamp_us = stamp
                if self._p[2] is not None:
                    self.velocity_ned_mps = self._p[2]
            return True

    def get(self):
        with self._lock:
            return self.state, self.stamp_us

    def ownship(self, fallback_state, fallback_stamp_us: int):
        """The vehicle now for guidance: the latest nav state with its velocity, else ``fallback_state`` (a map's
        capture pose) with an unknown velocity."""
        from eonav.obstacles.tracking import Ownship
        with self._lock:
            if self.state is not None:
                return Ownship(self.state.position_ned_m, self.state.T_body_ned, self.velocity_ned_mps, self.stamp_us)
        return None if fallback_state is None else Ownship.from_state(fallback_state, stamp_us=fallback_stamp_us)


class Guidance:
    """The obstacle tracker and the track topic's publisher, shared by the map worker and the timer worker."""

    def __init__(self, node: Node, nav: LatestNav, rate_hz: float, stale_after_s: float):
        import threading

        from eonav.obstacles.guidance import GuidancePublisher
        from eonav.obstacles.tracking import Tracker, TrackerConfig
        self.node, self.nav = node, nav
        self.lock = threading.Lock()
        self.tracker = Tracker(TrackerConfig())
        self.publisher = GuidancePublisher(self.tracker, rate_hz=rate_hz, stale_after_s=stale_after_s)
        self.pub = node.publisher(K.obstacle_tracks(node.vehicle))
        self.last_state, self.last_stamp_us = None, -1      # the newest map's capture pose (no nav: the ownship)
        self.latest = None                                   # the newest map-triggered message (OBSTACLE_DISTANCE_3D)

    def put(self, msg) -> None:
        from eonav.bus import guidance_msg
        if msg is None:
            return
        self.pub.put(guidance_msg.encode(msg))
        self.node.count("out.obstacle_tracks")
        self.node.tick("out.obstacle_tracks")

    def on_map(self, res, msg, cam, state, cfg) -> tuple:
        """Track the map's obstacles: (the track id each listed obstacle supports (0: none), the track message to
        ``put`` once the obstacle list is out, or None)."""
        from dataclasses import replace

        from eonav.obstacles.tracking import FieldOfView, measurements_from_obstacles, merge_fragments
        frame_size = (msg.get("frame_width", 0), msg.get("frame_height", 0))
        # one measurement per listed obstacle (the labels), merged into one per object (the tracker's input)
        single = measurements_from_obstacles(res.obstacles, cam, state, replace(self.tracker.cfg, merge_gap_m=0.0),
                                             frame_size=frame_size, camera_id=msg["camera_id"])
        meas = merge_fragments(single, self.tracker.cfg.merge_gap_m)
        view = FieldOfView(cam, state, cfg.max_obstacle_distance_m, cfg.min_distance_m, msg["range_m"],
                           res.data_mask)
        with self.lock:
            try:
                self.tracker.update(meas, msg["stamp_us"], view)
            except InputError:                          # older than the last map (another camera's, late)
                self.node.count("tracker.map_out_of_order")
                return [0] * len(res.obstacles), None
            self.last_state, self.last_stamp_us = state, int(msg["stamp_us"])
            ids = self.tracker.label(single) if len(single) == len(res.obstacles) else [0] * len(res.obstacles)
            own = self.nav.ownship(state, msg["stamp_us"])
            out = self.publisher.on_map(now_us(), own)
            self.latest = out
        return ids, out

    def timer_loop(self) -> None:
        """The fixed-rate messages (guidance sees a stall in ``status`` / ``map_age_s`` even with no map coming)."""
        while not self.node.stop_event.wait(self.publisher.wait_s(now_us())):
            with self.lock:
                own = self.nav.ownship(self.last_state, self.last_stamp_us)
                out = None if own is None else self.publisher.on_tick(now_us(), own)
            self.node.guarded("obstacle_tracks", self.put, out)
            if own is None:
                self.node.stop_event.wait(0.1)


def body(node: Node, args) -> None:
    cfg = obstacle_config(args)
    sender = None
    if args.mavlink_out:
        from eonav.nav.mavlink_out import ObstacleDistanceSender
        if args.mavlink_rate_hz < 10.0:
            node.log.warning("--mavlink-rate-hz %.1f is below the 10 Hz the autopilots are tuned for",
                             args.mavlink_rate_hz)
        sender = ObstacleDistanceSender(args.mavlink_out, system_id=args.mavlink_source_system,
                                        rate_hz=args.mavlink_rate_hz, stale_s=args.stale_s,
                                        messages=args.mavlink_messages)
    pub = node.publisher(K.obstacles(node.vehicle))          # reliable, small, express
    maps = node.subscribe(K.range_maps_all(node.vehicle), ring=2)
    nav = LatestNav()
    args._freshness = FreshnessGate(args.max_input_age_ms / 1000.0)
    node.expect_input("range maps", args.input_timeout_ms / 1000.0)
    if not args.no_nav:
        navsub = node.subscribe(K.nav_state(node.vehicle), ring=1)
        node.expect_input("nav", args.nav_timeout_ms / 1000.0)
        node.worker(nav_loop, node, navsub, nav, name="nav")
    guidance = Guidance(node, nav, args.tracks_rate_hz, args.stale_s)
    node.worker(obstacle_loop, node, maps, pub, cfg, guidance, nav, sender, args, name="obstacles")
    node.worker(guidance.timer_loop, name="tracks")
    if sender is not None:
        def send_loop():
            try:
                last, link_state = 0.0, None
                while not node.stop_event.wait(sender.tick()):
                    if time.monotonic() - last >= 0.5:
                        last = time.monotonic()
                        mirror_counters(node, sender)
                        state, detail = sender.link_status()     # autopilot link down / not heard: degraded
                        if state != link_state:
                            node.set_state("ok" if state == "up" else "degraded", detail)
                            link_state = state
            finally:
                mirror_counters(node, sender)
                sender.close()
        node.worker(send_loop, name="mavlink")
        node.log.info("OBSTACLE_DISTANCE to %s at %.0f Hz (stale after %.2f s)", args.mavlink_out,
                      args.mavlink_rate_hz, args.stale_s)


def mirror_counters(node: Node, sender) -> None:
    """The sender's counters into the node's health counters (as mavlink.<name>)."""
    have = node.counters()
    for k, v in dict(sender.counters).items():
        d = v - have.get(f"mavlink.{k}", 0)
        if d:
            node.count(f"mavlink.{k}", d)


def nav_loop(node: Node, sub, nav: LatestNav) -> None:
    def one(sample):
        msg = node.decode(sample, expect="nav_state")
        if msg is None:
            return
        node.input_seen("nav")
        if not nav.add(msg["stamp_us"], msg["q_wxyz"], msg["position_ned_m"], msg["velocity_ned_mps"]):
            node.count("nav_incomplete")             # no whole pose yet (or its parts too far apart in time)

    for sample in sub:
        node.guarded("nav_state", one, sample)


def obstacle_loop(node: Node, sub, pub, cfg, guidance: Guidance, nav: LatestNav, sender, args) -> None:
    import scipy.ndimage  # noqa: F401  (now, with the subscriber declared: the first map must not pay ~0.5 s)

    from eonav.obstacles import detect as ob
    from eonav.geometry.camera import VehicleState
    from eonav.services.locator import CameraCache, drain_latest
    cameras = CameraCache()
    warm_up(node, cfg, ob)
    for first in sub:
        for sample, newest in drain_latest(first, sub):
            if not newest:                  # a newer map of the same camera is waiting: latest wins
                node.count("maps_superseded")
                continue
            node.guarded("range_map", process_map, node, sample, pub, cfg, guidance, nav, sender, args, cameras, ob,
                         VehicleState)


def analyse_msg(ob, msg: dict, cam, state, cfg, now_state=None):
    """``eonav.obstacles.analyse`` of a decoded range_map on its own grid: ``cam`` is the message's camera, the frame
    size (0 x 0 from older locators: the map is on the frame's grid) makes the pixel counts frame pixels."""
    return ob.analyse(msg["range_m"], cam, state, confidence=msg["confidence"], flags=msg["flags"],
                      inv_range_std_per_m=msg["inv_range_std_per_m"], cfg=cfg, now_state=now_state,
                      frame_size=(msg.get("frame_width", 0), msg.get("frame_height", 0)), n_fused=msg.get("n_fused"))


def synthetic_map(width: int = 160, height: int = 120) -> dict:
    """A decoded range_map message of a level camera 10 m above flat ground facing a wall 30 m ahead that covers the
    middle third of the columns (sky above the horizon elsewhere): confident obstacle pixels, ground and pixels at
    infinity, so ``analyse`` goes through every branch (pooling, components, sectors)."""
    from eonav.bus import schema
    from eonav.geometry.camera import Camera
    from eonav.ranging.rangemap import AT_INFINITY, VALID
    cam = Camera("warmup", width, height, 0.8 * width, 0.8 * width, (width - 1) / 2, (height - 1) / 2)
    v, u = np.mgrid[0:height, 0:width].astype(np.float64)
    slope = (v - cam.cy) / cam.fy
    with np.errstate(divide="ignore"):
        r = np.where(slope > 0, 10.0 / slope, np.inf)                  # ground 10 m below the lens
    wall = (u >= width / 3) & (u < 2 * width / 3) & (r > 30.0)
    r[wall] = 30.0
    flags = np.where(np.isfinite(r), VALID, AT_INFINITY).astype(np.uint8)
    return schema.decode(schema.encode(
        "range_map", camera_id="warmup", seq=1, stamp_us=1, method="synthetic", range_m=r.astype(np.float32),
        confidence=np.ones(r.shape, np.float16), flags=flags,
        inv_range_std_per_m=np.full(r.shape, 1e-4, np.float16), camera=schema.camera_to_msg(cam),
        position_ned_m=[0.0, 0.0, -10.0], q_wxyz=[1.0, 0.0, 0.0, 0.0], frame_width=2 * width,
        frame_height=2 * height), expect="range_map")


def warm_up(node: Node, cfg, ob):
    """One ``analyse_msg`` on ``synthetic_map`` (with a now-pose, so ``sectors_now`` runs too), timed as the latency
    ``warmup``; a failure is counted (``warmup_errors``) and logged, never raised: the real maps say whether the
    analysis works. Returns the result (None on failure)."""
    from eonav.geometry.camera import VehicleState
    from eonav.bus.schema import camera_from_msg
    t0 = time.perf_counter()
    try:
        msg = synthetic_map()
        state = VehicleState.from_quat(msg["position_ned_m"], msg["q_wxyz"])
        res = analyse_msg(ob, msg, camera_from_msg(msg["camera"]), state, cfg, now_state=state)
    except Exception as e:  # noqa: BLE001  (see docstring)
        node.count("warmup_errors")
        node.log.warning("obstacle analysis warm-up failed: %s: %s", type(e).__name__, e)
        return None
    node.latency("warmup", time.perf_counter() - t0)
    node.log.info("obstacle analysis warm-up: %.1f ms, %d obstacles", (time.perf_counter() - t0) * 1e3,
                  len(res.obstacles))
    return res


def process_map(node: Node, sample, pub, cfg, guidance: Guidance, nav: LatestNav, sender, args, cameras, ob,
                VehicleState):
    t_deq, cpu0 = now_us(), time.thread_time()
    msg = node.decode(sample, expect="range_map")
    gate = args._freshness
    if msg is None or not screen(node, gate, msg["camera_id"], msg["stamp_us"], "arrival"):
        return
    node.input_seen("range maps")
    node.latency("age.dequeued", (t_deq - msg["stamp_us"]) * 1e-6)
    node.latency("cpu.decode", time.thread_time() - cpu0)
    t0, cpu1 = time.perf_counter(), time.thread_time()
    try:
        K.check_chunk(msg["camera_id"], "camera id")
        cam = cameras.get(msg["camera"])[0]
        q = np.asarray(msg["q_wxyz"], float)
        state = VehicleState.from_quat(msg["position_ned_m"], q)
        now_state, nav_stamp = (None, None) if args.no_nav else nav.get()
        if now_state is not None and not (0 <= nav_stamp - msg["stamp_us"] <= NAV_MAX_AHEAD_S * 1e6):
            now_state = None                  # older than the map, or from another clock: use the capture pose
        res = analyse_msg(ob, msg, cam, state, cfg, now_state)
    except InputError as e:
        node.count("bad_maps")
        node.log_limited("bad_map", logging.WARNING, "range map %s/%s rejected: %s", msg.get("camera_id"),
                         msg.get("seq"), e)
        return
    t1, cpu2 = time.perf_counter(), time.thread_time()
    node.latency("analyse", t1 - t0)
    node.latency("cpu.analyse", cpu2 - cpu1)
    if not screen(node, gate, msg["camera_id"], msg["stamp_us"], "publish"):   # stale by now: no list, no tracks
        return
    ids, tracks = guidance.on_map(res, msg, cam, state, cfg)
    for o, track_id in zip(res.obstacles, ids):
        o.id = track_id
    t2, cpu3 = time.perf_counter(), time.thread_time()
    node.latency("track", t2 - t1)
    node.latency("cpu.track", cpu3 - cpu2)
    node.put(pub, "obstacle_list", stamp_us=msg["stamp_us"], camera_id=msg["camera_id"],
             obstacles=[o.to_msg() for o in res.obstacles], sectors=res.sectors.to_msg(),
             position_ned_m=msg["position_ned_m"], q_wxyz=q, frame_age_ms=age_ms(msg["stamp_us"]))
    gate.commit(msg["camera_id"], msg["stamp_us"])
    compute_s = time.perf_counter() - t0
    node.latency("publish", time.perf_counter() - t2)
    node.latency("cpu.publish", time.thread_time() - cpu3)
    t3, cpu4 = time.perf_counter(), time.thread_time()
    guidance.put(tracks)                      # guidance's track message, after the obstacle list it labels
    node.latency("cpu.track_message", time.thread_time() - cpu4)
    node.latency("track_message", time.perf_counter() - t3)
    node.count("maps_processed")
    node.count("obstacles_published", len(res.obstacles))
    node.latency("compute", compute_s)
    node.latency("capture_to_obstacles", (now_us() - msg["stamp_us"]) * 1e-6)
    if sender is not None:
        sender.update(res.sectors_now if res.sectors_now is not None else res.sectors, msg["stamp_us"],
                      source=msg["camera_id"])
        node.count("mavlink.nav_compensated" if res.sectors_now is not None else "mavlink.capture_pose")
        if sender.send_3d and guidance.latest is not None:      # the confirmed tracks, from the pose the sectors use
            pose = now_state if res.sectors_now is not None else state
            sender.update_tracks(guidance.latest["tracks"], guidance.latest["stamp_us"], pose.position_ned_m,
                                 pose.T_body_ned, cfg.min_distance_m, cfg.max_distance_m)


if __name__ == "__main__":
    service_main("obstacles", add_arguments, body)
