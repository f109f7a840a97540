"""Real lenses (eonav.io.calibration): calibration files of each format written from known values give the camera and
the remap tables cv2 computes from those values; the output camera has no black border and no wasted field; Kalibr
extrinsics project like the pair-file mount; pair and cameras files undistort on load and reject unknown keys; a
simulated distorted camera ranges, after undistortion, about as well as a pinhole one (and badly without it)."""
import copy
import json
import time

import cv2
import numpy as np
import pytest

from eonav import InputError
from eonav.io.calibration import (DistortedCamera, Undistorter, frame_correction, load_calibration,
                               mount_from_T_cam_imu, output_camera_matrix)
from eonav.geometry.camera import Camera, View
from eonav.geometry.frames import T_PAPERCAM_OPTICAL, T_cam_body_from_eps
from eonav.io.pairfile import camera_to_dict, load_camera_models, load_cameras, load_pair_file

W, H = 64, 48
K_VALUES = dict(fx=52.0, fy=51.5, cx=32.7, cy=23.2)
RADTAN = (-0.21, 0.045, 1.2e-3, -6e-4, 0.0)
RATIONAL = (-0.2, 0.04, 1e-3, -5e-4, 0.0, 0.01, 0.002, 0.0)
EQUI = (-0.03, 0.008, -0.002, 0.0004)
CRIT = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 100, 1e-12)


def K_of(v=K_VALUES):
    return np.array([[v["fx"], 0, v["cx"]], [0, v["fy"], v["cy"]], [0, 0, 1.0]])


def cv2_maps(model, coeffs, K_new, K=None, size=(W, H)):
    """The tables cv2 computes directly from the known values (the reference)."""
    K = K_of() if K is None else K
    if model == "equidistant":
        return cv2.fisheye.initUndistortRectifyMap(K, np.array(coeffs).reshape(-1, 1), np.eye(3), K_new, size,
                                                   cv2.CV_32FC1)
    return cv2.initUndistortRectifyMap(K, np.array(coeffs), None, K_new, size, cv2.CV_32FC1)


def assert_same_as_cv2(dist, model, coeffs, K=None, size=(W, H)):
    K = K_of() if K is None else K
    assert (dist.width, dist.height) == size and dist.model == model
    np.testing.assert_allclose(dist.K, K, rtol=0, atol=1e-9)
    np.testing.assert_allclose(dist.coeffs, coeffs, rtol=0, atol=1e-12)
    und = Undistorter.for_camera(dist, "nose")
    ref_u, ref_v = cv2_maps(model, coeffs, und.K_new, K, size)
    mu, mv = und.maps()
    assert np.array_equal(mu, ref_u) and np.array_equal(mv, ref_v)
    img = np.random.default_rng(3).integers(0, 255, (size[1], size[0]), dtype=np.uint8)
    assert np.array_equal(und(img), cv2.remap(img, ref_u, ref_v, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE))
    return und


# ---- files of each format -------------------------------------------------------------------------------------

def write_opencv(path, K, D, fisheye=False, size=(W, H)):
    fs = cv2.FileStorage(str(path), cv2.FILE_STORAGE_WRITE)
    fs.write("image_width", size[0])
    fs.write("image_height", size[1])
    fs.write("flags", 0)
    fs.write("fisheye_model", int(fisheye))
    fs.write("camera_matrix", K)
    fs.write("distortion_coefficients", np.array(D, float).reshape(-1, 1))
    fs.write("avg_reprojection_error", 0.21)
    fs.release()
    return path


@pytest.mark.parametrize("suffix", [".yaml", ".xml"])
def test_opencv_file_radtan_and_fisheye(tmp_path, suffix):
    p = write_opencv(tmp_path / f"cam{suffix}", K_of(), RADTAN)
    assert_same_as_cv2(load_calibration(p), "radtan", RADTAN)
    p = write_opencv(tmp_path / f"fish{suffix}", K_of(), EQUI, fisheye=True)
    assert_same_as_cv2(load_calibration(p), "equidistant", EQUI)


ROS_INFO = """image_width: {w}
image_height: {h}
camera_name: nose
camera_matrix:
  rows: 3
  cols: 3
  data: [{fx}, 0.0, {cx}, 0.0, {fy}, {cy}, 0.0, 0.0, 1.0]
distortion_model: {model}
distortion_coefficients:
  rows: 1
  cols: {n}
  data: [{coeffs}]
rectification_matrix:
  rows: 3
  cols: 3
  data: [1.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0]
projection_matrix:
  rows: 3
  cols: 4
  data: [{fx}, 0.0, {cx}, 0.0, 0.0, {fy}, {cy}, 0.0, 0.0, 0.0, 1.0, 0.0]
"""


@pytest.mark.parametrize("ros_model,model,coeffs", [("plumb_bob", "radtan", RADTAN),
                                                    ("rational_polynomial", "radtan", RATIONAL),
                                                    ("equidistant", "equidistant", EQUI)])
def test_ros_camera_info(tmp_path, ros_model, model, coeffs):
    p = tmp_path / "camera_info.yaml"
    p.write_text(ROS_INFO.format(w=W, h=H, model=ros_model, n=len(coeffs), coeffs=", ".join(map(repr, coeffs)),
                                 **K_VALUES))
    assert_same_as_cv2(load_calibration(p), model, coeffs)


