"""From a range map to what guidance and the autopilot consume: OBSTACLE_DISTANCE sectors and an obstacle list.

Pure numpy/scipy: no transport, no MAVLink (``eonav.nav.mavlink_out`` packs the sectors). ``analyse(range map,
camera, pose, config)`` turns every confident pixel into a NED point (inverse of eqs. 8-9, then eq. 33), removes
the ground, and gives (a) 72 sectors of 5 degrees round the vehicle in the autopilots' own layout (element k centred
on the body-relative bearing 5k deg; nearest obstacle, clear, or unknown) and (b) the obstacle list (connected
components cut at range discontinuities). Decisions a reader must know: distances and bearings are measured from
the vehicle origin, not the lens (where the autopilot puts a proximity sensor); a bin is clear only when it lies
wholly inside the camera's view with enough evidence; wide maps are analysed on blocks, each represented by a
robust minimum of its own pixels. The rules and thresholds: docs/methods.md, "Obstacles".
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field, fields, replace

import numpy as np

from eonav import InputError
from eonav.geometry.camera import Camera, VehicleState
from eonav.geometry.frames import ned_from_camera, ypr_from_T_body_ned
from eonav.ranging.rangemap import AT_INFINITY, VALID

UINT16_MAX = 65535
N_SECTORS = 72
SECTOR_INCREMENT_DEG = 360.0 / N_SECTORS     # 5 degrees: the autopilots' own bins
# element 0 is centred 20 deg left of the nose, so the array starts at the left edge of ArduPilot's ahead sector
# (-22.5 .. 22.5 deg) instead of wrapping through it: ArduPilot stores a sector each time a run of elements leaves it,
# so with element 0 on the nose the elements left of it (68 .. 71) overwrote a nearer obstacle right of it (0 .. 4)
SECTOR_ANGLE_OFFSET_DEG = -20.0


@dataclass(frozen=True)
class ObstacleConfig:
    min_confidence: float = 0.0        # pixels with confidence below this are ignored
    max_rel_std: float = 0.34          # ... and those whose 1-sigma range error exceeds this fraction of range
                                       # (the dense method's own VALID threshold; its sigma is calibrated on truth)
    min_distance_m: float = 0.5        # OBSTACLE_DISTANCE min_distance
    max_distance_m: float = 150.0      # OBSTACLE_DISTANCE max_distance; farther points are "clear" evidence
    ground_down_m: float | None = None  # NED down of the ground; None: estimate from the points (docs/methods.md)
    ground_clearance_m: float = 0.6    # points within this of the ground (or below it) are ground ...
    ground_sigma_k: float = 3.0        # ... anywhere in their inverse range's interval of this many 1-sigma ...
    ground_window_px: float = 2.0      # ... plus the height a matching window of this many rows spans on the ground
                                       # at the point's range: x_c k / fy, whatever the map's own sigma
    max_height_above_m: float = 200.0  # points higher than this above the vehicle are ignored (top of the band)
    ground_max_slope_deg: float = 20.0  # the fitted ground plane's steepest allowed slope (steeper: horizontal)
    plane_law_beta: float = 0.5        # a component whose inverse range follows the ground plane's with a log-log
                                       # slope above this is ground ranged too near, not vertical structure ...
    plane_law_min_span: float = 0.1    # ... when its ln(ground inverse range) spans at least this (5..95 %)
    percentile: float = 5.0            # robust minimum of a sector / an obstacle
    min_sector_pixels: int = 4         # obstacle pixels a sector needs to report a distance
    min_clear_pixels: int = 20         # evidence pixels a sector needs to report "clear"
    max_obstacle_distance_m: float = 100.0   # obstacle list: only components nearer than this
    max_rel_jump: float = 0.08         # range discontinuity that separates two objects (relative) ...
    jump_sigma_k: float = 3.0          # ... and beyond this many times the hypot of the two pixels' relative sigmas
    layer_gap_rel: float = 0.4         # a component whose ranges fall into two layers this far apart (the near
                                       # layer's 90th percentile to the far one's 10th, relative) is two objects,
                                       # however smoothly a halo joins them (0: off; ``split_layers``)
    min_obstacle_pixels: int = 12      # smallest component kept (list and sectors)
    min_obstacle_height_m: float = 0.3  # flatter components (5..95 % of down) are mismatch speckle, dropped
    max_obstacles: int = 32            # nearest first
    min_fused: int = 1                 # fused maps: pixels fused from fewer measurements are ignored (agreement
                                       # needs at least two); maps without n_fused are not affected
    horizon_min_fused: int = 1         # fused maps: pixels whose ray does not come down onto the ground plane (at or
                                       # above its horizon: no ground test can vet them) need this many measurements
                                       # (1: off; the fused map's held-single rule covers the sky one pair ranged;
                                       # 2 helps on point-sampled renders, docs/guidance.md)
    max_width_px: int = 160            # pool the map to at most this many columns (0: full resolution)
    pool_percentile: float = 10.0      # which confident pixel of a pooling block stands for it (0 = the nearest)

    def __post_init__(self):
        pos = ("max_rel_std", "min_distance_m", "max_distance_m", "max_height_above_m", "max_obstacle_distance_m",
               "max_rel_jump")
        for name in pos:
            v = getattr(self, name)
            if not (isinstance(v, (int, float)) and math.isfinite(v) and v > 0):
                raise InputError(f"obstacle config: {name} must be a finite number > 0, got {v!r}")
        if self.min_distance_m < 0.01:
            raise InputError(f"obstacle config: min_distance_m {self.min_distance_m} must be >= 0.01 (OBSTACLE_DISTANCE "
                             f"min_distance >= 1 cm; ArduPilot ignores 0)")
        if not self.min_distance_m < self.max_distance_m:
            raise InputError(f"obstacle config: min_distance_m {self.min_distance_m} must be < max_distance_m "
                             f"{self.max_distance_m}")
        if self.max_distance_m * 100 + 1 >= UINT16_MAX:
            raise InputError(f"obstacle config: max_distance_m {self.max_distance_m} does not fit OBSTACLE_DISTANCE "
                             f"(u16 cm, below {(UINT16_MAX - 2) / 100} m)")
        if not 0 <= self.percentile <= 100:
            raise InputError(f"obstacle config: percentile must be in [0, 100], got {self.percentile}")
        if not 0 <= self.pool_percentile <= 100:
            raise InputError(f"obstacle config: pool_percentile must be in [0, 100], got {self.pool_percentile}")
        if not (isinstance(self.max_width_px, int) and self.max_width_px >= 0):
            raise InputError(f"obstacle config: max_width_px must be an integer >= 0, got {self.max_width_px!r}")
        if not 0 <= self.ground_max_slope_deg < 90:
            raise InputError(f"obstacle config: ground_max_slope_deg must be in [0, 90), got {self.ground_max_slope_deg}")
        if not (math.isfinite(self.layer_gap_rel) and self.layer_gap_rel >= 0):
            raise InputError(f"obstacle config: layer_gap_rel must be a finite number >= 0, got {self.layer_gap_rel!r}")
        if not (math.isfinite(self.jump_sigma_k) and self.jump_sigma_k >= 0):
            raise InputError(f"obstacle config: jump_sigma_k must be a finite number >= 0, got {self.jump_sigma_k!r}")
        if not (0 < self.plane_law_beta and self.plane_law_min_span > 0):
            raise InputError("obstacle config: plane_law_beta and plane_law_min_span must be > 0")
        if self.ground_down_m is not None and not math.isfinite(self.ground_down_m):
            raise InputError("obstacle config: ground_down_m must be finite or None")
        if not (math.isfinite(self.ground_window_px) and self.ground_window_px >= 0):
            raise InputError(f"obstacle config: ground_window_px must be a finite number >= 0, got {self.ground_window_px}")
        for name in ("min_sector_pixels", "min_clear_pixels", "min_obstacle_pixels", "max_obstacles", "min_fused",
                     "horizon_min_fused"):
            v = getattr(self, name)
            if not (isinstance(v, int) and v >= 1):
                raise InputError(f"obstacle config: {name} must be an integer >= 1, got {v!r}")


@dataclass
class Sectors:
    """OBSTACLE_DISTANCE content (MAV_FRAME_BODY_FRD). ``distances_cm`` u16[72]."""
    distances_cm: np.ndarray
    increment_deg: float
    angle_offset_deg: float
    min_distance_cm: int
    max_distance_cm: int
    counts: np.ndarray = field(repr=False, default=None)    # obstacle pixels per bin

    def to_msg(self) -> dict:
        return {"distances_cm": [int(x) for x in self.distances_cm], "increment_deg": float(self.increment_deg),
                "angle_offset_deg": float(self.angle_offset_deg), "min_distance_cm": int(self.min_distance_cm),
                "max_distance_cm": int(self.max_distance_cm), "frame": "body_frd"}

    @classmethod
    def from_msg(cls, d: dict) -> "Sectors":
        try:
            dist = np.asarray(d["distances_cm"], dtype=np.int64)
            out = cls(dist.astype(np.uint16), float(d["increment_deg"]), float(d["angle_offset_deg"]),
                      int(d["min_distance_cm"]), int(d["max_distance_cm"]))
        except (KeyError, TypeError, ValueError) as e:
            raise InputError(f"sectors: expected distances_cm[72], increment_deg, angle_offset_deg, min/max_distance_cm "
                             f"({type(e).__name__}: {e})") from None
        if dist.shape != (N_SECTORS,) or dist.min() < 0 or dist.max() > UINT16_MAX:
            raise InputError(f"sectors: distances_cm must be {N_SECTORS} values in 0..{UINT16_MAX}")
        return out

    def bin_centres_deg(self) -> np.ndarray:
        """Body-relative bearing of each element's centre (OBSTACLE_DISTANCE: angle_offset is element 0's centre)."""
        return self.angle_offset_deg + np.arange(N_SECTORS) * self.increment_deg

    @classmethod
    def unknown(cls, like: "Sectors") -> "Sectors":
        return cls(np.full(N_SECTORS, UINT16_MAX, np.uint16), like.increment_deg, like.angle_offset_deg,
                   like.min_distance_cm, like.max_distance_cm)


@dataclass
class Obstacle:
    id: int
    distance_m: float              # robust minimum (percentile) of Euclidean distance from the vehicle origin
    distance_median_m: float
    horizontal_distance_m: float   # robust minimum of the horizontal distance
    bearing_deg: float             # body frame, 0 = nose, clockwise positive (of the median body-frame point)
    elevation_deg: float           # body frame, positive up
    range_std_m: float             # 1-sigma of x_c (median per-pixel estimate, else robust spread)
    position_ned_m: list           # median NED point
    extent_ned_m: list             # 5..95 % extent along N, E, D
    width_m: float                 # horizontal extent across the line of sight
    height_m: float                # vertical extent
    pixel_count: int
    confidence: float              # median confidence of its pixels
    bbox_px: list                  # [u_min, v_min, u_max, v_max]
    range_noise_std_m: float = math.nan  # sigma of the 5..95 % span its pixels' range noise spreads them over
                                         # (``mixture_sigma``; NaN: not given, range_std_m stands in)

    def to_msg(self) -> dict:
        # shallow (the fields are numbers and flat lists): dataclasses.asdict's deep copy costs more than the rest
        return {f.name: _msg_value(getattr(self, f.name)) for f in fields(self)}


def _msg_value(v):
    if isinstance(v, (float, np.floating)):
        return float(v)
    return list(v) if isinstance(v, list) else v


@dataclass
class Points:
    """Geometry of the confident pixels of one range map: one point per cell of the analysis grid (the full-resolution
    pixel grid, or its k x k pooling blocks, see ``pool_confident``), in grid order."""
    idx: np.ndarray           # flat full-resolution index of the pixel that stands for the cell
    range_m: np.ndarray       # x_c
    ned_m: np.ndarray         # (n, 3)
    body_m: np.ndarray        # (n, 3) relative to the vehicle origin, body axes
    hdist_m: np.ndarray       # horizontal distance from the vehicle origin
    dist_m: np.ndarray        # Euclidean distance from the vehicle origin
    bearing_rad: np.ndarray   # horizontal bearing from the vehicle origin relative to the heading
    sigma_m: np.ndarray | None
    confidence: np.ndarray
    weight: np.ndarray | None = None   # full-resolution confident pixels the point stands for (1 without pooling)
    cell: np.ndarray | None = None     # flat index on the analysis grid (== idx without pooling)

    def __post_init__(self):
        if self.weight is None:
            self.weight = np.ones(self.idx.size)
        if self.cell is None:
            self.cell = self.idx


def _check_maps(range_m, confidence, flags, inv_range_std_per_m, camera: Camera):
    r = np.asarray(range_m)
    if r.ndim != 2:
        raise InputError(f"range_m must be a 2-D H x W map, got shape {r.shape}")
    if r.shape != (camera.height, camera.width):
        raise InputError(f"range_m is {r.shape[1]}x{r.shape[0]} but camera {camera.name!r} is "
                         f"{camera.width}x{camera.height}")
    for name, a in (("confidence", confidence), ("flags", flags), ("inv_range_std_per_m", inv_range_std_per_m)):
        if a is not None and np.shape(a) != r.shape:
            raise InputError(f"{name} has shape {np.shape(a)}, expected {r.shape} like range_m")


def frame_grid(camera: Camera, frame_size=None) -> tuple:
    """(frame width, frame height, frame pixels per map pixel) of a map on ``camera``'s grid ranged from a frame of
    ``frame_size`` = (width, height) (None or zeros: the map is on the frame's grid). Raises InputError when the frame
    is smaller than the map."""
    if frame_size is None or not any(frame_size):
        return camera.width, camera.height, 1.0
    try:
        fw, fh = (int(x) for x in frame_size)
    except (TypeError, ValueError):
        raise InputError(f"frame size {frame_size!r}: expected (width, height)") from None
    if fw < camera.width or fh < camera.height:
        raise InputError(f"frame size {fw}x{fh} is smaller than the map's camera {camera.name!r} "
                         f"{camera.width}x{camera.height}")
    return fw, fh, (fw / camera.width) * (fh / camera.height)


def confident_mask(range_m, confidence=None, flags=None, inv_range_std_per_m=None, cfg: ObstacleConfig = ObstacleConfig(),
                   n_fused=None):
    """Pixels with a finite positive range the estimator stands behind (``n_fused``: measurements per pixel of a
    fused map, at least ``cfg.min_fused``)."""
    r = np.asarray(range_m, np.float32)
    with np.errstate(invalid="ignore"):
        m = np.isfinite(r) & (r > 0)
        if flags is not None:
            m &= (np.asarray(flags) & VALID) != 0
        if confidence is not None:
            m &= np.asarray(confidence) >= cfg.min_confidence
        if inv_range_std_per_m is not None:
            s = np.asarray(inv_range_std_per_m, np.float32)
            m &= ~(s * r > cfg.max_rel_std)           # sigma_r / r = sigma_rho * r (first order); NaN std passes
        if n_fused is not None and cfg.min_fused > 1:
            m &= np.asarray(n_fused) >= cfg.min_fused
    return m


def infinity_mask(range_m, flags=None):
    r = np.asarray(range_m, np.float32)
    m = np.isposinf(r)
    if flags is not None:
        m |= (np.asarray(flags) & AT_INFINITY) != 0
    return m


def unconfirmed_above_horizon(conf_m, n_fused, min_fused: int, range_m, camera: Camera, state: VehicleState,
                              plane: "GroundPlane") -> np.ndarray | None:
    """Pixels of ``conf_m`` fused from fewer than ``min_fused`` measurements whose ray does not come down onto
    ``plane`` (at or above its horizon), or None when there are none. Below the horizon a range too near lifts a
    point off the ground and the ground tests weigh it; above it any range is clear of the ground, and a cell that
    one measurement started and nothing measured since (sky: LOW_TEXTURE pair after pair) is held at that range
    for as long as it stays in view: faint cloud ranged at 20-90 m (docs/guidance.md)."""
    cand = np.flatnonzero(conf_m & (np.asarray(n_fused) < min_fused))
    if not cand.size:
        return None
    p = pixel_points(range_m, camera, state, None, idx=cand)
    lens = state.position_ned_m + state.T_body_ned.T @ camera.l_body_m
    up = plane.inverse_range_per_m(lens, (p.ned_m - lens) / p.range_m[:, None]) <= 0
    if not up.any():
        return None
    out = np.zeros(conf_m.shape, bool)
    out.flat[cand[up]] = True
    return out


def pool_factor(width: int, cfg: ObstacleConfig) -> int:
    """Side k of the pooling blocks: the smallest integer that brings ``width`` to at most ``cfg.max_width_px``."""
    if not cfg.max_width_px or width <= cfg.max_width_px:
        return 1
    return -(-int(width) // int(cfg.max_width_px))


def pool_confident(range_m, conf_mask, k: int, pool_percentile: float = 10.0):
    """The analysis grid: (idx, weight, cell, (grid_h, grid_w)).

    k == 1: every confident pixel is a point. k > 1: the map is cut into k x k blocks and each block with at least one
    confident pixel is represented by ONE of its own pixels, the ``pool_percentile``-th of its confident pixels by range
    (10: the 2nd nearest of 16; the nearest when a block has at most 10). A robust minimum, not a mean: where a block
    straddles a near object and what is behind it, the near object wins (an obstacle grows by at most a block, it never
    moves away), and a single too-near mismatch does not. The chosen pixel keeps its exact (u, v) and range, so its
    geometry is exact; ``weight`` (confident pixels in the block) keeps pixel-count thresholds in full-resolution
    units."""
    H, W = conf_mask.shape
    if k == 1:
        idx = np.flatnonzero(conf_mask)
        return idx, np.ones(idx.size), idx, (H, W)
    gh, gw = -(-H // k), -(-W // k)
    rr = np.full((gh * k, gw * k), np.inf, np.float32)
    rr[:H, :W] = np.where(conf_mask, range_m, np.inf)
    if math.floor(pool_percentile / 100.0 * (k * k - 1)) == 0:
        return _pool_nearest(rr, k, W, (gh, gw))
    blocks = rr.reshape(gh, k, gw, k).transpose(0, 2, 1, 3).reshape(gh * gw, k * k)
    n = np.count_nonzero(np.isfinite(blocks), axis=1)
    cell = np.flatnonzero(n)
    n = n[cell]
    order = np.argsort(blocks[cell], axis=1)
    rank = np.floor(pool_percentile / 100.0 * (n - 1)).astype(np.int64)
    pick = order[np.arange(cell.size), rank]
    by, bx = np.divmod(pick, k)
    gy, gx = np.divmod(cell, gw)
    return (gy * k + by) * W + (gx * k + bx), n.astype(np.float64), cell, (gh, gw)


def _pool_nearest(rr, k: int, W: int, grid: tuple):
    """``pool_confident`` when every block's rank is 0 (k <= 3 at the default 10 %: the nearest confident pixel): the
    same picks from the k * k strided sub-grids with element-wise minimum and compare, instead of an argsort of every
    k * k block (about half the time). Ties (equal ranges in one block) go to the first pixel of the block in
    row-major order, which a stable sort would pick (numpy's default argsort breaks ties by platform: SIMD sorts
    are not stable)."""
    gh, gw = grid
    subs = [rr[i::k, j::k] for i in range(k) for j in range(k)]       # each gh x gw: offset (i, j) of every block
    m = subs[0].copy()
    n = np.isfinite(subs[0]).astype(np.int64)
    for sub in subs[1:]:
        np.minimum(m, sub, out=m)
        n += np.isfinite(sub)
    pick = np.zeros((gh, gw), np.int64)
    for o in range(len(subs) - 1, 0, -1):                             # backwards: the first offset at the minimum wins
        pick[subs[o] == m] = o
    pick[subs[0] == m] = 0
    n = n.ravel()
    cell = np.flatnonzero(n)
    by, bx = np.divmod(pick.ravel()[cell], k)
    gy, gx = np.divmod(cell, gw)
    return (gy * k + by) * W + (gx * k + bx), n[cell].astype(np.float64), cell, (gh, gw)


def pixel_points(range_m, camera: Camera, state: VehicleState, mask: np.ndarray | None, confidence=None,
                 inv_range_std_per_m=None, idx: np.ndarray | None = None) -> Points:
    """Geometry of the pixels in ``mask`` (or of the flat pixel indices ``idx``) (eq. 33 per pixel)."""
    if idx is None:
        idx = np.flatnonzero(mask)
    r = np.asarray(range_m).ravel()[idx].astype(np.float64)
    v, u = np.divmod(idx, camera.width)
    cam_pts = np.stack([r, r * (u - camera.cx) / camera.fx, r * (v - camera.cy) / camera.fy], axis=1)
    ned = ned_from_camera(cam_pts, camera.T_cam_body, state.T_body_ned, state.position_ned_m, camera.l_body_m)
    rel = ned - state.position_ned_m
    body = rel @ state.T_body_ned.T                                  # T2 (x - x_v), row-vector form
    yaw = ypr_from_T_body_ned(state.T_body_ned)[0]
    bearing = np.arctan2(rel[:, 1], rel[:, 0]) - yaw
    bearing = (bearing + np.pi) % (2 * np.pi) - np.pi
    sigma = None
    if inv_range_std_per_m is not None:
        sigma = np.asarray(inv_range_std_per_m).ravel()[idx].astype(np.float64) * r * r   # sigma_r = sigma_rho / rho^2
    conf = (np.asarray(confidence).ravel()[idx].astype(np.float64) if confidence is not None else np.ones(idx.size))
    hdist = np.hypot(rel[:, 0], rel[:, 1])
    return Points(idx, r, ned, body, hdist, np.hypot(hdist, rel[:, 2]), bearing, sigma, conf)


def estimate_ground_down_m(pts: Points, state: VehicleState, cfg: ObstacleConfig) -> float:
    """Ground height (NED down) from the configuration or the points (see module doc)."""
    if cfg.ground_down_m is not None:
        return float(cfg.ground_down_m)
    sel = pts.ned_m[:, 2] > state.position_ned_m[2] + 0.5
    if pts.weight[sel].sum() >= 50:
        return float(np.percentile(pts.ned_m[sel, 2], 90))
    return 0.0


@dataclass(frozen=True)
class GroundPlane:
    """The ground as a plane in NED: down = a + b north + c east (b = c = 0: level)."""
    a: float
    b: float = 0.0
    c: float = 0.0

    def down_m(self, ned_m) -> np.ndarray:
        ned_m = np.asarray(ned_m, float)
        return self.a + self.b * ned_m[..., 0] + self.c * ned_m[..., 1]

    def height_and_descent(self, lens_ned_m, ray_ned) -> tuple[float, np.ndarray]:
        """(H, descent): the lens' height above the plane (> 0: above it) and how fast each ray lens + x_c ray
        (``ray_ned`` = NED direction per metre of x_c) comes down onto it per metre of x_c; the point at x_c stands
        H - x_c descent above the plane."""
        lens = np.asarray(lens_ned_m, float)
        ray = np.asarray(ray_ned, float)
        return float(self.down_m(lens) - lens[2]), ray[..., 2] - self.b * ray[..., 0] - self.c * ray[..., 1]

    def inverse_range_per_m(self, lens_ned_m, ray_ned) -> np.ndarray:
        """1 / x_c at which each ray lens + x_c ray meets the plane; <= 0 where the ray does not descend onto it (at
        or above the horizon). Linear in the ray: the plane law."""
        below, descent = self.height_and_descent(lens_ned_m, ray_ned)
        return descent / below if below > 0 else np.zeros(descent.shape)


def height_above_plane_low(plane: GroundPlane, lens_ned_m, ray_ned, rho_per_m, sigma_rho_per_m=None,
                           k: float = 0.0) -> np.ndarray:
    """The least height above ``plane`` of the points lens + ray / rho' for rho' in the k-sigma interval of each
    point's inverse range, rho +- k sigma_rho (the map's noise model is Gaussian in inverse range). The height is
    linear in x_c = 1 / rho' (H - x_c descent, ``GroundPlane.inverse_range_per_m``), so its least value is at an
    end of the interval; rho - k sigma <= 0 holds infinity: a descending ray then reaches the ground, -inf. The
    first-order range sigma (sigma_rho / rho^2) puts the far end at x_c + k sigma_r instead of 1 / (rho - k sigma),
    short of it by k^2 sigma_r sigma_rho / (rho - k sigma): at 3 sigma and sigma_rho / rho = 0.2 the far end is
    1.6 x_c, not 2.5 x_c, and far ground ranged at half its range stands metres above its clearance."""
    H, descent = plane.height_and_descent(lens_ned_m, ray_ned)
    rho = np.asarray(rho_per_m, float)
    dr = 0.0 if sigma_rho_per_m is None else k * np.asarray(sigma_rho_per_m, float)
    with np.errstate(divide="ignore", invalid="ignore"):
        near = H - descent / (rho + dr)
        lo = rho - dr
        far = np.where(lo > 0, H - descent / np.where(lo > 0, lo, 1.0),
                       np.where(descent > 0, -np.inf, np.where(descent < 0, np.inf, H)))
    return np.minimum(near, far)


def fit_ground(pts: Points, state: VehicleState, cfg: ObstacleConfig) -> GroundPlane:
    """The ground plane: ``cfg.ground_down_m`` when configured (level); else a robust least-squares plane through
    the confident points below the vehicle, from the level plane of the 90th percentile of down, iterated on the
    points at most 3 m, then 1 m, then 0.5 m above the current plane (obstacles stand above the ground; the ground is
    the lowest dense surface), its slope capped at
    ``cfg.ground_max_slope_deg`` (steeper: the level plane of the 90th percentile of down); level 0 m with too few
    points."""
    if cfg.ground_down_m is not None:
        return GroundPlane(float(cfg.ground_down_m))
    level = GroundPlane(estimate_ground_down_m(pts, state, cfg))
    sel = pts.ned_m[:, 2] > state.position_ned_m[2] + 0.5
    if pts.weight[sel].sum() < 50:
        return level
    p = pts.ned_m[sel]
    w = pts.weight[sel]
    A = np.stack([np.ones(len(p)), p[:, 0], p[:, 1]], axis=1)
    coef = np.array([level.a, 0.0, 0.0])
    for tol in (3.0, 3.0, 3.0, 1.0, 1.0, 0.5, 0.5):
        res = p[:, 2] - A @ coef                          # > 0: below the plane
        keep = (res >= -tol) & (res <= 3.0 * tol)         # obstacles stand above the ground, not below it
        if w[keep].sum() < 50:
            return level
        sw = np.sqrt(w[keep])
        coef = np.linalg.lstsq(A[keep] * sw[:, None], p[keep, 2] * sw, rcond=None)[0]
    if math.hypot(coef[1], coef[2]) > math.tan(math.radians(cfg.ground_max_slope_deg)):
        return level
    return GroundPlane(float(coef[0]), float(coef[1]), float(coef[2]))


def camera_hfov_deg(camera: Camera) -> tuple:
    """(left, right) body-relative bearings in degrees of the image's outer pixel edges (camera yaw eps1 included)."""
    yaw_cam = math.degrees(float(camera.eps_rad[0]))
    left = math.degrees(math.atan2(-0.5 - camera.cx, camera.fx))
    right = math.degrees(math.atan2(camera.width - 0.5 - camera.cx, camera.fx))
    return yaw_cam + left, yaw_cam + right


