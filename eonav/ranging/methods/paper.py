"""The paper's locator, faithfully: method "paper" (Menon, Chatterji & Sridhar 1993).

Per pixel of the reference image E1 (view a):

1. E_hat, dE/dx_p, dE/dy_p of both images from the causal recursive estimators, eqs. (34)-(42)
   (``eonav.ranging.derivatives``), the same estimator on both so that its delay is common;
2. k0..k5 of eq. (24) from the relative pose of the pair (``eonav.geometry.frames.k_coefficients``; eq. (23) for
   one camera over time, tests/test_geometry_paper.py);
3. a1, b1 (eqs. 29-30), c1 and the closed form eq. (28) for x_c, with c1 = E1 - E2: substituting (25)-(26) into
   (27) gives (28) exactly with that sign, so the printed (31), E2 - E1, is a transcription slip
   (tests/test_paper_method.py::test_c1_sign decides it on a synthetic scene);
4. only where the inter-frame change |c1| and the gradient |(a1, b1)| are significant; elsewhere NaN with
   LOW_TEXTURE (the paper assigned a "maximum scene depth"; we do not);
5. the eq. (7) truncation test at the estimated range (flag TRUNCATION: range kept, VALID cleared);
6. inv_range_std_per_m by first-order propagation of white image noise through the estimators and eq. (28)
   (linear in rho = 1/x_c); confidence = rho / std(rho).

The geometry is evaluated on the estimators' delayed grid and the maps shifted back by round(delay) pixels. With
fx != fy the x-rows use fx and the y-rows fy; a view b with other intrinsics is first resampled onto a virtual camera
with view a's intrinsics at view b's pose (pixels outside image b: OUT_OF_VIEW).
"""
from __future__ import annotations

import time

import numpy as np
from scipy import ndimage

from eonav import InputError
from eonav.geometry.camera import Camera, View, pair_geometry
from eonav.ranging.derivatives import estimate_derivatives, noise_gains
from eonav.geometry.frames import k_coefficients, ned_from_camera
from eonav.ranging.rangemap import (ILL_CONDITIONED, LOW_TEXTURE, OUT_OF_VIEW, TRUNCATION, VALID, RangeResult)

METHOD_NAME = "paper"


def range_eq28(a1, b1, c1, k, xp, yp, fx: float, fy: float | None = None):
    """Closed form eq. (28): returns (x_c, num, den) with x_c = num / den.

    c1 must be E1 - E2 (module docstring). k = (k0..k5) of eq. (24); xp, yp pixels from the principal
    point; fx (and fy, default fx) in pixels."""
    fy = fx if fy is None else fy
    k0, k1, k2, k3, k4, k5 = k
    Mx = fx * k4 - xp * k3
    My = fy * k5 - yp * k3
    Nx = fx * k1 - xp * k0
    Ny = fy * k2 - yp * k0
    num = k3 * c1 - a1 * Mx - b1 * My                       # eq. (28), numerator
    den = a1 * Nx + b1 * Ny - c1 * (1.0 + k0)               # eq. (28), denominator
    with np.errstate(divide="ignore", invalid="ignore"):
        xc = num / den
    return xc, num, den


def disparity(k, xp, yp, fx: float, fy: float, rho):
    """Eqs. (25)-(26) with separate fx, fy: (dx_p, dy_p) in pixels at inverse range rho."""
    k0, k1, k2, k3, k4, k5 = k
    Dn = 1.0 + k0 + k3 * rho
    with np.errstate(divide="ignore", invalid="ignore"):
        dx = (fx * k1 - xp * k0 + (fx * k4 - xp * k3) * rho) / Dn     # eq. (25)
        dy = (fy * k2 - yp * k0 + (fy * k5 - yp * k3) * rho) / Dn     # eq. (26)
    return dx, dy, Dn


def _same_intrinsics(ca: Camera, cb: Camera) -> bool:
    return (ca.width, ca.height) == (cb.width, cb.height) and np.allclose(
        [ca.fx, ca.fy, ca.cx, ca.cy], [cb.fx, cb.fy, cb.cx, cb.cy], rtol=0, atol=1e-9)


