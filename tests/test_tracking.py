"""Obstacle tracker, guidance quantities and the obstacle_tracks message, on hand-made measurements with known truth:
points seen by a known camera at known poses, noise drawn from the covariance the camera geometry gives."""
import math
import subprocess
import sys

import numpy as np
import pytest

from eonav import InputError
from eonav.bus import guidance_msg as G
from eonav.obstacles import guidance as GP
from eonav.obstacles import tracking as T
from eonav.geometry.camera import Camera, VehicleState
from eonav.geometry.frames import camera_from_ned, ned_from_camera
from eonav.obstacles.detect import Obstacle
from eonav.bus.schema import SchemaError

RATE_HZ = 15.0
F_PX = 0.5 * 320 / math.tan(math.radians(20.0))          # 40 deg horizontal field of view over 320 px
CAM = Camera("nose", 320, 240, F_PX, F_PX, 159.5, 119.5)
HOVER = VehicleState.from_ypr([0.0, 0.0, -10.0], [0.0, 0.0, 0.0])


def us(t_s):
    return int(round(t_s * 1e6))


def x_c(p, st, cam=CAM):
    return float(camera_from_ned(np.asarray(p, float), cam.T_cam_body, st.T_body_ned, st.position_ned_m,
                                 cam.l_body_m)[0])


def observe(p, st, rng, rel_sigma=0.01, px_sigma=1.0, extent=(0.3, 0.3, 3.0), cam=CAM):
    """A measurement of the true point p: noise drawn from the camera-geometry covariance it carries."""
    p = np.asarray(p, float)
    C = T.camera_covariance(p, cam, st, rel_sigma * x_c(p, st, cam), px_sigma, px_sigma)
    return T.Measurement(rng.multivariate_normal(p, C), C, np.asarray(extent, float))


def fov(st, cam=CAM, **kw):
    return T.FieldOfView(cam, st, max_distance_m=100.0, **kw)


def box_map(st, boxes, cam=CAM):
    """Range map of boxes (center, half extents) in front of a sky: each box's projected corner box at the x_c of
    its centre (enough for the occlusion test: something nearer covers the pixels)."""
    r = np.full((cam.height, cam.width), np.inf, np.float32)
    for c, h in sorted(boxes, key=lambda b: -x_c(b[0], st, cam)):          # far first, near overwrites
        corners = np.array([[c[0] + sx * h[0], c[1] + sy * h[1], c[2] + sz * h[2]]
                            for sx in (-1, 1) for sy in (-1, 1) for sz in (-1, 1)])
        pc = camera_from_ned(corners, cam.T_cam_body, st.T_body_ned, st.position_ned_m, cam.l_body_m)
        u = cam.cx + cam.fx * pc[:, 1] / pc[:, 0]
        v = cam.cy + cam.fy * pc[:, 2] / pc[:, 0]
        u0, u1 = int(max(0, np.floor(u.min()))), int(min(cam.width - 1, np.ceil(u.max())))
        v0, v1 = int(max(0, np.floor(v.min()))), int(min(cam.height - 1, np.ceil(v.max())))
        if u1 >= u0 and v1 >= v0:
            r[v0:v1 + 1, u0:u1 + 1] = x_c(c, st, cam)
    return r


# -- measurement model -------------------------------------------------------------------------------------------
def test_camera_covariance_on_axis_is_hand_derived():
    # level camera looking north: Xc = N, Yc = E, Zc = D; on the axis J = diag(1, x_c/fx, x_c/fy)
    p = [50.0, 0.0, -10.0]
    C = T.camera_covariance(p, CAM, HOVER, 0.5, 2.0, 3.0)
    want = np.diag([0.5 ** 2, (50.0 * 2.0 / F_PX) ** 2, (50.0 * 3.0 / F_PX) ** 2])
    np.testing.assert_allclose(C, want, rtol=1e-9, atol=1e-12)


def test_camera_covariance_off_axis_matches_sampling_through_the_geometry():
    # a yawed, pitched, rolled vehicle and a mounted, tilted camera; a point off the axis at the image corner
    cam = Camera("side", 320, 240, F_PX, F_PX, 159.5, 119.5, l_body_m=[2.0, 0.5, 0.3],
                 eps_rad=np.deg2rad([25.0, -8.0, 3.0]))
    st = VehicleState.from_ypr([10.0, -5.0, -30.0], np.deg2rad([40.0, 5.0, -10.0]))
    u, v, xc = 290.0, 30.0, 60.0
    m = np.array([1.0, (u - cam.cx) / cam.fx, (v - cam.cy) / cam.fy])
    p = ned_from_camera(xc * m, cam.T_cam_body, st.T_body_ned, st.position_ned_m, cam.l_body_m)
    s_x, s_u, s_v = 0.6, 1.5, 2.5
    C = T.camera_covariance(p, cam, st, s_x, s_u, s_v)
    rng = np.random.default_rng(7)
    n = 200_000
    xs = xc + s_x * rng.standard_normal(n)
    us_ = u + s_u * rng.standard_normal(n)
    vs = v + s_v * rng.standard_normal(n)
    pts = np.stack([xs, xs * (us_ - cam.cx) / cam.fx, xs * (vs - cam.cy) / cam.fy], 1)
    ned = ned_from_camera(pts, cam.T_cam_body, st.T_body_ned, st.position_ned_m, cam.l_body_m)
    emp = np.cov(ned.T)
    np.testing.assert_allclose(C, emp, atol=0.02 * np.abs(emp).max())
    # along the ray the spread is the range sigma times |m|, across it x_c / f times the pixel sigma
    ray = (p - T.lens_ned_m(cam, st)) / np.linalg.norm(p - T.lens_ned_m(cam, st))
    assert math.sqrt(ray @ C @ ray) == pytest.approx(s_x * np.linalg.norm(m), rel=0.02)


def _obstacle(p, bbox, range_std=0.4, ext=(0.5, 0.5, 4.0)):
    return Obstacle(id=1, distance_m=0.0, distance_median_m=0.0, horizontal_distance_m=0.0, bearing_deg=0.0,
                    elevation_deg=0.0, range_std_m=range_std, position_ned_m=list(p), extent_ned_m=list(ext),
                    width_m=0.5, height_m=4.0, pixel_count=80, confidence=0.9, bbox_px=list(bbox))


def test_measurement_from_obstacle_hand_derived_and_grid_independent():
    cfg = T.TrackerConfig(nav_sigma_m=0.0, attitude_sigma_rad=0.0)
    p = [40.0, 0.0, -10.0]                          # on the axis: N along the ray, E and D across
    o = _obstacle(p, bbox=[155, 90, 164, 149], ext=(2.0, 0.5, 4.0))       # 10 x 60 frame pixels
    m, = T.measurements_from_obstacles([o], CAM, HOVER, cfg)
    # range sigma and 15 % of the points' depth spread (N extent 2 m); of that spread 3.29 x 0.4 m is the 0.4 m
    # range noise along the ray (on the axis the ray per metre of range is N itself), which the object's extent
    # leaves out
    depth = math.sqrt(2.0 ** 2 - (3.29 * 0.4) ** 2)
    s_x = math.hypot(0.4, 0.15 * 2.0)
    np.testing.assert_allclose(m.extent_ned_m, [2.0, 0.5, 4.0])
    np.testing.assert_allclose(m.extent_noise_ned_m, [3.29 * 0.4, 0.0, 0.0], atol=1e-12)
    np.testing.assert_allclose(m.object_extent_ned_m, [depth, 0.5, 4.0], rtol=1e-9)
    s_u = math.sqrt(1.0 + (0.15 * 10) ** 2)
    s_v = math.sqrt(1.0 + (0.15 * 60) ** 2)
    want = np.diag([s_x ** 2, (40.0 * s_u / F_PX) ** 2, (40.0 * s_v / F_PX) ** 2])
    np.testing.assert_allclose(m.cov_ned_m2, want, rtol=1e-9, atol=1e-12)
    assert m.pixel_count == 80 and m.confidence == 0.9
    # the same obstacle from a map at half scale (bbox still in frame pixels): the same covariance
    from eonav.geometry.camera import scaled_camera
    half = scaled_camera(CAM, 0.5)
    m2, = T.measurements_from_obstacles([o], half, HOVER, cfg, frame_size=(320, 240))
    np.testing.assert_allclose(m2.cov_ned_m2, want, rtol=1e-3)
    # navigation sigma adds isotropically
    m3, = T.measurements_from_obstacles([o], CAM, HOVER, T.TrackerConfig(nav_sigma_m=0.5, attitude_sigma_rad=0.0))
    np.testing.assert_allclose(m3.cov_ned_m2, want + 0.25 * np.eye(3), rtol=1e-9)


def test_camera_covariance_takes_each_pixel_axis_at_its_own_focal_length():
    """Non-square pixels (fx = 2 fy): on the axis the across-ray sigmas are x_c s_u / fx east and x_c s_v / fy down,
    each at its own focal length (J = diag(1, x_c/fx, x_c/fy)); a camera with fx = fy cannot tell them apart."""
    cam = Camera("anamorphic", 320, 240, 400.0, 200.0, 159.5, 119.5)
    C = T.camera_covariance([50.0, 0.0, -10.0], cam, HOVER, 0.5, 2.0, 3.0)
    want = np.diag([0.5 ** 2, (50.0 * 2.0 / 400.0) ** 2, (50.0 * 3.0 / 200.0) ** 2])     # 0.25, 0.0625, 0.5625
    np.testing.assert_allclose(C, want, rtol=1e-9, atol=1e-12)


