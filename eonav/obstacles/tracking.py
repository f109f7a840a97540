"""Obstacle tracks in NED from the obstacle lists of successive range maps, and what guidance needs from them.

Pure numpy/scipy: no transport, no wall clock (every time is a ``stamp_us`` given by the caller).

Measurement (one obstacle of ``eonav.obstacles.analyse``): its median NED point ``z`` with a covariance built from
the camera geometry. A point seen at pixel (u, v) and range x_c is x_cam = x_c [1, (u - cx)/fx, (v - cy)/fy]
(inverse of eqs. 8-9); linearised in (x_c, u, v),
    J = [[1, 0, 0], [a, x_c/fx, 0], [b, 0, x_c/fy]],  a = (u - cx)/fx, b = (v - cy)/fy,
    R_cam = J diag(s_x^2, s_u^2, s_v^2) J^T,          R = R_ned_cam R_cam R_ned_cam^T + s_nav^2 I   (eq. 33)
with s_x the range 1-sigma (the obstacle's ``range_std_m``, plus ``extent_fraction`` of its depth along the axis),
s_u, s_v the pixel 1-sigma of the median point (``pixel_sigma_px``, ``extent_fraction`` of the box's pixel width /
height: the median moves as more or less of the object is seen, and the attitude error ``attitude_sigma_rad`` x f).
Error along the ray is the range sigma, across it the pixel extent at that range. Obstacles of one list whose boxes
come within ``merge_gap_m`` of each other are merged first (``merge_fragments``: the list cuts a thin pole at its
range noise into stacked pieces; one object, one measurement).

Filter: one constant-velocity Kalman filter per track, state [position_ned_m, velocity_ned_mps], white-noise
acceleration of spectral density ``accel_sigma_mps2^2`` (F = [[I, dt I], [0, I]], Q = q [[dt^3/3 I, dt^2/2 I],
[dt^2/2 I, dt I]]), Joseph-form update.

Association per range map: every track is predicted to the map's stamp; a track and a measurement may pair when the
squared Mahalanobis distance of the innovation, d^2 = y^T S^-1 y with S = P_pos + R, is within ``gate_chi2`` (3
degrees of freedom); the pairs minimise sum(d^2 + ln det S) (``scipy.optimize.linear_sum_assignment``). Unpaired
measurements start tentative tracks (new ids, never reused). A track that is not paired is classified with the
map's ``FieldOfView``: in view and unobstructed = a miss; out of view (behind, outside the image, beyond the listed
distance), occluded (the map sees something nearer at its pixel) or without data there = coasting (prediction
only: the covariance grows, no miss counted).

Two options, off by default (docs/guidance.md has what they do on the benchmark): ``see_through_k`` > 0 makes a
measurement that lies farther than a confirmed track along its own ray by more than k of the track's sigma there a
bearing-only measurement for that track (its range variance grows by (k e)^2, e the excess): a matching window
wider than a thin object ranges its background. ``duplicate_chi2`` > 0 merges two confirmed tracks whose position and
velocity agree within that d^2 into the older id.

Phantoms that follow the vehicle (the static-world test, ``drift_test``): ground seen near the horizon and ranged
too near stays at a near-constant range ahead, so its detections drift in NED along the vehicle's own velocity, at
(1 - r'/r) of its speed for a range r' ranged as a fixed fraction of the true r, at the full speed for a constant
range; a static obstacle's detections stay put. Each track fits a line to its last ``follow_window_s`` of detections
along the vehicle's velocity (the view's ``velocity_ned_mps``, else the difference of successive views' poses), with
the fit's own scatter (the maps' sigma is not trusted for this: it is what lets the phantoms through): STATIC when
the drift is below ``follow_fraction`` of the speed by ``follow_k`` sigma, FOLLOWS when above it by as much,
UNDECIDED in between. A real obstacle moving away along the vehicle's path faster than that fraction looks the same
and is held too (a monocular camera ranges such a mover as static anyway).

Life cycle: tentative -> confirmed after ``confirm_hits`` hits and a STATIC verdict; a tentative track dies at its
first miss or when not confirmed within ``confirm_window_s``, unless the test is still deciding it (UNDECIDED with a
drift inside the static band: then at its second consecutive miss or after ``follow_window_s``, ``still_deciding``)
or has not had the ``follow_min_hits`` detections its fit needs yet and nothing came inside its gate (then at its
second consecutive miss, and still after ``confirm_window_s``, ``awaiting_fit``);
any track dies at a FOLLOWS verdict; a confirmed track dies after ``max_misses`` consecutive misses, after
``max_coast_s`` without a hit, or when its position 1-sigma exceeds ``max_position_sigma_m``. Without a
``FieldOfView`` the tracker knows no vehicle motion and the test passes.

Guidance (``assess``): for each track predicted to the current time, the distance and the bearing in body FRD of the
current pose, and the collision cone along the current velocity. The obstacle is a box in NED centred on the track
position with the track's extent, inflated on each axis by ``vehicle_radius_m + k_sigma * sigma_axis`` (sigma_axis
the track's position 1-sigma on that axis): the relative motion w = v_vehicle - v_obstacle (v_obstacle = 0 unless
the track is ``moving``) puts it in the cone when the ray t -> w t from the vehicle hits that box within
``horizon_s``; the time to contact is the ray's entry time (0 when already inside), the earliest contact consistent
with k sigma; the expected time to contact is the entry into the box grown by the vehicle radius only
(``expected_contact_time``). The track's extent is the measurements' with the per-pixel range noise taken out
(``range_noise_extent``: a face seen head-on spreads along the ray by its range noise alone). See docs/guidance.md.
"""
from __future__ import annotations

import math
from collections import deque
from dataclasses import dataclass, field
from functools import lru_cache

import numpy as np
from scipy.optimize import linear_sum_assignment
from scipy.stats import norm, t as student_t

from eonav import InputError
from eonav.geometry.camera import Camera, VehicleState
from eonav.geometry.frames import camera_from_ned

# visibility of a predicted track in one range map
VISIBLE, OUT_OF_VIEW, OCCLUDED, NO_DATA = "visible", "out_of_view", "occluded", "no_data"
# the static-world test's verdict on a track (``drift_test``)
STATIC, FOLLOWS, UNDECIDED = "static", "follows", "undecided"
TENTATIVE, CONFIRMED, COASTING = "tentative", "confirmed", "coasting"
CHI2_3_999 = 16.266                  # 3-dof chi-square, 99.9 %
CHI2_3_99 = 11.345                   # 3-dof chi-square, 99 %
CHI2_6_99 = 16.812                   # 6-dof chi-square, 99 %


def _positive(name, v, allow_zero=False):
    ok = isinstance(v, (int, float)) and not isinstance(v, bool) and math.isfinite(v) and (v >= 0 if allow_zero
                                                                                           else v > 0)
    if not ok:
        raise InputError(f"tracker config: {name} must be a finite number {'>= 0' if allow_zero else '> 0'}, "
                         f"got {v!r}")


