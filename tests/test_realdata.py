"""Readers of the public real data (eonav.io.datasets) checked against independent references in that data."""
from pathlib import Path

import cv2
import numpy as np
import pytest

from eonav.geometry.camera import pair_geometry
from eonav.ranging.locate import locate
from eonav.io.datasets import MIDDLEBURY_BASELINE_M, kitti_views, middlebury_pair

DATA = Path(__file__).resolve().parents[1].parent / "shared" / "data"
pytestmark = pytest.mark.realdata


def need(sub):
    if not (DATA / sub).is_dir():
        pytest.skip(f"real data not found at {DATA / sub} (../shared/data)")


def test_middlebury_truth_is_f_b_over_gt_disparity():
    need("middlebury2001_2003")
    a, b, truth, mask = middlebury_pair(DATA, "venus")
    gt = cv2.imread(str(DATA / "middlebury2001_2003/venus/groundtruth.png"), cv2.IMREAD_GRAYSCALE) / 8.0
    assert np.allclose(truth[mask], a.camera.fx * MIDDLEBURY_BASELINE_M / gt[mask], rtol=1e-5)
    g = pair_geometry(a, b)      # rectified: right camera 0.1 m to starboard, no rotation
    assert np.allclose(g.R_ba, np.eye(3)) and np.allclose(g.t_ba_m, [0, -MIDDLEBURY_BASELINE_M, 0])


def test_kitti_stereo_geometry_agrees_with_an_independent_disparity():
    # The slambook disparity of frame 0 comes from another stereo method (not ground truth): our KITTI camera
    # model + mount turned into disparity must agree with it where both exist.
    need("kitti00_frames0-5")
    views, right0 = kitti_views(DATA)
    res = locate(views[0], right0, method="dense")
    fb = right0.camera.fx * right0.camera.l_body_m[1]
    ours = fb / res.range_m
    ref = cv2.imread(str(DATA / "kitti00_frames0-5/disparity_000000_slambook_NOT_GT.png"), -1).astype(np.float32)
    ok = np.isfinite(ours) & (ref > 5)
    assert ok.sum() > 50_000
    assert abs(np.median(ref[ok] / ours[ok]) - 1) < 0.02
    assert np.median(np.abs(ref[ok] - ours[ok])) < 1.0          # pixels


def test_kitti_poses_move_the_camera_forward():
    need("kitti00_frames0-5")
    views, _ = kitti_views(DATA)
    g = pair_geometry(views[0], views[1])
    # ~0.86 m forward along the optical axis: a point ahead is nearer in frame 1 (t_x < 0), little sideways
    assert -0.9 < g.t_ba_m[0] < -0.8 and abs(g.t_ba_m[1]) < 0.1 and abs(g.t_ba_m[2]) < 0.1


def test_default_data_dir_is_shared_data_beside_the_checkout():
    # the benches' default --data: the folder beside the repository (its parent holds both), as the tests find it
    from eonav.io.datasets import default_data_dir
    assert default_data_dir() == Path(__file__).resolve().parents[1].parent / "shared" / "data"


def test_hololens_reader_against_its_files():
    """The HoloLens sequence as the files give it: truth = depth PNG in mm / 1000 (0 unknown -> NaN), stamps k / 30 s,
    and the pair geometry from poses.txt (camera-to-world, optical x right, y down, z forward) worked by hand:
    X_b = R_ba X_a + t_ba with R_x = P R_wx^T, P the optical -> paper-camera axes (x forward = z_opt, y = x_opt,
    z = y_opt), so R_ba = P R_wb^T R_wa P^T and t_ba = P R_wb^T (c_a - c_b). Catches a unit slip of the depth and
    the pose read as world-to-camera (rotation not transposed)."""
    need("hololens_dvmvs_20f")
    from eonav.io.datasets import hololens_sequence
    d = DATA / "hololens_dvmvs_20f"
    views, truth = hololens_sequence(DATA)
    names = sorted(p.name for p in (d / "images").glob("*.png"))
    assert len(views) == len(truth) == len(names) == 20
    for k in (0, 13):
        depth = cv2.imread(str(d / "depth" / names[k]), cv2.IMREAD_UNCHANGED).astype(np.float64)
        assert np.array_equal(np.isnan(truth[k]), depth == 0)
        np.testing.assert_allclose(truth[k][depth > 0], depth[depth > 0] / 1000.0, rtol=1e-6)
    assert [v.state.t_s for v in views[:3]] == pytest.approx([0.0, 1 / 30, 2 / 30])
    poses = np.loadtxt(d / "poses.txt").reshape(-1, 4, 4)
    P = np.array([[0, 0, 1], [1, 0, 0], [0, 1, 0]], float)
    for a, b in ((0, 1), (3, 19)):
        Ra, ca, Rb, cb = poses[a][:3, :3], poses[a][:3, 3], poses[b][:3, :3], poses[b][:3, 3]
        g = pair_geometry(views[a], views[b])
        np.testing.assert_allclose(g.R_ba, P @ Rb.T @ Ra @ P.T, atol=1e-4)
        np.testing.assert_allclose(g.t_ba_m, P @ Rb.T @ (ca - cb), atol=1e-4)
