"""The pair file (docs/pair-file.md): a public contract read by ``eonav locate`` and written by users and tests.

    {"cameras": {"nose": {"width", "height", "fx", "fy", "cx", "cy",
                          "mount": {"l_m": [x, y, z], "eps_deg": [eps1, eps2, eps3]}}},
     "frames": [{"image": "f1.png", "camera": "nose", "t": 0.0,
                 "position_ned_m": [n, e, d], "ypr_deg": [yaw, pitch, roll]  |  "q_wxyz": [w, x, y, z]}, ...]}

Image paths are relative to the pair file. Frame 0 is the reference: ranges come on its pixel grid.
Every error names the field and what was expected.
"""
from __future__ import annotations

import json
import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from eonav import InputError
from eonav.geometry.camera import Camera, VehicleState, View
from eonav.io.files import read_regular_file
from eonav.io.images import ImageSizeError, load_grey

MAX_PAIR_FILE_BYTES = 16 << 20     # a pair file is a few kB per frame: 16 MiB is tens of thousands of frames
MAX_TOTAL_PIXELS = 1 << 28         # decoded images of one pair file: 1 GiB of float32 grey


@dataclass
class PairFile:
    cameras: dict
    frames: list          # list of dicts with keys: image_path (Path), camera (str), t (float), state (VehicleState)

    def views(self, load_images: bool = True, indices=None) -> list:
        """Views of the frames ``indices`` (default all, in file order). Images are loaded and checked against the
        camera size (from the file header, before decoding); at most ``MAX_TOTAL_PIXELS`` are decoded in all."""
        idx = range(len(self.frames)) if indices is None else list(indices)
        total = sum(self.cameras[self.frames[i]["camera"]].width * self.cameras[self.frames[i]["camera"]].height
                    for i in idx)
        if load_images and total > MAX_TOTAL_PIXELS:
            raise InputError(f"frames: {len(idx)} images of {total} pixels in all, more than the "
                             f"{MAX_TOTAL_PIXELS} eonav decodes for one pair file")
        out = []
        for i in idx:
            fr = self.frames[i]
            cam = self.cameras[fr["camera"]]
            if not load_images:
                out.append(View(cam, fr["state"], np.zeros((cam.height, cam.width), np.float32)))
                continue
            try:
                img = load_grey(fr["image_path"], expect_wh=(cam.width, cam.height))
            except ImageSizeError as e:
                raise InputError(f"frames[{i}].image {fr['image_path'].name}: image is {e.size[0]}x{e.size[1]} "
                                 f"but camera {fr['camera']!r} declares {cam.width}x{cam.height}") from None
            out.append(View(cam, fr["state"], img))
        return out


def _num(obj, key, where, positive=False, integer=False):
    if key not in obj:
        raise InputError(f"{where}.{key}: missing (expected a number)")
    v = obj[key]
    if isinstance(v, bool) or not isinstance(v, (int, float)):
        raise InputError(f"{where}.{key}: expected a number, got {v!r}")
    try:
        f = float(v)                                    # (JSON integers have no limit; floats do)
    except OverflowError:
        raise InputError(f"{where}.{key}: expected a finite number, got an integer of {v.bit_length()} bits") from None
    if not math.isfinite(f):
        raise InputError(f"{where}.{key}: expected a finite number, got {v!r}")
    if integer and int(v) != v:
        raise InputError(f"{where}.{key}: expected a whole number, got {v!r}")
    if positive and v <= 0:
        raise InputError(f"{where}.{key}: expected a positive number, got {v!r}")
    return int(v) if integer else float(v)


def _vec(obj, key, n, where):
    if key not in obj:
        raise InputError(f"{where}.{key}: missing (expected a list of {n} numbers)")
    v = obj[key]
    if (not isinstance(v, (list, tuple)) or len(v) != n
            or not all(isinstance(x, (int, float)) and not isinstance(x, bool) for x in v)):
        raise InputError(f"{where}.{key}: expected a list of {n} numbers, got {v!r}")
    try:
        a = np.array([float(x) for x in v])
    except OverflowError:
        raise InputError(f"{where}.{key}: expected finite numbers, got an integer beyond the float range") from None
    if not np.all(np.isfinite(a)):
        raise InputError(f"{where}.{key}: expected finite numbers, got {v!r}")
    return a


def parse_camera(name: str, c: dict) -> Camera:
    where = f"cameras.{name}"
    if not isinstance(c, dict):
        raise InputError(f"{where}: expected an object, got {type(c).__name__}")
    w = _num(c, "width", where, positive=True, integer=True)
    h = _num(c, "height", where, positive=True, integer=True)
    fx = _num(c, "fx", where, positive=True)
    fy = _num(c, "fy", where, positive=True)
    cx = _num(c, "cx", where)
    cy = _num(c, "cy", where)
    mount = c.get("mount", {})
    if not isinstance(mount, dict):
        raise InputError(f"{where}.mount: expected an object with l_m and eps_deg")
    l_m = _vec(mount, "l_m", 3, where + ".mount") if "l_m" in mount else np.zeros(3)
    eps = _vec(mount, "eps_deg", 3, where + ".mount") if "eps_deg" in mount else np.zeros(3)
    return Camera(name, w, h, fx, fy, cx, cy, l_m, np.deg2rad(eps))


