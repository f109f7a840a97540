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
   (cv2.remap), so that the Taylor remainder (eq. 7) stays small, and solve the windowed, Huber-weighted
   normal equations of r + J (rho' - rho) = 0 with J = grad I_b(warped) . d(u_b, v_b)/d rho (analytic
   derivative of the rational map), with a Levenberg trust term of about one pixel of disparity.

Per-pixel 1-sigma of rho from the normal equations and the noise (robust MAD of the final residual);
confidence = rho / sigma. Flags: OUT_OF_VIEW (map leaves b, behind b, or occluded = high windowed
residual), LOW_TEXTURE, ILL_CONDITIONED (epipolar sensitivity tiny: focus of expansion, gradient
perpendicular to the epipolar direction, or relative std too large), TRUNCATION (eq. 7-style: the last
update still moved by more than ``trunc_px`` pixels), AT_INFINITY (rho within 2 sigma of 0 with a tight
sigma: range +inf).

All per-pixel work is float32 numpy / OpenCV on whole images: no per-pixel Python.
"""
from __future__ import annotations

import math
import time

import cv2
import numpy as np

from ..camera import View, pair_geometry
from ..rangemap import ILL_CONDITIONED, LOW_TEXTURE, OUT_OF_VIEW, TRUNCATION, RangeResult
from ._common import (F32, EpipolarMap, classify, far_inverse_range, no_motion_result, pyr_up_to, pyramid)

METHOD = "dense"
INTERP = cv2.INTER_LINEAR


def _blur(img: np.ndarray, sigma: float) -> np.ndarray:
    """Gaussian window (separable), kernel radius ceil(2.5 sigma)."""
    k = 2 * int(math.ceil(2.5 * sigma)) + 1
    return cv2.GaussianBlur(img, (k, k), sigma, borderType=cv2.BORDER_REFLECT)


def _grad(img: np.ndarray):
    gx = cv2.Scharr(img, cv2.CV_32F, 1, 0, scale=1.0 / 32.0, borderType=cv2.BORDER_REFLECT)
    gy = cv2.Scharr(img, cv2.CV_32F, 0, 1, scale=1.0 / 32.0, borderType=cv2.BORDER_REFLECT)
    return gx, gy


def _residual(wv: np.ndarray, ia: np.ndarray, ub: np.ndarray, vb: np.ndarray) -> np.ndarray:
    """I_b(u_b, v_b) - I_a from a cv2.remap of [I, gx, gy, ...] of b. cv2.remap rounds float coordinates to
    1/32 pixel (INTER_BITS = 5); that quantisation (up to 1/64 px) biases sub-pixel estimates, so correct it
    to first order with the warped gradient: I(p) ~ I(q) + grad I(q) . (p - q), q = rint(32 p) / 32."""
    du = ub - np.rint(ub * F32(32.0)) * F32(1.0 / 32.0)
    dv = vb - np.rint(vb * F32(32.0)) * F32(1.0 / 32.0)
    return wv[..., 0] + wv[..., 1] * du + wv[..., 2] * dv - ia


def _robust_sigma(r: np.ndarray, mask: np.ndarray, step: int = 3, floor: float = 0.3) -> float:
    """1.4826 * median |r| over a subsampled masked grid (noise of the residual image)."""
    rs = r[::step, ::step]
    ms = mask[::step, ::step]
    vals = np.abs(rs[ms])
    if vals.size < 16:
        return floor
    return max(float(1.4826 * np.median(vals)), floor)


def _max_disparity(emap: EpipolarMap, rho: float, scale: float, stride: int = 4) -> float:
    """Largest displacement (level-0 pixels) over a sub-grid of pixels between rho = 0 and rho; inf if
    some point would be at or behind camera b."""
    sub = EpipolarMap(emap.A0[::stride, ::stride], emap.A1[::stride, ::stride], emap.A2[::stride, ::stride],
                      emap.B, emap.C1[::stride, ::stride], emap.C2[::stride, ::stride], emap.cam_b,
                      emap.rho_cap[::stride, ::stride])
    den = sub.A0 + sub.B[0] * F32(rho)
    if np.any(den <= 0.05):
        return math.inf
    u0, v0, _ = sub(F32(0.0))
    u1, v1, _ = sub(F32(rho))
    return float(np.sqrt((u1 - u0) ** 2 + (v1 - v0) ** 2).max() * scale)


def _hypotheses(emap: EpipolarMap, level: int, rho_max: float, step_px: float):
    """Inverse-range hypotheses 0 = rho_0 < rho_1 < ... <= rho_max spaced so that the largest displacement
    in the image grows by ``step_px`` pixels of the search level from one hypothesis to the next."""
    grid = np.linspace(0.0, rho_max, 257)
    d = np.array([_max_disparity(emap, r, 1.0, stride=4) for r in grid])
    d = np.maximum.accumulate(np.where(np.isfinite(d), d, np.nanmax(d[np.isfinite(d)])))
    n = max(2, int(math.ceil(d[-1] / step_px)) + 1)
    targets = np.linspace(0.0, d[-1], n)
    return np.interp(targets, d, grid).astype(np.float64)


def _find_rho_max(emap: EpipolarMap, max_disp_px: float) -> float:
    """Inverse range at which the largest displacement in the image reaches max_disp_px (bisection in log rho).
    Returns inf if even a huge rho gives less (no parallax)."""
    lo, hi = 0.0, 1e-6
    while _max_disparity(emap, hi, 1.0) < max_disp_px:
        lo, hi = hi, hi * 10.0
        if hi > 1e9:
            return math.inf
    for _ in range(40):
        mid = 0.5 * (lo + hi)
        if _max_disparity(emap, mid, 1.0) < max_disp_px:
            lo = mid
        else:
            hi = mid
    return lo


def _search(a: np.ndarray, b: np.ndarray, emap: EpipolarMap, rhos: np.ndarray, win: int, noise: float):
    """Windowed ZNCC cost along the epipolar curve for every hypothesis; WTA + parabola. Returns rho, cost."""
    h, w = a.shape
    ksz = (win, win)
    ma = cv2.boxFilter(a, -1, ksz, borderType=cv2.BORDER_REFLECT)
    va = cv2.boxFilter(a * a, -1, ksz, borderType=cv2.BORDER_REFLECT) - ma * ma
    eps = F32((noise * noise) ** 2)
    b2 = cv2.merge([b, np.ones_like(b)])
    n = len(rhos)
    cost = np.empty((n, h, w), F32)
    for k, r in enumerate(rhos):
        ub, vb, inv = emap(F32(r))
        wb = cv2.remap(b2, ub, vb, cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT, borderValue=0)
        bw, m = wb[..., 0], wb[..., 1]
        mb = cv2.boxFilter(bw, -1, ksz, borderType=cv2.BORDER_REFLECT)
        vb_ = cv2.boxFilter(bw * bw, -1, ksz, borderType=cv2.BORDER_REFLECT) - mb * mb
        cab = cv2.boxFilter(a * bw, -1, ksz, borderType=cv2.BORDER_REFLECT) - ma * mb
        zn = cab / np.sqrt(np.maximum(va, 0) * np.maximum(vb_, 0) + eps)
        c = 1.0 - zn
        c[(m < 0.999) | (inv <= 0)] = 2.0
        cost[k] = c
    kbest = np.argmin(cost, axis=0)
    cbest = np.take_along_axis(cost, kbest[None], 0)[0]
    km = np.clip(kbest - 1, 0, n - 1)
    kp = np.clip(kbest + 1, 0, n - 1)
    cm = np.take_along_axis(cost, km[None], 0)[0]
    cp = np.take_along_axis(cost, kp[None], 0)[0]
    den = cm - 2 * cbest + cp
    with np.errstate(divide="ignore", invalid="ignore"):
        off = np.where((den > 1e-6) & (kbest > 0) & (kbest < n - 1), 0.5 * (cm - cp) / den, 0.0)
    kf = kbest + np.clip(off, -0.5, 0.5)
    rho = np.interp(kf.ravel(), np.arange(n), rhos).reshape(h, w).astype(F32)
    return rho, cbest


def locate_dense(view_a: View, view_b: View, *, max_disp_px: float | None = None, min_range_m: float | None = None,
                 search_level: int | None = None, search_step_px: float = 1.0, search_window: int = 5,
                 median: bool = True, iters=(4, 3, 2), window_sigma: float = 2.0, huber_k: float = 2.0,
                 trust_px: float = 1.0, presmooth_sigma: float = 0.8, max_rel_std: float = 0.25,
                 far_parallax_px: float = 0.5, tex_k: float = 0.5, orient_min: float = 0.02,
                 occ_k: float = 3.0, trunc_px: float = 0.5, std_scale: float = 1.0) -> RangeResult:
    """Dense inverse range of every pixel of view a from the pair (a, b) with known poses.

    max_disp_px / min_range_m: search range (default: largest displacement 0.3 * image size).
    search_level: pyramid level of the epipolar search (default: coarsest level with >= 64 px, at most 2).
    iters: Gauss-Newton iterations per level, finest level last (padded with its first entry if short).
    window_sigma: Gaussian window (level pixels) of the normal equations. huber_k: Huber threshold in
    noise sigmas. trust_px: Levenberg trust term ~ one step of this many pixels of displacement.
    """
    t_start = time.perf_counter()
    geo = pair_geometry(view_a, view_b)
    Ia, Ib = view_a.image, view_b.image
    ha, wa = Ia.shape
    hb, wb = Ib.shape
    if geo.baseline_m <= 1e-12:
        return no_motion_result((ha, wa), METHOD, "zero baseline")
    if search_level is None:
        m = min(ha, wa, hb, wb)
        search_level = int(max(0, min(2, math.floor(math.log2(m / 64.0)))))
    nlev = search_level + 1
    if presmooth_sigma > 0:
        Ia = _blur(Ia, presmooth_sigma)
        Ib = _blur(Ib, presmooth_sigma)
    pa, pb = pyramid(Ia, nlev), pyramid(Ib, nlev)

    L = search_level
    emaps = {L: EpipolarMap.build(geo, L, pa[L].shape, pb[L].shape)}
    if min_range_m is not None:
        rho_max = 1.0 / float(min_range_m)
    else:
        md = float(max_disp_px) if max_disp_px is not None else 0.3 * max(wa, ha)
        rho_max = _find_rho_max(emaps[L], md / 2.0 ** L)
        if not math.isfinite(rho_max):
            return no_motion_result((ha, wa), METHOD, "no parallax at any range")
    rhos = _hypotheses(emaps[L], L, rho_max, search_step_px)
    rho, _ = _search(pa[L], pb[L], emaps[L], rhos, search_window, noise=2.0)
    if median:
        rho = cv2.medianBlur(rho, 3)
    rho_hi = F32(rho_max * 1.25)

    iters = list(iters)
    while len(iters) < nlev:
        iters.insert(0, iters[0])
    iters = iters[-nlev:]
    sigma = 2.0
    n_eff = 4.0 * math.pi * window_sigma ** 2
    last_step_px = None
    for lev in range(L, -1, -1):
        if lev not in emaps:
            emaps[lev] = EpipolarMap.build(geo, lev, pa[lev].shape, pb[lev].shape)
        em = emaps[lev]
        if rho.shape != pa[lev].shape:
            rho = pyr_up_to(rho, pa[lev].shape)
        gxb, gyb = _grad(pb[lev])
        b4 = cv2.merge([pb[lev], gxb, gyb, np.ones_like(gxb)])
        ia = pa[lev]
        cap = np.minimum(em.rho_cap, rho_hi)
        for it in range(iters[L - lev]):
            ub, vb, inv = em(rho)
            wv = cv2.remap(b4, ub, vb, INTERP, borderMode=cv2.BORDER_CONSTANT, borderValue=0)
            r = _residual(wv, ia, ub, vb)
            inv2 = inv * inv
            J = (wv[..., 1] * em.C1 + wv[..., 2] * em.C2) * inv2
            mask = wv[..., 3] > 0.999
            sigma = _robust_sigma(r, mask)
            ar = np.abs(r)
            wgt = np.where(ar > huber_k * sigma, (huber_k * sigma) / np.maximum(ar, 1e-12), F32(1.0)).astype(F32)
            wgt *= mask
            wJ = wgt * J
            H = _blur(wJ * J, window_sigma)
            g = _blur(wJ * (J * rho - r), window_sigma)
            E2 = (em.C1 * em.C1 + em.C2 * em.C2) * (inv2 * inv2)
            lam = (sigma * sigma / n_eff / (trust_px * trust_px)) * E2
            new = (g + lam * rho) / (H + lam + F32(1e-30))
            new = np.clip(new, F32(0), cap)
            if lev == 0 and it == iters[L - lev] - 1:
                last_step_px = np.abs(new - rho) * np.sqrt(E2)
            rho = new.astype(F32, copy=False)

    # final evaluation at level 0 at the final rho
    em = emaps[0]
    gxb, gyb = _grad(pb[0])
    b4 = cv2.merge([pb[0], gxb, gyb, np.ones_like(gxb)])
    ub, vb, inv = em(rho)
    wv = cv2.remap(b4, ub, vb, INTERP, borderMode=cv2.BORDER_CONSTANT, borderValue=0)
    r = _residual(wv, pa[0], ub, vb)
    inv2 = inv * inv
    J = (wv[..., 1] * em.C1 + wv[..., 2] * em.C2) * inv2
    mask = (wv[..., 3] > 0.999) & (inv > 0)
    maskf = mask.astype(F32)
    sigma = _robust_sigma(r, mask)
    E = np.sqrt(em.C1 * em.C1 + em.C2 * em.C2) * inv2
    HJ = _blur(maskf * J * J, window_sigma)
    gxa, gya = _grad(pa[0])
    G = _blur(maskf * (gxa * gxa + gya * gya), window_sigma)
    R2 = _blur(maskf * r * r, window_sigma)
    cover = _blur(maskf, window_sigma)
    with np.errstate(divide="ignore", invalid="ignore"):
        var = (sigma * sigma) / (n_eff * HJ)
        std = (np.sqrt(var) * F32(std_scale)).astype(F32)
        orient = HJ / (E * E * G)
    bad = np.zeros((ha, wa), np.uint8)
    bad[~mask | (cover < 0.5)] |= OUT_OF_VIEW
    bad[R2 > (occ_k * sigma) ** 2] |= OUT_OF_VIEW
    low = G < (tex_k * max(sigma, 0.5)) ** 2
    bad[low] |= LOW_TEXTURE
    bad[~low & ~(orient >= orient_min)] |= ILL_CONDITIONED
    if last_step_px is not None:
        bad[last_step_px > trunc_px] |= TRUNCATION
    info = {"seconds": time.perf_counter() - t_start, "noise_sigma": sigma, "rho_max_per_m": rho_max,
            "n_hypotheses": int(len(rhos)), "search_level": L, "baseline_m": geo.baseline_m}
    return classify(rho, std, bad_flags=bad, method=METHOD, rho_far=far_inverse_range(geo, far_parallax_px),
                    max_rel_std=max_rel_std, info=info)


__all__ = ["locate_dense"]
