"""The default range estimator: a dense, direct inverse-range method (brightness constancy + known motion).

Idea (the paper's, eqs. 25-28, made robust): with the relative pose known, every pixel of image a can
only move along its epipolar curve in image b, parameterised exactly by its inverse range rho = 1/x_c
(eqs. 25-26, ``_common.EpipolarMap``). Brightness constancy I_b(map(rho)) = I_a is then ONE equation in
ONE unknown per pixel; its first-order expansion (the paper's eq. 27 after multiplying through by the
denominator of eqs. 25-26) is linear in rho. We solve it

1. where the first-order model breaks (disparities of many pixels) by a 1-D search over inverse-range
   hypotheses along the epipolar curve at a coarse pyramid level (windowed ZNCC, winner-take-all,
   parabola sub-sample fit, 3x3 median) -- no 2-D flow search anywhere;
2. then coarse-to-fine by re-linearised Gauss-Newton: at each level warp b at the current rho
   (cv2.remap), so that the Taylor remainder (eq. 7) stays small, and solve the windowed (box), Huber-
   weighted normal equations of r + J (rho' - rho) = 0, r = I_b(map(rho)) - I_a,
   J = grad I_b(warped) . d(u_b, v_b)/d rho (analytic derivative of the rational map), with a
   Levenberg trust term worth about ``trust_px`` pixels of displacement.

Per-pixel 1-sigma of rho from the normal equations and the noise (robust MAD of the final residual),
confidence = rho / sigma. Flags: OUT_OF_VIEW (map leaves b, behind b, or occluded = high windowed
residual), LOW_TEXTURE (gradient energy not above the noise's own), ILL_CONDITIONED (focus of expansion,
gradient perpendicular to the epipolar direction, relative std above ``max_rel_std``), TRUNCATION
(eq. 7-style: the last update still moved by more than ``trunc_px``), AT_INFINITY (rho within 2 sigma
of 0 with a tight sigma: range +inf).

All per-pixel work is float32 numpy / OpenCV on whole images: no per-pixel Python.
"""
from __future__ import annotations

import math
import time
from functools import lru_cache

import cv2
import numpy as np

from ..camera import View, pair_geometry
from ..rangemap import ILL_CONDITIONED, LOW_TEXTURE, OUT_OF_VIEW, TRUNCATION, RangeResult
from ._common import F32, EpipolarMap, classify, far_inverse_range, no_motion_result, pyr_up_to, pyramid

METHOD = "dense"
_BR = cv2.BORDER_REFLECT


def _blur(img: np.ndarray, sigma: float) -> np.ndarray:
    k = 2 * int(math.ceil(2.5 * sigma)) + 1
    return cv2.GaussianBlur(img, (k, k), sigma, borderType=_BR)


def _box(img: np.ndarray, win: int) -> np.ndarray:
    return cv2.boxFilter(img, -1, (win, win), borderType=_BR)


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
    vals = np.abs(rs[mask[::step, ::step]] if mask is not None else rs)
    if vals.size < 16:
        return floor
    return max(float(1.4826 * np.median(vals)), floor)


def _sparse(emap: EpipolarMap, n: int = 17) -> EpipolarMap:
    """The same map on an n x n grid of pixels spanning the image (corners included)."""
    h, w = emap.A0.shape
    iy = np.linspace(0, h - 1, n).round().astype(int)
    ix = np.linspace(0, w - 1, n).round().astype(int)
    g = np.ix_(iy, ix)
    return EpipolarMap(emap.A0[g], emap.A1[g], emap.A2[g], emap.B, emap.C1[g], emap.C2[g], emap.cam_b,
                       emap.rho_cap[g])


def _max_disparity(sub: EpipolarMap, rho: float, u0, v0) -> float:
    """Largest displacement (level pixels) over the sparse grid between rho = 0 and rho; inf if some
    point would be at or behind camera b."""
    den = sub.A0 + sub.B[0] * F32(rho)
    if np.any(den <= 0.05):
        return math.inf
    u1, v1, _ = sub(F32(rho))
    return float(np.sqrt((u1 - u0) ** 2 + (v1 - v0) ** 2).max())


