"""Named two-view scenes with ground truth: ``make_pair(name)`` renders them, ``write_pair`` saves them as a
pair file (docs/pair-file.md) plus ground truth.

Presets (reference view first):
- "paper":    replica of the paper's CH-47B sequence (Table I): 512x512, ~40 deg FOV nose camera, 12 ft over a
              runway, vehicles at 356.4 / 607.0 / 232.8 ft range beside it, motion [5.41, -0.44, 0.02] ft and
              pitch +0.059, yaw -0.08, roll +0.12 deg over 0.17 s.
- "fast":     low fast forward flight, 25 m/s, 0.1 s: tens of pixels of disparity near the ground.
- "turning":  coordinated turn, 15 m/s, 15 deg bank, yaw rate 10 deg/s, 0.1 s.
- "climbing": 20 m/s, pitching up 3 deg/s while climbing at 3 m/s, 0.1 s.
- "stereo":   two cameras at one instant on a 0.8 m rig, different intrinsics, close obstacles.
- "hover":    no motion at all: identical poses (the frames differ only in time stamp and sensor noise).
"""
from __future__ import annotations

from dataclasses import dataclass, field, replace
from pathlib import Path

import numpy as np

from eonav import InputError
from eonav.geometry.camera import Camera, VehicleState, View
from eonav.sim.render import render
from eonav.sim.scene import Box, Runway, Scene

FT_M = 0.3048
PRESETS = ("paper", "fast", "turning", "climbing", "stereo", "hover")


@dataclass
class SimPair:
    views: list                      # [View, View], reference first
    truth: list                      # [Render, Render], one per view
    objects: dict                    # object id -> name
    meta: dict = field(default_factory=dict)
    scene: Scene | None = None


def focal_for_fov(width_px: int, fov_deg: float) -> float:
    """Focal length (pixels) giving a horizontal field of view of fov_deg over width_px pixels."""
    return 0.5 * width_px / np.tan(np.deg2rad(fov_deg) / 2)


def scale_camera(cam: Camera, size) -> Camera:
    """The same camera at another image size (square int or (w, h)): intrinsics scaled, mount kept."""
    if size is None:
        return cam
    w, h = (size, size) if np.isscalar(size) else tuple(size)
    if int(w) != w or int(h) != h or w < 8 or h < 8:
        raise InputError(f"size must be an int >= 8 or (w, h) of ints >= 8, got {size!r}")
    w, h = int(w), int(h)
    sx, sy = w / cam.width, h / cam.height
    return replace(cam, width=w, height=h, fx=cam.fx * sx, fy=cam.fy * sy,
                   cx=(cam.cx + 0.5) * sx - 0.5, cy=(cam.cy + 0.5) * sy - 0.5)


def north_for_range(cam: Camera, state: VehicleState, x_c_m: float, east_m: float, down_m: float) -> float:
    """North coordinate at which the NED point (north, east_m, down_m) is at range x_c_m from ``cam`` at ``state``
    (x_c is affine in north)."""
    from eonav.geometry.frames import camera_from_ned
    args = (cam.T_cam_body, state.T_body_ned, state.position_ned_m, cam.l_body_m)
    x0 = camera_from_ned(np.array([0.0, east_m, down_m]), *args)[0]
    x1 = camera_from_ned(np.array([1.0, east_m, down_m]), *args)[0]
    return float((x_c_m - x0) / (x1 - x0))


def _nose_camera(name="nose", fov_deg=40.0, tilt_deg=-2.0, size=512) -> Camera:
    f = focal_for_fov(size, fov_deg)
    return Camera(name, size, size, f, f, (size - 1) / 2, (size - 1) / 2,
                  l_body_m=[7.6, 0.0, 0.6], eps_rad=np.deg2rad([0.0, tilt_deg, 0.0]))


