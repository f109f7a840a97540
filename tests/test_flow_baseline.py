"""Baselines: DIS flow + triangulation with the known motion, and StereoSGBM on rectified pairs."""
from __future__ import annotations

import numpy as np
import pytest

from test_dense import sine_texture
from eonav.geometry.camera import Camera, VehicleState, View, pair_geometry
from eonav.ranging.methods.flow_baseline import locate_dis, locate_sgbm, sgbm_disparity, triangulate_matches
from eonav.ranging.rangemap import VALID



def rectified(left, right, f=500.0, b=0.1):
    h, w = left.shape
    st = VehicleState.from_ypr([0, 0, 0], [0, 0, 0])
    ca = Camera("L", w, h, f, f, (w - 1) / 2, (h - 1) / 2, [0, 0, 0], [0, 0, 0])
    cb = Camera("R", w, h, f, f, (w - 1) / 2, (h - 1) / 2, [0, b, 0], [0, 0, 0])
    return View(ca, st, left), View(cb, st, right)


def shifted_pair(d, h=120, w=160, noise=0.5, seed=0):
    y, x = np.mgrid[0:h, 0:w].astype(np.float64)
    rng = np.random.default_rng(seed)
    left = sine_texture(x, y) + rng.normal(0, noise, (h, w)).astype(np.float32)
    right = sine_texture(x + d, y) + rng.normal(0, noise, (h, w)).astype(np.float32)   # R(u - d) = L(u)
    return left, right


def _general_pose():
    """A two-camera pair of general pose (different intrinsics, mounts and attitudes; 1.5 m of forward motion)."""
    ca = Camera("a", 64, 48, 300.0, 310.0, 31.0, 24.5, [1.0, 0.2, 0.1], np.deg2rad([1.0, -3.0, 0.5]))
    cb = Camera("b", 64, 48, 330.0, 320.0, 33.0, 22.0, [1.0, 0.6, 0.1], np.deg2rad([-0.5, -2.0, 0.0]))
    sa = VehicleState.from_ypr([0, 0, -5], np.deg2rad([2.0, 1.0, -1.0]))
    sb = VehicleState.from_ypr([1.5, -0.2, -5.1], np.deg2rad([2.5, 1.3, -0.7]))
    return pair_geometry(View(ca, sa, np.zeros((48, 64))), View(cb, sb, np.zeros((48, 64))))


def test_triangulation_exact_for_general_pose():
    """Exact matches from the forward map (eqs. 25-26, general two-camera pose, different intrinsics):
    the least-squares triangulation returns the inverse range it was built from, and a zero epipolar residual."""
    geo = _general_pose()
    rho = np.random.default_rng(0).uniform(0.01, 0.2, (48, 64)).astype(np.float32)
    ub, vb, _ = geo.map_to_b(rho)
    est, sens, resid, _ = triangulate_matches(geo, ub, vb)
    np.testing.assert_allclose(est, rho, rtol=2e-3, atol=1e-5)
    assert np.nanmax(resid) < 1e-2
    assert np.all(sens > 0)


def test_dis_on_shifted_plane():
    f, b, d = 500.0, 0.1, 6.4
    a, bv = rectified(*shifted_pair(d), f, b)
    res = locate_dis(a, bv)
    core = (slice(15, -15), slice(20, -15))
    valid = (res.flags[core] & VALID) > 0
    assert valid.mean() > 0.9
    assert abs(np.median(res.range_m[core][valid]) / (f * b / d) - 1) < 0.02   # measured < 0.5 %


def test_dis_zero_baseline_no_ranges():
    left, _ = shifted_pair(0.0)
    a, bv = rectified(left, left + 1.0, b=0.0)
    res = locate_dis(a, bv)
    assert not np.any(res.flags & VALID)
    assert np.all(np.isnan(res.range_m))


def test_sgbm_on_shifted_plane():
    f, b, d = 500.0, 0.1, 9.0
    left, right = shifted_pair(d, w=200)
    disp = sgbm_disparity(left, right, max_disp=32)
    core = disp[15:-15, 50:-15]
    assert np.isfinite(core).mean() > 0.9
    assert abs(np.nanmedian(core) - d) < 0.25
    res = locate_sgbm(*rectified(left, right, f, b), max_disp=32)
    assert abs(np.nanmedian(res.range_m[15:-15, 50:-15]) / (f * b / d) - 1) < 0.03