def sector_geometry(camera: Camera) -> tuple:
    """(increment_deg, angle_offset_deg) of the sectors: the fixed 72 x 5-degree layout, element k centred on bearing
    -20 + 5k deg (``SECTOR_ANGLE_OFFSET_DEG``).

    The layout does not depend on the camera: every camera's sectors index the same bins, so the sectors of several
    cameras merge bin by bin into one message (``merge_sectors``)."""
    return SECTOR_INCREMENT_DEG, SECTOR_ANGLE_OFFSET_DEG


def bins_in_view(camera: Camera) -> tuple:
    """Masks over the 72 bins: (wholly inside the camera's horizontal view, touched by it)."""
    left, right = camera_hfov_deg(camera)
    centre = SECTOR_ANGLE_OFFSET_DEG + np.arange(N_SECTORS) * SECTOR_INCREMENT_DEG
    half = SECTOR_INCREMENT_DEG / 2
    # the bins' edges relative to the view's middle, wrapped to (-180, 180]
    mid = 0.5 * (left + right)
    rel = (centre - mid + 180.0) % 360.0 - 180.0
    lo, hi = rel - half, rel + half
    half_view = 0.5 * (right - left)
    return (lo >= -half_view) & (hi <= half_view), (hi > -half_view) & (lo < half_view)


