"""An independent formulation of the dense method's per-pixel stages with OpenCV / numpy array operations, the
reference that tests/test_dense.py checks the numba kernels (eonav.ranging.methods._dense_kernels) against.

``search`` is the coarse epipolar search (cv2.remap for the warp, box filters, a numpy winner-take-all): the
kernels give its result bit for bit. ``gauss_newton_step`` is one re-linearised Gauss-Newton step of a whole level
(warp, normal equations, update and, in the final step, the uncertainty, flags and classification) and
``residual_noise`` the noise sample: the kernels agree with them to float rounding (their window sums add in another
order). ``use_reference(monkeypatch)`` makes ``locate_dense`` run these instead of the kernels; the rest of the
method (hypotheses, seed, pyramids, fill) is the production code.
"""
from __future__ import annotations

import weakref

import cv2
import numpy as np

from eonav.ranging.methods import dense
from eonav.ranging.methods._common import F32, EpipolarMap, classify_into
from eonav.ranging.methods.dense import _a_side, _box, _grad, _rho_at_disp, _robust_sigma, _sgm
from eonav.ranging.rangemap import ILL_CONDITIONED, LOW_TEXTURE, OCCLUDED, OUT_OF_VIEW, TRUNCATION

__all__ = ["search", "wta", "gauss_newton_step", "residual_noise", "shift_windows", "use_reference"]


def use_reference(monkeypatch) -> None:
    """locate_dense with this module's search, Gauss-Newton steps and noise sample instead of the kernels."""
    monkeypatch.setattr(dense, "_search", search)
    monkeypatch.setattr(dense, "_gauss_newton_step", gauss_newton_step)
    monkeypatch.setattr(dense, "_residual_noise", residual_noise)


# ---------------------------------------------------------------- the coarse search

