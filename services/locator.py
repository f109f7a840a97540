"""Locator: posed frames -> range maps with confidence (docs/bus.md, "Locator").

In: schema ``posed_frame`` on ``keys.posed_frames_all(vehicle)`` (or one camera). Out: schema ``range_map`` on
``keys.range_map(vehicle, camera_id)`` with the reference frame's stamp, pose and camera. A small history per camera
feeds ``eonav.ranging.pair_policy``; each pair goes through ``eonav.ranging.locate.locate``.

Two decisions a reader must know:

- latest frame wins: the subscriber is a RingChannel and, after each locate, only the newest frame of each camera
  is ranged (older ones become pair partners), so a slow locator skips frames instead of queueing them;
- the locate scale is adaptive by default (``eonav.ranging.scale_control``: the largest scale whose compute time
  fits a budget, calibrated on a synthetic pair at a camera's first frame), and the map is published on the grid
  it was computed on, with that grid's (scaled) camera in the message.
"""
from __future__ import annotations

import argparse
import logging
import math
import time

import numpy as np

from eonav import InputError
from eonav.bus import keys as K
from eonav.bus.freshness import FreshnessGate, age_ms, screen
from eonav.bus.node import Node, add_flag, now_us, service_main
from eonav.bus.session import env_flag

log = logging.getLogger("eonav.service.locator")

MAX_SEQ_GAP = 10_000          # a larger jump of a camera's seq is a restart (or corruption), not dropped frames


def add_arguments(p):
    from eonav.ranging.pair_policy import PairPolicyConfig
    d = PairPolicyConfig()                       # the pair policy's defaults are the library's
    add_flag(p, "--method", env="EONAV_LOCATOR_METHOD", default="dense",
             help="range estimator (eonav.ranging.locate.METHODS): dense (default), paper, dis")
    p.add_argument("--method-param", action="append", default=[], metavar="NAME=VALUE",
                   help="extra keyword for the method, e.g. search_window=7 (repeatable; numbers parsed)")
    add_flag(p, "--cv-threads", env="EONAV_CV_THREADS", default=-1, type=int, metavar="N",
             help="cv2.setNumThreads(N); -1 keeps OpenCV's default, 0 disables its threading")
    add_flag(p, "--camera-id", env="EONAV_LOCATOR_CAMERA_ID", default=None,
             help="only this camera id (default: every camera of the vehicle)",
             aliases="--camera", old_env="EONAV_LOCATOR_CAMERA")
    add_flag(p, "--ring", env="EONAV_LOCATOR_RING", default=2, type=int,
             help="RingChannel depth of the posed-frame subscriber (newest N kept)")
    add_flag(p, "--scale", env="EONAV_LOCATOR_SCALE", default="auto", metavar="auto|FACTOR",
             help="auto: per camera and pair, the largest scale of the ladder (1, 0.5, ... --min-scale) whose "
                  "compute time fits --budget-ms (eonav.ranging.scale_control); a number FACTOR in (0, 1]: always "
                  "locate on images resized by FACTOR (0.5 = half resolution, ~4x less work). See --publish-grid")
    add_flag(p, "--min-scale", env="EONAV_LOCATOR_MIN_SCALE", default=0.3, type=float, metavar="FACTOR",
             help="--scale auto: lowest rung of the ladder 1, 0.5, 0.25, ... (FACTOR itself is the last rung; "
                  "default 0.3: 1, 0.5, 0.3)")
    add_flag(p, "--latency-target-ms", env="EONAV_LOCATOR_LATENCY_TARGET_MS", default=25.0, type=float, metavar="MS",
             help="--scale auto: step down a rung when the p90 of the locator's recent time per frame (frame taken "
                  "off the ring -> range map put) exceeds this; a frame also waits up to one such time in the ring, "
                  "so the default bounds the locator's share of a 100 ms capture -> obstacle list at about 50 ms; "
                  "0: compute budget only")
    add_flag(p, "--budget-ms", env="EONAV_LOCATOR_BUDGET_MS", default=None, type=float, metavar="MS",
             help="--scale auto: compute-time budget per pair; default 60 %% of the camera's measured frame interval, "
                  "clamped to [20, 200] ms")
    p.add_argument("--warmup", action=argparse.BooleanOptionalAction,
                   default=env_flag("EONAV_LOCATOR_WARMUP", True),
                   help="at a camera's first frame, time one locate call per scale rung on a synthetic pair made of "
                        "that frame (its first pair then runs warm, at a rung that fits the budget: "
                        "calibrate_camera) (env EONAV_LOCATOR_WARMUP; default on)")
    add_flag(p, "--publish-grid", env="EONAV_LOCATOR_PUBLISH_GRID", default="locate", choices=("locate", "frame"),
             help="locate (default): publish the range map on the grid it was computed on, with that grid's (scaled) "
                  "camera and the frame size in the message; frame: upsample it to the frame's grid (nearest)")
    add_flag(p, "--fusion", env="EONAV_LOCATOR_FUSION", default="auto", choices=("auto", "on", "off"),
             help="fuse every camera's measurements over time into one inverse-range state per camera and publish "
                  "the fused map (eonav.fusion); auto: on with the dense method, off with the others")
    add_flag(p, "--pair-checks", env="EONAV_LOCATOR_PAIR_CHECKS", action="store_true",
             help="fusion with the dense method: check every measured pair first (eonav.fusion.measure): image b "
                  "brought onto a's brightness when exposure changed, the pose error seen on sparse tracks added to "
                  "the pair's sigma, and a frame whose pose disagrees with its neighbours' by more than "
                  "--max-pose-shift-px never used as a partner. For real cameras and navigation whose pose errors "
                  "reach a pixel; costs ~10-15 ms CPU per pair (docs/methods.md). Default off")
    add_flag(p, "--max-pose-shift-px", env="EONAV_LOCATOR_MAX_POSE_SHIFT_PX", default=0.75, type=float, metavar="PX",
             help="--pair-checks: a frame whose pose shifts its tracks with both neighbours by more than this "
                  "(px across the epipolar lines) is no partner (default 0.75)")
    add_flag(p, "--max-input-age-ms", env="EONAV_LOCATOR_MAX_INPUT_AGE_MS", default=800.0, type=float,
             help="drop (count dropped.too_old) a posed frame older than this on arrival, and a range map whose frame "
                  "is older than this when it would be published (docs/bus.md, Staleness)")
    add_flag(p, "--input-timeout-ms", env="EONAV_LOCATOR_INPUT_TIMEOUT_MS", default=1000.0, type=float,
             help="no usable posed frame for this long: state degraded (5 periods of a 5 fps camera)")
    add_flag(p, "--range-std", env="EONAV_LOCATOR_RANGE_STD", default="f16", choices=("f16", "f32", "off"),
             help="send inv_range_std_per_m as float16, float32, or not at all")
    g = p.add_argument_group("pair policy (eonav.ranging.pair_policy)")
    add_flag(g, "--min-disparity-px", env="EONAV_PAIR_MIN_DISPARITY_PX", default=d.min_disparity_px, type=float,
             metavar="PX", help="median translational disparity of a point at --ref-range-m needed for a pair",
             aliases="--min-disparity", old_env="EONAV_PAIR_MIN_DISPARITY")
    add_flag(g, "--ref-range-m", env="EONAV_PAIR_REF_RANGE_M", default=d.ref_range_m, type=float, metavar="M",
             help="range at which parallax is judged", aliases="--ref-range", old_env="EONAV_PAIR_REF_RANGE")
    add_flag(g, "--min-baseline-m", env="EONAV_PAIR_MIN_BASELINE_M", default=d.min_baseline_m, type=float, metavar="M",
             help="a baseline of at least this also qualifies (0: off)",
             aliases="--min-baseline", old_env="EONAV_PAIR_MIN_BASELINE")
    add_flag(g, "--max-age-s", env="EONAV_PAIR_MAX_AGE_S", default=d.max_age_s, type=float, metavar="S",
             help="oldest earlier frame used", aliases="--max-age", old_env="EONAV_PAIR_MAX_AGE")
    add_flag(g, "--max-rotation-deg", env="EONAV_PAIR_MAX_ROTATION_DEG", default=d.max_rotation_deg, type=float,
             metavar="DEG", help="largest rotation between the two frames of a motion pair",
             aliases="--max-rotation", old_env="EONAV_PAIR_MAX_ROTATION")
    add_flag(g, "--history", env="EONAV_PAIR_HISTORY", default=d.history, type=int, help="frames kept per camera")
    add_flag(g, "--stereo", env="EONAV_PAIR_STEREO", default=None, metavar="REF,PARTNER",
             help="stereo rig: two camera ids, the first is the reference")
    add_flag(g, "--max-stereo-dt-s", env="EONAV_PAIR_MAX_STEREO_DT_S", default=d.max_stereo_dt_s, type=float,
             metavar="S", help="largest stamp difference within a stereo pair",
             aliases="--max-stereo-dt", old_env="EONAV_PAIR_MAX_STEREO_DT")