def _find_rho_max(sub: EpipolarMap, max_disp: float) -> float:
    """Inverse range at which the largest displacement reaches max_disp (level pixels); inf if never."""
    u0, v0, _ = sub(F32(0.0))
    lo, hi = 0.0, 1e-6
    while _max_disparity(sub, hi, u0, v0) < max_disp:
        lo, hi = hi, hi * 10.0
        if hi > 1e9:
            return math.inf
    for _ in range(30):
        mid = 0.5 * (lo + hi)
        if _max_disparity(sub, mid, u0, v0) < max_disp:
            lo = mid
        else:
            hi = mid
    return lo


def _hypotheses(sub: EpipolarMap, rho_max: float, step_px: float) -> np.ndarray:
    """Inverse-range hypotheses 0 = rho_0 < ... = rho_max such that the largest displacement in the image
    grows by ``step_px`` level pixels from one to the next (uniform in displacement, not in rho)."""
    u0, v0, _ = sub(F32(0.0))
    grid = np.linspace(0.0, rho_max, 65)
    d = np.array([_max_disparity(sub, r, u0, v0) for r in grid])
    fin = np.isfinite(d)
    d = np.maximum.accumulate(np.where(fin, d, d[fin].max()))
    n = max(2, int(math.ceil(d[-1] / step_px)) + 1)
    return np.interp(np.linspace(0.0, d[-1], n), d, grid)


def _search(a: np.ndarray, b: np.ndarray, emap: EpipolarMap, rhos: np.ndarray, win: int, noise: float):
    """Windowed ZNCC along the epipolar curve for all hypotheses at once (stacked into one tall image,
    each slab padded by symmetric rows so the box filters do not mix hypotheses); winner-take-all with a
    parabola sub-sample fit. Returns rho (h x w) and the best cost (1 - ZNCC)."""
    h, w = a.shape
    n = len(rhos)
    p = win // 2
    R = rhos.astype(F32)[:, None, None]
    B = emap.B
    inv = 1.0 / (emap.A0[None] + B[0] * R)
    ub = (emap.A1[None] + B[1] * R) * inv * F32(emap.cam_b.fx) + F32(emap.cam_b.cx)
    vb = (emap.A2[None] + B[2] * R) * inv * F32(emap.cam_b.fy) + F32(emap.cam_b.cy)
    hb, wb = b.shape
    bad = ~((ub >= 0) & (ub <= wb - 1) & (vb >= 0) & (vb <= hb - 1) & (inv > 0))
    pad = ((0, 0), (p, p), (0, 0))
    hp = h + 2 * p
    ubs = np.pad(ub, pad, mode="symmetric").reshape(n * hp, w)
    vbs = np.pad(vb, pad, mode="symmetric").reshape(n * hp, w)
    bw = cv2.remap(b, ubs, vbs, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)
    at = np.ascontiguousarray(np.broadcast_to(np.pad(a, ((p, p), (0, 0)), mode="symmetric")[None], (n, hp, w))
                              ).reshape(n * hp, w)
    ksz = (win, win)
    ma = cv2.boxFilter(at, -1, ksz, borderType=_BR)
    va = cv2.boxFilter(at * at, -1, ksz, borderType=_BR) - ma * ma
    mb = cv2.boxFilter(bw, -1, ksz, borderType=_BR)
    vbb = cv2.boxFilter(bw * bw, -1, ksz, borderType=_BR) - mb * mb
    cab = cv2.boxFilter(at * bw, -1, ksz, borderType=_BR) - ma * mb
    den = np.sqrt(np.maximum(va, 0) * np.maximum(vbb, 0) + F32(noise ** 4))
    cost = (1.0 - cab / den).reshape(n, hp, w)[:, p:p + h, :]
    cost[bad] = 2.0
    kbest = np.argmin(cost, axis=0)
    cbest = np.take_along_axis(cost, kbest[None], 0)[0]
    cm = np.take_along_axis(cost, np.clip(kbest - 1, 0, n - 1)[None], 0)[0]
    cp = np.take_along_axis(cost, np.clip(kbest + 1, 0, n - 1)[None], 0)[0]
    curv = cm - 2 * cbest + cp
    with np.errstate(divide="ignore", invalid="ignore"):
        off = np.where((curv > 1e-6) & (kbest > 0) & (kbest < n - 1), 0.5 * (cm - cp) / curv, 0.0)
    kf = kbest + np.clip(off, -0.5, 0.5)
    rho = np.interp(kf.ravel(), np.arange(n), rhos).reshape(h, w).astype(F32)
    # confidence of the winner: correlation (>= 0) times texture (windowed variance against the noise)
    vat = va.reshape(n, hp, w)[0, p:p + h, :]
    conf = np.clip(1.0 - cbest, 0.0, 1.0) ** 2 * (vat / (vat + F32(noise * noise)))
    return rho, conf.astype(F32)