def test_sgbm_rejects_unrectified():
    left, right = shifted_pair(3.0)
    a, bv = rectified(left, right)
    cb = Camera("R", bv.camera.width, bv.camera.height, 500.0, 500.0, 80.0, 60.0, [0, 0.1, 0], [0.01, 0, 0])
    with pytest.raises(ValueError):
        locate_sgbm(a, View(cb, bv.state, right))


def test_triangulation_sensitivity_is_the_derivative_of_the_forward_map():
    """sens is |d(u_b, v_b)/d rho| in pixels of b (what sigma_rho = flow noise / sens rests on). Independent truth: the
    central difference of the exact forward map (map_to_b) for a pose with 1.5 m of forward motion, where the depth
    ratio den = A0 + B0 rho is 0.7 - 1.0; a sensitivity not divided by den is up to 1 / 0.7 too large."""
    geo = _general_pose()
    rho = np.random.default_rng(7).uniform(0.01, 0.2, (48, 64)).astype(np.float32)
    ub, vb, _ = geo.map_to_b(rho)
    _, sens, _, den = triangulate_matches(geo, ub, vb)
    h = np.float32(1e-3)
    up, vp, _ = geo.map_to_b(rho + h)
    um, vm, _ = geo.map_to_b(rho - h)
    fd = np.hypot((up.astype(float) - um) / (2 * h), (vp.astype(float) - vm) / (2 * h))
    assert den.min() < 0.8                      # the forward motion makes den matter here
    np.testing.assert_allclose(sens, fd, rtol=1e-3)


def test_matches_beyond_infinity_triangulate_to_zero_inverse_range():
    """Rectified pair, b 0.1 m to the right, f = 500 px: a match d px to the left is rho = d / (f b) (hand value), and
    a match 2 px to the RIGHT (flow noise on a far point, "beyond infinity") is clamped to rho = 0, the far end,
    never a negative inverse range (= a negative range, or a near one once squared by a caller)."""
    a, bv = rectified(np.zeros((20, 30)), np.zeros((20, 30)))
    geo = pair_geometry(a, bv)
    u, v = a.camera.pixel_grid()
    rho, _, resid, _ = triangulate_matches(geo, u - 5.0, v)
    np.testing.assert_allclose(rho, 5.0 / 50.0, rtol=1e-5)
    rho, _, resid, _ = triangulate_matches(geo, u + 2.0, v)
    assert np.all(rho == 0.0)
    assert np.nanmax(resid) < 1e-4


def test_sgbm_zero_disparity_is_a_valid_far_match():
    """Identical rectified images (a scene at infinity): StereoSGBM's disparity 0 is a real match, the far end, and
    must stay finite; only OpenCV's invalid value (minDisparity - 1 = -1 px) becomes NaN."""
    left, _ = shifted_pair(0.0, w=200)
    disp = sgbm_disparity(left, left, max_disp=32)
    core = disp[15:-15, 50:-15]
    assert np.isfinite(core).mean() > 0.9
    assert np.nanmax(np.abs(core)) < 0.25


def test_dis_with_a_finer_camera_b_maps_matches_back_through_pixel_centres():
    """Camera b at 2x the columns and 1.5x the rows of a (fx, fy scaled alike, pixel centres kept), on a plane at
    f b / d = 12.5 m: DIS runs on b resized to a's grid and its matches are mapped back to b's pixels through the
    pixel centres, u_b = (u + flow + 0.5) sx - 0.5. Range within 1 % (measured 0.03 %); dropping the half-pixel
    terms moves u_b by 0.5 px of b (-5.9 %), and swapping sx and sy leaves no valid pixel (measured)."""
    f, b, d, h, w, kx, ky = 500.0, 0.1, 4.0, 120, 160, 2.0, 1.5
    st = VehicleState.from_ypr([0, 0, 0], [0, 0, 0])
    cx, cy = (w - 1) / 2, (h - 1) / 2
    ca = Camera("a", w, h, f, f, cx, cy, [0, 0, 0], [0, 0, 0])
    W, H = int(w * kx), int(h * ky)
    cb = Camera("b", W, H, f * kx, f * ky, (cx + 0.5) * kx - 0.5, (cy + 0.5) * ky - 0.5, [0, b, 0], [0, 0, 0])
    rng = np.random.default_rng(0)
    y, x = np.mgrid[0:h, 0:w].astype(np.float64)
    left = sine_texture(x, y) + rng.normal(0, 0.5, (h, w))
    yb, xb = np.mgrid[0:H, 0:W].astype(np.float64)
    right = sine_texture((xb + 0.5) / kx - 0.5 + d, (yb + 0.5) / ky - 0.5) + rng.normal(0, 0.5, (H, W))
    res = locate_dis(View(ca, st, left), View(cb, st, right))
    core = (slice(15, -15), slice(20, -15))
    valid = (res.flags[core] & VALID) > 0
    assert valid.mean() > 0.9
    assert abs(np.median(res.range_m[core][valid]) / (f * b / d) - 1) < 0.01