def parse_params(items) -> dict:
    out = {}
    for it in items:
        name, sep, val = str(it).partition("=")
        if not sep or not name.isidentifier():
            raise InputError(f"--method-param {it!r}: expected NAME=VALUE")
        for conv in (int, float):
            try:
                out[name] = conv(val)
                break
            except ValueError:
                continue
        else:
            out[name] = {"true": True, "false": False, "none": None}.get(val.lower(), val)
    return out


def policy_config(args):
    from eonav.ranging.pair_policy import PairPolicyConfig
    rig = None
    if args.stereo:
        rig = tuple(s.strip() for s in args.stereo.split(","))
        for c in rig:
            K.check_chunk(c, "--stereo camera id")
    return PairPolicyConfig(min_disparity_px=args.min_disparity_px, ref_range_m=args.ref_range_m,
                            min_baseline_m=args.min_baseline_m, max_age_s=args.max_age_s,
                            max_rotation_deg=args.max_rotation_deg, history=args.history, stereo_rig=rig,
                            max_stereo_dt_s=args.max_stereo_dt_s)


def grey_image(msg: dict) -> np.ndarray:
    """The posed frame's image as float32 grey H x W (mono8/mono16 as is, bgr8 converted)."""
    img = msg["image"]
    enc = msg.get("encoding", "mono8")
    if enc in ("mono8", "mono16") and img.ndim == 2:
        return img.astype(np.float32)
    if enc in ("bgr8", "rgb8") and img.ndim == 3 and img.shape[2] == 3:
        import cv2
        code = cv2.COLOR_BGR2GRAY if enc == "bgr8" else cv2.COLOR_RGB2GRAY
        return cv2.cvtColor(np.ascontiguousarray(img), code).astype(np.float32)
    raise InputError(f"posed frame image: encoding {enc!r} with shape {img.shape} not understood "
                     "(expected mono8/mono16 H x W or bgr8/rgb8 H x W x 3)")