@dataclass(frozen=True)
class TrackerConfig:
    accel_sigma_mps2: float = 1.0          # white-noise acceleration of the constant-velocity model
    initial_speed_sigma_mps: float = 10.0  # velocity 1-sigma of a new track (velocity starts at 0)
    gate_chi2: float = CHI2_3_999          # association gate on d^2 (3 dof)
    confirm_hits: int = 3                  # N: hits that confirm a tentative track
    confirm_window_s: float = 1.0          # a tentative track not confirmed this long after birth dies (one the
                                           # static-world test is still deciding: up to follow_window_s, and it
                                           # outlives a single miss; one without a fit yet outlives a single miss)
    max_misses: int = 6                    # M: consecutive in-view misses that delete a confirmed track
    max_coast_s: float = 5.0               # no hit this long (coasting out of view or occluded): deleted
    max_position_sigma_m: float = 25.0     # largest position 1-sigma (any axis) a track may reach
    confidence_window: int = 10            # confidence = hits / in-view maps over this many last in-view maps
    moving_chi2: float = CHI2_3_99         # v^T P_v^-1 v above this: the track is moving
    extent_smoothing: float = 0.3          # weight of a new measurement's extent (exponential average)
    # measurement model (module docstring)
    pixel_sigma_px: float = 1.0            # frame pixels
    extent_fraction: float = 0.15          # of the box's pixel width / height (across) and depth (along)
    attitude_sigma_rad: float = math.radians(0.2)
    nav_sigma_m: float = 0.2
    min_range_rel_sigma: float = 0.002     # floor of the range 1-sigma, relative to range
    merge_gap_m: float = 0.5               # obstacles of one list whose boxes come this close are one (0: off)
    see_through_k: float = 0.0             # a measurement farther than a confirmed track along its ray by more
                                           # than this many of the track's sigma saw past it: bearing only (0: off)
    duplicate_chi2: float = 0.0            # two confirmed tracks this close in position and velocity (d^2 of
                                           # their state difference, 6 dof; CHI2_6_99): one, the older id kept (0: off)
    # static-world test (module docstring, "Phantoms that follow the vehicle"; off without a FieldOfView)
    follow_k: float = 3.0                  # sigma of the drift test (0: off)
    follow_fraction: float = 0.6           # drift along the vehicle's velocity above this fraction of its speed:
                                           # the track follows the vehicle (ground ranged at a near-constant range)
    follow_min_hits: int = 5               # detections the drift fit needs before it decides
    follow_window_s: float = 1.5           # the detections of this last stretch of time are fitted
    follow_rel_scatter: float = 0.01       # floor of the fit's position scatter, relative to the distance
    follow_min_speed_mps: float = 2.0      # the vehicle slower than this: nothing drifts, the test passes
    # visibility
    edge_margin_px: float = 1.0            # map pixels: a track projected this close to the edge is out of view
    occlusion_rel: float = 0.08            # nearer than (1 - this) x_c (and 3 sigma, and the depth extent): the
                                           # range jump that separates two objects (ObstacleConfig.max_rel_jump)
    occlusion_window_px: int = 1           # half-size of the map window looked at around the projected pixel

    def __post_init__(self):
        for name in ("accel_sigma_mps2", "initial_speed_sigma_mps", "gate_chi2", "confirm_window_s", "max_coast_s",
                     "max_position_sigma_m", "moving_chi2", "pixel_sigma_px", "occlusion_rel"):
            _positive(name, getattr(self, name))
        for name in ("extent_fraction", "attitude_sigma_rad", "nav_sigma_m", "min_range_rel_sigma",
                     "edge_margin_px", "merge_gap_m"):
            _positive(name, getattr(self, name), allow_zero=True)
        for name in ("see_through_k", "duplicate_chi2", "follow_k", "follow_fraction", "follow_rel_scatter",
                     "follow_min_speed_mps"):
            _positive(name, getattr(self, name), allow_zero=True)
        _positive("follow_window_s", self.follow_window_s)
        if not (isinstance(self.follow_min_hits, int) and not isinstance(self.follow_min_hits, bool)
                and self.follow_min_hits >= 3):
            raise InputError(f"tracker config: follow_min_hits must be an integer >= 3 (a line and a scatter), "
                             f"got {self.follow_min_hits!r}")
        for name in ("confirm_hits", "max_misses", "confidence_window"):
            v = getattr(self, name)
            if not (isinstance(v, int) and not isinstance(v, bool) and v >= 1):
                raise InputError(f"tracker config: {name} must be an integer >= 1, got {v!r}")
        if not (isinstance(self.occlusion_window_px, int) and self.occlusion_window_px >= 0):
            raise InputError(f"tracker config: occlusion_window_px must be an integer >= 0, "
                             f"got {self.occlusion_window_px!r}")
        if not 0 < self.extent_smoothing <= 1:
            raise InputError(f"tracker config: extent_smoothing must be in (0, 1], got {self.extent_smoothing!r}")


def _vec(name, v, n=3):
    a = np.asarray(v, float)
    if a.shape != (n,) or not np.all(np.isfinite(a)):
        raise InputError(f"{name}: expected {n} finite numbers, got {np.asarray(v).tolist()!r}")
    return a


def _stamp(stamp_us, what="stamp_us") -> int:
    if isinstance(stamp_us, bool) or not isinstance(stamp_us, (int, np.integer)):
        raise InputError(f"{what}: expected integer microseconds, got {type(stamp_us).__name__} {stamp_us!r}")
    return int(stamp_us)


@dataclass
class Measurement:
    """One detected obstacle: its NED point with covariance, and what the detector said about it."""
    position_ned_m: np.ndarray
    cov_ned_m2: np.ndarray
    extent_ned_m: np.ndarray = field(default_factory=lambda: np.zeros(3))   # 5..95 % extent along N, E, D
    pixel_count: int = 0                    # supporting pixels (frame pixels)
    confidence: float = 1.0                 # the estimator's median confidence over those pixels
    camera_id: str = ""
    lens_ned_m: np.ndarray | None = None    # the camera's lens centre (the ray's origin); None: no see-through test
    extent_noise_ned_m: np.ndarray = field(default_factory=lambda: np.zeros(3))   # what range noise spreads the
                                            # points over (5..95 %, per axis; range_noise_extent)

    def __post_init__(self):
        self.position_ned_m = _vec("measurement position_ned_m", self.position_ned_m)
        if self.lens_ned_m is not None:
            self.lens_ned_m = _vec("measurement lens_ned_m", self.lens_ned_m)
            if not np.linalg.norm(self.position_ned_m - self.lens_ned_m) > 0:
                raise InputError("measurement lens_ned_m: must differ from position_ned_m (the ray's origin)")
        self.extent_ned_m = _vec("measurement extent_ned_m", self.extent_ned_m)
        self.extent_noise_ned_m = _vec("measurement extent_noise_ned_m", self.extent_noise_ned_m)
        if np.any(self.extent_noise_ned_m < 0):
            raise InputError("measurement extent_noise_ned_m: must be >= 0")
        c = np.asarray(self.cov_ned_m2, float)
        # symmetric as np.allclose(c, c.T, rtol=1e-9, atol=1e-12) would say, without its per-call overhead
        if c.shape != (3, 3) or not np.isfinite(c).all() or not (np.abs(c - c.T) <= 1e-12 + 1e-9 * np.abs(c.T)).all():
            raise InputError("measurement cov_ned_m2: expected a finite symmetric 3 x 3 matrix")
        if np.linalg.eigvalsh(c).min() <= 0:
            raise InputError("measurement cov_ned_m2: must be positive definite")
        self.cov_ned_m2 = 0.5 * (c + c.T)
        if np.any(self.extent_ned_m < 0):
            raise InputError("measurement extent_ned_m: must be >= 0")

    @property
    def object_extent_ned_m(self) -> np.ndarray:
        """The extent with the range noise taken out in quadrature (``range_noise_extent``): what the track keeps."""
        e, n = self.extent_ned_m, self.extent_noise_ned_m
        return np.sqrt(np.maximum(e * e - n * n, 0.0))