# cam0 rotation: optical x = body y, optical y = body z, optical z = body x (a forward camera), then 5 deg down
_c, _s = np.cos(np.deg2rad(5.0)), np.sin(np.deg2rad(5.0))
R_TILT = np.array([[1, 0, 0], [0, _c, -_s], [0, _s, _c]])        # about optical x: optical z 5 deg below the nose
R_CAM0_IMU = R_TILT @ np.array([[0.0, 1, 0], [0, 0, 1], [1, 0, 0]])
L_CAM0_BODY = np.array([0.30, -0.05, 0.10])


def kalibr_text(coeffs1_model="equidistant"):
    T = np.eye(4)
    T[:3, :3], T[:3, 3] = R_CAM0_IMU, -R_CAM0_IMU @ L_CAM0_BODY
    rows = "\n".join(f"  - [{', '.join(repr(float(x)) for x in r)}]" for r in T)
    return f"""cam0:
  T_cam_imu:
{rows}
  cam_overlaps: [1]
  camera_model: pinhole
  distortion_coeffs: [{', '.join(map(repr, RADTAN[:4]))}]
  distortion_model: radtan
  intrinsics: [{K_VALUES['fx']}, {K_VALUES['fy']}, {K_VALUES['cx']}, {K_VALUES['cy']}]
  resolution: [{W}, {H}]
  rostopic: /cam0/image_raw
  timeshift_cam_imu: -0.0123
cam1:
  camera_model: pinhole
  distortion_coeffs: [{', '.join(map(repr, EQUI))}]
  distortion_model: {coeffs1_model}
  intrinsics: [40.0, 40.0, 31.5, 23.5]
  resolution: [{W}, {H}]
  rostopic: /cam1/image_raw
"""


def test_kalibr_camchain_radtan_and_equi_with_extrinsics(tmp_path):
    p = tmp_path / "camchain-imucam.yaml"
    p.write_text(kalibr_text())
    cam0 = load_calibration(p)                              # cam0 by default
    assert_same_as_cv2(cam0, "radtan", RADTAN[:4])
    assert cam0.timeshift_s == pytest.approx(-0.0123)
    l_m, eps = mount_from_T_cam_imu(cam0.T_cam_imu)
    np.testing.assert_allclose(l_m, L_CAM0_BODY, atol=1e-12)
    np.testing.assert_allclose(np.rad2deg(eps), [0.0, -5.0, 0.0], atol=1e-9)   # forward camera, 5 deg down
    cam1 = load_calibration(p, camera="cam1")
    assert_same_as_cv2(cam1, "equidistant", EQUI, K=np.array([[40.0, 0, 31.5], [0, 40, 23.5], [0, 0, 1]]))
    assert cam1.T_cam_imu is None and cam1.timeshift_s is None
    with pytest.raises(InputError, match=r"camera 'cam2' is not one of \['cam0', 'cam1'\]"):
        load_calibration(p, camera="cam2")
    p.write_text(kalibr_text("fov"))
    with pytest.raises(InputError, match=r"cam1.distortion_model: 'fov' is not supported"):
        load_calibration(p, camera="cam1")


def test_kalibr_equi_is_the_equidistant_model(tmp_path):
    """Kalibr's short name ``equi`` (its ``pinhole-equi`` camera model) is the fisheye model: cam1 written as ``equi``
    loads as ``equidistant`` and undistorts with cv2.fisheye's own tables for its known values."""
    p = tmp_path / "camchain.yaml"
    p.write_text(kalibr_text("equi"))
    cam1 = load_calibration(p, camera="cam1")
    assert_same_as_cv2(cam1, "equidistant", EQUI, K=np.array([[40.0, 0, 31.5], [0, 40, 23.5], [0, 0, 1]]))


def test_kalibr_camchain_of_one_camera_defaults_to_that_camera(tmp_path):
    """A camchain holding a single entry that is not ``cam0`` (the belly camera calibrated alone as ``cam1``) gives
    that camera when none is named; ``cam0`` is only the default among several."""
    text = kalibr_text()
    p = tmp_path / "camchain-belly.yaml"
    p.write_text(text[text.index("cam1:"):])
    cam = load_calibration(p)
    assert (cam.fx, cam.fy, cam.cx, cam.cy, cam.model) == (40.0, 40.0, 31.5, 23.5, "equidistant")
    assert cam.coeffs == EQUI and cam.T_cam_imu is None
    with pytest.raises(InputError, match=r"camera 'cam0' is not one of \['cam1'\]"):
        load_calibration(p, camera="cam0")