def scaled_camera(cam, scale: float):
    """``cam`` for images resized by ``scale`` (pixel centres kept): ``eonav.camera.scaled_camera``."""
    from eonav.geometry.camera import scaled_camera as scaled
    return scaled(cam, scale)


def upsample_index(full: int, small: int) -> np.ndarray:
    """Nearest scaled pixel of each full-resolution pixel: floor((u + 0.5) small / full)."""
    return np.minimum(((np.arange(full) + 0.5) * (small / full)).astype(np.int64), small - 1)


class CameraCache:
    """``camera_from_msg`` once per distinct camera map (the sync service sends the same one with every frame), and
    the camera scaled for locate at ``scale`` (the default of ``get``) or any other scale (``scaled``)."""

    def __init__(self, scale: float = 1.0):
        self.scale = scale
        self._c: dict = {}
        self._scaled: dict = {}

    def scaled(self, cam, scale: float):
        """``cam`` (a camera this cache returned) for images resized by ``scale``; ``cam`` itself at 1."""
        if scale == 1.0:
            return cam
        k = (id(cam), scale)
        hit = self._scaled.get(k)
        if hit is None or hit[0] is not cam:
            if len(self._scaled) >= 64:
                self._scaled.clear()
            hit = self._scaled[k] = (cam, scaled_camera(cam, scale))
        return hit[1]

    @staticmethod
    def _key(d: dict):
        return tuple(sorted((k, tuple(v) if isinstance(v, (list, tuple)) else v) for k, v in d.items()))

    def get(self, d: dict):
        """(camera, camera scaled for locate)."""
        from eonav.bus.schema import camera_from_msg
        try:
            key = self._key(d)
            hash(key)
        except TypeError:
            key = None
        hit = self._c.get(key) if key is not None else None
        if hit is None:
            cam = camera_from_msg(d)
            hit = (cam, self.scaled(cam, self.scale))
            if key is not None:
                if len(self._c) >= 32:
                    self._c.clear()
                self._c[key] = hit
        return hit


def frame_info(msg: dict, cameras: CameraCache | None = None):
    """Schema posed_frame -> PosedFrameInfo (camera, pose, grey image as payload). Raises InputError.

    The payload carries the grey image at the cache's scale and the camera for it, the quaternion, the camera map and
    ``scaled``: the grey images at other scales made so far (``scaled_view``)."""
    from eonav.geometry.camera import VehicleState
    from eonav.ranging.pair_policy import PosedFrameInfo
    cameras = cameras or CameraCache()
    cam, loc_cam = cameras.get(msg["camera"])
    q = np.asarray(msg["q_wxyz"], float)
    state = VehicleState.from_quat(msg["position_ned_m"], q, msg["stamp_us"] * 1e-6,
                                   what=f"posed frame {msg['camera_id']}/{msg['seq']}: q_wxyz")
    img = grey_image(msg)
    if img.shape != (cam.height, cam.width):
        raise InputError(f"posed frame {msg['camera_id']}/{msg['seq']}: image {img.shape[1]}x{img.shape[0]} but "
                         f"camera says {cam.width}x{cam.height}")
    if loc_cam is not cam:
        import cv2
        img = cv2.resize(img, (loc_cam.width, loc_cam.height), interpolation=cv2.INTER_AREA)
    return PosedFrameInfo(msg["camera_id"], int(msg["seq"]), int(msg["stamp_us"]), cam, state,
                          payload={"image": img, "camera": loc_cam, "q_wxyz": q, "camera_msg": msg["camera"],
                                   "scaled": {}})


def scaled_view(f, scale: float, cameras: CameraCache):
    """The View of frame ``f`` (from ``frame_info`` with a scale-1 cache: full-resolution grey image) at ``scale``. The
    resized image is kept in the frame's payload, so a frame that is the partner of the next pair is resized once."""
    from eonav.geometry.camera import View
    p = f.payload
    if scale == 1.0:
        return View(p["camera"], f.state, p["image"])
    img = p["scaled"].get(scale)
    cam = cameras.scaled(f.camera, scale)
    if img is None:
        import cv2
        img = p["scaled"][scale] = cv2.resize(p["image"], (cam.width, cam.height), interpolation=cv2.INTER_AREA)
    return View(cam, f.state, img)


def to_full_grid(a, cam):
    """A map computed at the locate scale back on the frame's grid (nearest neighbour); None stays None.

    Two ``take`` calls (rows, then columns) rather than one ``a[np.ix_(rows, cols)]``: the same pixels in about a
    quarter of the time (four maps per pair: range, confidence, std, flags)."""
    if a is None or a.shape == (cam.height, cam.width):
        return a
    a = np.asarray(a)
    return a.take(upsample_index(cam.height, a.shape[0]), axis=0).take(upsample_index(cam.width, a.shape[1]), axis=1)


F16_MAX = np.float32(np.finfo(np.float16).max)


