"""The paper's motion model: eq. (23) is the one-camera case of the general two-view form (eq. 24 with
k from the relative pose), and eqs. (25)-(26) are exact perspective (hand-made point clouds).

Truth here is independent of eonav.geometry.k_coefficients: eq. (23) is coded again from the paper's
own matrices, and disparities come from projecting 3-D points with eqs. (8), (9), (12), (15)."""
import numpy as np
import pytest

from eonav.geometry.frames import (T_body_ned_from_ypr, T_cam_body_from_eps, camera_from_ned, disparity_eq25_26,
                            k_coefficients, relative_pose)
from eonav.ranging.methods.paper import disparity as disparity_fxfy

F_PX = 600.0


def _random_case(rng):
    """One camera on a vehicle at two states (a, b): small attitude change, ~2 m translation."""
    T1 = T_cam_body_from_eps(rng.uniform(-0.2, 0.2, 3))
    l_m = rng.uniform(-3, 3, 3)
    ypr_a = rng.uniform([-np.pi, -0.4, -0.4], [np.pi, 0.4, 0.4])
    ypr_b = ypr_a + rng.normal(0, 0.02, 3)
    xv_a = rng.uniform(-100, 100, 3)
    xv_b = xv_a + rng.normal(0, 1.0, 3)
    return T1, l_m, T_body_ned_from_ypr(*ypr_a), T_body_ned_from_ypr(*ypr_b), xv_a, xv_b


def _k_eq23(T1, l_m, T2, T2b, dxv, xp, yp, f):
    """Eq. (23) as printed (with l for the 'I' of eq. 21): k0..k2 = T1 dT2 T2^T T1^T [1, xp/f, yp/f];
    the terms divided by x_c give k3..k5 = T1 dT2 T2^T l - T1 (T2 + dT2) dx_v."""
    dT2 = T2b - T2
    m = np.stack([np.ones_like(xp), xp / f, yp / f])                    # 3 x N
    k012 = (T1 @ dT2 @ T2.T @ T1.T) @ m
    k345 = T1 @ dT2 @ T2.T @ l_m - T1 @ (T2 + dT2) @ dxv
    return k012, k345


def test_general_two_view_form_reduces_to_eq23():
    rng = np.random.default_rng(23)
    for _ in range(50):
        T1, l_m, T2a, T2b, xva, xvb = _random_case(rng)
        xp, yp = rng.uniform(-300, 300, 40), rng.uniform(-300, 300, 40)
        R, t = relative_pose(T1, T2a, xva, l_m, T1, T2b, xvb, l_m)
        k = k_coefficients(R, t, xp, yp, F_PX)
        k012, k345 = _k_eq23(T1, l_m, T2a, T2b, xvb - xva, xp, yp, F_PX)
        np.testing.assert_allclose(np.stack(k[:3]), k012, atol=1e-12)
        np.testing.assert_allclose(np.array(k[3:]), k345, atol=1e-12)


def test_eq21_needs_the_mount_vector_l():
    """Eq. (21): x - x_v = T2^T (T1^T x_c + l) holds for a real point; the printed 'I' (read as a unit
    vector or zero) does not, for a non-zero mount offset."""
    rng = np.random.default_rng(21)
    T1, l_m, T2, _, xv, _ = _random_case(rng)
    x_ned = xv + rng.uniform(-50, 50, 3)
    x_c = camera_from_ned(x_ned, T1, T2, xv, l_m)
    np.testing.assert_allclose(T2.T @ (T1.T @ x_c + l_m), x_ned - xv, atol=1e-10)       # eq. (21) with l
    assert np.linalg.norm(T2.T @ (T1.T @ x_c + np.ones(3)) - (x_ned - xv)) > 1e-3


def test_eq24_matches_camera_frame_motion_of_points():
    """Delta x_c / x_c = k0 + k3/x_c etc. (eq. 24), with Delta x_c from transforming real points."""
    rng = np.random.default_rng(24)
    for _ in range(20):
        T1, l_m, T2a, T2b, xva, xvb = _random_case(rng)
        pts_ned = xva + rng.uniform(-80, 80, (30, 3))
        pa = camera_from_ned(pts_ned, T1, T2a, xva, l_m)
        pb = camera_from_ned(pts_ned, T1, T2b, xvb, l_m)
        xc = pa[:, 0]
        xp, yp = F_PX * pa[:, 1] / xc, F_PX * pa[:, 2] / xc                         # eqs. (8), (9)
        R, t = relative_pose(T1, T2a, xva, l_m, T1, T2b, xvb, l_m)
        k0, k1, k2, k3, k4, k5 = k_coefficients(R, t, xp, yp, F_PX)
        d = (pb - pa) / xc[:, None]
        np.testing.assert_allclose(d[:, 0], k0 + k3 / xc, atol=1e-10)
        np.testing.assert_allclose(d[:, 1], k1 + k4 / xc, atol=1e-10)
        np.testing.assert_allclose(d[:, 2], k2 + k5 / xc, atol=1e-10)


