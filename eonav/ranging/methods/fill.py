"""Inverse range for the pixels a pair cannot measure, inferred from the measured ones around them (flag FILLED).

A plane's inverse range is an affine function of the image coordinates (a point X = x_c (1, x_n, y_n) on the plane
n . X = d has rho = 1 / x_c = (n_1 + n_2 x_n + n_3 y_n) / d), so a weighted least-squares plane through the measured
rho of a window predicts rho at a hole, also just outside the measured region (the ground band that has left image
b). Windows grow by octaves (7 x 7 cells of 2^g pixels, g = 2..7: 28 .. 896 px wide); each cell takes the finest
window with enough measured support. Every window's sums come from box filters of per-cell moments (no per-pixel
loop).

The 1-sigma of a filled rho is the plane fit's prediction error (the window's residual variance, which a depth edge
inflates, scaled for the distance from the support's centroid) plus the squared disagreement with the next coarser
window's prediction: a plane that holds at two scales is trusted, one that does not is not. Its calibration against
truth: docs/methods.md, "Figures".
"""
from __future__ import annotations

import cv2
import numpy as np

from eonav.ranging.rangemap import FILLED, OCCLUDED, OUT_OF_VIEW, TRUNCATION, VALID
from eonav.ranging.methods._common import optional_kernels

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


def _box(m: np.ndarray) -> np.ndarray:
    return cv2.boxFilter(m, -1, (_WIN, _WIN), normalize=False, borderType=cv2.BORDER_CONSTANT)


def _down(m: np.ndarray, shape) -> np.ndarray:
    """Sums over 2 x 2 cells of the last two axes into ``shape`` (an odd last row / column of cells sums what it
    has)."""
    h, w = m.shape[-2:]
    if (h, w) != (2 * shape[0], 2 * shape[1]):
        m = np.pad(m, ((0, 0),) * (m.ndim - 2) + ((0, 2 * shape[0] - h), (0, 2 * shape[1] - w)))
    out = m[..., 0::2, 0::2] + m[..., 1::2, 0::2]
    out += m[..., 0::2, 1::2]
    out += m[..., 1::2, 1::2]
    return out