@pytest.mark.parametrize("text,match", [
    ("camera_matrix: {rows: 3, cols: 3, data: [1, 0]}\ndistortion_model: plumb_bob\n", r"camera_matrix.data: expected 9"),
    ("a: [1, 2\n", "not valid YAML"),
    ("width: 3\n", "not an OpenCV"),
    ("cam0: {camera_model: pinhole, distortion_model: radtan, distortion_coeffs: [0, 0, 0, 0], resolution: [64, 48],"
     " intrinsics: [1" + "0" * 400 + ", 40, 31.5, 23.5]}\n", r"cam0.intrinsics: expected finite numbers, got an integer"),
    ("camera_matrix: {data: [1" + "0" * 400 + ", 0, 32, 0, 50, 24, 0, 0, 1]}\ndistortion_model: plumb_bob\n",
     r"camera_matrix.data: expected finite numbers, got an integer beyond the float range"),
    # image sizes: the undistortion maps are built at this size before any image is read (8192 x 8192 is the most)
    ("cam0: {camera_model: pinhole, distortion_model: radtan, distortion_coeffs: [0, 0, 0, 0], resolution: [8193, "
     "8192], intrinsics: [40, 40, 31.5, 23.5]}\n", r"cam0.resolution: 8193 x 8192 is more than the 67108864 pixels"),
    ("cam0: {camera_model: pinhole, distortion_model: radtan, distortion_coeffs: [0, 0, 0, 0], resolution: [1" + "0" * 400
     + ", 48], intrinsics: [40, 40, 31.5, 23.5]}\n", r"cam0.resolution: .* is more than the 67108864 pixels"),
    ("cam0: {camera_model: pinhole, distortion_model: radtan, distortion_coeffs: [0, 0, 0, 0], resolution: [.inf, "
     "48], intrinsics: [40, 40, 31.5, 23.5]}\n", r"cam0.resolution: expected a positive whole image width"),
])
def test_bad_calibration_files_name_the_problem(tmp_path, text, match):
    p = tmp_path / "bad.yaml"
    p.write_text(text)
    with pytest.raises(InputError, match=match):
        load_calibration(p)
    with pytest.raises(InputError, match="calibration file not found"):
        load_calibration(tmp_path / "none.yaml")


# ---- the output camera ----------------------------------------------------------------------------------------

@pytest.mark.parametrize("model,coeffs", [("radtan", RADTAN), ("radtan", (0.12, 0.02, 0.0, 0.0)),    # barrel, pincushion
                                          ("radtan", RATIONAL), ("equidistant", EQUI),
                                          ("equidistant", (0.2, 0.1, -0.05, 0.01))])
def test_output_camera_has_no_black_border_and_no_wasted_field(model, coeffs):
    dist = DistortedCamera(640, 480, 500.0, 498.0, 322.0, 236.0, model, coeffs)
    K = output_camera_matrix(dist)
    assert K[0, 0] == K[1, 1]                                                    # square pixels

    def inside(K_new):
        mu, mv = cv2_maps(model, coeffs, K_new, dist.K, (640, 480))
        return (mu >= -1e-3) & (mu <= 639 + 1e-3) & (mv >= -1e-3) & (mv <= 479 + 1e-3)
    assert inside(K).all()                   # every pixel sees the raw image (to float32 rounding of the tables)
    wider = K.copy()
    wider[0, 0] = wider[1, 1] = K[0, 0] * 0.995                                  # 0.5 % more field: off the image
    assert not inside(wider).all()
    if model == "radtan":     # cv2's own alpha = 0 camera: the same inner field, stretched per axis
        K_cv, _ = cv2.getOptimalNewCameraMatrix(dist.K, np.array(coeffs), (640, 480), 0)
        assert K[0, 0] == pytest.approx(max(K_cv[0, 0], K_cv[1, 1]), rel=2e-3)


def test_undistorter_rejects_a_frame_of_another_size():
    und = Undistorter.for_camera(DistortedCamera(W, H, **K_VALUES, model="radtan", coeffs=RADTAN), "nose")
    with pytest.raises(InputError, match=r"frame is 32x24 but its calibration is 64x48"):
        und(np.zeros((24, 32), np.uint8))


# ---- Kalibr extrinsics -> mount ---------------------------------------------------------------------------------

@pytest.mark.parametrize("imu_frame", ["frd", "flu"])
@pytest.mark.parametrize("eps_deg", [[10.0, -20.0, 5.0], [0.0, -90.0, 0.0], [-170.0, 30.0, 100.0]])
def test_mount_from_T_cam_imu_projects_like_the_extrinsics(imu_frame, eps_deg):
    rng = np.random.default_rng(4)
    R_opt_body = T_PAPERCAM_OPTICAL.T @ T_cam_body_from_eps(np.deg2rad(eps_deg))   # optical <- body FRD
    R_imu_body = np.eye(3) if imu_frame == "frd" else np.diag([1.0, -1, -1])
    l_body = np.array([1.2, -0.4, 0.3])
    T = np.eye(4)
    T[:3, :3] = R_opt_body @ R_imu_body.T                                         # optical <- IMU
    T[:3, 3] = -R_opt_body @ l_body
    l_m, eps = mount_from_T_cam_imu(T, imu_frame)
    pts_body = rng.normal(0, 5, (20, 3))
    pts_imu = pts_body @ R_imu_body.T
    via_kalibr = T_PAPERCAM_OPTICAL @ (T[:3, :3] @ pts_imu.T + T[:3, 3:])        # paper camera frame
    via_mount = T_cam_body_from_eps(eps) @ (pts_body - l_m).T                     # eq. (12)
    np.testing.assert_allclose(via_mount, via_kalibr, atol=1e-9)
    np.testing.assert_allclose(l_m, l_body, atol=1e-12)


def test_mount_from_T_cam_imu_rejects_non_rigid():
    T = np.eye(4)
    T[0, 0] = 2.0
    with pytest.raises(InputError, match="not a proper rotation"):
        mount_from_T_cam_imu(T)
    with pytest.raises(InputError, match="imu_frame 'enu' is not one of"):
        mount_from_T_cam_imu(np.eye(4), "enu")


