"""The pair file contract (docs/pair-file.md): every error path names the field and what was expected."""
import copy
import json

import cv2
import numpy as np
import pytest

from eonav import InputError
from eonav.io.pairfile import load_pair_file

DOC = {
    "cameras": {"nose": {"width": 32, "height": 24, "fx": 40.0, "fy": 40.0, "cx": 15.5, "cy": 11.5,
                         "mount": {"l_m": [7.6, 0.0, 0.6], "eps_deg": [0.0, -2.0, 0.0]}}},
    "frames": [
        {"image": "f1.png", "camera": "nose", "t": 0.0, "position_ned_m": [0, 0, -3.66], "ypr_deg": [0, 0, 0]},
        {"image": "f2.png", "camera": "nose", "t": 0.17, "position_ned_m": [1.649, -0.134, -3.652],
         "ypr_deg": [-0.08, 0.059, 0.12]},
    ],
}


@pytest.fixture
def pair_dir(tmp_path):
    rng = np.random.default_rng(1)
    cv2.imwrite(str(tmp_path / "f1.png"), rng.integers(0, 255, (24, 32), dtype=np.uint8))
    cv2.imwrite(str(tmp_path / "f2.png"), rng.integers(0, 255, (24, 32, 3), dtype=np.uint8))   # colour is fine
    cv2.imwrite(str(tmp_path / "f16.png"), rng.integers(0, 65535, (24, 32), dtype=np.uint16))  # 16 bit is fine
    cv2.imwrite(str(tmp_path / "small.png"), np.zeros((10, 10), np.uint8))
    (tmp_path / "corrupt.png").write_bytes(b"\x89PNG\r\n\x1a\nthis is not a png")
    return tmp_path


def write(d, doc):
    p = d / "pair.json"
    p.write_text(json.dumps(doc))
    return p


def test_valid_pair_loads_with_degrees_converted(pair_dir):
    pf = load_pair_file(write(pair_dir, DOC))
    cam = pf.cameras["nose"]
    assert np.allclose(cam.eps_rad, np.deg2rad([0, -2, 0]))
    assert np.allclose(cam.l_body_m, [7.6, 0, 0.6])
    views = pf.views()
    assert views[0].image.shape == (24, 32) and views[1].image.dtype == np.float32
    assert np.allclose(views[1].state.position_ned_m, [1.649, -0.134, -3.652])


def test_sixteen_bit_image_is_scaled_to_the_8_bit_range(pair_dir):
    doc = copy.deepcopy(DOC)
    doc["frames"][1]["image"] = "f16.png"
    img = load_pair_file(write(pair_dir, doc)).views()[1].image
    raw = cv2.imread(str(pair_dir / "f16.png"), cv2.IMREAD_UNCHANGED)
    assert np.allclose(img, raw / 257.0, atol=1e-3)


def test_quaternion_attitude_equals_ypr(pair_dir):
    from eonav.geometry.frames import quat_wxyz_from_ypr
    doc = copy.deepcopy(DOC)
    ypr = doc["frames"][1].pop("ypr_deg")
    doc["frames"][1]["q_wxyz"] = quat_wxyz_from_ypr(*np.deg2rad(ypr)).tolist()
    a = load_pair_file(write(pair_dir, doc)).frames[1]["state"].T_body_ned
    b = load_pair_file(write(pair_dir, DOC)).frames[1]["state"].T_body_ned
    assert np.allclose(a, b, atol=1e-12)


def mutate(path, value):
    doc = copy.deepcopy(DOC)
    obj = doc
    for k in path[:-1]:
        obj = obj[k]
    if value is KeyError:
        del obj[path[-1]]
    else:
        obj[path[-1]] = value
    return doc


@pytest.mark.parametrize("path,value,match", [
    (("cameras",), {}, "cameras: expected a non-empty object"),
    (("cameras", "nose", "fx"), -3, r"cameras.nose.fx: expected a positive number"),
    (("cameras", "nose", "fx"), 0, r"cameras.nose.fx: expected a positive number"),     # 0 is not positive
    (("cameras", "nose", "fy"), 0.0, r"cameras.nose.fy: expected a positive number"),
    (("cameras", "nose", "width"), 0, r"cameras.nose.width: expected a positive number"),
    (("cameras", "nose", "width"), 32.5, r"cameras.nose.width: expected a whole number"),
    (("cameras", "nose", "cy"), "centre", r"cameras.nose.cy: expected a number"),
    (("cameras", "nose", "height"), KeyError, r"cameras.nose.height: missing"),
    (("cameras", "nose", "mount", "l_m"), [1, 2], r"cameras.nose.mount.l_m: expected a list of 3 numbers"),
    (("frames",), [DOC["frames"][0]], "frames: expected a list of at least 2"),
    (("frames", 1, "camera"), "tail", r"frames\[1\].camera: 'tail' is not one of the cameras"),
    (("frames", 0, "image"), None, r"frames\[0\].image: expected a path"),
    (("frames", 0, "position_ned_m"), [0, 0, float("nan")], r"frames\[0\].position_ned_m: expected finite"),
    (("frames", 0, "ypr_deg"), KeyError, r"frames\[0\]: give exactly one attitude"),
    (("frames", 1, "q_wxyz"), [1, 0, 0, 0], r"frames\[1\]: give exactly one attitude"),
    (("frames", 0, "t"), "noon", r"frames\[0\].t: expected a number"),
])
def test_pair_file_errors_name_the_field(pair_dir, path, value, match):
    with pytest.raises(InputError, match=match):
        load_pair_file(write(pair_dir, mutate(path, value)))