def merge_sectors(parts: list) -> "Sectors":
    """One OBSTACLE_DISTANCE picture from the sectors of several cameras (same layout and limits): per bin the nearest
    obstacle any camera reports; else clear if any camera sees it clear; else unknown."""
    if not parts:
        raise InputError("merge_sectors: no sectors to merge")
    first = parts[0]
    for p in parts[1:]:
        if (p.increment_deg, p.angle_offset_deg, p.min_distance_cm, p.max_distance_cm) != (
                first.increment_deg, first.angle_offset_deg, first.min_distance_cm, first.max_distance_cm):
            raise InputError("merge_sectors: sectors of different layouts or distance limits")
    d = np.stack([np.asarray(p.distances_cm, np.int64) for p in parts])
    clear = first.max_distance_cm + 1
    hit = np.where(d <= first.max_distance_cm, d, UINT16_MAX).min(axis=0)
    out = np.where(hit < UINT16_MAX, hit, np.where((d == clear).any(axis=0), clear, UINT16_MAX))
    return Sectors(out.astype(np.uint16), first.increment_deg, first.angle_offset_deg, first.min_distance_cm,
                   first.max_distance_cm)


@dataclass
class ObstacleResult:
    sectors: Sectors
    obstacles: list
    ground_down_m: float
    n_confident: int
    n_obstacle_px: int
    sectors_now: Sectors | None = None      # sectors relative to ``now_state`` when one was given
    data_mask: np.ndarray | None = None     # pixels with a usable range: confident (as analysed) or at infinity
    ground: GroundPlane | None = None       # the ground plane used (``ground_down_m`` is its down under the vehicle)


