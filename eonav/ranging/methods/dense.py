"""The default range estimator "dense": a direct inverse-range method (brightness constancy and known motion).

With the relative pose known, every pixel of image a can only move along its epipolar curve in image b, which is
parameterised exactly by its inverse range rho = 1/x_c (the paper's eqs. 25-26, ``_common.EpipolarMap``).
Brightness constancy I_b(map(rho)) = I_a is then one equation in one unknown per pixel; its first-order
expansion (eq. 27, multiplied through by the denominator of eqs. 25-26) is linear in rho. ``locate_dense`` runs
the method in four stages (docs/methods.md describes it):

1. search: at a coarse pyramid level, where the first-order model breaks (disparities of many pixels), a 1-D
   search over inverse-range hypotheses along each pixel's epipolar curve, uniform in the pixel's own
   displacement (windowed ZNCC, winner-take-all, parabola sub-sample fit), then a 3 x 3 median and a
   normalised-convolution fill of the weak matches: the seed of the refinement. No 2-D flow search anywhere;
2. refine per level, coarse to fine: re-linearised Gauss-Newton steps. Each warps b at the current rho, so that
   the Taylor remainder (eq. 7) stays small, and solves the windowed, Huber-weighted normal equations of
   r + J (rho' - rho) = 0 with r = I_b(map(rho)) - I_a and J = grad I . d(u_b, v_b)/d rho (the gradient
   averaged over I_a and the warped I_b: eq. 27's symmetric form), a brightness offset per window eliminated,
   shiftable windows at the coarse levels and a Levenberg trust term worth ``trust_px`` pixels of displacement;
3. classify, in level 0's last step: per-pixel 1-sigma of rho from the normal equations and the noise (robust MAD
   of the residual; then each window's own residual, ``_apply_model_error``), confidence rho / sigma, and the flags OUT_OF_VIEW (the map leaves b or lies behind it;
   OCCLUDED: a windowed residual neither the noise nor a small misregistration explains), LOW_TEXTURE,
   ILL_CONDITIONED (focus of expansion, gradient across the epipolar direction, relative sigma above
   ``max_rel_std``, or a point at infinity explains the window as well), TRUNCATION (the last step still moved by
   more than ``trunc_px``) and AT_INFINITY (rho within 2 sigma of 0 with a tight sigma: range +inf); one rho per
   window is then moved from the window's effective centre to the pixel (``_model_error``);
4. fill: the pixels without a measurement get an inverse range from plane fits of the measured ones around them
   (``fill.fill_unmeasured``), flagged FILLED.

With a prior (``prior``: a fused state predicted into image a) stage 1 and the coarse levels can be skipped where it
is converged, the refinement starting from it (``_prior_start``, ``_prior_finish``).

The per-pixel work runs in numba kernels (``_dense_kernels``): one pass per Gauss-Newton step of a level, three
kernels for the search. They are the only implementation (numba is a dependency of eonav; importing this module
without it fails, naming numba); tests/dense_reference.py holds an independent OpenCV formulation of the same
arithmetic, which the tests check the kernels against. Large per-level buffers are per-thread work buffers
reused from call to call (``_ws``).
"""
from __future__ import annotations

import math
import threading
import time
from dataclasses import dataclass, replace
from functools import lru_cache, partial

import cv2
import numpy as np

from eonav import InputError
from eonav.geometry.camera import Camera, VehicleState, View, pair_geometry
from eonav.ranging.methods._common import (F32, EpipolarMap, far_inverse_range, make_result, no_motion_result,
                                           numba_kernels, pyr_up_to, pyramid)
from eonav.ranging.methods.fill import fill_unmeasured
from eonav.ranging.rangemap import AT_INFINITY, ILL_CONDITIONED, OCCLUDED, VALID, RangeResult

_K = numba_kernels("_dense_kernels")

METHOD = "dense"
_BR = cv2.BORDER_REFLECT


def _blur(img: np.ndarray, sigma: float, dst: np.ndarray | None = None) -> np.ndarray:
    k = 2 * int(math.ceil(2.5 * sigma)) + 1
    return cv2.GaussianBlur(img, (k, k), sigma, dst=dst, borderType=_BR)


_TLS = threading.local()


def _ws(key, shape, dtype=F32, fill=None) -> np.ndarray:
    """A per-thread work buffer, reused from call to call (never part of a result): large fresh arrays cost a page
    fault per 4 KiB page on every call (the allocator returns them to the OS). ``fill``: constant contents, written
    once."""
    d = getattr(_TLS, "bufs", None)
    if d is None or len(d) > 128:      # bounded: a stream of ever-new image sizes cannot grow it without end
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


def _box(img: np.ndarray, win: int, dst: np.ndarray | None = None) -> np.ndarray:
    """Mean over a win x win window (reflected border), into ``dst`` if given. A separable direct filter: for the
    small windows used here OpenCV's SIMD sepFilter2D is faster than its running-sum boxFilter."""
    k = _box_kernel(win)
    return cv2.sepFilter2D(img, -1, k, k, dst=dst, borderType=_BR)


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



@lru_cache(maxsize=8)
def _pad_rows(h: int, p: int) -> np.ndarray:
    """Source row of each of the h + 2p rows of an image padded by p rows as np.pad "symmetric" (np.pad: 0.1 ms)."""
    return np.pad(np.arange(h), (p, p), mode="symmetric")     # (shared: never written)


