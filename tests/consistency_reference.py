"""The numpy / OpenCV formulation of the left-right check on ``EpipolarMap`` (the dense method's epipolar map),
which tests/test_consistency.py checks the numba kernel (``eonav.ranging._consistency_kernels``) against."""
from __future__ import annotations

import cv2
import numpy as np

from eonav.geometry.camera import PairGeometry
from eonav.ranging.consistency import LRCheckConfig, _check_shapes, _reverse
from eonav.ranging.methods._common import EpipolarMap
from eonav.ranging.rangemap import FILLED, VALID, RangeResult

F32 = np.float32


def inconsistent_reference(res_ab: RangeResult, res_ba: RangeResult, geo: PairGeometry,
                 cfg: LRCheckConfig = LRCheckConfig()) -> tuple[np.ndarray, np.ndarray]:
    """(inconsistent, checked): bool masks on a's grid of the pixels of ``res_ab`` (the pair a -> b of ``geo``)
    whose estimate ``res_ba`` (the pair b -> a, on b's grid) contradicts, and of those it could judge at all
    (module docstring)."""
    _check_shapes(res_ab, geo.cam_a, "a -> b")
    _check_shapes(res_ba, geo.cam_b, "b -> a")
    rho_a, std_a = res_ab.inv_range_per_m, res_ab.inv_range_std_per_m
    rho_b, std_b = res_ba.inv_range_per_m, res_ba.inv_range_std_per_m
    hb, wb = rho_b.shape
    with np.errstate(invalid="ignore", divide="ignore", over="ignore"):
        cand = np.isfinite(rho_a) & np.isfinite(std_a) & ((res_ab.flags & FILLED) == 0)
        em = EpipolarMap.build(geo, 0, rho_a.shape, (hb, wb))
        ub, vb, inv_den = em(np.where(cand, rho_a, F32(0)))
        cand &= inv_den > 0
        pred = rho_a * inv_den                                      # rho_a / den: the point's rho seen from b
        pred_var = np.square(em.A0 * inv_den * inv_den * std_a)     # (A0 / den^2 sigma_a)^2
        # b's side, per pixel of b: its rho where it measured one (NaN elsewhere), its variance, and the floor in
        # rho_b (floor_px over the pair b -> a's sensitivity at rho_b, pixels of a per 1/m)
        em_ba = EpipolarMap.build(_reverse(geo), 0, (hb, wb), rho_a.shape)
        inv_den_ba = 1.0 / (em_ba.A0 + em_ba.B[0] * rho_b)
        sens = np.hypot(em_ba.C1, em_ba.C2) * inv_den_ba * inv_den_ba
        use_b = np.isfinite(rho_b) & np.isfinite(std_b) & ((res_ba.flags & (VALID | FILLED)) == VALID)
        planes = np.dstack([np.where(use_b, rho_b, np.nan), np.square(std_b), F32(cfg.floor_px) / sens]).astype(F32)
        # the four pixels of b around q, sampled exactly (integer maps, nearest); outside b: NaN
        x0 = np.clip(np.floor(np.where(cand, ub, -4)), -4, wb + 4).astype(F32)
        y0 = np.clip(np.floor(np.where(cand, vb, -4)), -4, hb + 4).astype(F32)
        agree = np.zeros(rho_a.shape, bool)
        usable = np.zeros(rho_a.shape, bool)
        k = F32(cfg.k)
        for dy in (0, 1):
            for dx in (0, 1):
                smp = cv2.remap(planes, x0 + F32(dx), y0 + F32(dy), cv2.INTER_NEAREST,
                                borderMode=cv2.BORDER_CONSTANT, borderValue=(np.nan,) * 3)
                r, v, fl = smp[..., 0], smp[..., 1], smp[..., 2]
                ok = np.isfinite(r)
                diff = pred - r if cfg.farther else np.abs(pred - r)
                agree |= ok & (diff <= k * np.sqrt(pred_var + v) + fl)
                usable |= ok
    usable &= cand
    return usable & ~agree, usable
