"""Fused per-pixel kernels (numba) of the dense method's Gauss-Newton strips (``dense._gn_block``).

The OpenCV path of ``_gn_block`` makes ~100 passes over each strip (one array operation each, plus a fixed cost
per call); these kernels do the same float32 arithmetic in three passes per strip: the epipolar map before the
warp (cv2.remap), the weighted terms whose window sums the normal equations need (box-filtered by OpenCV, as in
the OpenCV path), and the update (with ``final``: the uncertainty, the flags and the classification of
``_common.classify_into``). Each elementwise operation is the one of the OpenCV path, in the same order and in
float32 (no fast-math: no reassociation, no fused multiply-add), so the two paths agree to float rounding
(tests/test_dense.py::test_fused_kernels_match_opencv_path).

The coarse epipolar search (``dense._search_fused``) has its kernels here too (``search_*``), bit-identical to
``dense._search``'s OpenCV path (tests/test_dense.py::test_fused_search_matches_opencv_search).

Imported only when numba is installed (``_common.optional_kernels``); without it the OpenCV path runs.
"""
from __future__ import annotations

import numpy as np
from llvmlite import ir
from numba import njit, types
from numba.core import cgutils
from numba.extending import intrinsic

from ..rangemap import AT_INFINITY, ILL_CONDITIONED, LOW_TEXTURE, OCCLUDED, OUT_OF_VIEW, TRUNCATION, VALID

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
    here (fused multiply-add; llvm.fma.f32). It was a float64 product and sum rounded to float32: the same but for
    ties that double rounding breaks differently, and ~1.5x the time of the final-level kernel."""
    return _fma32(a, b, c)


@njit(**_JIT)
def epipolar_map(R, a0r, a0c, p1r, p1c, p2r, p2c, B0, Q1, Q2, inv, ub, vb):
    """Map of the strip's pixels into b at rho = R: inv = 1 / (A0 + B0 rho), u_b = (P1 + Q1 rho) inv,
    v_b = (P2 + Q2 rho) inv; each affine map is its row part (w) plus its column part (rows of the strip)."""
    n, w = R.shape
    for y in range(n):
        ca, c1, c2 = a0c[y], p1c[y], p2c[y]
        for x in range(w):
            r = R[y, x]
            d = _ONE / _fma(r, B0, a0r[x] + ca)
            inv[y, x] = d
            ub[y, x] = _fma(r, Q1, p1r[x] + c1) * d
            vb[y, x] = _fma(r, Q2, p2r[x] + c2) * d


@njit(inline="always", **_JIT)
def _terms(y, x, mask, r, gx, gy, C1, C2, d, Ryx, ks, c2_fma, wJJ, wJq, wgt_o, wJ_o, wq_o, E2_o):
    """One pixel's Huber-weighted normal-equation terms and E2 (shared by gn_terms and gn_terms_final)."""
    J = gx * C1
    J = _fma(gy, C2, J)
    i2 = d * d
    J = J * i2
    c2 = C1 * C1
    c2 = _fma(C2, C2, c2) if c2_fma else c2 + C2 * C2
    E2_o[y, x] = c2 * (i2 * i2)
    a = max(abs(r), ks)
    wgt = (mask * ks) / a
    wJ = wgt * J
    q = J * Ryx
    q = q - r
    wJJ[y, x] = wJ * J
    wJq[y, x] = wJ * q
    wgt_o[y, x] = wgt
    wJ_o[y, x] = wJ
    wq_o[y, x] = wgt * q