def map_fields(res, f, loc_cam, range_std: str = "f16", publish_grid: str = "locate") -> dict:
    """The range_map fields that depend on the grid: the maps (range_m float32, confidence float16, flags uint8,
    inv_range_std_per_m per ``range_std``), ``camera`` and ``frame_width`` / ``frame_height``. ``res`` was located on
    ``loc_cam`` (the frame ``f``'s camera scaled for locate, or ``f.camera`` itself). ``locate``: the maps as computed,
    with ``loc_cam`` as the camera and the frame's size (none when ``loc_cam`` is the frame's camera); ``frame``: the
    maps upsampled to the frame's grid (``to_full_grid``) with the frame's camera."""
    from eonav.bus.schema import camera_to_msg
    std = None
    if res.inv_range_std_per_m is not None and range_std != "off":
        std = np.asarray(res.inv_range_std_per_m, np.float32)
        if range_std == "f16":
            # beyond float16's 65504 /m: +inf (such a sigma says: no information). Set explicitly: numpy's cast
            # takes a slow path on overflow (4.2 ms instead of 0.6 ms for a 320 x 320 dense map)
            std = np.where(std > F16_MAX, np.float32(np.inf), std).astype(np.float16)
    conf = np.asarray(res.confidence, np.float32)
    conf = np.where(conf > F16_MAX, np.float32(np.inf), conf).astype(np.float16)
    out = {"range_m": np.asarray(res.range_m, np.float32), "confidence": conf,
           "inv_range_std_per_m": std, "flags": None if res.flags is None else np.asarray(res.flags, np.uint8)}
    cam = f.camera
    if loc_cam is cam or publish_grid == "frame":
        out = {k: to_full_grid(v, cam) for k, v in out.items()}
        return dict(out, camera=f.payload["camera_msg"])
    return dict(out, camera=camera_to_msg(loc_cam), frame_width=cam.width, frame_height=cam.height)


def body(node: Node, args) -> None:
    from eonav.ranging.locate import get_method
    from eonav.ranging.pair_policy import PairPolicy
    if args.cv_threads >= 0:
        import cv2
        cv2.setNumThreads(args.cv_threads)
    get_method(args.method)                     # unknown method: configuration error (exit 2)
    if args.method == "dense":                  # its numba kernels compiled / loaded now, not in the first pair
        from eonav.ranging.methods.dense import prepare_kernels
        prepare_kernels()
    params = parse_params(args.method_param)
    policy = PairPolicy(policy_config(args))
    if args.ring < 1:
        raise InputError(f"--ring must be >= 1, got {args.ring}")
    new_controller = scale_controllers(args.scale, args.min_scale, args.budget_ms, args.latency_target_ms)
    new_controller()                            # bad --scale / --min-scale / --budget-ms: configuration error
    runner = fusion_runner(args, params)
    if runner is not None:
        warm_up_fusion(node, runner)
    key = K.posed_frame(node.vehicle, args.camera_id) if args.camera_id else K.posed_frames_all(node.vehicle)
    gate = FreshnessGate(args.max_input_age_ms / 1000.0)
    sub = node.subscribe(key, ring=args.ring)
    node.expect_input("posed frames", args.input_timeout_ms / 1000.0)
    node.worker(locate_loop, node, sub, policy, args.method, params, new_controller, args.range_std, args.warmup,
                args.publish_grid, runner, gate, name="locate")
    node.log.info("locator: method %s, fusion %s, scale %s (ladder %s, budget %s), publish grid %s, %s, policy %s",
                  args.method, "on" if runner else "off", args.scale, new_controller().ladder,
                  "auto" if args.budget_ms is None else f"{args.budget_ms:g} ms", args.publish_grid, key,
                  policy.config)


def fusion_runner(args, params: dict):
    """The locator's ``eonav.fusion`` runner (None with fusion off): the pair policy's judgement schedules the
    measurements, each one the configured method without its own fill (the fused map fills once)."""
    if args.fusion == "off" or (args.fusion == "auto" and args.method != "dense"):
        return None
    if args.method != "dense":
        raise InputError(f"--fusion on needs a method with a calibrated sigma (dense), not {args.method!r}")
    from dataclasses import replace

    from eonav.fusion.schedule import ScheduleConfig
    from eonav.fusion.sequence import FusionConfig, FusionRunner
    from eonav.ranging.locate import locate
    pol = policy_config(args)
    checks = bool(args.pair_checks)
    if checks and not args.max_pose_shift_px > 0:
        raise InputError(f"--max-pose-shift-px must be > 0, got {args.max_pose_shift_px!r}")
    schedule = ScheduleConfig(policy=replace(pol, stereo_rig=None), stereo_rig=pol.stereo_rig,
                              max_stereo_dt_s=pol.max_stereo_dt_s,
                              max_pose_shift_px=args.max_pose_shift_px if checks else math.inf)
    measure_params = dict(params, fill=False)
    if checks:
        from eonav.fusion.measure import checked_dense
        dense_params = {k: v for k, v in measure_params.items() if k != "fill"}

        def measure(va, vb, **prior):
            return checked_dense(va, vb, **dense_params, **prior)
    else:
        def measure(va, vb, **prior):
            return locate(va, vb, method=args.method, **measure_params, **prior)
    # fresh_measurements: the runner may write the fused map into a measurement's arrays (nothing else keeps them);
    # takes_prior: the dense method starts from the predicted state between full searches (FusionConfig.prior)
    return FusionRunner(FusionConfig(schedule=schedule), fresh_measurements=True, takes_prior=args.method == "dense",
                        measure=CpuTimed(measure))


