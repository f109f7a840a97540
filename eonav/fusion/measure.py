"""The fusion's default measurement of a pair: the dense method (without its own fill) after two checks of the pair
that one pair alone does not need but a filter fusing many does.

1. Brightness (``eonav.ranging.photometric``): image b brought onto image a's brightness by a robust affine fit
   (exposure / gain change), when the change is worth correcting.
2. Pose (``eonav.ranging.tracks``): the shift s (px) that the pair's pose error puts on its sparse tracks, measured
   across the epipolar lines. The dense method searches along the lines, so the same error along them moves its
   match by about as much, at every pixel alike, whatever the texture: a pixel error its own sigma (image noise
   through the window's gradients) does not hold. Every pixel's sigma of rho gets it in quadrature,

       sigma^2 = sigma_dense^2 + (s / |d(u_b, v_b)/d rho|)^2,

   the sensitivity of eqs. (25)-(26) at the measured rho (``add_pose_sigma``). A filter that took each
   pair's sigma at its word would fuse the pairs' pose errors as if they were independent image noise: a pair of a
   few pixels of parallax with a pixel of pose error would count as a good one.
3. Pose along the lines (``state_shift_px``, applied by the fusion runner, which holds the state): where the fused
   state knows the tracks' points well, each point has one place in b under the pair's pose, and the tracks'
   offsets from those places show the pose error's shift along the lines too; what exceeds the across-line shift
   enters the sigma the same way.
4. The sigma against the state (``innovation_scale``, applied by the runner last): where the predicted state is
   confident, a measurement's innovations x - mu must spread as sqrt(tau^2 + s^2) says. Where they spread wider,
   the pair's sigma tau misses an error the checks above do not model (the rest of a pose error, a rolling
   shutter, a lighting change) and is scaled by the c >= 1 that makes the innovations' robust spread 1; never
   scaled down (the state shares the pair's older frame: its innovations understate the error).

The tracks cost a few milliseconds per pair (``track_points``; the pair the scheduler's pose check tracked already is
not tracked again, ``recent_tracks``, nor its shift fitted again, ``recent_pose_shift``; each frame's tracking level,
corners and window means are computed once for the pairs it is in, ``ImageMemo``, ``recent_means``); the figures
are in docs/methods.md.
"""
from __future__ import annotations

import math

import numpy as np

from eonav.geometry.camera import View, pair_geometry
from eonav.fusion.state import F32, optional_kernels
from eonav.ranging.methods._common import EpipolarMap
from eonav.ranging.photometric import match_brightness, recent_means
from eonav.ranging.rangemap import RangeResult
from eonav.ranging.tracks import median_1d, recent_pose_shift, recent_tracks, tukey_weights


def add_pose_sigma(res: RangeResult, geo, shift_px: float) -> None:
    """sigma^2 += (shift_px / sensitivity)^2 in ``res.inv_range_std_per_m`` (in place) at every pixel with a
    finite rho; nothing when the shift is not finite or zero. The sensitivity is |C| / den^2 of the pair's
    ``EpipolarMap`` on the map's grid (den = A0 + B0 rho). With numba one pass over the pixels (``_kernels.pose_sigma``,
    the same values as ``_pose_sigma_numpy``) instead of the map's arrays and a dozen array passes."""
    if not (math.isfinite(shift_px) and shift_px > 0):
        return
    K = optional_kernels()
    rho, std = res.inv_range_per_m, res.inv_range_std_per_m
    if K is None or not (rho.flags.c_contiguous and std.flags.c_contiguous):
        _pose_sigma_numpy(rho, std, geo, shift_px)
        return
    h, w = rho.shape
    ca, cb = geo.cam_a, geo.cam_b
    m1 = (np.arange(w, dtype=np.float64) - ca.cx) / ca.fx       # EpipolarMap.build's row and column parts
    m2 = (np.arange(h, dtype=np.float64) - ca.cy) / ca.fy
    R = np.asarray(geo.R_ba, float)
    ra = (R[:, :1] + R[:, 1:2] * m1[None, :]).astype(F32)
    cm = (R[:, 2:3] * m2[None, :]).astype(F32)
    K.pose_sigma(rho, std, ra, cm, np.asarray(geo.t_ba_m, float).astype(F32), F32(cb.fx), F32(cb.fy),
                 F32(shift_px))


def _pose_sigma_numpy(rho, std, geo, shift_px: float) -> None:
    """``add_pose_sigma``'s arithmetic on the ``EpipolarMap``'s arrays (the reference of ``_kernels.pose_sigma``)."""
    em = EpipolarMap.build(geo, 0, rho.shape, (geo.cam_b.height, geo.cam_b.width))
    with np.errstate(divide="ignore", invalid="ignore", over="ignore"):
        den = em.A0 + em.B[0] * rho
        extra = np.float32(shift_px) * den * den / np.hypot(em.C1, em.C2)      # shift / (|C| / den^2)
        np.copyto(std, np.sqrt(std * std + extra * extra).astype(np.float32),
                  where=np.isfinite(rho) & np.isfinite(std) & (den > 0))