def test_mount_from_T_cam_imu_rejects_a_mirrored_rotation():
    """An orthonormal block with determinant -1 (a left-handed frame, e.g. an exporter's flipped y axis) is no
    rigid motion: no attitude reproduces it, so it is refused rather than turned into some eps."""
    T = np.eye(4)
    T[:3, :3] = np.diag([1.0, -1.0, 1.0]) @ R_CAM0_IMU            # orthonormal, det = -1
    T[:3, 3] = -T[:3, :3] @ L_CAM0_BODY
    assert np.allclose(T[:3, :3] @ T[:3, :3].T, np.eye(3)) and np.linalg.det(T[:3, :3]) == pytest.approx(-1.0)
    with pytest.raises(InputError, match="not a proper rotation"):
        mount_from_T_cam_imu(T)


def test_mount_from_T_cam_imu_rejects_a_transposed_matrix():
    """A T_cam_imu written column-major (transposed) has the translation in its last row and a rotation block that
    is still a proper rotation (R^T): only the last-row check tells it from a camera at the IMU origin with the
    inverse attitude, so it must be refused, not turned into a mount 0.32 m and 126 deg off."""
    T = np.eye(4)
    T[:3, :3], T[:3, 3] = R_CAM0_IMU, -R_CAM0_IMU @ L_CAM0_BODY
    with pytest.raises(InputError, match=r"T_cam_imu: expected a 4 x 4 rigid transform with last row \[0, 0, 0, 1\]"):
        mount_from_T_cam_imu(T.T)


def test_mount_from_T_cam_imu_rotation_tolerance_both_sides():
    """Kalibr prints T_cam_imu to ~1e-7 and that rounding is no error: the mount is the exact one to 1e-6. A block
    stretched by 1e-4 (R R^T off I by 2e-4: lengths change, no rigid motion does that) is refused, not taken as
    the nearest rotation."""
    T = np.eye(4)
    T[:3, :3], T[:3, 3] = R_CAM0_IMU, -R_CAM0_IMU @ L_CAM0_BODY
    l_m, eps = mount_from_T_cam_imu(np.round(T, 7))
    np.testing.assert_allclose(l_m, L_CAM0_BODY, atol=1e-6)
    np.testing.assert_allclose(np.rad2deg(eps), [0.0, -5.0, 0.0], atol=1e-4)
    stretched = T.copy()
    stretched[:3, :3] *= 1.0 + 1e-4
    with pytest.raises(InputError, match="not a proper rotation"):
        mount_from_T_cam_imu(stretched)


# ---- pair file and cameras file --------------------------------------------------------------------------------

PAIR = {
    "cameras": {"nose": {"width": W, "height": H, **K_VALUES,
                         "distortion": {"model": "radtan", "coeffs": list(RADTAN)},
                         "mount": {"l_m": [7.6, 0.0, 0.6], "eps_deg": [0.0, -2.0, 0.0]}}},
    "frames": [
        {"image": "f1.png", "camera": "nose", "t": 0.0, "position_ned_m": [0, 0, -3.66], "ypr_deg": [0, 0, 0]},
        {"image": "f2.png", "camera": "nose", "t": 0.1, "position_ned_m": [1.6, 0, -3.66], "ypr_deg": [0, 0, 0]},
    ],
}


@pytest.fixture
def pair_dir(tmp_path):
    rng = np.random.default_rng(1)
    for n in ("f1.png", "f2.png"):
        cv2.imwrite(str(tmp_path / n), rng.integers(0, 255, (H, W), dtype=np.uint8))
    return tmp_path


def write_pair(d, doc):
    p = d / "pair.json"
    p.write_text(json.dumps(doc))
    return p


def test_distortion_entry_undistorts_the_images_to_the_pinhole_camera(pair_dir):
    pf = load_pair_file(write_pair(pair_dir, PAIR))
    cam = pf.cameras["nose"]
    K_new = output_camera_matrix(DistortedCamera(W, H, **K_VALUES, model="radtan", coeffs=RADTAN))
    assert (cam.fx, cam.fy, cam.cx, cam.cy) == (K_new[0, 0], K_new[1, 1], K_new[0, 2], K_new[1, 2])
    np.testing.assert_allclose(np.rad2deg(cam.eps_rad), [0, -2, 0])
    raw = cv2.imread(str(pair_dir / "f1.png"), cv2.IMREAD_UNCHANGED).astype(np.float32)
    mu, mv = cv2_maps("radtan", RADTAN, K_new)
    expect = cv2.remap(raw, mu, mv, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)
    assert np.array_equal(pf.views()[0].image, expect)
    pinhole = copy.deepcopy(PAIR)
    del pinhole["cameras"]["nose"]["distortion"]                   # the same file without the lens model
    assert np.array_equal(load_pair_file(write_pair(pair_dir, pinhole)).views()[0].image, raw)


def test_calibration_entry_reads_the_file_beside_the_pair_file(pair_dir):
    write_opencv(pair_dir / "nose.yaml", K_of(), RADTAN)
    doc = copy.deepcopy(PAIR)
    cam = doc["cameras"]["nose"]
    for k in ("width", "height", *K_VALUES, "distortion"):
        del cam[k]
    cam["calibration"] = "nose.yaml"
    a = load_pair_file(write_pair(pair_dir, doc))
    b = load_pair_file(write_pair(pair_dir, PAIR))
    assert camera_to_dict(a.cameras["nose"]) == camera_to_dict(b.cameras["nose"])
    assert np.array_equal(a.views()[1].image, b.views()[1].image)


