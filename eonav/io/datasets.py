"""Readers that turn the public real data sets into eonav views (used by the benchmark and realdata tests).

- Middlebury 2001/2003 rectified stereo (Scharstein & Szeliski): a two-camera rig at one instant. No focal
  length or baseline is published, so we pick f = image width (pixels) and b = 0.1 m; range = f b / d.
- KITTI odometry 00, frames 0-5: a forward-driving camera with ground-truth poses (camera-to-world, optical
  convention x right, y down, z forward) and one right-camera frame (baseline 0.53716 m). No ground-truth depth.
"""
from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np

from eonav import InputError
from eonav.geometry.camera import Camera, VehicleState, View
from eonav.geometry.frames import T_PAPERCAM_OPTICAL
from eonav.io.images import load_grey

MIDDLEBURY_SCENES = ("tsukuba", "venus", "teddy", "cones")
MIDDLEBURY_BASELINE_M = 0.1


def default_data_dir() -> Path:
    """``shared/data`` beside the repository checkout (its parent folder holds both; where CI puts it)."""
    return Path(__file__).resolve().parents[3] / "shared" / "data"


def middlebury_pair(data_dir, scene: str):
    """(view_left, view_right, truth_range_m, mask_nonocc) for one Middlebury scene; truth NaN where unknown."""
    d = Path(data_dir) / "middlebury2001_2003" / scene
    if not d.is_dir():
        raise InputError(f"Middlebury scene folder not found: {d}")
    left, right = load_grey(d / "imL.png"), load_grey(d / "imR.png")
    scale = float((d / "info.txt").read_text().split()[0])
    gt = cv2.imread(str(d / "groundtruth.png"), cv2.IMREAD_GRAYSCALE).astype(np.float32) / scale
    nonocc = cv2.imread(str(d / "nonocc.png"), cv2.IMREAD_GRAYSCALE) > 0
    h, w = left.shape
    f = float(w)
    cam_l = Camera("left", w, h, f, f, (w - 1) / 2, (h - 1) / 2)
    cam_r = Camera("right", w, h, f, f, (w - 1) / 2, (h - 1) / 2, l_body_m=[0.0, MIDDLEBURY_BASELINE_M, 0.0])
    state = VehicleState.from_ypr([0, 0, 0], [0, 0, 0])
    with np.errstate(divide="ignore"):
        truth = np.where(gt > 0, f * MIDDLEBURY_BASELINE_M / gt, np.nan).astype(np.float32)
    return View(cam_l, state, left), View(cam_r, state, right), truth, nonocc & (gt > 0)


def _kitti_calib(d: Path):
    """fx, cx, cy and stereo baseline from KITTI's calib.txt (P0, P1 rows: baseline = -P1[0,3] / fx)."""
    rows = {}
    for line in (d / "calib.txt").read_text().splitlines():
        if ":" in line:
            k, v = line.split(":", 1)
            rows[k.strip()] = np.array(v.split(), float).reshape(3, 4)
    if "P0" not in rows or "P1" not in rows:
        raise InputError(f"{d / 'calib.txt'}: expected P0 and P1 projection rows")
    P0, P1 = rows["P0"], rows["P1"]
    return P0[0, 0], P0[0, 2], P0[1, 2], -P1[0, 3] / P1[0, 0]


def kitti_views(data_dir):
    """Views of KITTI 00 frames 0-5 (left camera, poses from ground truth) plus the right frame 0."""
    d = Path(data_dir) / "kitti00_frames0-5"
    if not d.is_dir():
        raise InputError(f"KITTI folder not found: {d}")
    fx, cx, cy, baseline = _kitti_calib(d)
    poses = np.loadtxt(d / "poses_00_first6.txt").reshape(-1, 3, 4)
    times = np.loadtxt(d / "times_first6.txt").reshape(-1)
    first = load_grey(d / "image_0" / "000000.png")
    h, w = first.shape
    cam_l = Camera("left", w, h, fx, fx, cx, cy)
    cam_r = Camera("right", w, h, fx, fx, cx, cy, l_body_m=[0.0, baseline, 0.0])
    views = []
    for i, P in enumerate(poses):
        R_w_opt, t_w = P[:, :3], P[:, 3]
        # Body frame = paper camera frame of the left camera; the KITTI world frame stands in for NED.
        T_body_world = T_PAPERCAM_OPTICAL @ R_w_opt.T
        img = load_grey(d / "image_0" / f"{i:06d}.png")
        views.append(View(cam_l, VehicleState(t_w, T_body_world, t_s=float(times[i])), img))
    right0 = View(cam_r, views[0].state, load_grey(d / "image_1" / "000000.png"))
    return views, right0


HOLOLENS_RATE_HZ = 30.0       # the recording gives no stamps: frames are taken 1/30 s apart


def hololens_sequence(data_dir):
    """(views, truth_range_m list) of the 20-frame real HoloLens 2 indoor sequence (deep-video-mvs sample data):
    colour PNGs as grey, poses camera-to-world (optical convention) as for KITTI, stamps k / HOLOLENS_RATE_HZ;
    truth = the headset's depth sensor reprojected onto the colour camera (mm, 0 unknown -> NaN): a reference,
    not perfect truth."""
    d = Path(data_dir) / "hololens_dvmvs_20f"
    if not d.is_dir():
        raise InputError(f"HoloLens sequence folder not found: {d}")
    K = np.loadtxt(d / "K.txt").reshape(3, 3)
    poses = np.loadtxt(d / "poses.txt").reshape(-1, 4, 4)
    images = sorted((d / "images").glob("*.png"))
    if len(images) != len(poses):
        raise InputError(f"{d}: {len(images)} images but {len(poses)} poses")
    first = load_grey(images[0])
    h, w = first.shape
    cam = Camera("hololens", w, h, K[0, 0], K[1, 1], K[0, 2], K[1, 2])
    views, truth = [], []
    for i, (P, img) in enumerate(zip(poses, images)):
        u, _, vt = np.linalg.svd(P[:3, :3])          # the file's rotations are orthonormal to ~1e-5 only
        T_body_world = T_PAPERCAM_OPTICAL @ (u @ vt).T
        views.append(View(cam, VehicleState(P[:3, 3], T_body_world, t_s=i / HOLOLENS_RATE_HZ), load_grey(img)))
        depth = cv2.imread(str(d / "depth" / img.name), cv2.IMREAD_UNCHANGED)
        if depth is None or depth.shape != (h, w):
            raise InputError(f"{d / 'depth' / img.name}: missing or not {w}x{h}")
        truth.append(np.where(depth > 0, depth.astype(np.float32) / 1000.0, np.nan).astype(np.float32))
    return views, truth