def merge_fragments(measurements, gap_m: float) -> list:
    """Measurements whose extent boxes (position +- extent / 2, NED) come within ``gap_m`` of each other on every
    axis, directly or through others, become one: the union box, the pixel-weighted mean position, the weighted mean
    covariance plus the weighted spread of the positions, the summed pixels. The obstacle list splits a thin pole or a
    mast into pieces at its range noise; one object, one track."""
    meas = list(measurements)
    if gap_m <= 0 or len(meas) < 2:
        return meas
    p = np.stack([m.position_ned_m for m in meas])
    half = 0.5 * np.stack([m.extent_ned_m for m in meas])
    lo, hi = p - half, p + half
    touch = np.all((lo[:, None] <= hi[None] + gap_m) & (lo[None] <= hi[:, None] + gap_m), axis=-1)
    n, labels = _components_of(touch)
    if n == len(meas):
        return meas
    out = []
    for k in range(n):
        idx = np.flatnonzero(labels == k)
        if idx.size == 1:
            out.append(meas[idx[0]])
            continue
        w = np.array([max(meas[i].pixel_count, 1) for i in idx], float)
        w /= w.sum()
        pos = w @ p[idx]
        d = p[idx] - pos
        cov = np.einsum("i,ijk->jk", w, np.stack([meas[i].cov_ned_m2 for i in idx])) + (d * w[:, None]).T @ d
        ext = _mixture_extent(lo[idx], hi[idx], w)
        ohalf = 0.5 * np.stack([meas[i].object_extent_ned_m for i in idx])
        obj = _mixture_extent(p[idx] - ohalf, p[idx] + ohalf, w)
        out.append(Measurement(pos, cov, ext, int(sum(meas[i].pixel_count for i in idx)),
                               float(w @ [meas[i].confidence for i in idx]), meas[idx[0]].camera_id,
                               meas[idx[0]].lens_ned_m, np.sqrt(np.maximum(ext * ext - obj * obj, 0.0))))
    return out


def _mixture_extent(lo: np.ndarray, hi: np.ndarray, w: np.ndarray) -> np.ndarray:
    """Per axis, the 5..95 % span of the points of several fragments of one obstacle, each fragment's points spread
    evenly with weight w (its share of the pixels) so that its own 5..95 % span is its box [lo, hi]: the merged
    obstacle's extent in the sense of a single one's (a 12-pixel speck beside a 3000-pixel wall does not stretch it
    as the union of their boxes would; one fragment alone gives its own box). Exact: the mixture's distribution is
    piecewise linear between the ends of the fragments' supports."""
    pad = (hi - lo) / 18.0                                   # 5 % of a uniform support beyond each end of [lo, hi]
    a, b = lo - pad, np.maximum(hi + pad, lo - pad + 1e-9)
    w = np.asarray(w, float) / float(np.sum(w))
    out = np.empty(3)
    for ax in range(3):
        x = np.unique(np.concatenate([a[:, ax], b[:, ax]]))
        cdf = np.clip((x[:, None] - a[None, :, ax]) / (b - a)[None, :, ax], 0.0, 1.0) @ w
        q = []
        for level in (0.05, 0.95):
            k = int(np.searchsorted(cdf, level))
            k = min(max(k, 1), x.size - 1)
            f = (level - cdf[k - 1]) / (cdf[k] - cdf[k - 1]) if cdf[k] > cdf[k - 1] else 0.0
            q.append(x[k - 1] + f * (x[k] - x[k - 1]))
        out[ax] = q[1] - q[0]
    return out


def _components_of(touch: np.ndarray) -> tuple:
    """(count, label per node) of the connected components of a small symmetric adjacency matrix, numbered in the
    order of their lowest node (as scipy.sparse.csgraph.connected_components, without its sparse-graph set-up,
    which costs more than the search on the few obstacles of one list)."""
    labels = np.full(len(touch), -1, np.int64)
    n = 0
    for start in range(len(touch)):
        if labels[start] >= 0:
            continue
        labels[start] = n
        todo = [start]
        while todo:
            for j in np.flatnonzero(touch[todo.pop()] & (labels < 0)):
                labels[j] = n
                todo.append(j)
        n += 1
    return n, labels


def R_ned_cam(camera: Camera, state: VehicleState) -> np.ndarray:
    """Rotation camera -> NED: T2^T T1^T (eq. 33)."""
    return state.T_body_ned.T @ camera.T_cam_body.T


def lens_ned_m(camera: Camera, state: VehicleState) -> np.ndarray:
    """NED position of the lens centre: x_v + T2^T l (eq. 33 at x_c = 0)."""
    return state.position_ned_m + state.T_body_ned.T @ camera.l_body_m


def camera_covariance(point_ned_m, camera: Camera, state: VehicleState, sigma_range_m: float, sigma_u_px: float,
                      sigma_v_px: float) -> np.ndarray:
    """NED covariance of a point seen by ``camera`` at ``state`` with 1-sigma errors in range x_c (metres) and in its
    pixel (u, v) (pixels of ``camera``): J diag(s_x^2, s_u^2, s_v^2) J^T rotated into NED (module docstring)."""
    p_cam = camera_from_ned(np.asarray(point_ned_m, float), camera.T_cam_body, state.T_body_ned,
                            state.position_ned_m, camera.l_body_m)
    x_c = float(p_cam[0])
    if not x_c > 0:
        raise InputError(f"camera_covariance: point is behind the camera (x_c = {x_c:.3f} m)")
    a, b = p_cam[1] / x_c, p_cam[2] / x_c
    J = np.array([[1.0, 0.0, 0.0], [a, x_c / camera.fx, 0.0], [b, 0.0, x_c / camera.fy]])
    cov_cam = J @ np.diag([sigma_range_m ** 2, sigma_u_px ** 2, sigma_v_px ** 2]) @ J.T
    R = R_ned_cam(camera, state)
    return R @ cov_cam @ R.T


SPAN_5_95 = 3.29                     # the 5..95 % span of a normal distribution, in sigma


def range_noise_extent(ray_ned_per_m, sigma_range_m: float) -> np.ndarray:
    """Per NED axis, the 5..95 % span over which a per-pixel range 1-sigma ``sigma_range_m`` spreads the points of a
    flat face: a range error dx_c moves a point by dx_c ``ray_ned_per_m`` (the ray per metre of x_c, [1, a, b] of
    eqs. 8-9 rotated into NED), and 5..95 % of a normal distribution spans 3.29 sigma. Seen head-on, a face's points
    spread along the ray by this alone; the box centred on their median point would stand half of it in front of
    the face (and make the time to contact early). ``Measurement.object_extent_ned_m`` takes it out in quadrature:
    sqrt(max(e^2 - n^2, 0)) per axis."""
    return SPAN_5_95 * max(float(sigma_range_m), 0.0) * np.abs(np.asarray(ray_ned_per_m, float))


