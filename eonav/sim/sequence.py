"""Multi-frame simulated sequences with ground truth per frame: what fusion over the stream is tested and benchmarked on.

- A two-view preset (``eonav.sim.presets``: "paper", "fast", "turning", "climbing") flown as a sequence: the
  preset's motion between its two states extended at constant velocity and constant body rate, sampled at
  ``rate_hz``. The LAST frame is the preset's reference state (``end_at_reference``), so that the newest frame --
  the one fusion ranges -- sees the preset's geometry (the paper replica's Table I vehicles at 356 / 607 / 233 ft).
- A continuous flight (``eonav.sim.flight``: "approach", "turning", "climbing") as ``flight:<name>``.

``render_sequence`` returns the views and renders; ``write_sequence`` writes frame PNGs, ``seq.json`` (a pair file
with every frame, docs/pair-file.md), ``truth.npz`` (range_m N x H x W float32, +inf sky; object_id N x H x W) and
``objects.json`` (object names and the meta).
"""
from __future__ import annotations

import json
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from eonav import InputError
from eonav.geometry.camera import VehicleState, View

SEQUENCE_PRESETS = ("paper", "fast", "turning", "climbing")


@dataclass
class SimSequence:
    views: list                      # View per frame, in time order
    truth: list                      # Render per frame
    objects: dict                    # object id -> name
    meta: dict = field(default_factory=dict)


def preset_states(name: str, times_s, end_at_reference: bool = True):
    """Vehicle states of preset ``name`` at ``times_s`` (1-D, seconds): the preset's motion from its first to its
    second state, extended at constant velocity and body rate; with ``end_at_reference`` the last time is the
    preset's first (reference) state, else the first time is."""
    from scipy.spatial.transform import Rotation

    from eonav.sim.presets import preset_scene
    if name not in SEQUENCE_PRESETS:
        raise InputError(f"unknown sequence preset {name!r}; expected one of {', '.join(SEQUENCE_PRESETS)}")
    _, cams, (s0, s1), _ = preset_scene(name)
    t = np.asarray(times_s, float).reshape(-1)
    dt = s1.t_s - s0.t_s
    vel = (s1.position_ned_m - s0.position_ned_m) / dt
    R0 = s0.T_body_ned.T                                             # body -> NED
    rate = Rotation.from_matrix(R0.T @ s1.T_body_ned.T).as_rotvec() / dt   # body-frame rotation per second
    t_ref = t[-1] if end_at_reference else t[0]
    out = []
    for ti in t:
        tau = ti - t_ref
        R = R0 @ Rotation.from_rotvec(rate * tau).as_matrix()
        out.append(VehicleState(s0.position_ned_m + vel * tau, R.T, float(ti)))
    return cams[0], out


def render_sequence(name: str, *, n_frames: int, rate_hz: float, size=None, seed: int = 0, supersample: int = 3,
                    noise_sigma: float = 1.0) -> SimSequence:
    """Render ``n_frames`` at ``rate_hz`` of a preset (``SEQUENCE_PRESETS``) or a flight (``flight:<name>``). Sensor
    noise of frame i uses seed (seed, i)."""
    from eonav.sim.flight import flight, flight_states
    from eonav.sim.presets import preset_scene, scale_camera
    from eonav.sim.render import render
    if int(n_frames) != n_frames or n_frames < 2:
        raise InputError(f"render_sequence: n_frames must be a whole number >= 2, got {n_frames!r}")
    if not (np.isfinite(rate_hz) and rate_hz > 0):
        raise InputError(f"render_sequence: rate_hz must be > 0, got {rate_hz!r}")
    times = np.arange(int(n_frames)) / float(rate_hz)
    if name.startswith("flight:"):
        fl = flight(name.split(":", 1)[1])
        scene, cam, states = fl.scene, fl.camera, flight_states(fl.name, times)
        meta = {"description": fl.description}
    else:
        scene, _, _, meta = preset_scene(name)
        cam, states = preset_states(name, times)
    cam = scale_camera(cam, size)
    views, truth = [], []
    for i, st in enumerate(states):
        noise_seed = int(np.random.SeedSequence([int(seed), i]).generate_state(1)[0])
        r = render(scene, cam, st, supersample=supersample, noise_sigma=noise_sigma, seed=noise_seed)
        views.append(View(cam, st, r.image))
        truth.append(r)
    meta = dict(meta, sequence=name, n_frames=int(n_frames), rate_hz=float(rate_hz), seed=int(seed),
                noise_sigma=float(noise_sigma), supersample=int(supersample))
    return SimSequence(views, truth, dict(scene.objects), meta)


def write_sequence(seq: SimSequence, out_dir, camera_id: str | None = None) -> Path:
    """Write the sequence (module docstring); returns the path of seq.json."""
    import cv2

    from eonav.io.pairfile import frame_to_dict, write_pair_file
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    cam = seq.views[0].camera
    cid = camera_id or cam.name
    frames = []
    for i, v in enumerate(seq.views):
        name = f"frame{i:04d}.png"
        if not cv2.imwrite(str(out / name), np.clip(np.round(v.image), 0, 255).astype(np.uint8)):
            raise InputError(f"cannot write image {out / name}")
        frames.append(frame_to_dict(name, cid, v.state))
    path = out / "seq.json"
    write_pair_file(path, {cid: cam}, frames)
    np.savez_compressed(out / "truth.npz", range_m=np.stack([r.range_m for r in seq.truth]).astype(np.float32),
                        object_id=np.stack([r.object_id for r in seq.truth]))
    (out / "objects.json").write_text(json.dumps({"objects": {str(k): n for k, n in seq.objects.items()},
                                                  "meta": seq.meta}, indent=2))
    return path