def _a_side(a: np.ndarray, win: int):
    """Image a padded by half a window of symmetric rows (as np.pad "symmetric"), its windowed mean and variance,
    and the variance clipped at 0: the search's a-side statistics."""
    ap = a[_pad_rows(a.shape[0], win // 2)]
    ma = _box(ap, win)
    va = _box(ap * ap, win) - ma * ma
    return ap, ma, va, np.maximum(va, 0)


def _search(a: np.ndarray, b: np.ndarray, emap: EpipolarMap, rhos: np.ndarray, win: int, noise: float,
            sgm_p1: float = 0.0, sgm_p2: float = 0.0, sgm_tau: float = 0.0, chunk_px: int = 32768,
            disp=None, cap=None):
    """Windowed ZNCC along the epipolar curve for every hypothesis (rhos; with ``disp``, hypotheses uniform in each
    pixel's own displacement: rho per pixel by ``_rho_at_disp``, at most ``cap``), optional semi-global aggregation
    (sgm_p2 > 0), winner-take-all with a parabola sub-sample fit. Returns rho (h x w) and the confidence of the
    winner: correlation (>= 0) squared times texture (windowed variance against the noise).

    Per chunk of ~chunk_px pixels of hypotheses (the rows of a padded by half a window of symmetric rows, so the
    box sums do not mix hypotheses): one kernel pass for the rho, the map, the in-view test and b sampled there (as
    cv2.remap INTER_LINEAR would) with the products the box sums need, OpenCV's box sums, one pass for the cost;
    then one pass for the winner-take-all, the rho and the confidence (``_dense_kernels.search_*``)."""
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
        _K.search_warp(hyp[k0:k1], per_pixel, rows, emap.A0, emap.A1, emap.A2, cn, capf, fx, cx, fy, cy, B0, Q1, Q2,
                       a, b, bw, bw2, bwa, good)
        for t in (bw, bw2, bwa):
            _box(t, win, dst=t)
        _K.search_cost(bw, bw2, bwa, good, ma, va_pos, noise4, p, cost[k0:k1])
    agg = np.ascontiguousarray(_sgm(cost, a, sgm_p1, sgm_p2, sgm_tau)) if sgm_p2 > 0 else cost
    rho = np.empty((h, w), F32)
    conf = np.empty((h, w), F32)
    _K.search_wta(agg, cost, hyp, per_pixel, emap.A0, cn, B0, capf, va[p:p + h], F32(noise * noise), rho, conf)
    return rho, conf


class _Level:
    """One pyramid level's constants for the Gauss-Newton steps: image a (ia) with its Scharr gradient (gxa, gya),
    image b (ib) as the warp source b4p ([I, gx, gy, 1] per pixel with a border of one zero pixel), and the
    epipolar map with the intrinsics folded in.

    Every map is affine in the pixel's normalised coordinates m = [1, m1, m2] of camera a (A = R m):
    den = A0 + B0 rho, u_b = (P1 + Q1 rho) / den, v_b = (P2 + Q2 rho) / den, d(u_b, v_b)/d rho = (C1, C2) / den^2
    (see _common.EpipolarMap). Each is stored as a row part rw (c0 + c1 m1, per column) and a column part kc
    (c2 m2, per row) that the kernels add per pixel; rows: A0, P1, P2, C1 / 2, C2 / 2 (the 1/2 of the averaged
    gradient folded in) and, when b moves towards the scene (B0 < 0, ``use_cap``), the largest rho keeping
    den >= den_min."""

    def __init__(self, geo, lev, ia, ib, rho_hi, den_min: float = 0.05):
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
        cs = [a0, fxb * a1 + cxb * a0, fyb * a2 + cyb * a0, 0.5 * fxb * (t[1] * a0 - t[0] * a1),
              0.5 * fyb * (t[2] * a0 - t[0] * a2)]
        self.use_cap = bool(t[0] < 0)
        if self.use_cap:
            cs.append(np.array([a0[0] - den_min, a0[1], a0[2]]) / -t[0])
        coef = np.array(cs)
        self.rw = (coef[:, :1] + coef[:, 1:2] * m1[None, :]).astype(F32)
        self.kc = (coef[:, 2:3] * m2[None, :]).astype(F32)
        self.ia, self.ib = ia, ib
        self.B0 = F32(t[0])
        self.Q1 = F32(fxb * t[1] + cxb * t[0])
        self.Q2 = F32(fyb * t[2] + cyb * t[0])
        self.rho_hi = F32(rho_hi)
        self.gxa, self.gya = _ws("gxa", ia.shape), _ws("gya", ia.shape)
        _K.scharr(ia, self.gxa, self.gya)
        hb, wb = ib.shape
        self.b4p = _ws("b4p", (hb + 2, wb + 2, 4))
        _K.pack_b4p(ib, self.b4p)


def _residual_noise(lv: _Level, rho, final: bool = True, step: int = 3):
    """Robust noise of the residual I_b(map(rho)) - I_a on every ``step``-th row and column: over all pixels (the
    Huber scale) and over the fully in-view ones (the classification's noise; None unless ``final``)."""
    g = (-(-lv.h // step), -(-lv.w // step))
    r, inview = _ws("noise_r", g), _ws("noise_in", g, np.uint8)
    _K.residual_grid(lv.b4p, lv.ia, lv.rw, lv.kc, rho, lv.B0, lv.Q1, lv.Q2, step, r, inview)
    return _robust_sigma(r, step=1), (_robust_sigma(r, inview.view(bool), step=1) if final else None)


def locate_dense(view_a: View, view_b: View, *, max_disp_px: float | None = None, min_range_m: float | None = None,
                 search_level: int | None = None, search_step_px: float = 1.0, search_window: int = 5,
                 median: bool = True, iters=(3, 2, 2, 1), window: int = 7, huber_k: float = 2.0,
                 trust_px: float = 1.0, presmooth_sigma: float = 0.6, max_rel_std: float = 0.34,
                 far_parallax_px: float = 0.5, tex_k: float = 1.0, orient_min: float = 0.02,
                 occ_k: float = 3.0, occ_window: int = 3, occ_px: float = 0.25, trunc_px: float = 1.0,
                 std_scale: float | None = None, shift_px: int = 2, shift_ratio: float = 0.4,
                 fill_sigma: float = 4.0, fill_c: float = 0.3, highpass_sigma: float = 0.0,
                 highpass_levels: int = 9, bias: bool = True,
                 match_floor_px: float = 0.05, sgm: bool = False,
                 tex_noise: str = "image", noise_info: bool = True, per_pixel_search: bool = True,
                 inf_test: bool = True, fill: bool = True,
                 sgm_p1: float = 1.0, sgm_p2: float = 8.0, sgm_tau: float = 8.0,
                 prior=None, prior_level: int = 1, prior_k: float = 3.0, prior_reach_px: float = 1.0,
                 prior_min_fraction: float = 0.5, prior_max_bad: float = 0.1, slant: bool = False,
                 slant_curv: float = 0.05, window_noise: bool = True, centroid: bool = True,
                 window_floor: str = "global", match_blur: bool = False, aperture_px: float = 0.0) -> RangeResult:
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
    window: box window (level pixels, odd) of the normal equations.
    slant / slant_curv: the slanted window (``_slant_shape``) at levels 1 and 0: the window of centre c models
    rho_j = rho_c + A_c (S_j - S_c), S a box mean of the current estimate, instead of one rho for all its pixels,
    which measures rho at the texture-weighted centre of the window, not at the pixel, wherever rho varies across
    it (ground at grazing angles, slanted walls): an error tied to the texture, the same in every pair, that
    temporal fusion cannot average. A_c = 1 where rho is flat or planar about c (its relative gradient or its
    relative second difference, both per pixel, within slant_curv) and 0 from twice that on: a depth edge (a
    jump) keeps one rho per window, a steep but smooth surface (ground near the horizon) keeps the slant. Off by
    default: it lowers the sim flights' errors (fused and single-pair), but the real sequences gain nothing and,
    with its calibrated sigma, the obstacle list found about twice the false obstacles on far ground (with the
    window's own residual in the sigma, ``window_noise``, 1.4 x one rho per window's: docs/methods.md). Figures in
    docs/methods.md. huber_k: Huber threshold in noise
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
    do not support that range. Both residuals are summed over the window's pixels that both warps keep in view of b;
    where none is (near a border of image a, the warp at infinity leaves b), infinity is not ruled out. Judged at level 1's last iteration and carried to level 0 (a quarter of the work;
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
    std_scale: calibration factor of the reported sigma, from the measured robust spread of (rho - rho_true) / sigma
    (the window's samples are correlated by the pre-smoothing and the interpolation): None (default) takes the one
    for the window model, 1.35 with one rho per window (at the global window floor the Middlebury pairs' spread is
    then 0.98 and the sim presets' 0.83: real images do not under-report; at the "valid" floor 1.05 and 0.95), 1.25
    with the slanted window (measured on the sim presets with the sensor floor; docs/methods.md "The sigma across
    range"). max_rel_std (0.34) was set as 0.25 x 1.35 and kept: the VALID rule is on the calibrated sigma.
    window_noise: each VALID pixel's sigma from its own window's residual (noise plus the window model's misfit)
    where that exceeds the floor, instead of the image's noise alone (``_apply_model_error``): the image-wide figure
    under-reports the sigma of far ground near the horizon and of edges, where the window's model does not hold.
    window_floor: the floor of the window's residual variance (``_window_floor2``). "global" (default), the image's
    final residual noise over every pixel in view: the window term only raises the sigma above the image-wide model's,
    where its window misfits. "valid" takes that figure over the VALID pixels alone: on the sim flights 47-57 % of the
    pixels in view are ones the method rejects (sky, occlusions), whose residual raises the "global" figure 1.5 x and
    makes the near ground's sigma over-report (pair z 0.61-0.67 there; 0.87-0.94 with "valid"); not the default, since
    on the real HoloLens sequence, whose pairs' sigma under-reports, the fused z at frame 10 went 1.18 -> 1.37 and the
    obstacle list found one more false track per seed (docs/methods.md "The sigma across range"). "sensor" (the
    sensor noise alone) also lowers it where a window fits better than the image-wide figure (near sim ground): even
    sim bins, but on real images the window's residual misses part of the error and Middlebury teddy / cones,
    HoloLens under-reported (z 1.49 / 1.31 / 1.74 against 0.95 / 0.61 / 1.18); "mid", the geometric mean of
    "sensor" and "global", lies between.
    centroid: with window_noise and one rho per window, each VALID rho moved from the window's effective centre
    (the texture-weighted centroid the normal equations measure) back to the pixel along rho's slope, where rho is
    planar about the pixel (the slanted window's gate); elsewhere that bias goes into the sigma (``_model_error``).
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
    match_blur: at level 0, image a blurred per pixel as much as image b is in a's pixels (``_match_blur``): b's
    texture reaches the match through b's own pixels and pre-smoothing, scaled by the map's local magnification,
    and through the bilinear interpolation of the warp, a's through neither. Brightness constancy then fails by a
    blur difference tied to the texture, the same in every pair of a forward flight (b farther, its texture
    smaller), which fusion cannot average. Only a is blurred (b finer than a, a camera moving away, is left as it
    was). Off by default: it lowers the fused maps' error on every sequence (docs/methods.md, "The resolution
    match"), but their sigma, not recalibrated for it, then over-reports more (the held-out flight of
    tests/test_fusion.py: z spread 0.86 -> 0.72), and the fused map's slant term that would restore it leaves far
    ground's sigma too tight.
    aperture_px: the 1-sigma misregistration of image b ACROSS the epipolar direction (pixels at level 0) that the
    sigma allows for (``_apply_aperture``): a pose error moves b's epipolar line sideways, and a window whose
    gradients lie mostly across the epipolar direction (a straight edge within a few degrees of it) turns such a
    shift into a disparity error of up to shift / tan(angle). 0 (default): off. Off by default because the exact-pose
    sim presets pay for it (0.1 px: coverage of the approach pair's VALID pixels 80.3 -> 76.7 %, z spread of the sim
    presets 0.71-0.99 -> 0.57-0.94, i.e. more over-reported; 0.05 px: -1.0 point, 0.66-0.98) and the false track it was
    built for (the runway's edge on approach-clear) is not a line-position error (docs/methods.md, "Known limits").
    For a pose whose error is known, e.g. the pair checks' ``pose_shift_px``, pass that.
    fill: pixels without a measurement (low texture, ill-conditioned, out of view of b; not occluded or truncated)
    get an inverse range inferred from the measured ones around them (``eonav.ranging.methods.fill``: plane fits in
    windows growing by octaves, sigma from the fit and its disagreement across scales), flagged FILLED (not VALID),
    where that sigma is within max_rel_std like any VALID pixel's. Sim presets: coverage of the non-sky pixels
    63-79 % -> 73-91 %, median error 0.34-0.80 % -> 0.37-0.83 %; the filled pixels' z spread 0.6-0.8 (their
    own median error 0.3-2 %); Middlebury coverage 65-80 % -> 81-87 %, medians within +0.1 pp.
    (Not to be confused with fill_sigma / fill_c: the coarse search's normalised-convolution fill, which only
    seeds the Gauss-Newton steps.)
    bias: a brightness offset per window, eliminated from the normal equations. The kernels always eliminate it;
    False turns the shiftable windows off (they choose by the offset model's cost), nothing else.
    sgm: semi-global aggregation (4 scanline paths) of the coarse ZNCC cost volume before winner-take-all;
    sgm_p1 / sgm_p2: penalties (cost units, 1 - ZNCC) of a one-hypothesis / larger jump between neighbours,
    sgm_tau: grey levels over which the jump penalty halves across an intensity edge. Off by default:
    measured on Middlebury it lowers the raw all-pixel median error (teddy 0.94 -> 0.83 %, venus 1.51 ->
    1.41 %, share of pixels off by > 5 %: teddy 22.5 -> 17.2 %, venus 25.6 -> 19.8 %), but on the paper
    preset it pulls the small far vehicles into their background at the coarse level (vehicle2 +2.7 ->
    +8.8 %, vehicle1 -0.0 -> -1.3 %), whatever the penalties (0.2/2 .. 1/8, tau 1 .. 8).
    prior: (rho, sigma) on view a's grid (NaN / inf: none), e.g. a fused state predicted into view a (REMODE and SVO
    search only mu +- 2-3 sigma of a converged depth filter). Where its prior_k-sigma interval spans at most
    prior_reach_px pixels of displacement at level prior_level (``_prior_ok``: the Gauss-Newton steps' reach), the
    refinement starts there from the prior, and the search and the coarser levels are skipped, when that holds at
    least prior_min_fraction of the level's pixels (else the search as usual). The pixels it does not seed are not
    measured (rho NaN, sigma inf, not VALID: a prior never stands in for a measurement); where more than
    prior_max_bad of the seeded pixels fit badly (OCCLUDED: the prior is wrong there, or the scene moved) the whole
    pair is searched again without the prior. ``info["prior"]``: seeded_fraction, bad_fraction, level, full_search.
    """
    call = dict(locals())                  # (the full search again, when the prior fits badly)
    t_start = time.perf_counter()
    geo = pair_geometry(view_a, view_b)
    ha, wa = view_a.image.shape
    if geo.baseline_m <= 1e-12:
        return no_motion_result((ha, wa), METHOD, "zero baseline")
    L = _default_search_level(view_a.image.shape, view_b.image.shape) if search_level is None else search_level
    if window_floor not in ("sensor", "global", "mid", "valid"):
        raise InputError(f"window_floor {window_floor!r}: expected 'sensor', 'global', 'mid' or 'valid'")
    if std_scale is None:
        std_scale = 1.25 if slant else 1.35
    if not (math.isfinite(slant_curv) and slant_curv > 0):
        raise InputError(f"slant_curv must be a finite relative second difference > 0 (per pixel), got {slant_curv!r}")
    if tex_noise not in ("image", "residual"):
        raise InputError(f"tex_noise must be 'image' or 'residual', got {tex_noise!r}")
    img_sigma = image_noise_sigma(view_a.image) if tex_noise == "image" else None
    pa = _pyramid(view_a.image, "pre_a", L + 1, presmooth_sigma, highpass_sigma, highpass_levels)
    pb = _pyramid(view_b.image, "pre_b", L + 1, presmooth_sigma, highpass_sigma, highpass_levels)

    # 1. search along the epipolar curves at level L, and the seed of the refinement -- or, with a prior that
    # holds most of the image, the prior itself as the seed of a finer level (``_prior_start``)
    start, first_lv, ok_lev = L, None, None
    if prior is not None:
        fast = _prior_start(geo, pa, pb, L, (ha, wa), prior, max_disp_px, min_range_m, per_pixel_search,
                            search_step_px, prior_level, prior_k, prior_reach_px, prior_min_fraction, fill_sigma)
        if fast is not None:
            start, first_lv, rho, ok_lev, rho_max, n_hyp = fast
    if first_lv is None:
        found = _search_epipolar(geo, pa[L], pb[L], L, (ha, wa), max_disp_px, min_range_m, per_pixel_search,
                                 search_step_px, search_window, sgm_p1, sgm_p2 if sgm else 0.0, sgm_tau)
        if found is None:
            return no_motion_result((ha, wa), METHOD, "no parallax at any range")
        rho, conf, rho_max, n_hyp = found
        rho = _seed(rho, conf, median, fill_sigma, fill_c)

    # 2. refine per level, coarse to fine; 3. classify in level 0's last step
    steps = _Steps(window=window, occ_window=min(int(occ_window), window), huber_k=huber_k,
                   lam_k=1.0 / (window * window * trust_px * trust_px), shift_ratio=F32(shift_ratio))
    g0, gG = _noise_gains(float(presmooth_sigma))
    rules = dict(img_sigma=img_sigma, g0=g0, gG=gG, window=window, tex_k=tex_k,
                 occ_k=occ_k, occ_px=occ_px, trunc_px=trunc_px, match_floor_px=match_floor_px, noise_info=noise_info,
                 inf_test=inf_test, std_scale=std_scale, orient_min=orient_min,
                 rho_far=far_inverse_range(geo, far_parallax_px), max_rel_std=max_rel_std)
    iters = _iterations(iters, L + 1)
    # the infinity test runs at level 1's last step (a quarter of the pixels; the ambiguous regions are blobs of tens
    # of pixels) and its verdict is carried to level 0; at level 0 itself when there is no level 1
    inf_at_level1 = inf_test and L >= 1 and iters[L - 1] >= 1
    inf_mask = None
    rho_hi = F32(rho_max * 1.25)
    for lev in range(start, -1, -1):
        rho = _to_level(rho, pa[lev].shape)
        n_it = max(iters[L - lev], 1 if lev == 0 else 0)
        if n_it == 0:
            continue
        if lev == start and first_lv is not None:
            lv = first_lv
        else:
            ia = _match_blur(geo, pa[0], rho, presmooth_sigma) if match_blur and lev == 0 else pa[lev]
            lv = _Level(geo, lev, ia, pb[lev], rho_hi)
        # shiftable windows at the coarser levels, where a pixel's estimate settles on one surface or the other;
        # level 0 refines within a pixel, and its sigma and flags are those of the pixel's own (centred) window
        shift = int(shift_px) if bias and lev >= 1 else 0
        # the slanted window at levels 1 and 0 (at the coarser ones it changed nothing the finer ones keep)
        steps_l = replace(steps, slant_curv=float(slant_curv) if slant and lev <= 1 else 0.0)
        if lev > 0:
            rho, amb = _refine_level(lv, rho, n_it, steps_l, shift, infinity_test=inf_at_level1 and lev == 1)
            if amb is not None:
                inf_mask = cv2.resize(amb, (wa, ha), interpolation=cv2.INTER_NEAREST)
        else:
            rho, fin = _refine_level(lv, rho, n_it, steps_l, shift, rules=rules, inf_mask=inf_mask)
            if window_noise:
                floor2 = partial(_window_floor2, window_floor, g0, img_sigma, fin.sigma)
                _apply_model_error(lv, rho, fin, window, floor2, centroid and not slant, max_rel_std, slant_curv)
            if aperture_px > 0:
                _apply_aperture(lv, rho, fin, window, F32(std_scale * aperture_px), max_rel_std)

    prior_info = None
    if first_lv is not None:
        # the pixels the prior did not seed are not measured; too many bad fits where it did: the full search
        prior_info = _prior_finish(prior, ok_lev, start, rho, fin)
        if prior_info["bad_fraction"] > prior_max_bad:
            res = locate_dense(**dict(call, prior=None))
            res.info["prior"] = dict(prior_info, full_search=True)
            return res
    # 4. fill the pixels without a measurement
    n_filled = fill_unmeasured(rho, fin.std, fin.flags, fin.rng, fin.conf, max_rel_std, rho_far=fin.rho_far,
                               exclude=fin.amb) if fill else 0
    info = {"seconds": time.perf_counter() - t_start, "noise_sigma": fin.sigma, "noise_sigma_valid": fin.sigma_valid,
            "rho_max_per_m": rho_max,
            "n_hypotheses": n_hyp, "search_level": L, "baseline_m": geo.baseline_m,
            "filled_fraction": n_filled / max(rho.size, 1)}
    if prior is not None:
        info["prior"] = prior_info if prior_info is not None else {"seeded_fraction": 0.0, "full_search": True}
    return make_result(rho, fin.std, fin.flags, fin.rng, fin.conf, METHOD, fin.n_val, fin.n_inf, info)


def _prior_ok(lv: _Level, rho, std, k: float, reach_px: float) -> tuple:
    """Where a prior (rho, its sigma; on lv's grid) can seed lv's refinement: finite, in front of camera b, and its
    k-sigma interval no longer than ``reach_px`` level pixels of displacement along the epipolar curve (|d map /
    d rho| = |C| / den^2, the rows of ``_Level``): within the Gauss-Newton steps' reach, so that the steps, not the
    prior, decide the match. Returns (uint8 mask, count) (``_dense_kernels.prior_gate``)."""
    ok = np.empty(rho.shape, np.uint8)
    return ok, _K.prior_gate(lv.rw, lv.kc, lv.B0, rho, std, F32(k), F32(reach_px), ok)


def _prior_start(geo, pa, pb, L: int, shape0, prior, max_disp_px, min_range_m, per_pixel_search: bool,
                 search_step_px: float, prior_level: int, prior_k: float, reach_px: float, min_fraction: float,
                 fill_sigma: float):
    """The refinement's start from a prior instead of the search: (level, its _Level, seed, seeded mask, largest rho
    of the search range, 0 hypotheses), or None (the search as usual) when the prior seeds less than min_fraction
    of the level's pixels. The seed is the prior where ``_prior_ok``, elsewhere the seeded pixels around it
    (normalised convolution; those pixels are not measured, ``_prior_finish``)."""
    rho_p, std_p = (np.asarray(x, F32) for x in prior)
    if rho_p.shape != tuple(shape0) or std_p.shape != tuple(shape0):
        raise InputError(f"dense prior: (rho, sigma) must both be on image a's grid {tuple(shape0)}, "
                         f"got {rho_p.shape} and {std_p.shape}")
    lev = max(0, min(int(prior_level), L))
    if not per_pixel_search:
        return None
    em, sub, md = _search_scale(geo, L, pa[L].shape, pb[L].shape, shape0, max_disp_px)
    rng = _per_pixel_range(geo, em, sub, md, min_range_m, search_step_px)
    if rng is None:
        return None
    rho_max = rng[2]
    lv = _Level(geo, lev, pa[lev], pb[lev], F32(rho_max * 1.25))
    s = 2 ** lev                        # (pyrDown alignment: level pixel i is level-0 pixel s i)
    r, sd = np.ascontiguousarray(rho_p[::s, ::s]), np.ascontiguousarray(std_p[::s, ::s])
    ok, n = _prior_ok(lv, r, sd, prior_k, reach_px)
    if n < min_fraction * ok.size or n == 0:
        return None
    okb = ok.view(bool)
    seed = np.where(okb, r, F32(0)).astype(F32)
    if n < ok.size:
        wsum = _blur(ok.astype(F32), fill_sigma)
        nc = _blur(seed, fill_sigma) / np.maximum(wsum, F32(1e-6))
        seed = np.where(okb, seed, nc).astype(F32)
    return lev, lv, np.ascontiguousarray(seed), ok, rho_max, 0


_PRIOR_BAD = np.uint8(OCCLUDED)


def _prior_finish(prior, ok_lev, lev: int, rho, fin) -> dict:
    """After a refinement started from the prior at level ``lev``: the pixels it did not seed made unmeasured (rho
    NaN, sigma inf, VALID / AT_INFINITY cleared), in place (``_dense_kernels.prior_unmeasure``); returns the seeded
    fraction and the fraction of seeded pixels whose final fit is bad (OCCLUDED, ``_PRIOR_BAD``: the prior was
    wrong there, or the scene moved)."""
    rho_p = np.ascontiguousarray(prior[0], F32)
    n_ok, bad, d_val, d_inf = _K.prior_unmeasure(ok_lev, 2 ** lev, rho_p, _PRIOR_BAD, rho, fin.std, fin.flags,
                                                 fin.rng, fin.conf)
    fin.n_val -= d_val
    fin.n_inf -= d_inf
    return {"seeded_fraction": n_ok / max(rho.size, 1), "bad_fraction": bad / max(n_ok, 1), "level": lev,
            "full_search": False}


def _default_search_level(shape_a, shape_b) -> int:
    """The coarsest pyramid level whose geometric-mean size is >= 64 px, at most 3: the search's resolution follows
    the image's area, not its short side (640 x 480 searches at 80 x 60 like 512 x 512 at 64 x 64)."""
    m = math.sqrt(min(shape_a[0] * shape_a[1], shape_b[0] * shape_b[1]))
    return int(max(0, min(3, math.floor(math.log2(m / 64.0)))))


def _pyramid(img: np.ndarray, key: str, n_levels: int, presmooth_sigma: float, highpass_sigma: float,
             highpass_levels: int) -> list:
    """The image pre-smoothed (into work buffer ``key``) and its Gaussian pyramid; with highpass_sigma, local
    brightness offsets (illumination, vignetting, exposure) removed from its first highpass_levels levels. Every
    level C-contiguous (the kernels are compiled for that layout)."""
    img = np.ascontiguousarray(img)
    if presmooth_sigma > 0:
        img = _blur(img, presmooth_sigma, dst=_ws(key, img.shape))
    pyr = pyramid(img, n_levels)
    if highpass_sigma > 0:
        pyr = [x - _blur(x, highpass_sigma) if i < highpass_levels else x for i, x in enumerate(pyr)]
    return pyr


# the blur a camera's pixel adds to its image (a box of one pixel: variance 1/12 per axis) and the bilinear
# interpolation of the warp to image b (at fraction f the kernel (1 - f, f), variance f (1 - f); 1/6 on average)
_PIXEL_VAR = 1.0 / 12.0
_BILINEAR_VAR = 1.0 / 6.0
_BLUR_LADDER = (0.0, 0.25, 0.5, 1.0, 2.0)   # variances (level-0 px^2) of the blurred copies of a, interpolated between


def _magnification(geo, rho, step: int = 1) -> np.ndarray:
    """The map a -> b's local linear magnification, sqrt |det d(u_b, v_b) / d(u_a, v_a)| (central differences,
    one-sided at the borders), on every ``step``-th pixel of a (rows and columns) at the surface rho (its 3 x 3
    mean; NaN taken as 0): below 1 where b sees the surface smaller (a farther view). The map is eqs. (25)-(26) as ``PairGeometry.map_to_b``,
    X_b / x_c = R_ba m + t rho, m = [1, (u - cx) / fx, (v - cy) / fy], on the sub-grid only."""
    r = cv2.blur(np.nan_to_num(np.asarray(rho, F32), nan=0.0, posinf=0.0, neginf=0.0), (3, 3), borderType=_BR)
    r = np.ascontiguousarray(r[::step, ::step])
    ca, cb = geo.cam_a, geo.cam_b
    m1 = ((np.arange(0, r.shape[1] * step, step) - ca.cx) / ca.fx).astype(F32)[None, :]
    m2 = ((np.arange(0, r.shape[0] * step, step) - ca.cy) / ca.fy).astype(F32)[:, None]
    R = np.asarray(geo.R_ba, F32)
    t = np.asarray(geo.t_ba_m, F32)
    with np.errstate(divide="ignore", invalid="ignore"):
        inv = F32(1.0) / (R[0, 0] + R[0, 1] * m1 + R[0, 2] * m2 + t[0] * r)
        ub = F32(cb.fx) * (R[1, 0] + R[1, 1] * m1 + R[1, 2] * m2 + t[1] * r) * inv
        vb = F32(cb.fy) * (R[2, 0] + R[2, 1] * m1 + R[2, 2] * m2 + t[2] * r) * inv
    (uy, ux), (vy, vx) = np.gradient(ub), np.gradient(vb)           # one-sided at the borders
    return np.sqrt(np.abs(ux * vy - uy * vx)) / F32(step)


def _match_blur(geo, ia: np.ndarray, rho, presmooth_sigma: float) -> np.ndarray:
    """Level 0's image a blurred so that its texture reaches the match as blurred as b's (``locate_dense``,
    match_blur). In b's pixels b carries its pixel's box, the pre-smoothing and the warp's bilinear interpolation,
    s_b^2 = 1/12 + presmooth^2 + 1/6; a surface b sees with magnification m (``_magnification``, at the current
    rho) has that blur s_b^2 / m^2 in a's pixels, where a carries s_a^2 = 1/12 + presmooth^2 (variances of
    convolved kernels add). a gets the difference, max(s_b^2 / m^2 - s_a^2, 0), per pixel, as the linear
    interpolation in variance between the two nearest of a few Gaussian blurs of a (``_BLUR_LADDER``; beyond its
    last, the last). The magnification is taken on every other pixel and resized (it varies over tens of pixels
    except at depth edges)."""
    s_a2 = _PIXEL_VAR + float(presmooth_sigma) ** 2
    m2 = np.square(_magnification(geo, rho, step=2))
    need = np.clip(F32(s_a2 + _BILINEAR_VAR) / np.maximum(m2, F32(1e-6)) - F32(s_a2), 0.0, _BLUR_LADDER[-1])
    need = cv2.resize(need, (ia.shape[1], ia.shape[0]), interpolation=cv2.INTER_LINEAR)
    top = float(need.max())
    n = next((j + 1 for j, vj in enumerate(_BLUR_LADDER) if vj >= top), len(_BLUR_LADDER))
    rungs = np.empty((n,) + ia.shape, F32)
    rungs[0] = ia
    for j in range(1, n):
        _blur(ia, math.sqrt(_BLUR_LADDER[j]), dst=rungs[j])
    out = np.empty(ia.shape, F32)
    _K.blend_ladder(need, rungs, np.asarray(_BLUR_LADDER[:n], F32), out)
    return out


def _search_epipolar(geo, a, b, L: int, shape0, max_disp_px, min_range_m, per_pixel_search: bool,
                     search_step_px: float, search_window: int, sgm_p1: float, sgm_p2: float, sgm_tau: float):
    """Stage 1: the search at level L (images a, b) over displacements up to max_disp_px (level-0 pixels; default
    0.3 x the larger side of shape0). Returns (rho, confidence, largest rho searched, number of hypotheses), or
    None when no range gives parallax."""
    em, sub, md = _search_scale(geo, L, a.shape, b.shape, shape0, max_disp_px)
    sgm_kw = dict(sgm_p1=sgm_p1, sgm_p2=sgm_p2, sgm_tau=sgm_tau)
    if per_pixel_search:
        rng = _per_pixel_range(geo, em, sub, md, min_range_m, search_step_px)
        if rng is None:
            return None
        disp, cap, rho_max = rng
        rho, conf = _search(a, b, em, disp, search_window, noise=2.0, disp=disp, cap=cap, **sgm_kw)
        return rho, conf, rho_max, int(len(disp))
    if min_range_m is not None:
        rho_max = 1.0 / float(min_range_m)
    else:
        rho_max = _find_rho_max(sub, md)
        if not math.isfinite(rho_max):
            return None
    rhos = _hypotheses(sub, rho_max, search_step_px)
    rho, conf = _search(a, b, em, rhos, search_window, noise=2.0, **sgm_kw)
    return rho, conf, rho_max, int(len(rhos))


def _per_pixel_range(geo, em: EpipolarMap, sub: EpipolarMap, md: float, min_range_m, search_step_px: float):
    """The per-pixel search's hypotheses (displacements up to md level pixels), each pixel's rho cap and the largest
    rho searched anywhere; None when no range gives parallax."""
    if not math.isfinite(_find_rho_max(sub, md)):
        return None
    # nothing nearer than min_range_m, or than 5 % of the baseline (near the focus of contraction of a camera
    # moving away, a pixel's displacement is reached only at absurd rho; the den cap only binds moving towards)
    near_m = float(min_range_m) if min_range_m is not None else 0.05 * geo.baseline_m
    cap = np.minimum(em.rho_cap, F32(1.0 / near_m))
    disp = np.arange(0.0, md + 0.5 * search_step_px, search_step_px)
    return disp, cap, _largest_rho(em, disp, cap)


def _search_scale(geo, L: int, shape_a, shape_b, shape0, max_disp_px) -> tuple:
    """The map at the search level L, its sparse grid and the largest displacement searched (level-L pixels)."""
    em = EpipolarMap.build(geo, L, shape_a, shape_b)
    md = (float(max_disp_px) if max_disp_px is not None else 0.3 * max(shape0[1], shape0[0])) / 2.0 ** L
    return em, _sparse(em), md


def _largest_rho(em: EpipolarMap, disp, cap) -> float:
    """The largest finite rho the per-pixel search reaches anywhere: at the largest displacement some pixel can reach
    (moving away from the scene, displacements are bounded). The Gauss-Newton steps are clipped at 1.25 x it."""
    cn = np.hypot(em.C1, em.C2)
    for dv in disp[::-1]:
        rm = _rho_at_disp(F32(dv), em.A0, cn, F32(em.B[0]), cap)
        rm = rm[np.isfinite(rm)]
        if rm.size:
            return float(rm.max())
    return 0.0


def _seed(rho, conf, median: bool, fill_sigma: float, fill_c: float):
    """The search's rho as the seed of the refinement: a 3 x 3 median, then weak matches (textureless, ambiguous)
    pulled towards their confident neighbours' value by normalised convolution."""
    if median:
        rho = cv2.medianBlur(rho, 3)
    if fill_sigma > 0:
        nc = _blur(conf * rho, fill_sigma) / (_blur(conf, fill_sigma) + F32(1e-6))
        wf = conf / (conf + F32(fill_c))
        rho = (wf * rho + (1 - wf) * nc).astype(F32)
    return rho


def _iterations(iters, n_levels: int) -> list:
    """Gauss-Newton iterations per level, coarsest first: the finest level's last, padded with the first entry."""
    iters = list(iters)
    while len(iters) < n_levels:
        iters.insert(0, iters[0])
    return iters[-n_levels:]


def _to_level(rho, shape):
    """rho carried one pyramid level down (pyrUp alignment) when it is not on ``shape`` yet."""
    if rho.shape == tuple(shape):
        return rho
    h, w = shape
    if rho.shape[0] * 2 == h and rho.shape[1] * 2 == w:     # into a work buffer: same values
        return cv2.pyrUp(rho, dst=_ws("rho_up", (h, w)), dstsize=(w, h))
    return pyr_up_to(rho, shape)


@dataclass(frozen=True)
class _Steps:
    """The Gauss-Newton steps' parameters: box window (level pixels) of the normal equations and of the occlusion
    test, Huber threshold (noise sigmas), Levenberg factor (lam = sigma^2 lam_k |d map / d rho|^2) and the
    shiftable windows' cost ratio."""
    window: int
    occ_window: int
    huber_k: float
    lam_k: float
    shift_ratio: np.float32
    slant_curv: float = 0.0        # > 0: the slanted window, up to this relative second difference of rho


def _refine_level(lv: _Level, rho, n_it: int, steps: _Steps, shift_px: int, *, infinity_test: bool = False,
                  rules: dict | None = None, inf_mask=None):
    """Stage 2 at one level: n_it re-linearised Gauss-Newton steps from rho, the Huber scale from the residual at the
    level's start. infinity_test: the last step also judges whether a point at infinity explains each window as
    well (returned as a uint8 mask, else None). rules (level 0, stage 3): the last step also classifies, with the
    noise of the residual before it, into a _Final (returned instead of the mask); inf_mask: a coarser level's
    infinity verdict on this level's grid."""
    sigma = None
    for it in range(n_it):
        last = it == n_it - 1
        final = last and rules is not None
        if it == 0 or final:
            sig_all, sig_in = _residual_noise(lv, rho, final=final)
        if it == 0:
            sigma = sig_all
        fin = _Final(rho.shape, sig_in, **rules) if final else None
        # the final estimate is a result (fresh array); intermediate ones are work buffers
        new = np.empty_like(rho) if final else _ws(("rho", it % 2), rho.shape)
        amb = _ws("inf_l1", rho.shape, np.uint8) if infinity_test and last else None
        _gauss_newton_step(lv, rho, new, sigma, steps, shift_px, fin=fin, inf_out=amb,
                           inf_mask=inf_mask if final else None)
        rho = new
    return rho, (fin if rules is not None else amb)


class _Final:
    """Stage 3's rules (thresholds of the uncertainty, the flags and the classification, from the noise ``sigma`` of
    the residual) and its output arrays, written by level 0's last Gauss-Newton step."""

    def __init__(self, shape, sigma, img_sigma, g0, gG, window, tex_k, occ_k, occ_px, trunc_px, match_floor_px,
                 noise_info, inf_test, std_scale, orient_min, rho_far, max_rel_std):
        self.sigma = sigma
        self.sigma_valid = sigma        # the residual's noise over the VALID pixels (``_apply_model_error``)
        n_win = float(window * window)
        sc2 = float(std_scale) ** 2
        self.var_k = F32(sc2 * sigma * sigma / n_win)
        self.floor2 = F32(sc2 * match_floor_px ** 2 / 4.0)  # E2 in the kernels is a quarter of |d map/d rho|^2
        # gradient energy of the noise alone: of the sensor noise (img_sigma), or of the final residual's (which on
        # real images also holds interpolation and non-Lambertian misfit)
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

    def thresholds(self) -> np.ndarray:
        """The thresholds in the order ``_dense_kernels.gn_level`` takes them (fp)."""
        return np.array([self.noise_G, self.var_k, self.floor2, self.trunc2, self.low_thr, self.occ_px2, self.occ_thr,
                         self.orient_min, self.rho_far, self.max_rel_std], F32)


_NO_AMB = np.empty((0, 0), np.uint8)
_NO_F2 = np.empty((0, 0), F32)
_NO_FP = np.zeros(10, F32)


_NO_SLANT = np.empty((0, 0), F32)


def _slant_shape(rho, steps: _Steps):
    """The slanted window's shape for the Gauss-Newton step from rho: (S, M), the window of centre c modelling
    rho_j = rho_c + A_c (S_j - S_c) over its pixels j (``_dense_kernels._slant_row``). S is the estimate's mean over
    2 window - 3 pixels (a box filter: a plane stays that plane, noise is averaged; over the window itself the
    noise it feeds back cost Middlebury 0.01-0.03 pp more); A_c = 1 where either the relative gradient of rho or
    its relative departure from a plane across the window stays within ``steps.slant_curv`` over the
    (2 window - 1)^2 pixels about c, falling to 0 at twice that (M: the smaller of the two largest values there, of
    rho's 3 x 3 mean's central difference and its second difference over half a window,
    ``_dense_kernels.slant_gate_inputs`` and two dilations; S over c's window reads 3 window - 4 pixels, the 3 x 3
    mean spreads an edge by 2). A depth edge (a jump, steep in both, also where the estimate has widened it into a
    ramp of up to a window: a second difference over one pixel let those pass as planes, Middlebury +0.01-0.09 pp)
    keeps one rho per window (the ramp S makes of it would smear it); a plane of any slope (ground at grazing
    angles up to the horizon, slanted walls: rho affine in the pixel) keeps the slant, and the window measures rho
    at its centre, not at the texture-weighted mean of
    its pixels. (_NO_SLANT, _NO_SLANT: one rho per window.)"""
    if not steps.slant_curv > 0:
        return _NO_SLANT, _NO_SLANT
    S = _box(rho, max(2 * steps.window - 3, steps.window), dst=_ws("slant_S", rho.shape))
    g, c = _ws("slant_g", rho.shape), _ws("slant_c", rho.shape)
    _K.slant_gate_inputs(_box(rho, 3, dst=_ws("slant_b3", rho.shape)), max(steps.window // 2, 2), g, c)
    k = _rect_kernel(2 * steps.window - 1)
    M = cv2.dilate(g, k, borderType=_BR, dst=_ws("slant_M", rho.shape))
    return S, cv2.min(M, cv2.dilate(c, k, borderType=_BR, dst=_ws("slant_Mc", rho.shape)), dst=M)


@lru_cache(maxsize=8)
def _rect_kernel(k: int) -> np.ndarray:
    return np.ones((k, k), np.uint8)


def _gauss_newton_step(lv: _Level, rho, new, sigma: float, steps: _Steps, shift_px: int, fin: _Final | None = None,
                       inf_out=None, inf_mask=None) -> None:
    """One re-linearised Gauss-Newton step of the whole level ``lv`` from rho into ``new``, in one kernel pass
    (``_dense_kernels.gn_level``: the map, the warp, the terms, their window sums streamed row by row through a ring
    of window-height planes, the update). With ``fin`` also the uncertainty, flags and classification (stage 3),
    the infinity test's verdict taken from inf_mask or, without one, judged here; inf_out: write the verdict."""
    inf_mode, amb_in = 0, _NO_AMB
    if inf_out is not None:
        inf_mode = 1
    elif fin is not None and fin.inf_test:
        if inf_mask is not None:
            amb_in = inf_mask
        else:
            inf_mode = 2      # no level 1: the infinity test at level 0
    ks = F32(max(steps.huber_k * sigma, 1e-6))
    lam_c = F32(4.0 * sigma * sigma * steps.lam_k)
    if fin is None:
        fp, outs, noise_info = _NO_FP, (_NO_AMB, _NO_F2, _NO_AMB, _NO_F2, _NO_F2, _NO_AMB), False
    else:
        fp, outs, noise_info = fin.thresholds(), (_NO_AMB, fin.std, fin.flags, fin.rng, fin.conf,
                                                  fin.amb.view(np.uint8)), fin.noise_info
    if inf_out is not None:
        outs = (inf_out,) + outs[1:]
    S, M = _slant_shape(rho, steps)
    inv_g2 = F32(0.5 / steps.slant_curv) if steps.slant_curv > 0 else F32(0.0)
    nv, ni = _K.gn_level(lv.b4p, lv.ia, lv.gxa, lv.gya, lv.rw, lv.kc, rho, S, M, inv_g2, lv.B0, lv.Q1, lv.Q2, ks,
                         lam_c, lv.use_cap, lv.rho_hi, int(steps.window), int(steps.occ_window), shift_px,
                         steps.shift_ratio,
                         fin is not None, inf_mode, amb_in, fp, noise_info, new, *outs)
    if fin is not None:
        fin.n_val += nv
        fin.n_inf += ni


@lru_cache(maxsize=8)
def _ramp_kernel(win: int) -> np.ndarray:
    return ((np.arange(win) - win // 2) / win).astype(F32)


def _window_means(lv: "_Level", rho, window: int):
    """The window means the model error needs (``_dense_kernels.model_error_finish``): of the epipolar gradient J
    at rho and of J^2 (m1, and m0J = mean J^2 - m1^2), of J^2 and J weighted by the pixel's column and row offset
    from the window's centre (rx2, rx1, ry2, ry1), and of the residual I_b(map(rho)) - I_a, its square and the
    in-view mask over the pixels in view of b (mr, mr2, mv); and the residual (0 out of view) and the in-view mask
    themselves (r, m)."""
    h, w = rho.shape
    J, J2 = _ws("me_J", (h, w)), _ws("me_J2", (h, w))
    r, iv = _ws("me_r", (h, w)), _ws("me_iv", (h, w), np.uint8)
    _K.residual_grid(lv.b4p, lv.ia, lv.rw, lv.kc, rho, lv.B0, lv.Q1, lv.Q2, 1, r, iv)
    m = iv.astype(F32)
    _K.centroid_terms(lv.rw, lv.kc, lv.B0, rho, lv.gxa, lv.gya, J, J2, m, r)
    box, ramp = _box_kernel(window), _ramp_kernel(window)
    m1 = _box(J, window)
    m0J = _box(J2, window) - m1 * m1
    rx2, rx1 = (cv2.sepFilter2D(t, -1, ramp, box, borderType=_BR) for t in (J2, J))
    ry2, ry1 = (cv2.sepFilter2D(t, -1, box, ramp, borderType=_BR) for t in (J2, J))
    mr, mr2, mv = _box(r, window), _box(r * r, window), _box(m, window)
    return m1, m0J, rx2, rx1, ry2, ry1, mr, mr2, mv, r, m


def _window_floor2(kind: str, g0: float, img_sigma: float | None, inview_sigma: float, valid_sigma: float) -> float:
    """The floor of the window's residual variance in ``_apply_model_error``: "sensor" the sensor noise's own
    (2 g0 sigma_img^2), "global" ``inview_sigma``^2, the image's final residual noise over every pixel in view (the
    classification's, ``_Final.sigma``: the window can only raise the sigma), "mid" their geometric mean, "valid"
    ``valid_sigma``^2, the final residual's robust noise over the VALID pixels (``locate_dense`` has checked the
    name)."""
    sensor = 2.0 * g0 * img_sigma ** 2 if img_sigma is not None else 0.0
    glob = max(float(inview_sigma), 1e-6) ** 2
    return {"sensor": sensor, "global": glob, "mid": math.sqrt(sensor * glob),
            "valid": max(float(valid_sigma), 1e-6) ** 2}[kind]


def _apply_model_error(lv: "_Level", rho, fin: "_Final", window: int, noise_floor2, centroid: bool,
                       max_rel_std: float, curv: float) -> None:
    """In place on level 0's final estimate: the sigma of each VALID pixel with its own window's noise and model
    error instead of the image's noise alone, and (``centroid``) rho corrected by the window model's bias.

    The kernels' sigma is the image's robust residual noise through the window's normal equations (sigma_n^2 /
    H). Where the window's model does not hold -- rho varies across it (ground at grazing angles: the window then
    misregisters its pixels by the disparity's change over it), edges the interpolation blurs, texture the
    pre-smoothing or the rendering changes between the images -- the window's residual holds that misfit on top
    of the noise, sigma_n^2 + sigma_model^2, and the match is worse by as much; where the window fits to the
    sensor noise (near sim ground) the image-wide figure over-reports it. So the noise part of sigma^2 is scaled by
    max(s_w^2, noise_floor2) / sigma_n^2: s_w^2 the window's residual variance (over its pixels in view of b, the
    brightness offset removed, times n / (n - 2) for the two parameters it fitted), its floor noise_floor2(s_v)
    (``_window_floor2`` with the kind bound, s_v the residual's robust noise over the VALID pixels,
    ``fin.sigma_valid``): by default sigma_n^2 itself, so that a window can only widen the sigma (on real images a
    window's small residual does not mean a small error); "valid" s_v^2 (sigma_n is taken over every pixel in view,
    sky and occluded pixels included, whose residual at an estimate the method rejects is not the noise of the ones
    it ranges: sim flights sigma_n 1.37-1.39, s_v 0.90); or the sensor noise's own.

    One rho per window measures rho not at the pixel but at the window's effective centre: its normal equations
    (brightness offset eliminated) solve rho = sum_j W_j rho_j / sum_j W_j, W_j = J_j (J_j - mean J), J_j the
    epipolar gradient, so the texture picks the point, offset o = sum_j W_j (x_j - x_c) / sum_j W_j from the pixel
    (clipped to the window). On a surface with slope g its bias is b = g . o (g: minmod of the 3 x 3 mean of the
    estimate over half a window each way, a plane's slope and not a depth edge's). With ``centroid`` rho is moved
    back by A b, A the slanted window's planarity gate (1 where rho is planar about the pixel, 0 at depth edges,
    ``_slant_shape``), and what the gate leaves, (1 - A) b, goes into the sigma in quadrature. A pixel whose
    relative sigma then exceeds max_rel_std loses VALID (ILL_CONDITIONED, as the kernels' rule)
    (``_dense_kernels.model_error_finish``)."""
    m1, m0J, rx2, rx1, ry2, ry1, mr, mr2, mv, r, m = _window_means(lv, rho, window)
    measured = ((fin.flags & VALID) != 0) & ((fin.flags & AT_INFINITY) == 0) & (m > 0)
    enough = np.count_nonzero(measured[::3, ::3]) >= 16
    fin.sigma_valid = _robust_sigma(r, measured) if enough else fin.sigma
    noise_floor2 = noise_floor2(fin.sigma_valid)
    rs = _box(rho, 3, dst=_ws("me_rs", rho.shape))
    if centroid:
        S, M = _slant_shape(rho, _Steps(window, 3, 0.0, 0.0, F32(0.0), slant_curv=curv))
    else:
        S = M = rs
    lost = _K.model_error_finish(rho, rs, max(window // 2, 1), S, M, F32(0.5 / curv), m1, m0J, rx2, rx1, ry2, ry1,
                                 F32(window // 2), mr, mr2, mv, F32(window * window), F32(noise_floor2),
                                 F32(max(fin.sigma, 1e-6) ** 2), lv.rw, lv.kc, lv.B0, fin.floor2, F32(max_rel_std),
                                 bool(centroid), fin.std, fin.flags, fin.rng, fin.conf)
    fin.n_val -= int(lost)


def _aperture_gain(lv: "_Level", c1, c2, window: int) -> np.ndarray:
    """Per pixel, q = d(disparity) / d(shift of image b across the epipolar direction) of the window's estimate.

    The window's normal equations (brightness offset eliminated) solve the disparity change along the unit epipolar
    direction l from sum_j g_l,j (r_j - mean r) = sum_j g_l,j (g_l,j - mean g_l) dd, g_l = grad I . l. A shift s of
    b along the unit normal p = (-l_2, l_1) adds g_p,j s to every residual, so it moves the estimate by
    dd = -q s with q = cov(g_l, g_p) / var(g_l) over the window (gradients of image a at level 0, l from the
    epipolar map's derivative (C1, C2)). Isotropic texture has q ~ 0 (its cross-products cancel); a straight edge at
    angle theta to l has q = cot(theta) (g_l = -|g| sin theta, g_p = |g| cos theta): the aperture problem. This is
    LSD-SLAM's geometric disparity error sigma_l^2 / <g, l>^2 (Engel, Sturm, Cremers 2013, "Semi-dense visual
    odometry for a monocular camera", ICCV 2013, section 2.1.3), written for a window's least-squares fit instead of one pixel.
    (c1, c2): the epipolar map's derivative on level 0's grid (``_apply_aperture``)."""
    n = np.sqrt(c1 * c1 + c2 * c2)
    n[n == 0] = F32(1.0)
    l1, l2 = c1 / n, c2 / n
    gl = lv.gxa * l1 + lv.gya * l2
    gp = lv.gya * l1 - lv.gxa * l2
    m_l, m_p = _box(gl, window), _box(gp, window)
    var_l = _box(gl * gl, window) - m_l * m_l
    cov = _box(gl * gp, window) - m_l * m_p
    with np.errstate(invalid="ignore", divide="ignore"):
        q = cov / var_l
    return np.where(np.isfinite(q), q, F32(0.0)).astype(F32)


def _apply_aperture(lv: "_Level", rho, fin: "_Final", window: int, sigma_l: float, max_rel_std: float) -> None:
    """In place on level 0's final estimate: each VALID (not AT_INFINITY) pixel's sigma^2 gains the geometric term
    (sigma_l q / E)^2 in quadrature, q the window's gain from a shift of b across the epipolar direction to its
    disparity (``_aperture_gain``), E = |d map / d rho| (pixels of disparity per unit rho), sigma_l the shift's
    1-sigma (std_scale x ``aperture_px``). A pixel whose relative sigma then exceeds max_rel_std loses VALID
    (ILL_CONDITIONED, as the kernels' rule)."""
    c1 = lv.rw[3][None, :] + lv.kc[3][:, None]          # the epipolar map's derivative C / 2 (rows 3, 4)
    c2 = lv.rw[4][None, :] + lv.kc[4][:, None]
    q = _aperture_gain(lv, c1, c2, window)
    ok = ((fin.flags & VALID) > 0) & ((fin.flags & AT_INFINITY) == 0)
    den = rho * lv.B0 + lv.rw[0][None, :] + lv.kc[0][:, None]
    with np.errstate(invalid="ignore", divide="ignore", over="ignore"):
        E = 2.0 * np.sqrt(c1 * c1 + c2 * c2) / (den * den)     # rows 3, 4 hold C / 2
        add = (sigma_l * q / E) ** 2
        sd = np.sqrt(fin.std * fin.std + add).astype(F32)
        fin.std[ok] = sd[ok]
        bad = ok & ~((sd <= max_rel_std * rho) & np.isfinite(sd))
        fin.conf[ok] = (rho / sd)[ok]
    fin.flags[bad] = (fin.flags[bad] & ~np.uint8(VALID)) | np.uint8(ILL_CONDITIONED)
    fin.rng[bad] = np.nan
    fin.conf[bad] = 0.0
    fin.n_val -= int(bad.sum())


def _plane_pair(size: int, range_m: float = 20.0, seed: int = 0) -> tuple[View, View]:
    """A textured wall ``range_m`` ahead of camera a, seen again by camera b 1 m nearer and 0.3 m to the right: a
    pair with known geometry for ``prepare_kernels``. Image b is image a through the homography the plane induces:
    a pixel's m = [1, (u - cx) / f, (v - cy) / f] goes to X_b / x_c = (R + rho t e0^T) m at the wall's rho (eqs.
    25-26), then to b's pixel. Both images carry unit sensor noise."""
    f = 0.8 * size
    c = (size - 1) / 2.0
    cam = Camera("plane", size, size, f, f, c, c)
    rng = np.random.default_rng(seed)
    texture = cv2.GaussianBlur(rng.standard_normal((size, size)).astype(F32), (0, 0), 1.5) * F32(150.0) + F32(128.0)
    a = View(cam, VehicleState.from_ypr([0.0, 0.0, 0.0], [0.0, 0.0, 0.0]), texture)
    st_b = VehicleState.from_ypr([1.0, 0.3, 0.0], [0.0, 0.0, 0.0])
    geo = pair_geometry(a, View(cam, st_b, texture))
    to_m = np.array([[0.0, 0.0, 1.0], [1.0 / f, 0.0, -c / f], [0.0, 1.0 / f, -c / f]])
    to_px = np.array([[c, f, 0.0], [c, 0.0, f], [1.0, 0.0, 0.0]])
    H = to_px @ (geo.R_ba + np.outer(geo.t_ba_m, [1.0 / range_m, 0.0, 0.0])) @ to_m
    img_b = cv2.warpPerspective(texture, H, (size, size), flags=cv2.INTER_LINEAR, borderMode=cv2.BORDER_REFLECT)
    noisy = lambda img: (img + rng.standard_normal(img.shape)).astype(F32)
    return View(cam, a.state, noisy(texture)), View(cam, st_b, noisy(img_b))


def prepare_kernels() -> None:
    """Compile the kernels (or load them from numba's cache) now, for the argument types locate_dense passes them,
    instead of in the first locate: a service spends this before its first frame (compiling takes seconds, tens of
    seconds on a fresh install). numba compiles per argument type, and every locate passes each kernel the same
    types (C-contiguous float32 / uint8 arrays, the same scalar types) whatever the image size or the options: one
    small plane pair (``_plane_pair``) reaches them all, the fill's included, and once more with a prior (its
    gate and its finish), and once each with the slanted window and the resolution match (both off by default)."""
    a, b = _plane_pair(96)
    locate_dense(a, b)
    locate_dense(a, b, slant=True)
    locate_dense(a, b, match_blur=True)
    locate_dense(a, b, fill=False, prior=(np.full(a.image.shape, 0.05, F32), np.full(a.image.shape, 1e-4, F32)))


__all__ = ["locate_dense", "prepare_kernels"]
