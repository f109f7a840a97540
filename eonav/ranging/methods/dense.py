"""The default range estimator: a dense, direct inverse-range method (brightness constancy + known motion).

Idea (the paper's, eqs. 25-28, made robust): with the relative pose known, every pixel of image a can
only move along its epipolar curve in image b, parameterised exactly by its inverse range rho = 1/x_c
(eqs. 25-26, ``_common.EpipolarMap``). Brightness constancy I_b(map(rho)) = I_a is then ONE equation in
ONE unknown per pixel; its first-order expansion (the paper's eq. 27 after multiplying through by the
denominator of eqs. 25-26) is linear in rho. We solve it

1. where the first-order model breaks (disparities of many pixels) by a 1-D search over inverse-range
   hypotheses along the epipolar curve, uniform in each pixel's own displacement, at a coarse pyramid level
   (windowed ZNCC, winner-take-all, parabola sub-sample fit, 3x3 median) -- no 2-D flow search anywhere;
2. then coarse-to-fine by re-linearised Gauss-Newton: at each level warp b at the current rho
   (cv2.remap), so that the Taylor remainder (eq. 7) stays small, and solve the windowed (box), Huber-
   weighted normal equations of r + J (rho' - rho) = 0, r = I_b(map(rho)) - I_a,
   J = grad I . d(u_b, v_b)/d rho (analytic derivative of the rational map) with the gradient averaged over
   I_a and the warped I_b (eq. 27's symmetric form: a second-order step, half the interpolation bias of a
   one-sided gradient), with a Levenberg trust term worth about ``trust_px`` pixels of displacement.

Per-pixel 1-sigma of rho from the normal equations and the noise (robust MAD of the final residual),
confidence = rho / sigma. Flags: OUT_OF_VIEW (map leaves b, behind b, or occluded = high windowed
residual), LOW_TEXTURE (gradient energy not above the noise's own), ILL_CONDITIONED (focus of expansion,
gradient perpendicular to the epipolar direction, relative std above ``max_rel_std``), TRUNCATION
(eq. 7-style: the last update still moved by more than ``trunc_px``), AT_INFINITY (rho within 2 sigma
of 0 with a tight sigma: range +inf).

All per-pixel work is float32 numpy / OpenCV or (when numba is installed) fused numba kernels (``_dense_kernels``,
``fused``) that give the same result to float rounding: no per-pixel Python. With numba each Gauss-Newton step of a
level is one pass (rows streamed through a ring of window-height term planes). The OpenCV path runs the steps, the
flags and the classification on strips of rows (``strip_px`` pixels each including a half-window halo, so the
box sums are exactly those of the whole image): the temporaries of a strip are 16 work planes that stay in
the CPU cache; they and the large per-level buffers (warp source, gradients, cost volume) are per-thread work
buffers reused from strip to strip and call to call (_ws), never fresh (page-faulting) arrays.
"""
from __future__ import annotations

import math
import threading
import time
from functools import lru_cache

import cv2
import numpy as np

from eonav import InputError
from eonav.geometry.camera import View, pair_geometry
from eonav.ranging.rangemap import ILL_CONDITIONED, LOW_TEXTURE, OCCLUDED, OUT_OF_VIEW, TRUNCATION, VALID, RangeResult
from eonav.ranging.methods._common import (F32, EpipolarMap, classify_into, far_inverse_range, make_result,
                      no_motion_result, optional_kernels, pyr_up_to, pyramid)
from eonav.ranging.methods.fill import fill_unmeasured

METHOD = "dense"
_BR = cv2.BORDER_REFLECT


def _blur(img: np.ndarray, sigma: float, dst: np.ndarray | None = None) -> np.ndarray:
    k = 2 * int(math.ceil(2.5 * sigma)) + 1
    return cv2.GaussianBlur(img, (k, k), sigma, dst=dst, borderType=_BR)


_TLS = threading.local()


def _ws(key, shape, dtype=F32, fill=None) -> np.ndarray:
    """A per-thread work buffer, reused from call to call (never part of a result). Large fresh arrays cost
    a page fault per 4 KiB page on every call (the allocator returns them to the OS): ~1000 faults for the
    4-channel warp source of a 512 x 512 image alone. ``fill``: constant contents, written once."""
    d = getattr(_TLS, "bufs", None)
    if d is None or len(d) > 128:      # bounded: a stream of ever-new image sizes cannot grow it without end
        # (one 512 x 512 locate holds ~50 buffers: the strips' work planes, caches and warps per level)
        d = _TLS.bufs = {}
    k = (key, tuple(shape), np.dtype(dtype).str, fill)
    a = d.get(k)
    if a is None:
        a = d[k] = np.empty(shape, dtype)
        if fill is not None:
            a.fill(fill)
    return a


@lru_cache(maxsize=8)
def _box_kernel(win: int) -> np.ndarray:
    return np.full(win, 1.0 / win, F32)


def _box(img: np.ndarray, win: int) -> np.ndarray:
    """Mean over a win x win window (reflected border). A separable direct filter: for the small windows
    used here OpenCV's SIMD sepFilter2D is ~1.6x faster than its running-sum boxFilter."""
    k = _box_kernel(win)
    return cv2.sepFilter2D(img, -1, k, k, borderType=_BR)


def _grad(img: np.ndarray):
    gx = cv2.Scharr(img, cv2.CV_32F, 1, 0, scale=1.0 / 32.0, borderType=_BR)
    gy = cv2.Scharr(img, cv2.CV_32F, 0, 1, scale=1.0 / 32.0, borderType=_BR)
    return gx, gy


@lru_cache(maxsize=16)
def _noise_gains(presmooth_sigma: float):
    """Variance gain of the pre-smoothing and mean squared-gradient gain (Scharr of the pre-smoothed image)
    for unit white noise, measured once on a seeded noise image: used to tell texture from noise."""
    n = np.random.default_rng(12345).standard_normal((256, 256)).astype(F32)
    s = _blur(n, presmooth_sigma) if presmooth_sigma > 0 else n
    gx, gy = _grad(s)
    c = (slice(16, -16), slice(16, -16))
    return float(s[c].var()), float((gx[c] ** 2 + gy[c] ** 2).mean())


def _robust_sigma(r: np.ndarray, mask: np.ndarray | None = None, step: int = 3, floor: float = 0.3) -> float:
    """1.4826 * median |r| over a subsampled (masked) grid: the noise of the residual image."""
    rs = r[::step, ::step]
    vals = np.abs(rs[mask[::step, ::step]] if mask is not None else rs).ravel()
    if vals.size < 16:
        return floor
    k = vals.size // 2
    return max(float(1.4826 * np.partition(vals, k)[k]), floor)


_LAPLACE_NOISE = np.array([[1, -2, 1], [-2, 4, -2], [1, -2, 1]], F32)


def image_noise_sigma(img: np.ndarray) -> float:
    """Sensor noise (grey levels, 1 sigma) of an image: 1.4826 x the median |I * N| / 6 on every other pixel, N the
    3 x 3 kernel of Immerkaer (1996) that cancels intensity planes (unit-noise gain 6); the median ignores the
    textured pixels. Sim frames with noise sigma 1.0: 0.99."""
    r = cv2.filter2D(img, cv2.CV_32F, _LAPLACE_NOISE, borderType=_BR)[1:-1:2, 1:-1:2]
    a = np.abs(r).ravel()
    k = a.size // 2
    return float(1.4826 * np.partition(a, k)[k] / 6.0) if a.size else 0.0


def _sparse(emap: EpipolarMap, n: int = 17) -> EpipolarMap:
    """The same map on an n x n grid of pixels spanning the image (corners included)."""
    h, w = emap.A0.shape
    iy = np.linspace(0, h - 1, n).round().astype(int)
    ix = np.linspace(0, w - 1, n).round().astype(int)
    g = np.ix_(iy, ix)
    return EpipolarMap(emap.A0[g], emap.A1[g], emap.A2[g], emap.B, emap.C1[g], emap.C2[g], emap.cam_b,
                       emap.rho_cap[g])


def _disp_coeffs(sub: EpipolarMap):
    """Displacement of a grid point between rho = 0 and rho is exactly rho |C| / (A0 (A0 + B0 rho)) (level
    pixels): returns (|C|, A0, B0) of the sparse grid."""
    return np.hypot(sub.C1, sub.C2).astype(np.float64).ravel(), sub.A0.astype(np.float64).ravel(), float(sub.B[0])


def _max_disparity(sub: EpipolarMap, rho, coeffs=None):
    """Largest displacement (level pixels) over the sparse grid between rho = 0 and each rho; inf if some
    point would be at or behind camera b (depth ratio <= 0.05)."""
    cn, a0, b0 = coeffs if coeffs is not None else _disp_coeffs(sub)
    rho = np.atleast_1d(np.asarray(rho, np.float64))[:, None]
    den = a0[None] + b0 * rho
    with np.errstate(divide="ignore", invalid="ignore"):
        d = rho * cn[None] / (a0[None] * den)
    d = np.where((den <= 0.05).any(axis=1, keepdims=True) | (a0[None] <= 0.05).any(axis=1, keepdims=True),
                 np.inf, d)
    return d.max(axis=1)


def _find_rho_max(sub: EpipolarMap, max_disp: float) -> float:
    """Inverse range at which the largest displacement reaches max_disp (level pixels); inf if never.
    Closed form per grid point: rho_i = D A0^2 / (|C| - D A0 B0) (monotone in rho while A0 + B0 rho > 0)."""
    cn, a0, b0 = _disp_coeffs(sub)
    if np.any(a0 <= 0.05):
        return 0.0
    with np.errstate(divide="ignore", invalid="ignore"):
        denom = cn - max_disp * a0 * b0
        r_i = np.where(denom > 0, max_disp * a0 * a0 / denom, np.inf)
    r = float(r_i.min())
    if b0 < 0:   # the map runs off to infinity where a point reaches the plane of camera b: stop short of it
        r = min(r, float(((a0 - 0.05) / -b0).min()))
    return r if r < 1e9 else math.inf