def measurements_from_obstacles(obstacles, camera: Camera, state: VehicleState, cfg: TrackerConfig = TrackerConfig(),
                                frame_size=None, camera_id: str = "") -> list:
    """``Measurement`` of each ``eonav.obstacles.Obstacle`` of one range map, fragments of one object merged
    (``merge_fragments`` with ``cfg.merge_gap_m``). ``camera`` / ``state`` / ``frame_size`` are those given to
    ``analyse`` (the map's grid camera, the capture pose, the frame's (width, height) or None): ``bbox_px`` and the
    pixel sigma are in frame pixels."""
    fw, fh = (camera.width, camera.height) if not frame_size or not any(frame_size) else map(int, frame_size)
    fx, fy = camera.fx * fw / camera.width, camera.fy * fh / camera.height       # focal lengths in frame pixels
    R = R_ned_cam(camera, state)
    lens = lens_ned_m(camera, state)
    out = []
    for o in obstacles:
        p = _vec(f"obstacle {o.id} position_ned_m", o.position_ned_m)
        ext = np.abs(_vec(f"obstacle {o.id} extent_ned_m", o.extent_ned_m))
        p_cam = camera_from_ned(p, camera.T_cam_body, state.T_body_ned, state.position_ned_m, camera.l_body_m)
        x_c = float(p_cam[0])
        if not x_c > 0:
            continue                                  # cannot happen for a point of this map; nothing to track
        s_pix = float(o.range_std_m) if math.isfinite(o.range_std_m) else 0.0
        s_noise = float(o.range_noise_std_m)
        noise = range_noise_extent(R @ (p_cam / x_c), s_noise if math.isfinite(s_noise) else s_pix)
        # 15 % of the raw depth spread, range noise included, as before the noise was taken out of the extent:
        # the measurement sigma (and so the association) is unchanged (docs/guidance.md, head-on)
        depth_ext = float(np.linalg.norm(R[:, 0] * ext))
        s_range = math.hypot(s_pix, cfg.extent_fraction * depth_ext)
        s_range = max(s_range, cfg.min_range_rel_sigma * x_c)
        u0, v0, u1, v1 = o.bbox_px
        s_u = math.sqrt(cfg.pixel_sigma_px ** 2 + (cfg.extent_fraction * (u1 - u0 + 1)) ** 2
                        + (cfg.attitude_sigma_rad * fx) ** 2)
        s_v = math.sqrt(cfg.pixel_sigma_px ** 2 + (cfg.extent_fraction * (v1 - v0 + 1)) ** 2
                        + (cfg.attitude_sigma_rad * fy) ** 2)
        # camera_covariance takes pixels of ``camera``: convert the frame-pixel sigmas
        cov = camera_covariance(p, camera, state, s_range, s_u * camera.width / fw, s_v * camera.height / fh)
        cov = cov + cfg.nav_sigma_m ** 2 * np.eye(3)
        out.append(Measurement(p, cov, ext, int(o.pixel_count), float(o.confidence), camera_id, lens, noise))
    return merge_fragments(out, cfg.merge_gap_m)


@dataclass
class FieldOfView:
    """What one range map could see: its camera (the map's grid), capture pose, the listed distance band and,
    optionally, the map itself (``range_m`` with ``data_mask`` = pixels with a usable range: confident or at
    infinity) to tell an occluded or unmeasured track from a missed one."""
    camera: Camera
    state: VehicleState
    max_distance_m: float = math.inf
    min_distance_m: float = 0.0
    range_m: np.ndarray | None = None
    data_mask: np.ndarray | None = None
    velocity_ned_mps: np.ndarray | None = None     # the vehicle's; None: the tracker differences the views' poses

    def __post_init__(self):
        if self.velocity_ned_mps is not None:
            self.velocity_ned_mps = _vec("field of view velocity_ned_mps", self.velocity_ned_mps)
        if self.range_m is not None:
            r = np.asarray(self.range_m)
            if r.shape != (self.camera.height, self.camera.width):
                raise InputError(f"field of view: range_m is {r.shape} but camera {self.camera.name!r} is "
                                 f"{self.camera.height} x {self.camera.width}")
            if self.data_mask is not None and np.shape(self.data_mask) != r.shape:
                raise InputError(f"field of view: data_mask has shape {np.shape(self.data_mask)}, expected {r.shape}")

    def classify(self, position_ned_m, sigma_range_m: float = 0.0, depth_extent_m: float = 0.0,
                 cfg: TrackerConfig = TrackerConfig()) -> str:
        """VISIBLE, OUT_OF_VIEW, OCCLUDED or NO_DATA for one NED point."""
        cam, st = self.camera, self.state
        p = np.asarray(position_ned_m, float)
        dist = float(np.linalg.norm(p - st.position_ned_m))
        if not self.min_distance_m <= dist <= self.max_distance_m:
            return OUT_OF_VIEW
        pc = camera_from_ned(p, cam.T_cam_body, st.T_body_ned, st.position_ned_m, cam.l_body_m)
        if pc[0] <= 0:
            return OUT_OF_VIEW
        u = cam.cx + cam.fx * pc[1] / pc[0]                     # eq. (8)
        v = cam.cy + cam.fy * pc[2] / pc[0]                     # eq. (9)
        m = cfg.edge_margin_px
        if not (m - 0.5 <= u <= cam.width - 0.5 - m and m - 0.5 <= v <= cam.height - 0.5 - m):
            return OUT_OF_VIEW
        if self.range_m is None:
            return VISIBLE
        k = cfg.occlusion_window_px
        iu, iv = int(round(u)), int(round(v))
        u0, u1 = max(0, iu - k), min(cam.width, iu + k + 1)
        v0, v1 = max(0, iv - k), min(cam.height, iv + k + 1)
        r = np.asarray(self.range_m[v0:v1, u0:u1], float)
        if self.data_mask is not None:
            ok = np.asarray(self.data_mask[v0:v1, u0:u1], bool)
        else:
            with np.errstate(invalid="ignore"):
                ok = np.isposinf(r) | (np.isfinite(r) & (r > 0))
        if not ok.any():
            return NO_DATA
        seen = float(np.median(r[ok]))
        margin = max(cfg.occlusion_rel * pc[0], 3.0 * sigma_range_m, depth_extent_m)
        return OCCLUDED if seen < pc[0] - margin else VISIBLE


_I6 = np.eye(6)
_DIAG3 = (np.arange(3), np.arange(3))


def _F(dt):
    F = _I6.copy()
    F[_DIAG3[0], _DIAG3[1] + 3] = dt
    return F


def _Q(dt, q):
    """q [[dt^3/3 I, dt^2/2 I], [dt^2/2 I, dt I]], filled in place (np.block costs more than the filter step)."""
    Q = np.zeros((6, 6))
    i = _DIAG3[0]
    Q[i, i] = q * (dt ** 3 / 3)
    Q[i, i + 3] = Q[i + 3, i] = q * (dt ** 2 / 2)
    Q[i + 3, i + 3] = q * dt
    return Q


def predict_state(x, P, dt_s: float, cfg: TrackerConfig):
    """Constant-velocity prediction over dt_s >= 0 seconds."""
    F = _F(dt_s)
    return F @ x, F @ P @ F.T + _Q(dt_s, cfg.accel_sigma_mps2 ** 2)