def test_cameras_file_kalibr_mount_time_offset_and_overrides(tmp_path):
    (tmp_path / "cal").mkdir()
    (tmp_path / "cal" / "camchain-imucam.yaml").write_text(kalibr_text())
    doc = {"nose": {"calibration": "cal/camchain-imucam.yaml"},
           "belly": {"calibration": {"file": "cal/camchain-imucam.yaml", "camera": "cam1"},
                     "mount": {"eps_deg": [0, -90, 0]}, "time_offset_s": 0.004},
           "tail": {"calibration": {"file": "cal/camchain-imucam.yaml", "imu_frame": "flu"}}}
    p = tmp_path / "cameras.json"
    p.write_text(json.dumps(doc))
    models = load_camera_models(p)
    nose, belly, tail = models["nose"], models["belly"], models["tail"]
    np.testing.assert_allclose(nose.camera.l_body_m, L_CAM0_BODY, atol=1e-12)
    np.testing.assert_allclose(np.rad2deg(nose.camera.eps_rad), [0, -5, 0], atol=1e-9)
    assert nose.time_offset_s == pytest.approx(-0.0123) and nose.undistort.dist.model == "radtan"
    assert belly.time_offset_s == 0.004 and belly.undistort.dist.model == "equidistant"
    np.testing.assert_allclose(np.rad2deg(belly.camera.eps_rad)[1], -90.0)
    np.testing.assert_allclose(tail.camera.l_body_m, [0.30, 0.05, -0.10], atol=1e-12)   # FLU: y and z flip
    assert camera_to_dict(load_cameras(p)["nose"]) == camera_to_dict(nose.camera)


def test_explicit_mount_wins_over_the_kalibr_extrinsics(tmp_path):
    """docs/pair-file.md: the mount defaults to the one Kalibr's T_cam_imu gives; an explicit ``mount`` wins. cam0
    has a T_cam_imu (lens at L_CAM0_BODY, 5 deg down): a camera entry that gives its own mount gets that mount,
    as written, and still Kalibr's time shift."""
    (tmp_path / "cal").mkdir()
    (tmp_path / "cal" / "camchain-imucam.yaml").write_text(kalibr_text())
    p = tmp_path / "cameras.json"
    p.write_text(json.dumps({"nose": {"calibration": "cal/camchain-imucam.yaml",
                                      "mount": {"l_m": [7.6, 0.0, 0.6], "eps_deg": [0.0, -2.0, 1.5]}}}))
    nose = load_camera_models(p)["nose"]
    np.testing.assert_allclose(nose.camera.l_body_m, [7.6, 0.0, 0.6], atol=1e-12)
    np.testing.assert_allclose(np.rad2deg(nose.camera.eps_rad), [0.0, -2.0, 1.5], atol=1e-9)
    assert nose.time_offset_s == pytest.approx(-0.0123) and nose.undistort is not None


@pytest.mark.parametrize("mount,l_m,eps_deg", [({"eps_deg": [0.0, -2.0, 1.5]}, [0.0, 0.0, 0.0], [0.0, -2.0, 1.5]),
                                               ({"l_m": [7.6, 0.0, 0.6]}, [7.6, 0.0, 0.6], [0.0, 0.0, 0.0]),
                                               ({}, [0.0, 0.0, 0.0], [0.0, 0.0, 0.0])])
def test_partial_explicit_mount_wins_whole_over_the_kalibr_extrinsics(tmp_path, mount, l_m, eps_deg):
    """docs/pair-file.md: an explicit mount wins whole; its missing parts are zero, not the file's. cam0's T_cam_imu
    says lens at L_CAM0_BODY, 5 deg down: a mount giving only eps_deg has its lens at the body origin, one giving
    only l_m looks along the nose, and an empty mount is all zero."""
    (tmp_path / "camchain-imucam.yaml").write_text(kalibr_text())
    p = tmp_path / "cameras.json"
    p.write_text(json.dumps({"nose": {"calibration": "camchain-imucam.yaml", "mount": mount}}))
    nose = load_camera_models(p)["nose"]
    np.testing.assert_allclose(nose.camera.l_body_m, l_m, atol=1e-12)
    np.testing.assert_allclose(np.rad2deg(nose.camera.eps_rad), eps_deg, atol=1e-9)


def test_calibration_entry_refuses_a_distortion_beside_it(pair_dir):
    """The lens comes from the calibration file: an entry giving a calibration and a distortion as well (and no
    intrinsics) is an error naming the distortion key, not a lens model silently dropped."""
    write_opencv(pair_dir / "nose.yaml", K_of(), RADTAN)
    doc = copy.deepcopy(PAIR)
    cam = doc["cameras"]["nose"]
    for k in ("width", "height", *K_VALUES):
        del cam[k]
    cam["calibration"] = "nose.yaml"
    with pytest.raises(InputError, match=r"cameras.nose.distortion: the intrinsics come from the calibration file"):
        load_pair_file(write_pair(pair_dir, doc))


