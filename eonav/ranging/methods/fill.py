"""Inverse range for the pixels a pair cannot measure, inferred from the measured ones around them (flag FILLED).

A plane's inverse range is an affine function of the image coordinates (a point X = x_c (1, x_n, y_n) on the plane
n . X = d has rho = 1 / x_c = (n_1 + n_2 x_n + n_3 y_n) / d), so a weighted least-squares plane through the measured
rho of a window predicts rho at a hole, also just outside the measured region (the ground band that has left image
b). Windows grow by octaves (7 x 7 cells of 2^g pixels, g = 2..7: 28 .. 896 px wide); each cell takes the finest
window with enough measured support. Every window's sums are 7 x 7 box sums of per-cell moments, each octave's
moments the 2 x 2 sums of the finer one's (no per-pixel loop).

The 1-sigma of a filled rho is the plane fit's prediction error (the window's residual variance, which a depth edge
inflates, scaled for the distance from the support's centroid) plus the squared disagreement with the next coarser
window's prediction: a plane that holds at two scales is trusted, one that does not is not. Its calibration against
truth: docs/methods.md, "Figures".

Cells of 4 px (first octave 2). The pixel passes (sums into the cells, the cells' planes back to the pixels with
the gating), the cells' moments, octave and window sums and the per-cell plane fits run in numba kernels
(``_fill_kernels``, the only implementation); tests/fill_reference.py is the numpy / OpenCV formulation the tests
check them against.
"""
from __future__ import annotations

import numpy as np

from eonav.ranging.rangemap import OCCLUDED, TRUNCATION
from eonav.ranging.methods._common import numba_kernels

_K = numba_kernels("_fill_kernels")

F32 = np.float32
# not filled: a pixel hidden in image b, or whose last step was past the first-order model's trust, sits at a depth
# edge, where a plane through its neighbours mixes two surfaces (Middlebury: filled with a median error of 15-20 %
# against 2-7 % for the low-texture and ill-conditioned ones)
NO_FILL = OCCLUDED | TRUNCATION
# largest leverage of an interpolation (d^T C^-1 d; a pixel at the rim of a half-plane of support has 3, one inside a
# hole ringed by support ~0): at 3 the fast preset's sky took a 2-4 px band beside a pole's measured pixels
LEV_MAX = 1.0
FIRST_OCTAVE = 2

# least share of a window's pixels inside the image that must be measured, per octave from the first (finer windows
# need more: a window 3/4 empty is mostly a hole's own rim, where depth edges are). Of the part inside the image, not
# of the whole window: a 24 x 24 image got no fill at all (its windows are larger than it), and a corner cell's
# finest windows could never qualify (sim presets at 512: coverage -1.9 .. +0 points, medians -0.05 .. +0.02 pp)
MIN_SUPPORT = (0.3, 0.25, 0.2, 0.15, 0.15, 0.15)
_WIN = 7        # window, cells of the octave's grid


