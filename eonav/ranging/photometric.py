"""Affine brightness between the two images of a pair: I_a ~ gain I_b + offset, fitted robustly, and image b
brought onto image a's brightness before a method compares them.

A camera's automatic exposure and gain change an image's brightness between frames. The dense method removes a
brightness offset per window but not a gain: with the gain g the residual keeps (g - 1)(I - mean) of every window's
texture. DSO (Engel, Koltun & Cremers 2018) models the same affine change (a, b) per frame. Here it is fitted per
pair without depth, at the pair's sparse tracks (``eonav.ranging.tracks``: corners of a tracked into b): the means
of small windows at the matched points, I_a ~ gain I_b + offset, by iteratively reweighted least squares (Tukey's
biweight, so that occluded and mismatched points drop out). A fit with too few points, too little brightness spread
among them, a gain outside ``max_gain_ratio`` or a change too small to matter is not applied. Where the windows'
means spread little against the noise (fine texture), the least-squares gain is attenuated towards 1.
"""
from __future__ import annotations

from dataclasses import dataclass, replace

import cv2
import numpy as np

from eonav import InputError
from eonav.geometry.camera import View
from eonav.ranging.tracks import IdentityMemo, Tracks, median_1d, track_points, tukey_weights


@dataclass(frozen=True)
class BrightnessFit:
    """I_a ~ gain I_b + offset; ``used``: trusted and applied; ``reason``: why not, or "ok"."""
    gain: float
    offset: float
    n_points: int
    used: bool
    reason: str


def _sample(img_f32: np.ndarray, pts: np.ndarray) -> np.ndarray:
    """Bilinear samples of an image at points (n x 2, x y)."""
    m = pts.reshape(1, -1, 2).astype(np.float32)
    return cv2.remap(img_f32, m[..., 0], m[..., 1], cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE).ravel()


def _median(x: np.ndarray):
    """``np.median`` of a 1-D array, the same value in the array's dtype (``median_1d``, without its overhead)."""
    return x.dtype.type(median_1d(x))


def box_means(img: np.ndarray, window: int) -> np.ndarray:
    """The mean of the window x window box about every pixel (float32, ``cv2.blur``)."""
    return cv2.blur(np.asarray(img, np.float32), (window, window))


class RecentMeans(IdentityMemo):
    """``box_means`` of the last ``size`` images, looked up by the array's identity: in a stream each frame's
    brightness fit blurs it as image a and, a frame later, as image b (the same values; the images must not be edited
    in place, as a View's image is not)."""

    def __call__(self, img: np.ndarray, window: int) -> np.ndarray:
        return self.get((img,), window, lambda: box_means(img, window))


recent_means = RecentMeans(4)
"""The process's memo of ``box_means`` for the fusion's pair checks (one thread: the fusion runner's)."""


def fit_brightness(img_a: np.ndarray, img_b: np.ndarray, tracks: Tracks | None = None, *, window: int = 7,
                   min_points: int = 30, min_spread: float = 8.0, max_gain_ratio: float = 1.5,
                   min_change: float = 2.0, means=box_means) -> BrightnessFit:
    """Robust affine brightness I_a ~ gain I_b + offset between two grey images (module docstring).

    tracks: the pair's point tracks (``eonav.ranging.tracks.track_points``; computed here when None). window: side
    of the box whose mean is compared at each matched point (pixels; a mean is insensitive to a small
    misregistration). min_spread: least robust spread (grey levels) of the points' brightness in b: with less, a
    gain cannot be told from an offset. max_gain_ratio: a gain beyond [1 / r, r] is not an exposure change but a
    bad fit. min_change: the least brightness change (grey levels, the larger at the points' 10th and 90th
    percentile of b) worth correcting: below the residual's own noise a correction adds its fit's error only.
    means: ``box_means`` or a memo of it (``recent_means``)."""
    if img_a.ndim != 2 or img_b.ndim != 2:
        raise InputError(f"fit_brightness: expected two grey images, got shapes {img_a.shape} and {img_b.shape}")
    tracks = tracks if tracks is not None else track_points(img_a, img_b)
    n = len(tracks)
    if n < min_points:
        return BrightnessFit(1.0, 0.0, n, False, f"{n} tracked points (< {min_points})")
    ma = _sample(means(img_a, window), tracks.pts_a)
    mb = _sample(means(img_b, window), tracks.pts_b)
    if 1.4826 * _median(np.abs(mb - _median(mb))) < min_spread:
        return BrightnessFit(1.0, 0.0, n, False, f"brightness spread of the points below {min_spread:g} grey levels")
    X = np.stack([mb, np.ones_like(mb)], axis=1).astype(np.float64)
    y = ma.astype(np.float64)
    w = np.ones_like(y)
    p = np.array([1.0, 0.0])
    for _ in range(10):                                     # IRLS, Tukey's biweight at 4.685 robust sigmas
        sw = np.sqrt(w)
        p = np.linalg.lstsq(X * sw[:, None], y * sw, rcond=None)[0]
        w = tukey_weights(y - X @ p, 0.5)
        if np.count_nonzero(w > 0) < min_points:
            return BrightnessFit(1.0, 0.0, n, False, "too few inliers of the brightness fit")
    gain, offset = float(p[0]), float(p[1])
    if not (1.0 / max_gain_ratio <= gain <= max_gain_ratio):
        return BrightnessFit(gain, offset, n, False, f"gain {gain:.3f} outside [1/{max_gain_ratio:g}, {max_gain_ratio:g}]")
    lo, hi = np.percentile(mb, [10, 90])
    change = max(abs((gain - 1.0) * lo + offset), abs((gain - 1.0) * hi + offset))
    if change < min_change:
        return BrightnessFit(gain, offset, n, False, f"change {change:.2f} grey levels below {min_change:g}")
    return BrightnessFit(gain, offset, n, True, "ok")


def match_brightness(view_a: View, view_b: View, tracks: Tracks | None = None, **fit_params) -> tuple[View, BrightnessFit]:
    """View b with its image mapped to view a's brightness (gain I_b + offset, float32) when the fit is trusted,
    else view b itself; and the fit."""
    fit = fit_brightness(view_a.image, view_b.image, tracks, **fit_params)
    if not fit.used:
        return view_b, fit
    img = np.multiply(view_b.image, np.float32(fit.gain), dtype=np.float32)
    img += np.float32(fit.offset)
    return replace(view_b, image=img), fit


__all__ = ["BrightnessFit", "box_means", "RecentMeans", "recent_means", "fit_brightness", "match_brightness"]