class CpuTimed:
    """``fn`` with the CPU time of its calls (this thread's) summed in ``cpu_s``: the locate share of a fused
    frame's CPU, reported apart from the fusion's (health latency ``cpu.locate``)."""

    def __init__(self, fn):
        self.fn, self.cpu_s = fn, 0.0

    def __call__(self, *args, **kw):
        c0 = time.thread_time()
        try:
            return self.fn(*args, **kw)
        finally:
            self.cpu_s += time.thread_time() - c0


def warm_up_fusion(node: Node, runner) -> None:
    """Run predict, update and the fused map once on a small plane pair, before the first frame: their numba passes
    load (or compile, on a fresh install) now, not in the first fused map, which would then be too old to publish.
    A failure is counted (``warmup_errors``) and logged; the real frames then pay the load."""
    from eonav.fusion.schedule import ScheduleConfig
    from eonav.fusion.sequence import FusionConfig, FusionRunner, frame
    from eonav.ranging.methods.dense import _plane_pair
    from eonav.ranging.pair_policy import PairPolicyConfig
    t0 = time.perf_counter()
    try:
        va, vb = _plane_pair(96)
        probe = FusionRunner(FusionConfig(schedule=ScheduleConfig(policy=PairPolicyConfig(min_disparity_px=0.01))),
                             measure=runner.measure, fresh_measurements=True)
        maps = [m for k, v in enumerate((va, vb, va)) for m in probe.push(frame("warmup", v, 1_000_000 + k * 100_000, k))]
    except Exception as e:  # noqa: BLE001  (see docstring)
        node.count("warmup_errors")
        node.log.warning("fusion warm-up failed: %s: %s", type(e).__name__, e)
        return
    node.latency("warmup_fusion", time.perf_counter() - t0)
    node.log.info("fusion warm-up: %.0f ms, %d fused maps", (time.perf_counter() - t0) * 1e3, len(maps))


def scale_controllers(scale="auto", min_scale: float = 0.5, budget_ms: float | None = None,
                      latency_target_ms: float | None = None):
    """A factory of per-camera ``ScaleController``s for ``--scale`` (``auto`` or a number), ``--min-scale``,
    ``--budget-ms`` and ``--latency-target-ms`` (None or 0: none). Raises InputError on a bad value."""
    from eonav.ranging.scale_control import ScaleController, ladder, parse_scale
    fixed = parse_scale(scale)
    ladder(min_scale)
    budget_s = None if budget_ms is None else budget_ms * 1e-3
    if budget_s is not None and not budget_s > 0:
        raise InputError(f"--budget-ms must be > 0, got {budget_ms!r}")
    if latency_target_ms is not None and not (latency_target_ms >= 0):
        raise InputError(f"--latency-target-ms must be >= 0, got {latency_target_ms!r}")
    target_s = latency_target_ms * 1e-3 if latency_target_ms else None
    return lambda: ScaleController(fixed=fixed, min_scale=min_scale, budget_s=budget_s, latency_target_s=target_s)


def drain_latest(first, sub) -> list:
    """``first`` and everything already waiting in ``sub``, as (sample, is_newest_of_its_key) in arrival order."""
    batch = [first]
    while True:
        s = sub.try_recv()
        if s is None:
            break
        batch.append(s)
    last = {}
    for i, s in enumerate(batch):
        last[str(s.key_expr)] = i
    newest = set(last.values())
    return [(s, i in newest) for i, s in enumerate(batch)]


def rig_first(batch: list, ref_key: str | None) -> list:
    """A drained batch (``drain_latest``) with the stereo rig's reference frames (key ``ref_key``, its posed-frame
    key) moved after the others, each camera's own order kept. When both frames of an instant wait in the ring, the
    reference's push then finds the partner's frame of its instant and fuses it in the same push (the fusion runner
    otherwise holds the reference's measurements until the partner's frame comes: ``FusionRunner._hold_or_join``).
    ``ref_key`` None (no rig): the batch as it is."""
    if ref_key is None or len(batch) < 2:
        return batch
    return sorted(batch, key=lambda item: str(item[0].key_expr) == ref_key)


def synthetic_partner(f):
    """A partner for frame ``f`` made of ``f`` itself: the same image and camera, taken 0.1 s earlier from 2 m behind
    along the body x axis (forward flight: parallax everywhere but at the focus of expansion). Its ranges mean
    nothing; it exists so that a locate call on the camera's size can be timed before the first real pair."""
    from dataclasses import replace

    from eonav.geometry.camera import VehicleState
    st = f.state
    back = VehicleState(st.position_ned_m - 2.0 * st.T_body_ned[0], st.T_body_ned, st.t_s - 0.1)
    return replace(f, seq=f.seq - 1, stamp_us=f.stamp_us - 100_000, state=back, payload=dict(f.payload, scaled={}))


def calibrate_camera(f, controller, method: str, params: dict, cameras: CameraCache, locate) -> dict:
    """Warm-up at a camera's first frame: one untimed locate call at the lowest rung (the process's first call pays
    imports, OpenCV and work-buffer set-up), then one timed call per rung of ``controller``'s ladder on ``synthetic_partner(f)``. Returns {scale: seconds}
    for ``controller.calibrate``, so the camera's first real pairs run warm and at a rung that fits the budget.
    Raises what locate raises."""
    b = synthetic_partner(f)
    rungs = sorted(controller.ladder)
    locate(scaled_view(f, rungs[0], cameras), scaled_view(b, rungs[0], cameras), method=method, **params)
    out = {}
    for scale in rungs:
        va, vb = scaled_view(f, scale, cameras), scaled_view(b, scale, cameras)
        t0 = time.perf_counter()
        locate(va, vb, method=method, **params)
        out[scale] = time.perf_counter() - t0
    return out