def _hypotheses(sub: EpipolarMap, rho_max: float, step_px: float) -> np.ndarray:
    """Inverse-range hypotheses 0 = rho_0 < ... = rho_max such that the largest displacement in the image
    grows by ``step_px`` level pixels from one to the next (uniform in displacement, not in rho)."""
    grid = np.linspace(0.0, rho_max, 65)
    d = _max_disparity(sub, grid)
    fin = np.isfinite(d)
    d = np.maximum.accumulate(np.where(fin, d, d[fin].max()))
    n = max(2, int(math.ceil(d[-1] / step_px)) + 1)
    return np.interp(np.linspace(0.0, d[-1], n), d, grid)


def _rho_at_disp(D, A0, cn, B0, cap):
    """Inverse range at which each pixel's displacement from its rho = 0 position reaches D level pixels:
    D = rho |C| / (A0 (A0 + B0 rho))  =>  rho = D A0^2 / (|C| - D A0 B0) (``_disp_coeffs``), at most ``cap``
    (where D is never reached -- a pixel near the focus of expansion, or one whose point would pass camera b --
    the cap itself)."""
    with np.errstate(divide="ignore", invalid="ignore", over="ignore"):
        den = cn - D * A0 * B0
        r = D * A0 * A0 / den
        r = np.where((den > 0) & (A0 > 0), r, cap)
    return np.minimum(r, cap).astype(F32)


def _sgm_paths(C: np.ndarray, img: np.ndarray, P1: float, P2: float, tau: float) -> np.ndarray:
    """Semi-global aggregation (Hirschmueller) along axis 0 of C (m, n, k), both directions at once:
    L(i, d) = C(i, d) + min(L(i-1, d), L(i-1, d +- 1) + P1, min L(i-1) + P2') - min L(i-1), with the jump
    penalty P2' = max(P1, P2 / (1 + |img(i) - img(i-1)| / tau)) lower across intensity edges (img (m, k)).
    Returns the sum of the forward and the backward path costs (m, n, k)."""
    m = C.shape[0]
    Lf = np.empty_like(C)
    Lb = np.empty_like(C)
    Cb = C[::-1]
    prev = np.stack([C[0], Cb[0]])          # (2, n, k): the forward and the backward path in one array
    Lf[0] = prev[0]
    Lb[m - 1] = prev[1]
    a = np.empty_like(prev)
    t = np.empty_like(prev[:, 1:])
    p1 = F32(P1)
    dI = np.abs(np.diff(img, axis=0))
    if tau > 0:
        p2s = np.maximum(F32(P2) / (F32(1.0) + dI * F32(1.0 / tau)), p1).astype(F32)   # (m-1, k)
    else:
        p2s = np.full(dI.shape, F32(P2), F32)
    p2 = np.empty((2, 1, C.shape[2]), F32)
    for i in range(1, m):
        p2[0, 0] = p2s[i - 1]
        p2[1, 0] = p2s[m - 1 - i]
        mn = prev.min(axis=1, keepdims=True)
        np.add(prev[:, :-1], p1, out=t)
        np.minimum(prev[:, 1:], t, out=a[:, 1:])
        a[:, 0] = prev[:, 0]
        np.add(prev[:, 1:], p1, out=t)
        np.minimum(a[:, :-1], t, out=a[:, :-1])
        np.minimum(a, mn + p2, out=a)
        a -= mn
        a[0] += C[i]
        a[1] += Cb[i]
        Lf[i] = a[0]
        Lb[m - 1 - i] = a[1]
        prev, a = a, prev
    Lf += Lb
    return Lf


def _sgm(cost: np.ndarray, img: np.ndarray, P1: float, P2: float, tau: float) -> np.ndarray:
    """Sum of the 4 scanline path costs (left/right, up/down) of the cost volume (n, h, w) of image img."""
    ch = np.ascontiguousarray(cost.transpose(2, 0, 1))       # (w, n, h): paths along rows
    cv = np.ascontiguousarray(cost.transpose(1, 0, 2))       # (h, n, w): paths along columns
    return (_sgm_paths(ch, img.T, P1, P2, tau).transpose(1, 2, 0)
            + _sgm_paths(cv, img, P1, P2, tau).transpose(1, 0, 2))