def test_measurement_seen_by_a_yawed_pitched_camera_uses_the_optical_axis_in_ned():
    """Vehicle yawed 30 deg and nose up 20 deg, camera along the nose: the optical axis in NED is
    d = (cos 20 cos 30, cos 20 sin 30, -sin 20), the image's right r = (-sin 30, cos 30, 0) and its down
    g = (sin 20 cos 30, sin 20 sin 30, cos 20). An obstacle 40 m along d with a 5..95 % spread of (2, 1, 4) m in
    N, E, D: its depth along the axis is |d * ext| (2.178 m), so the range sigma is hypot(0.4, 0.15 |d * ext|), and
    the 0.4 m range noise spreads its points along d, 3.29 x 0.4 |d| per axis. A level camera looking north (the
    other tests) has d = N, where the camera and NED frames, and a row and a column of the rotation, all agree."""
    yaw, pitch = math.radians(30.0), math.radians(20.0)
    st = VehicleState.from_ypr([5.0, -3.0, -20.0], [yaw, pitch, 0.0])
    d = np.array([math.cos(pitch) * math.cos(yaw), math.cos(pitch) * math.sin(yaw), -math.sin(pitch)])
    r = np.array([-math.sin(yaw), math.cos(yaw), 0.0])
    g = np.array([math.sin(pitch) * math.cos(yaw), math.sin(pitch) * math.sin(yaw), math.cos(pitch)])
    p = st.position_ned_m + 40.0 * d
    ext = np.array([2.0, 1.0, 4.0])
    cfg = T.TrackerConfig(nav_sigma_m=0.0, attitude_sigma_rad=0.0)
    m, = T.measurements_from_obstacles([_obstacle(p, bbox=[155, 90, 164, 149], ext=ext)], CAM, st, cfg)
    depth = float(np.linalg.norm(d * ext))
    assert depth == pytest.approx(2.1775, abs=1e-4)
    s_x = math.hypot(0.4, 0.15 * depth)
    s_e = 40.0 * math.sqrt(1.0 + (0.15 * 10) ** 2) / F_PX
    s_d = 40.0 * math.sqrt(1.0 + (0.15 * 60) ** 2) / F_PX
    want = s_x ** 2 * np.outer(d, d) + s_e ** 2 * np.outer(r, r) + s_d ** 2 * np.outer(g, g)
    np.testing.assert_allclose(m.cov_ned_m2, want, rtol=1e-9, atol=1e-12)
    np.testing.assert_allclose(m.extent_noise_ned_m, 3.29 * 0.4 * np.abs(d), rtol=1e-9)
    np.testing.assert_allclose(m.object_extent_ned_m, np.sqrt(ext ** 2 - (3.29 * 0.4 * d) ** 2), rtol=1e-9)


def test_range_sigma_has_a_floor_relative_to_range():
    """A far obstacle that the map ranges to 5 cm (a flat face, no depth spread) at 100 m: the measurement's range
    sigma is floored at ``min_range_rel_sigma`` (0.2 %) of the range, 0.2 m, so one overconfident map cannot pin a
    track; across the ray the pixel sigmas are unchanged."""
    cfg = T.TrackerConfig(nav_sigma_m=0.0, attitude_sigma_rad=0.0)
    o = _obstacle([100.0, 0.0, -10.0], bbox=[155, 90, 164, 149], range_std=0.05, ext=(0.0, 0.5, 4.0))
    m, = T.measurements_from_obstacles([o], CAM, HOVER, cfg)
    s_u = math.sqrt(1.0 + (0.15 * 10) ** 2)
    s_v = math.sqrt(1.0 + (0.15 * 60) ** 2)
    want = np.diag([0.2 ** 2, (100.0 * s_u / F_PX) ** 2, (100.0 * s_v / F_PX) ** 2])
    np.testing.assert_allclose(m.cov_ned_m2, want, rtol=1e-9, atol=1e-12)
    # at 10 m the floor (2 cm) is below the 5 cm: the map's sigma stands
    o10 = _obstacle([10.0, 0.0, -10.0], bbox=[155, 90, 164, 149], range_std=0.05, ext=(0.0, 0.5, 4.0))
    m10, = T.measurements_from_obstacles([o10], CAM, HOVER, cfg)
    assert m10.cov_ned_m2[0, 0] == pytest.approx(0.05 ** 2, rel=1e-9)


def test_attitude_sigma_adds_its_angle_times_the_focal_length_to_each_pixel_sigma():
    """The attitude error (default 0.2 deg, in radians) moves the pixel of the median point by that angle times the
    focal length, on each image axis at its own: s_u^2 = 1 + (0.15 w)^2 + (0.2 deg fx)^2 and likewise with h and fy.
    Non-square pixels (fx = 440, fy = 220) on the axis at 40 m, navigation sigma off: hand-derived east and down
    variances (40 s_u / fx)^2 and (40 s_v / fy)^2 (the attitude terms are 1.536 and 0.768 px)."""
    cam = Camera("anamorphic", 320, 240, 440.0, 220.0, 159.5, 119.5)
    cfg = T.TrackerConfig(nav_sigma_m=0.0)
    assert cfg.attitude_sigma_rad == pytest.approx(math.pi * 0.2 / 180.0)
    m, = T.measurements_from_obstacles([_obstacle([40.0, 0.0, -10.0], bbox=[155, 90, 164, 149])], cam, HOVER, cfg)
    att = math.pi * 0.2 / 180.0
    s_u = math.sqrt(1.0 + (0.15 * 10) ** 2 + (att * 440.0) ** 2)
    s_v = math.sqrt(1.0 + (0.15 * 60) ** 2 + (att * 220.0) ** 2)
    np.testing.assert_allclose(m.cov_ned_m2[1:, 1:], np.diag([(40.0 * s_u / 440.0) ** 2, (40.0 * s_v / 220.0) ** 2]),
                               rtol=1e-9, atol=1e-12)


def test_attitude_sigma_is_taken_at_the_frames_focal_length_on_a_reduced_map():
    """A map located at half the frame's resolution (its grid camera's focal length F_PX / 2, the bbox in frame
    pixels): the pixel sigmas are in frame pixels, the attitude term 0.2 deg x F_PX (1.53 px) included, so the
    covariance is the full-resolution one, hand-derived on the axis at 40 m: east and down variances (40 s / F_PX)^2
    with s^2 = 1 + (0.15 w)^2 + (0.2 deg x F_PX)^2. The attitude term taken at the map's focal length would be half
    (0.77 px): across-ray sigmas too small on every reduced map."""
    from eonav.geometry.camera import scaled_camera
    cfg = T.TrackerConfig(nav_sigma_m=0.0)
    att = math.pi * 0.2 / 180.0
    o = _obstacle([40.0, 0.0, -10.0], bbox=[155, 90, 164, 149])             # 10 x 60 frame pixels
    s_u = math.sqrt(1.0 + (0.15 * 10) ** 2 + (att * F_PX) ** 2)
    s_v = math.sqrt(1.0 + (0.15 * 60) ** 2 + (att * F_PX) ** 2)
    want = np.diag([(40.0 * s_u / F_PX) ** 2, (40.0 * s_v / F_PX) ** 2])
    for cam, frame in ((CAM, None), (scaled_camera(CAM, 0.5), (320, 240))):
        m, = T.measurements_from_obstacles([o], cam, HOVER, cfg, frame_size=frame)
        np.testing.assert_allclose(m.cov_ned_m2[1:, 1:], want, rtol=1e-9, atol=1e-12, err_msg=cam.name)


def test_merged_fragments_confidence_is_their_pixel_weighted_mean():
    """The merged measurement's confidence (the track's measurement_confidence on the message) is its fragments'
    pixel-weighted mean, as its position: pieces of 100, 300 and 100 pixels with confidences 0.5, 0.9 and 0.7 give
    0.2 x 0.5 + 0.6 x 0.9 + 0.2 x 0.7 = 0.78, in whichever order the list gives them."""
    cov = np.diag([0.25, 0.01, 0.01])
    parts = [T.Measurement([60.0, 0.0, -1.0], cov, [0.3, 0.3, 2.0], 100, 0.5),
             T.Measurement([60.2, 0.0, -3.2], cov, [0.3, 0.3, 2.0], 300, 0.9),
             T.Measurement([60.0, 0.1, -5.4], cov, [0.3, 0.3, 2.0], 100, 0.7)]
    for order in (parts, parts[::-1], parts[1:] + parts[:1]):
        m, = T.merge_fragments(order, gap_m=0.5)
        assert m.confidence == pytest.approx(0.78, abs=1e-12)


def test_fragments_of_one_pole_merge_and_a_neighbour_does_not():
    cov = np.diag([0.25, 0.01, 0.01])
    # a pole (0.3 m wide) listed as three stacked pieces 0.2 m apart, and a second pole 2 m to the east
    parts = [T.Measurement([60.0, 0.0, -1.0], cov, [0.3, 0.3, 2.0], 100),
             T.Measurement([60.2, 0.0, -3.2], cov, [0.3, 0.3, 2.0], 300),
             T.Measurement([60.0, 0.1, -5.4], cov, [0.3, 0.3, 2.0], 100)]
    other = T.Measurement([60.0, 2.0, -3.0], cov, [0.3, 0.3, 6.0], 50)
    out = T.merge_fragments(parts + [other], gap_m=0.5)
    assert len(out) == 2 and out[1] is other
    m = out[0]
    w = np.array([0.2, 0.6, 0.2])
    want = w @ np.array([p.position_ned_m for p in parts])
    np.testing.assert_allclose(m.position_ned_m, want)
    # 5..95 % of the pieces' points (each spread evenly, its own box its 5..95 %: support 2 + 2/9 m in down):
    # the lowest piece (weight 0.2, support -6.511..-4.289) holds the 5 % point a quarter up, -5.956; the top one
    # the 95 % point a quarter down from 0.111, -0.444: 5.511 m, inside the union of the boxes (6.4 m)
    assert m.extent_ned_m[2] == pytest.approx(6.4 + 4.0 / 18.0 - 2 * 0.25 * (2.0 + 4.0 / 18.0), abs=1e-9)
    assert np.all(m.extent_ned_m <= np.array([0.5, 0.4, 6.4]) + 1e-12) and np.all(m.extent_ned_m >= 0.3 - 1e-12)
    spread = sum(wi * np.outer(p.position_ned_m - want, p.position_ned_m - want) for wi, p in zip(w, parts))
    np.testing.assert_allclose(m.cov_ned_m2, cov + spread, atol=1e-12)
    assert m.pixel_count == 500
    # pieces 0.6 m apart (beyond the 0.5 m gap) stay apart
    apart = [parts[0], T.Measurement([60.0, 0.0, -3.6], cov, [0.3, 0.3, 2.0], 300)]
    assert len(T.merge_fragments(apart, gap_m=0.5)) == 2
    assert len(T.merge_fragments(apart, gap_m=0.7)) == 1