def drift_test(stamps_us, positions_ned_m, distances_m, own_velocity_ned_mps, cfg: TrackerConfig) -> tuple:
    """The static-world test of one track: (verdict, drift, its 1-sigma), the drift in m/s along the vehicle's
    velocity. A line a + b t fitted by least squares to the detections' positions along the vehicle's velocity
    direction gives the drift b; its 1-sigma is s / sqrt(sum (t - mean t)^2), s the fit's own residual scatter
    (n - 2 degrees of freedom), at least ``follow_rel_scatter`` of the median distance. FOLLOWS when b exceeds
    ``follow_fraction`` of the vehicle's speed by k_t sigma, STATIC when it stays below it by as much, UNDECIDED in
    between or with fewer than ``follow_min_hits`` detections; k_t is the Student-t quantile (n - 2 degrees of
    freedom) of the normal's one-sided level at ``follow_k`` (the scatter is estimated from the same few points: a
    small one by chance must not pass a phantom). STATIC when the test is off (``follow_k`` 0) or the vehicle moves
    slower than ``follow_min_speed_mps``."""
    v = np.asarray(own_velocity_ned_mps, float).reshape(3)
    speed = float(np.linalg.norm(v))
    if cfg.follow_k <= 0 or not math.isfinite(speed) or speed < cfg.follow_min_speed_mps:
        return STATIC, math.nan, math.nan
    n = len(stamps_us)
    if n < cfg.follow_min_hits:
        return UNDECIDED, math.nan, math.nan
    t = (np.asarray(stamps_us, np.int64) - int(stamps_us[-1])) * 1e-6
    a = np.asarray(positions_ned_m, float) @ (v / speed)
    tc = t - t.mean()
    stt = float(tc @ tc)
    if not stt > 0:
        return UNDECIDED, math.nan, math.nan
    ac = a - a.mean()
    b = float(tc @ ac) / stt
    res = ac - b * tc
    s = max(math.sqrt(float(res @ res) / (n - 2)), cfg.follow_rel_scatter * float(np.median(distances_m)))
    sb = s / math.sqrt(stt)
    thr = cfg.follow_fraction * speed
    k = student_k(cfg.follow_k, n - 2)
    if b - k * sb > thr:
        return FOLLOWS, b, sb
    if b + k * sb < thr:
        return STATIC, b, sb
    return UNDECIDED, b, sb


def still_deciding(verdict: str, drift_mps: float, age_s: float, speed_mps: float, cfg: TrackerConfig) -> bool:
    """Whether the static-world test is still deciding a tentative track, which then outlives ``confirm_window_s``
    and a single miss: its verdict UNDECIDED, its drift estimate inside the static band (|drift| below
    ``follow_fraction`` of the vehicle's speed: more detections could still make it STATIC) and its age within the
    test's own window, ``follow_window_s``. At 100 m the fused maps scatter a static obstacle's detections by 3-4 m,
    and a fit over 1 s cannot tell a drift of 0 from 0.6 of 20 m/s at 3 sigma; a thin object is missed in single
    maps. Killed at 1 s or at a miss, the track restarts its fit from nothing (docs/guidance.md, "Confirmation on
    fused maps")."""
    if verdict != UNDECIDED or not (math.isfinite(drift_mps) and math.isfinite(speed_mps)):
        return False
    return age_s <= cfg.follow_window_s and abs(drift_mps) < cfg.follow_fraction * speed_mps


def awaiting_fit(verdict: str, n_detections: int, cfg: TrackerConfig) -> bool:
    """Whether the static-world test has not had the detections it needs yet: the verdict UNDECIDED with fewer than
    ``follow_min_hits`` detections in the track's window (no drift fitted; a STATIC verdict without a fit is the test
    being off or the vehicle at rest). Such a tentative track outlives a single miss in which no measurement fell
    inside its gate (the list lost the object in that map), as one ``still_deciding`` does, but not
    ``confirm_window_s``; a miss whose measurement went to another track (a duplicate beside an older track) still
    kills it. The fused maps lose a far obstacle in single maps before its fifth detection (the van of the approach
    flight at 95 m, seed 1: four detections, one map without it, and its next track confirmed 0.33 s later than the
    first would have been; docs/guidance.md, "The van's confirmation")."""
    return verdict == UNDECIDED and n_detections < cfg.follow_min_hits


@lru_cache(maxsize=256)
def student_k(k_normal: float, dof: int) -> float:
    """The Student-t quantile with ``dof`` degrees of freedom at the normal distribution's one-sided level of
    ``k_normal`` sigma (k = 2: 97.7 %; 3 degrees of freedom: 3.31, 13: 2.21)."""
    return float(student_t.ppf(norm.cdf(k_normal), dof))


@dataclass
class Track:
    """One tracked obstacle. ``x`` = [position_ned_m, velocity_ned_mps] and ``P`` at ``stamp_us``."""
    id: int
    x: np.ndarray
    P: np.ndarray
    stamp_us: int
    born_us: int
    last_hit_us: int
    hits: int = 1
    misses: int = 0                        # consecutive in-view misses
    confirmed: bool = False
    last_outcome: str = "hit"              # hit, or the visibility of the last map that did not detect it
    miss_taken: bool = False               # its last miss: a measurement inside its gate was paired with another track
    extent_ned_m: np.ndarray = field(default_factory=lambda: np.zeros(3))
    pixel_count: int = 0
    measurement_confidence: float = 0.0
    camera_id: str = ""
    seen: deque = field(default_factory=deque)      # True/False per in-view map (newest last)
    detections: deque = field(default_factory=deque)   # (stamp_us, position_ned_m, distance_m) of the last
                                                       # ``follow_window_s`` of detections (the drift test's input)
    verdict: str = UNDECIDED                        # the static-world test's, after the last detection
    drift_mps: float = math.nan                     # the fitted drift along the vehicle's velocity, and its 1-sigma
    drift_sigma_mps: float = math.nan

    @property
    def state(self) -> str:
        if not self.confirmed:
            return TENTATIVE
        return COASTING if self.last_outcome in (OUT_OF_VIEW, OCCLUDED, NO_DATA) else CONFIRMED

    @property
    def confidence(self) -> float:
        """Fraction of the last ``confidence_window`` in-view maps in which it was detected."""
        return float(np.mean(self.seen)) if self.seen else 0.0

    def position_sigma_m(self) -> float:
        return float(math.sqrt(max(np.diag(self.P)[:3].max(), 0.0)))