def resample_to_intrinsics(image_b: np.ndarray, cam_b: Camera, cam_a: Camera) -> np.ndarray:
    """Image of a virtual camera with cam_a's intrinsics at cam_b's pose (same rays, so exact for a
    pinhole), on cam_a's grid; outside image b it repeats b's border (``_in_camera_b`` tells a point's side)."""
    u, v = cam_a.pixel_grid()
    ub, vb = _to_camera_b(u, v, cam_a, cam_b)
    return ndimage.map_coordinates(np.asarray(image_b, np.float64), [vb, ub], order=1, mode="nearest")


def _to_camera_b(u, v, cam_a: Camera, cam_b: Camera):
    """Pixel (u, v) of the virtual camera (cam_a's intrinsics at b's pose) in camera b's own pixels (the same ray)."""
    return cam_b.cx + cam_b.fx * (u - cam_a.cx) / cam_a.fx, cam_b.cy + cam_b.fy * (v - cam_a.cy) / cam_a.fy


def _in_camera_b(u, v, cam_a: Camera, cam_b: Camera):
    """Whether the point at (u, v) of the virtual camera (cam_a's intrinsics at b's pose) lies inside image b."""
    ub, vb = _to_camera_b(u, v, cam_a, cam_b)
    return (ub >= 0) & (ub <= cam_b.width - 1) & (vb >= 0) & (vb <= cam_b.height - 1)


def _shift_back(arr, s: int, fill):
    """out[v, u] = arr[v + s, u + s] (re-register delayed estimates), ``fill`` where out of range."""
    if s == 0:
        return arr
    out = np.full_like(arr, fill)
    out[:-s, :-s] = arr[s:, s:]
    return out


def _hessian_from_gradient(gx, gy):
    """Order-1 estimators give no second derivatives: central differences of the estimated gradient
    (zero-phase, so on the same delayed grid), symmetrised."""
    gxx = np.gradient(gx, axis=1)
    gyy = np.gradient(gy, axis=0)
    gxy = 0.5 * (np.gradient(gx, axis=0) + np.gradient(gy, axis=1))
    return gxx, gxy, gyy