def search(a: np.ndarray, b: np.ndarray, emap: EpipolarMap, rhos: np.ndarray, win: int, noise: float,
           sgm_p1: float = 0.0, sgm_p2: float = 0.0, sgm_tau: float = 0.0, chunk_px: int = 32768,
           disp=None, cap=None):
    """dense._search: b warped for every hypothesis into one tall image (cv2.remap), each slab padded by symmetric
    rows so the box filters do not mix hypotheses; ZNCC from box sums; optional SGM; winner-take-all with a parabola
    sub-sample fit. Returns rho and the confidence of the winner."""
    h, w = a.shape
    n = len(rhos)
    p = win // 2
    B = emap.B
    cb = emap.cam_b
    hp = h + 2 * p
    hb, wb = b.shape
    A0, A1, A2 = (np.pad(x, ((p, p), (0, 0)), mode="symmetric")[None] for x in (emap.A0, emap.A1, emap.A2))
    if disp is not None:      # hypotheses uniform in each pixel's own displacement: rho per pixel
        cn = np.hypot(emap.C1, emap.C2)
        cn_p, cap_p = (np.pad(x, ((p, p), (0, 0)), mode="symmetric")[None] for x in (cn, cap))
    P1 = A1 * F32(cb.fx) + A0 * F32(cb.cx)
    P2 = A2 * F32(cb.fy) + A0 * F32(cb.cy)
    Q1, Q2 = F32(cb.fx * B[1] + cb.cx * B[0]), F32(cb.fy * B[2] + cb.cy * B[0])
    ap, ma, va, va_pos = _a_side(a, win)
    cost = np.empty((n, h, w), F32)
    c = (slice(None), slice(p, p + h))
    step = max(1, min(n, chunk_px // (hp * w)))
    ap_t, ma_t, va_t = (np.tile(x, (step, 1)) for x in (ap, ma, va_pos))
    noise4 = F32(noise ** 4)
    mul, sub = cv2.multiply, cv2.subtract
    for k0 in range(0, n, step):
        k1 = min(n, k0 + step)
        m = k1 - k0
        mh = m * hp
        if disp is not None:
            R = _rho_at_disp(disp[k0:k1].astype(F32)[:, None, None], A0, cn_p, F32(B[0]), cap_p)
        else:
            R = rhos[k0:k1].astype(F32)[:, None, None]
        inv, ub, vb = (np.empty((m, hp, w), F32) for _ in range(3))
        # (a per-pixel rho of +inf, a displacement the pixel never reaches: its map is NaN, out of view below)
        with np.errstate(invalid="ignore", divide="ignore", over="ignore"):
            np.add(A0, B[0] * R, out=inv)
            np.divide(F32(1.0), inv, out=inv)
            np.multiply(np.add(P1, Q1 * R, out=ub), inv, out=ub)
            np.multiply(np.add(P2, Q2 * R, out=vb), inv, out=vb)
        ub2, vb2 = ub.reshape(mh, w), vb.reshape(mh, w)
        good = cv2.bitwise_and(cv2.inRange(ub2, 0.0, float(wb - 1)), cv2.inRange(vb2, 0.0, float(hb - 1)))
        if not float(inv.min()) > 0:
            good &= (inv.reshape(mh, w) > 0).view(np.uint8)
        bw = cv2.remap(b, ub2, vb2, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)
        mb = _box(bw, win)
        vbb = _box(mul(bw, bw), win)
        sub(vbb, mul(mb, mb), dst=vbb)
        cab = _box(mul(bw, ap_t[:mh]), win)
        sub(cab, mul(ma_t[:mh], mb), dst=cab)
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
    kf, cbest = wta(_sgm(cost, a, sgm_p1, sgm_p2, sgm_tau) if sgm_p2 > 0 else cost, cost)
    conf = np.clip(1.0 - cbest, 0.0, 1.0) ** 2 * tex
    if disp is not None:
        D = np.interp(kf.ravel(), np.arange(n), disp).reshape(h, w).astype(F32)
        rho = _rho_at_disp(D, emap.A0, cn, F32(B[0]), cap)
    else:
        rho = np.interp(kf.ravel(), np.arange(n), rhos).reshape(h, w).astype(F32)
    return rho, conf.astype(F32)


def wta(agg: np.ndarray, cost: np.ndarray):
    """Winner-take-all over axis 0 of agg with a parabola sub-sample fit: fractional index and the (raw) cost of the
    winner."""
    n = agg.shape[0]
    shape = agg.shape[1:]
    flat = agg.reshape(n, -1)
    best = flat.min(axis=0)
    kbest = (flat == best).argmax(axis=0)            # the first minimum
    ar = np.arange(best.size)
    cbest = cost.reshape(n, -1)[kbest, ar]
    cm = flat[np.maximum(kbest - 1, 0), ar]
    cp = flat[np.minimum(kbest + 1, n - 1), ar]
    curv = cm - 2 * best + cp
    with np.errstate(divide="ignore", invalid="ignore"):
        off = np.where((curv > 1e-6) & (kbest > 0) & (kbest < n - 1), 0.5 * (cm - cp) / curv, 0.0)
    return (kbest + np.clip(off, -0.5, 0.5)).reshape(shape), cbest.reshape(shape)


# ---------------------------------------------------------------- the Gauss-Newton steps

class Level:
    """A level in OpenCV's terms, built from dense._Level's inputs: a's gradient (cv2.Scharr), b with its gradient
    and an in-view channel as one 4-channel warp source, and the affine maps (dense._Level: row part rw, column part
    kc) as full images."""

    def __init__(self, lv):
        self.ia, self.ib, self.h, self.w = lv.ia, lv.ib, lv.h, lv.w
        self.B0, self.Q1, self.Q2, self.rho_hi = lv.B0, lv.Q1, lv.Q2, lv.rho_hi
        full = [np.matmul(np.stack([np.ones(lv.h, F32), kc], 1), np.stack([rw, np.ones(lv.w, F32)]))
                for rw, kc in zip(lv.rw, lv.kc)]      # rw[i] + kc[i] per pixel, exactly
        self.A0, self.P1, self.P2, self.C1, self.C2 = full[:5]
        self.cap = np.clip(full[5], F32(0), self.rho_hi) if lv.use_cap else None
        self.cap_binds = lv.use_cap and float(lv.rw[5].min()) + float(lv.kc[5].min()) < self.rho_hi
        self.gxa, self.gya = _grad(lv.ia)
        gx, gy = _grad(lv.ib)
        self.b4 = cv2.merge([lv.ib, gx, gy, np.ones_like(lv.ib)])

    def warp(self, rho):
        """1/den and the warped [I_b, gx_b, gy_b, in-view] at rho (zero outside b)."""
        inv = cv2.scaleAdd(rho, float(self.B0), self.A0)
        np.divide(F32(1.0), inv, out=inv)
        ub = cv2.multiply(cv2.scaleAdd(rho, float(self.Q1), self.P1), inv)
        vb = cv2.multiply(cv2.scaleAdd(rho, float(self.Q2), self.P2), inv)
        wv = cv2.remap(self.b4, ub, vb, cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT, borderValue=0)
        return inv, cv2.split(wv)

    def residual_at_infinity(self):
        """I_b warped at rho = 0 (the rotation alone) minus I_a, NaN where that leaves b (or lies behind it)."""
        ub = cv2.divide(self.P1, self.A0)
        vb = cv2.divide(self.P2, self.A0)
        if not float(self.A0.min()) > 0:
            ub[self.A0 <= 0] = -1e6
        r0 = cv2.remap(self.ib, ub, vb, cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT, borderValue=float("nan"))
        return cv2.subtract(r0, self.ia)


_LEVELS = weakref.WeakKeyDictionary()


def _level(lv) -> Level:
    if lv not in _LEVELS:
        _LEVELS[lv] = Level(lv)
    return _LEVELS[lv]


def shift_windows(sh: int, ratio, H, g, S0, S1, Sq, Q, *extra) -> None:
    """Shiftable windows, in place on the window means: each pixel takes the sums of the window shifted sh pixels
    left or right (clamped at the image border) instead of its centred one where that one fits the linearised model
    with less than ``ratio`` times the centred window's cost. Cost: the weighted residual left after the window's
    least-squares solution (rho and the brightness offset), per unit weight: (Q - Sq^2 / S0 - g'^2 / H') / S0,
    g' = g - Sq S1 / S0, H' = H - S1^2 / S0. A tie takes the left one. ``extra`` planes (the slanted window's sums)
    move with the five."""
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
    right = cr < cl
    take = np.where(right, cr, cl) < ratio * c0
    for a in planes[:5] + extra:
        np.copyto(a, np.where(right, a[:, cols[1]], a[:, cols[0]]), where=take)


def infinity_ambiguous(L: Level, r2, mf, win: int) -> np.ndarray:
    """Does a point at infinity explain the window at least as well as the estimate (r2: the squared residual at the
    estimate, mf: where that is in view of b)? Both sums over the pixels where both are in view (none: yes)."""
    r0 = L.residual_at_infinity()
    both = np.isfinite(r0) & (mf > 0)
    r0s = np.where(both, r0 * r0, F32(0)).astype(F32)
    return _box(r0s, win) <= _box(np.where(both, r2, F32(0)).astype(F32), win)


def gauss_newton_step(lv, rho, new, sigma: float, steps, shift_px: int, fin=None, inf_out=None,
                      inf_mask=None) -> None:
    """dense._gauss_newton_step with whole-image OpenCV / numpy operations."""
    L = _level(lv)
    mul, add, sub = cv2.multiply, cv2.add, cv2.subtract
    win = steps.window
    R = rho
    inv, (Ib, gxb, gyb, mask) = L.warp(R)
    r = sub(Ib, L.ia)
    # J = grad I . d(u_b, v_b)/d rho with the gradient averaged over both images (C1, C2 are halved)
    J = mul(add(gxb, L.gxa), L.C1)
    cv2.accumulateProduct(add(gyb, L.gya), L.C2, J)
    inv2 = mul(inv, inv)
    mul(J, inv2, dst=J)
    c2 = cv2.accumulateSquare(L.C2, mul(L.C1, L.C1))
    # Huber weights min(1, k sigma / |r|) times the in-view mask
    ks = F32(max(steps.huber_k * sigma, 1e-6))
    wgt = np.maximum(np.abs(r), ks)
    cv2.divide(mask, wgt, dst=wgt, scale=float(ks))
    wJ = mul(wgt, J)
    q = sub(mul(J, R), r)
    H = _box(mul(wJ, J), win)
    g = _box(mul(wJ, q), win)
    # the brightness offset per window eliminated (Schur complement)
    S0 = _box(wgt, win)
    S0 += F32(1e-6)
    S1 = _box(wJ, win)
    Sq = _box(mul(wgt, q), win)
    # the slanted window (dense._slant_shape: S, A): rho_j = rho_c + A_c (S_j - S_c) over the window of centre c
    S, M = dense._slant_shape(R, steps)
    if S.size:      # the weight of the slant per centre: 1 where M / S_c <= 2 curv, 0 from 4 curv on
        A = np.clip(2.0 - M / (2.0 * steps.slant_curv * np.maximum(S, 1e-12)), 0.0, 1.0).astype(F32)
    extra = (_box(mul(mul(wJ, J), S), win), _box(mul(wJ, S), win)) if S.size else ()
    if shift_px > 0 and H.shape[1] > 2 * shift_px:
        shift_windows(shift_px, steps.shift_ratio, H, g, S0, S1, Sq, _box(mul(mul(wgt, q), q), win), *extra)
    if extra:     # J_j rho_c = q_j - A_c J_j (S_j - S_c): the window means of wJ q and w q change
        JJS, JS = extra
        sub(g, mul(A, sub(JJS, mul(S, H))), dst=g)
        sub(Sq, mul(A, sub(JS, mul(S, S1))), dst=Sq)
    wsum = S0.copy()
    S1n = cv2.divide(S1, S0)
    sub(g, mul(Sq, S1n), dst=g)
    sub(H, mul(S1, S1n), dst=H)
    E2 = mul(c2, mul(inv2, inv2))
    # Levenberg: (H + lam) rho' = g + lam rho, lam = lam_c E2
    lam_c = float(4.0 * sigma * sigma * steps.lam_k)
    cv2.divide(cv2.scaleAdd(mul(E2, R), lam_c, g), cv2.scaleAdd(E2, lam_c, H), dst=new)
    np.maximum(new, F32(0), out=new)
    np.minimum(new, L.cap if L.cap_binds else L.rho_hi, out=new)
    mf = cv2.threshold(mask, 0.999, 1.0, cv2.THRESH_BINARY)[1]
    if fin is None:
        if inf_out is not None:
            rm = mul(r, mf)
            inf_out[:] = infinity_ambiguous(L, mul(rm, rm), mf, win)
        return
    # --- the final step: uncertainty, flags and classification
    d = sub(new, R)
    trunc = mul(mul(d, d), E2) > fin.trunc2
    if not float(inv.min()) > 0:
        mul(mf, cv2.threshold(inv, 0.0, 1.0, cv2.THRESH_BINARY)[1], dst=mf)
    G = mul(L.gxa, L.gxa)
    cv2.accumulateSquare(L.gya, G)
    mul(G, mf, dst=G)
    G3 = _box(G, steps.occ_window)
    G = _box(G, win)
    r2 = mul(mul(r, r), mf)
    if fin.inf_test:
        amb = (inf_mask != 0) if inf_mask is not None else infinity_ambiguous(L, r2, mf, win)
    R2 = _box(r2, steps.occ_window)
    std = fin.std
    with np.errstate(divide="ignore", invalid="ignore"):
        if fin.noise_info:      # the information the noise's own gradients put into H is none about rho
            H = cv2.scaleAdd(mul(E2, wsum), -float(fin.noise_G), H)
            np.maximum(H, F32(1e-12), out=H)
        np.divide(fin.var_k, H, out=std)
        std += np.divide(fin.floor2, E2)
        np.sqrt(std, out=std)
        orient = np.divide(H, mul(E2, G))     # share of the gradient energy along the epipolar direction
    Mx = _box(mul(L.gxa, mf), win)
    My = _box(mul(L.gya, mf), win)
    low = sub(sub(G, mul(Mx, Mx)), mul(My, My)) < fin.low_thr
    occ = R2 > G3 * fin.occ_px2 + fin.occ_thr
    oov = (mf == F32(0)) | occ
    ill = ~(orient >= fin.orient_min) & ~low
    if fin.inf_test:
        amb &= new > F32(2.0) * std
        ill |= amb
        fin.amb[:] = amb
    flags = fin.flags
    np.multiply(oov.view(np.uint8), np.uint8(OUT_OF_VIEW), out=flags)
    flags |= low.view(np.uint8) * np.uint8(LOW_TEXTURE)
    flags |= ill.view(np.uint8) * np.uint8(ILL_CONDITIONED)
    flags |= trunc.view(np.uint8) * np.uint8(TRUNCATION)
    flags |= occ.view(np.uint8) * np.uint8(OCCLUDED)
    nv, ni = classify_into(new, std, flags, fin.rng, fin.conf, rho_far=fin.rho_far, max_rel_std=fin.max_rel_std)
    fin.n_val += nv
    fin.n_inf += ni


def residual_noise(lv, rho, final: bool = True, step: int = 3):
    """dense._residual_noise: the residual on every step-th row and column (cv2.remap of the warp source), its
    robust noise over all and over the in-view pixels."""
    L = _level(lv)
    sr, sc = slice(0, L.h, step), slice(0, L.w, step)
    rs = np.ascontiguousarray(rho[sr, sc])
    inv = rs * L.B0
    inv += L.A0[sr, sc]
    np.divide(F32(1.0), inv, out=inv)
    ub = (rs * L.Q1 + L.P1[sr, sc]) * inv
    vb = (rs * L.Q2 + L.P2[sr, sc]) * inv
    wv = cv2.remap(L.b4, ub, vb, cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT, borderValue=0)
    r = wv[..., 0] - L.ia[sr, sc]
    if not final:
        return _robust_sigma(r, step=1), None
    inview = (wv[..., 3] > F32(0.999)) & (inv > 0)
    return _robust_sigma(r, step=1), _robust_sigma(r, inview, step=1)


# --- the window model's error (dense._apply_model_error, _dense_kernels.model_error_finish) in numpy


def minmod_slope(r: np.ndarray, k: int, axis: int) -> np.ndarray:
    """Per pixel the slope of r along ``axis`` from its two one-sided differences over k pixels (fewer at the
    border): the smaller in magnitude where they agree in sign, 0 where they do not (the minmod limiter)."""
    n = r.shape[axis]
    idx = np.arange(n)
    shp = [1, 1]
    shp[axis] = n
    hi, lo = np.minimum(idx + k, n - 1), np.maximum(idx - k, 0)
    with np.errstate(divide="ignore", invalid="ignore"):
        sf = (np.take(r, hi, axis=axis) - r) / (hi - idx).reshape(shp)
        sb = (r - np.take(r, lo, axis=axis)) / (idx - lo).reshape(shp)
    sf = np.where(np.isfinite(sf), sf, sb)
    sb = np.where(np.isfinite(sb), sb, sf)
    out = np.where(np.abs(sf) < np.abs(sb), sf, sb)
    return np.where(sf * sb > 0, out, 0).astype(F32)


def window_centroid(lv, rho, window: int):
    """Offset (ox, oy) of each window's effective centre, sum_j W_j (x_j - x_c) / sum_j W_j, W_j = J_j (J_j -
    mean J), J = grad I_a . (C1, C2) / den^2 at rho (box filters with a ramp kernel), clipped to the window."""
    a0 = lv.rw[0][None, :] + lv.kc[0][:, None]
    c1 = lv.rw[3][None, :] + lv.kc[3][:, None]
    c2 = lv.rw[4][None, :] + lv.kc[4][:, None]
    with np.errstate(divide="ignore", invalid="ignore", over="ignore"):
        den = a0 + lv.B0 * np.nan_to_num(rho, nan=0.0, posinf=0.0)
        J = ((lv.gxa * c1 + lv.gya * c2) / (den * den)).astype(F32)
    J = np.where(np.isfinite(J), J, F32(0)).astype(F32)
    box = np.full(window, 1.0 / window, F32)
    ramp = ((np.arange(window) - window // 2) / window).astype(F32)
    m1 = _box(J, window)
    m0 = _box(J * J, window) - m1 * m1
    h = window // 2
    offs = []
    for kx, ky in ((ramp, box), (box, ramp)):
        r2 = cv2.sepFilter2D(J * J, -1, kx, ky, borderType=cv2.BORDER_REFLECT)
        r1 = cv2.sepFilter2D(J, -1, kx, ky, borderType=cv2.BORDER_REFLECT)
        with np.errstate(divide="ignore", invalid="ignore"):
            o = (r2 - m1 * r1) / m0
        offs.append(np.clip(np.where(np.isfinite(o), o, 0), -h, h).astype(F32))
    return offs[0], offs[1]
