"""Sparse point tracks between the two images of a pair, and what they say about the pair's known relative pose.

Shi-Tomasi corners of image a tracked into image b by pyramidal Lucas-Kanade (OpenCV), kept where tracking back
lands within ``fb_max_px`` of the start (forward-backward check). A correct relative pose puts every static point's
match on its epipolar line (eqs. 25-26 for rho from 0 to infinity: a straight line in b); the distance of the
matches from their lines measures the pose's error in pixels (``epipolar_residual_px``). The dense methods search
along that line only, so a pose error shifts their matches by as much without their residual showing it: its robust
spread (``pose_sigma_px``) is the pixel error a measurement of this pair shares, whatever its texture. (Its component
along the lines, which changes the range, is not observed from one pair's images; it is taken to be as large. The
fusion sees it where its state knows the points' ranges: ``eonav.fusion.measure.state_shift_px``.)
"""
from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from eonav import InputError
from eonav.geometry.camera import PairGeometry


@dataclass(frozen=True)
class Tracks:
    """Matched points (n x 2, x y pixels) of image a and image b."""
    pts_a: np.ndarray
    pts_b: np.ndarray

    def __len__(self) -> int:
        return len(self.pts_a)


def _to_u8(img: np.ndarray) -> np.ndarray:
    if img.dtype == np.uint8:
        return img
    r = np.rint(img)
    np.clip(r, 0, 255, out=r)
    return r.astype(np.uint8)