def _cell_shape(shape, g: int):
    return -(-shape[0] // 2 ** g), -(-shape[1] // 2 ** g)


def _centres(n_cells: int, g: int, n_px: int, scale: float) -> np.ndarray:
    """Scaled coordinate of the centres of n_cells cells of 2^g pixels along an axis of n_px pixels."""
    return ((np.arange(n_cells) * 2.0 ** g + 0.5 * (2 ** g - 1) - 0.5 * (n_px - 1)) * scale).astype(F32)


def _fit_cells(n, sr, sx, sy, sv, shape, g1: int, scale: float):
    """The plane of every first-octave cell (p, v, lev, b, c; rho in the units of the sums) and the cells' centres
    (xp row, yp column vectors): each octave's planes at its own cell centres, then coarse to fine."""
    h, w = shape
    # the samples are the cells' means, at the centroid of their measured pixels (a half-measured cell's mean lies
    # half a cell off its centre: on steep ground 1 % of rho per pixel); the sums of squares and products are
    # those of the means (n * mean^2 ...), so the window's residual is the scatter of the cell means about the
    # plane, not the slope across a cell nor the per-pixel noise (1/n of it in a cell mean)
    # (sv * inv: each cell mean's noise variance, sum sigma^2 / n, weighted by n; the last: the cells' pixel counts
    # in the image, so a window's support share is of its part inside the image: near a border or in an image
    # smaller than the window a constant share could never be met)
    M = np.empty((12,) + n.shape, F32)
    _K.moments(n, sr, sx, sy, sv, 2 ** g1, h, w, M)
    fits = []
    for k, min_share in enumerate(MIN_SUPPORT):
        g = g1 + k
        if k and _WIN * 2 ** (g - 1) >= 2 * max(h, w):
            break            # the previous window already spans the image from any cell
        shg = _cell_shape((h, w), g)
        if k:
            M, Mk = np.empty((12,) + shg, F32), M
            _K.down(Mk, M)
        xc, yc = _centres(shg[1], g, w, scale), _centres(shg[0], g, h, scale)
        win_px = _WIN * 2 ** g
        min_det = (0.05 * (win_px * scale) ** 2 / 12) ** 2
        out = [np.empty(shg, F32) for _ in range(5)]         # p, v, b, c, lev
        S = np.empty_like(M)
        _K.window_sums(M, S)
        _K.plane(*S, xc, yc, min_share, min_det, *out)
        fits.append((xc, yc) + tuple(out))
    # coarse to fine: a cell keeps its own plane where it has one, else takes its parent's, carried along the
    # parent's plane to the cell's centre -- except that an interpolation (leverage <= LEV_MAX) is not replaced by
    # a finer extrapolation (a hole wider than the fine window); a cell's own pick gains its squared disagreement
    # with the parent's
    p = v = b = c = lev = xp = yp = None
    for i in range(len(fits) - 1, -1, -1):
        xc, yc, pk, vk, bk, ck, lk = fits[i]
        if p is not None:
            _K.merge(p, v, lev, b, c, xp, yp, pk, vk, lk, bk, ck, xc, yc, F32(LEV_MAX))
        p, v, b, c, lev = pk, vk, bk, ck, lk
        xp, yp = xc, yc
    return p, v, lev, b, c, xp, yp


def _axes(shape):
    h, w = shape
    scale = 2.0 / max(h, w)
    return (scale, ((np.arange(w) - 0.5 * (w - 1)) * scale).astype(F32),
            ((np.arange(h) - 0.5 * (h - 1)) * scale).astype(F32))


def _cells(rho, flags, std, g1: int):
    """The planes of the first-octave cells (``_fit_cells``) from the VALID pixels' sums, rho in units of the
    measured mean (returned too, with the pixels' coordinate vectors); None without support."""
    h, w = rho.shape
    scale, xs, ys = _axes((h, w))
    sums = [np.zeros(_cell_shape((h, w), g1), F32) for _ in range(5)]
    std_in = std if std is not None else np.full((h, w), np.nan, F32)
    cnt, tot = _K.cell_sums(rho, std_in, flags, xs, ys, g1, *sums)
    if cnt == 0:
        return None
    ref = tot / cnt or 1.0       # the measured mean: rho in units of it (float32 sums of O(1) values)
    n, sr, sx, sy, sv = sums
    sr *= F32(1.0 / ref)
    sv *= F32(1.0 / (ref * ref))
    return _fit_cells(n, sr, sx, sy, sv, (h, w), g1, scale), ref, xs, ys


def fill_unmeasured(rho, std, flags, rng, conf, max_rel_std: float, rho_far: float = 0.0, exclude=None,
                    no_fill: int = NO_FILL, strict=None, strict_rel_std: float = 0.0) -> int:
    """In place on a method's outputs: every pixel without a measurement (not VALID, not OCCLUDED or TRUNCATION)
    whose fill has a relative sigma within max_rel_std (the rule VALID pixels meet) gets the filled rho, its sigma,
    range 1/rho, confidence rho/sigma and the FILLED flag (its other flags say why it was not measured). Only a
    pixel out of view of image b is extrapolated (the ground band that has left the image: a plane carries on);
    any other is filled only inside its window's support (leverage <= LEV_MAX): a textureless pixel beyond the measured
    ones may be sky (the fast preset's faint sky took the terrain's plane: 2.3 % of it finite). ``exclude``: more
    pixels not to fill (the dense method's infinity test: a point at infinity explains them as well). rho_far:
    nothing is filled farther than this (the pair's far limit: beyond it a finite range means nothing; a fill
    among sky pixels at infinity took a tiny rho). no_fill: the flag bits of pixels never filled (default
    ``NO_FILL``). strict: pixels (bool) filled whatever their no_fill bits and ``exclude`` say, but only within
    the tighter strict_rel_std (a caller's contested pixels: a neighbours' plane may stand in for them only where
    it is far tighter than the rule). Returns the number of pixels filled."""
    cells = _cells(rho, flags, std, FIRST_OCTAVE)
    if cells is None:
        return 0
    (p, v, lev, b, c, xp, yp), ref, xs, ys = cells
    ex = exclude if exclude is not None else np.zeros((1, 1), bool)
    sx = strict if strict is not None else np.zeros((1, 1), bool)
    return int(_K.to_pixels(p, v, lev, b, c, xs, ys, xp, yp, FIRST_OCTAVE, F32(ref), flags, np.uint8(no_fill), ex,
                            exclude is not None, F32(max_rel_std), F32(rho_far), F32(LEV_MAX), sx, strict is not None,
                            F32(strict_rel_std), rho, std, rng, conf))


__all__ = ["fill_unmeasured", "MIN_SUPPORT", "NO_FILL"]