def _airfield_boxes(extra=()):
    """Generic airfield clutter away from the flight line (buildings far off, a mast)."""
    return [Box.on_ground("hangar", 520.0, -70.0, 40.0, 30.0, 14.0, yaw_deg=8.0, albedo=150.0, contrast=25.0),
            Box.on_ground("tower", 700.0, 60.0, 8.0, 8.0, 22.0, yaw_deg=-15.0, albedo=170.0, contrast=25.0),
            *extra]


def _paper():
    cam = _nose_camera()
    dt = 0.17
    s0 = VehicleState.from_ypr([0.0, 0.0, -12.0 * FT_M], [0.0, 0.0, 0.0], 0.0)
    d_ned = np.array([5.41, -0.44, 0.02]) * FT_M
    s1 = VehicleState.from_ypr(s0.position_ned_m + d_ned, np.deg2rad([-0.08, 0.059, 0.12]), dt)
    # Table I vehicles: range of the centre of the face towards the camera, in ft; parked either side of the runway
    table = [("vehicle1", 356.4, -24.0, 2.6), ("vehicle2", 607.0, 26.0, 3.2), ("vehicle3", 232.8, 21.0, 2.4)]
    boxes = []
    for name, rng_ft, east, height in table:
        length, width = 6.5, 2.5
        n_face = north_for_range(cam, s0, rng_ft * FT_M, east, -height / 2)
        boxes.append(Box.on_ground(name, n_face + length / 2, east, length, width, height,
                                   albedo=95.0 + 12 * len(boxes), contrast=28.0))
    boxes += [Box.on_ground("vehicle4", 140.0, -27.0, 5.0, 2.2, 2.0, yaw_deg=30.0, albedo=140.0, contrast=30.0),
              Box.on_ground("vehicle5", 300.0, 30.0, 9.0, 2.6, 3.4, yaw_deg=-10.0, albedo=85.0, contrast=25.0),
              Box.on_ground("pole", 90.0, 18.0, 0.4, 0.4, 9.0, albedo=60.0, contrast=15.0)]
    scene = Scene(tuple(_airfield_boxes(boxes)), Runway(15.0, -300.0, 2500.0), seed=0)
    meta = {"description": "replica of the paper's CH-47B flight (Menon et al. 1993, Table I): 12 ft over a runway",
            "table1_range_m": {n: r * FT_M for n, r, _, _ in table},
            "table1_range_ft": {n: r for n, r, _, _ in table}}
    return scene, [cam, cam], [s0, s1], meta


def _fast():
    cam = _nose_camera(tilt_deg=-6.0)
    dt, speed = 0.1, 25.0
    s0 = VehicleState.from_ypr([0.0, 2.0, -6.0], [0.0, 0.0, 0.0], 0.0)
    s1 = VehicleState.from_ypr([speed * dt, 2.0, -6.0], [0.0, 0.0, 0.0], dt)
    boxes = [Box.on_ground("truck", 60.0, -8.0, 7.0, 2.5, 3.0, yaw_deg=5.0, albedo=100.0),
             Box.on_ground("van", 35.0, 9.0, 5.0, 2.0, 2.2, yaw_deg=-20.0, albedo=150.0),
             Box.on_ground("pole", 45.0, 3.5, 0.3, 0.3, 8.0, albedo=70.0, contrast=15.0),
             Box.on_ground("shed", 120.0, -25.0, 12.0, 10.0, 6.0, yaw_deg=12.0, albedo=135.0)]
    scene = Scene(tuple(_airfield_boxes(boxes)), Runway(15.0, -300.0, 2500.0), seed=1)
    return scene, [cam, cam], [s0, s1], {"description": "fast low forward flight: 25 m/s at 6 m, 0.1 s apart"}