def test_eq25_26_disparities_equal_exact_projection():
    """A hand-made point cloud projected in both views (eqs. 8, 9, 12, 15) vs eqs. (25)-(26)."""
    rng = np.random.default_rng(25)
    T1 = T_cam_body_from_eps(np.deg2rad([1.0, -2.0, 0.5]))
    l_m = np.array([7.6, 0.0, 0.6])
    T2a = T_body_ned_from_ypr(*np.deg2rad([10.0, 1.0, -0.5]))
    T2b = T_body_ned_from_ypr(*np.deg2rad([9.92, 1.059, -0.38]))
    xva, xvb = np.array([0.0, 0.0, -3.66]), np.array([1.649, -0.134, -3.654])
    # points ahead of the camera: 5 m to 500 m down the optical axis, spread over a 60 deg field
    R_ned_cam = T2a.T @ T1.T
    rng_m = np.exp(rng.uniform(np.log(5), np.log(500), 200))
    dirs = np.stack([np.ones(200), rng.uniform(-0.55, 0.55, 200), rng.uniform(-0.55, 0.55, 200)], 1)
    pts_ned = xva + (l_m @ T2a) + (dirs * rng_m[:, None]) @ R_ned_cam.T
    pa = camera_from_ned(pts_ned, T1, T2a, xva, l_m)
    pb = camera_from_ned(pts_ned, T1, T2b, xvb, l_m)
    np.testing.assert_allclose(pa[:, 0], rng_m, rtol=1e-12)             # the cloud is where we put it
    xa, ya = F_PX * pa[:, 1] / pa[:, 0], F_PX * pa[:, 2] / pa[:, 0]
    xb, yb = F_PX * pb[:, 1] / pb[:, 0], F_PX * pb[:, 2] / pb[:, 0]
    R, t = relative_pose(T1, T2a, xva, l_m, T1, T2b, xvb, l_m)
    k = k_coefficients(R, t, xa, ya, F_PX)
    dx, dy = disparity_eq25_26(k, xa, ya, F_PX, 1.0 / pa[:, 0])
    np.testing.assert_allclose(dx, xb - xa, atol=1e-9)
    np.testing.assert_allclose(dy, yb - ya, atol=1e-9)
    assert np.abs(dx).max() > 5.0                                       # not a trivially tiny motion
    # separate fx, fy (eonav.ranging.methods.paper.disparity): k from m = [1, xp/fx, yp/fy]
    fx, fy = F_PX, 1.2 * F_PX
    ya2, yb2 = fy * pa[:, 2] / pa[:, 0], fy * pb[:, 2] / pb[:, 0]
    k2 = k_coefficients(R, t, xa, ya2 * fx / fy, fx)
    dx2, dy2, _ = disparity_fxfy(k2, xa, ya2, fx, fy, 1.0 / pa[:, 0])
    np.testing.assert_allclose(dx2, xb - xa, atol=1e-9)
    np.testing.assert_allclose(dy2, yb2 - ya2, atol=1e-9)


@pytest.mark.parametrize("stereo", [False, True])
def test_two_cameras_general_form_projection(stereo):
    """Stereo (two cameras, one instant): k from relative_pose still gives exact disparities."""
    rng = np.random.default_rng(26 + stereo)
    T1a, T1b = T_cam_body_from_eps([0, 0, 0]), T_cam_body_from_eps([0.02, -0.01, 0.0])
    la, lb = np.array([1.0, -0.4, 0.0]), np.array([1.0, 0.4, 0.0])
    T2 = T_body_ned_from_ypr(0.3, 0.05, 0.0)
    xv = np.array([10.0, 5.0, -20.0])
    T2b, xvb = (T2, xv) if stereo else (T_body_ned_from_ypr(0.31, 0.05, 0.01), xv + [1.0, 0.2, 0.0])
    pts = xv + rng.uniform(-60, 60, (50, 3))                            # NED points around the vehicle
    pts = pts[camera_from_ned(pts, T1a, T2, xv, la)[:, 0] > 3]
    pa = camera_from_ned(pts, T1a, T2, xv, la)
    pb = camera_from_ned(pts, T1b, T2b, xvb, lb)
    xa, ya = F_PX * pa[:, 1] / pa[:, 0], F_PX * pa[:, 2] / pa[:, 0]
    R, t = relative_pose(T1a, T2, xv, la, T1b, T2b, xvb, lb)
    dx, dy = disparity_eq25_26(k_coefficients(R, t, xa, ya, F_PX), xa, ya, F_PX, 1.0 / pa[:, 0])
    ok = pb[:, 0] > 0
    np.testing.assert_allclose(dx[ok], (F_PX * pb[:, 1] / pb[:, 0] - xa)[ok], atol=1e-8)
    np.testing.assert_allclose(dy[ok], (F_PX * pb[:, 2] / pb[:, 0] - ya)[ok], atol=1e-8)