def test_a_speck_merged_with_a_wall_does_not_stretch_its_extent():
    # a 3000-pixel wall face (5..95 % of its points 1 m deep) and a 12-pixel speck at its top edge ranged 15 m
    # nearer, whose boxes touch: one obstacle, whose extent is the wall's, not the 16 m union of the two boxes
    cov = np.diag([4.0, 0.04, 0.04])
    wall = T.Measurement([100.0, 0.0, -4.0], cov, [1.0, 12.0, 8.0], 3000)
    speck = T.Measurement([92.5, 0.0, -8.2], cov, [14.0, 0.5, 0.5], 12)
    m, = T.merge_fragments([wall, speck], gap_m=0.5)
    assert m.pixel_count == 3012
    assert m.extent_ned_m[0] < 1.2                          # the union would be 100.5 - 85.5 = 15 m
    np.testing.assert_allclose(m.extent_ned_m[1:], [12.0, 8.0], atol=0.15)
    # two equal pieces side by side: the union, less the outer 5 % of the pair
    a = T.Measurement([0.0, 0.0, 0.0], cov, [1.0, 1.0, 1.0], 100)
    b = T.Measurement([0.0, 1.2, 0.0], cov, [1.0, 1.0, 1.0], 100)
    m, = T.merge_fragments([a, b], gap_m=0.5)
    # east: supports -0.556..0.556 and 0.644..1.756, weight 1/2 each: 5 % at 0.1 of the first, 95 % at 0.9 of
    # the second
    assert m.extent_ned_m[1] == pytest.approx((0.644444 + 0.9 * 1.111111) - (-0.555556 + 0.1 * 1.111111), abs=1e-5)


def test_label_names_the_nearest_track_inside_the_gate():
    cov = 0.04 * np.eye(3)                                                  # 0.2 m 1-sigma
    tr = T.Tracker(T.TrackerConfig(gate_chi2=9.0))
    tr.update([T.Measurement([50.0, 0.0, -5.0], cov), T.Measurement([50.0, 1.0, -5.0], cov)], us(0.0))
    a, b = (t.id for t in tr.tracks)
    # S = P + R = 2 x 0.04 I at the track's birth stamp: d^2 = |y|^2 / 0.08; the gate 9 is |y| = 0.8485 m
    near_a = T.Measurement([50.0, 0.4, -5.0], cov)                          # d^2 2.0 to a, 4.5 to b
    near_b = T.Measurement([50.0, 0.7, -5.0], cov)                          # d^2 1.1 to b, 6.1 to a
    outside = T.Measurement([50.0, 0.0, -5.85], cov)                        # d^2 9.03 to a
    inside = T.Measurement([50.0, 0.0, -5.84], cov)                         # d^2 8.82 to a
    assert tr.label([near_a, near_b, outside, inside]) == [a, b, 0, a]
    assert tr.label([]) == []
    assert T.Tracker().label([near_a]) == [0]                               # no tracks


def test_a_precise_track_wins_a_detection_over_a_vague_one_by_d2_plus_ln_det_s():
    """Two tracks gate one detection: a precise one (P = 0.04 I) 0.8 m from it and a vague one (P = 4 I, a re-born or
    long-coasting track) 2 m from it. By d^2 alone the vague one is nearer; the assignment minimises d^2 + ln det S,
    which gives the detection to the precise track (hand-derived below); the unpaired track misses and, tentative,
    dies."""
    tr = T.Tracker(T.TrackerConfig(gate_chi2=T.CHI2_3_999))
    r = 0.04 * np.eye(3)
    tr.update([T.Measurement([50.0, 0.0, -5.0], r), T.Measurement([50.0, 2.8, -5.0], 4.0 * np.eye(3))], us(0.0))
    precise, vague = tr.tracks
    # same stamp: no prediction, S = P + R = 0.08 I (precise) and 4.04 I (vague)
    z = T.Measurement([50.0, 0.8, -5.0], r)
    d2_p, d2_v = 0.8 ** 2 / 0.08, 2.0 ** 2 / 4.04                          # 8.0 and 0.99: both inside the gate
    cost_p, cost_v = d2_p + 3 * math.log(0.08), d2_v + 3 * math.log(4.04)   # 0.42 and 5.18
    assert d2_v < d2_p < T.CHI2_3_999 and cost_p < cost_v
    tr.update([z], us(0.0))
    assert [t.id for t in tr.tracks] == [precise.id] and tr.tracks[0].hits == 2


def test_bad_measurements_and_config_are_named():
    with pytest.raises(InputError, match="positive definite"):
        T.Measurement([1, 2, 3], np.diag([1.0, 0.0, 1.0]))
    with pytest.raises(InputError, match="symmetric 3 x 3"):
        T.Measurement([1, 2, 3], np.eye(2))
    with pytest.raises(InputError, match="position_ned_m"):
        T.Measurement([1, np.nan, 3], np.eye(3))
    # symmetric within rtol 1e-9 (of the mirrored element) + atol 1e-12: either side of that tolerance
    skew = np.eye(3)
    skew[0, 1] = 0.5
    skew[1, 0] = 0.5 * (1 + 5e-10)
    T.Measurement([1, 2, 3], skew)
    skew[1, 0] = 0.5 * (1 + 5e-9)
    with pytest.raises(InputError, match="symmetric 3 x 3"):
        T.Measurement([1, 2, 3], skew)
    with pytest.raises(InputError, match="confirm_hits"):
        T.TrackerConfig(confirm_hits=0)
    with pytest.raises(InputError, match="gate_chi2"):
        T.TrackerConfig(gate_chi2=-1.0)
    with pytest.raises(InputError, match="behind the camera"):
        T.camera_covariance([-5.0, 0.0, -10.0], CAM, HOVER, 1.0, 1.0, 1.0)
    tr = T.Tracker()
    tr.update([], us(1.0))
    with pytest.raises(InputError, match="older than the last"):
        tr.update([], us(0.5))
    with pytest.raises(InputError, match="integer microseconds"):
        tr.update([], 2.5)
    with pytest.raises(InputError, match="Measurement objects"):
        tr.update([[50.0, 0.0, 0.0]], us(2.0))


# -- track life cycle --------------------------------------------------------------------------------------------
def test_confirmed_after_n_hits_and_clutter_never_confirms():
    rng = np.random.default_rng(11)
    tr = T.Tracker()                                  # N = 3
    p = [60.0, 3.0, -8.0]
    for k in range(2):                                # a point seen twice, then gone: never confirmed
        tr.update([observe(p, HOVER, rng)], us(k / RATE_HZ), fov(HOVER))
        assert tr.confirmed() == []
    tr.update([], us(2 / RATE_HZ), fov(HOVER))        # in view, not detected: the tentative track dies
    assert tr.tracks == []
    for k in range(3, 6):                             # seen three times in a row: confirmed at the third
        tr.update([observe(p, HOVER, rng)], us(k / RATE_HZ), fov(HOVER))
        assert len(tr.confirmed()) == (1 if k == 5 else 0)
    # 20 s of clutter: one to three spurious points a map, anywhere in a 10..95 m deep block ahead
    tr = T.Tracker()
    n_clutter = 0
    for k in range(int(20 * RATE_HZ)):
        pts = [[rng.uniform(10, 95), rng.uniform(-15, 15), rng.uniform(-25, 0)] for _ in range(rng.integers(1, 4))]
        n_clutter += len(pts)
        tr.update([observe(q, HOVER, rng) for q in pts], us(k / RATE_HZ), fov(HOVER))
        assert tr.confirmed() == [], k
    assert n_clutter > 500


def test_confirmed_track_survives_m_minus_one_misses_and_dies_at_m():
    rng = np.random.default_rng(12)
    p = [50.0, -2.0, -6.0]
    for gap, survives in ((5, True), (6, False)):     # M = 6 consecutive in-view misses
        tr = T.Tracker()
        k = 0
        for _ in range(5):
            tr.update([observe(p, HOVER, rng)], us(k / RATE_HZ), fov(HOVER))
            k += 1
        first = tr.confirmed()[0].id
        for _ in range(gap):
            tr.update([], us(k / RATE_HZ), fov(HOVER))
            k += 1
        assert (len(tr.tracks) == 1) is survives
        tr.update([observe(p, HOVER, rng)], us(k / RATE_HZ), fov(HOVER))
        assert (tr.tracks[0].id == first) is survives
        assert tr.tracks[0].confirmed is survives


def test_two_close_obstacles_keep_two_stable_ids():
    # two poles 2 m apart across the line of sight at 60 m (15 sigma of the across-ray noise), 3 s of maps
    rng = np.random.default_rng(13)
    truth = {"left": np.array([60.0, -1.0, -6.0]), "right": np.array([60.0, 1.0, -6.0])}
    tr = T.Tracker()
    ids = {}
    for k in range(int(3 * RATE_HZ)):
        meas = [observe(p, HOVER, rng) for p in truth.values()]
        tr.update(meas[::(-1) ** k], us(k / RATE_HZ), fov(HOVER))       # list order alternates
        conf = tr.confirmed()
        if k >= 2:
            assert len(conf) == 2 and len(tr.tracks) == 2, k
            for name, p in truth.items():
                t = min(conf, key=lambda t: np.linalg.norm(t.x[:3] - p))
                e = t.x[:3] - p
                assert e @ np.linalg.solve(t.P[:3, :3], e) < T.CHI2_3_999          # consistent with its covariance
                assert math.hypot(e[1], e[2]) < 0.5                                # not drawn to the other pole
                assert ids.setdefault(name, t.id) == t.id, (k, name)
    assert ids["left"] != ids["right"]


def _crossing(tr, rng, use_map):
    """A (north 48 m) and B (north 55 m, behind A: 13 % farther) cross at 6 m/s each way; while they overlap in the
    image only A is measured. Returns (ids of A and B per frame after confirmation, B's states during the overlap)."""
    seen, b_states = [], []
    for k in range(int(5 * RATE_HZ)):
        t = k / RATE_HZ
        a = np.array([48.0, -15.0 + 6.0 * t, -6.0])
        b = np.array([55.0, 15.0 - 6.0 * t, -6.0])
        overlap = abs(a[1] * 55.0 / 48.0 - b[1]) < 1.3          # B's centre behind A's 2 x 1.2 m outline
        meas = [observe(a, HOVER, rng, extent=(1.0, 2.4, 3.0))]
        if not overlap:
            meas.append(observe(b, HOVER, rng, extent=(1.0, 2.4, 3.0)))
        rmap = box_map(HOVER, [(a, [0.5, 1.2, 1.5]), (b, [0.5, 1.2, 1.5])]) if use_map else None
        tr.update(meas, us(t), fov(HOVER, range_m=rmap))
        if k >= 3:
            def nearest(p):
                return min(tr.tracks, key=lambda tt: np.linalg.norm(tt.x[:3] - p))
            seen.append((nearest(a).id, nearest(b).id))
            if overlap:
                b_states.append(nearest(b).state)
    return seen, b_states


