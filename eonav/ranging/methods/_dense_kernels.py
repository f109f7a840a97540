"""Numba kernels of the dense method (``dense.locate_dense``): its only implementation of the per-pixel work.

``gn_level`` does one re-linearised Gauss-Newton step of a whole pyramid level in one pass: rows stream through a
ring of window-height term planes (the map into b, b's bilinear samples, the Huber-weighted normal-equation terms),
and as soon as a row's window is complete its window sums (at the coarse levels the shiftable windows' choice,
``_shift_windows_row``), its update and (final step) its uncertainty, flags and classification follow. Nothing
per pixel is written but the outputs. With the slanted window (``dense._slant_shape``) the window sums hold two more
terms and ``_slant_row`` takes the update. ``scharr`` and ``pack_b4p`` prepare a level (a's gradient; b with its
gradient and a zero border as the warp source), ``residual_grid`` samples the residual for the noise estimate.
The coarse epipolar search (``dense._search``) has its kernels here too (``search_*``).

The arithmetic is float32 with fused multiply-adds (``_fma``), as OpenCV computes it. tests/dense_reference.py
formulates the same steps with OpenCV array operations: the search gives the same result bit for bit
(tests/test_dense.py::test_search_kernels_match_reference); the Gauss-Newton steps agree to float rounding (the
window sums add in another order and the borders of the warp round differently:
tests/test_dense.py::test_kernels_match_reference).

Writing kernels numba vectorises: index row views with the loop variable itself, or with unsigned offsets (numba
tests a signed index that varies along the loop for wraparound on every element, which stops the vectorisation);
no views inside per-row loops (each costs ~20 ns of reference counting); keep branches out of the elementwise
loops (selects vectorise).
"""
from __future__ import annotations

import numpy as np
from llvmlite import ir
from numba import njit, types
from numba.core import cgutils
from numba.extending import intrinsic

from eonav.ranging.rangemap import AT_INFINITY, ILL_CONDITIONED, LOW_TEXTURE, OCCLUDED, OUT_OF_VIEW, TRUNCATION, VALID

F32 = np.float32
_ZERO = F32(0.0)
_ONE = F32(1.0)
_TWO = F32(2.0)
_EPS_S0 = F32(1e-6)
_H_MIN = F32(1e-12)
_MASK_IN = F32(0.999)
_OOV, _LOW, _ILL, _TRUNC = np.uint8(OUT_OF_VIEW), np.uint8(LOW_TEXTURE), np.uint8(ILL_CONDITIONED), np.uint8(TRUNCATION)
_OCC = np.uint8(OCCLUDED)
_BAD = np.uint8(OUT_OF_VIEW | LOW_TEXTURE | ILL_CONDITIONED | TRUNCATION)
_VAL = np.uint8(VALID)
_INF_VAL = np.uint8(AT_INFINITY | VALID)
_NAN = F32(np.nan)
_INF = F32(np.inf)

_JIT = dict(cache=True, fastmath=False, nogil=True, error_model="numpy")


@intrinsic
def _fma32(typingctx, a, b, c):
    """a * b + c rounded once (llvm.fma.f32: the hardware's fused multiply-add, as OpenCV's v_fma)."""
    sig = types.float32(types.float32, types.float32, types.float32)

    def codegen(context, builder, signature, args):
        t = args[0].type
        f = cgutils.get_or_insert_function(builder.module, ir.FunctionType(t, [t, t, t]), "llvm.fma.f32")
        return builder.call(f, args)
    return sig, codegen


@njit(inline="always", **_JIT)
def _fma(a, b, c):
    """a * b + c rounded once to float32, as OpenCV's scaleAdd / accumulateProduct / accumulateSquare compute it
    here (fused multiply-add; llvm.fma.f32; a float64 product and sum rounded to float32 would break ties
    differently, at a higher cost)."""
    return _fma32(a, b, c)


# --- the coarse epipolar search (dense._search): per chunk of hypotheses, one pass before and one after the box
# sums (OpenCV's), and one pass for the winner-take-all


@njit(inline="always", **_JIT)
def _rho_disp(d, a0, cn, B0, cap):
    """dense._rho_at_disp of one pixel: rho = D A0^2 / (|C| - D A0 B0) where den > 0 and A0 > 0, else cap;
    np.minimum(rho, cap) (NaN propagates)."""
    t = d * a0
    den = cn - t * B0
    r = (t * a0) / den
    if not ((den > _ZERO) & (a0 > _ZERO)):
        r = cap
    if r > cap or np.isnan(cap):
        r = cap
    return r




_I32_LO = F32(-2147483648.0)
_I32_HI = F32(2147483648.0)
_I32_MIN = np.int32(-2147483648)


@njit(**_JIT)
def search_warp(disp, per_pixel, rows, A0, A1, A2, cn, cap, fx, cx, fy, cy, B0, Q1, Q2, a, b, bw, bw2, bwa, good):
    """One chunk of hypotheses of dense._search (m = len(disp)), on the rows of a padded by symmetric rows (``rows``:
    the padded rows' source rows, hp of them): per pixel the hypothesis' rho (per_pixel: ``_rho_at_disp`` of the
    displacement disp[k], else rho = disp[k]), the map into b, its in-view test (good: 0 <= u_b <= wb - 1,
    0 <= v_b <= hb - 1, 1 / den > 0), and b sampled there as cv2.remap INTER_LINEAR, BORDER_REPLICATE does it
    (OpenCV 5's float interpolation: cvFloor -- INT32_MIN out of range and for NaN, as x86's conversion --, the
    four neighbours clamped into b, two fused multiply-adds along x, one along y); writes the warped b (bw), its
    square (bw2) and its product with a (bwa) as (m * hp, w) planes for the box sums. Per row two loops: the map,
    the clamped neighbours and the weights (vectorised), then the sampling (gathers)."""
    m = disp.shape[0]
    hp = rows.shape[0]
    w = A0.shape[1]
    hb, wb = b.shape
    bf = b.ravel()
    ub_hi = F32(wb - 1)
    vb_hi = F32(hb - 1)
    i00 = np.empty(w, np.int32)
    dxr = np.empty(w, np.int32)
    dyr = np.empty(w, np.int32)
    sxr = np.empty(w, F32)
    syr = np.empty(w, F32)
    for k in range(m):
        dk = F32(disp[k])
        for i in range(hp):
            y = rows[i]
            o = k * hp + i
            for x in range(w):
                a0 = A0[y, x]
                if per_pixel:
                    r = _rho_disp(dk, a0, cn[y, x], B0, cap[y, x])
                else:
                    r = dk
                inv = a0 + B0 * r
                inv = _ONE / inv
                p1 = A1[y, x] * fx
                p1 = p1 + a0 * cx
                p2 = A2[y, x] * fy
                p2 = p2 + a0 * cy
                ub = (p1 + Q1 * r) * inv
                vb = (p2 + Q2 * r) * inv
                good[o, x] = np.uint8((ub >= _ZERO) & (ub <= ub_hi) & (vb >= _ZERO) & (vb <= vb_hi) & (inv > _ZERO))
                fu = np.floor(ub)
                fv = np.floor(vb)
                ix = np.int32(fu) if (fu >= _I32_LO) & (fu < _I32_HI) else _I32_MIN
                iy = np.int32(fv) if (fv >= _I32_LO) & (fv < _I32_HI) else _I32_MIN
                sxr[x] = ub - F32(ix)
                syr[x] = vb - F32(iy)
                x0 = min(max(ix, 0), wb - 1)
                x1 = min(max(ix + 1, 0), wb - 1)
                y0 = min(max(iy, 0), hb - 1)
                y1 = min(max(iy + 1, 0), hb - 1)
                i00[x] = y0 * wb + x0
                dxr[x] = x1 - x0
                dyr[x] = (y1 - y0) * wb
            for x in range(w):
                j = np.uint32(i00[x])
                dx = np.uint32(dxr[x])
                dy = np.uint32(dyr[x])
                p00 = bf[j]
                p10 = bf[j + dy]
                sx = sxr[x]
                v0 = _fma32(sx, bf[j + dx] - p00, p00)
                v1 = _fma32(sx, bf[j + dy + dx] - p10, p10)
                v = _fma32(syr[x], v1 - v0, v0)
                bw[o, x] = v
                bw2[o, x] = v * v
                bwa[o, x] = v * a[y, x]