class _Level:
    """Per-level constants: the epipolar map with the intrinsics folded in, and b with its gradients."""

    def __init__(self, geo, lev, ia, ib):
        em = EpipolarMap.build(geo, lev, ia.shape, ib.shape)
        cb = em.cam_b
        B = em.B
        self.em = em
        self.ia = ia
        self.A0 = em.A0
        self.B0 = F32(B[0])
        # u_b = (P1 + Q1 rho) / den with P1 = fx A1 + cx A0, Q1 = fx B1 + cx B0 (likewise v)
        self.P1 = F32(cb.fx) * em.A1 + F32(cb.cx) * em.A0
        self.Q1 = F32(cb.fx * B[1] + cb.cx * B[0])
        self.P2 = F32(cb.fy) * em.A2 + F32(cb.cy) * em.A0
        self.Q2 = F32(cb.fy * B[2] + cb.cy * B[0])
        self.C1, self.C2 = em.C1, em.C2
        self.Csq = em.C1 * em.C1 + em.C2 * em.C2
        self.cap = em.rho_cap
        gx, gy = _grad(ib)
        self.b4 = cv2.merge([ib, gx, gy, np.ones_like(ib)])
        self.shape_b = ib.shape

    def warp(self, rho):
        """Warped [I_b, gx_b, gy_b, in-view] at rho, and 1/den."""
        inv = cv2.divide(1.0, self.A0 + self.B0 * rho)
        ub = (self.P1 + self.Q1 * rho) * inv
        vb = (self.P2 + self.Q2 * rho) * inv
        wv = cv2.remap(self.b4, ub, vb, cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT, borderValue=0)
        return wv, inv


