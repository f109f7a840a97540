"""A numpy formulation (float32 array operations) of the fill's numba kernels (eonav.ranging.methods._fill_kernels),
the reference that tests/test_fill.py checks them against. The functions take and write what the kernels do;
``use_reference(monkeypatch)`` makes ``fill.fill_unmeasured`` (and so the dense method's fill) run them instead."""
from __future__ import annotations

import types

import cv2
import numpy as np

from eonav.ranging.methods import fill
from eonav.ranging.rangemap import FILLED, OCCLUDED, OUT_OF_VIEW, VALID

F32 = np.float32


def cell_sums(rho, std, flags, xs, ys, g1, n, sr, sx, sy, sv):
    """Per cell of 2^g1 pixels, over its measured pixels (VALID, rho finite): count, sums of rho, x, y and std^2
    (std not finite: 0), exact sums with partial edge cells, into the zeroed cell arrays. Returns (number of
    measured pixels, sum of their rho)."""
    h, w = rho.shape
    k = 2 ** g1
    sup = ((flags & np.uint8(VALID)) != 0) & np.isfinite(rho)
    var = np.zeros((h, w), F32)
    np.copyto(var, std, where=sup & np.isfinite(std))
    var *= var
    r = np.zeros((h, w), F32)
    np.copyto(r, rho, where=sup)
    sup_f = sup.astype(F32)
    for out, a in zip((n, sr, sx, sy, sv), (sup_f, r, sup_f * xs[None, :], sup_f * ys[:, None], var)):
        a = np.pad(a, ((0, n.shape[0] * k - h), (0, n.shape[1] * k - w)))
        out[...] = a.reshape(n.shape[0], k, n.shape[1], k).sum(axis=(1, 3), dtype=np.float64)
    return int(np.count_nonzero(sup)), float(r.sum(dtype=np.float64))


def plane(S0, S1, S2, S3, S4, S5, S6, S7, S8, S9, S10, S11, xc, yc, min_share, min_det, p_o, v_o, b_o, c_o, lev_o):
    """Weighted least-squares plane r = mr + b (x - mx) + c (y - my) of each cell's window sums (count, sums of x,
    y, r, xx, xy, yy, xr, yr, rr, noise variance, pixels in the image): its prediction, error variance (residual
    variance x (1 + (1 + leverage) / n)), slopes and leverage at the cell centres (xc per column, yc per row); the
    prediction NaN where fewer than min_share of the window's pixels inside the image are measured, or too little
    spread in x and y."""
    S = (S0, S1, S2, S3, S4, S5, S6, S7, S8, S9, S10, S11)
    xc, yc = xc[None, :], yc[:, None]
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
        res = np.maximum(res, S[10] * inv_n)
        v = res * (F32(1) + (F32(1) + lev) * inv_n)
    bad = ~((n >= F32(min_share) * S[11]) & (det > F32(min_det)) & np.isfinite(p) & np.isfinite(v))
    p[bad] = np.nan
    for out, a in zip((p_o, v_o, b_o, c_o, lev_o), (p, v, b, c, lev)):
        out[...] = a


def moments(n, sr, sx, sy, sv, k1, h, w, M):
    """The 12 moments of the first octave's cells into M: count, sums of x, y, rho, the cell means' products
    (sums x mean), the mean noise variance and the cell's pixels inside the h x w image (cells of k1 pixels)."""
    with np.errstate(divide="ignore", invalid="ignore"):
        inv = np.where(n > 0, 1.0 / n, F32(0)).astype(F32)
    xc, yc = sx * inv, sy * inv
    rows = np.minimum(k1, h - k1 * np.arange(n.shape[0])).astype(F32)
    cols = np.minimum(k1, w - k1 * np.arange(n.shape[1])).astype(F32)
    M[...] = np.stack([n, sx, sy, sr, sx * xc, sx * yc, sy * yc, sr * xc, sr * yc, sr * sr * inv, sv * inv,
                       rows[:, None] * cols[None, :]])


def down(M, out):
    """Sums over 2 x 2 cells of M's last two axes into out (an odd last row / column sums what it has)."""
    hg, wg = out.shape[-2:]
    h, w = M.shape[-2:]
    m = np.pad(M, ((0, 0), (0, 2 * hg - h), (0, 2 * wg - w)))
    out[...] = m[:, 0::2, 0::2] + m[:, 1::2, 0::2]
    out += m[:, 0::2, 1::2]
    out += m[:, 1::2, 1::2]