def test_crossing_obstacles_keep_their_ids_through_the_overlap():
    rng = np.random.default_rng(14)
    seen, b_states = _crossing(T.Tracker(), rng, use_map=True)
    assert len(set(seen)) == 1 and seen[0][0] != seen[0][1]
    assert b_states and set(b_states) == {"coasting"}           # B hidden by A: coasting, no misses


def test_occluded_obstacle_coasts_and_keeps_its_id():
    # B stands at 80 m; a near wall (30 m) covers it from t = 1 s to 2.5 s (22 maps, far more than M = 6 misses)
    rng = np.random.default_rng(15)
    b = np.array([80.0, 0.0, -8.0])
    wall = (np.array([30.0, 0.0, -8.0]), [0.5, 4.0, 4.0])
    for use_map in (True, False):
        tr = T.Tracker()
        ids, sig = [], []
        for k in range(int(4 * RATE_HZ)):
            t = k / RATE_HZ
            hidden = 1.0 <= t < 2.5
            meas = [] if hidden else [observe(b, HOVER, rng)]
            rmap = box_map(HOVER, [wall] if hidden else [(b, [0.5, 0.5, 3.0])])
            tr.update(meas, us(t), fov(HOVER, range_m=rmap) if use_map else fov(HOVER))
            bt = [tt for tt in tr.tracks if np.linalg.norm(tt.x[:3] - b) < 5.0]
            ids.append(bt[0].id if bt else None)
            if hidden and bt and use_map:
                assert bt[0].state == "coasting" and bt[0].misses == 0
                sig.append(bt[0].position_sigma_m())
            elif hidden and bt:
                assert bt[0].last_outcome == "miss" and bt[0].misses >= 1
        if use_map:
            assert None not in ids[3:] and len(set(ids[3:])) == 1         # one id before, during and after
            assert np.all(np.diff(sig) > 0)                                # covariance grows while coasting
        else:
            # without the map to explain the gap, every hidden map is a miss: deleted, a new id afterwards
            assert None in ids[int(1.5 * RATE_HZ):int(2.5 * RATE_HZ)]
            assert ids[-1] is not None and ids[-1] != ids[10]


def test_a_surface_within_the_tracks_range_sigma_along_the_axis_is_no_occluder_when_yawed():
    """The occlusion margin takes 3 of the track's position sigma along the camera's optical axis: with the vehicle
    yawed 45 deg, a track 80 m ahead with a range 1-sigma of 8 m (0.2 m across) and a map that sees a surface at
    65 m there: 15 m nearer is within 3 sigma = 24 m (the surface may be the track itself), so the map missed the
    track; a surface at 50 m (30 m nearer) hides it. The sigma across the ray (a row of the rotation taken for its
    column) would make the 8 % margin (6.4 m) decide and call the first map an occlusion."""
    st = VehicleState.from_ypr([0.0, 0.0, -10.0], [math.radians(45.0), 0.0, 0.0])
    axis = np.array([math.cos(math.radians(45.0)), math.sin(math.radians(45.0)), 0.0])
    p = st.position_ned_m + 80.0 * axis
    assert x_c(p, st) == pytest.approx(80.0)
    cov = T.camera_covariance(p, CAM, st, 8.0, 1.0, 1.0)
    for seen_m, outcome in ((65.0, "miss"), (50.0, T.OCCLUDED)):
        tr = T.Tracker(T.TrackerConfig(confirm_hits=1))
        tr.update([T.Measurement(p, cov)], us(0.0))
        trk, = tr.confirmed()
        tr.update([], us(1 / RATE_HZ), fov(st, range_m=np.full((CAM.height, CAM.width), seen_m, np.float32)))
        sigma_axis = math.sqrt(axis @ trk.P[:3, :3] @ axis)               # 8 m, and a little growth over 1/15 s
        assert 8.0 < sigma_axis < 8.1
        assert trk.last_outcome == outcome and trk.misses == (1 if outcome == "miss" else 0), seen_m


def test_a_surface_within_the_tracks_depth_along_the_axis_is_no_occluder():
    """The occlusion margin also takes the track's own depth along the optical axis: a building 10 m deep along the
    view (its extent 2, 10, 2 m in N, E, D) tracked at its centre 50 m east of a vehicle yawed 90 deg. A map that sees
    a surface at 44 m there (6 m nearer: beyond the 8 % margin, 4 m, and 3 of the track's 0.8 m sigma along the axis,
    but within its 10 m depth) sees the building itself, so the map missed the track; a surface at 38 m (12 m nearer)
    hides it. The depth is taken along the axis (east here), not north (2 m: the 4 m margin would decide)."""
    st = VehicleState.from_ypr([0.0, 0.0, -10.0], [math.radians(90.0), 0.0, 0.0])
    p = st.position_ned_m + np.array([0.0, 50.0, 0.0])
    assert x_c(p, st) == pytest.approx(50.0)
    cov = T.camera_covariance(p, CAM, st, 0.5, 1.0, 1.0)
    for seen_m, outcome in ((44.0, "miss"), (38.0, T.OCCLUDED)):
        tr = T.Tracker(T.TrackerConfig(confirm_hits=1))
        tr.update([T.Measurement(p, cov, [2.0, 10.0, 2.0])], us(0.0))
        trk, = tr.confirmed()
        np.testing.assert_allclose(trk.extent_ned_m, [2.0, 10.0, 2.0])
        tr.update([], us(1 / RATE_HZ), fov(st, range_m=np.full((CAM.height, CAM.width), seen_m, np.float32)))
        assert 3.0 * math.sqrt(trk.P[1, 1]) < 4.0                          # the 8 % margin is the larger of those two
        assert trk.last_outcome == outcome and trk.misses == (1 if outcome == "miss" else 0), seen_m


def test_a_confirmed_track_coasts_where_the_map_has_no_range():
    """A confirmed track whose pixel has no usable range in the next map (NaN: unmatched or unconfident there) was
    not looked at: no miss, its state coasting, as out of view or occluded (what the obstacle_tracks message says of
    it); and it outlives more than M = 6 such maps. Where the map sees the sky (infinity, a usable range) it is a
    miss and its state stays confirmed."""
    p = [50.0, 0.0, -10.0]
    nodata = np.full((CAM.height, CAM.width), np.nan, np.float32)
    tr = T.Tracker(T.TrackerConfig(confirm_hits=1))
    tr.update([T.Measurement(p, 0.04 * np.eye(3))], us(0.0), fov(HOVER))
    trk, = tr.confirmed()
    for k in range(1, 10):
        tr.update([], us(k / RATE_HZ), fov(HOVER, range_m=nodata))
        assert tr.tracks == [trk]
        assert (trk.last_outcome, trk.misses, trk.state) == (T.NO_DATA, 0, T.COASTING), k
    tr.update([], us(10 / RATE_HZ), fov(HOVER, range_m=np.full((CAM.height, CAM.width), np.inf, np.float32)))
    assert (trk.last_outcome, trk.misses, trk.state) == ("miss", 1, T.CONFIRMED)


def test_a_tentative_track_is_confirmed_within_confirm_window_s_or_dies_just_after():
    """A tentative track (2 hits of 3, hovering: the static-world test passes) that then coasts (no range at its
    pixel: no miss counted) lives while it may still be confirmed within confirm_window_s (1 s) of its birth: alive
    at exactly 1 s, gone 1 us later."""
    p = [50.0, 0.0, -10.0]
    nodata = np.full((CAM.height, CAM.width), np.nan, np.float32)
    for last_us, alive in ((us(1.0), True), (us(1.0) + 1, False)):
        tr = T.Tracker()
        tr.update([T.Measurement(p, 0.04 * np.eye(3))], us(0.0), fov(HOVER))
        tr.update([T.Measurement(p, 0.04 * np.eye(3))], us(1 / RATE_HZ), fov(HOVER))
        tr.update([], us(0.5), fov(HOVER, range_m=nodata))
        trk, = tr.tracks
        assert (trk.confirmed, trk.misses, trk.last_outcome, trk.verdict) == (False, 0, T.NO_DATA, T.STATIC)
        tr.update([], last_us, fov(HOVER, range_m=nodata))
        assert (tr.tracks == [trk]) is alive, last_us


def test_obstacle_leaving_view_coasts_then_is_deleted_and_returns_with_its_id_in_time():
    rng = np.random.default_rng(16)
    p = np.array([50.0, 0.0, -8.0])
    cfg = T.TrackerConfig(max_coast_s=2.0)

    def run(away_s):
        tr = T.Tracker(cfg)
        k, ids = 0, []
        t = 0.0
        while t < 1.0 + away_s + 1.0:
            t = k / RATE_HZ
            away = 1.0 <= t < 1.0 + away_s
            yaw = math.radians(60.0) if away else 0.0            # vehicle looks 60 deg to the right
            st = VehicleState.from_ypr(HOVER.position_ned_m, [yaw, 0.0, 0.0])
            assert fov(st).classify(p) == (T.OUT_OF_VIEW if away else T.VISIBLE)
            tr.update([] if away else [observe(p, st, rng)], us(t), fov(st))
            if away and tr.tracks:
                assert tr.tracks[0].state == "coasting" and tr.tracks[0].misses == 0
            ids.append(tr.tracks[0].id if tr.tracks else None)
            k += 1
        return ids

    ids = run(1.5)                                   # back within max_coast_s: the same id throughout
    assert None not in ids[2:] and len(set(ids[2:])) == 1
    ids = run(2.6)                                   # longer: deleted while away, a new track afterwards
    assert None in ids and ids[-1] is not None and ids[-1] != ids[5]


