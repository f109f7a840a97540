"""Cameras, vehicle states and views: the inputs of every range estimator.

A ``Camera`` is intrinsics (pixels) plus its mount on the body (eqs. 10-12): lens centre at
``l_body_m`` (FRD, metres) and angles ``eps_rad`` = [eps1 about Zc, eps2 about Yc, eps3 about Xc].
A ``VehicleState`` is the vehicle pose in NED (eqs. 13-15). A ``View`` is an image taken by one
camera at one state. ``pair_geometry`` gives the relative pose and the exact pixel mapping between
two views for any inverse range: the basis of every method.
"""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from eonav import InputError
from eonav.geometry.frames import (T_body_ned_from_quat, T_body_ned_from_ypr, T_cam_body_from_eps,
                       relative_pose)


@dataclass(frozen=True)
class Camera:
    """Pinhole camera: pixel (u right, v down, centres at integers); x_p = u - cx, y_p = v - cy."""
    name: str
    width: int
    height: int
    fx: float
    fy: float
    cx: float
    cy: float
    l_body_m: np.ndarray = field(default_factory=lambda: np.zeros(3))
    eps_rad: np.ndarray = field(default_factory=lambda: np.zeros(3))

    def __post_init__(self):
        object.__setattr__(self, "l_body_m", np.asarray(self.l_body_m, float).reshape(3))
        object.__setattr__(self, "eps_rad", np.asarray(self.eps_rad, float).reshape(3))
        if self.width <= 0 or self.height <= 0:
            raise InputError(f"camera {self.name!r}: width/height must be positive, got {self.width}x{self.height}")
        if not (self.fx > 0 and self.fy > 0):
            raise InputError(f"camera {self.name!r}: fx, fy must be positive pixels, got fx={self.fx} fy={self.fy}")
        vals = [self.cx, self.cy, *self.l_body_m, *self.eps_rad]
        if not np.all(np.isfinite(vals)):
            raise InputError(f"camera {self.name!r}: cx, cy, mount must be finite")

    @property
    def T_cam_body(self) -> np.ndarray:
        """T1, eq. (11)."""
        return T_cam_body_from_eps(self.eps_rad)

    def pixel_grid(self):
        """(u, v) float32 arrays of shape (height, width)."""
        v, u = np.mgrid[0:self.height, 0:self.width].astype(np.float32)
        return u, v

    def rays(self):
        """Per-pixel [1, x_p/fx, y_p/fy] (float32, H x W each): camera-frame point at unit range x_c = 1."""
        u, v = self.pixel_grid()
        return (np.ones_like(u), (u - np.float32(self.cx)) / np.float32(self.fx),
                (v - np.float32(self.cy)) / np.float32(self.fy))


@dataclass(frozen=True)
class VehicleState:
    """Vehicle pose: position of the body origin in NED and T2 = T_body_ned (eq. 14)."""
    position_ned_m: np.ndarray
    T_body_ned: np.ndarray
    t_s: float = 0.0

    def __post_init__(self):
        p = np.asarray(self.position_ned_m, float).reshape(3)
        T = np.asarray(self.T_body_ned, float).reshape(3, 3)
        if not (np.all(np.isfinite(p)) and np.all(np.isfinite(T))):
            raise InputError("vehicle state: position_ned_m and attitude must be finite")
        if np.abs(T @ T.T - np.eye(3)).max() > 1e-6 or np.linalg.det(T) < 0:     # orthonormal, and not a reflection
            raise InputError("vehicle state: T_body_ned is not a rotation matrix")
        object.__setattr__(self, "position_ned_m", p)
        object.__setattr__(self, "T_body_ned", T)

    @classmethod
    def from_ypr(cls, position_ned_m, ypr_rad, t_s: float = 0.0) -> "VehicleState":
        y, p, r = np.asarray(ypr_rad, float).reshape(3)
        return cls(position_ned_m, T_body_ned_from_ypr(y, p, r), t_s)

    @classmethod
    def from_quat(cls, position_ned_m, q_wxyz, t_s: float = 0.0, what: str = "q_wxyz") -> "VehicleState":
        """From the attitude quaternion (MAVLink ATTITUDE_QUATERNION: body -> NED). A quaternion whose norm is
        off 1 by more than 1e-3 is an error (InputError naming ``what``), not silently normalised."""
        q = np.asarray(q_wxyz, float).reshape(4)
        n = float(np.linalg.norm(q))
        if not (np.isfinite(n) and abs(n - 1.0) <= 1e-3):
            raise InputError(f"{what}: expected a unit quaternion, got {q.tolist()} (norm {n:.6f})")
        return cls(position_ned_m, T_body_ned_from_quat(q), t_s)


@dataclass
class View:
    """One image (grey float32, H x W, any linear scale) taken by ``camera`` at ``state``."""
    camera: Camera
    state: VehicleState
    image: np.ndarray

    def __post_init__(self):
        img = np.asarray(self.image)
        if img.ndim != 2:
            raise InputError(f"view image must be 2-D grey, got shape {img.shape}")
        if img.shape != (self.camera.height, self.camera.width):
            raise InputError(f"image is {img.shape[1]}x{img.shape[0]} but camera {self.camera.name!r} "
                             f"is {self.camera.width}x{self.camera.height}")
        self.image = img.astype(np.float32, copy=False)


