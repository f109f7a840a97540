"""Baselines: OpenCV DIS optical flow + triangulation with the known motion, and OpenCV StereoSGBM for
rectified stereo pairs. They exist to be beaten by the direct method ("dense") on the same pairs.

Triangulation (locate_dis): the flow gives the match (u_b, v_b) of every pixel of a. With the pose known,
the exact cross-multiplied eqs. (25)-(26),

    (u_b - cx_b)(A0 + B0 rho) = fx_b (A1 + B1 rho),   (v_b - cy_b)(A0 + B0 rho) = fy_b (A2 + B2 rho),

are two linear equations a_u rho = b_u, a_v rho = b_v in the inverse range rho; least squares gives
rho = (a_u b_u + a_v b_v) / (a_u^2 + a_v^2). Dividing by den = A0 + B0 rho turns both into pixel units:
sqrt(a_u^2 + a_v^2) / den is the sensitivity |d(u_b, v_b)/d rho| and the residual perpendicular to the
epipolar direction (the epipolar-consistency error, px) measures the flow error. sigma_rho = flow-noise /
sensitivity, with the flow noise from the robust spread of the epipolar residual (global) and the local
residual; confidence = rho / sigma_rho.
"""
from __future__ import annotations

import time

import cv2
import numpy as np

from eonav import InputError
from eonav.geometry.camera import View, pair_geometry
from eonav.ranging.rangemap import OUT_OF_VIEW, RangeResult
from eonav.ranging.methods._common import F32, classify, far_inverse_range, no_motion_result, rectified_stereo_baseline, to_u8

DIS_PRESETS = {"ultrafast": cv2.DISOPTICAL_FLOW_PRESET_ULTRAFAST, "fast": cv2.DISOPTICAL_FLOW_PRESET_FAST,
               "medium": cv2.DISOPTICAL_FLOW_PRESET_MEDIUM}


def dis_flow(img_a: np.ndarray, img_b: np.ndarray, preset: str = "medium") -> np.ndarray:
    """Dense flow a -> b (H x W x 2, pixels) from OpenCV DIS on 8-bit images of equal size."""
    if preset not in DIS_PRESETS:
        raise InputError(f"unknown DIS preset {preset!r}; expected one of {sorted(DIS_PRESETS)}")
    dis = cv2.DISOpticalFlow_create(DIS_PRESETS[preset])
    return dis.calc(to_u8(img_a), to_u8(img_b), None)


def triangulate_matches(geo, ub: np.ndarray, vb: np.ndarray):
    """Least-squares inverse range from matches (u_b, v_b) of every pixel of a (exact eqs. 25-26).

    Returns rho (>= 0 where finite), sensitivity (px per 1/m at rho) and the epipolar residual (px)."""
    A0, A1, A2, B = geo.ray_terms()
    cb = geo.cam_b
    xu = ub - F32(cb.cx)
    xv = vb - F32(cb.cy)
    a_u = xu * B[0] - F32(cb.fx) * B[1]
    b_u = F32(cb.fx) * A1 - xu * A0
    a_v = xv * B[0] - F32(cb.fy) * B[2]
    b_v = F32(cb.fy) * A2 - xv * A0
    n2 = a_u * a_u + a_v * a_v
    with np.errstate(divide="ignore", invalid="ignore"):
        rho = (a_u * b_u + a_v * b_v) / n2
        rho_c = np.maximum(rho, 0)
        den = A0 + B[0] * rho_c
        sens = np.sqrt(n2) / np.abs(den)
        resid = np.abs(a_u * b_v - a_v * b_u) / np.sqrt(n2) / np.abs(den)
    rho_c = np.where(np.isfinite(rho_c), rho_c, np.nan)
    return rho_c.astype(F32), sens.astype(F32), resid.astype(F32), den.astype(F32)


