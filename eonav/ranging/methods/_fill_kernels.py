"""Numba kernels of the fill (``fill.fill_unmeasured``): the pixels' sums into the first octave's cells
(``cell_sums``), the cells' moments (``moments``), their 2 x 2 sums into the next octave (``down``), the 7 x 7
window sums of every moment (``window_sums``), each octave's weighted plane fit per cell (``plane``), the
coarse-to-fine merge of the octaves (``merge``), and the cells' planes back to the pixels with the gating and the
writing of the outputs (``to_pixels``): one pass each. ``moments`` and ``down`` add in numpy's order (float32) and
``window_sums`` in float64 cast to float32, as OpenCV's unnormalised box filter on float32 does: the same sums. The
planes are fitted in float64 inside. tests/fill_reference.py holds the numpy / OpenCV formulation that
tests/test_fill.py checks them against.
"""
from __future__ import annotations

import math

import numpy as np
from numba import njit

from eonav.ranging.rangemap import FILLED, OCCLUDED, OUT_OF_VIEW, VALID

_JIT = dict(cache=True, fastmath=False, nogil=True, error_model="numpy")
_VALID = np.uint8(VALID)
_FILLED = np.uint8(FILLED)
_OOV_OCC = np.uint8(OUT_OF_VIEW | OCCLUDED)
_OOV = np.uint8(OUT_OF_VIEW)


@njit(**_JIT)
def cell_sums(rho, std, flags, xs, ys, g1, n, sr, sx, sy, sv):
    """Per cell of 2^g1 pixels, over its measured pixels (VALID, rho finite): count, sum of rho, of x, of y and of
    std^2 (std not finite: 0) into the zeroed float32 cell arrays. Returns (number of measured pixels, sum of
    their rho) for the caller's scaling."""
    h, w = rho.shape
    cnt = 0
    tot = 0.0
    for y in range(h):
        cy = y >> g1
        yv = ys[y]
        for x in range(w):
            r = rho[y, x]
            if (flags[y, x] & _VALID) == 0 or not math.isfinite(r):
                continue
            cx = x >> g1
            n[cy, cx] += 1.0
            sr[cy, cx] += r
            sx[cy, cx] += xs[x]
            sy[cy, cx] += yv
            s = std[y, x]
            if math.isfinite(s):
                sv[cy, cx] += s * s
            cnt += 1
            tot += r
    return cnt, tot


@njit(**_JIT)
def moments(n, sr, sx, sy, sv, k1, h, w, M):
    """The 12 moments of the first octave's cells (cells of k1 pixels of an h x w image) into M (12 x cells,
    float32): count, sums of x, y, rho, the cell means' products (n xm xm, n xm ym, n ym ym, n rm xm, n rm ym,
    n rm rm), the mean noise variance (sum std^2 / n) and the cell's pixels inside the image."""
    hc, wc = n.shape
    one = np.float32(1.0)
    for y in range(hc):
        rows = np.float32(min(k1, h - k1 * y))
        for x in range(wc):
            nn = n[y, x]
            inv = one / nn if nn > 0 else np.float32(0.0)
            ax, ay, ar = sx[y, x], sy[y, x], sr[y, x]
            xm = ax * inv
            ym = ay * inv
            M[0, y, x] = nn
            M[1, y, x] = ax
            M[2, y, x] = ay
            M[3, y, x] = ar
            M[4, y, x] = ax * xm
            M[5, y, x] = ax * ym
            M[6, y, x] = ay * ym
            M[7, y, x] = ar * xm
            M[8, y, x] = ar * ym
            M[9, y, x] = ar * ar * inv
            M[10, y, x] = sv[y, x] * inv
            M[11, y, x] = rows * np.float32(min(k1, w - k1 * x))


@njit(**_JIT)
def down(M, out):
    """Sums over 2 x 2 cells of M (k x h x w) into out (k x ceil(h/2) x ceil(w/2)), in the order
    ((m00 + m10) + m01) + m11; an odd last row / column sums what it has (zeros added)."""
    nk, h, w = M.shape
    _, hg, wg = out.shape
    z = np.float32(0.0)
    for k in range(nk):
        for y in range(hg):
            y0 = 2 * y
            y1 = y0 + 1
            for x in range(wg):
                x0 = 2 * x
                x1 = x0 + 1
                a = M[k, y0, x0] + (M[k, y1, x0] if y1 < h else z)
                a += M[k, y0, x1] if x1 < w else z
                a += M[k, y1, x1] if (y1 < h and x1 < w) else z
                out[k, y, x] = a


@njit(**_JIT)
def window_sums(M, S):
    """Every moment's sum over the 7 x 7 cells about each cell (zeros beyond the grid) into S (M's shape):
    rows then columns, in float64, cast to float32."""
    nk, h, w = M.shape
    r = 3
    row = np.zeros(w + 2 * r, np.float64)
    rs = np.zeros((h + 2 * r, w), np.float64)
    for k in range(nk):
        for y in range(h):
            for x in range(w):
                row[x + r] = M[k, y, x]
            for x in range(w):
                s = 0.0
                for j in range(2 * r + 1):
                    s += row[x + j]
                rs[y + r, x] = s
        for y in range(h):
            for x in range(w):
                s = 0.0
                for j in range(2 * r + 1):
                    s += rs[y + j, x]
                S[k, y, x] = np.float32(s)