@njit(**_JIT)
def gn_terms(wv, ia, gxa, gya, c1r, c1c, c2r, c2c, inv, R, ks, c2_fma, wJJ, wJq, wgt_o, wJ_o, wq_o, E2_o):
    """Per pixel of the strip (wv: warped [I_b, gx_b, gy_b, in-view]): the Huber-weighted terms of the normal
    equations whose window sums are needed (wJ J, wJ q, w, wJ, w q) and E2 (a quarter of |d map / d rho|^2)."""
    n, w = R.shape
    for y in range(n):
        k1, k2 = c1c[y], c2c[y]
        for x in range(w):
            mask = wv[y, x, 3]
            r = wv[y, x, 0] - ia[y, x]
            gx = wv[y, x, 1] + gxa[y, x]
            gy = wv[y, x, 2] + gya[y, x]
            d = inv[y, x]
            _terms(y, x, mask, r, gx, gy, c1r[x] + k1, c2r[x] + k2, d, R[y, x], ks, c2_fma, wJJ, wJq, wgt_o, wJ_o, wq_o,
                   E2_o)


@njit(**_JIT)
def gn_terms_final(wv, ia, gxa, gya, c1r, c1c, c2r, c2c, inv, R, ks, c2_fma, wJJ, wJq, wgt_o, wJ_o, wq_o, E2_o,
                   G_o, rr_o, mx_o, my_o, mf_o):
    """gn_terms of the final linearisation, with its extra per-pixel terms in the same pass: the in-view mask mf
    (mask > 0.999 and inv > 0), the masked gradient energy of a (G), the masked squared residual (rr) and the
    masked gradient of a (mx, my)."""
    n, w = R.shape
    for y in range(n):
        k1, k2 = c1c[y], c2c[y]
        for x in range(w):
            mask = wv[y, x, 3]
            r = wv[y, x, 0] - ia[y, x]
            ga, gb = gxa[y, x], gya[y, x]
            gx = wv[y, x, 1] + ga
            gy = wv[y, x, 2] + gb
            d = inv[y, x]
            _terms(y, x, mask, r, gx, gy, c1r[x] + k1, c2r[x] + k2, d, R[y, x], ks, c2_fma, wJJ, wJq, wgt_o, wJ_o, wq_o,
                   E2_o)
            mf = _ONE if (mask > _MASK_IN) & (d > _ZERO) else _ZERO
            mf_o[y, x] = mf
            G = ga * ga
            G = _fma(gb, gb, G)
            G_o[y, x] = G * mf
            rr = r * r
            rr_o[y, x] = rr * mf
            mx_o[y, x] = ga * mf
            my_o[y, x] = gb * mf


@njit(**_JIT)
def inview_residual(wv, ia, rr_o):
    """The residual masked by the warp's in-view mask > 0.999 (the infinity test's input)."""
    n, w = ia.shape
    for y in range(n):
        for x in range(w):
            rr_o[y, x] = (wv[y, x, 0] - ia[y, x]) * (_ONE if wv[y, x, 3] > _MASK_IN else _ZERO)


@njit(**_JIT)
def gn_update(H, g, S0, S1, Sq, E2, R, lam_c, capr, capc, cap_hi, out):
    """The Levenberg-damped update of the strip's own rows from the window sums (brightness offset eliminated):
    (H - S1^2 / S0 + lam) rho' = g - Sq S1 / S0 + lam rho, lam = lam_c E2, clipped to [0, cap]: cap the affine
    cap map (row part capr, column part capc: den >= den_min) clipped to [0, cap_hi], or cap_hi where capr is
    empty. Leaves S0 + 1e-6 in S0 and H - S1^2/S0 in H."""
    n, w = out.shape
    use_cap = capr.shape[0] > 0
    for y in range(n):
        cc = capc[y] if use_cap else _ZERO
        for x in range(w):
            s0 = S0[y, x] + _EPS_S0
            S0[y, x] = s0
            s1 = S1[y, x]
            s1n = s1 / s0
            gg = g[y, x] - Sq[y, x] * s1n
            hh = H[y, x] - s1 * s1n
            H[y, x] = hh
            e2 = E2[y, x]
            num = _fma(e2 * R[y, x], lam_c, gg)
            den = _fma(e2, lam_c, hh)
            v = num / den if den != _ZERO else _ZERO
            if v < _ZERO:
                v = _ZERO
            hi = cap_hi
            if use_cap:
                c = capr[x] + cc
                hi = c if c < cap_hi else cap_hi      # np.clip(c, 0, cap_hi) (NaN-free), as _Level.cap_rows
                if hi < _ZERO:
                    hi = _ZERO
            if v > hi:
                v = hi
            out[y, x] = v