@njit(**_JIT)
def search_cost(mb, vbb, cab, good, ma, va, noise4, p, cost):
    """Cost 1 - ZNCC of one chunk (m, h, w) from the window sums of the warped b (mb: mean, vbb: mean square,
    cab: mean product with a; (m * hp, w) planes) and a's (ma, va: mean and variance (>= 0), rows of the padded
    a); 2 where the hypothesis is out of view."""
    m, h, w = cost.shape
    hp = h + 2 * p
    for k in range(m):
        for y in range(h):
            i = y + p
            o = k * hp + i
            for x in range(w):
                if good[o, x] == 0:
                    cost[k, y, x] = _TWO
                    continue
                mbv = mb[o, x]
                v = vbb[o, x] - mbv * mbv
                c = cab[o, x] - ma[i, x] * mbv
                if v < _ZERO:
                    v = _ZERO
                v = v * va[i, x]
                v = v + noise4
                v = np.sqrt(v)
                cost[k, y, x] = _ONE - c / v


@njit(**_JIT)
def search_wta(agg, cost, hyp, per_pixel, A0, cn, B0, cap, va, noise2, rho_o, conf_o):
    """Winner-take-all (first minimum over the hypotheses of agg, parabola fit of the sub-sample offset), np.interp of
    the fractional index into the hypotheses (hyp: displacements with per_pixel, else inverse ranges), the rho of
    that displacement (per_pixel: ``_rho_at_disp``), and the confidence clip(1 - cost, 0, 1)^2 x texture
    (va / (va + noise2)), per pixel."""
    n, h, w = agg.shape
    bestr = np.empty(w, F32)
    kbr = np.empty(w, np.int64)
    nanr = np.empty(w, np.bool_)
    for y in range(h):
        # the first minimum over the hypotheses, row by row (vectorised over x)
        for x in range(w):
            c = agg[0, y, x]
            bestr[x] = c
            kbr[x] = 0
            nanr[x] = np.isnan(c)
        for k in range(1, n):
            for x in range(w):
                c = agg[k, y, x]
                nanr[x] |= np.isnan(c)
                lt = c < bestr[x]
                bestr[x] = c if lt else bestr[x]
                kbr[x] = k if lt else kbr[x]
        for x in range(w):
            best = bestr[x]
            kb = kbr[x]
            if nanr[x]:                 # np.min propagates NaN; argmax of an all-False mask is 0
                best = _NAN
                kb = 0
            cb = cost[kb, y, x]
            cm = agg[max(kb - 1, 0), y, x]
            cp = agg[min(kb + 1, n - 1), y, x]
            curv = cm - F32(2.0) * best
            curv = curv + cp
            off = _ZERO
            if (curv > F32(1e-6)) & (kb > 0) & (kb < n - 1):
                off = (F32(0.5) * (cm - cp)) / curv
            if off < F32(-0.5):
                off = F32(-0.5)
            elif off > F32(0.5):
                off = F32(0.5)
            kf = np.float64(kb) + np.float64(off)
            # np.interp(kf, arange(n), hyp)
            if np.isnan(kf):
                d = kf
            elif kf < 0.0:
                d = hyp[0]
            elif kf >= np.float64(n - 1):
                d = hyp[n - 1]
            else:
                j = np.int64(np.floor(kf))
                if np.float64(j) == kf:
                    d = hyp[j]
                else:
                    slope = (hyp[j + 1] - hyp[j]) / (np.float64(j + 1) - np.float64(j))
                    d = slope * (kf - np.float64(j)) + hyp[j]
                    if np.isnan(d):
                        d = slope * (kf - np.float64(j + 1)) + hyp[j + 1]
                        if np.isnan(d) and hyp[j] == hyp[j + 1]:
                            d = hyp[j]
            d32 = F32(d)
            if per_pixel:
                rho_o[y, x] = _rho_disp(d32, A0[y, x], cn[y, x], B0, cap[y, x])
            else:
                rho_o[y, x] = d32
            v = va[y, x]
            tex = v / (v + noise2)
            q = _ONE - cb
            if q < _ZERO:
                q = _ZERO
            elif q > _ONE:
                q = _ONE
            conf_o[y, x] = (q * q) * tex


# --- one Gauss-Newton step of a whole pyramid level in one pass (dense._gauss_newton_step): rows stream through a ring
# of window-height term planes; the window sums, the update and (final) the uncertainty, flags and classification
# of a row follow as soon as its window is complete. Nothing but the ring (a few hundred KiB) is written per pixel.

# ring planes: the five terms of the normal equations (window sums), then the final step's extras, then the
# infinity test's, then the centre values (not summed)
_P_WJJ, _P_WJQ, _P_W, _P_WJ, _P_WQ = 0, 1, 2, 3, 4
_P_G, _P_MX, _P_MY, _P_RR = 5, 6, 7, 8
_P_SE, _P_R0 = 9, 10
_P_E2, _P_MF = 11, 12
_P_WQQ = 13                # w q^2: a window's least-squares cost (shiftable windows)
_P_WJJS, _P_WJS = 14, 15   # wJ J S, wJ S: the slanted window's (S: the shape's field)
_N_PLANES = 16
# window sums (ext rows): the five terms, G / Mx / My (window), G / rr (occlusion window), se / r0^2 (window)
_S_G, _S_MX, _S_MY, _S_G3, _S_R2, _S_SE, _S_R0 = 5, 6, 7, 8, 9, 10, 11
_S_WQQ = 12
_S_WJJS, _S_WJS = 13, 14
_N_SUMS = 15


@njit(inline="always", **_JIT)
def _reflect(v, n):
    """cv2.BORDER_REFLECT's source index of row / column v (fedcba|abcdef|fedcba), for an overhang <= n."""
    if v < 0:
        return -v - 1
    if v >= n:
        return 2 * n - 1 - v
    return v


@njit(inline="always", **_JIT)
def _lerp2(bf, j, dx, dy, sx, sy):
    """Bilinear interpolation in a flat array between its elements j, j + dx (next column) and j + dy (next row):
    two fused multiply-adds along x, one along y, as OpenCV 5's float remap. (Unsigned indices: numba tests a
    signed index for wraparound on every read.)"""
    p00 = bf[j]
    p10 = bf[j + dy]
    v0 = _fma32(sx, bf[j + dx] - p00, p00)
    v1 = _fma32(sx, bf[j + dy + dx] - p10, p10)
    return _fma32(sy, v1 - v0, v0)


@njit(inline="always", **_JIT)
def _map_px(r, a0, p1, p2, B0, Q1, Q2):
    """One pixel's map into b at rho = r (eqs. 25-26 via the affine parts A0, P1, P2 at the pixel):
    (1 / den, u_b, v_b)."""
    d = _ONE / _fma(r, B0, a0)
    return d, _fma(r, Q1, p1) * d, _fma(r, Q2, p2) * d