def warm_up_camera(node: Node, f, controller, method: str, params: dict, cameras: CameraCache, locate) -> None:
    """``calibrate_camera`` and hand the timings to the controller; a failure is counted (``warmup_errors``) and
    logged, and the camera then starts uncalibrated at full scale."""
    t0 = time.perf_counter()
    try:
        costs = calibrate_camera(f, controller, method, params, cameras, locate)
    except Exception as e:  # the real pairs will say whether the method works; a warm-up must not stop the service
        node.count("warmup_errors")
        node.log_limited("warmup_error", logging.WARNING, "warm-up for camera %s failed: %s: %s", f.camera_id,
                         type(e).__name__, e)
        return
    new = controller.calibrate(costs)
    node.latency("warmup", time.perf_counter() - t0)
    node.log.info("camera %s: warm-up %s; starts at scale %g (budget %.1f ms)", f.camera_id,
                  ", ".join(f"scale {s:g}: {t * 1e3:.1f} ms" for s, t in sorted(costs.items(), reverse=True)), new,
                  controller.budget_s() * 1e3)


def show_scale(node: Node, camera_id: str, controller, shown: dict) -> None:
    """The gauge ``scale_pct.<camera>`` (a counter kept by deltas) follows the controller's scale."""
    pct = round(100 * controller.scale)
    d = pct - shown.get(camera_id, 0)
    if d or camera_id not in shown:
        node.count(f"scale_pct.{camera_id}", d)
        shown[camera_id] = pct


def locate_loop(node: Node, sub, policy, method: str, params: dict, new_controller=None,
                range_std: str = "f16", warmup: bool = False, publish_grid: str = "locate", runner=None,
                gate: FreshnessGate | None = None) -> None:
    """``new_controller()`` makes a camera's ScaleController (``scale_controllers``; default: fixed scale 1);
    ``warmup``: ``warm_up_camera`` at each camera's first frame; ``publish_grid``: ``locate`` or ``frame`` (module
    docstring); ``runner``: an ``eonav.fusion`` FusionRunner (``fusion_runner``), which then schedules the pairs and
    whose fused maps are published, instead of one pair's map per frame; ``gate``: the max-age and stamp-order
    gate on arrival and before each put (``eonav.bus.freshness``; None: none)."""
    if publish_grid not in ("locate", "frame"):
        raise InputError(f"publish grid must be 'locate' or 'frame', got {publish_grid!r}")
    from eonav.ranging.locate import locate
    new_controller = new_controller or scale_controllers(1.0)
    pubs: dict = {}
    last_seq: dict = {}
    scalers: dict = {}
    shown: dict = {}                            # camera -> scale_pct gauge value reported so far
    cameras = CameraCache(1.0)                  # the history keeps full-resolution grey images; pairs resize on use
    errors_in_row = 0
    reported_fusion: dict = {}                  # runner counts reported to the health counters so far
    sources: dict = {}                          # (camera, seq) -> posed frame, for the fused maps

    def one(sample, newest) -> None:
        nonlocal errors_in_row
        t_deq, cpu0, t_rx0 = now_us(), time.thread_time(), time.perf_counter()   # the frame taken off the ring
        msg = node.decode(sample, expect="posed_frame")
        if msg is None or (gate is not None and not screen(node, gate, msg["camera_id"], msg["stamp_us"], "arrival")):
            return
        node.input_seen("posed frames")
        t_rx = now_us()
        node.latency("capture_to_received", (t_rx - msg["stamp_us"]) * 1e-6)
        node.latency("age.dequeued", (t_deq - msg["stamp_us"]) * 1e-6)
        try:
            K.check_chunk(msg["camera_id"], "camera id")
            f = frame_info(msg, cameras)
        except InputError as e:
            node.count("bad_frames")
            node.log_limited("bad_frame", logging.WARNING, "bad posed frame on %s: %s", sample.key_expr, e)
            return
        node.latency("cpu.ingest", time.thread_time() - cpu0)      # decode, grey image
        prev = last_seq.get(f.camera_id)
        if prev is not None and prev + 1 < f.seq <= prev + MAX_SEQ_GAP:
            node.count("frames_skipped", f.seq - prev - 1)        # ring channel dropped them while we computed
        elif prev is not None and f.seq != prev + 1:
            node.count("seq_jumps")                               # a restarted camera, or a corrupt seq
        last_seq[f.camera_id] = f.seq
        if f.camera_id not in pubs:      # declared at the camera's first frame, not its first map, and before
            # the warm-up: a put right after the declaration can miss subscribers the route to which is not set
            # up yet (docs/zenoh.md, the declaration race); with the declaration after the warm-up, a second frame already waiting was
            # ranged and put ~10 ms after it, and its map was lost now and then
            pubs[f.camera_id] = node.publisher(K.range_map(node.vehicle, f.camera_id), image=True)
        sc = scalers.get(f.camera_id)
        if sc is None:
            sc = scalers[f.camera_id] = new_controller()
            if warmup:
                warm_up_camera(node, f, sc, method, params, cameras, locate)
            # the camera's first map must not be lost to a route not set up yet (see the declaration above):
            # its first frame only starts a pair, so a bounded wait here delays no map
            node.wait_matching(pubs[f.camera_id], 1.0)
        sc.observe_frame(f.seq, f.stamp_us)          # (a calibrated start may move with the budget: gauge it)
        show_scale(node, f.camera_id, sc, shown)
        if not newest:                   # a newer frame of this camera is already waiting: partner only
            if runner is not None:
                runner.remember(fusion_frame(f, sc.scale, cameras))
            else:
                policy.remember(f)
            node.count("frames_superseded")
            return
        if runner is not None:
            fuse_frame(node, runner, f, sc, pubs, range_std, t_rx0, cameras, publish_grid, reported_fusion, sources,
                       gate, scalers)
            return
        d = policy.offer(f)
        node.count(f"pairs.{d.reason}")
        if not d.ok:
            node.count("skipped")
            node.count(f"skipped.{d.reason}")
            node.log_limited(f"skip:{d.reason}", logging.INFO, "frame %s/%d: no pair (%s): %s",
                             f.camera_id, f.seq, d.reason, d.detail)
            return
        ref = d.a.camera_id                 # the reference camera's controller (a stereo pair's `a` may
        sc = scalers[ref]                   # be the rig frame that arrived before f)
        scale = sc.scale                    # one scale for both frames of the pair
        errors_in_row, compute_s = range_pair(node, d, pubs, method, params, scale, range_std, errors_in_row,
                                              t_rx0, cameras, locate, publish_grid, gate)
        if compute_s is not None:
            stage_s = time.perf_counter() - t_rx0             # (the map was put at the end of range_pair)
            report_change(node, ref, sc.observe_compute(scale, compute_s))
            report_change(node, ref, sc.observe_latency(scale, stage_s))
            show_scale(node, ref, sc, shown)


    rig = runner.config.schedule.stereo_rig if runner is not None else None
    ref_key = K.posed_frame(node.vehicle, rig[0]) if rig else None
    for first in sub:
        for sample, newest in rig_first(drain_latest(first, sub), ref_key):
            node.guarded("posed_frame", one, sample, newest)