@njit(**_JIT)
def gn_final(H, S0, E2, R, out, G, G3, R2, Mx, My, mf, amb, use_amb, noise_info, noise_G, var_k, floor2, trunc2,
             low_thr, occ_px2, occ_thr, orient_min, rho_far, max_rel_std, std_o, flags_o, rng_o, conf_o, amb_o):
    """Uncertainty, flags and classification of the strip's own rows after ``gn_update`` (H, S0 as it leaves
    them): the arithmetic of the OpenCV path of dense._gn_block and of _common.classify_into, per pixel; amb_o
    gets the infinity test's verdict (1: a point at infinity explains the window as well). Returns
    (n_valid, n_at_infinity)."""
    n, w = out.shape
    nv = 0
    ni = 0
    for y in range(n):
        for x in range(w):
            rho = out[y, x]
            e2 = E2[y, x]
            dd = rho - R[y, x]
            dd = dd * dd
            dd = dd * e2
            trunc = dd > trunc2
            hh = H[y, x]
            if noise_info:
                hh = _fma(e2 * S0[y, x], -noise_G, hh)
                if not hh >= _H_MIN and not np.isnan(hh):
                    hh = _H_MIN
            std = var_k / hh
            std = std + floor2 / e2
            std = np.sqrt(std)
            std_o[y, x] = std
            Gw = G[y, x]
            orient = hh / (e2 * Gw)
            mx, my = Mx[y, x], My[y, x]
            gc = Gw - mx * mx
            gc = gc - my * my
            low = gc < low_thr
            g3 = G3[y, x] * occ_px2
            g3 = g3 + occ_thr
            occ = R2[y, x] > g3
            oov = mf[y, x] == _ZERO or occ
            ill = (not orient >= orient_min) and not low
            amb_o[y, x] = 0
            if use_amb and amb[y, x] != 0 and rho > _TWO * std:
                ill = True
                amb_o[y, x] = 1
            fl = np.uint8(0)
            if oov:
                fl |= _OOV
            if occ:
                fl |= _OCC
            if low:
                fl |= _LOW
            if ill:
                fl |= _ILL
            if trunc:
                fl |= _TRUNC
            # classify_into
            two = std * _TWO
            inf_ok = two < rho_far
            near0 = rho < two
            inf_ok = inf_ok and near0
            rel = std / rho
            good = rel <= max_rel_std and not near0
            good = (good or inf_ok) and np.isfinite(rho) and np.isfinite(std)
            if not good:
                fl |= _ILL
            ok = (fl & _BAD) == 0
            if ok and inf_ok:
                fl |= _INF_VAL
                ni += 1
                rng_o[y, x] = _INF
                c = rho_far / std
            elif ok:
                fl |= _VAL
                nv += 1
                rng_o[y, x] = _ONE / abs(rho)
                c = rho / std
            else:
                rng_o[y, x] = _NAN
                c = _ZERO
            conf_o[y, x] = c if c > _ZERO else _ZERO
            flags_o[y, x] = fl
    return nv, ni


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
    a); 2 where the hypothesis is out of view. The arithmetic of dense._search's OpenCV path."""
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
    """dense._wta (first minimum over the hypotheses of agg, parabola fit of the sub-sample offset), np.interp of
    the fractional index into the hypotheses (hyp: displacements with per_pixel, else inverse ranges), the rho of
    that displacement (per_pixel: ``_rho_at_disp``), and the confidence clip(1 - cost, 0, 1)^2 x texture
    (va / (va + noise2)): dense._search's arithmetic, per pixel."""
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