def _search(a: np.ndarray, b: np.ndarray, emap: EpipolarMap, rhos: np.ndarray, win: int, noise: float,
            sgm_p1: float = 0.0, sgm_p2: float = 0.0, sgm_tau: float = 0.0, chunk_px: int = 32768,
            disp=None, cap=None, K=None):
    """Windowed ZNCC along the epipolar curve for all hypotheses at once (b warped for every hypothesis into
    one tall image, each slab padded by symmetric rows so the box filters do not mix hypotheses);
    optional semi-global aggregation (sgm_p2 > 0); winner-take-all with a parabola sub-sample fit.
    Returns rho (h x w) and the confidence of the winner. K: the numba kernels (``_search_fused``), else the
    OpenCV path (the reference)."""
    if K is not None:
        return _search_fused(K, a, b, emap, rhos, win, noise, sgm_p1, sgm_p2, sgm_tau, chunk_px, disp, cap)
    h, w = a.shape
    n = len(rhos)
    p = win // 2
    B = emap.B
    cb = emap.cam_b
    hp = h + 2 * p
    hb, wb = b.shape
    # maps on the rows of a padded by p symmetric rows; hypotheses in chunks of ~chunk_px pixels (one tall
    # remap and box filtering per chunk: the temporaries stay in cache, the peak memory stays small)
    A0, A1, A2 = (np.pad(x, ((p, p), (0, 0)), mode="symmetric")[None] for x in (emap.A0, emap.A1, emap.A2))
    if disp is not None:      # hypotheses uniform in each pixel's own displacement (rhos = disp): rho per pixel
        cn = np.hypot(emap.C1, emap.C2)
        cn_p, cap_p = (np.pad(x, ((p, p), (0, 0)), mode="symmetric")[None] for x in (cn, cap))
    P1 = A1 * F32(cb.fx) + A0 * F32(cb.cx)
    P2 = A2 * F32(cb.fy) + A0 * F32(cb.cy)
    Q1, Q2 = F32(cb.fx * B[1] + cb.cx * B[0]), F32(cb.fy * B[2] + cb.cy * B[0])
    ap, ma, va, va_pos = _a_side(a, win)
    cost = _ws("cost", (n, h, w))
    c = (slice(None), slice(p, p + h))
    step = max(1, min(n, chunk_px // (hp * w)))
    # a-side statistics tiled once for a whole chunk: the per-hypothesis arithmetic is then OpenCV's
    # array-array ops on 2-D (m * hp, w) images (no numpy broadcasting)
    ap_t, ma_t, va_t = (np.tile(x, (step, 1)) for x in (ap, ma, va_pos))
    noise4 = F32(noise ** 4)
    mul, sub = cv2.multiply, cv2.subtract
    # a chunk's temporaries in reused work planes (fresh ones page-fault: ~320 faults per locate)
    Wk = _ws("search", (7, step * hp, w))
    Wg = _ws("search_good", (2, step * hp, w), np.uint8)
    for k0 in range(0, n, step):
        k1 = min(n, k0 + step)
        m = k1 - k0
        mh = m * hp
        if disp is not None:
            R = _rho_at_disp(disp[k0:k1].astype(F32)[:, None, None], A0, cn_p, F32(B[0]), cap_p)
        else:
            R = rhos[k0:k1].astype(F32)[:, None, None]
        inv, ub, vb = (Wk[i, :mh].reshape(m, hp, w) for i in (4, 5, 6))
        # (per-pixel rho is +inf for a displacement the pixel can never reach: its map is NaN, the hypothesis
        # out of view below)
        with np.errstate(invalid="ignore", divide="ignore", over="ignore"):
            np.add(A0, B[0] * R, out=inv)
            np.divide(F32(1.0), inv, out=inv)
            np.multiply(np.add(P1, Q1 * R, out=ub), inv, out=ub)
            np.multiply(np.add(P2, Q2 * R, out=vb), inv, out=vb)
        ub2, vb2 = ub.reshape(mh, w), vb.reshape(mh, w)
        good = cv2.bitwise_and(cv2.inRange(ub2, 0.0, float(wb - 1), dst=Wg[0, :mh]),
                               cv2.inRange(vb2, 0.0, float(hb - 1), dst=Wg[1, :mh]), dst=Wg[0, :mh])
        if not float(inv.min()) > 0:
            good &= (inv.reshape(mh, w) > 0).view(np.uint8)
        bw = cv2.remap(b, ub2, vb2, cv2.INTER_LINEAR, dst=Wk[0, :mh], borderMode=cv2.BORDER_REPLICATE)
        mb = _box_to(bw, win, dst=Wk[1, :mh])
        vbb = _box_to(mul(bw, bw, dst=Wk[2, :mh]), win, dst=Wk[2, :mh])
        sub(vbb, mul(mb, mb, dst=Wk[3, :mh]), dst=vbb)
        cab = _box_to(mul(bw, ap_t[:mh], dst=Wk[3, :mh]), win, dst=Wk[3, :mh])
        sub(cab, mul(ma_t[:mh], mb, dst=mb), dst=cab)
        np.maximum(vbb, 0, out=vbb)
        mul(vbb, va_t[:mh], dst=vbb)
        vbb += noise4
        np.sqrt(vbb, out=vbb)
        cv2.divide(cab, vbb, dst=cab)
        ck = cost[k0:k1]
        np.subtract(F32(1.0), cab.reshape(m, hp, w)[c], out=ck)
        np.copyto(ck, F32(2.0), where=good.reshape(m, hp, w)[c] == 0)
    vat = va[p:p + h]
    tex = vat / (vat + F32(noise * noise))
    kf, cbest = _wta(_sgm(cost, a, sgm_p1, sgm_p2, sgm_tau) if sgm_p2 > 0 else cost, cost)
    # confidence of the winner: correlation (>= 0) times texture (windowed variance against the noise)
    conf = np.clip(1.0 - cbest, 0.0, 1.0) ** 2 * tex
    if disp is not None:
        D = np.interp(kf.ravel(), np.arange(n), disp).reshape(h, w).astype(F32)
        rho = _rho_at_disp(D, emap.A0, cn, F32(B[0]), cap)
    else:
        rho = np.interp(kf.ravel(), np.arange(n), rhos).reshape(h, w).astype(F32)
    return rho, conf.astype(F32)


@lru_cache(maxsize=8)
def _pad_rows(h: int, p: int) -> np.ndarray:
    """Source row of each of the h + 2p rows of an image padded by p rows as np.pad "symmetric" (np.pad: 0.1 ms)."""
    return np.pad(np.arange(h), (p, p), mode="symmetric")     # (shared: never written)


def _a_side(a: np.ndarray, win: int):
    """Image a padded by half a window of symmetric rows (as np.pad "symmetric"), its windowed mean and variance,
    and the variance clipped at 0: the search's a-side statistics (both paths)."""
    ap = a[_pad_rows(a.shape[0], win // 2)]
    ma = _box(ap, win)
    va = _box(ap * ap, win) - ma * ma
    return ap, ma, va, np.maximum(va, 0)


def _search_fused(K, a, b, emap: EpipolarMap, rhos, win: int, noise: float, sgm_p1: float, sgm_p2: float,
                  sgm_tau: float, chunk_px: int, disp, cap):
    """_search with its per-pixel work in numba kernels (``_dense_kernels.search_*``): per chunk of hypotheses one
    pass for the rho, the map, the in-view test and the bilinear sample of b with the products the box sums need,
    OpenCV's box sums, one pass for the cost; one pass for the winner-take-all, the rho and the confidence. The
    same float32 arithmetic as the OpenCV path (the sample reproduces cv2.remap's): the same result."""
    h, w = a.shape
    n = len(rhos)
    p = win // 2
    hp = h + 2 * p
    B0 = F32(emap.B[0])
    B = emap.B
    cb = emap.cam_b
    per_pixel = disp is not None
    # the padded rows' source rows (np.pad "symmetric"): the maps and a are read through it, never padded
    rows = _pad_rows(h, p)
    if per_pixel:
        cn = np.hypot(emap.C1, emap.C2)
        capf = np.asarray(cap, F32)
    else:
        cn = capf = emap.A0          # unused
    Q1, Q2 = F32(cb.fx * B[1] + cb.cx * B[0]), F32(cb.fy * B[2] + cb.cy * B[0])
    _, ma, va, va_pos = _a_side(a, win)
    hyp = np.asarray(disp if per_pixel else rhos, np.float64)
    cost = _ws("cost", (n, h, w))
    step = max(1, min(n, chunk_px // (hp * w)))
    Wk = _ws("search", (3, step * hp, w))
    Wg = _ws("search_good", (step * hp, w), np.uint8)
    noise4 = F32(noise ** 4)
    fx, cx, fy, cy = F32(cb.fx), F32(cb.cx), F32(cb.fy), F32(cb.cy)
    for k0 in range(0, n, step):
        k1 = min(n, k0 + step)
        mh = (k1 - k0) * hp
        bw, bw2, bwa = Wk[0, :mh], Wk[1, :mh], Wk[2, :mh]
        good = Wg[:mh]
        K.search_warp(hyp[k0:k1], per_pixel, rows, emap.A0, emap.A1, emap.A2, cn, capf, fx, cx, fy, cy, B0, Q1, Q2,
                      a, b, bw, bw2, bwa, good)
        for t in (bw, bw2, bwa):
            _box_to(t, win, dst=t)
        K.search_cost(bw, bw2, bwa, good, ma, va_pos, noise4, p, cost[k0:k1])
    agg = np.ascontiguousarray(_sgm(cost, a, sgm_p1, sgm_p2, sgm_tau)) if sgm_p2 > 0 else cost
    rho = np.empty((h, w), F32)
    conf = np.empty((h, w), F32)
    K.search_wta(agg, cost, hyp, per_pixel, emap.A0, cn, B0, capf, va[p:p + h], F32(noise * noise), rho, conf)
    return rho, conf


def _wta(agg: np.ndarray, cost: np.ndarray):
    """Winner-take-all over axis 0 of agg with a parabola sub-sample fit: fractional index and the (raw)
    cost of the winner."""
    n = agg.shape[0]
    shape = agg.shape[1:]
    flat = agg.reshape(n, -1)
    # first index of the minimum: a min-reduction over contiguous rows, then argmax of the equality mask
    # (~4x faster than numpy's strided argmin over axis 0 or a running minimum with masked copies)
    best = flat.min(axis=0)
    kbest = (flat == best).argmax(axis=0)
    ar = np.arange(best.size)
    cbest = cost.reshape(n, -1)[kbest, ar]
    cm = flat[np.maximum(kbest - 1, 0), ar]
    cp = flat[np.minimum(kbest + 1, n - 1), ar]
    curv = cm - 2 * best + cp
    with np.errstate(divide="ignore", invalid="ignore"):
        off = np.where((curv > 1e-6) & (kbest > 0) & (kbest < n - 1), 0.5 * (cm - cp) / curv, 0.0)
    return (kbest + np.clip(off, -0.5, 0.5)).reshape(shape), cbest.reshape(shape)


class _Level:
    """Per-level constants: the epipolar map with the intrinsics folded in, and b with its gradients.

    Every geometric map is affine in the pixel's normalised coordinates m = [1, m1, m2] of camera a (A = R m):
    den = A0 + B0 rho, u_b = (P1 + Q1 rho) / den, v_b = (P2 + Q2 rho) / den, d(u_b, v_b)/d rho = (C1, C2) / den^2
    (see _common.EpipolarMap). They are stored as a row part (c0 + c1 m1, per column) and a column part
    (c2 m2, per row) and built block by block (one broadcast add each), never as full-size arrays."""

    def __init__(self, geo, lev, ia, ib, rho_hi, den_min: float = 0.05, cache: bool = False,
                 strip_rows: int | None = None, n_strips: int = 1, kernels=None):
        sc = 0.5 ** lev      # level intrinsics (as level_camera, without building Camera objects)
        ca, cb = geo.cam_a, geo.cam_b
        fxa, fya, cxa, cya = ca.fx * sc, ca.fy * sc, ca.cx * sc, ca.cy * sc
        fxb, fyb, cxb, cyb = cb.fx * sc, cb.fy * sc, cb.cx * sc, cb.cy * sc
        self.h, self.w = ia.shape
        m1 = (np.arange(self.w, dtype=np.float64) - cxa) / fxa
        m2 = (np.arange(self.h, dtype=np.float64) - cya) / fya
        R = np.asarray(geo.R_ba, float)
        t = np.asarray(geo.t_ba_m, float)
        a0, a1, a2 = R[0], R[1], R[2]
        # the maps' coefficients (c0, c1, c2): A0, P1, P2, C1, C2 and (b moving towards the scene) cap:
        # half of (C1, C2): the 1/2 of the averaged gradient folded in (so E2 below is a quarter of |C|^2/den^4);
        # cap: largest rho keeping den >= den_min (only bounded when b moves towards the scene), and at most rho_hi
        cs = [a0, fxb * a1 + cxb * a0, fyb * a2 + cyb * a0, 0.5 * fxb * (t[1] * a0 - t[0] * a1),
              0.5 * fyb * (t[2] * a0 - t[0] * a2)]
        if t[0] < 0:
            cs.append(np.array([a0[0] - den_min, a0[1], a0[2]]) / -t[0])
        K = np.array(cs)
        # per map: (row part (1, w), column part (h, 1), [1, column] (h, 2), [row; 1] (2, w)): a block of rows s
        # of the map is X[s] @ W (one small matmul: exact, and ~3x faster than numpy's broadcast add); all maps
        # in one go (the same float64 arithmetic as one map at a time, ~0.2 ms less Python per level)
        n = len(cs)
        rw = (K[:, :1] + K[:, 1:2] * m1[None, :]).astype(F32)
        kc = (K[:, 2:3] * m2[None, :]).astype(F32)
        X = np.ones((n, self.h, 2), F32)
        X[:, :, 1] = kc
        Wm = np.ones((n, 2, self.w), F32)
        Wm[:, 0] = rw
        aff = [(rw[i][None, :], kc[i][:, None], X[i], Wm[i]) for i in range(n)]
        self.rw, self.kc = rw, np.ascontiguousarray(kc)     # (the fused kernels add the parts per pixel: the same sum)
        self.ia = ia
        self.ib = ib
        self.A0, self.P1, self.P2, self.C1, self.C2 = aff[:5]
        self.B0 = F32(t[0])
        self.Q1 = F32(fxb * t[1] + cxb * t[0])
        self.Q2 = F32(fyb * t[2] + cyb * t[0])
        self.cap = aff[5] if t[0] < 0 else None
        self.rho_hi = F32(rho_hi)
        self.kernels = kernels
        if kernels is not None:
            # the fused kernels: the gradient of a for the whole level, and b4 with a border of one zero pixel
            # (gn_level's samples then read no neighbour outside it); b4 is its interior
            self.gxa, self.gya = _ws("gxa", ia.shape), _ws("gya", ia.shape)
            kernels.scharr(ia, self.gxa, self.gya)
            hb, wb = ib.shape
            self.b4p = _ws("b4p", (hb + 2, wb + 2, 4))
            kernels.pack_b4p(ib, self.b4p)
            self.b4 = self.b4p[1:-1, 1:-1]
        else:
            gx = cv2.Scharr(ib, cv2.CV_32F, 1, 0, dst=_ws("gxb", ib.shape), scale=1.0 / 32.0, borderType=_BR)
            gy = cv2.Scharr(ib, cv2.CV_32F, 0, 1, dst=_ws("gyb", ib.shape), scale=1.0 / 32.0, borderType=_BR)
            self.b4 = cv2.merge([ib, gx, gy, _ws("one", ib.shape, fill=1.0)], dst=_ws("b4", ib.shape + (4,)))
        # strips' geometric maps and gradients of a, kept for the next iteration (levels iterated more than
        # once); read-only. Stored in planes of a work buffer (8 per strip), like every temporary of a strip
        # (``work``): fresh strip-sized arrays page-faulted, the allocator trimming the heap they were freed to
        # (~6500 minor faults, ~11 ms of system time per 512 x 512 locate, before the work planes)
        self.strip_rows = min(self.h, strip_rows or self.h)
        self._cache = {} if cache else None
        self._cplanes = (_ws(("gn_cache", lev), (8 * n_strips, self.strip_rows + 2, self.w)) if cache else None)
        self._ncp = 0

    _N_WORK = 16

    def work(self) -> np.ndarray:
        """The strips' work planes (_N_WORK, strip_rows + 2, w): a strip of n rows uses [:, :n] (each plane
        contiguous); the 2 spare rows take the Scharr halo of grad_a."""
        return _ws(("gn_work", self.w), (self._N_WORK, self.strip_rows + 2, self.w))

    def _cache_plane(self, rows: int) -> np.ndarray:
        """Next free plane of the level's cache buffer (rows x w); a fresh array if it is full."""
        if self._ncp < len(self._cplanes):
            self._ncp += 1
            return self._cplanes[self._ncp - 1, :rows]
        return np.empty((rows, self.w), F32)

    def rows(self, c, s: slice, out: np.ndarray | None = None) -> np.ndarray:
        """Rows s of an affine map, into ``out`` (read-only and not in ``out`` when cached)."""
        if self._cache is None:
            return np.matmul(c[2][s], c[3], out=out)
        k = (id(c), s.start, s.stop)
        v = self._cache.get(k)
        if v is None:
            v = self._cache[k] = np.matmul(c[2][s], c[3], out=self._cache_plane(s.stop - s.start))
        return v

    def c2(self, s: slice) -> np.ndarray:
        """A quarter of |C|^2 on rows s (C1, C2 are halved): the sensitivity without its 1/den^4 factor."""
        k = ("c2", s.start, s.stop)
        v = self._cache.get(k) if self._cache is not None else None
        if v is None:
            C1, C2 = self.rows(self.C1, s), self.rows(self.C2, s)
            if self._cache is not None:
                v = self._cache[k] = cv2.multiply(C1, C1, dst=self._cache_plane(s.stop - s.start))
                cv2.add(v, cv2.multiply(C2, C2, dst=_ws("c2_tmp", v.shape)), dst=v)
            else:
                v = cv2.multiply(C1, C1, dst=C1)
                cv2.add(v, cv2.multiply(C2, C2, dst=C2), dst=v)
        return v

    def grad_a(self, ya: int, yb: int, work=None):
        """Gradient of a on rows [ya, yb) (one extra row each side when available, so the Scharr kernel sees
        the image's own rows and reflects only at the image border), in two planes of ``work`` (w wide, at
        least yb - ya + 2 rows) unless cached. Read-only."""
        k = ("ga", ya, yb)
        v = self._cache.get(k) if self._cache is not None else None
        if v is None:
            y0, y1 = max(0, ya - 1), min(self.h, yb + 1)
            n = y1 - y0
            if self._cache is not None:
                dx, dy = self._cache_plane(n), self._cache_plane(n)
            elif work is not None:
                dx, dy = work[0][:n], work[1][:n]
            else:
                dx = dy = None
            src = self.ia[y0:y1]
            gx = cv2.Scharr(src, cv2.CV_32F, 1, 0, dst=dx, scale=1.0 / 32.0, borderType=_BR)
            gy = cv2.Scharr(src, cv2.CV_32F, 0, 1, dst=dy, scale=1.0 / 32.0, borderType=_BR)
            v = gx[ya - y0:yb - y0], gy[ya - y0:yb - y0]
            if self._cache is not None:
                self._cache[k] = v
        return v

    def cap_rows(self, y0: int, y1: int) -> np.ndarray:
        """Rows [y0, y1) of the level's rho cap (den >= den_min, clipped to [0, rho_hi]), computed once per level
        (the per-pixel search sets rho_hi from the pixels nearest the focus of expansion, so the cap binds in most
        strips of every iteration)."""
        if getattr(self, "_capmap", None) is None:
            cap = np.matmul(self.cap[2], self.cap[3])
            self._capmap = np.clip(cap, F32(0), self.rho_hi, out=cap)
        return self._capmap[y0:y1]

    def residual_at_infinity(self, s: slice, out, u, v):
        """Rows s of I_b warped at rho = 0 (the rotation alone) minus I_a, NaN where that leaves b (or lies behind
        it), in ``out`` (``u``, ``v``: work planes for the map; all three rows-of-s x w)."""
        den = self.rows(self.A0, s, out=out)
        ub = cv2.divide(self.rows(self.P1, s, out=u), den, dst=u)
        vb = cv2.divide(self.rows(self.P2, s, out=v), den, dst=v)
        if not float(den.min()) > 0:
            ub[den <= 0] = -1e6
        r0 = cv2.remap(self.ib, ub, vb, cv2.INTER_LINEAR, dst=out, borderMode=cv2.BORDER_CONSTANT,
                       borderValue=float("nan"))
        return cv2.subtract(r0, self.ia[s], dst=r0)

    def warp(self, rho, s: slice, T):
        """Warped [I_b, gx_b, gy_b, in-view] at rho (rows s of a), and 1/den (in T[0]; T[1], T[2]: the map)."""
        inv = cv2.scaleAdd(rho, float(self.B0), self.rows(self.A0, s, out=T[0]), dst=T[0])
        np.divide(F32(1.0), inv, out=inv)
        ub = cv2.scaleAdd(rho, float(self.Q1), self.rows(self.P1, s, out=T[1]), dst=T[1])
        cv2.multiply(ub, inv, dst=ub)
        vb = cv2.scaleAdd(rho, float(self.Q2), self.rows(self.P2, s, out=T[2]), dst=T[2])
        cv2.multiply(vb, inv, dst=vb)
        wv = cv2.remap(self.b4, ub, vb, cv2.INTER_LINEAR, dst=_ws("wv", ub.shape + (4,)),
                       borderMode=cv2.BORDER_CONSTANT, borderValue=0)
        return wv, inv

    def noise(self, rho, step: int = 3, final: bool = True):
        """Robust residual noise on the subsampled grid (every ``step``-th pixel) at rho: over all pixels
        (Huber scale) and over the fully in-view ones (the final noise; None unless ``final``)."""
        sr, sc = slice(0, self.h, step), slice(0, self.w, step)
        if self.kernels is not None:    # the same residuals in one numba pass (b sampled as gn_level does)
            g = (-(-self.h // step), -(-self.w // step))
            r, inview = _ws("noise_r", g), _ws("noise_in", g, np.uint8)
            self.kernels.residual_grid(self.b4p, self.ia, self.rw, self.kc, rho, self.B0, self.Q1, self.Q2, step, r,
                                       inview)
            return _robust_sigma(r, step=1), (_robust_sigma(r, inview.view(bool), step=1) if final else None)
        rs = np.ascontiguousarray(rho[sr, sc])
        B0, Q1, Q2 = self.B0, self.Q1, self.Q2
        sub = lambda c: np.matmul(c[2][sr], np.ascontiguousarray(c[3][:, sc]))   # the map on the grid (exact)
        inv = rs * B0
        inv += sub(self.A0)
        np.divide(F32(1.0), inv, out=inv)
        ub = rs * Q1
        ub += sub(self.P1)
        ub *= inv
        vb = rs * Q2
        vb += sub(self.P2)
        vb *= inv
        wv = cv2.remap(self.b4, ub, vb, cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT, borderValue=0)
        r = wv[..., 0] - self.ia[sr, sc]
        if not final:
            return _robust_sigma(r, step=1), None
        inview = (wv[..., 3] > F32(0.999)) & (inv > 0)
        return _robust_sigma(r, step=1), _robust_sigma(r, inview, step=1)


def locate_dense(view_a: View, view_b: View, *, max_disp_px: float | None = None, min_range_m: float | None = None,
                 search_level: int | None = None, search_step_px: float = 1.0, search_window: int = 5,
                 median: bool = True, iters=(3, 2, 2, 1), window: int = 7, huber_k: float = 2.0,
                 trust_px: float = 1.0, presmooth_sigma: float = 0.6, max_rel_std: float = 0.34,
                 far_parallax_px: float = 0.5, tex_k: float = 1.0, orient_min: float = 0.02,
                 occ_k: float = 3.0, occ_window: int = 3, occ_px: float = 0.25, trunc_px: float = 1.0,
                 std_scale: float = 1.35, shift_px: int = 2, shift_ratio: float = 0.4,
                 fill_sigma: float = 4.0, fill_c: float = 0.3, highpass_sigma: float = 0.0,
                 highpass_levels: int = 9, bias: bool = True,
                 match_floor_px: float = 0.05, strip_px: int = 49152, sgm: bool = False,
                 tex_noise: str = "image", noise_info: bool = True, per_pixel_search: bool = True,
                 inf_test: bool = True, fill: bool = True,
                 sgm_p1: float = 1.0, sgm_p2: float = 8.0, sgm_tau: float = 8.0,
                 fused: bool | None = None) -> RangeResult:
    """Dense inverse range of every pixel of view a from the pair (a, b) with known poses.

    max_disp_px / min_range_m: search range: displacements up to max_disp_px (default 0.3 * image size) along
    each pixel's epipolar curve, and (when given) no range below min_range_m.
    per_pixel_search: the hypotheses are uniform in each pixel's OWN displacement (rho per pixel, closed form
    ``_rho_at_disp``), capped where the point would reach camera b's plane and, without min_range_m, at 5 % of the
    baseline (a camera moving away reaches a large displacement near the focus of contraction only at absurd rho). With one set of rho for all
    pixels (False: the old search), the range where the image's fastest-moving pixel reaches max_disp_px was
    the least range searched ANYWHERE: 14 m on the demo approach flight at 5 Hz, so a pole straight ahead at
    11 m (51 px of motion near the focus of expansion, where 77 px were allowed) could not be found (raw error
    of its pixels 50 % -> 2.9 %, within 5 %: 34 -> 55 %). Sim presets and Middlebury: medians unchanged,
    coverage within 0.6 points, gross errors on the paper preset 1283 -> 1129 pixels.
    search_level: pyramid level of the epipolar search (default: coarsest level of geometric-mean size >= 64 px,
    at most 3).
    search_step_px: hypothesis spacing, pixels of displacement at the search level.
    iters: Gauss-Newton iterations per level, finest level last (padded with its first entry if short).
    (3, 3, 1, 1) is ~8 % faster and as accurate on the sim presets, but leaves a 0.03 px disparity bias on
    the sub-pixel plane test (vs <= 0.011 px): level 1 needs its second iteration.
    window: box window (level pixels, odd) of the normal equations. huber_k: Huber threshold in noise
    sigmas. trust_px: Levenberg trust term ~ a step of this many pixels of displacement per iteration.
    presmooth_sigma: Gaussian pre-smoothing of both images (pixels). 0.6 measured best overall (sim medians
    fast/paper 0.64/0.78 % at 0.8 -> 0.59/0.72 %; 0.4 and below trade a higher 90th percentile and worse
    Middlebury venus/tsukuba for lower sim medians).
    max_rel_std: largest relative std of the range for VALID. far_parallax_px: AT_INFINITY needs
    2 sigma below the inverse range of this much parallax (see _common.far_inverse_range).
    tex_k: LOW_TEXTURE where the texture the model can use -- the windowed variance of the gradient (a brightness
    ramp is absorbed by the per-window offset) -- is below (1 + tex_k^2) x the gradient energy of the noise alone,
    i.e. below the noise's own at tex_k = 1 (with the total gradient energy, the faint sky gradient of the fast
    preset passed and 3.4 % of its sky got a finite range; with the variance 0.75 %). tex_noise: which noise:
    "image" (the sensor noise measured on image a, ``image_noise_sigma``) or "residual" (the final residual's,
    which on real images also holds interpolation and non-Lambertian misfit, 2.6-3.4 x the sensor noise on
    Middlebury teddy / cones: there it flagged 22-25 % of the pixels, whose estimates were within 0.6-1.6 %).
    "image" with tex_k 1 (was "residual" with 0.5): Middlebury coverage cones 66 -> 80 %, teddy 60 -> 71 %,
    venus 64 -> 68 %, tsukuba 62 -> 65 %, median error within -0.07 .. +0.08 pp; sim presets coverage
    +0 .. +3 points, medians within 0.02 pp.
    noise_info: subtract the information the noise's own gradients put into the normal equations (E2 noise_G per
    unit weight) before the sigma: where texture is faint, sigma then grows instead of staying tight around the
    neighbours' value (sky pixels of the fast preset with a finite range: 0.75 -> 0.53 %).
    inf_test: ILL_CONDITIONED where a point at infinity (rho = 0: b warped by the rotation alone) explains the
    7 x 7 window at least as well as the estimate does (and the estimate is more than 2 sigma from 0): the data
    do not support that range. Judged at level 1's last iteration and carried to level 0 (a quarter of the work;
    the regions it catches are blobs of tens of pixels): sky pixels VALID nearer than 50 m on the approach flight
    73 -> 26 against the level-0 test, coverage within 0.5 point. Faint clouds reached by a wrong start (the coarse search's fill) were ranged at
    9-44 m with a tight sigma and became the nearest "obstacles" of the demo approach flight at 512 x 512; with
    the test none is left nearer than the real ones; fast preset sky with a finite range 0.53 -> 0.25 %;
    coverage -0.1 point on the sim presets, -0.2 .. -1.7 on Middlebury (medians equal).
    orient_min: ILL_CONDITIONED where the epipolar share of the gradient energy is below this.
    occ_k: occluded (OUT_OF_VIEW) where the RMS residual over an occ_window x occ_window window exceeds
    occ_k x noise. occ_window 3 (not the 7 of the normal equations): on a thin near object (the demo flight's
    pole, 3-8 px wide) every 7 x 7 window straddles the depth edge and flagged 2/3 of its correct estimates;
    3 x 3 keeps them (pole coverage 0.32 -> 0.60 at 1.5 % median error; sim presets +0.5-2.6 points of
    coverage, median error +0.01 pp; the estimates themselves are unchanged). occ_px: a residual that a
    misregistration of occ_px pixels explains (occ_px^2 x the windowed gradient energy) is not an occlusion: at
    edges of strong contrast interpolation alone leaves such residuals (Middlebury venus: 11 % of the pixels were
    flagged occluded with a median error of 1.3 %; at 0.25 px the flagged ones have 40 % and coverage rises
    65 -> 70 %; sim presets +1 .. +4 points of coverage, medians within 0.02 pp).
    trunc_px: TRUNCATION where the last update still moves the match by more than this (level-0 px): the
    step past which the first-order model is not trusted (at 0.5 px, 17-30 % of sim pixels were flagged
    with a median error of 1 %, since the reported estimate is the one after that step).
    std_scale: calibration factor of the reported sigma: 1.35 = the measured robust spread of
    (rho - rho_true) / sigma on the sim presets (1.1-1.5; the window's samples are correlated by the
    pre-smoothing and the interpolation). max_rel_std is 0.25 x 1.35 so that VALID is unchanged by it.
    shift_px / shift_ratio: shiftable windows at the levels above 0 (``_shift_windows``): a pixel takes the
    normal-equation sums of the window shift_px pixels to its left or right where that window's least-squares cost
    is below shift_ratio x its centred window's. A window straddling a depth edge fits neither surface and its
    estimate blends them (the nearer one "fattens"); one shifted onto the pixel's side fits. Level 0 keeps the
    centred window (its estimate moves within a pixel; its sigma and flags are the pixel's own window's). Measured
    against shift_px 0: share of estimates off by > 25 % paper 4.0 -> 3.2 %, fast 2.4 -> 2.4, turning 1.7 -> 1.6,
    climbing 1.0 -> 1.0, stereo 1.9 -> 1.9, Middlebury tsukuba 3.1 -> 2.8, venus 3.3 -> 3.0, teddy 3.4 -> 2.8,
    cones 2.1 -> 1.8 %; coverage +0.3 .. +3.2 points; medians within -0.07 .. +0.02 pp (paper 0.82 -> 0.75 %);
    Table I vehicles -0.5 / +2.3 / +0.7 %; +1.5 % locate time. At every level (level 0 too) the gains were the
    same at +6 % time; at 3 px with ratio 0.5 the small far Table I vehicle went +2.3 -> +7.4 %; without the ratio
    (least cost wins) the sim medians rose (noise picks the window).
    strip_px: pixels per strip of rows of the Gauss-Newton steps, halo included; strips balanced in height
    (<= 0: whole image at once; same result). 49152 (6 strips of 86 rows at 512 x 512): the 16 work planes,
    ~3 MiB, stay in a 4 MiB L2, with fewer halo rows and calls than 32768 (9 strips): 2-5 % faster per
    locate (interleaved in one process, 25 rounds x 5 presets, twice); 65536 as fast, 98304 slower.
    fill: pixels without a measurement (low texture, ill-conditioned, out of view of b; not occluded or truncated)
    get an inverse range inferred from the measured ones around them (``eonav.ranging.methods.fill``: plane fits in
    windows growing by octaves, sigma from the fit and its disagreement across scales), flagged FILLED (not VALID),
    where that sigma is within max_rel_std like any VALID pixel's. Sim presets: coverage of the non-sky pixels
    63-79 % -> 73-91 %, median error 0.34-0.80 % -> 0.37-0.83 %; the filled pixels' z spread 0.6-0.8 (their
    own median error 0.3-2 %); Middlebury coverage 65-80 % -> 81-87 %, medians within +0.1 pp.
    (Not to be confused with fill_sigma / fill_c: the coarse search's normalised-convolution fill, which only
    seeds the Gauss-Newton steps.)
    sgm: semi-global aggregation (4 scanline paths) of the coarse ZNCC cost volume before winner-take-all;
    sgm_p1 / sgm_p2: penalties (cost units, 1 - ZNCC) of a one-hypothesis / larger jump between neighbours,
    sgm_tau: grey levels over which the jump penalty halves across an intensity edge. Off by default:
    measured on Middlebury it lowers the raw all-pixel median error (teddy 0.94 -> 0.83 %, venus 1.51 ->
    1.41 %, share of pixels off by > 5 %: teddy 22.5 -> 17.2 %, venus 25.6 -> 19.8 %), but on the paper
    preset it pulls the small far vehicles into their background at the coarse level (vehicle2 +2.7 ->
    +8.8 %, vehicle1 -0.0 -> -1.3 %), whatever the penalties (0.2/2 .. 1/8, tau 1 .. 8).
    fused: each Gauss-Newton step of a level in one numba pass (``_dense_kernels.gn_level``: the map, the warp, the
    terms, their window sums streamed row by row, the update and the classification; ``_gn_level_fused``) instead
    of the OpenCV path's ~100 calls per strip of rows; None: when numba is installed, else the OpenCV path; False:
    the OpenCV path (the reference); True: numba required. The same result to float rounding (the window sums add in
    another order): ranges valid in both within 1.5e-5 (99th percentile) on the sim presets, flags differ on
    <= 1e-4 of the pixels. Level 0's final step 13.7 -> ~7 ms, locate dense / DIS 0.45-0.53 -> 0.32-0.36
    (512 x 512 sim presets, interleaved in one process). The coarse search too (``_search_fused``: the map,
    cv2.remap's bilinear sample, the ZNCC cost and the winner-take-all in three kernels, the box sums OpenCV's,
    bit-identical): 4.5-5.3 -> 1.3-1.7 ms.
    """
    t_start = time.perf_counter()
    geo = pair_geometry(view_a, view_b)
    Ia, Ib = view_a.image, view_b.image
    ha, wa = Ia.shape
    if geo.baseline_m <= 1e-12:
        return no_motion_result((ha, wa), METHOD, "zero baseline")
    if search_level is None:
        # coarsest level whose geometric-mean size is >= 64 px (at most 3): the search's resolution follows the
        # image's area, not its short side (640 x 480 searches at 80 x 60 like 512 x 512 at 64 x 64; with the
        # short side it searched at 160 x 120: 4x the work, 2x the locate time, no accuracy gain: 1.05 -> 1.02 %)
        m = math.sqrt(min(ha * wa, Ib.shape[0] * Ib.shape[1]))
        search_level = int(max(0, min(3, math.floor(math.log2(m / 64.0)))))
    L = search_level
    nlev = L + 1
    if tex_noise not in ("image", "residual"):
        raise InputError(f"tex_noise must be 'image' or 'residual', got {tex_noise!r}")
    img_sigma = image_noise_sigma(Ia) if tex_noise == "image" else None
    if presmooth_sigma > 0:
        Ia = _blur(Ia, presmooth_sigma, dst=_ws("pre_a", Ia.shape))
        Ib = _blur(Ib, presmooth_sigma, dst=_ws("pre_b", Ib.shape))
    pa, pb = pyramid(Ia, nlev), pyramid(Ib, nlev)
    if highpass_sigma > 0:   # remove local brightness offsets (illumination, vignetting, exposure)
        pa = [x - _blur(x, highpass_sigma) if i < highpass_levels else x for i, x in enumerate(pa)]
        pb = [x - _blur(x, highpass_sigma) if i < highpass_levels else x for i, x in enumerate(pb)]

    K = optional_kernels("_dense_kernels") if fused is None or fused else None
    if fused and K is None:
        raise InputError("fused=True needs numba (pip install numba)")

    # --- 1. epipolar search at the coarse level
    em_s = EpipolarMap.build(geo, L, pa[L].shape, pb[L].shape)
    sub = _sparse(em_s)
    md = (float(max_disp_px) if max_disp_px is not None else 0.3 * max(wa, ha)) / 2.0 ** L
    if per_pixel_search:
        if not math.isfinite(_find_rho_max(sub, md)):
            return no_motion_result((ha, wa), METHOD, "no parallax at any range")
        # nothing nearer than min_range_m, or than 5 % of the baseline (near the focus of contraction of a camera
        # moving away, a pixel's displacement is reached only at absurd rho; the den cap only binds moving towards)
        near_m = float(min_range_m) if min_range_m is not None else 0.05 * geo.baseline_m
        cap = np.minimum(em_s.rho_cap, F32(1.0 / near_m))
        disp = np.arange(0.0, md + 0.5 * search_step_px, search_step_px)
        # largest finite rho searched anywhere (the Gauss-Newton steps are clipped at 1.25 x it): at the largest
        # displacement some pixel can reach (moving away from the scene, displacements are bounded)
        cn = np.hypot(em_s.C1, em_s.C2)
        rho_max = 0.0
        for dv in disp[::-1]:
            rm = _rho_at_disp(F32(dv), em_s.A0, cn, F32(em_s.B[0]), cap)
            rm = rm[np.isfinite(rm)]
            if rm.size:
                rho_max = float(rm.max())
                break
        rhos = disp
        rho, conf = _search(pa[L], pb[L], em_s, disp, search_window, noise=2.0, sgm_p1=sgm_p1,
                            sgm_p2=sgm_p2 if sgm else 0.0, sgm_tau=sgm_tau, disp=disp, cap=cap, K=K)
    else:
        if min_range_m is not None:
            rho_max = 1.0 / float(min_range_m)
        else:
            rho_max = _find_rho_max(sub, md)
            if not math.isfinite(rho_max):
                return no_motion_result((ha, wa), METHOD, "no parallax at any range")
        rhos = _hypotheses(sub, rho_max, search_step_px)
        rho, conf = _search(pa[L], pb[L], em_s, rhos, search_window, noise=2.0, sgm_p1=sgm_p1,
                            sgm_p2=sgm_p2 if sgm else 0.0, sgm_tau=sgm_tau, K=K)
    if median:
        rho = cv2.medianBlur(rho, 3)
    if fill_sigma > 0:
        # normalised convolution: weak matches (textureless, ambiguous) take the confident neighbours' value
        nc = _blur(conf * rho, fill_sigma) / (_blur(conf, fill_sigma) + F32(1e-6))
        wf = conf / (conf + F32(fill_c))
        rho = (wf * rho + (1 - wf) * nc).astype(F32)
    rho_hi = F32(rho_max * 1.25)

    # --- 2. coarse-to-fine re-linearised Gauss-Newton, block by block (strips of rows: every temporary
    # stays in cache), each block with a halo of half a window so the box sums are those of the whole image
    iters = list(iters)
    while len(iters) < nlev:
        iters.insert(0, iters[0])
    iters = iters[-nlev:]
    prm = dict(window=window, occ_window=min(int(occ_window), window), huber_k=huber_k,
               lam_k=1.0 / (window * window * trust_px * trust_px), bias=bias,
               shift_px=0, shift_ratio=F32(shift_ratio))
    g0, gG = _noise_gains(float(presmooth_sigma))
    # the infinity test runs at level 1's last iteration (a quarter of the pixels; the ambiguous regions are blobs
    # of tens of pixels) and its mask is carried to level 0; at level 0 itself when there is no level 1
    inf_level = 1 if inf_test and L >= 1 and iters[L - 1] >= 1 else 0
    prm["inf_mask"] = None
    for lev in range(L, -1, -1):
        n_it = max(iters[L - lev], 1 if lev == 0 else 0)
        # shiftable windows at the coarser levels, where a pixel's estimate settles on one surface or the other;
        # level 0 refines within a pixel, and its sigma and flags are those of the pixel's own (centred) window
        prm["shift_px"] = int(shift_px) if bias and lev >= 1 else 0
        h, w = pa[lev].shape
        # strip arrays incl. the halo within strip_px (a strip's work planes stay in L2)
        step = max(8, strip_px // w - 2 * (window // 2)) if strip_px > 0 else h
        step = -(-h // -(-h // step))      # balanced: no thin last strip (each strip costs ~50 calls)
        lv = _Level(geo, lev, pa[lev], pb[lev], rho_hi, cache=n_it > 1 and K is None,
                    strip_rows=step + 2 * (window // 2), n_strips=-(-h // step), kernels=K)
        if rho.shape != pa[lev].shape:
            if rho.shape[0] * 2 == h and rho.shape[1] * 2 == w:     # into a work buffer: same values
                rho = cv2.pyrUp(rho, dst=_ws("rho_up", (h, w)), dstsize=(w, h))
            else:
                rho = pyr_up_to(rho, pa[lev].shape)
        for it in range(n_it):
            last = lev == 0 and it == n_it - 1
            if it == 0 or last:
                sig_all, sig_in = lv.noise(rho, final=last)
            if it == 0:
                sigma = sig_all
            # the final estimate is a result (fresh array); intermediate ones are work buffers
            new = np.empty_like(rho) if last else _ws(("rho", it % 2), rho.shape)
            if last:
                fin = _Final(rho.shape, sig_in, img_sigma, g0, gG, window,
                             presmooth_sigma, tex_k, occ_k, occ_px, trunc_px, match_floor_px, noise_info,
                             inf_test, std_scale, orient_min, far_inverse_range(geo, far_parallax_px),
                             max_rel_std)
            prm["inf_out"] = (_ws("inf_l1", (h, w), np.uint8) if inf_test and inf_level == lev == 1
                              and it == n_it - 1 else None)
            if K is not None:
                _gn_level_fused(K, lv, rho, new, sigma, prm, fin if last else None)
            else:
                for y0 in range(0, h, step):
                    _gn_block(lv, rho, new, y0, min(h, y0 + step), sigma, prm, fin if last else None)
            if prm["inf_out"] is not None:
                h0, w0 = pa[0].shape
                prm["inf_mask"] = cv2.resize(prm["inf_out"], (w0, h0), interpolation=cv2.INTER_NEAREST)
            rho = new
    n_filled = fill_unmeasured(rho, fin.std, fin.flags, fin.rng, fin.conf, max_rel_std, rho_far=fin.rho_far,
                               exclude=fin.amb) if fill else 0
    info = {"seconds": time.perf_counter() - t_start, "noise_sigma": fin.sigma, "rho_max_per_m": rho_max,
            "n_hypotheses": int(len(rhos)), "search_level": L, "baseline_m": geo.baseline_m,
            "filled_fraction": n_filled / max(rho.size, 1)}
    return make_result(rho, fin.std, fin.flags, fin.rng, fin.conf, METHOD, fin.n_val, fin.n_inf, info)


class _Final:
    """Output arrays and thresholds of the last linearisation at level 0 (uncertainty, flags, classification),
    filled block by block."""

    def __init__(self, shape, sigma, img_sigma, g0, gG, window, presmooth_sigma, tex_k, occ_k, occ_px, trunc_px,
                 match_floor_px, noise_info, inf_test, std_scale, orient_min, rho_far, max_rel_std):
        self.sigma = sigma
        n_win = float(window * window)
        sc2 = float(std_scale) ** 2
        self.var_k = F32(sc2 * sigma * sigma / n_win)
        self.floor2 = F32(sc2 * match_floor_px ** 2 / 4.0)  # E2 in _gn_block is a quarter of |d map/d rho|^2
        # gradient energy of the noise alone: of the sensor noise (img_sigma), or of the final residual's (which on
        # real images also holds interpolation and non-Lambertian misfit: 2.6-3.4 x the sensor noise on Middlebury
        # teddy / cones)
        noise_G = img_sigma * img_sigma * gG if img_sigma is not None else (sigma * sigma / (2.0 * g0)) * gG
        self.low_thr = F32((1.0 + tex_k * tex_k) * noise_G)
        self.noise_G = F32(noise_G)
        self.noise_info = bool(noise_info)
        self.inf_test = bool(inf_test)
        self.occ_thr = F32((occ_k * sigma) ** 2)
        self.occ_px2 = F32(float(occ_px) ** 2)
        self.trunc2 = F32(trunc_px * trunc_px / 4.0)
        self.orient_min = F32(4.0 * orient_min)
        self.rho_far, self.max_rel_std = rho_far, max_rel_std
        self.std = np.empty(shape, F32)
        self.flags = np.empty(shape, np.uint8)
        self.rng = np.empty(shape, F32)
        self.conf = np.empty(shape, F32)
        self.amb = np.zeros(shape, bool)      # the infinity test's: not filled either
        self.n_val = self.n_inf = 0


def _box_to(img: np.ndarray, win: int, dst: np.ndarray | None = None) -> np.ndarray:
    k = _box_kernel(win)
    return cv2.sepFilter2D(img, -1, k, k, dst=dst, borderType=_BR)


def _shift_windows(sh: int, ratio, H, g, S0, S1, Sq, Q) -> None:
    """Shiftable windows (in place on the window means of a block's rows): each pixel takes the sums of the window
    shifted sh pixels left or right (clamped at the image border; the pixel stays inside it) instead of its centred
    one where that one fits the linearised model with less than ``ratio`` times the centred window's cost. Cost: the
    weighted residual left after the window's least-squares solution (rho and the brightness offset), per unit
    weight: (Q - Sq^2 / S0 - g'^2 / H') / S0, g' = g - Sq S1 / S0, H' = H - S1^2 / S0. A window straddling a depth
    edge fits neither side (its rho is a blend: the nearer surface "fattens"); a shifted one on the pixel's side
    fits. The threshold keeps the centred window where the costs differ by noise (the least cost alone raised the
    sim presets' median errors)."""
    def cost(H_, g_, S0_, S1_, Sq_, Q_):
        with np.errstate(divide="ignore", invalid="ignore", over="ignore"):
            S1n = S1_ / S0_
            gp = g_ - Sq_ * S1n
            Hp = np.maximum(H_ - S1_ * S1n, F32(1e-12))
            c = (Q_ - Sq_ * Sq_ / S0_ - gp * gp / Hp) / S0_
        return np.where(np.isfinite(c), c, F32(np.inf))
    w = H.shape[1]
    planes = (H, g, S0, S1, Sq, Q)
    cols = [np.clip(np.arange(w) + d, 0, w - 1) for d in (-sh, sh)]
    c0 = cost(*planes)
    cl, cr = (cost(*(a[:, c] for a in planes)) for c in cols)
    right = cr < cl                                   # (a tie takes the left one)
    take = np.where(right, cr, cl) < ratio * c0
    for a in planes[:5]:
        np.copyto(a, np.where(right, a[:, cols[1]], a[:, cols[0]]), where=take)


def _infinity_ambiguous(lv: _Level, s: slice, o: slice, r, T, win: int, squared: bool = False) -> np.ndarray:
    """Does a point at infinity explain the window at least as well as the current estimate? (Then the estimate is
    not supported by the data: faint clouds ranged at whatever their neighbours had after a wrong start.) ``r``: the
    in-view-masked residual at the estimate on the strip rows s (squared already with ``squared``; either way
    consumed); rows o of the strip are judged. Uses work planes T1, T2, T6 (free after the weights)."""
    if not squared:
        cv2.multiply(r, r, dst=r)
    Se = _box_to(r, win)[o]
    r0 = lv.residual_at_infinity(s, T[1], T[2], T[6])
    cv2.multiply(r0, r0, dst=r0)
    return _box_to(r0, win, dst=r0)[o] <= Se       # (NaN, a window reaching out of b: no ambiguity)


def _strip(lv: _Level, rho, y0: int, y1: int, win: int):
    """A strip's rows with its halo of half a window (s), its own rows within them (o), the work planes (W, and T
    cut to the strip) and rho on the strip."""
    ya, yb = max(0, y0 - win // 2), min(lv.h, y1 + win // 2)
    W = lv.work()
    return slice(ya, yb), slice(y0 - ya, y1 - ya), W, W[:, :yb - ya], rho[ya:yb]


def _gn_block(lv: _Level, rho, new, y0: int, y1: int, sigma: float, prm: dict, fin: _Final | None):
    """One re-linearised Gauss-Newton step for rows [y0, y1) of ``rho``, written into ``new``; with ``fin``,
    also the uncertainty, flags and classification of those rows.

    Elementwise work is done with OpenCV's array-array arithmetic (cv2.multiply/add/subtract/scaleAdd into
    existing buffers): ~1.5x faster than numpy's ufuncs on these strip-sized float32 arrays. Every float
    temporary is one of the strip's work planes T[i] (lv.work; reused from strip to strip and call to call:
    fresh ones page-faulted, see _Level); the comments name what each plane holds."""
    mul, add, sub = cv2.multiply, cv2.add, cv2.subtract
    win = prm["window"]
    s, o, W, T, R = _strip(lv, rho, y0, y1, win)
    wv, inv = lv.warp(R, s, T)                                   # T0 inv (T1, T2: the map, free again)
    # the warp's channels (cv2.split into the planes: one pass, ~6x faster than 4 strided numpy copies)
    Ib, gxb, gyb, mask = cv2.split(wv, [T[3], T[4], T[5], T[6]])
    r = sub(Ib, lv.ia[s], dst=Ib)                                # T3 r
    gxa, gya = lv.grad_a(s.start, s.stop, (W[7], W[8]))                   # T7, T8 (unless cached)
    C1, C2 = lv.rows(lv.C1, s, out=T[1]), lv.rows(lv.C2, s, out=T[2])
    # J = grad I . d(u_b, v_b)/d rho with the gradient averaged over both images (eq. 27's symmetric form:
    # second-order accurate in the step, and the interpolation bias of a one-sided gradient halves)
    gx = add(gxb, gxa, dst=gxb)
    gy = add(gyb, gya, dst=gyb)
    J = mul(gx, C1, dst=gx)                                      # T4 J
    cv2.accumulateProduct(gy, C2, J)
    inv2 = mul(inv, inv, dst=T[9])                               # T9 inv2
    mul(J, inv2, dst=J)
    # a quarter of the squared sensitivity |d(u_b, v_b)/d rho|^2 = |C|^2 / den^4 (C1, C2 are halved)
    c2 = lv.c2(s) if lv._cache is not None else cv2.accumulateSquare(C2, mul(C1, C1, dst=C1))   # T1 c2
    # Huber weights min(1, k sigma / |r|) times the in-view mask: ks mask / max(|r|, ks)
    ks = F32(max(prm["huber_k"] * sigma, 1e-6))
    wgt = np.abs(r, out=T[5])                                    # T5 wgt
    np.maximum(wgt, ks, out=wgt)
    cv2.divide(mask, wgt, dst=wgt, scale=float(ks))
    wJ = mul(wgt, J, dst=T[2])                                   # T2 wJ
    q = mul(J, R, dst=T[10])                                     # T10 q
    sub(q, r, dst=q)
    # window sums; everything after them only on the block's own rows o (the halo only feeds the sums)
    H = _box_to(mul(wJ, J, dst=T[11]), win, dst=T[11])[o]       # T11 H
    g = _box_to(mul(wJ, q, dst=T[12]), win, dst=T[12])[o]       # T12 g
    wsum = None
    if prm["bias"]:   # unknown brightness offset per window, eliminated (Schur complement)
        S0 = _box_to(wgt, win, dst=T[13])[o]
        S0 += F32(1e-6)
        S1 = _box_to(wJ, win, dst=wJ)[o]
        Q = _box_to(mul(mul(wgt, q), q), win)[o] if prm["shift_px"] > 0 else None
        Sq = _box_to(mul(wgt, q, dst=q), win, dst=q)[o]
        if Q is not None and H.shape[1] > 2 * prm["shift_px"]:
            _shift_windows(prm["shift_px"], prm["shift_ratio"], H, g, S0, S1, Sq, Q)
        wsum = S0.copy() if fin is not None else None
        S1n = cv2.divide(S1, S0, dst=S0)
        sub(g, mul(Sq, S1n, dst=Sq), dst=g)
        sub(H, mul(S1, S1n, dst=S1), dst=H)
    Ro = R[o]
    i2 = inv2[o]
    E2 = mul(c2[o], mul(i2, i2, dst=i2), dst=i2)                 # T9 E2
    # Levenberg: (H + lam) rho' = g + lam rho, lam = lam_c E2 (den = 0 only where C = 0 and H = 0: OpenCV's
    # division gives 0 there)
    lam_c = float(4.0 * sigma * sigma * prm["lam_k"])
    num = cv2.scaleAdd(mul(E2, Ro, dst=T[14][o]), lam_c, g, dst=g)
    den = cv2.scaleAdd(E2, lam_c, H, dst=T[15][o])
    out = new[y0:y1]
    cv2.divide(num, den, dst=out)
    np.maximum(out, F32(0), out=out)
    if lv.cap is not None and float(lv.cap[0].min()) + float(lv.cap[1][s].min()) < lv.rho_hi:
        np.minimum(out, lv.cap_rows(y0, y1), out=out)               # the den >= den_min cap binds here
    else:
        np.minimum(out, lv.rho_hi, out=out)
    if fin is None:
        io = prm.get("inf_out")
        if io is not None:      # the infinity test, at this level (see _infinity_ambiguous)
            mf = cv2.threshold(mask, 0.999, 1.0, cv2.THRESH_BINARY, dst=T[13])[1]
            io[y0:y1] = _infinity_ambiguous(lv, s, o, mul(r, mf, dst=r), T, win)
        return
    # --- uncertainty and flags of rows [y0, y1), from this (the last) linearisation
    d = sub(out, Ro, dst=T[14][o])                               # T14 d
    mul(d, d, dst=d)
    mul(d, E2, dst=d)
    trunc = d > fin.trunc2
    # in view: 1.0 where mask > 0.999 and inv > 0 (thresholds straight to 0/1 floats)
    mf = cv2.threshold(mask, 0.999, 1.0, cv2.THRESH_BINARY, dst=T[4])[1]             # T4 mf
    if not float(inv.min()) > 0:     # (inv > 0 nearly everywhere: one read-only pass instead of two; NaN: False)
        mul(mf, cv2.threshold(inv, 0.0, 1.0, cv2.THRESH_BINARY, dst=T[13])[1], dst=mf)
    G = mul(gxa, gxa, dst=T[10])                                 # T10 G
    cv2.accumulateSquare(gya, G)
    mul(G, mf, dst=G)
    G3 = _box_to(G, prm["occ_window"])[o]
    G = _box_to(G, win, dst=G)[o]
    mul(r, r, dst=r)
    mul(r, mf, dst=r)
    if fin.inf_test:
        amb = (prm["inf_mask"][y0:y1] != 0) if prm.get("inf_mask") is not None else \
            _infinity_ambiguous(lv, s, o, r, T, win, squared=True)
    R2 = _box_to(r, prm["occ_window"], dst=r)[o]
    std = fin.std[y0:y1]
    with np.errstate(divide="ignore", invalid="ignore"):
        # normal-equation information (Huber-weighted, brightness offset eliminated) of the last linearisation
        # plus a floor of match_floor_px pixels of displacement (interpolation bias, surface slant, ...), times
        # std_scale (folded in squared)
        if fin.noise_info:
            # the part of H that the image noise's own gradients contribute (E[J^2] of noise alone = E2 noise_G
            # per unit weight) is no information about rho: without it a window of faint texture reports a
            # tight sigma around whatever its neighbours suggested
            H = cv2.scaleAdd(mul(E2, wsum) if wsum is not None else E2, -float(fin.noise_G), H)
            np.maximum(H, F32(1e-12), out=H)
        np.divide(fin.var_k, H, out=std)
        std += np.divide(fin.floor2, E2, out=d)
        np.sqrt(std, out=std)
        E2 = mul(E2, G, dst=E2)
        orient = np.divide(H, E2, out=E2)     # share of the gradient energy along the epipolar direction
    # texture the brightness-offset model can use: the windowed variance of the gradient (a brightness ramp,
    # e.g. a smooth sky, has a constant gradient that the per-window offset absorbs entirely)
    Mx = _box_to(mul(gxa, mf), win)[o]
    My = _box_to(mul(gya, mf), win)[o]
    Gc = sub(G, mul(Mx, Mx, dst=Mx))
    sub(Gc, mul(My, My, dst=My), dst=Gc)
    low = Gc < fin.low_thr
    oov = mf[o] == F32(0)
    # occluded: a residual that neither the noise nor a misregistration of occ_px pixels explains
    G3 *= fin.occ_px2
    G3 += fin.occ_thr
    occ = R2 > G3
    oov |= occ
    ill = orient >= fin.orient_min
    np.logical_not(ill, out=ill)
    ill &= ~low
    if fin.inf_test:
        # (a rho within 2 sigma of 0 is AT_INFINITY's business, not an ambiguity)
        amb &= new[y0:y1] > F32(2.0) * std
        ill |= amb
        fin.amb[y0:y1] = amb
    flags = fin.flags[y0:y1]
    np.multiply(oov.view(np.uint8), np.uint8(OUT_OF_VIEW), out=flags)
    flags |= low.view(np.uint8) * np.uint8(LOW_TEXTURE)
    flags |= ill.view(np.uint8) * np.uint8(ILL_CONDITIONED)
    flags |= trunc.view(np.uint8) * np.uint8(TRUNCATION)
    flags |= occ.view(np.uint8) * np.uint8(OCCLUDED)
    nv, ni = classify_into(new[y0:y1], std, flags, fin.rng[y0:y1], fin.conf[y0:y1], rho_far=fin.rho_far,
                           max_rel_std=fin.max_rel_std, work=(T[0][o], T[2][o], T[5][o]))
    fin.n_val += nv
    fin.n_inf += ni



_NO_AMB = np.empty((0, 0), np.uint8)


def _gn_level_fused(K, lv: _Level, rho, new, sigma: float, prm: dict, fin: _Final | None):
    """One Gauss-Newton step of the whole level ``lv`` in one numba pass (``_dense_kernels.gn_level``): the
    arithmetic of _gn_block (map, warp, terms, window sums, update; with ``fin`` the uncertainty, flags and
    classification; the infinity test) with the window sums taken row by row from a ring of window-height term
    planes, so no per-pixel plane is written but the outputs (the level's gradient of a and padded b: _Level)."""
    io = prm.get("inf_out") if fin is None else None
    inf_mode, amb_in = 0, _NO_AMB
    if io is not None:
        inf_mode = 1
    elif fin is not None and fin.inf_test:
        if prm.get("inf_mask") is not None:
            amb_in = prm["inf_mask"]
        else:
            inf_mode = 2      # no level 1: the infinity test at level 0
    ks = F32(max(prm["huber_k"] * sigma, 1e-6))
    lam_c = F32(4.0 * sigma * sigma * prm["lam_k"])
    if fin is None:
        fp, outs = _NO_FP, (_NO_AMB, _NO_F2, _NO_AMB, _NO_F2, _NO_F2, _NO_AMB)
        noise_info = False
    else:
        fp = np.array([fin.noise_G, fin.var_k, fin.floor2, fin.trunc2, fin.low_thr, fin.occ_px2, fin.occ_thr,
                       fin.orient_min, fin.rho_far, fin.max_rel_std], F32)
        outs = (_NO_AMB, fin.std, fin.flags, fin.rng, fin.conf, fin.amb.view(np.uint8))
        noise_info = fin.noise_info
    if io is not None:
        outs = (io,) + outs[1:]
    nv, ni = K.gn_level(lv.b4p, lv.ia, lv.gxa, lv.gya, lv.rw, lv.kc, rho, lv.B0, lv.Q1, lv.Q2, ks, lam_c,
                        lv.cap is not None, lv.rho_hi, int(prm["window"]), int(prm["occ_window"]), prm["shift_px"],
                        prm["shift_ratio"], fin is not None,
                        inf_mode, amb_in, fp, noise_info, new, *outs)
    if fin is not None:
        fin.n_val += nv
        fin.n_inf += ni


_NO_FP = np.zeros(10, F32)
_NO_F2 = np.empty((0, 0), F32)


def prepare_kernels() -> bool:
    """Compile (or load from numba's cache) the fused kernels now, for the argument types locate_dense passes them,
    instead of in the first locate: ~15-25 s cold (once per install), ~2 s from the cache on the bench machine, which a
    service should spend before its first frame (a first pair delayed by it went stale). False without numba."""
    K = optional_kernels("_dense_kernels")
    if K is None:
        return False
    # every kernel of a locate, with the argument types it passes them: two small simulated pairs, without a
    # level 1 (the infinity test at level 0) and with one (its verdict carried down to level 0)
    from eonav.sim.presets import make_pair
    for size in (96, 160):
        locate_dense(*make_pair("turning", size=size, supersample=1).views)
    # the fill's passes: a 64 x 64 plane with a hole, with and without an exclusion mask
    rho = np.full((64, 64), 0.05, F32)
    for ex in (None, np.zeros((64, 64), bool)):
        flags = np.full((64, 64), VALID, np.uint8)
        flags[20:30, 20:30] = LOW_TEXTURE
        fill_unmeasured(rho.copy(), np.full((64, 64), 1e-3, F32), flags, np.zeros_like(rho), np.zeros_like(rho), 0.34,
                        exclude=ex)
    return True


__all__ = ["locate_dense", "prepare_kernels"]