def track_points(img_a: np.ndarray, img_b: np.ndarray, *, max_points: int = 200, min_distance_px: int = 10,
                 win_px: int = 15, levels: int = 3, fb_max_px: float = 0.5, max_side_px: int = 180,
                 memo: "ImageMemo | None" = None) -> Tracks:
    """Forward-backward checked Lucas-Kanade tracks of image a's corners into image b (grey, any sizes), on the
    coarsest pyramid level whose shorter side is still at least ``max_side_px`` (points in level-0 pixels, pyrDown alignment:
    level-L pixel x is level-0 pixel 2^L x; ``fb_max_px`` holds on that level). memo: an ``ImageMemo`` whose
    tracking levels and corners of the images it holds are used (the same values)."""
    if img_a.ndim != 2 or img_b.ndim != 2:
        raise InputError(f"track_points: expected two grey images, got shapes {img_a.shape} and {img_b.shape}")
    scale = 1
    while min(*img_a.shape, *img_b.shape) // (2 * scale) >= max_side_px:
        scale *= 2
    n_down = scale.bit_length() - 1           # track on a coarser level of a large image (pyrDown alignment)
    min_dist = max(min_distance_px // scale, 3)
    if memo is None:
        a8, b8 = _tracking_level(img_a, n_down), _tracking_level(img_b, n_down)
        pts = _corners(a8, max_points, min_dist)
    else:
        a8, b8 = memo.level(img_a, n_down), memo.level(img_b, n_down)
        pts = memo.corners(a8, max_points, min_dist)
    if pts is None:
        return Tracks(np.zeros((0, 2), np.float32), np.zeros((0, 2), np.float32))
    lk = dict(winSize=(win_px, win_px), maxLevel=levels,
              criteria=(cv2.TERM_CRITERIA_EPS | cv2.TERM_CRITERIA_COUNT, 30, 0.01))
    pb, st, _ = cv2.calcOpticalFlowPyrLK(a8, b8, pts, None, **lk)
    pts, pb = pts.reshape(-1, 2), pb.reshape(-1, 2)
    hb, wb = b8.shape
    ok = (st.ravel() == 1) & (pb[:, 0] >= 0) & (pb[:, 0] <= wb - 1) & (pb[:, 1] >= 0) & (pb[:, 1] <= hb - 1)
    pts, pb = pts[ok], pb[ok]
    if len(pts):       # back only the points the forward pass kept (LK tracks each point on its own: the same values)
        pa, st2, _ = cv2.calcOpticalFlowPyrLK(b8, a8, pb.reshape(-1, 1, 2), None, **lk)
        ok = (st2.ravel() == 1) & (np.linalg.norm(pa.reshape(-1, 2) - pts, axis=1) <= fb_max_px)
        pts, pb = pts[ok], pb[ok]
    return Tracks((pts * scale).astype(np.float32), (pb * scale).astype(np.float32))


def _tracking_level(img: np.ndarray, n_down: int) -> np.ndarray:
    """The image as uint8, ``n_down`` times pyrDown'ed: what the tracks run on."""
    img8 = _to_u8(img)
    for _ in range(n_down):
        img8 = cv2.pyrDown(img8)
    return img8


def _corners(img8: np.ndarray, max_points: int, min_dist: int):
    """Shi-Tomasi corners of a tracking level (n x 1 x 2 float32, or None)."""
    return cv2.goodFeaturesToTrack(img8, maxCorners=max_points, qualityLevel=0.01, minDistance=min_dist, blockSize=7)


class IdentityMemo:
    """The results of the last ``size`` calls, each held with the arguments it was computed from: a call whose
    identity arguments are the very objects held (``is``) and whose value key is equal gets the held result. It holds
    those objects, so an identity names the same object while it is held."""

    def __init__(self, size: int = 2):
        self.size = int(size)
        self._held: list = []            # (identity arguments, value key, result), newest last
        self.hits = 0

    def get(self, ids: tuple, key, compute):
        """The held result for the objects ``ids`` and the value ``key``, else ``compute()``, then held."""
        for held_ids, k, v in self._held:
            if all(a is b for a, b in zip(held_ids, ids)) and k == key:
                self.hits += 1
                return v
        v = compute()
        self._held = (self._held + [(ids, key, v)])[-self.size:] if self.size > 0 else []
        return v


class ImageMemo:
    """The tracking levels (``_tracking_level``) of the last ``size`` images and the corners of the last two levels,
    looked up by the arrays' identity: in a stream each frame is tracked as image a and then, a frame later, as
    image b, and a wide pair tracks the newest frame's corners again (the same values; the images must not be
    edited in place, as a View's image is not)."""

    def __init__(self, size: int = 4):
        self._levels = IdentityMemo(size)
        self._corners = IdentityMemo(min(size, 2))

    def level(self, img: np.ndarray, n_down: int) -> np.ndarray:
        return self._levels.get((img,), n_down, lambda: _tracking_level(img, n_down))

    def corners(self, img8: np.ndarray, max_points: int, min_dist: int):
        return self._corners.get((img8,), (max_points, min_dist), lambda: _corners(img8, max_points, min_dist))


class RecentTracks(IdentityMemo):
    """``track_points`` of the last ``size`` image pairs, looked up by the arrays' identity: the fusion's scheduler
    tracks each frame against the camera's previous one (its pose check) and the measurement of that same pair
    tracks it again (its pair checks); the second call gets the first's tracks (the same values). A new pair reuses
    its images' tracking levels and image a's corners where they were computed for an earlier pair
    (``ImageMemo``). The images must not be edited in place after they are tracked (a View's image is not)."""

    def __init__(self, size: int = 2):
        super().__init__(size)
        self.images = ImageMemo(2 * self.size) if self.size > 0 else None

    def __call__(self, img_a: np.ndarray, img_b: np.ndarray) -> Tracks:
        return self.get((img_a, img_b), None, lambda: track_points(img_a, img_b, memo=self.images))


recent_tracks = RecentTracks()
"""The process's memo of the default ``track_points`` (one thread: the fusion runner's)."""


def epipolar_residual_px(geo: PairGeometry, tracks: Tracks):
    """(d, normal): signed distance (px of b) of each match from its point's epipolar line under the pair's pose
    and the unit normal of that line (n x 2); NaN where the pose puts the point behind b or the pair has no
    baseline. The line runs through the point's image at rho = 0, (cx + fx A1 / A0, cy + fy A2 / A0), along the
    derivative of eqs. (25)-(26) there, (fx (B1 A0 - B0 A1), fy (B2 A0 - B0 A2)) (``EpipolarMap``'s C1, C2), with
    A = R_ba m, m = [1, x_p / fx, y_p / fy], B = t_ba."""
    cb = geo.cam_b
    pb = tracks.pts_b.astype(np.float64)
    A = geo.point_rays(tracks.pts_a)
    B = np.asarray(geo.t_ba_m, float)
    with np.errstate(divide="ignore", invalid="ignore"):
        u0 = cb.cx + cb.fx * A[1] / A[0]
        v0 = cb.cy + cb.fy * A[2] / A[0]
        du = cb.fx * (B[1] * A[0] - B[0] * A[1])
        dv = cb.fy * (B[2] * A[0] - B[0] * A[2])
        n = np.hypot(du, dv)
        normal = np.stack([dv / n, -du / n], axis=1)
        d = (pb[:, 0] - u0) * normal[:, 0] + (pb[:, 1] - v0) * normal[:, 1]
    ok = (A[0] > 1e-6) & (n > 1e-12 * max(cb.fx, cb.fy))
    return np.where(ok, d, np.nan), np.where(ok[:, None], normal, np.nan)


def median_1d(x: np.ndarray) -> float:
    """``np.median`` of an array's values (as with axis=None), the same value (its partition and the mean of the two
    middle values), without its generic overhead (~10 us a call, 8-10 calls per robust fit below)."""
    x = np.ravel(x)
    n = x.size
    if n == 0:
        return float(np.median(x))              # NaN with its warning, as np.median
    k = n // 2
    part = np.partition(x, (k, n - 1) if n % 2 else (k - 1, k, n - 1))      # n - 1: a NaN sorts last, as there
    m = 0.0 + part[k] if n % 2 else (0.0 + part[k - 1] + part[k]) / 2      # np.mean's sum starts at +0.0
    return float("nan") if np.isnan(part[-1]) else float(m)


def tukey_weights(r: np.ndarray, min_scale: float) -> np.ndarray:
    """Tukey's biweight weights of residuals r at 4.685 robust sigmas (1.4826 MAD, at least ``min_scale``): the
    IRLS step of the robust fits here and in ``eonav.ranging.photometric``."""
    sc = max(1.4826 * median_1d(np.abs(r)), min_scale)
    u = r / (4.685 * sc)
    return np.where(np.abs(u) < 1, (1 - u * u) ** 2, 0.0)


def pose_shift_px(geo: PairGeometry, tracks: Tracks, min_tracks: int = 20, min_share: float = 0.25) -> float:
    """Length (px) of the image shift that the pair's pose error puts on its matches: the 2-vector s fitted
    robustly (Tukey IRLS) to the matches' distances from their epipolar lines, d_i = n_i . s (n_i the lines' unit
    normals). A small rotation error moves every point of b by about one shift; the tracks' own errors are
    independent from point to point and average out of s (their spread, not s, grows with a wide baseline's
    distortion). Where the lines are all nearly parallel (a sideways motion) only s's component across them is
    seen: a direction whose share of the normal equations (eigenvalue / weights' sum) is below ``min_share`` is
    left out of s instead of taking the noise's whim. NaN with fewer than ``min_tracks`` usable matches."""
    if len(tracks) == 0:
        return float("nan")
    d, nrm = epipolar_residual_px(geo, tracks)
    ok = np.isfinite(d)
    d, nrm = d[ok], nrm[ok]
    if d.size < min_tracks:
        return float("nan")
    w = np.ones_like(d)
    s = np.zeros(2)
    for _ in range(8):
        nw = (nrm * w[:, None]).T
        ev, V = np.linalg.eigh(nw @ nrm)
        rhs = V.T @ (nw @ d)
        keep = ev > min_share * w.sum()
        s = V @ np.where(keep, rhs / np.where(keep, ev, 1.0), 0.0)
        w = tukey_weights(d - nrm @ s, 0.05)
        if w.sum() < min_tracks / 2:
            return float("nan")
    return float(np.hypot(*s))


class RecentShifts(IdentityMemo):
    """``pose_shift_px`` of the last ``size`` (tracks, pair geometry) asked for, looked up by the tracks' identity and
    the geometry's values (relative pose and both cameras' intrinsics, bit for bit): the fusion's scheduler measures
    each frame's shift to the camera's previous one (its pose check) and the measurement of that same pair asks
    again with the same tracks (``recent_tracks``) and an equal geometry; the second call gets the first's value."""

    @staticmethod
    def _key(geo: PairGeometry) -> tuple:
        ca, cb = geo.cam_a, geo.cam_b
        return (np.asarray(geo.R_ba, float).tobytes(), np.asarray(geo.t_ba_m, float).tobytes(),
                (ca.fx, ca.fy, ca.cx, ca.cy), (cb.fx, cb.fy, cb.cx, cb.cy))

    def __call__(self, geo: PairGeometry, tracks: Tracks) -> float:
        return self.get((tracks,), self._key(geo), lambda: pose_shift_px(geo, tracks))


recent_pose_shift = RecentShifts()
"""The process's memo of the default ``pose_shift_px`` (one thread: the fusion runner's)."""


__all__ = ["Tracks", "track_points", "IdentityMemo", "ImageMemo", "RecentTracks", "recent_tracks", "epipolar_residual_px", "pose_shift_px",
           "RecentShifts", "recent_pose_shift", "median_1d", "tukey_weights"]