def fusion_frame(f, scale: float, cameras: CameraCache):
    """The fusion runner's frame of posed frame ``f`` at the locate ``scale``."""
    from eonav.fusion.sequence import frame
    return frame(f.camera_id, scaled_view(f, scale, cameras), f.stamp_us, f.seq)


def fresh_to_put(node: Node, gate: FreshnessGate | None, camera_id: str, stamp_us: int) -> bool:
    """Whether a range map of ``camera_id`` stamped ``stamp_us`` may be put now (``gate`` None: always)."""
    return gate is None or screen(node, gate, camera_id, stamp_us, "publish")


def fuse_frame(node: Node, runner, f, sc, pubs: dict, range_std: str, t_rx0: float, cameras: CameraCache,
               publish_grid: str, reported: dict, sources: dict, gate: FreshnessGate | None = None,
               scalers: dict | None = None) -> None:
    """Push posed frame ``f`` through the fusion runner and publish the fused maps it returns (normally one: ``f``'s
    camera; a stereo partner's frame returns the rig reference's). A map carries the scale its own frame was pushed
    at, and its compute time (measurements + fusion) drives its own camera's scale controller (``scalers``, by
    camera id; ``sc``, ``f``'s, when absent) as a single pair's would."""
    scale = sc.scale
    t0, cpu0 = time.perf_counter(), time.thread_time()
    measure_cpu0 = getattr(runner.measure, "cpu_s", 0.0)
    worker_cpu0 = getattr(runner, "worker_cpu_s", 0.0)       # predict on the runner's worker thread
    node.latency("age.locate_start", (now_us() - f.stamp_us) * 1e-6)
    sources[(f.camera_id, f.seq)] = (f, scale)   # the posed frame behind a fused map (its quaternion, camera map)
    while len(sources) > 64:
        sources.pop(next(iter(sources)))
    try:
        maps = runner.push(fusion_frame(f, scale, cameras))
    except Exception as e:  # one bad frame must not stop the locator: forget the camera's state, start afresh
        node.count("locate_errors")
        node.count("fusion.resets_on_error")
        runner.reset(f.camera_id)
        node.log_limited("fusion_error", logging.ERROR, "fusion of %s/%d failed (state reset): %s: %s",
                         f.camera_id, f.seq, type(e).__name__, e)
        return
    cpu_push = time.thread_time() - cpu0 + getattr(runner, "worker_cpu_s", 0.0) - worker_cpu0
    cpu_measure = getattr(runner.measure, "cpu_s", 0.0) - measure_cpu0
    if maps:
        node.latency("age.fused", (now_us() - f.stamp_us) * 1e-6)
        node.latency("cpu.locate", cpu_measure)
        node.latency("cpu.fusion", cpu_push - cpu_measure)
    for name, v in runner.counts.items():
        d = v - reported.get(name, 0)
        if d:
            node.count(f"fusion.{name}", d)
            reported[name] = v
    for m in maps:
        t_pub, cpu_pub = time.perf_counter(), time.thread_time()
        a, map_scale = sources.get((m.frame.camera_id, m.frame.seq), (None, scale))
        if a is None:
            node.count("fusion.map_without_frame")
            continue
        msc = (scalers or {}).get(a.camera_id, sc)
        ms = m.measurements[-1] if m.measurements else {}
        compute_s = m.locate_s + m.fusion_s
        fields = map_fields(m.result, a, m.frame.camera, range_std, publish_grid)
        n = np.minimum(np.asarray(m.n_fused), 255).astype(np.uint8)
        if fields["range_m"].shape != n.shape:
            n = to_full_grid(n, a.camera)
        if not fresh_to_put(node, gate, a.camera_id, a.stamp_us):
            continue
        node.put(pubs[a.camera_id], "range_map", camera_id=a.camera_id, seq=a.seq, stamp_us=a.stamp_us,
                 other_camera_id=ms.get("other_camera_id", ""), other_seq=ms.get("other_seq", -1),
                 method=m.result.method, position_ned_m=a.state.position_ned_m, q_wxyz=a.payload["q_wxyz"],
                 baseline_m=ms.get("baseline_m", float("nan")), compute_s=compute_s, scale=float(map_scale),
                 overhead_s=(t0 - t_rx0), n_fused=n, frame_age_ms=age_ms(a.stamp_us), **fields)
        if gate is not None:
            gate.commit(a.camera_id, a.stamp_us)
        node.count("pairs_computed", len(m.measurements))
        node.count("maps_fused")
        node.tick("pairs_computed")
        node.latency("compute", compute_s)
        node.latency("locate", m.locate_s)
        node.latency("fusion", m.fusion_s)
        node.latency("publish", time.perf_counter() - t_pub)
        node.latency("cpu.publish", time.thread_time() - cpu_pub)
        age_s = (now_us() - a.stamp_us) * 1e-6
        node.latency("capture_to_published", age_s)
        if m.measurements:
            report_change(node, a.camera_id, msc.observe_compute(map_scale, compute_s))
        # the locator's own time for the frame (taken off the ring -> map put): what the scale controls
        frame_s = time.perf_counter() - t_rx0
        node.latency("frame_time", frame_s)
        report_change(node, a.camera_id, msc.observe_latency(map_scale, frame_s))