def locate_paper(view_a: View, view_b: View, *, bandwidth: float = 0.25, order: int = 1,
                 min_gradient: float = 2.0, min_change: float = 2.0, truncation_tol: float | None = 0.5,
                 max_range_m: float = 5000.0, noise_sigma: float = 1.0, discretisation: str = "foh",
                 combine: str = "eq40", bias: float | None = None) -> RangeResult:
    """Range x_c (metres) at every pixel of view a by the paper's method (module docstring).

    bandwidth: estimator bandwidth a, per pixel (eqs. 41-42; the paper's 5.0 had unstated units). The
    default 0.25 /px (delay 4 px) was chosen on the sim "paper" preset: it gave the most even per-vehicle
    errors; 0.5-1 is better for vehicle 1 (~1 px disparity) and much worse for vehicle 3 (~7 px), 5.0
    per pixel (no smoothing at all) is worse everywhere.
    order: 1 (eqs. 41-42, as the paper) or 2. min_gradient: |(a1, b1)| threshold, grey levels per pixel.
    min_change: |c1| threshold, grey levels. truncation_tol: eq. (7) ratio limit, None = no test.
    max_range_m: estimates beyond are discarded (NaN, ILL_CONDITIONED). noise_sigma: image noise,
    grey levels, for inv_range_std_per_m and confidence. discretisation, combine, bias: see
    eonav.derivatives.estimate_derivatives."""
    t0 = time.perf_counter()
    if not isinstance(view_a, View) or not isinstance(view_b, View):
        raise InputError("locate_paper expects two eonav.camera.View objects")
    for name, val in (("min_gradient", min_gradient), ("min_change", min_change), ("noise_sigma", noise_sigma)):
        if not (np.isfinite(val) and val >= 0):
            raise InputError(f"{name} must be finite and >= 0, got {val!r}")
    if not (max_range_m > 0):
        raise InputError(f"max_range_m must be > 0, got {max_range_m!r}")
    if truncation_tol is not None and not (truncation_tol > 0):
        raise InputError(f"truncation_tol must be > 0 or None, got {truncation_tol!r}")
    ca, cb = view_a.camera, view_b.camera
    H, W = ca.height, ca.width
    img_a = view_a.image
    same = _same_intrinsics(ca, cb)
    img_b = view_b.image if same else resample_to_intrinsics(view_b.image, cb, ca)
    pg = pair_geometry(view_a, view_b)

    # eqs. (34)-(42): the same estimator on both images (common delay)
    est = dict(bandwidth_per_px=bandwidth, order=order, discretisation=discretisation, combine=combine)
    if bias is None:     # one bias for both images, so E_hat1 - E_hat2 is unaffected by it
        lo = min(float(img_a.min()), float(img_b.min()))
        hi = max(float(img_a.max()), float(img_b.max()))
        bias = max(0.0, -lo) + max(1.0, hi - lo)
    d1 = estimate_derivatives(img_a, bias=bias, **est)
    d2 = estimate_derivatives(img_b, bias=bias, **est)
    delay = d1.delay_px
    s = int(round(delay))
    if s >= min(H, W):
        raise InputError(f"estimator delay {delay:.1f} px is larger than the image; raise the bandwidth")

    # pixel coordinates of the delayed grid (x_p = u - cx, y_p = v - cy)
    u, v = ca.pixel_grid()
    xp = u.astype(np.float64) - ca.cx - delay
    yp = v.astype(np.float64) - ca.cy - delay
    fx, fy = float(ca.fx), float(ca.fy)
    k = k_coefficients(pg.R_ba, pg.t_ba_m, xp, yp * (fx / fy), fx)       # eq. (24), m2 = y_p / fy

    a1 = 0.5 * (d1.Ex + d2.Ex)                                           # eq. (29)
    b1 = 0.5 * (d1.Ey + d2.Ey)                                           # eq. (30)
    c1 = d1.E - d2.E                                                     # eq. (27): E1 - E2 (not eq. 31)
    xc, num, den = range_eq28(a1, b1, c1, k, xp, yp, fx, fy)             # eq. (28)

    with np.errstate(divide="ignore", invalid="ignore", over="ignore"):
        rho = den / num
        dx, dy, Dn = disparity(k, xp, yp, fx, fy, rho)                   # eqs. (25)-(26)
        # noise propagation: eq. (28) is linear in rho, F = rho*G - (c1 (1 + k0) - a1 Nx - b1 Ny) = 0 with
        # G = a1 Mx + b1 My - c1 k3 = -num, so d rho = Dn (d c1 - dx d a1 - dy d b1) / G (Dn = 1 + k0 + k3 rho, the
        # depth ratio x_c,b / x_c,a), with white image noise of noise_sigma grey levels through the estimators
        gE, gdx, gdy = noise_gains(bandwidth, order, discretisation)
        var_c = 2.0 * (noise_sigma * gE) ** 2
        var_a = 0.5 * (noise_sigma * gdx) ** 2
        var_b = 0.5 * (noise_sigma * gdy) ** 2
        std_rho = np.abs(Dn) * np.sqrt(var_c + dx * dx * var_a + dy * dy * var_b) / np.abs(num)

        # eq. (7) truncation test
        if order == 2:
            hxx, hxy, hyy = d1.Exx + d2.Exx, d1.Exy + d2.Exy, d1.Eyy + d2.Eyy
        else:
            h1, h2 = _hessian_from_gradient(d1.Ex, d1.Ey), _hessian_from_gradient(d2.Ex, d2.Ey)
            hxx, hxy, hyy = h1[0] + h2[0], h1[1] + h2[1], h1[2] + h2[2]
        t7 = (d2.Ex - d1.Ex) * dx + (d2.Ey - d1.Ey) * dy + 0.5 * (hxx * dx * dx + 2 * hxy * dx * dy + hyy * dy * dy)
        first = a1 * dx + b1 * dy                                        # first-order term of eq. (6)
        trunc_ratio = np.abs(t7) / np.maximum(np.abs(first), 1e-12)

    flags = np.zeros((H, W), np.uint8)
    computed = (np.abs(c1) >= min_change) & (np.hypot(a1, b1) >= min_gradient)
    flags[~computed] |= LOW_TEXTURE
    good = computed & np.isfinite(xc) & (xc > 0) & (xc <= max_range_m) & (Dn > 0)
    flags[computed & ~good] |= ILL_CONDITIONED
    if truncation_tol is not None:
        flags[good & ~(trunc_ratio <= truncation_tol)] |= TRUNCATION
    # does the point stay in image b? (exact mapping, eqs. 25-26; index (v, u) of the delayed grid is the point
    # (u - delay, v - delay) of image a)
    ub = u - delay + dx
    vb = v - delay + dy
    out = ~((ub >= 0) & (ub <= W - 1) & (vb >= 0) & (vb <= H - 1))
    if not same:         # b resampled to a's intrinsics: the point must also lie inside b's own image
        with np.errstate(invalid="ignore"):
            out |= ~_in_camera_b(ub, vb, ca, cb)
    flags[good & out] |= OUT_OF_VIEW
    valid = good & ((flags & (TRUNCATION | OUT_OF_VIEW)) == 0)
    flags[valid] |= VALID

    range_m = np.where(good, xc, np.nan)
    rho_out = np.where(good, rho, np.nan)
    std_out = np.where(good, std_rho, np.nan)
    with np.errstate(divide="ignore", invalid="ignore"):
        conf = np.where(valid, rho / std_rho, 0.0)
    conf = np.where(np.isfinite(conf), conf, 0.0)

    # re-register to the pixel grid (undo the estimator delay by round(delay) px)
    range_m = _shift_back(range_m, s, np.nan).astype(np.float32)
    rho_out = _shift_back(rho_out, s, np.nan).astype(np.float32)
    std_out = _shift_back(std_out, s, np.nan).astype(np.float32)
    conf = _shift_back(conf, s, 0.0).astype(np.float32)
    flags = _shift_back(flags, s, LOW_TEXTURE)
    trunc_ratio = _shift_back(np.where(good, trunc_ratio, np.nan), s, np.nan).astype(np.float32)

    n = H * W
    info = dict(bandwidth_per_px=float(bandwidth), order=int(order), delay_px=float(delay), shift_px=s,
                discretisation=discretisation, combine=combine, bias=float(bias),
                coverage_computed=float(np.isfinite(range_m).sum() / n),
                coverage_valid=float(((flags & VALID) != 0).sum() / n),
                n_valid=int(((flags & VALID) != 0).sum()),
                baseline_m=pg.baseline_m, truncation_ratio=trunc_ratio,
                seconds=time.perf_counter() - t0)
    return RangeResult(range_m=range_m, confidence=conf, method=METHOD_NAME, inv_range_per_m=rho_out,
                       inv_range_std_per_m=std_out, flags=flags, info=info)