class Tracker:
    """Kalman tracks of obstacles across range maps (module docstring). Feed every range map, also those without
    obstacles, in stamp order: ``update(measurements, stamp_us, view)``."""

    def __init__(self, cfg: TrackerConfig = TrackerConfig()):
        self.cfg = cfg
        self._tracks: list[Track] = []
        self._next_id = 1
        self.last_stamp_us: int | None = None      # stamp of the newest map fed in
        self._last_view: tuple | None = None       # (stamp_us, vehicle position, velocity) of the newest view
        self._own = (None, None)                   # (vehicle velocity or None, vehicle position or None) now
        self.n_followers = 0                       # tracks deleted because they followed the vehicle (FOLLOWS)
        self.n_followers_confirmed = 0             # ... of them confirmed before

    @property
    def tracks(self) -> list:
        return list(self._tracks)

    def confirmed(self) -> list:
        return [t for t in self._tracks if t.confirmed]

    def update(self, measurements, stamp_us: int, view: FieldOfView | None = None) -> list:
        """One range map's measurements at capture ``stamp_us``. ``view`` (None: every unpaired track counts as a
        miss) says which unpaired tracks the map could have seen. Returns the tracks after the update."""
        stamp_us = _stamp(stamp_us)
        if self.last_stamp_us is not None and stamp_us < self.last_stamp_us:
            raise InputError(f"tracker: map stamp {stamp_us} us is older than the last one {self.last_stamp_us} us; "
                             f"feed maps in stamp order")
        meas = list(measurements)
        for m in meas:
            if not isinstance(m, Measurement):
                raise InputError(f"tracker: expected Measurement objects, got {type(m).__name__}")
        cfg = self.cfg
        self._own = self._own_motion(view, stamp_us)
        for t in self._tracks:
            t.x, t.P = predict_state(t.x, t.P, (stamp_us - t.stamp_us) * 1e-6, cfg)
            t.stamp_us = stamp_us
        pairs, gated = self._associate(meas)
        paired_t = {i for i, _, _ in pairs}
        paired_m = {j for _, j, _ in pairs}
        for i, j, R in pairs:
            self._correct(self._tracks[i], meas[j], stamp_us, R)
        for i, t in enumerate(self._tracks):
            if i in paired_t:
                continue
            outcome = VISIBLE if view is None else self._visibility(t, view)
            if outcome == VISIBLE:
                t.misses += 1
                t.last_outcome = "miss"
                t.miss_taken = i in gated             # a measurement in its gate went to another track
                self._seen(t, False)
            else:
                t.last_outcome = outcome
        dead = [t for t in self._tracks if self._dead(t, stamp_us)]
        self.n_followers += sum(1 for t in dead if t.verdict == FOLLOWS)
        self.n_followers_confirmed += sum(1 for t in dead if t.verdict == FOLLOWS and t.confirmed)
        gone = {t.id for t in dead}
        self._tracks = [t for t in self._tracks if t.id not in gone]
        self._merge_duplicates()
        for j, m in enumerate(meas):
            if j not in paired_m:
                self._tracks.append(self._new_track(m, stamp_us))
        self.last_stamp_us = stamp_us
        return self.tracks

    def _own_motion(self, view: FieldOfView | None, stamp_us: int) -> tuple:
        """(the vehicle's velocity, its position) at this map: the view's velocity, else the difference of the
        vehicle positions of this view and the last one (a map of the same stamp, another camera's: the velocity
        found before); None where not known (no view, the first map)."""
        if view is None:
            self._last_view = None
            return None, None
        pos = np.asarray(view.state.position_ned_m, float)
        vel = view.velocity_ned_mps
        if vel is None and self._last_view is not None:
            last_us, last_pos, last_vel = self._last_view
            vel = (pos - last_pos) / ((stamp_us - last_us) * 1e-6) if stamp_us > last_us else last_vel
        self._last_view = (stamp_us, pos, vel)
        return vel, pos

    def _judge(self, t: Track, m: Measurement, stamp_us: int) -> None:
        """Add the detection to the track's window and run the static-world test on it (``drift_test``)."""
        vel, pos = self._own
        dist = float(np.linalg.norm(m.position_ned_m - pos)) if pos is not None else 0.0
        t.detections.append((stamp_us, m.position_ned_m.copy(), dist))
        while t.detections and stamp_us - t.detections[0][0] > self.cfg.follow_window_s * 1e6:
            t.detections.popleft()
        if vel is None:
            t.verdict, t.drift_mps, t.drift_sigma_mps = STATIC, math.nan, math.nan
            return
        st = np.array([d[0] for d in t.detections])
        t.verdict, t.drift_mps, t.drift_sigma_mps = drift_test(st, np.stack([d[1] for d in t.detections]),
                                                               np.array([d[2] for d in t.detections]), vel, self.cfg)

    def label(self, measurements) -> list:
        """The id of the live track each measurement supports (inside its gate, nearest by Mahalanobis distance),
        0 where none does: the stable id an obstacle list's detections carry after ``update``."""
        meas = list(measurements)
        if not meas or not self._tracks:
            return [0] * len(meas)
        xs = np.stack([t.x[:3] for t in self._tracks])                     # (nt, 3)
        Ps = np.stack([t.P[:3, :3] for t in self._tracks])                 # (nt, 3, 3)
        zs = np.stack([m.position_ned_m for m in meas])                    # (nm, 3)
        Rs = np.stack([m.cov_ned_m2 for m in meas])                        # (nm, 3, 3)
        y = zs[:, None] - xs[None]                                         # (nm, nt, 3)
        d2 = np.einsum("ijk,ijk->ij", y, np.linalg.solve(Rs[:, None] + Ps[None], y[..., None])[..., 0])
        ids = np.array([t.id for t in self._tracks])
        out = []
        for row in d2:
            inside = np.flatnonzero(row <= self.cfg.gate_chi2)
            # the nearest; of equal distances the last track (as a scan keeping every d2 <= the best so far)
            out.append(int(ids[inside[::-1][np.argmin(row[inside][::-1])]]) if inside.size else 0)
        return out

    def _associate(self, meas) -> tuple:
        """([(track index, measurement index, the measurement's covariance for that pair)], the indices of the tracks
        with a measurement inside their gate)."""
        if not self._tracks or not meas:
            return [], set()
        xs = np.stack([t.x[:3] for t in self._tracks])                     # (nt, 3)
        Ps = np.stack([t.P[:3, :3] for t in self._tracks])                 # (nt, 3, 3)
        zs = np.stack([m.position_ned_m for m in meas])                    # (nm, 3)
        Rs = np.broadcast_to(np.stack([m.cov_ned_m2 for m in meas])[None], (len(xs), len(meas), 3, 3))
        Rs = self._see_through(Rs, xs, Ps, zs, meas)                       # (nt, nm, 3, 3)
        S = Ps[:, None] + Rs                                               # (nt, nm, 3, 3)
        y = zs[None] - xs[:, None]                                         # (nt, nm, 3)
        d2 = np.einsum("ijk,ijk->ij", y, np.linalg.solve(S, y[..., None])[..., 0])
        cost = d2 + np.linalg.slogdet(S)[1]
        inside = d2 <= self.cfg.gate_chi2
        big = 1e6 + np.abs(cost[inside]).max() if inside.any() else 1e6
        rows, cols = linear_sum_assignment(np.where(inside, cost, big))
        return ([(int(i), int(j), Rs[i, j]) for i, j in zip(rows, cols) if inside[i, j]],
                {int(i) for i in np.flatnonzero(inside.any(axis=1))})

    def _see_through(self, Rs, xs, Ps, zs, meas) -> np.ndarray:
        """The measurement covariance per (track, measurement) pair. A measurement that lies farther than a
        confirmed track along its own ray by e > ``see_through_k`` sigma (the track's position sigma along that ray)
        saw past the object (a matching window wider than a thin object ranges its background; the map's own sigma
        does not cover that): its range says nothing of the track, its bearing still does, so its variance along
        the ray grows by (k e)^2. Nearer measurements are used as they are (the conservative side)."""
        k = self.cfg.see_through_k
        has_lens = np.array([m.lens_ned_m is not None for m in meas])
        confirmed = np.array([t.confirmed for t in self._tracks])
        if k <= 0 or not has_lens.any() or not confirmed.any():
            return Rs
        lens = np.stack([m.lens_ned_m if m.lens_ned_m is not None else m.position_ned_m - np.array([1.0, 0.0, 0.0])
                         for m in meas])
        los = zs - lens
        los /= np.linalg.norm(los, axis=1, keepdims=True)                  # (nm, 3) unit rays
        excess = np.einsum("jk,ijk->ij", los, zs[None] - xs[:, None])      # (nt, nm) > 0: measurement farther
        var = np.einsum("jk,ikl,jl->ij", los, Ps, los)                     # the track's variance along the ray
        far = (excess > k * np.sqrt(var)) & confirmed[:, None] & has_lens[None]
        if not far.any():
            return Rs
        grow = np.where(far, (k * excess) ** 2, 0.0)
        return Rs + grow[..., None, None] * np.einsum("jk,jl->jkl", los, los)[None]

    def _merge_duplicates(self) -> None:
        """Two confirmed tracks whose states differ by d^2 = dx^T (P_a + P_b)^-1 dx <= ``duplicate_chi2`` (6 dof:
        position and velocity) are one object seen twice (a re-born track beside the one it replaces, fragments the
        list did not merge): one track stays, under the older id, with the state of the better-measured of the two
        (smaller position covariance) and the newer of their detections."""
        if self.cfg.duplicate_chi2 <= 0:
            return
        conf = [t for t in self._tracks if t.confirmed]        # birth order: the older first
        gone = set()
        for n, a in enumerate(conf):
            if a.id in gone:
                continue
            for b in conf[n + 1:]:
                if b.id in gone:
                    continue
                dx = b.x - a.x
                try:
                    d2 = float(dx @ np.linalg.solve(a.P + b.P, dx))
                except np.linalg.LinAlgError:
                    continue
                if d2 > self.cfg.duplicate_chi2:
                    continue
                if np.trace(b.P[:3, :3]) < np.trace(a.P[:3, :3]):
                    a.x, a.P, a.extent_ned_m = b.x.copy(), b.P.copy(), b.extent_ned_m.copy()
                if b.last_hit_us > a.last_hit_us:
                    a.last_hit_us, a.misses, a.last_outcome = b.last_hit_us, b.misses, b.last_outcome
                    a.pixel_count, a.measurement_confidence, a.camera_id = (b.pixel_count, b.measurement_confidence,
                                                                            b.camera_id)
                a.hits = max(a.hits, b.hits)
                gone.add(b.id)
        if gone:
            self._tracks = [t for t in self._tracks if t.id not in gone]

    def _correct(self, t: Track, m: Measurement, stamp_us: int, R: np.ndarray | None = None) -> None:
        cfg = self.cfg
        R = m.cov_ned_m2 if R is None else R
        H = np.hstack([np.eye(3), np.zeros((3, 3))])
        S = t.P[:3, :3] + R
        K = t.P[:, :3] @ np.linalg.inv(S)
        t.x = t.x + K @ (m.position_ned_m - t.x[:3])
        IKH = np.eye(6) - K @ H
        t.P = IKH @ t.P @ IKH.T + K @ R @ K.T                          # Joseph form: stays symmetric, PSD
        t.P = 0.5 * (t.P + t.P.T)
        t.hits += 1
        t.misses = 0
        t.last_hit_us = stamp_us
        t.last_outcome = "hit"
        a = cfg.extent_smoothing
        t.extent_ned_m = (1 - a) * t.extent_ned_m + a * m.object_extent_ned_m
        t.pixel_count, t.measurement_confidence, t.camera_id = m.pixel_count, m.confidence, m.camera_id
        self._seen(t, True)
        self._judge(t, m, stamp_us)
        if t.hits >= cfg.confirm_hits and t.verdict == STATIC:
            t.confirmed = True

    def _seen(self, t: Track, hit: bool) -> None:
        t.seen.append(bool(hit))
        while len(t.seen) > self.cfg.confidence_window:
            t.seen.popleft()

    def _visibility(self, t: Track, view: FieldOfView) -> str:
        cam, st = view.camera, view.state
        Xc = R_ned_cam(cam, st)[:, 0]                                     # optical axis in NED
        sigma = float(math.sqrt(max(Xc @ t.P[:3, :3] @ Xc, 0.0)))
        depth_ext = float(np.linalg.norm(Xc * t.extent_ned_m))
        return view.classify(t.x[:3], sigma, depth_ext, self.cfg)

    def _dead(self, t: Track, stamp_us: int) -> bool:
        cfg = self.cfg
        if t.position_sigma_m() > cfg.max_position_sigma_m:
            return True
        if t.verdict == FOLLOWS:
            return True                               # a phantom: ground ranged at a near-constant range ahead
        if (stamp_us - t.last_hit_us) * 1e-6 > cfg.max_coast_s:
            return True
        if not t.confirmed:
            age_s = (stamp_us - t.born_us) * 1e-6
            vel = self._own[0]
            speed = float(np.linalg.norm(vel)) if vel is not None else math.nan
            deciding = still_deciding(t.verdict, t.drift_mps, age_s, speed, cfg)
            waiting = awaiting_fit(t.verdict, len(t.detections), cfg) and not t.miss_taken
            return (t.misses >= (2 if deciding or waiting else 1)
                    or (age_s > cfg.confirm_window_s and not deciding))
        return t.misses >= cfg.max_misses

    def _new_track(self, m: Measurement, stamp_us: int) -> Track:
        cfg = self.cfg
        P = np.zeros((6, 6))
        P[:3, :3] = m.cov_ned_m2
        P[3:, 3:] = cfg.initial_speed_sigma_mps ** 2 * np.eye(3)
        t = Track(self._next_id, np.concatenate([m.position_ned_m, np.zeros(3)]), P, stamp_us, stamp_us, stamp_us,
                  extent_ned_m=m.object_extent_ned_m, pixel_count=m.pixel_count,
                  measurement_confidence=m.confidence, camera_id=m.camera_id)
        self._next_id += 1
        self._seen(t, True)
        self._judge(t, m, stamp_us)
        if cfg.confirm_hits <= 1 and t.verdict == STATIC:
            t.confirmed = True
        return t

    def snapshot(self, stamp_us: int) -> list:
        """(track, x, P) of every live track predicted to ``stamp_us`` (>= the last map's stamp), without changing
        the tracker; tracks that would have coasted past ``max_coast_s`` or ``max_position_sigma_m`` by then are
        left out (what a stalled pipeline reports)."""
        stamp_us = _stamp(stamp_us)
        out = []
        for t in self._tracks:
            dt = max(0, stamp_us - t.stamp_us) * 1e-6
            x, P = predict_state(t.x, t.P, dt, self.cfg)
            if (stamp_us - t.last_hit_us) * 1e-6 > self.cfg.max_coast_s:
                continue
            if math.sqrt(max(np.diag(P)[:3].max(), 0.0)) > self.cfg.max_position_sigma_m:
                continue
            out.append((t, x, P))
        return out


