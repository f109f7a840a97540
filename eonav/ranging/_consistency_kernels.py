"""Numba kernel of the left-right check (``eonav.ranging.consistency``): one pass over the pixels of a. The two
pairs' epipolar terms (eqs. 24-26: A = R m, den = A0 + B0 rho, the map's derivative C / den^2) are computed per
pixel from the cameras and the relative pose instead of read from ``EpipolarMap`` arrays; tests/consistency_reference.py
holds the numpy formulation on ``EpipolarMap`` that tests/test_consistency.py checks it against."""
from __future__ import annotations

import math

import numpy as np
from numba import njit

from eonav.ranging.rangemap import FILLED, VALID

_JIT = dict(cache=True, fastmath=False, nogil=True, error_model="numpy")
_VALID = np.uint8(VALID)
_FILLED = np.uint8(FILLED)
_VF = np.uint8(VALID | FILLED)


@njit(**_JIT)
def _b_terms(rho_b, std_b, flags_b, Rt, tt, cam_b, cam_a, floor_px, rb_out, var_out, floor_out):
    """Per pixel of b: its rho where it measured one (VALID, not FILLED; NaN elsewhere), its variance, and the floor
    in rho_b: floor_px over the pair b -> a's sensitivity |C| / den^2 at rho_b (Rt, tt: the pose of b in a)."""
    hb, wb = rho_b.shape
    fxb, fyb, cxb, cyb = cam_b[0], cam_b[1], cam_b[2], cam_b[3]
    fxa, fya = cam_a[0], cam_a[1]
    for y in range(hb):
        n2 = (y - cyb) / fyb
        for x in range(wb):
            rb = rho_b[y, x]
            sb = std_b[y, x]
            if not (math.isfinite(rb) and math.isfinite(sb)) or (flags_b[y, x] & _VF) != _VALID:
                rb_out[y, x] = np.nan
                continue
            n1 = (x - cxb) / fxb
            B0 = Rt[0, 0] + Rt[0, 1] * n1 + Rt[0, 2] * n2
            B1 = Rt[1, 0] + Rt[1, 1] * n1 + Rt[1, 2] * n2
            B2 = Rt[2, 0] + Rt[2, 1] * n1 + Rt[2, 2] * n2
            c1 = fxa * (tt[1] * B0 - tt[0] * B1)
            c2 = fya * (tt[2] * B0 - tt[0] * B2)
            d = B0 + tt[0] * rb
            rb_out[y, x] = rb
            var_out[y, x] = sb * sb
            floor_out[y, x] = floor_px * d * d / math.sqrt(c1 * c1 + c2 * c2)


@njit(**_JIT)
def check(rho_a, std_a, flags_a, rho_b, std_b, flags_b, R_ba, t_ba, cam_a, cam_b, k, floor_px, farther, bad, checked):
    """bad / checked (uint8, a's grid, written): the pixels of a whose estimate b contradicts, and those b could
    judge; farther: only where b sees farther than a's estimate (b sees through it). cam_a / cam_b: float64 (fx, fy, cx, cy); R_ba, t_ba: float64 pose of a in b (X_b = R X_a + t)."""
    ha, wa = rho_a.shape
    hb, wb = rho_b.shape
    fxa, fya, cxa, cya = cam_a[0], cam_a[1], cam_a[2], cam_a[3]
    fxb, fyb, cxb, cyb = cam_b[0], cam_b[1], cam_b[2], cam_b[3]
    Rt = R_ba.T.copy()                  # the pair b -> a: X_a = R^T X_b - R^T t
    tt = -(Rt @ t_ba)
    rb_ = np.empty((hb, wb), np.float64)
    vb_ = np.empty((hb, wb), np.float64)
    fb_ = np.empty((hb, wb), np.float64)
    _b_terms(rho_b, std_b, flags_b, Rt, tt, cam_b, cam_a, floor_px, rb_, vb_, fb_)
    k2 = k * k
    for i in range(ha):
        m2 = (i - cya) / fya
        for j in range(wa):
            bad[i, j] = 0
            checked[i, j] = 0
            r = rho_a[i, j]
            s = std_a[i, j]
            if not (math.isfinite(r) and math.isfinite(s)) or (flags_a[i, j] & _FILLED) != 0:
                continue
            m1 = (j - cxa) / fxa
            A0 = R_ba[0, 0] + R_ba[0, 1] * m1 + R_ba[0, 2] * m2
            A1 = R_ba[1, 0] + R_ba[1, 1] * m1 + R_ba[1, 2] * m2
            A2 = R_ba[2, 0] + R_ba[2, 1] * m1 + R_ba[2, 2] * m2
            den = A0 + t_ba[0] * r
            if not den > 0:
                continue
            inv = 1.0 / den
            ub = cxb + fxb * (A1 + t_ba[1] * r) * inv
            vb = cyb + fyb * (A2 + t_ba[2] * r) * inv
            if not (ub > -1.0 and ub < wb and vb > -1.0 and vb < hb):
                continue
            x0 = int(ub + 1.0) - 1            # floor (ub > -1)
            y0 = int(vb + 1.0) - 1
            pred = r * inv                    # rho_a / den: the point's rho seen from b
            ps = A0 * inv * inv * s           # A0 / den^2 sigma_a
            pv = ps * ps
            usable = False
            agree = False
            for c in range(4):                # the four pixels of b around the match
                y = y0 + (c >> 1)
                x = x0 + (c & 1)
                if y < 0 or y >= hb or x < 0 or x >= wb:
                    continue
                rb = rb_[y, x]
                if rb != rb:                  # NaN: b measured nothing there
                    continue
                usable = True
                d = pred - rb                   # > 0: b sees farther than a's estimate
                e = (d if farther else abs(d)) - fb_[y, x]   # difference - floor <= k sqrt(var_a' + var_b)
                if e <= 0.0 or e * e <= k2 * (pv + vb_[y, x]):
                    agree = True
            if usable:
                checked[i, j] = 1
                if not agree:
                    bad[i, j] = 1