@pytest.mark.parametrize("model,coeffs,match", [
    ("equidistant", [-0.03, 0.008, -0.002], r"coeffs: equidistant takes 4 coefficients \(k1, k2, k3, k4\), got 3"),
    ("equidistant", [-0.03, 0.008, -0.002, 0.0004, 0.0], r"coeffs: equidistant takes 4 coefficients .*, got 5"),
    ("radtan", [-0.21, 0.045, float("nan"), -6e-4], r"coeffs: expected finite numbers"),
    ("equidistant", [-0.03, float("inf"), -0.002, 0.0004], r"coeffs: expected finite numbers"),
    ("radtan", [-0.21, 0.045, 10 ** 400, -6e-4], r"coeffs: expected finite numbers, got an integer beyond"),
])
def test_distortion_coefficients_count_and_finiteness_name_the_field(pair_dir, model, coeffs, match):
    """An equidistant lens has exactly k1..k4 (not 3, and a fifth is not passed on to cv2.fisheye); NaN,
    Infinity (Python's JSON reads both) and an integer beyond the float range (JSON integers have no limit) are
    errors naming cameras.nose.distortion.coeffs."""
    doc = copy.deepcopy(PAIR)
    doc["cameras"]["nose"]["distortion"] = {"model": model, "coeffs": coeffs}
    with pytest.raises(InputError, match=r"cameras.nose.distortion." + match):
        load_pair_file(write_pair(pair_dir, doc))


@pytest.mark.parametrize("path,value,match", [
    (("cameras", "nose", "focal"), 50, r"cameras.nose.focal: unknown key; expected one of \['width'"),
    (("cameras", "nose", "mount", "tilt"), 3, r"cameras.nose.mount.tilt: unknown key"),
    (("cameras", "nose", "distortion", "k1"), 0.1, r"cameras.nose.distortion.k1: unknown key"),
    (("cameras", "nose", "distortion", "model"), "fisheye624", r"cameras.nose.distortion.model: 'fisheye624' is not one"),
    (("cameras", "nose", "distortion", "coeffs"), [0.1, 0.2, 0.3], r"radtan takes 4, 5, 8, 12, 14 coefficients"),
    (("cameras", "nose", "distortion"), "radtan", r"cameras.nose.distortion: expected an object"),
    (("cameras", "nose", "calibration"), "nose.yaml", r"cameras.nose.width: the intrinsics come from the calibration"),
    (("frames", 0, "exposure"), 0.01, r"frames\[0\].exposure: unknown key"),
    (("comment",), "hello", r"pair file.comment: unknown key; expected one of \['cameras', 'frames'\]"),
])
def test_unknown_and_conflicting_keys_are_errors_naming_the_key(pair_dir, path, value, match):
    doc = copy.deepcopy(PAIR)
    obj = doc
    for k in path[:-1]:
        obj = obj[k]
    obj[path[-1]] = value
    with pytest.raises(InputError, match=match):
        load_pair_file(write_pair(pair_dir, doc))


def test_cameras_file_unknown_key_and_calibration_object_key(tmp_path):
    p = tmp_path / "cameras.json"
    p.write_text(json.dumps({"nose": {"width": W, "height": H, **K_VALUES, "exposure_us": 5000}}))
    with pytest.raises(InputError, match=r"cameras.nose.exposure_us: unknown key"):
        load_cameras(p)
    p.write_text(json.dumps({"nose": {"calibration": {"file": "x.yaml", "cam": "cam1"}}}))
    with pytest.raises(InputError, match=r"cameras.nose.calibration.cam: unknown key"):
        load_cameras(p)
    p.write_text(json.dumps({"nose": {"calibration": "missing.yaml"}}))
    with pytest.raises(InputError, match="calibration file not found"):
        load_cameras(p)


# ---- per-frame correction ---------------------------------------------------------------------------------------

def test_frame_correction_undistorts_and_stamps_mid_exposure():
    und = Undistorter.for_camera(DistortedCamera(W, H, **K_VALUES, model="radtan", coeffs=RADTAN), "nose")
    img = np.random.default_rng(2).integers(0, 255, (H, W), dtype=np.uint8)
    out, stamp = frame_correction(und, time_offset_s=-0.0123, exposure_s=0.008)(img, 1_000_000)
    assert stamp == 1_000_000 - 12_300 + 4_000 and np.array_equal(out, und(img))
    out, stamp = frame_correction(None)(img, 5)
    assert stamp == 5 and out is img
    with pytest.raises(InputError, match="expected 0 .. 1 s"):
        frame_correction(None, exposure_s=-0.001)


def test_frame_correction_rounds_the_shift_to_the_nearest_microsecond():
    """Offset -4.8 ms and exposure 6 ms move the stamp by -4800 + 3000 = -1800 us exactly; in floating point the
    shift is -1799.9999999999998 us, which truncation would make -1799 (a microsecond late, every frame)."""
    img = np.zeros((H, W), np.uint8)
    _, stamp = frame_correction(None, time_offset_s=-0.0048, exposure_s=0.006)(img, 1_000_000)
    assert stamp == 1_000_000 - 1800
    _, stamp = frame_correction(None, time_offset_s=-0.0047, exposure_s=0.010)(img, 1_000_000)
    assert stamp == 1_000_000 + 300