# ------------------------------------------------------------------------------------------------------------------
# guidance quantities

@dataclass(frozen=True)
class ConeConfig:
    vehicle_radius_m: float = 1.0     # the vehicle as a sphere of this radius about its origin
    k_sigma: float = 2.0              # the obstacle box grows by this many position 1-sigma per axis
    horizon_s: float = 30.0           # contacts later than this are not threats
    min_speed_mps: float = 0.1        # relative speed below this: no direction, only "already inside" counts

    def __post_init__(self):
        _positive("vehicle_radius_m", self.vehicle_radius_m, allow_zero=True)
        _positive("k_sigma", self.k_sigma, allow_zero=True)
        _positive("horizon_s", self.horizon_s)
        _positive("min_speed_mps", self.min_speed_mps)


@dataclass(frozen=True)
class Ownship:
    """The vehicle now: pose (body origin in NED, T2) and velocity (NaN: unknown) at ``stamp_us``."""
    position_ned_m: np.ndarray
    T_body_ned: np.ndarray
    velocity_ned_mps: np.ndarray
    stamp_us: int = -1

    def __post_init__(self):
        st = VehicleState(self.position_ned_m, self.T_body_ned)      # validates position and rotation
        v = np.asarray(self.velocity_ned_mps, float).reshape(3)
        object.__setattr__(self, "position_ned_m", st.position_ned_m)
        object.__setattr__(self, "T_body_ned", st.T_body_ned)
        object.__setattr__(self, "velocity_ned_mps", v)

    @classmethod
    def from_state(cls, state: VehicleState, velocity_ned_mps=(math.nan,) * 3, stamp_us: int = -1) -> "Ownship":
        return cls(state.position_ned_m, state.T_body_ned, velocity_ned_mps, stamp_us)

    @property
    def velocity_known(self) -> bool:
        return bool(np.all(np.isfinite(self.velocity_ned_mps)))