@njit(inline="always", **_JIT)
def _b4p_index(fu, fv, wb):
    """Flat index (unsigned) in b4p, b's [I, gx, gy, 1] with a border of one zero pixel, of b's pixel (fu, fv)
    (floored coordinates, -1 allowed: the border)."""
    return np.uint64(((np.int64(fv) + 1) * (wb + 2) + np.int64(fu) + 1) * 4)


@njit(**_JIT)
def _sample_row(bfp, hb, wb, R, a0r, a0c, p1r, p1c, p2r, p2c, B0, Q1, Q2, jx, sxy, d_o, s4_o):
    """One row of the map at rho = R (eqs. 25-26 via the affine parts: d = 1 / den, u_b, v_b) and of b's
    [I, gx, gy, in-view] sampled there bilinearly (s4_o: w x 4), zero outside b (cv2.remap INTER_LINEAR,
    BORDER_CONSTANT 0). bfp: b4 with a border of one zero pixel (hb + 2, wb + 2, 4), flat: a sample inside
    (-1, wb) x (-1, hb) reads its four neighbours from it; one outside reads the zero corner (index 0) with zero
    weights. Two passes: the map, the index, the weights and the in-view channel (vectorised; into the row buffers
    jx and sxy), then the gathers of the other three."""
    w = R.shape[0]
    wp = wb + 2
    fw, fh = F32(wb), F32(hb)
    for x in range(w):
        d, u, v = _map_px(R[x], a0r[x] + a0c, p1r[x] + p1c, p2r[x] + p2c, B0, Q1, Q2)
        d_o[x] = d
        inside = (u > F32(-1.0)) & (u < fw) & (v > F32(-1.0)) & (v < fh)
        fu = np.floor(u) if inside else _ZERO
        fv = np.floor(v) if inside else _ZERO
        sx = u - fu if inside else _ZERO
        sy = v - fv if inside else _ZERO
        sxy[0, x] = sx
        sxy[1, x] = sy
        jx[x] = _b4p_index(fu, fv, wb) if inside else np.uint64(0)
        # the in-view channel (constant 1 in b, 0 outside) interpolated as the gathers would, from the
        # neighbours' positions alone
        x0 = _ONE if inside & (fu >= _ZERO) else _ZERO
        x1 = _ONE if inside & (fu + _ONE < fw) else _ZERO
        y0 = _ONE if inside & (fv >= _ZERO) else _ZERO
        y1 = _ONE if inside & (fv + _ONE < fh) else _ZERO
        m00, m01, m10, m11 = x0 * y0, x1 * y0, x0 * y1, x1 * y1
        v0 = _fma32(sx, m01 - m00, m00)
        v1 = _fma32(sx, m11 - m10, m10)
        s4_o[x, 3] = _fma32(sy, v1 - v0, v0)
    rs = np.uint64(4 * wp)
    c4 = np.uint64(4)
    for x in range(w):
        j = np.uint64(jx[x])
        sx, sy = sxy[0, x], sxy[1, x]
        s4_o[x, 0] = _lerp2(bfp, j, c4, rs, sx, sy)
        s4_o[x, 1] = _lerp2(bfp, j + np.uint64(1), c4, rs, sx, sy)
        s4_o[x, 2] = _lerp2(bfp, j + np.uint64(2), c4, rs, sx, sy)


@njit(**_JIT)
def residual_grid(b4p, ia, rw, kc, R, B0, Q1, Q2, step, r_o, inview_o):
    """The residual I_b(map(rho)) - I_a on every step-th row and column (the noise estimate's sample), b sampled as
    in ``gn_level`` (b4p: b's [I, gx, gy, 1] with a zero border), and where it is in view (the in-view channel
    > 0.999 and 1 / den > 0): r_o and inview_o are (ceil(h / step), ceil(w / step))."""
    hb, wb = b4p.shape[0] - 2, b4p.shape[1] - 2
    bfp = b4p.ravel()
    hg, wg = r_o.shape
    rs = np.uint64(4 * (wb + 2))
    c4 = np.uint64(4)
    fw, fh = F32(wb), F32(hb)
    for i in range(hg):
        y = i * step
        for k in range(wg):
            x = k * step
            d, u, v = _map_px(R[y, x], rw[0, x] + kc[0, y], rw[1, x] + kc[1, y], rw[2, x] + kc[2, y], B0, Q1, Q2)
            val = _ZERO
            m = _ZERO
            if (u > F32(-1.0)) & (u < fw) & (v > F32(-1.0)) & (v < fh):
                fu = np.floor(u)
                fv = np.floor(v)
                sx = u - fu
                sy = v - fv
                j = _b4p_index(fu, fv, wb)
                val = _lerp2(bfp, j, c4, rs, sx, sy)
                m = _lerp2(bfp, j + np.uint64(3), c4, rs, sx, sy)
            r_o[i, k] = val - ia[y, x]
            inview_o[i, k] = np.uint8(1) if (m > _MASK_IN) & (d > _ZERO) else np.uint8(0)


@njit(**_JIT)
def _residual_at_infinity_row(bfp, hb, wb, a0r, a0c, p1r, p1c, p2r, p2c, ia, r0_o):
    """One row of the squared residual of a point at infinity (rho = 0: b warped by the rotation alone), NaN where
    any of the four neighbours of the sample is outside b (cv2.remap with a NaN border; ``_row_terms`` leaves
    those pixels out of the test)."""
    w = ia.shape[0]
    rs = np.uint64(4 * (wb + 2))
    c4 = np.uint64(4)
    for x in range(w):
        a0 = a0r[x] + a0c
        r0 = _NAN
        if a0 > _ZERO:
            u = (p1r[x] + p1c) / a0
            v = (p2r[x] + p2c) / a0
            if (u >= _ZERO) & (u < F32(wb - 1)) & (v >= _ZERO) & (v < F32(hb - 1)):
                fu = np.floor(u)
                fv = np.floor(v)
                r0 = _lerp2(bfp, _b4p_index(fu, fv, wb), c4, rs, u - fu, v - fv) - ia[x]
        r0_o[x] = r0 * r0