def test_non_unit_quaternion_is_rejected(pair_dir):
    doc = copy.deepcopy(DOC)
    del doc["frames"][1]["ypr_deg"]
    doc["frames"][1]["q_wxyz"] = [1, 1, 0, 0]
    with pytest.raises(InputError, match=r"frames\[1\].q_wxyz: expected a unit quaternion"):
        load_pair_file(write(pair_dir, doc))


@pytest.mark.parametrize("norm,ok", [(1.0009, True), (0.9991, True), (1.0011, False), (0.9989, False),
                                     (1.05, False), (0.7, False)])
def test_quaternion_norm_tolerance_is_1e3(pair_dir, norm, ok):
    """A quaternion whose norm is within 1e-3 of 1 (float rounding of a written unit quaternion) is taken as the
    rotation it stands for; one farther off is an error, not silently normalised."""
    from eonav.geometry.frames import quat_wxyz_from_ypr
    doc = copy.deepcopy(DOC)
    ypr = doc["frames"][1].pop("ypr_deg")
    doc["frames"][1]["q_wxyz"] = (norm * quat_wxyz_from_ypr(*np.deg2rad(ypr))).tolist()
    if ok:
        a = load_pair_file(write(pair_dir, doc)).frames[1]["state"].T_body_ned
        b = load_pair_file(write(pair_dir, DOC)).frames[1]["state"].T_body_ned
        assert np.allclose(a, b, atol=1e-12)
    else:
        with pytest.raises(InputError, match=rf"frames\[1\].q_wxyz: expected a unit quaternion.*norm {norm:.6f}"):
            load_pair_file(write(pair_dir, doc))


@pytest.mark.parametrize("image,match", [
    ("missing.png", "image file not found"),
    ("corrupt.png", "cannot decode image"),
    ("small.png", r"frames\[1\].image small.png: image is 10x10 but camera 'nose' declares 32x24"),
])
def test_image_errors(pair_dir, image, match):
    doc = copy.deepcopy(DOC)
    doc["frames"][1]["image"] = image
    with pytest.raises(InputError, match=match):
        load_pair_file(write(pair_dir, doc)).views()


def test_not_json_and_missing_file(tmp_path):
    (tmp_path / "bad.json").write_text("{nope")
    with pytest.raises(InputError, match="not valid JSON"):
        load_pair_file(tmp_path / "bad.json")
    with pytest.raises(InputError, match="pair file not found"):
        load_pair_file(tmp_path / "none.json")


def test_pinhole_intrinsics_keep_their_axes(pair_dir):
    """fx is the focal length along u (image x), fy along v, cx and cy the principal point on those axes: a camera
    with non-square pixels (fx 40, fy 36) and an off-centre principal point (cx 14.0, cy 12.5) loads with each
    value where it was written, not swapped."""
    doc = copy.deepcopy(DOC)
    doc["cameras"]["nose"].update(fx=40.0, fy=36.0, cx=14.0, cy=12.5)
    cam = load_pair_file(write(pair_dir, doc)).cameras["nose"]
    assert (cam.width, cam.height, cam.fx, cam.fy, cam.cx, cam.cy) == (32, 24, 40.0, 36.0, 14.0, 12.5)


def test_frame_to_dict_quaternion_is_body_to_ned(pair_dir):
    """docs/pair-file.md: q_wxyz is the body -> NED rotation (MAVLink ATTITUDE_QUATERNION). Nose east (yaw +90 deg)
    is +90 deg about NED down: q = [cos 45, 0, 0, +sin 45] by hand (its inverse, NED -> body, has -sin 45). The
    written frame reads back with the attitude it was written from."""
    from eonav.geometry.camera import VehicleState
    from eonav.io.pairfile import frame_to_dict
    east = VehicleState.from_ypr([1.0, 2.0, -3.0], np.deg2rad([90.0, 0.0, 0.0]), 0.25)
    d = frame_to_dict("f2.png", "nose", east, use_quat=True)
    s = np.sqrt(0.5)
    np.testing.assert_allclose(d["q_wxyz"], [s, 0.0, 0.0, s], atol=1e-12)
    assert "ypr_deg" not in d and d["t"] == 0.25 and d["position_ned_m"] == [1.0, 2.0, -3.0]
    state = VehicleState.from_ypr([1.0, 2.0, -3.0], np.deg2rad([-30.0, 10.0, 20.0]), 0.17)
    doc = copy.deepcopy(DOC)
    doc["frames"][1] = frame_to_dict("f2.png", "nose", state, use_quat=True)
    back = load_pair_file(write(pair_dir, doc)).frames[1]["state"]
    np.testing.assert_allclose(back.T_body_ned, state.T_body_ned, atol=1e-12)