def _turning():
    cam = _nose_camera(tilt_deg=-5.0)
    dt, speed, bank = 0.1, 15.0, np.deg2rad(15.0)
    yaw_rate = 9.81 * np.tan(bank) / speed                       # coordinated turn
    radius = speed / yaw_rate
    def state(t):
        psi = yaw_rate * t
        pos = [radius * np.sin(psi), radius * (1 - np.cos(psi)), -8.0]   # right turn from heading north
        return VehicleState.from_ypr(pos, [psi, 0.0, bank], t)
    boxes = [Box.on_ground("truck", 45.0, 10.0, 7.0, 2.5, 3.0, yaw_deg=40.0, albedo=100.0),
             Box.on_ground("building", 80.0, 30.0, 15.0, 12.0, 9.0, yaw_deg=20.0, albedo=150.0),
             Box.on_ground("pole", 35.0, 4.0, 0.3, 0.3, 10.0, albedo=70.0, contrast=15.0),
             Box.on_ground("van", 60.0, -12.0, 5.0, 2.0, 2.2, yaw_deg=-20.0, albedo=130.0)]
    scene = Scene(tuple(_airfield_boxes(boxes)), Runway(15.0, -300.0, 2500.0), seed=2)
    meta = {"description": "coordinated right turn: 15 m/s, 15 deg bank, yaw rate %.1f deg/s" % np.rad2deg(yaw_rate)}
    return scene, [cam, cam], [state(0.0), state(dt)], meta


def _climbing():
    cam = _nose_camera(tilt_deg=-4.0)
    dt, speed, climb, q = 0.1, 20.0, 3.0, np.deg2rad(3.0)
    theta0 = np.deg2rad(5.0)
    s0 = VehicleState.from_ypr([0.0, -3.0, -10.0], [0.0, theta0, 0.0], 0.0)
    s1 = VehicleState.from_ypr([speed * dt, -3.0, -10.0 - climb * dt], [0.0, theta0 + q * dt, 0.0], dt)
    boxes = [Box.on_ground("building", 90.0, 12.0, 20.0, 15.0, 18.0, yaw_deg=5.0, albedo=150.0),
             Box.on_ground("mast", 60.0, -6.0, 0.5, 0.5, 25.0, albedo=70.0, contrast=15.0),
             Box.on_ground("truck", 45.0, -12.0, 7.0, 2.5, 3.0, yaw_deg=-30.0, albedo=100.0)]
    scene = Scene(tuple(_airfield_boxes(boxes)), Runway(15.0, -300.0, 2500.0), seed=3)
    return scene, [cam, cam], [s0, s1], {"description": "climb: 20 m/s, 3 m/s up, pitching up 3 deg/s from 5 deg"}


def _stereo():
    size = 512
    left = Camera("left", size, size, 700.0, 700.0, 255.5, 255.5,
                  l_body_m=[2.0, -0.4, 0.3], eps_rad=np.deg2rad([0.0, -6.0, 0.0]))
    right = Camera("right", size, size, 760.0, 758.0, 262.0, 249.0,
                   l_body_m=[2.0, 0.4, 0.3], eps_rad=np.deg2rad([-0.4, -6.3, 0.2]))
    s = VehicleState.from_ypr([0.0, 0.0, -3.0], [0.0, 0.0, 0.0], 0.0)
    boxes = [Box.on_ground("crate", 9.0, -1.5, 1.2, 1.2, 1.2, yaw_deg=20.0, albedo=140.0),
             Box.on_ground("van", 18.0, 3.0, 5.0, 2.0, 2.2, yaw_deg=-30.0, albedo=110.0),
             Box.on_ground("pole", 13.0, 1.2, 0.25, 0.25, 6.0, albedo=70.0, contrast=15.0),
             Box.on_ground("wall", 40.0, -4.0, 1.0, 14.0, 5.0, yaw_deg=10.0, albedo=150.0)]
    scene = Scene(tuple(boxes), Runway(15.0, -300.0, 2500.0), seed=4)
    meta = {"description": "stereo rig, 0.8 m baseline, two cameras with different intrinsics, one instant"}
    return scene, [left, right], [s, s], meta


