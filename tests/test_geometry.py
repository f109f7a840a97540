"""Rotation matrices and the two-view pose: properties checked against hand-derived values."""
import numpy as np
import pytest

from eonav import InputError
from eonav.geometry.camera import Camera, VehicleState, View, pair_geometry
from eonav.geometry.frames import (T_body_ned_from_quat, T_body_ned_from_ypr, T_cam_body_from_eps, camera_from_ned,
                            ned_from_camera, quat_wxyz_from_rotation, quat_wxyz_from_ypr, relative_pose,
                            rotation_from_quat_wxyz, slerp_quat_wxyz, ypr_from_T_body_ned)

RNG = np.random.default_rng(20261121)


def random_ypr(n):
    return np.column_stack([RNG.uniform(-np.pi, np.pi, n), RNG.uniform(-1.4, 1.4, n), RNG.uniform(-np.pi, np.pi, n)])


def test_T2_is_orthonormal_with_unit_determinant():
    for y, p, r in random_ypr(50):
        T = T_body_ned_from_ypr(y, p, r)
        assert np.allclose(T @ T.T, np.eye(3), atol=1e-12)
        assert np.isclose(np.linalg.det(T), 1.0)


def test_T2_hand_values_yaw_90_maps_east_to_nose():
    # Heading east (yaw +90 deg): an NED vector pointing east is straight ahead of the nose (body +X).
    T = T_body_ned_from_ypr(np.pi / 2, 0, 0)
    assert np.allclose(T @ [0, 1, 0], [1, 0, 0], atol=1e-12)
    # Pitch up 90 deg... use 30 deg: "up" (NED -Z) has a positive nose component sin(30).
    T = T_body_ned_from_ypr(0, np.deg2rad(30), 0)
    assert np.allclose(T @ [0, 0, -1], [0.5, 0, -np.cos(np.deg2rad(30))], atol=1e-12)
    # Roll right 90 deg: the starboard wing points down.
    T = T_body_ned_from_ypr(0, 0, np.pi / 2)
    assert np.allclose(T.T @ [0, 1, 0], [0, 0, 1], atol=1e-12)


def test_T1_has_the_same_form_as_T2():
    eps = [0.1, -0.2, 0.3]
    assert np.allclose(T_cam_body_from_eps(eps), T_body_ned_from_ypr(*eps))


def test_ypr_round_trip():
    for ypr in random_ypr(50):
        assert np.allclose(ypr_from_T_body_ned(T_body_ned_from_ypr(*ypr)), ypr, atol=1e-9)


def test_quaternion_euler_round_trip_and_mavlink_convention():
    for ypr in random_ypr(50):
        q = quat_wxyz_from_ypr(*ypr)
        assert np.isclose(np.linalg.norm(q), 1.0)
        # MAVLink ATTITUDE_QUATERNION rotates body vectors into NED: T2 = R(q)^T.
        assert np.allclose(T_body_ned_from_quat(q), T_body_ned_from_ypr(*ypr), atol=1e-12)
        assert np.allclose(quat_wxyz_from_rotation(rotation_from_quat_wxyz(q)), q, atol=1e-12)
    # Hand value: yaw +90 deg about NED down is q = (cos 45, 0, 0, sin 45).
    assert np.allclose(quat_wxyz_from_ypr(np.pi / 2, 0, 0), [np.sqrt(0.5), 0, 0, np.sqrt(0.5)])


def test_gimbal_lock_attitude_enters_through_quaternion():
    # Nadir camera case: pitch -90 deg. Euler angles are singular; the quaternion is not.
    q = np.array([np.cos(-np.pi / 4), 0, np.sin(-np.pi / 4), 0])   # rotation of -90 deg about body Y
    s = VehicleState.from_quat([0, 0, -50], q)
    # Nose points straight down (NED +Z) at pitch -90.
    assert np.allclose(s.T_body_ned.T @ [1, 0, 0], [0, 0, 1], atol=1e-12)
    assert np.allclose(s.T_body_ned @ s.T_body_ned.T, np.eye(3), atol=1e-12)


def test_bad_quaternion_is_rejected():
    with pytest.raises(InputError, match="quaternion"):
        rotation_from_quat_wxyz([0, 0, 0, 0])
    with pytest.raises(InputError, match="finite"):
        VehicleState([0, 0, np.nan], np.eye(3))
    with pytest.raises(InputError, match=r"attitude: expected a unit quaternion.*norm 2\.0"):
        VehicleState.from_quat([0, 0, 0], [2, 0, 0, 0], what="attitude")