def analyse(range_m, camera: Camera, state: VehicleState, confidence=None, flags=None, inv_range_std_per_m=None,
            cfg: ObstacleConfig = ObstacleConfig(), now_state: VehicleState | None = None,
            frame_size=None, n_fused=None, ground: GroundPlane | None = None) -> ObstacleResult:
    """Sectors and obstacle list of one range map (see the module docstring).

    ``state`` is the vehicle pose at capture (it places the points, eq. 33). ``now_state``, when given, is
    a newer pose (latest navigation): ``sectors_now`` are then measured from it, since the autopilot applies
    OBSTACLE_DISTANCE on arrival, relative to where the vehicle is then (20 m/s x 100 ms = 2 m).

    Maps wider than ``cfg.max_width_px`` are analysed on k x k pooling blocks (``pool_confident``): one robust-minimum
    pixel per block. Pixel counts (sector and component thresholds, ``pixel_count``) stay in full-resolution pixels.

    ``camera`` is the camera of the map's own grid. A map computed at a locate scale (``camera`` =
    ``eonav.geometry.camera.scaled_camera`` of the frame's) is analysed on that grid with ``frame_size`` = the frame's (width,
    height): each map pixel then counts as the frame pixels it stands for, so the thresholds, ``pixel_count``,
    ``n_confident`` and ``bbox_px`` stay in frame pixels and the result matches that of the same map upsampled to the
    frame (tests/test_obstacles.py), for a quarter of the pixels at scale 0.5.

    ``ground``, when given, is the ground plane to use instead of ``fit_ground``'s (a terrain model)."""
    _check_maps(range_m, confidence, flags, inv_range_std_per_m, camera)
    fw, fh, area = frame_grid(camera, frame_size)
    if n_fused is not None and np.shape(n_fused) != np.shape(range_m):
        raise InputError(f"n_fused has shape {np.shape(n_fused)}, expected {np.shape(range_m)} like range_m")
    conf_m = confident_mask(range_m, confidence, flags, inv_range_std_per_m, cfg, n_fused)
    k = pool_factor(camera.width, cfg)

    def points():
        idx, weight, cell, grid = pool_confident(np.asarray(range_m, np.float32), conf_m, k, cfg.pool_percentile)
        pts = pixel_points(range_m, camera, state, None, confidence, inv_range_std_per_m, idx=idx)
        pts.weight, pts.cell = (weight * area if area != 1.0 else weight), cell
        return pts, grid

    pts, grid = points()
    inf_m = infinity_mask(range_m, flags)
    inf_cols = np.count_nonzero(inf_m, axis=0)                              # pixels at infinity per image column
    if area != 1.0:
        inf_cols = inf_cols * area
    plane = ground if ground is not None else fit_ground(pts, state, cfg)
    ground = float(plane.down_m(state.position_ned_m))
    if n_fused is not None and cfg.horizon_min_fused > cfg.min_fused:
        doubt = unconfirmed_above_horizon(conf_m, n_fused, cfg.horizon_min_fused, range_m, camera, state, plane)
        if doubt is not None:                       # not confident: neither obstacle nor evidence of free space
            conf_m &= ~doubt
            pts, grid = points()
    z = pts.ned_m[:, 2]
    lens = state.position_ned_m + state.T_body_ned.T @ camera.l_body_m
    ray = (pts.ned_m - lens) / pts.range_m[:, None]               # NED direction per metre of x_c
    # a window of k rows on ground seen at a grazing angle d spans ranges x_c k / (fy tan d): the honest range error
    # there, whose height error x_c k / fy does not depend on the angle (docs/methods.md, "Obstacles")
    # (k in frame pixels: a map at a locate scale gives the obstacles of the same map upsampled to the frame)
    clearance = cfg.ground_clearance_m + cfg.ground_window_px * pts.range_m / (camera.fy * fh / camera.height)
    sig_rho = None
    if pts.sigma_m is not None and cfg.ground_sigma_k > 0:
        sig_rho = np.nan_to_num(pts.sigma_m / (pts.range_m * pts.range_m), nan=0.0, posinf=0.0)
    above_ground = height_above_plane_low(plane, lens, ray, 1.0 / pts.range_m, sig_rho, cfg.ground_sigma_k) > clearance
    rho_ground = plane.inverse_range_per_m(lens, ray)
    in_band = above_ground & (z > state.position_ned_m[2] - cfg.max_height_above_m)
    obstacle = in_band & (pts.hdist_m <= cfg.max_distance_m)
    # speckle (small or flat blobs: mismatched ground patches) is neither an obstacle nor in the sectors
    comps, kept = _components(pts, obstacle, camera, grid, k, state, cfg, (fw, fh), rho_ground)
    sectors = _sectors(pts, kept, ~obstacle, camera, inf_cols, cfg)
    obstacles = [o for o in comps if o.distance_m <= cfg.max_obstacle_distance_m][:cfg.max_obstacles]
    for i, o in enumerate(obstacles):
        o.id = i + 1
    sectors_now = None
    if now_state is not None:
        moved = relative_to(pts, now_state)
        sectors_now = _sectors(moved, kept & (moved.hdist_m <= cfg.max_distance_m),
                               in_band & (moved.hdist_m > cfg.max_distance_m) | ~in_band, camera, inf_cols, cfg)
    return ObstacleResult(sectors, obstacles, ground, int(round(np.count_nonzero(conf_m) * area)),
                          int(round(pts.weight[kept].sum())), sectors_now, conf_m | inf_m, plane)