def _cell_shape(shape, g: int):
    return -(-shape[0] // 2 ** g), -(-shape[1] // 2 ** g)


def _up(m: np.ndarray, shape, k: int) -> np.ndarray:
    """Each cell's value on the 2^k x finer grid of ``shape`` (element (y, x) takes cell (y >> k, x >> k), as the
    kernels index; cv2.resize's nearest neighbour maps by the size ratio, which differs at sizes not divisible)."""
    rows = np.minimum(np.arange(shape[0]) >> k, m.shape[0] - 1)
    cols = np.minimum(np.arange(shape[1]) >> k, m.shape[1] - 1)
    return m[rows[:, None], cols[None, :]]


def _centres(n_cells: int, g: int, n_px: int, scale: float) -> np.ndarray:
    """Scaled coordinate of the centres of n_cells cells of 2^g pixels along an axis of n_px pixels."""
    return ((np.arange(n_cells) * 2.0 ** g + 0.5 * (2 ** g - 1) - 0.5 * (n_px - 1)) * scale).astype(F32)


def _plane(S, xc, yc, min_share: float, min_det: float):
    """Weighted least-squares plane r = mr + b (x - mx) + c (y - my) of the window sums S (12 planes): prediction,
    its error variance, slopes b, c and leverage at the cell centres (xc row, yc column); NaN where fewer than
    min_share of the window's pixels inside the image (S[11]) are measured, or too little spread in x and y.
    Error variance: residual variance x (1 + (1 + leverage) / n), as for a new measurement -- the residual holds
    the support's noise besides the surface's departure from the plane, so this errs large where the noise
    dominates (the filled pixels' z spread is below 1: docs/methods.md); without the noise's share it erred
    small."""
    with np.errstate(divide="ignore", invalid="ignore", over="ignore"):
        n = S[0]
        inv_n = 1.0 / n
        mx, my, mr = S[1] * inv_n, S[2] * inv_n, S[3] * inv_n
        cxx = S[4] * inv_n - mx * mx
        cxy = S[5] * inv_n - mx * my
        cyy = S[6] * inv_n - my * my
        cxr = S[7] * inv_n - mx * mr
        cyr = S[8] * inv_n - my * mr
        crr = S[9] * inv_n - mr * mr
        det = cxx * cyy - cxy * cxy
        inv_det = 1.0 / det
        b = (cyy * cxr - cxy * cyr) * inv_det
        c = (cxx * cyr - cxy * cxr) * inv_det
        res = np.maximum(crr - b * cxr - c * cyr, 0) * n / np.maximum(n - 3, 1)
        dx, dy = xc - mx, yc - my
        p = mr + b * dx + c * dy
        lev = (cyy * dx * dx - F32(2) * cxy * dx * dy + cxx * dy * dy) * inv_det
        # (the scatter of the cell means is at least what their own noise gives: support that agrees only because
        # it was clipped, e.g. rho >= 0 at infinity, is no tighter than its measurements)
        res = np.maximum(res, S[10] * inv_n)
        v = res * (F32(1) + (F32(1) + lev) * inv_n)
    bad = ~((n >= F32(min_share) * S[11]) & (det > F32(min_det)) & np.isfinite(p) & np.isfinite(v))
    p[bad] = np.nan
    return p, v, b, c, lev


def _along(b, c, x, y, xp, yp, k: int) -> np.ndarray:
    """Change of a plane of slopes (b, c) (per element) from the centres (xp, yp) of the coarser cells to points
    (x, y) 2^k times finer (row / column coordinate vectors)."""
    ix = np.minimum(np.arange(x.size) >> k, xp.size - 1)
    iy = np.minimum(np.arange(y.size) >> k, yp.size - 1)
    return b * (x - xp[ix])[None, :] + c * (y - yp[iy])[:, None]


def _cell_sums_numpy(rho, support, std, xs, ys, g1: int, sh1):
    """Per cell of 2^g1 pixels, over its measured pixels: count, sums of rho, x, y and std^2 (numpy path of
    _fill_kernels.cell_sums; exact sums, partial edge cells included). Returns them and (count, sum of rho)."""
    h, w = rho.shape
    k = 2 ** g1
    sup = support & np.isfinite(rho)
    var = np.zeros((h, w), F32)
    if std is not None:
        np.copyto(var, std, where=sup & np.isfinite(std))
        var *= var
    r = np.zeros((h, w), F32)
    np.copyto(r, rho, where=sup)
    sup_f = sup.astype(F32)
    out = []
    for a in (sup_f, r, sup_f * xs[None, :], sup_f * ys[:, None], var):
        a = np.pad(a, ((0, sh1[0] * k - h), (0, sh1[1] * k - w)))
        out.append(a.reshape(sh1[0], k, sh1[1], k).sum(axis=(1, 3), dtype=np.float64).astype(F32))
    return out, int(np.count_nonzero(sup)), float(r.sum(dtype=np.float64))


def _fit_cells(n, sr, sx, sy, sv, shape, g1: int, scale: float, K=None):
    """The plane of every first-octave cell (p, v, lev, b, c; rho in the units of the sums) and the cells' centres
    (xp row, yp column vectors): each octave's planes at its own cell centres, then coarse to fine."""
    h, w = shape
    # the samples are the cells' means, at the centroid of their measured pixels (a half-measured cell's mean lies
    # half a cell off its centre: on steep ground 1 % of rho per pixel); the sums of squares and products are
    # those of the means (n * mean^2 ...), so the window's residual is the scatter of the cell means about the
    # plane, not the slope across a cell nor the per-pixel noise (1/n of it in a cell mean)
    with np.errstate(divide="ignore", invalid="ignore"):
        inv = np.where(n > 0, 1.0 / n, F32(0)).astype(F32)
    xc, yc = sx * inv, sy * inv
    # (sv * inv: each cell mean's noise variance, sum sigma^2 / n, weighted by n; the last: the cells' pixel counts
    # in the image, so a window's support share is of its part inside the image: near a border or in an image
    # smaller than the window a constant share could never be met)
    k1 = 2 ** g1
    rows = np.minimum(k1, h - k1 * np.arange(n.shape[0])).astype(F32)
    cols = np.minimum(k1, w - k1 * np.arange(n.shape[1])).astype(F32)
    M = np.stack([n, sx, sy, sr, sx * xc, sx * yc, sy * yc, sr * xc, sr * yc, sr * sr * inv, sv * inv,
                  rows[:, None] * cols[None, :]])
    fits = []
    for k, min_share in enumerate(MIN_SUPPORT):
        g = g1 + k
        if k and _WIN * 2 ** (g - 1) >= 2 * max(h, w):
            break            # the previous window already spans the image from any cell
        shg = _cell_shape((h, w), g)
        if k:
            M = _down(M, shg)
        xc, yc = _centres(shg[1], g, w, scale), _centres(shg[0], g, h, scale)
        win_px = _WIN * 2 ** g
        min_det = (0.05 * (win_px * scale) ** 2 / 12) ** 2
        if K is not None:
            out = [np.empty(shg, F32) for _ in range(5)]
            K.plane(*[_box(m) for m in M], xc, yc, min_share, min_det, *out)
            fits.append((xc, yc) + tuple(out))
        else:
            fits.append((xc, yc) + _plane([_box(m) for m in M], xc[None, :], yc[:, None], min_share, min_det))
    # coarse to fine: a cell keeps its own plane where it has one, else takes its parent's, carried along the
    # parent's plane to the cell's centre -- except that an interpolation (leverage <= LEV_MAX) is not replaced by
    # a finer extrapolation (a hole wider than the fine window); a cell's own pick gains its squared disagreement
    # with the parent's
    p = v = b = c = xp = yp = None
    for i in range(len(fits) - 1, -1, -1):
        xc, yc, pk, vk, bk, ck, lk = fits[i]
        if p is None:
            p, v, b, c, lev = pk, vk, bk, ck, lk
        elif K is not None:
            K.merge(p, v, lev, b, c, xp, yp, pk, vk, lk, bk, ck, xc, yc, F32(LEV_MAX))
            p, v, b, c, lev = pk, vk, bk, ck, lk
        else:
            shk = pk.shape
            p, v, lev, b, c = (_up(a, shk, 1) for a in (p, v, lev, b, c))
            p += _along(b, c, xc, yc, xp, yp, 1)
            own = np.isfinite(pk) & ((lk <= F32(LEV_MAX)) | ~(lev <= F32(LEV_MAX)))
            d = pk - p
            d *= d
            np.copyto(vk, vk + d, where=own & np.isfinite(d))
            np.copyto(p, pk, where=own)
            np.copyto(v, vk, where=own)
            np.copyto(lev, lk, where=own)
            np.copyto(b, bk, where=own)
            np.copyto(c, ck, where=own)
        xp, yp = xc, yc
    return p, v, lev, b, c, xp, yp


def _axes(shape):
    h, w = shape
    scale = 2.0 / max(h, w)
    return (scale, ((np.arange(w) - 0.5 * (w - 1)) * scale).astype(F32),
            ((np.arange(h) - 0.5 * (h - 1)) * scale).astype(F32))


def _cells(rho, support_or_flags, std, g1: int, K):
    """Cell sums (kernel or numpy path) scaled to rho in units of the measured mean; None without support."""
    h, w = rho.shape
    scale, xs, ys = _axes((h, w))
    sh1 = _cell_shape((h, w), g1)
    if K is not None:
        sums = [np.zeros(sh1, F32) for _ in range(5)]
        std_in = std if std is not None else np.full((h, w), np.nan, F32)
        cnt, tot = K.cell_sums(rho, std_in, support_or_flags, xs, ys, g1, *sums)
    else:
        sup = support_or_flags if support_or_flags.dtype == bool else (support_or_flags & np.uint8(VALID)) != 0
        sums, cnt, tot = _cell_sums_numpy(rho, sup, std, xs, ys, g1, sh1)
    if cnt == 0:
        return None
    ref = tot / cnt or 1.0       # the measured mean: rho in units of it (float32 sums of O(1) values)
    n, sr, sx, sy, sv = sums
    sr *= F32(1.0 / ref)
    sv *= F32(1.0 / (ref * ref))
    return _fit_cells(n, sr, sx, sy, sv, (h, w), g1, scale, K), ref, xs, ys


def fill_inverse_range(rho: np.ndarray, support: np.ndarray, std: np.ndarray | None = None,
                       first_octave: int = FIRST_OCTAVE):
    """Inverse range, its 1-sigma and the leverage of every pixel from the plane fits of the measured ``support``
    pixels (rho finite there; ``std`` their 1-sigma, None: noiseless) around it; the caller keeps them where
    it has no measurement. float32 H x W each, NaN where no window had support. Leverage (d^T C^-1 d of the
    pixel's offset d from the support's centroid, C their spatial covariance): 0 at the centroid, 3 at the rim of a
    half-plane of support; beyond, an extrapolation. Computed per cell of 2^first_octave pixels and carried to each
    pixel along the cell's plane, in float32 with the coordinates scaled to [-1, 1] and rho to the measured mean
    (the window sums subtract large means: relative error of a variance ~1e-7 / its share of the mean square, far
    below any sigma that matters). The numpy path throughout (fill_unmeasured runs the kernels when it can)."""
    h, w = rho.shape
    g1 = int(first_octave)
    cells = _cells(rho, support, std, g1, None)
    if cells is None:
        nan = np.full((h, w), np.nan, F32)
        return nan, nan.copy(), nan.copy()
    (p, v, lev, b, c, xp, yp), ref, xs, ys = cells
    # to every pixel: along its cell's plane from the cell's centre (a cell of 4 px spans 1.5 px of offset: on the
    # ground near the horizon 0.75 % of rho)
    p, v, lev, b, c = (_up(a, (h, w), g1) for a in (p, v, lev, b, c))
    p += _along(b, c, xs, ys, xp, yp, g1)
    p *= F32(ref)
    s = np.sqrt(v)
    s *= F32(abs(ref))
    return p, s, lev


def fill_unmeasured(rho, std, flags, rng, conf, max_rel_std: float, rho_far: float = 0.0, exclude=None,
                    kernels: bool | None = None) -> int:
    """In place on a method's outputs: every pixel without a measurement (not VALID, not OCCLUDED or TRUNCATION)
    whose fill has a relative sigma within max_rel_std (the rule VALID pixels meet) gets the filled rho, its sigma,
    range 1/rho, confidence rho/sigma and the FILLED flag (its other flags say why it was not measured). Only a
    pixel out of view of image b is extrapolated (the ground band that has left the image: a plane carries on);
    any other is filled only inside its window's support (leverage <= LEV_MAX): a textureless pixel beyond the measured
    ones may be sky (the fast preset's faint sky took the terrain's plane: 2.3 % of it finite). ``exclude``: more
    pixels not to fill (the dense method's infinity test: a point at infinity explains them as well). rho_far:
    nothing is filled farther than this (the pair's far limit: beyond it a finite range means nothing; a fill
    among sky pixels at infinity took a tiny rho). kernels: the numba passes (None: when installed; False: the
    numpy path). Returns the number of pixels filled."""
    K = optional_kernels("_fill_kernels") if kernels is None or kernels else None
    if kernels and K is None:
        raise ImportError("fill_unmeasured(kernels=True) needs numba")
    if K is not None:
        cells = _cells(rho, flags, std, FIRST_OCTAVE, K)
        if cells is None:
            return 0
        (p, v, lev, b, c, xp, yp), ref, xs, ys = cells
        ex = exclude if exclude is not None else np.zeros((1, 1), bool)
        return int(K.to_pixels(p, v, lev, b, c, xs, ys, xp, yp, FIRST_OCTAVE, F32(ref), flags, np.uint8(NO_FILL),
                               ex, exclude is not None, F32(max_rel_std), F32(rho_far), F32(LEV_MAX),
                               rho, std, rng, conf))
    support = (flags & np.uint8(VALID)) != 0
    rho_f, std_f, lev = fill_inverse_range(rho, support, std, first_octave=FIRST_OCTAVE)
    with np.errstate(invalid="ignore"):
        keep = std_f <= F32(max_rel_std) * rho_f          # (NaN: False; implies rho_f > 0)
        keep &= rho_f >= F32(rho_far)
        inside = lev <= F32(LEV_MAX)
    keep &= (flags & np.uint8(VALID | NO_FILL)) == 0
    inside |= (flags & np.uint8(OUT_OF_VIEW | OCCLUDED)) == np.uint8(OUT_OF_VIEW)
    keep &= inside
    if exclude is not None:
        keep &= ~exclude
    np.copyto(rho, rho_f, where=keep)
    np.copyto(std, std_f, where=keep)
    with np.errstate(divide="ignore", invalid="ignore"):
        np.copyto(rng, 1.0 / rho_f, where=keep)
        np.copyto(conf, rho_f / std_f, where=keep)
    flags |= keep.view(np.uint8) * np.uint8(FILLED)
    return int(np.count_nonzero(keep))


__all__ = ["fill_inverse_range", "fill_unmeasured", "MIN_SUPPORT", "NO_FILL"]