def parse_frame(i: int, fr: dict, cameras: dict, base: Path) -> dict:
    where = f"frames[{i}]"
    if not isinstance(fr, dict):
        raise InputError(f"{where}: expected an object")
    img = fr.get("image")
    if not isinstance(img, str) or not img:
        raise InputError(f"{where}.image: expected a path relative to the pair file, got {img!r}")
    cam = fr.get("camera")
    if not isinstance(cam, str) or cam not in cameras:
        raise InputError(f"{where}.camera: {cam!r} is not one of the cameras {sorted(cameras)}")
    t = _num(fr, "t", where) if "t" in fr else 0.0
    pos = _vec(fr, "position_ned_m", 3, where)
    has_ypr, has_q = "ypr_deg" in fr, "q_wxyz" in fr
    if has_ypr == has_q:
        raise InputError(f"{where}: give exactly one attitude, ypr_deg [yaw, pitch, roll] or q_wxyz [w, x, y, z]")
    if has_ypr:
        state = VehicleState.from_ypr(pos, np.deg2rad(_vec(fr, "ypr_deg", 3, where)), t)
    else:
        state = VehicleState.from_quat(pos, _vec(fr, "q_wxyz", 4, where), t, what=f"{where}.q_wxyz")
    return {"image_path": (base / img), "camera": cam, "t": t, "state": state}


def parse_pair(doc: dict, base: Path) -> PairFile:
    if not isinstance(doc, dict):
        raise InputError("pair file: expected a JSON object with 'cameras' and 'frames'")
    cams = doc.get("cameras")
    if not isinstance(cams, dict) or not cams:
        raise InputError("cameras: expected a non-empty object of named cameras")
    cameras = {name: parse_camera(name, c) for name, c in cams.items()}
    frames = doc.get("frames")
    if not isinstance(frames, list) or len(frames) < 2:
        raise InputError("frames: expected a list of at least 2 frames (frame 0 is the reference)")
    return PairFile(cameras, [parse_frame(i, fr, cameras, base) for i, fr in enumerate(frames)])


def read_json(path, what: str = "pair file"):
    """A JSON document (UTF-8, or UTF-16/32 with its byte order), with errors that say which file (``what``) and
    why. The file must be a regular file of at most ``MAX_PAIR_FILE_BYTES``."""
    p = Path(path)
    data = read_regular_file(p, what, MAX_PAIR_FILE_BYTES)
    try:
        return json.loads(data)
    except UnicodeDecodeError as e:
        raise InputError(f"{what} {p}: not UTF-8 text (byte 0x{e.object[e.start]:02x} at offset {e.start}); "
                         "expected a JSON document in UTF-8") from None
    except RecursionError:
        raise InputError(f"{what} {p}: not valid JSON (nested too deeply)") from None
    except ValueError as e:          # json.JSONDecodeError, and integers of more digits than Python converts
        raise InputError(f"{what} {p}: not valid JSON ({e})") from None


def load_pair_file(path) -> PairFile:
    return parse_pair(read_json(path), Path(path).parent)


def load_cameras(path, what: str = "cameras file") -> dict:
    """Named cameras from a JSON file holding a pair file's "cameras" section, or a whole pair file."""
    doc = read_json(path, what)
    if isinstance(doc, dict) and isinstance(doc.get("cameras"), dict):
        doc = doc["cameras"]
    if not isinstance(doc, dict) or not doc:
        raise InputError(f"{what} {path}: expected an object of named cameras")
    return {name: parse_camera(name, c) for name, c in doc.items()}


def camera_to_dict(cam: Camera) -> dict:
    return {"width": cam.width, "height": cam.height, "fx": cam.fx, "fy": cam.fy, "cx": cam.cx, "cy": cam.cy,
            "mount": {"l_m": [float(x) for x in cam.l_body_m],
                      "eps_deg": [float(x) for x in np.rad2deg(cam.eps_rad)]}}


def frame_to_dict(image: str, camera: str, state: VehicleState, use_quat: bool = False) -> dict:
    from eonav.geometry.frames import quat_wxyz_from_rotation, ypr_from_T_body_ned
    d = {"image": image, "camera": camera, "t": float(state.t_s),
         "position_ned_m": [float(x) for x in state.position_ned_m]}
    if use_quat:
        d["q_wxyz"] = [float(x) for x in quat_wxyz_from_rotation(state.T_body_ned.T)]
    else:
        d["ypr_deg"] = [float(x) for x in np.rad2deg(ypr_from_T_body_ned(state.T_body_ned))]
    return d


def write_pair_file(path, cameras: dict, frames: list) -> None:
    """Write a pair file. ``cameras``: name -> Camera; ``frames``: dicts from ``frame_to_dict``."""
    doc = {"cameras": {n: camera_to_dict(c) for n, c in cameras.items()}, "frames": frames}
    Path(path).write_text(json.dumps(doc, indent=2))