def test_slerp_midpoint_and_shortest_path():
    q0 = quat_wxyz_from_ypr(np.deg2rad(170), 0, 0)
    q1 = quat_wxyz_from_ypr(np.deg2rad(-170), 0, 0)
    mid = slerp_quat_wxyz(q0, q1, 0.5)
    yaw = ypr_from_T_body_ned(T_body_ned_from_quat(mid))[0]
    assert np.isclose(abs(yaw), np.pi, atol=1e-9)   # through 180 deg, not through 0


def test_ned_camera_round_trip_eqs_12_15_33():
    T1 = T_cam_body_from_eps([0.05, -0.1, 0.02])
    T2 = T_body_ned_from_ypr(0.3, 0.1, -0.05)
    xv, l = np.array([10.0, -4.0, -30.0]), np.array([2.0, 0.1, 0.5])
    pts = RNG.normal(size=(20, 3)) * 50
    assert np.allclose(ned_from_camera(camera_from_ned(pts, T1, T2, xv, l), T1, T2, xv, l), pts)


def test_relative_pose_moves_points_between_camera_frames():
    ca = Camera("a", 64, 48, 50, 50, 31.5, 23.5, [1.0, 0.2, 0.3], np.deg2rad([2, -5, 1]))
    cb = Camera("b", 80, 60, 70, 65, 40.0, 30.0, [1.0, -0.4, 0.3], np.deg2rad([-1, -4, 0]))
    sa = VehicleState.from_ypr([0, 0, -10], np.deg2rad([10, 2, -3]))
    sb = VehicleState.from_ypr([3, 0.5, -10.2], np.deg2rad([12, 1, -2]))
    R, t = relative_pose(ca.T_cam_body, sa.T_body_ned, sa.position_ned_m, ca.l_body_m,
                         cb.T_cam_body, sb.T_body_ned, sb.position_ned_m, cb.l_body_m)
    world = RNG.normal(size=(10, 3)) * 20 + [60, 0, 0]
    Xa = camera_from_ned(world, ca.T_cam_body, sa.T_body_ned, sa.position_ned_m, ca.l_body_m)
    Xb = camera_from_ned(world, cb.T_cam_body, sb.T_body_ned, sb.position_ned_m, cb.l_body_m)
    assert np.allclose(Xa @ R.T + t, Xb)


def test_map_to_b_is_exact_projection_for_two_different_cameras():
    ca = Camera("a", 64, 48, 50, 52, 31.5, 23.5, [1.0, 0.2, 0.3], np.deg2rad([2, -5, 1]))
    cb = Camera("b", 64, 48, 70, 65, 30.0, 20.0, [1.0, -0.4, 0.3], np.deg2rad([-1, -4, 0]))
    sa = VehicleState.from_ypr([0, 0, -10], np.deg2rad([10, 2, -3]))
    sb = VehicleState.from_ypr([3, 0.5, -10.2], np.deg2rad([12, 1, -2]))
    va, vb = View(ca, sa, np.zeros((48, 64))), View(cb, sb, np.zeros((48, 64)))
    g = pair_geometry(va, vb)
    rho = RNG.uniform(0.01, 0.2, size=(48, 64)).astype(np.float32)
    ub, vb_, _ = g.map_to_b(rho)
    # Independent route: back-project each pixel of a to NED, project into b with eqs. (8)-(9).
    u, v = ca.pixel_grid()
    xc = 1.0 / rho
    Xa = np.stack([xc, xc * (u - ca.cx) / ca.fx, xc * (v - ca.cy) / ca.fy], -1)
    world = ned_from_camera(Xa, ca.T_cam_body, sa.T_body_ned, sa.position_ned_m, ca.l_body_m)
    Xb = camera_from_ned(world, cb.T_cam_body, sb.T_body_ned, sb.position_ned_m, cb.l_body_m)
    assert np.allclose(ub, cb.cx + cb.fx * Xb[..., 1] / Xb[..., 0], atol=2e-3)
    assert np.allclose(vb_, cb.cy + cb.fy * Xb[..., 2] / Xb[..., 0], atol=2e-3)