def locate_dense(view_a: View, view_b: View, *, max_disp_px: float | None = None, min_range_m: float | None = None,
                 search_level: int | None = None, search_step_px: float = 1.0, search_window: int = 5,
                 median: bool = True, iters=(3, 2, 2, 1), window: int = 7, huber_k: float = 2.0,
                 trust_px: float = 1.0, presmooth_sigma: float = 0.8, max_rel_std: float = 0.25,
                 far_parallax_px: float = 0.5, tex_k: float = 1.5, orient_min: float = 0.02,
                 occ_k: float = 3.0, trunc_px: float = 0.5, std_scale: float = 1.0, fill_sigma: float = 4.0,
                 fill_c: float = 0.3, smooth_win: int = 0, highpass_sigma: float = 0.0,
                 highpass_levels: int = 9, bias: bool = True,
                 match_floor_px: float = 0.05) -> RangeResult:
    """Dense inverse range of every pixel of view a from the pair (a, b) with known poses.

    max_disp_px / min_range_m: search range (default: largest displacement 0.3 * image size).
    search_level: pyramid level of the epipolar search (default: coarsest level with >= 64 px, at most 3).
    search_step_px: hypothesis spacing, pixels of displacement at the search level.
    iters: Gauss-Newton iterations per level, finest level last (padded with its first entry if short).
    window: box window (level pixels, odd) of the normal equations. huber_k: Huber threshold in noise
    sigmas. trust_px: Levenberg trust term ~ a step of this many pixels of displacement per iteration.
    presmooth_sigma: Gaussian pre-smoothing of both images (pixels).
    max_rel_std: largest relative std of the range for VALID. far_parallax_px: AT_INFINITY needs
    2 sigma below the inverse range of this much parallax (see _common.far_inverse_range).
    tex_k: LOW_TEXTURE where the windowed gradient energy is below (1 + tex_k^2) x the noise's own.
    orient_min: ILL_CONDITIONED where the epipolar share of the gradient energy is below this.
    occ_k: occluded (OUT_OF_VIEW) where the windowed RMS residual exceeds occ_k x noise.
    trunc_px: TRUNCATION where the last update still moves the match by more than this (level-0 px).
    std_scale: calibration factor of the reported sigma.
    """
    t_start = time.perf_counter()
    geo = pair_geometry(view_a, view_b)
    Ia, Ib = view_a.image, view_b.image
    ha, wa = Ia.shape
    if geo.baseline_m <= 1e-12:
        return no_motion_result((ha, wa), METHOD, "zero baseline")
    if search_level is None:
        m = min(ha, wa, *Ib.shape)
        search_level = int(max(0, min(3, math.floor(math.log2(m / 64.0)))))
    L = search_level
    nlev = L + 1
    if presmooth_sigma > 0:
        Ia = _blur(Ia, presmooth_sigma)
        Ib = _blur(Ib, presmooth_sigma)
    pa, pb = pyramid(Ia, nlev), pyramid(Ib, nlev)
    if highpass_sigma > 0:   # remove local brightness offsets (illumination, vignetting, exposure)
        pa = [x - _blur(x, highpass_sigma) if i < highpass_levels else x for i, x in enumerate(pa)]
        pb = [x - _blur(x, highpass_sigma) if i < highpass_levels else x for i, x in enumerate(pb)]

    # --- 1. epipolar search at the coarse level
    em_s = EpipolarMap.build(geo, L, pa[L].shape, pb[L].shape)
    sub = _sparse(em_s)
    if min_range_m is not None:
        rho_max = 1.0 / float(min_range_m)
    else:
        md = float(max_disp_px) if max_disp_px is not None else 0.3 * max(wa, ha)
        rho_max = _find_rho_max(sub, md / 2.0 ** L)
        if not math.isfinite(rho_max):
            return no_motion_result((ha, wa), METHOD, "no parallax at any range")
    rhos = _hypotheses(sub, rho_max, search_step_px)
    rho, conf = _search(pa[L], pb[L], em_s, rhos, search_window, noise=2.0)
    if median:
        rho = cv2.medianBlur(rho, 3)
    if fill_sigma > 0:
        # normalised convolution: weak matches (textureless, ambiguous) take the confident neighbours' value
        nc = _blur(conf * rho, fill_sigma) / (_blur(conf, fill_sigma) + F32(1e-6))
        wf = conf / (conf + F32(fill_c))
        rho = (wf * rho + (1 - wf) * nc).astype(F32)
    rho_hi = F32(rho_max * 1.25)

    # --- 2. coarse-to-fine re-linearised Gauss-Newton
    iters = list(iters)
    while len(iters) < nlev:
        iters.insert(0, iters[0])
    iters = iters[-nlev:]
    n_win = float(window * window)
    sigma = 2.0
    for lev in range(L, -1, -1):
        lv = _Level(geo, lev, pa[lev], pb[lev])
        if rho.shape != pa[lev].shape:
            rho = pyr_up_to(rho, pa[lev].shape)
        cap = np.minimum(lv.cap, rho_hi)
        lam_k = F32(1.0 / (n_win * trust_px * trust_px))
        n_it = max(iters[L - lev], 1 if lev == 0 else 0)
        for it in range(n_it):
            wv, inv = lv.warp(rho)
            r = wv[..., 0] - lv.ia
            inv2 = inv * inv
            J = (wv[..., 1] * lv.C1 + wv[..., 2] * lv.C2) * inv2
            if it == 0:
                sigma = _robust_sigma(r)
            # Huber weights times the in-view mask
            wgt = np.minimum(F32(1.0), F32(huber_k * sigma) / (np.abs(r) + F32(1e-6)))
            wgt *= wv[..., 3]
            wJ = wgt * J
            q = J * rho - r
            H = _box(wJ * J, window)
            g = _box(wJ * q, window)
            if bias:   # unknown brightness offset per window, eliminated (Schur complement)
                S0 = _box(wgt, window) + F32(1e-6)
                S1 = _box(wJ, window)
                Sq = _box(wgt * q, window)
                S1n = S1 / S0
                H -= S1n * S1
                g -= S1n * Sq
            E2 = lv.Csq * (inv2 * inv2)
            lam = E2 * F32(sigma * sigma) * lam_k
            if smooth_win > 0:   # prior: confidence-weighted mean of the neighbours (diffuses into flat areas)
                Hs = H + lam
                prior = _box(Hs * rho, smooth_win) / _box(Hs, smooth_win)
            else:
                prior = rho
            new = (g + lam * prior) / (H + lam + F32(1e-30))
            np.clip(new, F32(0), cap, out=new)
            if lev == 0 and it == n_it - 1:
                step_px = np.abs(new - rho) * np.sqrt(E2)
                final = (wv, inv, r, J, E2, wgt, H)
            rho = new

    # --- 3. uncertainty and flags, from the last linearisation at level 0
    wv, inv, r, J, E2, wgt, Hf = final
    inview = (wv[..., 3] > 0.999) & (inv > 0)
    mf = inview.astype(F32)
    sigma = _robust_sigma(r, inview)
    g0, gG = _noise_gains(float(presmooth_sigma))
    noise_G = (sigma * sigma / (2.0 * g0)) * gG          # gradient energy of the noise alone
    gxa, gya = _grad(pa[0])
    G = _box(mf * (gxa * gxa + gya * gya), window)
    R2 = _box(mf * r * r, window)
    with np.errstate(divide="ignore", invalid="ignore"):
        # normal-equation information (Huber-weighted, brightness offset eliminated) of the last linearisation
        # plus a floor of match_floor_px pixels of displacement (interpolation bias, surface slant, ...)
        std = np.sqrt(F32(sigma * sigma / n_win) / Hf + F32(match_floor_px ** 2) / E2) * F32(std_scale)
        orient = Hf / (E2 * G)     # share of the gradient energy along the epipolar direction
    bad = np.zeros((ha, wa), np.uint8)
    bad[~inview] |= OUT_OF_VIEW
    bad[R2 > F32((occ_k * sigma) ** 2)] |= OUT_OF_VIEW
    low = G < F32((1.0 + tex_k * tex_k) * noise_G)
    bad[low] |= LOW_TEXTURE
    bad[~low & ~(orient >= orient_min)] |= ILL_CONDITIONED
    bad[step_px > trunc_px] |= TRUNCATION
    info = {"seconds": time.perf_counter() - t_start, "noise_sigma": sigma, "rho_max_per_m": rho_max,
            "n_hypotheses": int(len(rhos)), "search_level": L, "baseline_m": geo.baseline_m}
    return classify(rho, std.astype(F32), bad_flags=bad, method=METHOD,
                    rho_far=far_inverse_range(geo, far_parallax_px), max_rel_std=max_rel_std, info=info)


__all__ = ["locate_dense"]