def test_frame_correction_time_offset_is_bounded_on_both_sides():
    """A time offset is at most 10 s either way (docs/cameras.md: a camera clock's offset, not an epoch mix-up):
    +-10 s move the stamp by +-10 000 000 us; +-10.5 s are refused, the negative one as the positive one."""
    img = np.zeros((H, W), np.uint8)
    for off, shift in ((10.0, 10_000_000), (-10.0, -10_000_000)):
        assert frame_correction(None, time_offset_s=off)(img, 20_000_000)[1] == 20_000_000 + shift
    for off in (10.5, -10.5):
        with pytest.raises(InputError, match=rf"time_offset_s {off!r}: expected a finite offset of at most 10 s"):
            frame_correction(None, time_offset_s=off)


# ---- ranging with a distorted camera ----------------------------------------------------------------------------

def median_error(view_a, view_b, truth_m):
    from eonav.ranging.locate import locate
    from eonav.ranging.rangemap import VALID
    res = locate(view_a, view_b)
    near = np.isfinite(truth_m) & (truth_m < 200.0)
    ok = near & ((res.flags & VALID) > 0) & np.isfinite(res.range_m)
    return float(np.median(np.abs(res.range_m[ok] - truth_m[ok]) / truth_m[ok])), ok.sum() / near.sum()


@pytest.fixture(scope="module")
def distorted_flight():
    """The "fast" preset seen by a 320 x 240, ~50 deg camera with a strong barrel lens (k1 = -0.25: 9 % at the
    corners). Raw images: a pinhole render covering the lens's whole field, resampled through the lens model
    (cv2.undistortPoints of every raw pixel), then sensor noise; the pinhole reference is rendered directly with
    the undistorted camera, so both share one truth."""
    from eonav.sim.presets import focal_for_fov, preset_scene
    from eonav.sim.render import render
    scene, cams, states, _ = preset_scene("fast")
    mount = cams[0]
    w, h = 320, 240
    f = focal_for_fov(w, 50.0)
    dist = DistortedCamera(w, h, f, f, (w - 1) / 2 + 3.0, (h - 1) / 2 - 2.0, "radtan", (-0.25, 0.06, 1e-3, -5e-4, 0.0))
    und = Undistorter.for_camera(dist, "nose", mount.l_body_m, mount.eps_rad)
    v, u = np.mgrid[0:h, 0:w].astype(np.float64)
    xy = cv2.undistortPoints(np.c_[u.ravel(), v.ravel()].reshape(-1, 1, 2), dist.K, dist.D,
                             criteria=CRIT).reshape(h, w, 2)
    x0, y0 = xy[..., 0].min(), xy[..., 1].min()
    src = Camera("src", int(np.ceil((xy[..., 0].max() - x0) * f)) + 6, int(np.ceil((xy[..., 1].max() - y0) * f)) + 6,
                 f, f, 3 - x0 * f, 3 - y0 * f, mount.l_body_m, mount.eps_rad)
    mu, mv = (src.cx + f * xy[..., 0]).astype(np.float32), (src.cy + f * xy[..., 1]).astype(np.float32)
    rng = np.random.default_rng(11)
    raw, raw_truth = [], None
    for i, s in enumerate(states):
        r = render(scene, src, s, supersample=3, noise_sigma=0.0, quantize=False)
        img = cv2.remap(r.image, mu, mv, cv2.INTER_LINEAR)
        raw.append(np.clip(np.round(img + rng.normal(0.0, 1.0, img.shape)), 0, 255).astype(np.float32))
        if i == 0:
            raw_truth = cv2.remap(r.range_m, mu, mv, cv2.INTER_NEAREST)
    pin = [render(scene, und.camera, s, supersample=3, noise_sigma=1.0, seed=20 + i) for i, s in enumerate(states)]
    return dict(states=states, dist=dist, und=und, raw=raw, raw_truth=raw_truth, pin=pin, mount=mount)


def test_distorted_camera_ranges_after_undistortion_as_the_pinhole_one(distorted_flight):
    d = distorted_flight
    s, cam, truth = d["states"], d["und"].camera, d["pin"][0].range_m
    e_pin, cov_pin = median_error(View(cam, s[0], d["pin"][0].image), View(cam, s[1], d["pin"][1].image), truth)
    e_und, cov_und = median_error(View(cam, s[0], d["und"](d["raw"][0])), View(cam, s[1], d["und"](d["raw"][1])),
                                  truth)
    # the undistorted image has the raw camera's resolution, which the barrel lens lowers towards the edges
    assert e_und <= 1.25 * e_pin and cov_und >= 0.9 * cov_pin, (e_und, e_pin, cov_und, cov_pin)
    dc, m = d["dist"], d["mount"]
    as_pinhole = Camera("nose", dc.width, dc.height, dc.fx, dc.fy, dc.cx, dc.cy, m.l_body_m, m.eps_rad)
    e_raw, _ = median_error(View(as_pinhole, s[0], d["raw"][0]), View(as_pinhole, s[1], d["raw"][1]), d["raw_truth"])
    assert e_raw >= 2.5 * e_pin, (e_raw, e_pin)                   # the lens model matters


# ---- camera ingest ----------------------------------------------------------------------------------------------

def _ingest_args(argv):
    import argparse

    from eonav.services import camera_ingest as C
    p = argparse.ArgumentParser()
    C.add_arguments(p)
    return p.parse_args(argv)