def relative_to(pts: Points, state: VehicleState) -> Points:
    """The same points with distances and bearings measured from another vehicle pose."""
    rel = pts.ned_m - state.position_ned_m
    yaw = ypr_from_T_body_ned(state.T_body_ned)[0]
    bearing = (np.arctan2(rel[:, 1], rel[:, 0]) - yaw + np.pi) % (2 * np.pi) - np.pi
    hdist = np.hypot(rel[:, 0], rel[:, 1])
    return replace(pts, body_m=rel @ state.T_body_ned.T, hdist_m=hdist,
                   dist_m=np.hypot(hdist, rel[:, 2]), bearing_rad=bearing)


def _bins(bearing_rad, inc_deg, off_deg):
    """Element index of each bearing: element j is centred on off + j inc and covers +- inc / 2 (wraps at 360)."""
    b = np.floor((np.degrees(bearing_rad) - off_deg) / inc_deg + 0.5).astype(np.int64) % N_SECTORS
    return b, np.ones(b.shape, bool)


def _sorted_percentile(d, starts, n, q):
    """np.percentile (linear) of each run d[starts[j]:starts[j] + n[j]] of an ascending-sorted-per-run array."""
    pos = q / 100.0 * (n - 1)
    lo = np.floor(pos).astype(np.int64)
    hi = np.minimum(lo + 1, n - 1)
    frac = pos - lo
    return d[starts + lo] * (1.0 - frac) + d[starts + hi] * frac