def test_snapshot_of_a_stalled_tracker_drops_a_well_measured_track_after_max_coast_s():
    """No map after the last hit (a stalled pipeline): ``snapshot`` reports the track up to ``max_coast_s`` after its
    last hit and leaves it out after, also a track measured 3 s long, whose predicted position sigma stays far below
    ``max_position_sigma_m`` (the other rule that drops a coasting track) over that time."""
    rng = np.random.default_rng(21)
    tr = T.Tracker()
    p = [50.0, 0.0, -8.0]
    for k in range(int(3 * RATE_HZ)):
        tr.update([observe(p, HOVER, rng)], us(k / RATE_HZ), fov(HOVER))
    trk, = tr.confirmed()
    limit = trk.last_hit_us + us(tr.cfg.max_coast_s)
    (t, x, P), = tr.snapshot(limit)
    assert t is trk and math.sqrt(np.diag(P)[:3].max()) < 0.5 * tr.cfg.max_position_sigma_m
    assert tr.snapshot(limit + 1) == []
    assert len(tr.tracks) == 1                                  # snapshot changes nothing


def test_field_of_view_classification():
    v = fov(HOVER)
    assert v.classify([50.0, 0.0, -10.0]) == T.VISIBLE
    assert v.classify([-50.0, 0.0, -10.0]) == T.OUT_OF_VIEW                 # behind
    assert v.classify([50.0, 50.0 * math.tan(math.radians(21.0)), -10.0]) == T.OUT_OF_VIEW   # beyond 20 deg
    assert v.classify([50.0, 50.0 * math.tan(math.radians(19.0)), -10.0]) == T.VISIBLE
    assert v.classify([101.0, 0.0, -10.0]) == T.OUT_OF_VIEW                 # beyond the listed distance
    r = np.full((240, 320), np.nan, np.float32)
    assert fov(HOVER, range_m=r).classify([50.0, 0.0, -10.0]) == T.NO_DATA
    r[:] = 40.0                                                              # 10 m nearer: occluded (10 % = 5 m)
    assert fov(HOVER, range_m=r).classify([50.0, 0.0, -10.0]) == T.OCCLUDED
    r[:] = 46.0                                                              # 4 m nearer: within the margin
    assert fov(HOVER, range_m=r).classify([50.0, 0.0, -10.0]) == T.VISIBLE
    r[:] = np.inf                                                            # sky where it should be: visible
    assert fov(HOVER, range_m=r).classify([50.0, 0.0, -10.0]) == T.VISIBLE
    with pytest.raises(InputError, match="range_m is"):
        fov(HOVER, range_m=np.zeros((10, 10)))


def test_field_of_view_vertical_edges():
    """The image's top and bottom edges: 240 rows at fy = 439.6 px see 15.2 deg above and below the axis
    (atan(119.5 / fy); 15.15 deg inside the 1 px edge margin); a point 14 deg below or above the level nose is
    visible, one 17 deg below or above is out of view. The rows end at the height (240), not at the width (320)."""
    v = fov(HOVER)
    for deg, want in ((14.0, T.VISIBLE), (17.0, T.OUT_OF_VIEW)):
        dz = 50.0 * math.tan(math.radians(deg))
        assert v.classify([50.0, 0.0, -10.0 + dz]) == want, ("below", deg)          # down is +D
        assert v.classify([50.0, 0.0, -10.0 - dz]) == want, ("above", deg)


def test_occlusion_looks_at_the_3_x_3_pixels_around_the_projected_one():
    """``occlusion_window_px`` = 1: the map is read in the 3 x 3 pixels centred on the track's projected pixel. A
    point 50 m ahead that projects exactly onto pixel (u, v) = (170, 130); a map without data (NaN) but for one pixel
    ranged at 40 m (10 m nearer, beyond the 8 % margin): any of the nine pixels of the window occludes the track, a
    pixel two away (outside the window) leaves it without data."""
    p = [50.0, 50.0 * (170 - CAM.cx) / F_PX, -10.0 + 50.0 * (130 - CAM.cy) / F_PX]
    for dv in (-2, -1, 0, 1, 2):
        for du in (-2, -1, 0, 1, 2):
            r = np.full((CAM.height, CAM.width), np.nan, np.float32)
            r[130 + dv, 170 + du] = 40.0
            want = T.OCCLUDED if max(abs(du), abs(dv)) <= 1 else T.NO_DATA
            assert fov(HOVER, range_m=r).classify(p) == want, (du, dv)


# -- velocity and time to contact ----------------------------------------------------------------------------------
@pytest.mark.parametrize("name, p0, v", [("crossing", [50.0, -12.0, -6.0], [0.0, 8.0, 0.0]),
                                         ("receding", [40.0, 3.0, -6.0], [8.0, 0.0, 0.0]),
                                         ("diagonal", [60.0, 10.0, -6.0], [-4.0, -4.0, 0.0])])
def test_moving_obstacle_velocity_within_20_percent(name, p0, v):
    rng = np.random.default_rng(17)
    # receding at 0.8 of the vehicle's speed along its path is what a phantom does: the static-world test holds it
    # (tests/test_tracking_follow.py); the velocity estimate is tested here with that test off
    tr = T.Tracker(T.TrackerConfig(follow_k=0.0) if name == "receding" else T.TrackerConfig())
    v = np.asarray(v)
    errs = []
    for k in range(int(4 * RATE_HZ)):
        t = k / RATE_HZ
        st = VehicleState.from_ypr([10.0 * t, 0.0, -10.0], [0.0, 0.0, 0.0])     # the vehicle flies north too
        tr.update([observe(np.asarray(p0) + v * t, st, rng)], us(t), fov(st))
        if t >= 1.5:
            trk, = tr.confirmed()
            errs.append(np.linalg.norm(trk.x[3:] - v) / np.linalg.norm(v))
            assert T.is_moving(trk.x, trk.P, tr.cfg), (name, t)
    assert max(errs) < 0.2, (name, max(errs))


def test_static_obstacle_is_mostly_not_moving():
    rng = np.random.default_rng(18)
    tr = T.Tracker()
    flags = []
    p = np.array([0.0, 4.0, -6.0])
    for k in range(int(7 * RATE_HZ)):                 # flying past it at 20 m/s, from 150 m to 10 m
        t = k / RATE_HZ
        st = VehicleState.from_ypr([20.0 * t - 150.0, 0.0, -10.0], [0.0, 0.0, 0.0])
        seen = fov(st).classify(p) == T.VISIBLE
        tr.update([observe(p, st, rng)] if seen else [], us(t), fov(st))
        c = tr.confirmed()
        if c and k > 5:
            flags.append(T.is_moving(c[0].x, c[0].P, tr.cfg))
    assert len(flags) > 50 and np.mean(flags) < 0.05


def test_constant_velocity_prediction_is_hand_derived():
    """``predict_state`` over dt = 0.5 s with an acceleration sigma of 2 m/s^2 (q = 4 m^2/s^3), from P = diag(a I,
    b I): per axis the position moves by v dt, and the covariance is F P F^T + Q, hand-derived as
    [[a + b dt^2 + q dt^3/3, b dt + q dt^2/2], [b dt + q dt^2/2, b + q dt]]; the axes stay uncorrelated. The default
    sigma (1 m/s^2) is its own square, so only another value tells q = sigma^2 from sigma."""
    cfg = T.TrackerConfig(accel_sigma_mps2=2.0)
    x = np.array([10.0, -20.0, -5.0, 4.0, -6.0, 0.5])
    a, b, dt, q = 0.3, 2.0, 0.5, 4.0
    P = np.diag([a] * 3 + [b] * 3)
    x1, P1 = T.predict_state(x, P, dt, cfg)
    np.testing.assert_allclose(x1, [12.0, -23.0, -4.75, 4.0, -6.0, 0.5], rtol=1e-12)
    pp, pv, vv = a + b * dt ** 2 + q * dt ** 3 / 3, b * dt + q * dt ** 2 / 2, b + q * dt      # 0.9667, 1.5, 4.0
    want = np.block([[pp * np.eye(3), pv * np.eye(3)], [pv * np.eye(3), vv * np.eye(3)]])
    np.testing.assert_allclose(P1, want, rtol=1e-12, atol=1e-15)
    x0, P0 = T.predict_state(x, P, 0.0, cfg)                       # no time, no change
    np.testing.assert_allclose(x0, x, rtol=0, atol=0)
    np.testing.assert_allclose(P0, P, rtol=0, atol=0)


def _head_on(rng, speed=20.0, wall_n=100.0):
    """Vehicle flying north at ``speed`` towards a wall face at north ``wall_n`` (10 m wide, 10 m tall).
    Yields (true time to contact of the 1 m vehicle sphere with the face, nearest threat or None)."""
    tr = T.Tracker()
    cone = T.ConeConfig(vehicle_radius_m=1.0)
    t = 0.0
    k = 0
    while True:
        t = k / RATE_HZ
        n = -20.0 + speed * t
        true_ttc = (wall_n - 1.0 - n) / speed
        if true_ttc < 0.3:
            return
        st = VehicleState.from_ypr([n, 0.0, -6.0], [0.0, 0.0, 0.0])
        face = np.array([wall_n, 0.5, -5.0])                   # median point of the face seen
        if x_c(face, st) <= 100.0:
            tr.update([observe(face, st, rng, extent=(0.2, 10.0, 10.0))], us(t), fov(st))
        own = T.Ownship.from_state(st, [speed, 0.0, 0.0], us(t))
        yield true_ttc, T.nearest_threat(T.assess(tr.snapshot(us(t)), own, us(t), cone))
        k += 1


def test_head_on_time_to_contact_within_10_percent_from_3_s():
    rng = np.random.default_rng(19)
    n = 0
    for true_ttc, threat in _head_on(rng):
        if true_ttc <= 3.0:
            assert threat is not None
            assert threat.time_to_contact_s == pytest.approx(true_ttc, rel=0.10), true_ttc
            n += 1
    assert n >= 40