def test_on_grid_samples_the_pixel_centres_the_locator_upsampled_from():
    """A map resized to a locate grid and upsampled back (the locator's nearest rule) is recovered exactly by sampling
    the frame grid at the small pixels' centres, for scale 0.5 and odd sizes; scaled_camera keeps the pixel centres."""
    from eonav.geometry.camera import Camera, frame_pixel_index, on_grid, scaled_camera
    from eonav.services.locator import to_full_grid, upsample_index
    for (W, H), s in (((640, 480), 0.5), ((15, 11), 0.4), ((512, 512), 0.25)):
        cam = Camera("c", W, H, 300.0, 310.0, W / 2 - 0.3, H / 2 + 0.2)
        sc = scaled_camera(cam, s)
        small = np.random.default_rng(1).random((sc.height, sc.width)).astype(np.float32)
        assert np.array_equal(on_grid(to_full_grid(small, cam), sc.width, sc.height), small)
        assert np.array_equal(upsample_index(W, sc.width)[frame_pixel_index(sc.width, W)], np.arange(sc.width))
        # a small pixel's centre seen through the scaled camera is the same ray as its full-grid position
        u = np.arange(sc.width)
        full_u = (u + 0.5) * W / sc.width - 0.5
        np.testing.assert_allclose((u - sc.cx) / sc.fx, (full_u - cam.cx) / cam.fx, atol=1e-12)
        assert on_grid(small, sc.width, sc.height) is small


def test_point_rays_project_sub_pixel_points_exactly_with_unequal_focal_lengths():
    """PairGeometry.point_rays (the tracks' and the fusion scale check's rays): for sub-pixel points of a camera with
    fx != fy, A + t rho projected with eqs. (8)-(9) is where the point lies in image b, by the independent route
    (back-project to NED with eq. 33, into b with eqs. 12, 15). A y ray divided by fx instead of fy is off by
    (y_p / fx - y_p / fy) x_c: up to 11 px of b here (measured)."""
    ca = Camera("a", 64, 48, 50, 60, 31.5, 23.5, [1.0, 0.2, 0.3], np.deg2rad([2, -5, 1]))
    cb = Camera("b", 64, 48, 70, 65, 30.0, 20.0, [1.0, -0.4, 0.3], np.deg2rad([-1, -4, 0]))
    sa = VehicleState.from_ypr([0, 0, -10], np.deg2rad([10, 2, -3]))
    sb = VehicleState.from_ypr([3, 0.5, -10.2], np.deg2rad([12, 1, -2]))
    g = pair_geometry(View(ca, sa, np.zeros((48, 64))), View(cb, sb, np.zeros((48, 64))))
    rng = np.random.default_rng(136)
    pts = rng.uniform([0, 0], [63, 47], (40, 2))
    rho = rng.uniform(0.01, 0.2, 40)
    X = g.point_rays(pts) + g.t_ba_m[:, None] * rho
    xc = 1.0 / rho
    Xa = np.stack([xc, xc * (pts[:, 0] - ca.cx) / ca.fx, xc * (pts[:, 1] - ca.cy) / ca.fy], -1)
    Xb = camera_from_ned(ned_from_camera(Xa, ca.T_cam_body, sa.T_body_ned, sa.position_ned_m, ca.l_body_m),
                         cb.T_cam_body, sb.T_body_ned, sb.position_ned_m, cb.l_body_m)
    np.testing.assert_allclose(cb.cx + cb.fx * X[1] / X[0], cb.cx + cb.fx * Xb[:, 1] / Xb[:, 0], atol=1e-9)
    np.testing.assert_allclose(cb.cy + cb.fy * X[2] / X[0], cb.cy + cb.fy * Xb[:, 2] / Xb[:, 0], atol=1e-9)


def test_scaled_camera_scales_each_axis_by_its_own_rounded_size():
    """scaled_camera on a 40 x 11 camera at 0.4: 16 x 8 pixels (round(4.4) = 4 is raised to the 8-pixel floor), so
    sx = 16/40 and sy = 8/11 differ (hand values): fy' = 310 * 8/11, cy' = (cy + 0.5) * 8/11 - 0.5, and a small
    pixel's centre row is the same ray as its full-grid row. Scaling y by the width ratio puts fy' at 124 px, not 225.5."""
    from eonav.geometry.camera import scaled_camera
    cam = Camera("c", 40, 11, 300.0, 310.0, 19.2, 5.7)
    sc = scaled_camera(cam, 0.4)
    assert (sc.width, sc.height) == (16, 8)
    assert sc.fx == pytest.approx(300.0 * 0.4) and sc.cx == pytest.approx(19.7 * 0.4 - 0.5)
    assert sc.fy == pytest.approx(310.0 * 8 / 11) and sc.cy == pytest.approx(6.2 * 8 / 11 - 0.5)
    v = np.arange(sc.height)
    full_v = (v + 0.5) * 11 / 8 - 0.5
    np.testing.assert_allclose((v - sc.cy) / sc.fy, (full_v - cam.cy) / cam.fy, atol=1e-12)