def _pct_sorted(a, q):
    """np.percentile (linear) along axis 0 of an array already sorted along axis 0 (cheap for small groups)."""
    pos = q / 100.0 * (a.shape[0] - 1)
    lo = int(math.floor(pos))
    hi = min(lo + 1, a.shape[0] - 1)
    return a[lo] * (1.0 - (pos - lo)) + a[hi] * (pos - lo)


def _sectors(pts: Points, obstacle, evidence, camera, inf_cols, cfg: ObstacleConfig) -> Sectors:
    inc, off = sector_geometry(camera)
    min_cm, max_cm = int(round(cfg.min_distance_m * 100)), int(round(cfg.max_distance_m * 100))
    out = np.full(N_SECTORS, UINT16_MAX, np.uint16)
    b, ok = _bins(pts.bearing_rad, inc, off)
    # evidence of free space (full-resolution pixels): confident non-obstacle points, plus pixels at infinity (binned
    # by their column's bearing)
    sel = ok & evidence
    ev = np.bincount(b[sel], weights=pts.weight[sel], minlength=N_SECTORS)[:N_SECTORS]
    cols = np.flatnonzero(inf_cols)
    if cols.size:
        col_bearing = np.arctan2(cols - camera.cx, camera.fx) + camera.eps_rad[0]
        bi, oki = _bins(col_bearing, inc, off)
        ev = ev + np.bincount(bi[oki], weights=inf_cols[cols][oki], minlength=N_SECTORS)[:N_SECTORS]
    sel = ok & obstacle
    bo, d = b[sel], pts.hdist_m[sel]
    counts = np.bincount(bo, weights=pts.weight[sel], minlength=N_SECTORS)[:N_SECTORS]   # obstacle pixels per bin
    whole, _ = bins_in_view(camera)
    out[(ev >= cfg.min_clear_pixels) & whole] = max_cm + 1
    if bo.size:
        order = np.lexsort((d, bo))
        d = d[order]
        n = np.bincount(bo, minlength=N_SECTORS)[:N_SECTORS]                            # points per bin
        starts = np.concatenate([[0], np.cumsum(n)[:-1]])
        js = np.flatnonzero((counts >= cfg.min_sector_pixels) & (n > 0))
        if js.size:
            val = _sorted_percentile(d, starts[js], n[js], cfg.percentile)
            out[js] = np.clip(np.round(val * 100), min_cm, max_cm).astype(np.uint16)
    return Sectors(out, inc, off, min_cm, max_cm, np.round(counts).astype(np.int64))


def plane_law_slope(rho_m, rho_ground, starts, n_in, min_span: float) -> np.ndarray:
    """Per run ``starts[j]:starts[j] + n_in[j]`` of points (one component each): the least-squares slope beta of
    ln(1 / x_c) on ln(the ground plane's 1 / x_c along the same rays). Ground follows the plane law, whatever a
    range bias that is constant over the component: beta = 1; vertical structure keeps its range up its rows: beta
    = 0. NaN where the slope cannot be told: rays at or above the horizon in a fifth of the points or more (ground
    cannot be there: not ground), or a span of ln(ground inverse range) (5..95 %) below ``min_span``."""
    out = np.full(len(starts), np.nan)
    for j, (s0, n) in enumerate(zip(starts, n_in)):
        g, r = rho_ground[s0:s0 + n], rho_m[s0:s0 + n]
        ok = g > 0
        n_ok = int(np.count_nonzero(ok))
        if n_ok < 3 or 5 * (n - n_ok) >= n:           # a fifth or more at or above the horizon (integers: exact)
            continue
        x, y = np.log(g[ok]), np.log(r[ok])
        lo, hi = np.percentile(x, [5.0, 95.0])
        if hi - lo < min_span:
            continue
        xc = x - x.mean()
        out[j] = float(xc @ (y - y.mean()) / (xc @ xc))
    return out