@njit(**_JIT)
def _row_terms(rs, smp, s4, jrow, y, bfp, hb, wb, ia, gxa, gya, rw, kc, R, S, B0, Q1, Q2, ks, final, inf_mode, slant):
    """Row y's per-pixel terms into the ring row rs (planes x w): the map and b's samples (``_sample_row``, into
    the row buffers smp and s4), the Huber-weighted normal-equation terms (wJ J, wJ q, w, wJ, w q; slant: also
    wJ J S and wJ S, S the window shape's field, ``gn_level``), E2 (a quarter of
    |d map / d rho|^2); final: the in-view mask mf, the masked gradient energy, gradient and squared residual of a;
    inf_mode: the in-view squared residual and the squared residual of a point at infinity. The passes after the
    sampling read row buffers only (numba vectorises them)."""
    w = R.shape[1]
    Ry, iay, gxy, gyy = R[y], ia[y], gxa[y], gya[y]
    c1r, c2r = rw[3], rw[4]
    c1c, c2c = kc[3, y], kc[4, y]
    d_ = smp[2]
    _sample_row(bfp, hb, wb, Ry, rw[0], kc[0, y], rw[1], kc[1, y], rw[2], kc[2, y], B0, Q1, Q2, jrow, smp, d_, s4)
    e2o, wJJo, wJqo, wo, wJo, wqo = rs[_P_E2], rs[_P_WJJ], rs[_P_WJQ], rs[_P_W], rs[_P_WJ], rs[_P_WQ]
    wqqo = rs[_P_WQQ]
    for x in range(w):
        d = d_[x]
        mask = s4[x, 3]
        r = s4[x, 0] - iay[x]
        C1 = c1r[x] + c1c
        C2 = c2r[x] + c2c
        J = (s4[x, 1] + gxy[x]) * C1
        J = _fma(s4[x, 2] + gyy[x], C2, J)
        i2 = d * d
        J = J * i2
        c2 = C1 * C1
        c2 = _fma(C2, C2, c2)
        e2o[x] = c2 * (i2 * i2)
        wgt = (mask * ks) / max(abs(r), ks)
        wJ = wgt * J
        q = J * Ry[x]
        q = q - r
        wJJo[x] = wJ * J
        wJqo[x] = wJ * q
        wo[x] = wgt
        wJo[x] = wJ
        wq = wgt * q
        wqo[x] = wq
        wqqo[x] = wq * q
    if slant:
        Sy, wJJSo, wJSo = S[y], rs[_P_WJJS], rs[_P_WJS]
        for x in range(w):
            wJJSo[x] = wJJo[x] * Sy[x]
            wJSo[x] = wJo[x] * Sy[x]
    if final:
        mfo, Go, rro, mxo, myo = rs[_P_MF], rs[_P_G], rs[_P_RR], rs[_P_MX], rs[_P_MY]
        for x in range(w):
            mf = _ONE if (s4[x, 3] > _MASK_IN) & (d_[x] > _ZERO) else _ZERO
            mfo[x] = mf
            ga, gb = gxy[x], gyy[x]
            G = ga * ga
            G = _fma(gb, gb, G)
            Go[x] = G * mf
            r = s4[x, 0] - iay[x]
            rro[x] = (r * r) * mf
            mxo[x] = ga * mf
            myo[x] = gb * mf
    if inf_mode != 0:
        seo, r0o = rs[_P_SE], rs[_P_R0]
        _residual_at_infinity_row(bfp, hb, wb, rw[0], kc[0, y], rw[1], kc[1, y], rw[2], kc[2, y], iay, r0o)
        # both squared residuals over the pixels where both are in view of b (the test on the part of the window it
        # can see; none: 0 <= 0, the test cannot rule infinity out)
        for x in range(w):
            both = (s4[x, 3] > _MASK_IN) & (r0o[x] == r0o[x])
            rm = s4[x, 0] - iay[x]
            seo[x] = rm * rm if both else _ZERO
            r0o[x] = r0o[x] if both else _ZERO