def test_camera_ingest_correction_from_the_cameras_file(tmp_path):
    from eonav.services import camera_ingest as C
    p = tmp_path / "cameras.json"
    p.write_text(json.dumps({"nose": {**PAIR["cameras"]["nose"], "time_offset_s": -0.002}}))
    a = _ingest_args(["--cameras", str(p), "--camera-id", "nose", "--exposure-us", "6000"])
    corr = C.camera_correction(a)
    assert (a.width, a.height) == (W, H) and corr.shift_us == -2000 + 3000 and corr.undistort is not None
    with pytest.raises(InputError, match=r"--width 640: camera 'nose' in --cameras is 64x48"):
        C.camera_correction(_ingest_args(["--cameras", str(p), "--camera-id", "nose", "--width", "640"]))
    with pytest.raises(InputError, match=r"no camera 'tail' \(has \['nose'\]\)"):
        C.camera_correction(_ingest_args(["--cameras", str(p), "--camera-id", "tail"]))
    assert C.camera_correction(_ingest_args([])) is None
    assert C.camera_correction(_ingest_args(["--exposure-us", "1000"])).shift_us == 500


def test_camera_ingest_service_undistorts_and_stamps_mid_exposure(tmp_path):
    """The real service: a folder of raw frames with recorded stamps, a cameras file with a lens model and a time
    offset, a known exposure -> undistorted frames at recorded + offset + exposure / 2; a frame of another size is
    skipped."""
    zenoh = pytest.importorskip("zenoh")
    from eonav.app.processes import drain, free_port, start_service, wait_until
    from eonav.bus import keys as K
    from eonav.bus import schema
    from eonav.bus.session import endpoint, listener_session

    rng = np.random.default_rng(8)
    d = tmp_path / "rec"
    d.mkdir()
    raw = [rng.integers(0, 255, (H, W), dtype=np.uint8) for _ in range(3)]
    for i, img in enumerate(raw):
        cv2.imwrite(str(d / f"f_{i}.png"), img)
    cv2.imwrite(str(d / "f_3.png"), np.zeros((H, W + 2), np.uint8))                   # not the calibrated size
    stamps_us = [1_700_000_000_000_000 + 100_000 * i for i in range(4)]
    (d / "timestamps.txt").write_text("".join(f"{s}\n" for s in stamps_us))
    cams = tmp_path / "cameras.json"
    cams.write_text(json.dumps({"nose": {**PAIR["cameras"]["nose"], "time_offset_s": -0.0025}}))
    port = free_port()
    with listener_session(port) as s:
        sub = s.declare_subscriber(K.frame("t1", "nose"), zenoh.handlers.FifoChannel(100))
        proc = start_service(["-m", "eonav.services.camera_ingest", "--source", str(d), "--camera-id", "nose",
                              "--cameras", str(cams), "--exposure-us", "8000", "--keep-stamps", "--rate-hz", "0",
                              "--vehicle", "t1", "--connect", endpoint(port), "--wait-subscribers-s", "10"])
        try:
            code = proc.wait(30)
        finally:
            if proc.poll() is None:
                proc.kill()
        err = proc.stderr.read()
        assert code == 0, err
        msgs = []
        wait_until(lambda: len(drain(sub, msgs)) >= 3, 5, what="3 frames")
        time.sleep(0.2)
        drain(sub, msgs)
    frames = [schema.decode(m.payload.to_bytes(), expect="frame") for m in msgs]
    assert len(frames) == 3                                      # the 66 x 48 frame was skipped
    und = load_camera_models(cams)["nose"].undistort
    assert [f["stamp_us"] for f in frames] == [s - 2500 + 4000 for s in stamps_us[:3]]
    for f, img in zip(frames, raw):
        assert np.array_equal(f["image"], und(img))
    assert "undistorted, stamps +1500 us" in err


def test_deploy_example_cameras_file_loads_and_matches_the_camera_ingest_env():
    from pathlib import Path
    root = Path(__file__).resolve().parents[1] / "deploy"
    models = load_camera_models(root / "cameras.example.json")
    assert sorted(models) == ["belly", "nose", "tail"]
    env = dict(ln.split("=", 1) for ln in (root / "env" / "camera_ingest.env").read_text().splitlines()
               if ln.strip() and not ln.startswith("#"))
    nose = models[env["EONAV_CAMERA_ID"]]
    assert (nose.camera.width, nose.camera.height) == (int(env["EONAV_CAMERA_WIDTH"]), int(env["EONAV_CAMERA_HEIGHT"]))
    assert nose.undistort.dist.model == "radtan" and nose.time_offset_s == pytest.approx(-0.0042)
    np.testing.assert_allclose(np.rad2deg(nose.camera.eps_rad), [0, -2, 0], atol=1e-6)   # from its T_cam_imu
    assert models["belly"].undistort.dist.model == "equidistant" and models["tail"].undistort is None


def test_calibration_image_size_limit_on_both_sides():
    """A calibration's image may have up to 8192 x 8192 pixels (``MAX_IMAGE_PIXELS``, the largest image eonav
    decodes), one more row is refused before the undistortion maps are built at that size."""
    from eonav.io.calibration import _size
    assert _size(8192, 8192, "cam0.resolution") == (8192, 8192)
    assert _size(8192.0, 4096, "cam0.resolution") == (8192, 4096)
    with pytest.raises(InputError, match="8192 x 8193 is more than"):
        _size(8192, 8193, "cam0.resolution")