def _components(pts: Points, sel, camera: Camera, grid: tuple, k: int, state: VehicleState, cfg: ObstacleConfig,
                frame_size: tuple | None = None, rho_ground: np.ndarray | None = None):
    """Obstacles within ``cfg.max_obstacle_distance_m`` (nearest first; the details of farther components are not
    computed: 4 of the 14 components of a 640 x 480 approach-flight map) and the mask over ``pts`` of the points of all
    the components kept (the sectors use them at any distance). Works on the analysis
    grid (``grid`` = (rows, cols) of cells; a cell is a k x k block of pixels); ``bbox_px`` is in the pixels of the
    frame of ``frame_size`` (default: the map's own grid)."""
    from scipy import ndimage
    gh, gw = grid
    n_cells = gh * gw
    kept = np.zeros(pts.idx.size, bool)
    cells = pts.cell[sel]
    if not cells.size:
        return [], kept
    mask = np.zeros(n_cells, bool)
    mask[cells] = True
    mask = mask.reshape(gh, gw)
    r = np.full(n_cells, np.nan)
    r[cells] = pts.range_m[sel]
    r = r.reshape(gh, gw)
    # relative 1-sigma per pixel: a jump must beat both max_rel_jump and jump_sigma_k x hypot of the two sigmas, or
    # noisy far objects shatter into speckle (neighbours share most of their matching window, so their errors
    # correlate and their difference's sigma is below the hypot: docs/methods.md, "Obstacles")
    rel_sig = np.zeros(n_cells)
    if pts.sigma_m is not None:
        rel_sig[pts.cell] = np.nan_to_num(pts.sigma_m / pts.range_m, nan=0.0, posinf=0.0)
    rel_sig = rel_sig.reshape(gh, gw)
    base = math.log1p(cfg.max_rel_jump)
    with np.errstate(invalid="ignore", divide="ignore"):
        lr = np.log(r)
        cut = np.zeros((gh, gw), bool)
        dx = lr[:, 1:] - lr[:, :-1]                       # > 0: right pixel farther
        jump = np.abs(dx) > np.maximum(base, cfg.jump_sigma_k * np.hypot(rel_sig[:, 1:], rel_sig[:, :-1]))
        cut[:, 1:] |= jump & (dx > 0)
        cut[:, :-1] |= jump & (dx < 0)
        dy = lr[1:, :] - lr[:-1, :]
        jump = np.abs(dy) > np.maximum(base, cfg.jump_sigma_k * np.hypot(rel_sig[1:, :], rel_sig[:-1, :]))
        cut[1:, :] |= jump & (dy > 0)
        cut[:-1, :] |= jump & (dy < 0)
    labels, n = ndimage.label(mask & ~cut)
    if n == 0:
        return [], kept
    if cfg.layer_gap_rel > 0:
        labels, n = split_layers(labels, n, lr, mask & ~cut, math.log1p(cfg.layer_gap_rel), cfg.min_obstacle_pixels)
    wgrid = np.zeros(n_cells)
    wgrid[pts.cell] = pts.weight
    sizes = np.bincount(labels.ravel(), weights=wgrid, minlength=n + 1)     # full-resolution pixels per component
    big = sizes >= cfg.min_obstacle_pixels
    big[0] = False
    if not big.any():
        return [], kept
    # map each selected cell to its point
    pos = np.full(n_cells, -1, np.int64)
    pos[pts.cell] = np.arange(pts.idx.size)
    lab_flat = labels.ravel()
    px = np.flatnonzero(big[lab_flat])
    lab = lab_flat[px]
    order = np.argsort(lab, kind="stable")
    lab, px = lab[order], px[order]
    pi = pos[px]
    starts = np.concatenate([[0], np.flatnonzero(np.diff(lab)) + 1])
    n_in = np.diff(np.concatenate([starts, [lab.size]]))
    # flat components (5..95 % of down below min_obstacle_height_m) are speckle: one vectorised test for all
    down_sorted = pts.ned_m[pi, 2][np.lexsort((pts.ned_m[pi, 2], lab))]
    height = (_sorted_percentile(down_sorted, starts, n_in, 95.0) - _sorted_percentile(down_sorted, starts, n_in, 5.0))
    W, H = camera.width, camera.height
    FW, FH = frame_size or (W, H)
    q = cfg.percentile
    out = []
    real = height >= cfg.min_obstacle_height_m
    if rho_ground is not None:
        # ground ranged too near lifts it off the plane by metres near the horizon; its range still grows up its
        # rows like the ground's (docs/methods.md, "Obstacles")
        beta = plane_law_slope(1.0 / pts.range_m[pi], rho_ground[pi], starts, n_in, cfg.plane_law_min_span)
        real &= ~(beta >= cfg.plane_law_beta)
    for j in np.flatnonzero(real):
        grp_p, grp_px = pi[starts[j]:starts[j] + n_in[j]], px[starts[j]:starts[j] + n_in[j]]
        kept[grp_p] = True                            # in the sectors whatever its distance
        dist_s = np.sort(pts.dist_m[grp_p])
        if _pct_sorted(dist_s, q) > cfg.max_obstacle_distance_m:
            continue                                  # not listed (analyse keeps <= max_obstacle_distance_m)
        ned = pts.ned_m[grp_p]
        ned_s = np.sort(ned, axis=0)
        p5, p95 = _pct_sorted(ned_s, 5.0), _pct_sorted(ned_s, 95.0)
        med = _pct_sorted(ned_s, 50.0)
        body_med = _pct_sorted(np.sort(pts.body_m[grp_p], axis=0), 50.0)
        los = med - state.position_ned_m
        across = np.array([-los[1], los[0], 0.0])
        n_across = np.linalg.norm(across)
        if n_across > 1e-9:
            a_s = np.sort(ned @ (across / n_across))
            width = float(_pct_sorted(a_s, 95.0) - _pct_sorted(a_s, 5.0))
        else:
            width = 0.0
        rr = pts.range_m[grp_p]
        sg = pts.sigma_m[grp_p] if pts.sigma_m is not None else None
        if sg is not None and np.isfinite(sg).any():
            std = float(_pct_sorted(np.sort(sg[np.isfinite(sg)]), 50.0))
            noise_std = mixture_sigma(sg[np.isfinite(sg)], pts.weight[grp_p][np.isfinite(sg)])
        else:
            rmed = _pct_sorted(np.sort(rr), 50.0)
            std = float(1.4826 * _pct_sorted(np.sort(np.abs(rr - rmed)), 50.0))
            noise_std = std                           # no per-pixel sigma: the spread, as range_std_m
        gy, gx = np.divmod(grp_px, gw)
        out.append(Obstacle(
            id=0, distance_m=float(_pct_sorted(dist_s, q)), distance_median_m=float(_pct_sorted(dist_s, 50.0)),
            horizontal_distance_m=float(_pct_sorted(np.sort(pts.hdist_m[grp_p]), q)),
            bearing_deg=float(np.degrees(np.arctan2(body_med[1], body_med[0]))),
            elevation_deg=float(np.degrees(np.arctan2(-body_med[2], np.hypot(body_med[0], body_med[1])))),
            range_std_m=std, position_ned_m=[float(x) for x in med],
            extent_ned_m=[float(x) for x in (p95 - p5)], width_m=width, height_m=float(p95[2] - p5[2]),
            pixel_count=int(round(pts.weight[grp_p].sum())),
            confidence=float(_pct_sorted(np.sort(pts.confidence[grp_p]), 50.0)),
            bbox_px=_frame_bbox(gx.min() * k, gy.min() * k, min(W - 1, gx.max() * k + k - 1),
                                min(H - 1, gy.max() * k + k - 1), W, H, FW, FH), range_noise_std_m=noise_std))
    out.sort(key=lambda o: o.distance_m)
    return out, kept