@dataclass(frozen=True)
class PairGeometry:
    """Relative pose of view a in view b: X_b = R_ba X_a + t_ba_m (paper camera frames)."""
    cam_a: Camera
    cam_b: Camera
    R_ba: np.ndarray
    t_ba_m: np.ndarray

    @property
    def baseline_m(self) -> float:
        return float(np.linalg.norm(self.t_ba_m))

    def ray_terms(self):
        """A = R_ba m and B = t for every pixel of a (m = [1, x_p/fx, y_p/fy]): X_b / x_c = A + B * rho.

        This is eq. (24) written as X_b/x_c = m + k_rot + k_trans*rho with k_rot = (R - I) m.
        Returns A0, A1, A2 (float32 H x W) and B (3,) float.
        """
        m0, m1, m2 = self.cam_a.rays()
        R = self.R_ba.astype(np.float32)
        A0 = R[0, 0] * m0 + R[0, 1] * m1 + R[0, 2] * m2
        A1 = R[1, 0] * m0 + R[1, 1] * m1 + R[1, 2] * m2
        A2 = R[2, 0] * m0 + R[2, 1] * m1 + R[2, 2] * m2
        return A0, A1, A2, self.t_ba_m.astype(np.float32)

    def point_rays(self, pts_a) -> np.ndarray:
        """A = R_ba m (3 x n, float64) of points of a (n x 2, x y pixels): X_b / x_c = A + t rho, as ``ray_terms``
        for any sub-pixel points (tracks) instead of the pixel grid."""
        pts = np.asarray(pts_a, np.float64)
        ca = self.cam_a
        m = np.stack([np.ones(len(pts)), (pts[:, 0] - ca.cx) / ca.fx, (pts[:, 1] - ca.cy) / ca.fy])
        return np.asarray(self.R_ba, float) @ m

    def map_to_b(self, inv_range_per_m, terms=None):
        """Exact pixel (u_b, v_b) in image b of each pixel of a at inverse range rho = 1/x_c (1/m).

        Generalises eqs. (25)-(26) to two cameras with different intrinsics:
        u_b = cx_b + fx_b (A1 + B1 rho) / (A0 + B0 rho), and likewise v_b.
        Also returns the depth ratio x_c,b / x_c,a = A0 + B0 rho (<= 0: behind camera b).
        """
        A0, A1, A2, B = terms if terms is not None else self.ray_terms()
        rho = np.asarray(inv_range_per_m, dtype=np.float32)
        den = A0 + B[0] * rho
        with np.errstate(divide="ignore", invalid="ignore"):
            inv = 1.0 / den
            u_b = self.cam_b.cx + self.cam_b.fx * (A1 + B[1] * rho) * inv
            v_b = self.cam_b.cy + self.cam_b.fy * (A2 + B[2] * rho) * inv
        return u_b.astype(np.float32), v_b.astype(np.float32), den


def pair_geometry(view_a: View, view_b: View) -> PairGeometry:
    """Relative pose between two views (docs/conventions.md, "Two views"), for one camera over time or two cameras at once."""
    ca, cb = view_a.camera, view_b.camera
    R, t = relative_pose(ca.T_cam_body, view_a.state.T_body_ned, view_a.state.position_ned_m, ca.l_body_m,
                         cb.T_cam_body, view_b.state.T_body_ned, view_b.state.position_ned_m, cb.l_body_m)
    return PairGeometry(ca, cb, R, t)


def scaled_camera(cam: Camera, scale: float) -> Camera:
    """``cam`` for images resized by ``scale`` (cv2.INTER_AREA): ``round(scale * size)`` pixels a side (at least 8),
    pixel centres kept: fx' = sx fx and cx' = sx (cx + 0.5) - 0.5 with sx = width' / width (likewise y), so pixel u'
    of the resized image is centred on u = (u' + 0.5) / sx - 0.5 of the original. A range map located at a scale is
    on this camera's grid (what the locator publishes by default: services/locator.py)."""
    from dataclasses import replace
    w, h = max(8, int(round(cam.width * scale))), max(8, int(round(cam.height * scale)))
    sx, sy = w / cam.width, h / cam.height
    return replace(cam, width=w, height=h, fx=cam.fx * sx, fy=cam.fy * sy,
                   cx=(cam.cx + 0.5) * sx - 0.5, cy=(cam.cy + 0.5) * sy - 0.5)


def frame_pixel_index(small: int, full: int) -> np.ndarray:
    """For each of ``small`` pixels of a grid resized from ``full`` (``scaled_camera``), the full-grid pixel that
    contains its centre: floor((u' + 0.5) full / small), clipped. At scale 0.5 the centre lies on the border of two
    full pixels and the right/lower one is taken; the locator's nearest-neighbour upsampling (``upsample_index``)
    gives both of them this small pixel, so a map scored here or on the upsampled grid sees the same values."""
    return np.minimum(((np.arange(small) + 0.5) * (full / small)).astype(np.int64), full - 1)


def on_grid(full_map, width: int, height: int):
    """``full_map`` (H x W, e.g. a simulator's true range) sampled at the pixel centres of a ``width`` x ``height``
    grid resized from it (``frame_pixel_index``); the map itself when the sizes already agree."""
    a = np.asarray(full_map)
    if a.shape[:2] == (height, width):
        return a
    return a.take(frame_pixel_index(height, a.shape[0]), axis=0).take(frame_pixel_index(width, a.shape[1]), axis=1)