@njit(**_JIT)
def to_pixels(p, v, lev, b, c, xs, ys, xp, yp, g1, ref, flags, no_fill, exclude, use_exclude, max_rel_std, rho_far,
              lev_max, strict, use_strict, strict_rel_std, rho, std, rng, conf):
    """Every pixel without a measurement that may be filled (not VALID, none of the no_fill bits, not excluded)
    takes its cell's plane (p, v, lev, b, c in units of ref, at the cell centres xp, yp) carried to the pixel
    (xs, ys); kept where sigma <= max_rel_std rho, rho >= rho_far and (leverage <= lev_max or the pixel is out of
    view of b, not occluded): rho, std, range, confidence written and FILLED set. A pixel of ``strict`` (when
    use_strict) is filled whatever its no_fill bits and exclusion, but only where sigma <= strict_rel_std rho.
    Returns the number filled."""
    h, w = rho.shape
    hc, wc = p.shape
    nf = 0
    for y in range(h):
        cy = min(y >> g1, hc - 1)
        dy = ys[y] - yp[cy]
        for x in range(w):
            f = flags[y, x]
            lim = max_rel_std
            if use_strict and strict[y, x]:
                if (f & _VALID) != 0:
                    continue
                lim = strict_rel_std
            elif (f & (_VALID | no_fill)) != 0 or (use_exclude and exclude[y, x]):
                continue
            cx = min(x >> g1, wc - 1)
            pc = p[cy, cx]
            if not math.isfinite(pc):
                continue
            rf = np.float32((pc + b[cy, cx] * (xs[x] - xp[cx]) + c[cy, cx] * dy) * ref)
            sf = np.float32(math.sqrt(v[cy, cx]) * abs(ref))
            if not (sf <= lim * rf) or not (rf >= rho_far):
                continue
            if not (lev[cy, cx] <= lev_max) and (f & _OOV_OCC) != _OOV:
                continue
            rho[y, x] = rf
            std[y, x] = sf
            rng[y, x] = np.float32(1.0) / rf
            conf[y, x] = rf / sf
            flags[y, x] = f | _FILLED
            nf += 1
    return nf


@njit(**_JIT)
def plane(S0, S1, S2, S3, S4, S5, S6, S7, S8, S9, S10, S11, xc, yc, min_share, min_det, p, v, b, c, lev):
    """fill._plane per cell in one pass (same formulas, float64 inside): the window sums' weighted plane, its
    prediction and error variance, slopes and leverage at the cell centres; p NaN where the window lacks support."""
    hg, wg = p.shape
    for y in range(hg):
        for x in range(wg):
            n = float(S0[y, x])
            inv_n = 1.0 / n if n != 0.0 else math.inf
            mx, my, mr = S1[y, x] * inv_n, S2[y, x] * inv_n, S3[y, x] * inv_n
            cxx = S4[y, x] * inv_n - mx * mx
            cxy = S5[y, x] * inv_n - mx * my
            cyy = S6[y, x] * inv_n - my * my
            cxr = S7[y, x] * inv_n - mx * mr
            cyr = S8[y, x] * inv_n - my * mr
            crr = S9[y, x] * inv_n - mr * mr
            det = cxx * cyy - cxy * cxy
            inv_det = 1.0 / det if det != 0.0 else math.inf
            bb = (cyy * cxr - cxy * cyr) * inv_det
            cc = (cxx * cyr - cxy * cxr) * inv_det
            res = max(crr - bb * cxr - cc * cyr, 0.0) * n / max(n - 3.0, 1.0)
            res = max(res, S10[y, x] * inv_n)
            dx, dy = xc[x] - mx, yc[y] - my
            pp = mr + bb * dx + cc * dy
            lv = (cyy * dx * dx - 2.0 * cxy * dx * dy + cxx * dy * dy) * inv_det
            vv = res * (1.0 + (1.0 + lv) * inv_n)
            ok = n >= min_share * S11[y, x] and det > min_det and math.isfinite(pp) and math.isfinite(vv)
            p[y, x] = pp if ok else np.nan
            v[y, x] = vv
            b[y, x] = bb
            c[y, x] = cc
            lev[y, x] = lv


@njit(**_JIT)
def merge(p, v, lev, b, c, xp, yp, pk, vk, lk, bk, ck, xc, yc, lev_max):
    """fill._fit_cells' coarse-to-fine step in one pass, in place on the finer octave's arrays (pk, vk, lk, bk, ck):
    a cell keeps its own plane where it has one (unless it is an extrapolation and its parent's an interpolation),
    its variance plus the squared disagreement with the parent's plane carried to it; else takes the parent's."""
    hf, wf = pk.shape
    hc, wc = p.shape
    for y in range(hf):
        cy = min(y >> 1, hc - 1)
        dy = yc[y] - yp[cy]
        for x in range(wf):
            cx = min(x >> 1, wc - 1)
            carried = p[cy, cx] + b[cy, cx] * (xc[x] - xp[cx]) + c[cy, cx] * dy
            own = math.isfinite(pk[y, x]) and (lk[y, x] <= lev_max or not lev[cy, cx] <= lev_max)
            if own:
                d = pk[y, x] - carried
                if math.isfinite(d):
                    vk[y, x] += d * d
            else:
                pk[y, x] = carried
                vk[y, x] = v[cy, cx]
                lk[y, x] = lev[cy, cx]
                bk[y, x] = b[cy, cx]
                ck[y, x] = c[cy, cx]