def test_collision_cone_edges_and_bearings_hand_derived():
    tr = T.Tracker(T.TrackerConfig(confirm_hits=1))
    cov = np.diag([0.04, 0.04, 0.04])                       # 0.2 m 1-sigma on every axis
    # vehicle at the origin heading east (yaw 90 deg), flying east at 10 m/s
    st = VehicleState.from_ypr([0.0, 0.0, -10.0], [math.radians(90.0), 0.0, 0.0])
    cone = T.ConeConfig(vehicle_radius_m=1.0, k_sigma=2.0)
    h = 1.0 + 0.5 * 2.0 + 2.0 * 0.2                          # inflated half width across: radius + ext/2 + k sigma
    inside = np.array([0.0, 50.0, -10.0 + h - 0.05])        # 2.35 m below the path's line: in the cone
    outside = np.array([5.0, 50.0, -10.0 - h - 0.05])       # above by more than h, and 5 m to the north
    north = np.array([30.0, 0.0, -10.0])                    # abeam to port
    tr.update([T.Measurement(p, cov, np.array([2.0, 2.0, 2.0])) for p in (inside, outside, north)], us(0.0))
    own = T.Ownship.from_state(st, [0.0, 10.0, 0.0], us(0.0))
    views = T.assess(tr.snapshot(us(0.0)), own, us(0.0), cone)
    vi, vo, vn = views
    assert vi.in_cone and not vo.in_cone and not vn.in_cone
    # entry into the box [50 - 2.4, 50 + 2.4] east at 10 m/s
    assert vi.time_to_contact_s == pytest.approx((50.0 - h) / 10.0, rel=1e-9)
    assert vi.closing_speed_mps == pytest.approx(10.0 * 50.0 / np.linalg.norm(inside - st.position_ned_m))
    # bearings in body FRD: the vehicle faces east, so north is 90 deg to port; "outside" is up and left
    assert vn.azimuth_frd_rad == pytest.approx(-math.pi / 2) and vn.elevation_frd_rad == pytest.approx(0.0, abs=1e-12)
    assert vo.azimuth_frd_rad == pytest.approx(-math.atan2(5.0, 50.0))
    assert vo.elevation_frd_rad == pytest.approx(math.atan2(h + 0.05, math.hypot(5.0, 50.0)))
    assert vn.distance_m == pytest.approx(30.0) and vn.surface_distance_m == pytest.approx(29.0)
    assert T.nearest_threat(views) is vi
    # the velocity unknown: nothing in the cone; hovering: nothing either (no direction), unless inside
    unknown = T.Ownship.from_state(st, [math.nan] * 3, us(0.0))
    assert not any(v.in_cone for v in T.assess(tr.snapshot(us(0.0)), unknown, us(0.0), cone))
    hover = T.Ownship.from_state(VehicleState.from_ypr(inside + [0.0, 0.5, 0.0], [0.0, 0.0, 0.0]), [0, 0, 0], 0)
    hv = T.assess(tr.snapshot(us(0.0)), hover, us(0.0), cone)
    assert hv[0].in_cone and hv[0].time_to_contact_s == 0.0 and not hv[2].in_cone
    # beyond the horizon: not a threat
    far = T.assess(tr.snapshot(us(0.0)), own, us(0.0), T.ConeConfig(horizon_s=4.0))
    assert not far[0].in_cone


def test_box_entry_time_slabs():
    assert T.box_entry_time([10.0, 0.0, 0.0], [1.0, 1.0, 1.0], [2.0, 0.0, 0.0]) == pytest.approx(4.5)
    assert T.box_entry_time([10.0, 0.0, 0.0], [1.0, 1.0, 1.0], [-2.0, 0.0, 0.0]) is None       # moving away
    assert T.box_entry_time([10.0, 1.5, 0.0], [1.0, 1.0, 1.0], [2.0, 0.0, 0.0]) is None        # passes beside
    assert T.box_entry_time([10.0, 10.0, 0.0], [1.0, 1.0, 1.0], [1.0, 1.0, 0.0]) == pytest.approx(9.0)
    assert T.box_entry_time([0.5, 0.0, 0.0], [1.0, 1.0, 1.0], [0.0, 0.0, 0.0]) == 0.0          # inside


def test_moving_obstacle_coming_at_a_hovering_vehicle_is_a_threat():
    rng = np.random.default_rng(20)
    tr = T.Tracker()
    for k in range(int(3 * RATE_HZ)):
        t = k / RATE_HZ
        tr.update([observe([80.0 - 10.0 * t, 0.0, -10.0], HOVER, rng, extent=(1.0, 1.0, 1.0))], us(t), fov(HOVER))
    own = T.Ownship.from_state(HOVER, [0.0, 0.0, 0.0], us(t))
    th = T.nearest_threat(T.assess(tr.snapshot(us(t)), own, us(t)))
    true_ttc = (80.0 - 10.0 * t - 0.5 - 1.0) / 10.0
    assert th is not None and th.time_to_contact_s == pytest.approx(true_ttc, rel=0.1)


def test_nearest_threat_is_the_soonest_contact_not_the_nearest_surface():
    """Two tracks on the path of a vehicle flying north at 10 m/s: one 30 m ahead ranged to 0.2 m, one 40 m ahead
    ranged to 6 m (its box grows by 2 sigma = 12 m along the path). Hand-derived contacts: (30 - 1 - 0.4) / 10 =
    2.86 s and (40 - 1 - 12) / 10 = 2.7 s: the farther one is the nearest threat (it can be met first)."""
    tr = T.Tracker(T.TrackerConfig(confirm_hits=1))
    near = T.Measurement([30.0, 0.0, -10.0], np.diag([0.04, 0.04, 0.04]))
    vague = T.Measurement([40.0, 3.0, -10.0], np.diag([36.0, 0.04, 0.04]), [0.0, 8.0, 0.0])   # 3 m east, 8 m wide
    tr.update([near, vague], us(0.0))
    own = T.Ownship.from_state(HOVER, [10.0, 0.0, 0.0], us(0.0))
    views = T.assess(tr.snapshot(us(0.0)), own, us(0.0), T.ConeConfig(vehicle_radius_m=1.0, k_sigma=2.0))
    vn, vv = views
    assert vn.time_to_contact_s == pytest.approx(2.86) and vv.time_to_contact_s == pytest.approx(2.7)
    assert vn.surface_distance_m == pytest.approx(30.0) and vv.surface_distance_m == pytest.approx(40.0)
    assert T.nearest_threat(views) is vv


def test_surface_distance_to_obstacles_south_west_and_above():
    """2 m cubes 30 m south, 30 m west and 30 m above a hovering vehicle: each surface is 29 m away, as the one 30 m
    north (the box's near face is on the vehicle's side whatever the sign of the offset). Catches the absolute value
    dropped from the surface distance (those behind the NED axes came out at 0 m)."""
    tr = T.Tracker(T.TrackerConfig(confirm_hits=1))
    offsets = ([-30.0, 0.0, 0.0], [0.0, -30.0, 0.0], [0.0, 0.0, -30.0], [30.0, 0.0, 0.0])
    tr.update([T.Measurement(HOVER.position_ned_m + o, np.diag([0.04] * 3), [2.0, 2.0, 2.0]) for o in offsets],
              us(0.0))
    views = T.assess(tr.snapshot(us(0.0)), T.Ownship.from_state(HOVER, [0.0, 0.0, 0.0], us(0.0)), us(0.0))
    assert len(views) == 4
    for v in views:
        assert v.distance_m == pytest.approx(30.0) and v.surface_distance_m == pytest.approx(29.0)


def _view_ahead(north_m):
    """One fresh point track (0.5 m 1-sigma per axis) ``north_m`` ahead of a vehicle flying north at 10 m/s, assessed
    with the default cone."""
    tr = T.Tracker(T.TrackerConfig(confirm_hits=1))
    tr.update([T.Measurement(HOVER.position_ned_m + [north_m, 0.0, 0.0], np.diag([0.25] * 3))], us(0.0))
    v, = T.assess(tr.snapshot(us(0.0)), T.Ownship.from_state(HOVER, [10.0, 0.0, 0.0], us(0.0)), us(0.0))
    return v


def test_a_contact_at_exactly_the_horizon_is_a_threat():
    """Default cone (radius 1 m, 2 sigma, horizon 30 s): a point 302 m ahead is entered 302 - 1 - 2 x 0.5 = 300 m
    out, at 10 m/s exactly 30 s: in the cone with time to contact 30 s ("within horizon_s"); 1 m farther, 30.1 s,
    it is not. Catches '<' for '<=' at the horizon in assess."""
    v = _view_ahead(302.0)
    assert v.in_cone and v.time_to_contact_s == 30.0
    v = _view_ahead(303.0)
    assert not v.in_cone and math.isnan(v.time_to_contact_s)


def test_nearest_threat_ties_go_to_the_nearer_surface():
    """Two 1 m cubes 30 m ahead of a vehicle flying north at 10 m/s, one on the path, one 3 m east but 5 m wide (the
    path runs through its grown box): both entered at (30 - 0.5 - 1 - 2 x 0.2) / 10 = 2.81 s, a tie; the nearest
    threat is the one whose surface is nearer (29.5 m, not hypot(29.5, 0.5)) whichever comes first in the snapshot.
    Catches the surface distance dropped from nearest_threat's key (the first listed won)."""
    tr = T.Tracker(T.TrackerConfig(confirm_hits=1))
    cov = np.diag([0.04] * 3)
    tr.update([T.Measurement(HOVER.position_ned_m + [30.0, 3.0, 0.0], cov, [1.0, 5.0, 1.0]),
               T.Measurement(HOVER.position_ned_m + [30.0, 0.0, 0.0], cov, [1.0, 1.0, 1.0])], us(0.0))
    views = T.assess(tr.snapshot(us(0.0)), T.Ownship.from_state(HOVER, [10.0, 0.0, 0.0], us(0.0)), us(0.0),
                     T.ConeConfig(vehicle_radius_m=1.0, k_sigma=2.0))
    wide, on_path = views
    assert wide.in_cone and on_path.in_cone
    assert wide.time_to_contact_s == on_path.time_to_contact_s == pytest.approx(2.81)
    assert on_path.surface_distance_m == pytest.approx(29.5)
    assert wide.surface_distance_m == pytest.approx(math.hypot(29.5, 0.5))
    assert T.nearest_threat(views) is on_path
    assert T.nearest_threat(views[::-1]) is on_path


# -- message and publisher ----------------------------------------------------------------------------------------
def _tracker_with_tracks():
    tr = T.Tracker(T.TrackerConfig(confirm_hits=2))
    cov = np.diag([0.25, 0.04, 0.04])
    for k in range(2):
        tr.update([T.Measurement([40.0 + k, 0.0, -10.0], cov, [0.5, 2.0, 2.0], 120, 0.8, "nose"),
                   T.Measurement([60.0, 20.0, -10.0], cov, [1.0, 1.0, 5.0], 40, 0.7, "nose")], us(k * 0.1))
    tr.update([T.Measurement([90.0, -5.0, -3.0], cov)], us(0.2))            # tentative
    return tr