def camera_points_eq32(range_m: np.ndarray, camera: Camera) -> np.ndarray:
    """Eq. (32): (H, W, 3) camera-frame points [x_c, y_c, z_c] with y_c = x_c x_p / fx, z_c = x_c y_p / fy."""
    r = np.asarray(range_m, np.float64)
    if r.shape != (camera.height, camera.width):
        raise InputError(f"range map shape {r.shape} does not match camera {camera.height}x{camera.width}")
    _, m1, m2 = camera.rays()
    return np.stack([r, r * m1, r * m2], axis=-1)


def ned_point_cloud(result: RangeResult, view_a: View, *, valid_only: bool = True):
    """Eqs. (32)-(33): NED points (N, 3) of the finite ranges of ``result`` (VALID ones by default),
    x = x_v + T2^T (T1^T x_c + l), with the pixel indices (N, 2) as (v, u)."""
    pc = camera_points_eq32(result.range_m, view_a.camera)
    mask = np.isfinite(result.range_m)
    if valid_only and result.flags is not None:
        mask &= (result.flags & VALID) != 0
    vu = np.argwhere(mask)
    st = view_a.state
    ned = ned_from_camera(pc[mask], view_a.camera.T_cam_body, st.T_body_ned, st.position_ned_m,
                          view_a.camera.l_body_m)                       # eq. (33)
    return ned, vu