def _hover():
    scene, cams, states, _ = _paper()
    s0 = states[0]
    s1 = VehicleState(s0.position_ned_m.copy(), s0.T_body_ned.copy(), 0.1)
    return scene, cams, [s0, s1], {"description": "hover: identical poses 0.1 s apart (zero baseline)"}


_BUILDERS = {"paper": _paper, "fast": _fast, "turning": _turning, "climbing": _climbing,
             "stereo": _stereo, "hover": _hover}


def preset_scene(name: str):
    """(scene, [camera_a, camera_b], [state_a, state_b], meta) of a preset, at full size, not rendered."""
    if name not in _BUILDERS:
        raise InputError(f"unknown sim preset {name!r}; expected one of {', '.join(PRESETS)}")
    return _BUILDERS[name]()


def _motion_meta(cams, states) -> dict:
    from eonav.geometry.frames import ypr_from_T_body_ned
    s0, s1 = states
    return {"dt_s": float(s1.t_s - s0.t_s),
            "delta_position_ned_m": [float(x) for x in s1.position_ned_m - s0.position_ned_m],
            "ypr_deg": [[float(x) for x in np.rad2deg(ypr_from_T_body_ned(s.T_body_ned))] for s in states],
            "cameras": [c.name for c in cams]}


def make_pair(name: str, *, seed: int = 0, size=None, supersample: int = 3, noise_sigma: float = 1.0) -> SimPair:
    """Render a preset pair. ``seed`` drives the sensor noise (frame i uses seed*2 + i); ``size`` (int or (w, h))
    overrides the image size, scaling the intrinsics."""
    scene, cams, states, meta = preset_scene(name)
    cams = [scale_camera(c, size) for c in cams]
    truth = [render(scene, c, s, supersample=supersample, noise_sigma=noise_sigma, seed=2 * int(seed) + i)
             for i, (c, s) in enumerate(zip(cams, states))]
    views = [View(c, s, r.image) for c, s, r in zip(cams, states, truth)]
    meta = dict(meta, preset=name, seed=int(seed), noise_sigma=float(noise_sigma), supersample=int(supersample),
                motion=_motion_meta(cams, states))
    ref = truth[0]
    meta["object_range_m"] = {scene.objects[i]: float(np.median(ref.range_m[ref.object_id == i]))
                              for i in np.unique(ref.object_id) if i >= 2}
    return SimPair(views, truth, scene.objects, meta, scene)


def write_pair(sim_pair: SimPair, out_dir) -> Path:
    """Write frame PNGs (8-bit), pair.json (docs/pair-file.md), truth.npz (range_m, object_id of the reference frame)
    and objects.json (id -> name, plus meta). Returns the pair.json path."""
    import json

    import cv2

    from eonav.io.pairfile import camera_to_dict, frame_to_dict, write_pair_file
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    cameras, frames = {}, []
    for i, v in enumerate(sim_pair.views):
        name = f"frame{i + 1}.png"
        if not cv2.imwrite(str(out / name), np.clip(np.round(v.image), 0, 255).astype(np.uint8)):
            raise InputError(f"cannot write image {out / name}")
        if v.camera.name in cameras and camera_to_dict(cameras[v.camera.name]) != camera_to_dict(v.camera):
            raise InputError(f"two different cameras share the name {v.camera.name!r}")
        cameras[v.camera.name] = v.camera
        frames.append(frame_to_dict(name, v.camera.name, v.state))
    path = out / "pair.json"
    write_pair_file(path, cameras, frames)
    ref = sim_pair.truth[0]
    np.savez_compressed(out / "truth.npz", range_m=ref.range_m, object_id=ref.object_id,
                        range_m_frame2=sim_pair.truth[1].range_m, object_id_frame2=sim_pair.truth[1].object_id)
    (out / "objects.json").write_text(json.dumps({"objects": {str(k): n for k, n in sim_pair.objects.items()},
                                                  "meta": sim_pair.meta}, indent=2))
    return path