def test_matches_of_points_behind_camera_b_are_out_of_view(monkeypatch):
    """Camera b 10 m ahead of a (forward motion), flow replaced by the exact matches of the forward map: a plane at
    20 m (depth ratio den = 1 - 10/20 = 0.5) is ranged at 20 m, but a plane at 5 m is behind camera b (den = -1, hand
    value); its mirrored matches still land inside image b and triangulate exactly to 5 m, so only the den > 0 test
    keeps these pixels from being published as VALID 5 m obstacles: all must be OUT_OF_VIEW, none VALID."""
    import eonav.ranging.methods.flow_baseline as fbm
    from eonav.ranging.rangemap import OUT_OF_VIEW
    h, w = 40, 60
    cam = Camera("c", w, h, 100.0, 100.0, (w - 1) / 2, (h - 1) / 2)
    va = View(cam, VehicleState.from_ypr([0, 0, 0], [0, 0, 0]), np.zeros((h, w)))
    vb = View(cam, VehicleState.from_ypr([10, 0, 0], [0, 0, 0]), np.zeros((h, w)))
    geo = pair_geometry(va, vb)
    u, v = cam.pixel_grid()
    for rng_m in (20.0, 5.0):
        ub, vb_, den = geo.map_to_b(np.full((h, w), 1 / rng_m, np.float32))
        np.testing.assert_allclose(den, 1 - 10 / rng_m, atol=1e-6)
        flow = np.stack([ub - u, vb_ - v], -1).astype(np.float32)
        monkeypatch.setattr(fbm, "dis_flow", lambda a, b, preset="medium": flow)
        res = fbm.locate_dis(va, vb)
        valid = (res.flags & VALID) > 0
        if rng_m == 20.0:
            assert valid.mean() > 0.2       # the image doubles in size: about its central quarter stays in view
            np.testing.assert_allclose(res.range_m[valid], 20.0, rtol=1e-3)
        else:
            assert not valid.any()
            assert np.all(res.flags & OUT_OF_VIEW)


def test_noise_free_flow_keeps_the_flow_noise_floor(monkeypatch):
    """Rectified pair (f = 100 px, b = 0.1 m) with the flow replaced by the exact matches of a 10 m plane: the epipolar
    residual is 0, yet the flow noise is floored at 0.05 px, so sigma_rho = 0.05 / (f b) = 0.005 1/m and confidence
    rho / sigma = 20 (hand values), never a zero sigma and an infinite confidence handed to the fusion."""
    import eonav.ranging.methods.flow_baseline as fbm
    h, w = 40, 60
    a, bv = rectified(np.zeros((h, w)), np.zeros((h, w)), f=100.0, b=0.1)
    geo = pair_geometry(a, bv)
    u, v = a.camera.pixel_grid()
    ub, vb_, _ = geo.map_to_b(np.full((h, w), 0.1, np.float32))
    flow = np.stack([ub - u, vb_ - v], -1).astype(np.float32)
    monkeypatch.setattr(fbm, "dis_flow", lambda a, b, preset="medium": flow)
    res = fbm.locate_dis(a, bv)
    valid = (res.flags & VALID) > 0
    assert valid.mean() > 0.8
    np.testing.assert_allclose(res.range_m[valid], 10.0, rtol=1e-4)
    np.testing.assert_allclose(res.inv_range_std_per_m[valid], 0.005, rtol=1e-3)
    np.testing.assert_allclose(res.confidence[valid], 20.0, rtol=1e-3)
