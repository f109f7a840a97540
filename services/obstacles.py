"""Obstacle publisher: range maps (+ navigation) -> obstacle list for guidance, and MAVLink OBSTACLE_DISTANCE.

Subscribes ``keys.range_maps_all(vehicle)`` (RingChannel: the newest map wins) and ``keys.nav_state`` (ring of
1: only the latest pose matters). For each range map ``eonav.obstacles.analyse`` gives the 72 OBSTACLE_DISTANCE
sectors and the obstacle list (ids kept across maps by ``ObstacleTracker``), published as schema
``obstacle_list`` on ``keys.obstacles(vehicle)``: a reliable, small, express message (the node's default
non-image publisher: CongestionControl.BLOCK, DATA_HIGH, express). Everything in it refers to the range map's
capture stamp and pose, so guidance can use the absolute ``position_ned_m`` of each obstacle.

With ``--mavlink-out udpout:127.0.0.1:14560`` (any pymavlink connection string) a sender thread emits
OBSTACLE_DISTANCE at ``--mavlink-rate-hz`` (>= 10 Hz) with the merged latest sectors of every camera while they are
fresh, then one all-unknown message and silence (see ``eonav.nav.mavlink_out`` for why), plus a companion HEARTBEAT at 1 Hz. The sectors sent to
the autopilot are measured from the latest navigation pose when one newer than the map is at hand
(``sectors_now``): the autopilot applies them relative to where it is on arrival.

Latest map wins: after each map the worker drains the ring and analyses only the newest map of each camera (older
ones count ``maps_superseded``). The range map is analysed pooled to <= ``--max-width-px`` columns (eonav.obstacles.detect), on
its own grid with its own ``camera`` (a locator publishing at its locate scale sends the scaled camera and the frame's
size, ``frame_width`` / ``frame_height``: pixel counts and boxes come out in frame pixels); a map whose arrays do not
match its camera's size, or whose frame size is smaller than its camera, is rejected and counted (``bad_maps``).

Warm-up: before the subscriber is read, ``warm_up`` runs ``analyse`` once on a small synthetic range map (a wall and a
ground plane, 160 x 120, through schema encode/decode) with the service's configuration and a navigation pose, so the
first real map does not pay the first call's set-up (measured 291 ms for the first 640 x 480 map instead of ~15 ms);
its time is the latency ``warmup``, a failure is counted (``warmup_errors``) and logged and the service goes on.

Health: ``maps_processed``, ``obstacles_published``, ``bad_maps``, ``maps_superseded``, MAVLink counters; latencies
``capture_to_obstacles`` (frame capture -> obstacle list put: the pipeline's end-to-end figure), ``compute`` and
``warmup``.
"""
from __future__ import annotations

import logging
import time

import numpy as np

from eonav import InputError
from eonav.bus import keys as K
from eonav.bus.node import Node, add_flag, now_us, service_main

log = logging.getLogger("eonav.service.obstacles")

NAV_MAX_AHEAD_S = 1.0        # a nav state newer than the map by more than this is from another timeline


def add_arguments(p):
    from eonav.obstacles.detect import ObstacleConfig
    d = ObstacleConfig()                         # the extraction defaults are the library's
    add_flag(p, "--mavlink-out", env="EONAV_OBSTACLES_MAVLINK_OUT", default=None, metavar="CONNECTION",
             help="send OBSTACLE_DISTANCE on this pymavlink connection, e.g. udpout:127.0.0.1:14560")
    add_flag(p, "--mavlink-source-system", env="EONAV_OBSTACLES_MAVLINK_SOURCE_SYSTEM", default=1, type=int,
             help="our MAVLink system id (the vehicle's, as mavlink_ingest --source-system); component is 191 "
                  "(onboard computer)", aliases="--mavlink-sysid", old_env="EONAV_OBSTACLES_MAVLINK_SYSID")
    add_flag(p, "--mavlink-rate-hz", env="EONAV_OBSTACLES_MAVLINK_RATE_HZ", default=10.0, type=float, metavar="HZ",
             help="OBSTACLE_DISTANCE rate (ArduPilot/PX4 time out after 0.5 s)",
             aliases="--mavlink-rate", old_env="EONAV_OBSTACLES_MAVLINK_RATE")
    add_flag(p, "--stale-s", env="EONAV_OBSTACLES_STALE_S", default=0.5, type=float, metavar="S",
             help="after this long without a new range map, send one all-unknown OBSTACLE_DISTANCE and then none "
                  "until maps flow again (the autopilot then reports No Data)",
             aliases="--stale", old_env="EONAV_OBSTACLES_STALE")
    add_flag(p, "--no-nav", env="EONAV_OBSTACLES_NO_NAV", default=False, action="store_true",
             help="do not re-reference MAVLink sectors to the latest navigation pose")
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
    """The newest nav_state (pose + stamp), filled by a worker; read by the obstacle loop."""

    def __init__(self):
        import threading
        self._lock = threading.Lock()
        self.state = None
        self.stamp_us = None

    def set(self, state, stamp_us):
        with self._lock:
            if self.stamp_us is None or stamp_us >= self.stamp_us:
                self.state, self.stamp_us = state, stamp_us

    def get(self):
        with self._lock:
            return self.state, self.stamp_us