def mixture_sigma(sigma_m: np.ndarray, weight=None, p: float = 0.95) -> float:
    """The sigma of the normal distribution whose 5..95 % span is that of the mixture of N(0, s_i^2) (weights
    ``weight``: the full-resolution pixels each point stands for; equal by default): points each off by its own range
    noise spread as the mixture does, wider than the median sigma says where a few pixels carry most of the noise
    (a face near the focus of expansion, its centre ranged from little parallax). Brent's root of the mixture's CDF
    at ``p``, bracketed by the smallest and the largest sigma's quantile."""
    from scipy.optimize import brentq
    from scipy.special import ndtr
    s = np.asarray(sigma_m, float)
    w = np.ones(s.shape) if weight is None else np.asarray(weight, float)
    keep = (s > 0) & (w > 0)
    if not keep.any():
        return math.nan
    s, w = s[keep], w[keep] / w[keep].sum()
    z = 1.6448536269514722                                # the standard normal's 95 % quantile
    lo, hi = float(s.min()) * z, float(s.max()) * z
    if not hi > lo:
        return float(s[0])                                # one sigma: the mixture is that normal
    return brentq(lambda q: float(w @ ndtr(q / s)) - p, lo, hi, xtol=1e-12 * hi) / z


def split_layers(labels, n: int, log_range, mask, gap: float, min_cells: int) -> tuple:
    """Components that hold two layers of range, relabelled as the connected parts of each layer: (labels, n).
    A component's log ranges are split in two at Otsu's threshold; they are two layers when both hold at least
    ``min_cells`` cells and the far layer's 10th percentile lies more than ``gap`` (log) beyond the near layer's 90th. A
    thin object before a far background is one component when the map's window fattens it into a halo of intermediate
    ranges (no jump between neighbours beats the cut); its median point is then the background's. The halo may take a
    tenth of either layer; one surface receding smoothly (a wall seen obliquely) has no such gap. A layer's connected
    pieces smaller than ``min_cells`` go with the other layer (alone they would be dropped as speckle: a split loses
    no pixel of the list)."""
    from scipy import ndimage
    far = np.zeros(labels.shape, bool)
    for lab_j, box in enumerate(ndimage.find_objects(labels), start=1):
        comp = labels[box] == lab_j
        m = int(np.count_nonzero(comp))
        if m < 2 * min_cells:
            continue
        x = np.sort(log_range[box][comp])
        c = np.cumsum(x)
        k = np.arange(1, m)                                  # the near layer: x[:k]
        mu0, mu1 = c[:-1] / k, (c[-1] - c[:-1]) / (m - k)
        k0 = int(np.argmax(k * (m - k) * (mu1 - mu0) ** 2)) + 1  # Otsu: the largest between-class variance
        if min(k0, m - k0) < min_cells:
            continue
        near, farx = x[:k0], x[k0:]
        if _pct_sorted(farx, 10.0) - _pct_sorted(near, 90.0) <= gap:
            continue
        is_far = comp & (log_range[box] >= x[k0])
        small = []
        for part in (comp & ~is_far, is_far):               # a layer's fragments would be dropped as speckle:
            pl, _ = ndimage.label(part)                      # they go with the other layer
            sizes = np.bincount(pl.ravel())
            small.append(part & (sizes < min_cells)[pl])
        is_far = (is_far & ~small[1]) | small[0]
        if min(np.count_nonzero(is_far), np.count_nonzero(comp & ~is_far)) < min_cells:
            continue
        far[box] |= is_far
    if not far.any():
        return labels, n
    a, na = ndimage.label(mask & ~far)
    b, nb = ndimage.label(mask & far)
    return np.where(b > 0, b + na, a), na + nb


def _frame_bbox(u0, v0, u1, v1, W, H, FW, FH) -> list:
    """Map pixels [u0, u1] x [v0, v1] of a W x H grid as the frame pixels they cover on the FW x FH frame (the same
    box on the frame's grid)."""
    if (FW, FH) == (W, H):
        return [int(u0), int(v0), int(u1), int(v1)]
    return [int(u0 * FW // W), int(v0 * FH // H), int(min(FW - 1, -(-(u1 + 1) * FW // W) - 1)),
            int(min(FH - 1, -(-(v1 + 1) * FH // H) - 1))]


class ObstacleTracker:
    """Persistent obstacle ids across range maps: greedy nearest-neighbour association of NED positions within
    a gate of ``max(gate_m, gate_rel * distance)``; tracks unseen for ``max_age_s`` are forgotten."""

    def __init__(self, gate_m: float = 3.0, gate_rel: float = 0.15, max_age_s: float = 2.0):
        self.gate_m, self.gate_rel, self.max_age_s = gate_m, gate_rel, max_age_s
        self._tracks: dict[int, tuple] = {}       # id -> (position_ned_m, last_stamp_us)
        self._next = 1

    def update(self, obstacles: list, stamp_us: int) -> list:
        self._tracks = {i: t for i, t in self._tracks.items() if stamp_us - t[1] <= self.max_age_s * 1e6}
        free = dict(self._tracks)
        for o in sorted(obstacles, key=lambda o: o.distance_m):
            p = np.asarray(o.position_ned_m)
            best, best_d = None, max(self.gate_m, self.gate_rel * o.distance_m)
            for i, (q, _) in free.items():
                d = float(np.linalg.norm(p - q))
                if d <= best_d:
                    best, best_d = i, d
            if best is None:
                best = self._next
                self._next += 1
            else:
                del free[best]
            o.id = best
            self._tracks[best] = (p, stamp_us)
        return obstacles
