"""Frames, rotations and the two-view motion model of the paper.

Frames (docs/conventions.md):
- NED inertial frame (X north, Y east, Z down).
- Body frame FRD (X nose, Y starboard, Z down).
- Camera frame of the paper (Fig. 1): Xc along the optical axis, Yc right, Zc down.
  Image plane one focal length ahead: x_p = f*yc/xc, y_p = f*zc/xc (eqs. 8, 9).

Matrices are named ``T_<to>_<from>``: ``T_body_ned`` is the paper's T2 (eq. 14),
``T_cam_body`` the paper's T1 (eq. 11).
"""
from __future__ import annotations

import numpy as np

from eonav import InputError

# Optical convention (OpenCV / KITTI: x right, y down, z forward) -> paper camera frame
# (Xc forward, Yc right, Zc down): Xc = z, Yc = x, Zc = y.
T_PAPERCAM_OPTICAL = np.array([[0.0, 0.0, 1.0],
                               [1.0, 0.0, 0.0],
                               [0.0, 1.0, 0.0]])


def euler_zyx_matrix(a1_rad: float, a2_rad: float, a3_rad: float) -> np.ndarray:
    """The rotation form shared by eqs. (11) and (14): rotate by a1 about Z, a2 about the new Y,
    a3 about the new X, and return the matrix that maps parent-frame vectors into the rotated frame.

    With (a1, a2, a3) = (psi, theta, phi) this is T2 of eq. (14); with (eps1, eps2, eps3) it is T1 of eq. (11).
    """
    c1, s1 = np.cos(a1_rad), np.sin(a1_rad)
    c2, s2 = np.cos(a2_rad), np.sin(a2_rad)
    c3, s3 = np.cos(a3_rad), np.sin(a3_rad)
    return np.array([
        [c2 * c1, c2 * s1, -s2],
        [s3 * s2 * c1 - c3 * s1, s3 * s2 * s1 + c3 * c1, s3 * c2],
        [c3 * s2 * c1 + s3 * s1, c3 * s2 * s1 - s3 * c1, c3 * c2],
    ])


def T_body_ned_from_ypr(yaw_rad: float, pitch_rad: float, roll_rad: float) -> np.ndarray:
    """T2 of eq. (14): body (FRD) <- inertial (NED), yaw-pitch-roll (ZYX, as MAVLink ATTITUDE)."""
    return euler_zyx_matrix(yaw_rad, pitch_rad, roll_rad)


def T_cam_body_from_eps(eps_rad) -> np.ndarray:
    """T1 of eq. (11): camera <- body, eps = [eps1 about Zc, eps2 about Yc, eps3 about Xc]."""
    e = np.asarray(eps_rad, dtype=float).reshape(3)
    return euler_zyx_matrix(e[0], e[1], e[2])


def ypr_from_T_body_ned(T_body_ned: np.ndarray) -> np.ndarray:
    """Inverse of eq. (14): [yaw, pitch, roll] in radians. Singular at pitch = +-90 deg (yaw+roll only)."""
    T = np.asarray(T_body_ned, dtype=float)
    pitch = -np.arcsin(np.clip(T[0, 2], -1.0, 1.0))
    yaw = np.arctan2(T[0, 1], T[0, 0])
    roll = np.arctan2(T[1, 2], T[2, 2])
    return np.array([yaw, pitch, roll])