def state_shift_px(rho_state: np.ndarray, var_state: np.ndarray, n_state: np.ndarray, geo, tracks,
                   min_fused: int = 2, max_pred_px: float = 0.3, min_tracks: int = 20) -> float:
    """Length (px of b) of the shift that the pair's pose error puts on its matches, ALONG the epipolar lines too:
    each track's point of image a, at the fused state's inverse range of its cell (state on a's grid), has one place
    in b under the pair's pose; the 2-vector s fitted robustly (Tukey IRLS) to the tracks' offsets from those places
    is the pose error's shift. Only cells of at least ``min_fused`` measurements whose 1-sigma moves the place by
    at most ``max_pred_px`` count. ``pose_shift_px`` sees only s's part across the lines: a match anywhere on its
    line fits some range. NaN with fewer than ``min_tracks`` such tracks."""
    if len(tracks) == 0:
        return float("nan")
    pa, pb = tracks.pts_a.astype(np.float64), tracks.pts_b.astype(np.float64)
    h, w = rho_state.shape
    i, j = np.rint(pa[:, 1]).astype(int), np.rint(pa[:, 0]).astype(int)
    inside = (i >= 0) & (i < h) & (j >= 0) & (j < w)
    pa, pb, i, j = pa[inside], pb[inside], i[inside], j[inside]
    rho, sd = rho_state[i, j].astype(np.float64), np.sqrt(var_state[i, j].astype(np.float64))
    ok = np.isfinite(rho) & np.isfinite(sd) & (rho >= 0) & (n_state[i, j] >= min_fused)
    pa, pb, rho, sd = pa[ok], pb[ok], rho[ok], sd[ok]
    if len(rho) < min_tracks:
        return float("nan")
    cb = geo.cam_b
    A = geo.point_rays(pa)
    t = np.asarray(geo.t_ba_m, float)[:, None]

    def place(r):                            # eqs. (25)-(26) at each point's rho
        X = A + r[None, :] * t
        with np.errstate(divide="ignore", invalid="ignore"):
            return np.stack([cb.cx + cb.fx * X[1] / X[0], cb.cy + cb.fy * X[2] / X[0]], 1)

    p0 = place(rho)
    spread = np.linalg.norm(place(rho + sd) - p0, axis=1)
    keep = np.isfinite(spread) & (spread <= max_pred_px) & np.all(np.isfinite(p0), axis=1)
    r = (pb - p0)[keep]
    if len(r) < min_tracks:
        return float("nan")
    s = np.median(r, axis=0)
    for _ in range(8):
        d = np.linalg.norm(r - s, axis=1)
        wt = tukey_weights(d, 0.05)
        if wt.sum() < min_tracks / 2:
            return float("nan")
        s = (wt[:, None] * r).sum(0) / wt.sum()
    return float(np.hypot(*s))


def innovation_scale(rho_m: np.ndarray, std_m: np.ndarray, measured: np.ndarray, rho_state: np.ndarray,
                     var_state: np.ndarray, confident: np.ndarray, min_cells: int = 500, max_cells: int = 4096,
                     max_scale: float = 10.0) -> float:
    """The factor c >= 1 by which a measurement's sigma falls short of its innovations against the predicted state:
    over the pixels both ``measured`` and ``confident`` in the state, z = (x - mu) / sqrt(c^2 tau^2 + s^2) has a
    robust spread (1.4826 MAD) of 1 (Brent's root on c; at most ``max_cells`` pixels, an even stride over them). 1
    when the spread at c = 1 is at most 1 or fewer than ``min_cells`` pixels qualify; at most ``max_scale``."""
    from scipy.optimize import brentq
    sel = np.flatnonzero(measured & confident)
    if sel.size < min_cells:
        return 1.0
    sel = sel[:: max(1, sel.size // max_cells)]
    d = rho_m.ravel()[sel].astype(np.float64) - rho_state.ravel()[sel]
    t2 = np.square(std_m.ravel()[sel].astype(np.float64))
    s2 = var_state.ravel()[sel].astype(np.float64)

    def excess(c: float) -> float:                       # robust spread of z at c, minus 1: falls as c grows
        z = d / np.sqrt(c * c * t2 + s2)
        return 1.4826 * median_1d(np.abs(z - median_1d(z))) - 1.0

    if not excess(1.0) > 0.0:
        return 1.0
    if excess(max_scale) > 0.0:
        return float(max_scale)
    return float(brentq(excess, 1.0, max_scale, xtol=1e-4))


def checked_dense(view_a: View, view_b: View, *, brightness: bool = True, pose_sigma: bool = True,
                  **dense_params) -> RangeResult:
    """The dense method on (a, b) without its fill, after the brightness match, its sigma with the pose term
    (module docstring); ``res.info["pair_check"]``: the brightness fit and the pose shift."""
    from eonav.ranging.methods.dense import locate_dense
    tracks = recent_tracks(view_a.image, view_b.image) if (brightness or pose_sigma) else None
    check = {}
    if brightness:
        view_b, fit = match_brightness(view_a, view_b, tracks, means=recent_means)
        check.update(gain=fit.gain, offset=fit.offset, brightness_used=fit.used, brightness=fit.reason)
    res = locate_dense(view_a, view_b, fill=False, **dense_params)
    if pose_sigma:
        geo = pair_geometry(view_a, view_b)
        shift = recent_pose_shift(geo, tracks)
        add_pose_sigma(res, geo, shift)
        check.update(pose_shift_px=shift, tracks=len(tracks))
    res.info["pair_check"] = check
    return res


__all__ = ["checked_dense", "add_pose_sigma", "state_shift_px", "innovation_scale"]