def locate_dis(view_a: View, view_b: View, *, preset: str = "medium", max_rel_std: float = 0.25,
               far_parallax_px: float = 0.5, resid_window: int = 7) -> RangeResult:
    """OpenCV DIS optical flow a -> b, then per-pixel triangulation with the known relative pose."""
    t0 = time.perf_counter()
    geo = pair_geometry(view_a, view_b)
    h, w = view_a.image.shape
    if geo.baseline_m <= 1e-12:
        return no_motion_result((h, w), "dis", "zero baseline")
    img_b = view_b.image
    sx = sy = 1.0
    if img_b.shape != (h, w):   # DIS needs equal sizes: resample b onto a's size, map matches back
        sx, sy = img_b.shape[1] / w, img_b.shape[0] / h
        img_b = cv2.resize(img_b, (w, h), interpolation=cv2.INTER_AREA)
    flow = dis_flow(view_a.image, img_b, preset)
    u, v = view_a.camera.pixel_grid()
    ub = (u + flow[..., 0] + 0.5) * F32(sx) - 0.5
    vb = (v + flow[..., 1] + 0.5) * F32(sy) - 0.5
    rho, sens, resid, den = triangulate_matches(geo, ub, vb)
    # flow noise: global robust spread of the epipolar residual, raised locally where the residual is large
    fin = np.isfinite(resid)
    s_glob = float(1.4826 * np.median(resid[fin])) if fin.any() else 1.0
    s_glob = max(s_glob, 0.05)
    r2 = np.where(fin, resid * resid, 0).astype(F32)
    s_loc = np.sqrt(cv2.blur(r2, (resid_window, resid_window)))
    flow_sigma = np.sqrt(s_glob * s_glob + s_loc * s_loc)
    with np.errstate(divide="ignore", invalid="ignore"):
        std = (flow_sigma / sens).astype(F32)
    bad = np.zeros((h, w), np.uint8)
    cb = geo.cam_b
    oov = ~((ub >= 0) & (ub <= cb.width - 1) & (vb >= 0) & (vb <= cb.height - 1)) | ~(den > 0)
    bad[oov] |= OUT_OF_VIEW
    info = {"seconds": time.perf_counter() - t0, "preset": preset, "flow_sigma_px": s_glob}
    return classify(rho, std, bad_flags=bad, method="dis", rho_far=far_inverse_range(geo, far_parallax_px),
                    max_rel_std=max_rel_std, info=info)


def sgbm_disparity(img_l: np.ndarray, img_r: np.ndarray, *, max_disp: int = 64, block_size: int = 5,
                   uniqueness: int = 5, mode: int = cv2.STEREO_SGBM_MODE_SGBM_3WAY) -> np.ndarray:
    """OpenCV StereoSGBM disparity of the left image of a rectified pair (float32 px, NaN where invalid).

    max_disp is rounded up to a multiple of 16; P1/P2 follow the OpenCV sample (8/32 * block^2)."""
    nd = int(16 * np.ceil(max(16, max_disp) / 16.0))
    sg = cv2.StereoSGBM_create(minDisparity=0, numDisparities=nd, blockSize=block_size,
                               P1=8 * block_size ** 2, P2=32 * block_size ** 2, disp12MaxDiff=1,
                               uniquenessRatio=uniqueness, speckleWindowSize=100, speckleRange=2, mode=mode)
    d = sg.compute(to_u8(img_l), to_u8(img_r)).astype(F32) / 16.0
    d[d < 0] = np.nan
    return d


def locate_sgbm(view_a: View, view_b: View, *, max_disp: int | None = None, block_size: int = 5) -> RangeResult:
    """StereoSGBM on a rectified horizontal stereo pair (b to the right of a, same intrinsics, R = I):
    rho = d / (f b). Raises InputError for any other geometry."""
    geo = pair_geometry(view_a, view_b)
    fb = rectified_stereo_baseline(geo)
    if fb is None:
        raise InputError("locate_sgbm needs a rectified horizontal stereo pair (b right of a, R = I, same intrinsics)")
    f, b = fb
    h, w = view_a.image.shape
    md = max_disp if max_disp is not None else int(0.3 * w)
    d = sgbm_disparity(view_a.image, view_b.image, max_disp=md, block_size=block_size)
    rho = (d / F32(f * b)).astype(F32)
    std = np.full((h, w), 0.5 / (f * b), F32)        # nominal half-pixel disparity noise
    bad = np.where(np.isfinite(d), 0, OUT_OF_VIEW).astype(np.uint8)
    return classify(np.where(np.isfinite(rho), rho, 0).astype(F32), std, bad_flags=bad, method="sgbm",
                    rho_far=far_inverse_range(geo, 0.5), max_rel_std=np.inf, info={"f_px": f, "baseline_m": b})


__all__ = ["locate_dis", "locate_sgbm", "dis_flow", "sgbm_disparity", "triangulate_matches"]