def rotation_from_quat_wxyz(q_wxyz) -> np.ndarray:
    """Rotation matrix of a unit quaternion (w, x, y, z), active form: v' = R v.

    MAVLink ATTITUDE_QUATERNION rotates body-frame vectors into NED, so R(q) = T_ned_body and
    T2 = T_body_ned = R(q)^T.
    """
    q = np.asarray(q_wxyz, dtype=float).reshape(4)
    n = np.linalg.norm(q)
    if not np.isfinite(n) or n < 1e-9:
        raise InputError(f"quaternion q_wxyz={q.tolist()} is not finite and non-zero")
    w, x, y, z = q / n
    return np.array([
        [1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
        [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
        [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)],
    ])


def T_body_ned_from_quat(q_wxyz) -> np.ndarray:
    """T2 from the attitude quaternion of MAVLink ATTITUDE_QUATERNION (body -> NED): T2 = R(q)^T."""
    return rotation_from_quat_wxyz(q_wxyz).T


def quat_wxyz_from_rotation(R: np.ndarray) -> np.ndarray:
    """Unit quaternion (w, x, y, z), w >= 0, of an active rotation matrix (Shepperd's method)."""
    R = np.asarray(R, dtype=float)
    tr = np.trace(R)
    if tr > 0:
        s = 2.0 * np.sqrt(tr + 1.0)
        q = [0.25 * s, (R[2, 1] - R[1, 2]) / s, (R[0, 2] - R[2, 0]) / s, (R[1, 0] - R[0, 1]) / s]
    elif R[0, 0] > R[1, 1] and R[0, 0] > R[2, 2]:
        s = 2.0 * np.sqrt(1.0 + R[0, 0] - R[1, 1] - R[2, 2])
        q = [(R[2, 1] - R[1, 2]) / s, 0.25 * s, (R[0, 1] + R[1, 0]) / s, (R[0, 2] + R[2, 0]) / s]
    elif R[1, 1] > R[2, 2]:
        s = 2.0 * np.sqrt(1.0 + R[1, 1] - R[0, 0] - R[2, 2])
        q = [(R[0, 2] - R[2, 0]) / s, (R[0, 1] + R[1, 0]) / s, 0.25 * s, (R[1, 2] + R[2, 1]) / s]
    else:
        s = 2.0 * np.sqrt(1.0 + R[2, 2] - R[0, 0] - R[1, 1])
        q = [(R[1, 0] - R[0, 1]) / s, (R[0, 2] + R[2, 0]) / s, (R[1, 2] + R[2, 1]) / s, 0.25 * s]
    q = np.array(q)
    q /= np.linalg.norm(q)
    return q if q[0] >= 0 else -q


def quat_wxyz_from_ypr(yaw_rad: float, pitch_rad: float, roll_rad: float) -> np.ndarray:
    """Attitude quaternion (body -> NED, as MAVLink) of yaw-pitch-roll angles."""
    return quat_wxyz_from_rotation(T_body_ned_from_ypr(yaw_rad, pitch_rad, roll_rad).T)


def slerp_quat_wxyz(q0, q1, s: float) -> np.ndarray:
    """Spherical linear interpolation between unit quaternions, s in [0, 1] (shortest path)."""
    q0 = np.asarray(q0, dtype=float) / np.linalg.norm(q0)
    q1 = np.asarray(q1, dtype=float) / np.linalg.norm(q1)
    d = float(np.dot(q0, q1))
    if d < 0.0:
        q1, d = -q1, -d
    if d > 0.9995:
        q = q0 + s * (q1 - q0)
        return q / np.linalg.norm(q)
    th = np.arccos(d)
    return (np.sin((1 - s) * th) * q0 + np.sin(s * th) * q1) / np.sin(th)


def relative_pose(T_cam_body_a, T_body_ned_a, pos_ned_a_m, l_body_a_m,
                  T_cam_body_b, T_body_ned_b, pos_ned_b_m, l_body_b_m):
    """Pose of camera frame a in camera frame b: X_b = R_ba X_a + t_ba_m.

    From eqs. (12), (15) and (33) for camera a at state a and camera b at state b (docs/conventions.md, "Two views"):
        R = T1b T2b T2a^T T1a^T
        t = T1b (T2b (x_va - x_vb) + T2b T2a^T l_a - l_b)
    One camera at two instants (motion pair) or two cameras at one instant (stereo) alike.
    """
    T1a, T2a = np.asarray(T_cam_body_a, float), np.asarray(T_body_ned_a, float)
    T1b, T2b = np.asarray(T_cam_body_b, float), np.asarray(T_body_ned_b, float)
    xva, xvb = np.asarray(pos_ned_a_m, float).reshape(3), np.asarray(pos_ned_b_m, float).reshape(3)
    la, lb = np.asarray(l_body_a_m, float).reshape(3), np.asarray(l_body_b_m, float).reshape(3)
    R_ba = T1b @ T2b @ T2a.T @ T1a.T
    t_ba_m = T1b @ (T2b @ (xva - xvb) + T2b @ T2a.T @ la - lb)
    return R_ba, t_ba_m


def k_coefficients(R_ba: np.ndarray, t_ba_m: np.ndarray, xp, yp, f: float):
    """k0..k5 of eq. (24) from the general two-view pose: [k0,k1,k2] = (R - I)[1, x_p/f, y_p/f]^T,
    [k3,k4,k5] = t. k0..k2 vary per pixel (arrays broadcast), k3..k5 are the translation in metres."""
    m0 = np.ones_like(np.asarray(xp, dtype=float))
    m1 = np.asarray(xp, dtype=float) / f
    m2 = np.asarray(yp, dtype=float) / f
    D = np.asarray(R_ba, float) - np.eye(3)
    k0 = D[0, 0] * m0 + D[0, 1] * m1 + D[0, 2] * m2
    k1 = D[1, 0] * m0 + D[1, 1] * m1 + D[1, 2] * m2
    k2 = D[2, 0] * m0 + D[2, 1] * m1 + D[2, 2] * m2
    t = np.asarray(t_ba_m, float).reshape(3)
    return k0, k1, k2, t[0], t[1], t[2]


def disparity_eq25_26(k, xp, yp, f: float, inv_range_per_m):
    """Exact perspective disparity of a point at inverse range rho = 1/x_c, eqs. (25)-(26).

    Returns (dx_p, dy_p) in pixels; the point seen at (x_p, y_p) in image a is at
    (x_p + dx_p, y_p + dy_p) in image b (same intrinsics in both images).
    """
    k0, k1, k2, k3, k4, k5 = k
    rho = inv_range_per_m
    den = 1.0 + k0 + k3 * rho
    dxp = (f * k1 - xp * k0 + (f * k4 - xp * k3) * rho) / den   # eq. (25)
    dyp = (f * k2 - yp * k0 + (f * k5 - yp * k3) * rho) / den   # eq. (26)
    return dxp, dyp


def ned_from_camera(points_cam_m: np.ndarray, T_cam_body, T_body_ned, pos_ned_m, l_body_m) -> np.ndarray:
    """Eq. (33): x = x_v + T2^T (T1^T x_c + l), for points (..., 3) in the camera frame."""
    p = np.asarray(points_cam_m, float)
    T1, T2 = np.asarray(T_cam_body, float), np.asarray(T_body_ned, float)
    body = p @ T1 + np.asarray(l_body_m, float)          # T1^T x_c + l, row-vector form
    return body @ T2 + np.asarray(pos_ned_m, float)      # T2^T (...) + x_v


def camera_from_ned(points_ned_m: np.ndarray, T_cam_body, T_body_ned, pos_ned_m, l_body_m) -> np.ndarray:
    """Eqs. (12), (15): x_c = T1 (T2 (x - x_v) - l), for points (..., 3) in NED."""
    p = np.asarray(points_ned_m, float) - np.asarray(pos_ned_m, float)
    body = p @ np.asarray(T_body_ned, float).T - np.asarray(l_body_m, float)
    return body @ np.asarray(T_cam_body, float).T