def window_sums(M, S):
    """Each moment's sum over the 7 x 7 cells about each cell (zeros beyond the grid): OpenCV's box filter."""
    for m, s in zip(M, S):
        s[...] = cv2.boxFilter(m, -1, (7, 7), normalize=False, borderType=cv2.BORDER_CONSTANT)


def _up(m: np.ndarray, shape, k: int) -> np.ndarray:
    """Each cell's value on the 2^k x finer grid of ``shape``: element (y, x) takes cell (y >> k, x >> k)."""
    rows = np.minimum(np.arange(shape[0]) >> k, m.shape[0] - 1)
    cols = np.minimum(np.arange(shape[1]) >> k, m.shape[1] - 1)
    return m[rows[:, None], cols[None, :]]


def _along(b, c, x, y, xp, yp, k: int) -> np.ndarray:
    """Change of a plane of slopes (b, c) (per element) from the centres (xp, yp) of the coarser cells to points
    (x, y) 2^k times finer."""
    ix = np.minimum(np.arange(x.size) >> k, xp.size - 1)
    iy = np.minimum(np.arange(y.size) >> k, yp.size - 1)
    return b * (x - xp[ix])[None, :] + c * (y - yp[iy])[:, None]


def merge(p, v, lev, b, c, xp, yp, pk, vk, lk, bk, ck, xc, yc, lev_max):
    """One coarse-to-fine step, in place on the finer octave's planes: a cell keeps its own plane where it has one
    (unless it is an extrapolation and its parent's an interpolation), its variance plus the squared disagreement with
    the parent's plane carried to it; else takes the parent's, carried along it to the cell's centre."""
    p, v, lev, b, c = (_up(a, pk.shape, 1) for a in (p, v, lev, b, c))
    p += _along(b, c, xc, yc, xp, yp, 1)
    own = np.isfinite(pk) & ((lk <= lev_max) | ~(lev <= lev_max))
    d = pk - p
    d *= d
    np.copyto(vk, vk + d, where=own & np.isfinite(d))
    for fine, parent in ((pk, p), (vk, v), (lk, lev), (bk, b), (ck, c)):
        np.copyto(fine, parent, where=~own)


def to_pixels(p, v, lev, b, c, xs, ys, xp, yp, g1, ref, flags, no_fill, exclude, use_exclude, max_rel_std, rho_far,
              lev_max, strict, use_strict, strict_rel_std, rho, std, rng, conf):
    """Every pixel's fill from its cell's plane (in units of ref) carried to it, kept where sigma <= max_rel_std rho,
    rho >= rho_far, the pixel is not VALID, has none of the no_fill bits, is not excluded, and lies within the
    support (leverage <= lev_max) or out of view of b (not occluded): rho, std, range, confidence written and FILLED
    set; a pixel of ``strict`` (use_strict) regardless of its no_fill bits and exclusion, within strict_rel_std.
    Returns the number filled."""
    shape = rho.shape
    p, v, lev, b, c = (_up(a, shape, g1) for a in (p, v, lev, b, c))
    rho_f = (p + _along(b, c, xs, ys, xp, yp, g1)) * ref
    std_f = np.sqrt(v) * abs(ref)
    st = np.broadcast_to(strict, shape) if use_strict else np.zeros(shape, bool)
    lim = np.where(st, np.float32(strict_rel_std), np.float32(max_rel_std))
    with np.errstate(invalid="ignore"):
        keep = (std_f <= lim * rho_f) & (rho_f >= rho_far)
        inside = lev <= lev_max
    may = (flags & (np.uint8(VALID) | no_fill)) == 0
    if use_exclude:
        may &= ~exclude
    keep &= np.where(st, (flags & np.uint8(VALID)) == 0, may)
    inside |= (flags & np.uint8(OUT_OF_VIEW | OCCLUDED)) == np.uint8(OUT_OF_VIEW)
    keep &= inside
    np.copyto(rho, rho_f, where=keep)
    np.copyto(std, std_f, where=keep)
    with np.errstate(divide="ignore", invalid="ignore"):
        np.copyto(rng, 1.0 / rho_f, where=keep)
        np.copyto(conf, rho_f / std_f, where=keep)
    flags |= keep.view(np.uint8) * np.uint8(FILLED)
    return int(np.count_nonzero(keep))


KERNELS = types.SimpleNamespace(cell_sums=cell_sums, moments=moments, down=down, window_sums=window_sums, plane=plane,
                                merge=merge, to_pixels=to_pixels)


def use_reference(monkeypatch) -> None:
    """fill.fill_unmeasured with these functions in place of the numba kernels."""
    monkeypatch.setattr(fill, "_K", KERNELS)