@njit(**_JIT)
def _window_sum(ring, plane, slot0, n, ext, hs, k, inv_n):
    """Mean over an n x n window (n <= the ring's height, odd) centred on the ring's centre row, into hs[k]: the
    column sums of the n ring rows from slot0 on (cyclic) into ext[k] (w + 2p long, p = half the ring's height),
    reflected at the left and right borders, then summed along the row, times inv_n. One pass each way for n = 3,
    5 and 7 (the defaults), n passes otherwise. Indexed without views (a view per row and term cost ~20 ns each,
    ~3 us a row) and with unsigned offsets (numba tests a signed index that varies along the loop for wraparound on
    every element, which keeps it from vectorising)."""
    win, w = ring.shape[0], ring.shape[2]
    p = win // 2
    up = np.uint64(p)
    s0, s1, s2 = slot0 % win, (slot0 + 1) % win, (slot0 + 2) % win
    if n == 7:
        s3, s4, s5, s6 = (slot0 + 3) % win, (slot0 + 4) % win, (slot0 + 5) % win, (slot0 + 6) % win
        for x in range(w):
            ext[k, np.uint64(x) + up] = ((((((ring[s0, plane, x] + ring[s1, plane, x]) + ring[s2, plane, x])
                                           + ring[s3, plane, x]) + ring[s4, plane, x]) + ring[s5, plane, x])
                                         + ring[s6, plane, x])
    elif n == 5:
        s3, s4 = (slot0 + 3) % win, (slot0 + 4) % win
        for x in range(w):
            ext[k, np.uint64(x) + up] = ((((ring[s0, plane, x] + ring[s1, plane, x]) + ring[s2, plane, x])
                                         + ring[s3, plane, x]) + ring[s4, plane, x])
    elif n == 3:
        for x in range(w):
            ext[k, np.uint64(x) + up] = (ring[s0, plane, x] + ring[s1, plane, x]) + ring[s2, plane, x]
    else:
        for x in range(w):
            ext[k, np.uint64(x) + up] = ring[s0, plane, x]
        for i in range(1, n):
            si = (slot0 + i) % win
            for x in range(w):
                ext[k, np.uint64(x) + up] += ring[si, plane, x]
    for j in range(p):
        ext[k, p - 1 - j] = ext[k, p + j]
        ext[k, p + w + j] = ext[k, p + w - 1 - j]
    o = np.uint64(p - n // 2)
    o1, o2 = o + np.uint64(1), o + np.uint64(2)
    if n == 7:
        o3, o4, o5, o6 = o + np.uint64(3), o + np.uint64(4), o + np.uint64(5), o + np.uint64(6)
        for x in range(w):
            ux = np.uint64(x)
            hs[k, x] = ((((((ext[k, ux + o] + ext[k, ux + o1]) + ext[k, ux + o2]) + ext[k, ux + o3])
                           + ext[k, ux + o4]) + ext[k, ux + o5]) + ext[k, ux + o6]) * inv_n
    elif n == 5:
        o3, o4 = o + np.uint64(3), o + np.uint64(4)
        for x in range(w):
            ux = np.uint64(x)
            hs[k, x] = ((((ext[k, ux + o] + ext[k, ux + o1]) + ext[k, ux + o2]) + ext[k, ux + o3])
                        + ext[k, ux + o4]) * inv_n
    elif n == 3:
        for x in range(w):
            ux = np.uint64(x)
            hs[k, x] = ((ext[k, ux + o] + ext[k, ux + o1]) + ext[k, ux + o2]) * inv_n
    else:
        for x in range(w):
            hs[k, x] = ext[k, np.uint64(x) + o]
        for i in range(1, n):
            oi = o + np.uint64(i)
            for x in range(w):
                hs[k, x] += ext[k, np.uint64(x) + oi]
        for x in range(w):
            hs[k, x] *= inv_n


@njit(**_JIT)
def gn_level(b4p, ia, gxa, gya, rw, kc, R, S, M, inv_g2, B0, Q1, Q2, ks, lam_c, use_cap, cap_hi, win, occ, shift,
             shift_ratio, final, inf_mode, amb_in, fp, noise_info, out, inf_o, std_o, flags_o, rng_o, conf_o, amb_o):
    """One re-linearised Gauss-Newton step of a whole level (b4p: b's [I, gx, gy, 1] with a border of one zero
    pixel): the map, the warp, the terms, their window sums (window win, and occ for the occlusion test; reflected
    borders) and the Levenberg-damped update of every pixel into out (clipped to [0, cap]; cap: the affine cap map
    rw[5] + kc[5] clipped to [0, cap_hi] when use_cap, else cap_hi; shift > 0: shiftable windows,
    ``_shift_windows_row``). S, M (empty: one rho per window, fronto-parallel): the slanted window, whose centre c
    models rho_j = rho_c + A_c (S_j - S_c) over its window (S: the shape's field, A_c its weight from M and
    inv_g2; two more window sums, ``_slant_row``). final: also the uncertainty, flags and classification
    (std_o .. amb_o; fp: the thresholds of dense._Final in the order noise_G, var_k, floor2, trunc2, low_thr,
    occ_px2, occ_thr, orient_min, rho_far, max_rel_std). Infinity test (does a point at infinity explain the window
    as well?): inf_mode 1 writes its verdict into inf_o;
    inf_mode 2 (final) uses it for the flags; otherwise a non-empty amb_in (uint8, a coarser level's verdict) is
    used.
    Returns (n_valid, n_at_infinity)."""
    h, w = R.shape
    p = win // 2
    slant = S.shape[0] > 0
    ring = np.empty((win, _N_PLANES, w), F32)
    hb, wb = b4p.shape[0] - 2, b4p.shape[1] - 2
    bfp = b4p.ravel()
    smp = np.empty((3, w), F32)
    s4 = np.empty((w, 4), F32)
    jrow = np.empty(w, np.int64)
    ext = np.empty((_N_SUMS, w + 2 * p), F32)
    hs = np.empty((_N_SUMS, w), F32)
    # the window sums (ext / hs rows): the five terms; final: G, Mx, My (window), G, rr (occlusion window);
    # inf_mode: se, r0^2 (window). One call site (numba compiles a callee into each caller's site)
    sum_plane = np.array([_P_WJJ, _P_WJQ, _P_W, _P_WJ, _P_WQ, _P_G, _P_MX, _P_MY, _P_G, _P_RR, _P_SE, _P_R0,
                          _P_WQQ, _P_WJJS, _P_WJS])
    sum_n = np.array([win, win, win, win, win, win, win, win, occ, occ, win, win, win, win, win])
    active = np.zeros(_N_SUMS, np.bool_)      # (element by element: numba's slice assignment compiles an error
    for k in range(_N_SUMS):                   # path with string formatting, ~5 s of the kernels' first compile)
        active[k] = (k < 5 or (final and k < 10) or (inf_mode != 0 and 10 <= k < 12) or (k == _S_WQQ and shift > 0)
                     or (slant and k >= _S_WJJS))
    use_amb = amb_in.shape[0] > 0
    hrow = np.empty(w, F32)
    s0row = np.empty(w, F32)
    crow = np.empty(w, F32)
    sel = np.empty((7 if slant else 5, w), F32)
    code = np.empty(w, np.int8)
    ambr = np.zeros(w, np.uint8)
    nv = 0
    ni = 0
    for v in range(-p, h + p):
        _row_terms(ring[(v + p) % win], smp, s4, jrow, _reflect(v, h), bfp, hb, wb, ia, gxa, gya, rw, kc, R, S, B0,
                   Q1, Q2, ks, final, inf_mode, slant)
        y = v - p
        if y < 0:
            continue
        c = (y + p) % win                  # the slot of row y itself
        for k in range(_N_SUMS):
            if not active[k]:
                continue
            n = sum_n[k]
            _window_sum(ring, sum_plane[k], (c - n // 2 + win) % win, n, ext, hs, k, _ONE / F32(n * n))
        rc = ring[c]
        src = hs
        jjs, js = hs[_S_WJJS], hs[_S_WJS]
        if shift > 0 and w > 2 * shift:
            _shift_windows_row(hs, shift, shift_ratio, crow, code, sel)
            src = sel
            if slant:
                jjs, js = sel[5], sel[6]
        if slant:
            _slant_row(src[_P_WJJ], src[_P_WJQ], src[_P_W], src[_P_WJ], src[_P_WQ], jjs, js, S[y], M[y], inv_g2,
                       rc[_P_E2], R[y], lam_c, use_cap, rw[5], kc[5, y] if use_cap else _ZERO, cap_hi, out[y], hrow,
                       s0row)
        else:
            _update_row(src[_P_WJJ], src[_P_WJQ], src[_P_W], src[_P_WJ], src[_P_WQ], rc[_P_E2], R[y], lam_c,
                        use_cap, rw[5], kc[5, y] if use_cap else _ZERO, cap_hi, out[y], hrow, s0row)
        if inf_mode != 0:
            se, r0s = hs[_S_SE], hs[_S_R0]
            for x in range(w):
                ambr[x] = np.uint8(1) if r0s[x] <= se[x] else np.uint8(0)   # (sums over the pixels both see)
            if inf_mode == 1:
                io = inf_o[y]
                for x in range(w):
                    io[x] = ambr[x]
        elif use_amb:
            ai = amb_in[y]
            for x in range(w):
                ambr[x] = ai[x]
        if final:
            nv_, ni_ = _classify_row(out[y], R[y], rc[_P_E2], hrow, s0row, hs[_S_G], hs[_S_G3], hs[_S_R2], hs[_S_MX],
                                     hs[_S_MY], rc[_P_MF], ambr, fp, noise_info, std_o[y], flags_o[y], rng_o[y],
                                     conf_o[y], amb_o[y])
            nv += nv_
            ni += ni_
    return nv, ni


@njit(inline="always", **_JIT)
def _window_cost(sJJ, sJq, s0, sJ, sq, sqq):
    """A window's weighted residual after its least-squares solution (rho and the brightness offset), per unit
    weight (the shiftable windows' cost); +inf where not finite."""
    s1n = sJ / s0
    gp = sJq - sq * s1n
    hp = sJJ - sJ * s1n
    hp = hp if hp > F32(1e-12) else F32(1e-12)
    c = (sqq - sq * sq / s0 - gp * gp / hp) / s0
    return c if np.isfinite(c) else _INF


@njit(inline="always", **_JIT)
def _shift_code(c0, cl, cr, ratio):
    """-1 / +1: take the window shifted left / right, 0: keep the centred one (a tie takes the left)."""
    right = cr < cl
    cs = cr if right else cl
    d = np.int8(1) if right else np.int8(-1)
    return d if cs < ratio * c0 else np.int8(0)


@njit(**_JIT)
def _shift_windows_row(hs, sh, ratio, cost, code, sel):
    """The shiftable windows on one row of window means (hs rows 0-4 and _S_WQQ), into sel (rows 0-4; a sel of 7
    rows takes the slanted window's sums _S_WJJS, _S_WJS into rows 5-6; the choice is by the cost of one rho per
    window, ``_window_cost``): a pixel takes
    the sums of the window sh pixels to its left or right (clamped at the border) where that one's cost is below
    ratio x its centred window's. The interior columns by shifted views (numba vectorises the selects), the sh
    columns at each border one by one."""
    w = hs.shape[1]
    for x in range(w):
        cost[x] = _window_cost(hs[_P_WJJ, x], hs[_P_WJQ, x], hs[_P_W, x] + _EPS_S0, hs[_P_WJ, x], hs[_P_WQ, x],
                               hs[_S_WQQ, x])
    n = w - 2 * sh
    cL, cC, cR, kC = cost[0:n], cost[sh:sh + n], cost[2 * sh:2 * sh + n], code[sh:sh + n]
    for i in range(n):
        kC[i] = _shift_code(cC[i], cL[i], cR[i], ratio)
    for i in range(2 * sh):                   # the border columns: 0 .. sh - 1, w - sh .. w - 1
        x = i if i < sh else w - 2 * sh + i
        jl = x - sh if x >= sh else 0
        jr = x + sh if x + sh < w else w - 1
        code[x] = _shift_code(cost[x], cost[jl], cost[jr], ratio)
        for k in range(sel.shape[0]):
            kk = k if k < 5 else _S_WJJS + k - 5
            sel[k, x] = hs[kk, jl] if code[x] < 0 else (hs[kk, jr] if code[x] > 0 else hs[kk, x])
    for k in range(sel.shape[0]):
        a, o = hs[k if k < 5 else _S_WJJS + k - 5], sel[k]
        aL, aC, aR, oC = a[0:n], a[sh:sh + n], a[2 * sh:2 * sh + n], o[sh:sh + n]
        for i in range(n):
            c = kC[i]
            vl, vc, vr = aL[i], aC[i], aR[i]     # (loaded first: selects of loaded values vectorise, 5x faster)
            v = vr if c > 0 else vc
            oC[i] = vl if c < 0 else v


@njit(inline="always", **_JIT)
def _damped_step(e2, r, gg, hh, lam_c, use_cap, capr, x, capc, cap_hi):
    """The Levenberg-damped solution (hh + lam) rho' = gg + lam r, lam = lam_c e2, clipped to [0, cap] (cap: the
    affine cap map's capr[x] + capc clipped to [0, cap_hi] with use_cap, else cap_hi): the last step of both update
    rows."""
    num = _fma(e2 * r, lam_c, gg)
    den = _fma(e2, lam_c, hh)
    v = num / den
    v = v if den != _ZERO else _ZERO
    v = _ZERO if v < _ZERO else v
    hi = cap_hi
    if use_cap:
        c = capr[x] + capc             # (read only with use_cap: capr may be a row past the map's end)
        hi = c if c < cap_hi else cap_hi        # np.clip(c, 0, cap_hi)
        hi = _ZERO if hi < _ZERO else hi
    return hi if v > hi else v


@njit(**_JIT)
def _update_row(sJJ, sJq, sW, sJ, sq, E2, R, lam_c, use_cap, capr, capc, cap_hi, out, H_o, S0_o):
    """One row's Levenberg-damped update from its window means (brightness offset eliminated, Schur complement):
    (H - S1^2 / S0 + lam) rho' = g - Sq S1 / S0 + lam rho, lam = lam_c E2, clipped to [0, cap] (cap: the affine
    cap map's row capr + capc clipped to [0, cap_hi] with use_cap, else cap_hi). Leaves H - S1^2 / S0 in H_o and
    S0 + 1e-6 in S0_o. Branch-free: numba vectorises it."""
    w = out.shape[0]
    for x in range(w):
        s0 = sW[x] + _EPS_S0
        s1 = sJ[x]
        s1n = s1 / s0
        gg = sJq[x] - sq[x] * s1n
        hh = sJJ[x] - s1 * s1n
        H_o[x] = hh
        S0_o[x] = s0
        out[x] = _damped_step(E2[x], R[x], gg, hh, lam_c, use_cap, capr, x, capc, cap_hi)


@njit(**_JIT)
def _slant_row(sJJ, sJq, sW, sJ, sq, sJJS, sJS, Sc, Mc, inv_g2, E2, R, lam_c, use_cap, capr, capc, cap_hi, out, H_o,
               S0_o):
    """``_update_row`` for the slanted window: rho_j = rho_c + A_c (S_j - S_c) over the
    window of centre c, so that J_j rho_c = q_j - A_c J_j (S_j - S_c), and the window means of wJ q and w q become
    sJq - A_c (sJJS - S_c sJJ) and sq - A_c (sJS - S_c sJ); A_c = clip(2 - M_c inv_g2 / S_c, 0, 1) (M: the largest
    of the dilated gradient and second difference of S about c, ``slant_gate_inputs``; inv_g2 = 1 / (2 curv), curv the relative second difference
    where A starts to fall). (H - S1^2 / S0, the sigma's, is unchanged: so is the Jacobian of the residuals in rho_c.)
    Branch-free: numba vectorises it."""
    w = out.shape[0]
    for x in range(w):
        s0 = sW[x] + _EPS_S0
        s1 = sJ[x]
        s1n = s1 / s0
        sc = Sc[x]
        ac = _TWO - (Mc[x] * inv_g2) / max(sc, _H_MIN)
        ac = _ZERO if ac < _ZERO else ac           # (NaN: no slant)
        ac = _ONE if ac > _ONE else ac
        ac = ac if ac == ac else _ZERO
        m2 = sJJS[x] - sc * sJJ[x]
        m1 = sJS[x] - sc * s1
        gq = sJq[x] - ac * m2
        qq = sq[x] - ac * m1
        gg = gq - qq * s1n
        hh = sJJ[x] - s1 * s1n
        H_o[x] = hh
        S0_o[x] = s0
        out[x] = _damped_step(E2[x], R[x], gg, hh, lam_c, use_cap, capr, x, capc, cap_hi)


@njit(**_JIT)
def _classify_row(rho_r, R, E2, H, S0, G, G3, R2, Mx, My, mf, amb, fp, noise_info, std_o, flags_o, rng_o, conf_o,
                  amb_o):
    """One row's uncertainty, flags and classification from its final window means (the rules of
    _common.classify_into; fp: dense._Final's thresholds noise_G, var_k, floor2, trunc2, low_thr,
    occ_px2, occ_thr, orient_min, rho_far, max_rel_std); amb: the infinity test's verdict (1: a point at infinity
    explains the window as well), amb_o: where it made the pixel ILL_CONDITIONED. Returns (n_valid,
    n_at_infinity). Branch-free (selects): numba vectorises it."""
    noise_G, var_k, floor2, trunc2, low_thr = fp[0], fp[1], fp[2], fp[3], fp[4]
    occ_px2, occ_thr, orient_min, rho_far, max_rel_std = fp[5], fp[6], fp[7], fp[8], fp[9]
    nv = 0
    ni = 0
    for x in range(rho_r.shape[0]):
        rho = rho_r[x]
        e2 = E2[x]
        dd = rho - R[x]
        dd = dd * dd
        trunc = dd * e2 > trunc2
        hh = H[x]
        if noise_info:
            hh = _fma(e2 * S0[x], -noise_G, hh)
            hh = _H_MIN if hh < _H_MIN else hh           # (NaN stays NaN)
        std = var_k / hh
        std = std + floor2 / e2
        std = np.sqrt(std)
        Gw = G[x]
        orient = hh / (e2 * Gw)
        gc = Gw - Mx[x] * Mx[x]
        gc = gc - My[x] * My[x]
        low = gc < low_thr
        g3 = G3[x] * occ_px2
        occ = R2[x] > g3 + occ_thr
        oov = (mf[x] == _ZERO) | occ
        two = std * _TWO
        a = (amb[x] != 0) & (rho > two)
        ill = ((not orient >= orient_min) & (not low)) | a
        near0 = rho < two
        inf_ok = (two < rho_far) & near0
        good = ((std / rho <= max_rel_std) & (not near0)) | inf_ok
        good = good & np.isfinite(rho) & np.isfinite(std)
        ill = ill | (not good)
        bad = oov | low | ill | trunc
        at_inf = (not bad) & inf_ok
        val = (not bad) & (not inf_ok)
        fl = ((_OOV if oov else np.uint8(0)) | (_OCC if occ else np.uint8(0)) | (_LOW if low else np.uint8(0))
              | (_ILL if ill else np.uint8(0)) | (_TRUNC if trunc else np.uint8(0))
              | (_INF_VAL if at_inf else np.uint8(0)) | (_VAL if val else np.uint8(0)))
        flags_o[x] = fl
        amb_o[x] = np.uint8(1) if a else np.uint8(0)
        std_o[x] = std
        rng_o[x] = _INF if at_inf else (_ONE / abs(rho) if val else _NAN)
        c = rho_far / std if at_inf else (rho / std if val else _ZERO)
        conf_o[x] = c if c > _ZERO else _ZERO
        nv += 1 if val else 0
        ni += 1 if at_inf else 0
    return nv, ni


@njit(**_JIT)
def slant_gate_inputs(S, k, g_o, c_o):
    """Per pixel (reflected border) |S[y, x+1] - S[y, x-1]| + |S[y+1, x] - S[y-1, x]| into g_o and
    2/3 (|S[y, x+k] - 2 S[y, x] + S[y, x-k]| + |S[y+k, x] - 2 S[y, x] + S[y-k, x]|) into c_o: the slanted window's
    gate (``_slant_row``) before its dilations. At a step of height h, 3 x 3-averaged, both peak at 2 h / 3 (k >= 2),
    but c_o on a plane is 0 whatever its slope: it tells a depth edge from steep smooth ground, over 2 k + 1
    pixels, so that a jump the estimate has widened into a ramp of up to 2 k pixels still counts as one; g_o, less
    noisy, keeps the slant where rho is flat but its estimate noisy."""
    h, w = S.shape
    c23 = F32(2.0 / 3.0)
    two = F32(2.0)
    u1, uk = np.uint64(1), np.uint64(k)
    for y in range(h):
        r0, r1, r2, rkm, rkp = S[_reflect(y - 1, h)], S[y], S[_reflect(y + 1, h)], S[_reflect(y - k, h)], S[_reflect(y + k, h)]
        o, co = g_o[y], c_o[y]
        for x in range(k, w - k):          # inside: no reflection (numba vectorises it)
            ux = np.uint64(x)
            c2 = two * r1[ux]
            o[ux] = abs(r1[ux + u1] - r1[ux - u1]) + abs(r2[ux] - r0[ux])
            co[ux] = c23 * (abs(r1[ux + uk] + r1[ux - uk] - c2) + abs(rkp[ux] + rkm[ux] - c2))
        for i in range(2 * k):             # the k columns at either border
            x = i if i < k else w - 2 * k + i
            if x < 0 or x >= w or (i >= k and x < k):
                continue
            c2 = two * r1[x]
            o[x] = abs(r1[_reflect(x + 1, w)] - r1[_reflect(x - 1, w)]) + abs(r2[x] - r0[x])
            co[x] = c23 * (abs(r1[_reflect(x + k, w)] + r1[_reflect(x - k, w)] - c2) + abs(rkp[x] + rkm[x] - c2))


_SCHARR_SIDE = F32(3.0 / 32.0)
_SCHARR_MID = F32(10.0 / 32.0)


@njit(inline="always", **_JIT)
def _scharr_row(r0, r1, r2, x0, x1, x2):
    """Scharr derivatives / 32 (cv2.Scharr's kernels times 1/32) at the pixel whose columns left / centre / right
    are x0, x1, x2 in the rows above / at / below (r0, r1, r2)."""
    gx = _SCHARR_SIDE * (r0[x2] - r0[x0]) + _SCHARR_MID * (r1[x2] - r1[x0]) + _SCHARR_SIDE * (r2[x2] - r2[x0])
    gy = _SCHARR_SIDE * (r2[x0] - r0[x0]) + _SCHARR_MID * (r2[x1] - r0[x1]) + _SCHARR_SIDE * (r2[x2] - r0[x2])
    return gx, gy


@njit(inline="always", **_JIT)
def _scharr_rows(img, y, gx_o, gy_o):
    """Row y of the Scharr gradient of img / 32 into gx_o[0], gy_o[0] (reflected border)."""
    h, w = img.shape
    r0, r1, r2 = img[_reflect(y - 1, h)], img[y], img[_reflect(y + 1, h)]
    ox, oy = gx_o[0], gy_o[0]
    u1 = np.uint64(1)
    for x in range(1, w - 1):
        ux = np.uint64(x)
        ox[ux], oy[ux] = _scharr_row(r0, r1, r2, ux - u1, ux, ux + u1)
    for x in (0, w - 1):
        ox[x], oy[x] = _scharr_row(r0, r1, r2, _reflect(x - 1, w), x, _reflect(x + 1, w))


@njit(**_JIT)
def scharr(img, gx_o, gy_o):
    """The Scharr gradient of img / 32 into gx_o, gy_o (cv2.Scharr with scale 1/32 and BORDER_REFLECT, up to float
    rounding)."""
    for y in range(img.shape[0]):
        _scharr_rows(img, y, gx_o[y:y + 1], gy_o[y:y + 1])


@njit(**_JIT)
def pack_b4p(img, b4p_o):
    """The warp source of ``gn_level``: [img, its Scharr gradient / 32 (as ``scharr``), 1] per pixel, with a border
    of one zero pixel: b4p_o is (h + 2, w + 2, 4). Per row the gradient into row buffers (vectorised), then the
    interleaving."""
    h, w = img.shape
    for x in range(w + 2):
        for c in range(4):
            b4p_o[0, x, c] = _ZERO
            b4p_o[h + 1, x, c] = _ZERO
    gx = np.empty((1, w), F32)
    gy = np.empty((1, w), F32)
    for y in range(h):
        _scharr_rows(img, y, gx, gy)
        r1, ox, oy = img[y], gx[0], gy[0]
        o = b4p_o[y + 1]
        for c in range(4):
            o[0, c] = _ZERO
            o[w + 1, c] = _ZERO
        for x in range(w):
            ux = np.uint64(x) + np.uint64(1)
            o[ux, 0] = r1[x]
            o[ux, 1] = ox[x]
            o[ux, 2] = oy[x]
            o[ux, 3] = _ONE


# --- a prior as the refinement's start (dense._prior_start / _prior_finish)


@njit(**_JIT)
def prior_gate(rw, kc, B0, rho, std, k, reach, ok_o):
    """dense._prior_ok per pixel into ok_o (uint8): finite rho >= 0, den = A0 + B0 rho > 0.05 and
    k std |C| / den^2 <= reach (rw / kc: a _Level's affine rows, C / 2 in rows 3 and 4). Returns the number of
    pixels passed."""
    h, w = rho.shape
    n = 0
    for y in range(h):
        a0c, c1c, c2c = kc[0, y], kc[3, y], kc[4, y]
        for x in range(w):
            r = rho[y, x]
            c1 = rw[3, x] + c1c
            c2 = rw[4, x] + c2c
            den = _fma(r, B0, rw[0, x] + a0c)
            lim = k * std[y, x] * (_TWO * np.sqrt(c1 * c1 + c2 * c2))
            ok = (r >= _ZERO) & (den > F32(0.05)) & (lim <= reach * (den * den))    # (NaN: False)
            ok_o[y, x] = np.uint8(1) if ok else np.uint8(0)
            n += 1 if ok else 0
    return n


@njit(**_JIT)
def prior_unmeasure(ok_lev, s, rho_p, bad_bits, rho, std, flags, rng, conf):
    """After a refinement started from a prior seeded on a level of scale s (ok_lev: its gate): the level-0 pixels
    it did not seed (ok_lev[y // s, x // s] == 0, or no finite prior of their own) made unmeasured in place: rho
    NaN, std inf, range NaN, confidence 0, VALID and AT_INFINITY cleared. Returns (seeded pixels, those of them
    whose flags hold any of bad_bits, VALID pixels cleared (not at infinity), AT_INFINITY pixels cleared)."""
    h, w = rho.shape
    n_ok = 0
    n_bad = 0
    d_val = 0
    d_inf = 0
    clear = ~(_VAL | np.uint8(AT_INFINITY))
    inf_bit = np.uint8(AT_INFINITY)
    okx = np.empty(w, np.uint8)
    for y in range(h):
        okr = ok_lev[y // s]
        for x in range(w):
            okx[x] = okr[x // s]
        rp, fr, rr, sr, gr, cr = rho_p[y], flags[y], rho[y], std[y], rng[y], conf[y]
        for x in range(w):             # branch-free (selects: numba vectorises it)
            f = fr[x]
            keep = (okx[x] != 0) & np.isfinite(rp[x])
            n_ok += 1 if keep else 0
            n_bad += 1 if keep & ((f & bad_bits) != 0) else 0
            isinf = (f & inf_bit) != 0
            d_inf += 1 if (not keep) & isinf else 0
            d_val += 1 if (not keep) & (not isinf) & ((f & _VAL) != 0) else 0
            fr[x] = f if keep else f & clear
            rr[x] = rr[x] if keep else _NAN
            sr[x] = sr[x] if keep else _INF
            gr[x] = gr[x] if keep else _NAN
            cr[x] = cr[x] if keep else _ZERO
    return n_ok, n_bad, d_val, d_inf


# --- the window model's error after level 0's last step (dense._apply_model_error)


@njit(**_JIT)
def centroid_terms(rw, kc, B0, rho, gxa, gya, J_o, J2_o, m_o, r_o):
    """Per pixel the epipolar gradient J = grad I_a . (C1, C2) / den^2 at rho (rw / kc: a _Level's affine rows, C / 2
    in rows 3 and 4; 0 where not finite) and J^2 into J_o, J2_o; and r_o (the residual, from ``residual_grid``) made 0
    where not in view (m_o: the in-view mask as 1.0 / 0.0, from its uint8 form, in place of the residual's finite
    test)."""
    h, w = rho.shape
    for y in range(h):
        a0c, c1c, c2c = kc[0, y], kc[3, y], kc[4, y]
        for x in range(w):
            r = rho[y, x]
            r = r if np.isfinite(r) else _ZERO
            den = _fma(r, B0, rw[0, x] + a0c)
            j = (gxa[y, x] * (rw[3, x] + c1c) + gya[y, x] * (rw[4, x] + c2c)) / (den * den)
            j = j if np.isfinite(j) else _ZERO
            J_o[y, x] = j
            J2_o[y, x] = j * j
            rr = r_o[y, x]
            m = m_o[y, x]
            r_o[y, x] = rr * m if np.isfinite(rr) else _ZERO


@njit(inline="always", **_JIT)
def _minmod(a, b):
    """The smaller in magnitude of two slopes of the same sign, else 0."""
    s = a if abs(a) < abs(b) else b
    return s if a * b > _ZERO else _ZERO


@njit(**_JIT)
def model_error_finish(rho, rs, k, S, M, inv_g2, m1, m0J, rx2, rx1, ry2, ry1, half, mr, mr2, mv, n_win,
                       noise_floor2, sigma2, rw, kc, B0, floor2, max_rel_std, centroid, std, flags, rng, conf):
    """dense._apply_model_error per pixel, in place on the VALID (not AT_INFINITY) pixels: the sigma's noise part
    scaled by max(s_w^2, noise_floor2) / sigma2 (s_w^2: the window's residual variance from its window means mr, mr2
    over the in-view share mv, times n / (n - 2)); with ``centroid`` rho moved by the bias A b, b = grad rho . o (the
    minmod slopes of rs over k pixels each way, the offset o of the window's effective centre from the window means
    of J (m1), J^2 - mean J^2 (m0J) and the ramp-weighted J^2, J (rx2, rx1, ry2, ry1), clipped to +-half), A the
    planarity gate clip(2 - M inv_g2 / S, 0, 1) (as ``_slant_row``), and (1 - A) b into the sigma in quadrature; a
    pixel whose relative sigma then exceeds max_rel_std loses VALID (ILL_CONDITIONED). Returns the VALID pixels
    lost."""
    h, w = rho.shape
    lost = 0
    for y in range(h):
        yu = min(y + k, h - 1)
        yd = max(y - k, 0)
        a0c, c1c, c2c = kc[0, y], kc[3, y], kc[4, y]
        for x in range(w):
            f = flags[y, x]
            if (f & _VAL) == 0 or (f & np.uint8(AT_INFINITY)) != 0:
                continue
            r = rho[y, x]
            # the window's residual variance against the image's noise
            n = mv[y, x] * n_win
            mvv = mv[y, x]
            sw2 = _INF
            if n > F32(2.5):
                mm = mr[y, x] / mvv
                sw2 = (mr2[y, x] / mvv - mm * mm) * n / (n - _TWO)
                sw2 = sw2 if sw2 > _ZERO else _ZERO
            fac = (sw2 if sw2 > noise_floor2 else noise_floor2) / sigma2
            den = _fma(r, B0, rw[0, x] + a0c)
            c1 = rw[3, x] + c1c
            c2 = rw[4, x] + c2c
            d2 = den * den
            e2 = (c1 * c1 + c2 * c2) / (d2 * d2)
            fl = floor2 / e2 if e2 > _ZERO else _ZERO
            s = std[y, x]
            nz = s * s - fl
            nz = nz if nz > _ZERO else _ZERO
            var = nz * fac + fl
            new = r
            if centroid:
                xr = min(x + k, w - 1)
                xl = max(x - k, 0)
                c = rs[y, x]
                gx = _minmod((rs[y, xr] - c) / F32(max(xr - x, 1)) if xr > x else (c - rs[y, xl]) / F32(max(x - xl, 1)),
                             (c - rs[y, xl]) / F32(max(x - xl, 1)) if xl < x else (rs[y, xr] - c) / F32(max(xr - x, 1)))
                gy = _minmod((rs[yu, x] - c) / F32(max(yu - y, 1)) if yu > y else (c - rs[yd, x]) / F32(max(y - yd, 1)),
                             (c - rs[yd, x]) / F32(max(y - yd, 1)) if yd < y else (rs[yu, x] - c) / F32(max(yu - y, 1)))
                d0 = m0J[y, x]
                ox = (rx2[y, x] - m1[y, x] * rx1[y, x]) / d0
                oy = (ry2[y, x] - m1[y, x] * ry1[y, x]) / d0
                ox = ox if np.isfinite(ox) else _ZERO
                oy = oy if np.isfinite(oy) else _ZERO
                ox = min(max(ox, -half), half)
                oy = min(max(oy, -half), half)
                b = gx * ox + gy * oy
                sc = S[y, x]
                a = _TWO - (M[y, x] * inv_g2) / max(sc, _H_MIN)
                a = _ZERO if a < _ZERO else a
                a = _ONE if a > _ONE else a
                a = a if a == a else _ZERO
                new = r - a * b
                new = new if new > _ZERO else _ZERO
                bl = (_ONE - a) * b
                var = var + bl * bl
            sd = np.sqrt(var)
            ok = (new > _ZERO) & (sd <= max_rel_std * new) & np.isfinite(sd)
            rho[y, x] = new
            std[y, x] = sd
            if ok:
                rng[y, x] = _ONE / new
                conf[y, x] = new / sd
            else:
                flags[y, x] = (f & ~_VAL) | _ILL
                rng[y, x] = _NAN
                conf[y, x] = _ZERO
                lost += 1
    return lost


@njit(**_JIT)
def blend_ladder(need, rungs, v, out):
    """dense._match_blur's per-pixel blend: out = the linear interpolation in variance between rungs[k] and
    rungs[k + 1] (Gaussian blurs of one image of variances v[k] < v[k + 1]) with need in (v[k], v[k + 1]]; need at
    or below v[0] takes rungs[0], above the last rung's variance the last rung."""
    h, w = need.shape
    n = v.shape[0]
    for y in range(h):
        for x in range(w):
            q = need[y, x]
            if q <= v[0]:
                out[y, x] = rungs[0, y, x]
                continue
            if q >= v[n - 1]:
                out[y, x] = rungs[n - 1, y, x]
                continue
            k = 0
            while q > v[k + 1]:
                k += 1
            f = (q - v[k]) / (v[k + 1] - v[k])
            lo = rungs[k, y, x]
            out[y, x] = lo + f * (rungs[k + 1, y, x] - lo)