def _own(t_s=0.2, v=(10.0, 0.0, 0.0)):
    return T.Ownship.from_state(HOVER, v, us(t_s))


def test_message_round_trip_and_contents():
    tr = _tracker_with_tracks()
    msg = GP.build(tr, _own(), us(0.25), seq=7, trigger="timer", stale_after_s=0.5)
    back = G.decode(G.encode(msg))
    assert back["kind"] == "obstacle_tracks" and back["v"] == 1 and back["seq"] == 7
    assert back["status"] == "ok" and back["map_age_s"] == pytest.approx(0.05)
    assert back["map_stamp_us"] == us(0.2) and back["n_tentative"] == 1
    assert len(back["tracks"]) == 2                      # the tentative one is counted, not published
    near = min(back["tracks"], key=lambda t: t["distance_m"])
    snap = {t.id: (x, P) for t, x, P in tr.snapshot(us(0.25))}
    x, P = snap[near["id"]]
    np.testing.assert_allclose(near["position_ned_m"], x[:3])
    np.testing.assert_allclose(near["position_cov_ned_m2"], P[:3, :3])
    np.testing.assert_allclose(near["velocity_cov_ned_m2_per_s2"], P[3:, 3:])
    # the vehicle is carried to now by its velocity: 10 m/s x 0.05 s
    np.testing.assert_allclose(back["position_ned_m"], HOVER.position_ned_m + [0.5, 0.0, 0.0])
    assert near["distance_m"] == pytest.approx(np.linalg.norm(x[:3] - back["position_ned_m"]))
    assert near["camera_id"] == "nose" and near["pixel_count"] == 120 and near["state"] == "confirmed"
    th = back["nearest_threat"]
    assert th["id"] == near["id"] and near["in_cone"]
    assert th["time_to_contact_s"] == pytest.approx(near["time_to_contact_s"])
    np.testing.assert_allclose(back["q_wxyz"], [1.0, 0.0, 0.0, 0.0], atol=1e-12)


def test_message_attitude_is_body_to_ned_for_a_turned_vehicle():
    """q_wxyz is the body FRD -> NED rotation (as nav_state): heading east (yaw 90 deg) is a +90 deg turn about
    down, [cos 45, 0, 0, sin 45], and takes the nose [1, 0, 0] to east; nose up 30 deg is +30 deg about the right
    wing, [cos 15, 0, sin 15, 0], and takes the nose to north and up (down -0.5)."""
    from eonav.geometry.frames import rotation_from_quat_wxyz
    c45, c15, s15 = math.cos(math.pi / 4), math.cos(math.radians(15)), math.sin(math.radians(15))
    for ypr, want, nose_ned in (((90.0, 0.0, 0.0), [c45, 0.0, 0.0, c45], [0.0, 1.0, 0.0]),
                                ((0.0, 30.0, 0.0), [c15, 0.0, s15, 0.0], [math.sqrt(0.75), 0.0, -0.5])):
        st = VehicleState.from_ypr([0.0, 0.0, -10.0], np.radians(ypr))
        msg = GP.build(T.Tracker(), T.Ownship.from_state(st, [0.0, 0.0, 0.0], us(0.0)), us(0.0), seq=0,
                       trigger="timer", stale_after_s=0.5)
        q = G.decode(G.encode(msg))["q_wxyz"]
        np.testing.assert_allclose(q, want, atol=1e-12)
        np.testing.assert_allclose(rotation_from_quat_wxyz(q) @ [1.0, 0.0, 0.0], nose_ned, atol=1e-12)


def test_message_carries_a_coasting_track():
    """A confirmed track 40 m north of a hovering vehicle that then turns to face east (yaw 90 deg): the obstacle is
    abeam, out of view, and the track coasts (docs/guidance.md: the message holds confirmed and coasting tracks,
    ``state`` "coasting", no miss counted). The message encodes and decodes with it; a validator that knew only
    "confirmed" would refuse every message while an obstacle is occluded or out of view."""
    tr = T.Tracker(T.TrackerConfig(confirm_hits=2))
    cov = np.diag([0.25, 0.04, 0.04])
    for k in range(2):
        tr.update([T.Measurement([40.0, 0.0, -10.0], cov, [1.0, 1.0, 1.0])], us(k * 0.1), fov(HOVER))
    east = VehicleState.from_ypr(HOVER.position_ned_m, [math.radians(90.0), 0.0, 0.0])
    assert fov(east).classify([40.0, 0.0, -10.0]) == T.OUT_OF_VIEW
    tr.update([], us(0.2), fov(east))
    trk, = tr.confirmed()
    assert trk.state == "coasting" and trk.misses == 0
    back = G.decode(G.encode(GP.build(tr, T.Ownship.from_state(east, [0.0, 0.0, 0.0], us(0.2)), us(0.2), seq=0,
                                      trigger="map", stale_after_s=0.5)))
    t, = back["tracks"]
    assert t["id"] == trk.id and t["state"] == "coasting" and t["misses"] == 0
    assert t["azimuth_frd_rad"] == pytest.approx(-math.pi / 2)          # north is 90 deg to port of an east heading


def test_message_track_age_and_time_since_update_in_seconds():
    """A track born at 0 s and detected again at 0.1 s, missed at 0.2 s, published at 0.4 s: ``age_s`` 0.4 s since it
    was started and ``time_since_update_s`` 0.3 s since its last detection (a miss is no update), both in seconds
    (docs/guidance.md)."""
    tr = T.Tracker(T.TrackerConfig(confirm_hits=2))
    cov = np.diag([0.25, 0.04, 0.04])
    for k in range(2):
        tr.update([T.Measurement([40.0, 0.0, -10.0], cov, [1.0, 1.0, 1.0])], us(k * 0.1))
    tr.update([], us(0.2))
    trk, = tr.confirmed()
    assert trk.misses == 1
    back = G.decode(G.encode(GP.build(tr, _own(0.4, (0.0, 0.0, 0.0)), us(0.4), seq=0, trigger="timer",
                                      stale_after_s=0.5)))
    t, = back["tracks"]
    assert t["age_s"] == pytest.approx(0.4, abs=1e-9) and t["time_since_update_s"] == pytest.approx(0.3, abs=1e-9)
    assert t["hits"] == 2 and t["misses"] == 1


def test_nearest_threat_is_a_confirmed_track_even_when_a_tentative_one_comes_first():
    """A tentative track 30 m ahead (one detection, maybe clutter) and a confirmed one 60 m ahead, both on the path
    of a vehicle flying north at 10 m/s: the message's nearest threat is the confirmed one (what the message's
    tracks hold); the tentative one is in the cone and would have come first."""
    tr = T.Tracker(T.TrackerConfig(confirm_hits=2))
    cov = np.diag([0.25, 0.04, 0.04])
    for k in range(2):
        tr.update([T.Measurement([60.0, 0.0, -10.0], cov, [1.0, 2.0, 2.0])], us(k * 0.1))
    tr.update([T.Measurement([60.0, 0.0, -10.0], cov, [1.0, 2.0, 2.0]),
               T.Measurement([30.0, 0.0, -10.0], cov, [1.0, 2.0, 2.0])], us(0.2))
    conf, = tr.confirmed()
    tent = next(t for t in tr.tracks if not t.confirmed)
    own = _own(0.2, (10.0, 0.0, 0.0))
    views = {v.track.id: v for v in T.assess(tr.snapshot(us(0.2)), own, us(0.2))}
    assert views[tent.id].in_cone and views[tent.id].time_to_contact_s < views[conf.id].time_to_contact_s
    msg = GP.build(tr, own, us(0.2), seq=0, trigger="map", stale_after_s=0.5)
    assert msg["nearest_threat"]["id"] == conf.id and msg["n_tentative"] == 1
    assert msg["nearest_threat"]["time_to_contact_s"] == pytest.approx(views[conf.id].time_to_contact_s)
    assert G.decode(G.encode(msg))["nearest_threat"]["id"] == conf.id


def test_message_says_moving_for_the_moving_obstacle_only():
    """Noise-free detections at 15 Hz for 3 s of an obstacle closing on a hovering vehicle at 10 m/s and of a static
    one: the message's ``moving`` (the chi-square test docs/guidance.md gives; it decides whether the autopilot's
    OBSTACLE_DISTANCE_3D carries the track along its velocity) is true for the first only, whose velocity is the
    true -10 m/s north. Catches ``moving`` published as true for every track."""
    tr = T.Tracker(T.TrackerConfig(confirm_hits=2))
    cov = np.diag([0.25, 0.04, 0.04])
    for k in range(int(3 * RATE_HZ)):
        t = k / RATE_HZ
        tr.update([T.Measurement([80.0 - 10.0 * t, 0.0, -10.0], cov, [1.0, 1.0, 1.0]),
                   T.Measurement([60.0, 20.0, -10.0], cov, [1.0, 1.0, 1.0])], us(t))
    msg = GP.build(tr, _own(t, (0.0, 0.0, 0.0)), us(t), seq=0, trigger="map", stale_after_s=0.5)
    by_east = sorted(msg["tracks"], key=lambda x: x["position_ned_m"][1])
    mover, static = by_east
    assert static["position_ned_m"][1] == pytest.approx(20.0) and mover["position_ned_m"][1] == pytest.approx(0.0)
    assert mover["moving"] is True and static["moving"] is False
    assert mover["velocity_ned_mps"][0] == pytest.approx(-10.0, rel=0.05)


def test_message_status_is_ok_up_to_exactly_stale_after_s():
    """The newest map 0.5 s old with stale_after_s 0.5 is "ok" ("at most stale_after_s old", docs/guidance.md); 1 us
    older it is "stale". Catches '<' for '<=' in the status."""
    tr = T.Tracker(T.TrackerConfig(confirm_hits=1))
    tr.update([T.Measurement([40.0, 0.0, -10.0], np.eye(3) * 0.1, [1.0, 1.0, 1.0])], us(1.0))
    own = _own(1.0, (0.0, 0.0, 0.0))
    m = GP.build(tr, own, us(1.5), seq=0, trigger="timer", stale_after_s=0.5)
    assert m["status"] == "ok" and m["map_age_s"] == 0.5
    m = GP.build(tr, own, us(1.5) + 1, seq=1, trigger="timer", stale_after_s=0.5)
    assert m["status"] == "stale" and m["map_age_s"] == pytest.approx(0.500001)