def test_non_finite_quaternion_is_rejected_not_turned_into_a_nan_rotation():
    """rotation_from_quat_wxyz (T_body_ned_from_quat's core) refuses a NaN or infinite quaternion (a dropped or
    corrupt ATTITUDE_QUATERNION field) with InputError, as its docstring says, instead of returning a matrix of NaN
    that would poison every range and obstacle downstream. Dropping the finiteness check lets NaN through (NaN < 1e-9
    is False) and turns inf into NaN entries."""
    for q in ([np.nan, 0, 0, 0], [1, 0, np.nan, 0], [np.inf, 0, 0, 0], [1, 0, 0, -np.inf]):
        with pytest.raises(InputError, match="quaternion"):
            rotation_from_quat_wxyz(q)
        with pytest.raises(InputError, match="quaternion"):
            T_body_ned_from_quat(q)


def test_slerp_off_midpoint_moves_from_q0_towards_q1_for_near_and_far_attitudes():
    """slerp_quat_wxyz at s = 0.25 between yaw a and yaw b about one axis is yaw a + 0.25 (b - a) (hand value), both
    for attitude samples 1 deg apart (the normalised-lerp branch, d > 0.9995: the usual case between 50 Hz
    ATTITUDE_QUATERNION samples; nlerp's error there is ~1e-8 rad, measured) and 40 deg apart (the true slerp branch);
    s = 0 and 1 give the ends. A branch that runs from q1 back towards q0 gives 10.75 deg instead of 10.25 deg; the
    midpoint test cannot tell the two directions apart."""
    for a_deg, b_deg, atol in ((10.0, 11.0, 1e-7), (10.0, 50.0, 1e-12)):
        q0, q1 = quat_wxyz_from_ypr(np.deg2rad(a_deg), 0, 0), quat_wxyz_from_ypr(np.deg2rad(b_deg), 0, 0)
        for s in (0.0, 0.25, 1.0):
            ypr = ypr_from_T_body_ned(T_body_ned_from_quat(slerp_quat_wxyz(q0, q1, s)))
            np.testing.assert_allclose(ypr, [np.deg2rad(a_deg + s * (b_deg - a_deg)), 0, 0], atol=atol)


@pytest.mark.parametrize("fx,fy", [(0.0, 500.0), (-500.0, 500.0), (500.0, 0.0), (500.0, -500.0), (500.0, np.nan)])
def test_camera_rejects_a_focal_length_that_is_not_positive_on_either_axis(fx, fy):
    """A Camera's fx and fy are both checked: fy = 0 would make every y ray (v - cy) / fy infinite, and a negative fy
    (an image whose v axis points up) would silently mirror every range map top to bottom. A check that tests fx
    twice lets the fy cases through."""
    with pytest.raises(InputError, match="fx, fy must be positive"):
        Camera("c", 64, 48, fx, fy, 31.5, 23.5)


def test_vehicle_state_rejects_an_attitude_matrix_that_is_not_orthonormal():
    """VehicleState refuses a T_body_ned 1 % off orthonormal (a rotation scaled by 1.01, or sheared by 0.01: T T^T
    off the identity by 0.02 and 0.01, hand values), which would stretch every camera-to-NED distance, and takes a
    rotation rounded to float32 (T T^T off by ~5e-8, measured) as the rotation it is. A tolerance loosened to 0.1
    lets both bad matrices through."""
    T = T_body_ned_from_ypr(0.3, -0.2, 0.7)
    shear = np.eye(3)
    shear[0, 1] = 0.01
    for bad in (1.01 * T, shear @ T):
        with pytest.raises(InputError, match="not a rotation matrix"):
            VehicleState([0, 0, -10], bad)
    T32 = T.astype(np.float32).astype(float)
    np.testing.assert_array_equal(VehicleState([0, 0, -10], T32).T_body_ned, T32)


def test_vehicle_state_rejects_a_mirrored_attitude():
    """A reflection is orthonormal but not a rotation: T_body_ned with the body y axis flipped (a left-handed FLU-style
    body mixed with NED, det -1) would mirror every obstacle port for starboard. VehicleState refuses it, like a matrix
    that is not orthonormal; the proper rotation it came from is accepted."""
    T = T_body_ned_from_ypr(0.3, -0.2, 0.7)
    mirrored = np.diag([1.0, -1.0, 1.0]) @ T
    assert np.allclose(mirrored @ mirrored.T, np.eye(3)) and np.isclose(np.linalg.det(mirrored), -1.0)
    with pytest.raises(InputError, match="not a rotation matrix"):
        VehicleState([0, 0, -10], mirrored)
    VehicleState([0, 0, -10], T)