def report_change(node: Node, camera_id: str, change) -> None:
    """Count and log a scale change of ``camera_id``'s controller (None: nothing)."""
    if change is None:
        return
    node.count("scale_changes")
    node.count(f"scale_changes.{change.direction}")
    if change.probe:
        node.count("scale_changes.probe")
    node.log.info("camera %s: locate scale %g -> %g: %s", camera_id, change.old, change.new, change.reason)


def range_pair(node: Node, d, pubs: dict, method: str, params: dict, scale: float, range_std: str,
               errors_in_row: int, t_rx0: float, cameras: CameraCache, locate, publish_grid: str = "locate",
               gate: FreshnessGate | None = None) -> tuple:
    """Locate one pair at ``scale`` (both frames) and publish its range map on the ``publish_grid`` (``map_fields``)
    unless ``gate`` finds it stale; returns (the count of locate errors in a row, the locate call's seconds or None
    when it failed)."""
    a, b = d.a, d.b
    va, vb = scaled_view(a, scale, cameras), scaled_view(b, scale, cameras)
    t0 = time.perf_counter()
    try:
        res = locate(va, vb, method=method, **params)
    except Exception as e:  # one bad pair must not stop the locator; a persistent failure degrades it
        node.count("locate_errors")
        errors_in_row += 1
        node.log_limited("locate_error", logging.ERROR, "locate %s/%d with %s/%d failed: %s: %s",
                         a.camera_id, a.seq, b.camera_id, b.seq, type(e).__name__, e)
        if errors_in_row >= 3:
            node.set_state("degraded", f"locate failing: {type(e).__name__}: {e}")
        return errors_in_row, None
    t1 = time.perf_counter()
    compute_s = t1 - t0
    if node.state != "ok":
        node.set_state("ok")
    pub = pubs[a.camera_id]
    fields = map_fields(res, a, va.camera, range_std, publish_grid)
    range_m = fields["range_m"]
    overhead_s = (t0 - t_rx0) + (time.perf_counter() - t1)     # so far; the encode and put follow
    if not fresh_to_put(node, gate, a.camera_id, a.stamp_us):
        return 0, compute_s
    node.put(pub, "range_map", camera_id=a.camera_id, seq=a.seq, stamp_us=a.stamp_us,
             other_camera_id=b.camera_id, other_seq=b.seq, other_stamp_us=b.stamp_us, method=res.method,
             position_ned_m=a.state.position_ned_m, q_wxyz=a.payload["q_wxyz"], baseline_m=d.baseline_m,
             compute_s=compute_s, scale=float(scale), overhead_s=overhead_s, frame_age_ms=age_ms(a.stamp_us),
             **fields)
    if gate is not None:
        gate.commit(a.camera_id, a.stamp_us)
    node.count("pairs_computed")
    node.count(f"pairs_computed.{d.reason}")
    node.tick("pairs_computed")
    node.latency("compute", compute_s)
    node.latency("overhead", (t0 - t_rx0) + (time.perf_counter() - t1))
    node.latency("capture_to_published", (now_us() - a.stamp_us) * 1e-6)
    valid = np.isfinite(range_m)
    node.count("range_pixels_valid", int(np.count_nonzero(valid)))
    node.count("range_pixels_total", int(valid.size))
    node.count(f"pairs_computed.scale_{round(100 * scale)}")
    return 0, compute_s


if __name__ == "__main__":
    service_main("locator", add_arguments, body)