def body(node: Node, args) -> None:
    from eonav.obstacles.detect import ObstacleTracker
    cfg = obstacle_config(args)
    sender = None
    if args.mavlink_out:
        from eonav.nav.mavlink_out import ObstacleDistanceSender
        if args.mavlink_rate_hz < 10.0:
            node.log.warning("--mavlink-rate-hz %.1f is below the 10 Hz the autopilots are tuned for",
                             args.mavlink_rate_hz)
        sender = ObstacleDistanceSender(args.mavlink_out, system_id=args.mavlink_source_system,
                                        rate_hz=args.mavlink_rate_hz, stale_s=args.stale_s)
    pub = node.publisher(K.obstacles(node.vehicle))          # reliable, small, express
    maps = node.subscribe(K.range_maps_all(node.vehicle), ring=2)
    nav = LatestNav()
    if not args.no_nav:
        navsub = node.subscribe(K.nav_state(node.vehicle), ring=1)
        node.worker(nav_loop, node, navsub, nav, name="nav")
    node.worker(obstacle_loop, node, maps, pub, cfg, ObstacleTracker(), nav, sender, args, name="obstacles")
    if sender is not None:
        def send_loop():
            try:
                last = 0.0
                while not node.stop_event.wait(sender.tick()):
                    if time.monotonic() - last >= 0.5:
                        last = time.monotonic()
                        mirror_counters(node, sender)
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
    from eonav.geometry.camera import VehicleState
    for sample in sub:
        msg = node.decode(sample, expect="nav_state")
        if msg is None:
            continue
        p, q = np.asarray(msg["position_ned_m"], float), np.asarray(msg["q_wxyz"], float)
        if not (np.all(np.isfinite(p)) and np.all(np.isfinite(q)) and abs(np.linalg.norm(q) - 1) < 1e-3):
            node.count("nav_incomplete")
            continue
        nav.set(VehicleState.from_quat(p, q), int(msg["stamp_us"]))


def obstacle_loop(node: Node, sub, pub, cfg, tracker, nav: LatestNav, sender, args) -> None:
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
            process_map(node, sample, pub, cfg, tracker, nav, sender, args, cameras, ob, VehicleState)


def analyse_msg(ob, msg: dict, cam, state, cfg, now_state=None):
    """``eonav.obstacles.analyse`` of a decoded range_map on its own grid: ``cam`` is the message's camera, the frame
    size (0 x 0 from older locators: the map is on the frame's grid) makes the pixel counts frame pixels."""
    return ob.analyse(msg["range_m"], cam, state, confidence=msg["confidence"], flags=msg["flags"],
                      inv_range_std_per_m=msg["inv_range_std_per_m"], cfg=cfg, now_state=now_state,
                      frame_size=(msg.get("frame_width", 0), msg.get("frame_height", 0)))


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


def process_map(node: Node, sample, pub, cfg, tracker, nav: LatestNav, sender, args, cameras, ob, VehicleState):
    msg = node.decode(sample, expect="range_map")
    if msg is None:
        return
    t0 = time.perf_counter()
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
    tracker.update(res.obstacles, msg["stamp_us"])
    node.put(pub, "obstacle_list", stamp_us=msg["stamp_us"], camera_id=msg["camera_id"],
             obstacles=[o.to_msg() for o in res.obstacles], sectors=res.sectors.to_msg(),
             position_ned_m=msg["position_ned_m"], q_wxyz=q)
    compute_s = time.perf_counter() - t0
    node.count("maps_processed")
    node.count("obstacles_published", len(res.obstacles))
    node.latency("compute", compute_s)
    node.latency("capture_to_obstacles", (now_us() - msg["stamp_us"]) * 1e-6)
    if sender is not None:
        sender.update(res.sectors_now if res.sectors_now is not None else res.sectors, msg["stamp_us"],
                      source=msg["camera_id"])
        node.count("mavlink.nav_compensated" if res.sectors_now is not None else "mavlink.capture_pose")


if __name__ == "__main__":
    service_main("obstacles", add_arguments, body)