@dataclass
class TrackView:
    """One track as guidance sees it at one time: predicted state and its relation to the vehicle."""
    track: Track
    position_ned_m: np.ndarray
    velocity_ned_mps: np.ndarray
    P: np.ndarray
    age_s: float
    time_since_update_s: float
    moving: bool
    distance_m: float                 # vehicle origin -> track position
    surface_distance_m: float         # vehicle origin -> the track's extent box (0 inside)
    azimuth_frd_rad: float            # body FRD: atan2(y_b, x_b), 0 = nose, positive to starboard
    elevation_frd_rad: float          # body FRD: atan2(-z_b, hypot(x_b, y_b)), positive up
    in_cone: bool
    time_to_contact_s: float          # NaN when not in the cone
    closing_speed_mps: float          # rate at which the distance shrinks (positive = approaching)
    expected_time_to_contact_s: float = math.nan   # without the k-sigma margin (assess); NaN when not in the cone


def box_entry_time(c, h, w):
    """Entry time t >= 0 of the ray s(t) = w t into the box |s - c| <= h (per axis), or None if it never enters
    (slab method). 0 when the origin is inside."""
    t_lo, t_hi = -math.inf, math.inf
    for ci, hi, wi in zip(c, h, w):
        lo_b, hi_b = ci - hi, ci + hi
        if abs(wi) < 1e-12:
            if not lo_b <= 0.0 <= hi_b:
                return None
            continue
        t1, t2 = lo_b / wi, hi_b / wi
        t_lo, t_hi = max(t_lo, min(t1, t2)), min(t_hi, max(t1, t2))
    if t_hi < max(t_lo, 0.0):
        return None
    return max(t_lo, 0.0)


def expected_contact_time(c, h, w, earliest_s: float) -> float:
    """Time to contact without the sigma margin: the entry time of the ray s(t) = w t into the box |s - c| <= h (the
    track's box grown by the vehicle radius only), or, when the ray passes that box and meets only the sigma-grown
    one, the time of its closest approach to the centre c (w.c / w.w), never before ``earliest_s`` (the entry into
    the grown box)."""
    te = box_entry_time(c, h, w)
    if te is not None:
        return float(te)
    ww = float(np.dot(w, w))
    return max(float(np.dot(w, c)) / ww, earliest_s) if ww > 0 else earliest_s


def is_moving(x, P, cfg: TrackerConfig) -> bool:
    """Velocity significantly non-zero: v^T P_v^-1 v > ``moving_chi2``."""
    v = x[3:]
    try:
        return float(v @ np.linalg.solve(P[3:, 3:], v)) > cfg.moving_chi2
    except np.linalg.LinAlgError:
        return False


def ownship_at(own: Ownship, now_us: int, max_extrapolate_s: float = 1.0) -> np.ndarray:
    """The vehicle origin at ``now_us``: the state's position moved on by its velocity over the state's age when
    that age is over 0 and at most ``max_extrapolate_s``; otherwise as it is (not capped at ``max_extrapolate_s``: a
    velocity that old is not trusted to carry it), and so when the velocity is unknown or the stamp is not set."""
    dt = (int(now_us) - own.stamp_us) * 1e-6
    if own.stamp_us < 0 or not own.velocity_known or not 0 < dt <= max_extrapolate_s:
        return own.position_ned_m
    return own.position_ned_m + own.velocity_ned_mps * dt


def assess(snapshot, own: Ownship, now_us: int, cone: ConeConfig = ConeConfig(),
           cfg: TrackerConfig = TrackerConfig()) -> list:
    """Guidance quantities of ``Tracker.snapshot(now_us)`` for the vehicle ``own`` (its position carried to
    ``now_us``, ``ownship_at``): one ``TrackView`` per track, in snapshot order. See the module docstring for the
    collision cone."""
    now_us = _stamp(now_us, "now_us")
    pos = ownship_at(own, now_us)
    views = []
    for t, x, P in snapshot:
        p, v = x[:3], x[3:]
        moving = is_moving(x, P, cfg)
        rel = p - pos
        b = own.T_body_ned @ rel                                           # eq. (15): body FRD
        dist = float(np.linalg.norm(rel))
        half = 0.5 * t.extent_ned_m
        surf = float(np.linalg.norm(np.maximum(np.abs(rel) - half, 0.0)))
        ttc, closing, expected = math.nan, math.nan, math.nan
        in_cone = False
        if own.velocity_known:
            w = own.velocity_ned_mps - (v if moving else 0.0)
            closing = float(w @ rel / dist) if dist > 0 else 0.0
            h0 = half + cone.vehicle_radius_m
            h = h0 + cone.k_sigma * np.sqrt(np.maximum(np.diag(P)[:3], 0.0))
            if float(np.linalg.norm(w)) < cone.min_speed_mps:
                w = np.zeros(3)
            te = box_entry_time(rel, h, w)
            if te is not None and te <= cone.horizon_s:
                in_cone, ttc = True, float(te)
                expected = expected_contact_time(rel, h0, w, te)
        views.append(TrackView(
            t, p.copy(), v.copy(), P, (now_us - t.born_us) * 1e-6, (now_us - t.last_hit_us) * 1e-6, moving, dist,
            surf, float(math.atan2(b[1], b[0])), float(math.atan2(-b[2], math.hypot(b[0], b[1]))), in_cone, ttc,
            closing, expected))
    return views


def nearest_threat(views, confirmed_only: bool = True):
    """The ``TrackView`` in the collision cone with the smallest time to contact (ties: the nearer surface), or
    None."""
    threats = [tv for tv in views if tv.in_cone and (tv.track.confirmed or not confirmed_only)]
    return min(threats, key=lambda tv: (tv.time_to_contact_s, tv.surface_distance_m)) if threats else None