def test_message_of_a_map_stamped_after_now_has_age_zero_and_encodes():
    """A map stamped 10 ms after the publisher's now (the camera host's clock a little ahead): map_age_s is 0, not
    -0.01 s, status ok, and the message passes the schema, which refuses a negative age. Catches the clamp at 0
    dropped from the age (the message failed the schema; only a timing-dependent service test saw it)."""
    tr = T.Tracker(T.TrackerConfig(confirm_hits=1))
    tr.update([T.Measurement([40.0, 0.0, -10.0], np.eye(3) * 0.1, [1.0, 1.0, 1.0])], us(1.01))
    m = GP.build(tr, _own(1.0, (0.0, 0.0, 0.0)), us(1.0), seq=0, trigger="timer", stale_after_s=0.5)
    assert m["status"] == "ok" and m["map_age_s"] == 0.0 and m["map_stamp_us"] == us(1.01)
    assert G.decode(G.encode(m))["map_age_s"] == 0.0


def test_message_registers_in_the_project_schema(monkeypatch):
    from eonav.bus import schema
    monkeypatch.setitem(schema.FIELDS, G.KIND, G.FIELDS)
    msg = GP.build(_tracker_with_tracks(), _own(), us(0.25), seq=1, trigger="map", stale_after_s=0.5)
    top = schema.decode(G.encode(msg), expect=G.KIND)
    assert top["seq"] == 1 and len(top["tracks"]) == 2
    fields = {k: v for k, v in msg.items() if k not in ("kind", "v")}
    assert G.decode(schema.encode(G.KIND, **G._plain(fields)))["tracks"][0]["id"] == msg["tracks"][0]["id"]


def test_message_validation_errors_name_the_field():
    good = G._plain({"kind": G.KIND, "v": G.SCHEMA_VERSION,
                     **GP.build(_tracker_with_tracks(), _own(), us(0.25), seq=1, trigger="map", stale_after_s=0.5)})
    G.validate(good)

    def bad(change, match):
        import copy
        m = copy.deepcopy(good)
        change(m)
        with pytest.raises(SchemaError, match=match):
            G.decode(G.msgpack.packb(m, use_bin_type=True))

    bad(lambda m: m.pop("map_age_s"), r"obstacle_tracks\.map_age_s: missing")
    bad(lambda m: m.update(seq="1"), r"obstacle_tracks\.seq: expected an integer")
    bad(lambda m: m.update(status="fine"), r"status: expected one of")
    bad(lambda m: m.update(trigger="poll"), r"trigger: expected one of")
    bad(lambda m: m.update(v=2), "unsupported schema version 2")
    bad(lambda m: m.update(kind="obstacle_list"), "expected a obstacle_tracks message")
    bad(lambda m: m.update(position_ned_m=[1.0, 2.0]), r"position_ned_m: expected a list of 3 numbers")
    bad(lambda m: m["tracks"][0].pop("velocity_ned_mps"), r"tracks\[0\]\.velocity_ned_mps: missing")
    bad(lambda m: m["tracks"][0].update(position_cov_ned_m2=[1.0] * 9), r"tracks\[0\]\.position_cov_ned_m2: "
                                                                          r"expected a 3 x 3")
    bad(lambda m: m["tracks"][0].update(state="tentative"), r"tracks\[0\]\.state: expected one of")
    bad(lambda m: m["tracks"][0].update(moving=1), r"tracks\[0\]\.moving: expected true or false")
    bad(lambda m: m["tracks"][1].update(position_ned_m=[math.nan, 0.0, 0.0]), r"tracks\[1\]\.position_ned_m: "
                                                                               r"expected finite")
    bad(lambda m: m["tracks"][1].update(id=m["tracks"][0]["id"]), "ids must be unique")
    bad(lambda m: m["nearest_threat"].update(id=999), "nearest_threat.id 999 is not one of the tracks")
    bad(lambda m: m.update(map_age_s=-0.1), "map_age_s: expected >= 0")
    with pytest.raises(SchemaError, match="not msgpack"):
        G.decode(b"\xc1\xc1")
    with pytest.raises(SchemaError, match="unknown field"):
        G.encode({**good, "speed": 3.0})
    with pytest.raises(SchemaError, match="missing required"):
        G.encode({k: v for k, v in good.items() if k != "tracks"})


def test_message_fields_left_out_read_as_unknown():
    """The optional top-level fields a publisher may leave out (an older or external one) read as their documented
    "unknown" (docs/guidance.md): vehicle velocity NaN (then nothing is in the cone; never a hovering vehicle),
    ``nav_stamp_us`` -1 (the map's capture pose), no tentative tracks, no nearest threat."""
    msg = G._plain({"kind": G.KIND, "v": G.SCHEMA_VERSION,
                    **GP.build(_tracker_with_tracks(), _own(), us(0.25), seq=1, trigger="map", stale_after_s=0.5)})
    for name in ("velocity_ned_mps", "nav_stamp_us", "n_tentative", "nearest_threat"):
        del msg[name]
    back = G.decode(G.msgpack.packb(msg, use_bin_type=True))
    assert back["velocity_ned_mps"].shape == (3,) and np.all(np.isnan(back["velocity_ned_mps"]))
    assert back["nav_stamp_us"] == -1 and back["n_tentative"] == 0 and back["nearest_threat"] is None
    assert len(back["tracks"]) == 2


def test_message_validation_refuses_infinite_track_states():
    """A track's position, velocity or covariance must be finite numbers (docs/guidance.md): +inf or -inf in any of
    them is refused naming the field, as NaN is (an infinite position would read as "infinitely far: no threat")."""
    good = G._plain({"kind": G.KIND, "v": G.SCHEMA_VERSION,
                     **GP.build(_tracker_with_tracks(), _own(), us(0.25), seq=1, trigger="map", stale_after_s=0.5)})
    G.validate(good)
    for name, bad in (("position_ned_m", [math.inf, 0.0, -10.0]), ("velocity_ned_mps", [0.0, -math.inf, 0.0]),
                      ("position_cov_ned_m2", [[math.inf, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]]),
                      ("velocity_cov_ned_m2_per_s2", [[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, math.inf]])):
        m = {**good, "tracks": [dict(good["tracks"][0], **{name: bad}), good["tracks"][1]]}
        with pytest.raises(SchemaError, match=rf"tracks\[0\]\.{name}: expected finite"):
            G.decode(G.msgpack.packb(m, use_bin_type=True))


def test_message_map_age_is_never_negative_infinite_or_nan():
    """``map_age_s`` is >= 0 s, +inf when there is no map yet (docs/guidance.md): a message of a tracker that has
    seen no map decodes with +inf; the same message with -inf (a negative age: "fresher than fresh") or NaN is
    refused naming the field, as -0.1 s is."""
    empty = G._plain({"kind": G.KIND, "v": G.SCHEMA_VERSION,
                      **GP.build(T.Tracker(), _own(), us(0.25), seq=0, trigger="timer", stale_after_s=0.5)})
    back = G.decode(G.msgpack.packb(empty, use_bin_type=True))
    assert back["status"] == "no_map" and back["map_age_s"] == math.inf
    for bad in (-math.inf, math.nan, -0.1):
        with pytest.raises(SchemaError, match="map_age_s: expected >= 0"):
            G.decode(G.msgpack.packb({**empty, "map_age_s": bad}, use_bin_type=True))


def test_publisher_timer_grid_map_trigger_and_stall():
    tr = T.Tracker(T.TrackerConfig(confirm_hits=1))
    pub = GP.GuidancePublisher(tr, rate_hz=10.0, stale_after_s=0.5)
    own = _own(0.0, (0.0, 0.0, 0.0))
    t0 = us(100.0)
    m = pub.on_tick(t0, own)                                         # first call starts the grid
    assert m["trigger"] == "timer" and m["status"] == "no_map" and math.isinf(m["map_age_s"])
    assert m["map_stamp_us"] == -1 and m["tracks"] == []
    assert pub.on_tick(t0 + 99_999, own) is None and pub.wait_s(t0 + 99_999) == pytest.approx(1e-6)
    assert pub.on_tick(t0 + 100_000, own)["seq"] == 1
    # a map (captured 30 ms ago) arrives between ticks: published at once, the grid is unchanged
    tr.update([T.Measurement([40.0, 0.0, -10.0], np.eye(3) * 0.1, [1.0, 1.0, 1.0])], t0 + 120_000)
    m = pub.on_map(t0 + 150_000, own)
    assert m["trigger"] == "map" and m["status"] == "ok" and m["map_age_s"] == pytest.approx(0.03)
    assert [t["id"] for t in m["tracks"]] == [1] and m["seq"] == 2
    assert pub.on_tick(t0 + 199_000, own) is None
    assert pub.on_tick(t0 + 200_000, own)["trigger"] == "timer"
    # a late caller gets one message and the next tick stays on the grid
    m = pub.on_tick(t0 + 470_000, own)
    assert m is not None and pub.next_tick_us == t0 + 500_000
    # the stall: no map after t0 + 120 ms; ok up to 0.5 s of age, stale after, tracks kept while coasting
    assert pub.on_tick(t0 + 600_000, own)["status"] == "ok"            # age 0.48 s
    m = pub.on_tick(t0 + 700_000, own)
    assert m["status"] == "stale" and m["map_age_s"] == pytest.approx(0.58) and len(m["tracks"]) == 1
    # past max_coast_s without a map the tracks are gone from the message, the status still says stale
    m = pub.on_tick(t0 + 120_000 + us(tr.cfg.max_coast_s) + 1, own)
    assert m["status"] == "stale" and m["tracks"] == []
    with pytest.raises(InputError, match="rate_hz"):
        GP.GuidancePublisher(tr, rate_hz=0.0)


def test_tracking_and_message_modules_import_no_transport():
    code = "import eonav.obstacles.tracking, eonav.bus.guidance_msg, sys; print('zenoh' in sys.modules)"
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True).stdout
    assert out.strip() == "False"
