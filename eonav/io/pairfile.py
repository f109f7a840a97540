"""The pair file (docs/pair-file.md): a public contract read by ``eonav locate`` and written by users and tests.

    {"cameras": {"nose": {"width", "height", "fx", "fy", "cx", "cy",
                          "mount": {"l_m": [x, y, z], "eps_deg": [eps1, eps2, eps3]}}},
     "frames": [{"image": "f1.png", "camera": "nose", "t": 0.0,
                 "position_ned_m": [n, e, d], "ypr_deg": [yaw, pitch, roll]  |  "q_wxyz": [w, x, y, z]}, ...]}

Image paths are relative to the pair file. Frame 0 is the reference: ranges come on its pixel grid.
A camera may carry a lens model (``"distortion"`` or ``"calibration"``, docs/pair-file.md): its images are then
undistorted on load to the pinhole camera the ranging uses (``eonav.io.calibration``).
Every error names the field and what was expected; so does a key the contract does not know.
"""
from __future__ import annotations

import json
import math
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from eonav import InputError
from eonav.geometry.camera import Camera, VehicleState, View
from eonav.io.calibration import (DistortedCamera, Undistorter, check_distortion, load_calibration,
                                 mount_from_T_cam_imu)
from eonav.io.files import read_regular_file
from eonav.io.images import ImageSizeError, load_grey

MAX_PAIR_FILE_BYTES = 16 << 20     # a pair file is a few kB per frame: 16 MiB is tens of thousands of frames
MAX_TOTAL_PIXELS = 1 << 28         # decoded images of one pair file: 1 GiB of float32 grey

PAIR_KEYS = ("cameras", "frames")
INTRINSIC_KEYS = ("width", "height", "fx", "fy", "cx", "cy")
CAMERA_KEYS = (*INTRINSIC_KEYS, "mount", "distortion", "calibration", "time_offset_s")
FRAME_KEYS = ("image", "camera", "t", "position_ned_m", "ypr_deg", "q_wxyz")


@dataclass
class CameraModel:
    """A camera entry: the pinhole ``camera`` the ranging uses, the ``undistort`` step from raw frames to it
    (None for a pinhole lens) and ``time_offset_s`` (source stamp -> start of exposure; camera ingest)."""
    camera: Camera
    undistort: Undistorter | None = None
    time_offset_s: float = 0.0


@dataclass
class PairFile:
    cameras: dict
    frames: list          # list of dicts with keys: image_path (Path), camera (str), t (float), state (VehicleState)
    undistorters: dict = field(default_factory=dict)     # camera name -> Undistorter (distorted cameras only)

    def views(self, load_images: bool = True, indices=None) -> list:
        """Views of the frames ``indices`` (default all, in file order). Images are loaded, checked against the
        camera size (from the file header, before decoding; at most ``MAX_TOTAL_PIXELS`` decoded in all) and, for a
        camera with a lens model, undistorted."""
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
            if fr["camera"] in self.undistorters:
                img = self.undistorters[fr["camera"]](img)
            out.append(View(cam, fr["state"], img))
        return out


def _known_keys(obj: dict, allowed, where: str) -> None:
    for k in obj:
        if k not in allowed:
            raise InputError(f"{where}.{k}: unknown key; expected one of {list(allowed)}")


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


def parse_camera(name: str, c: dict, base: Path | None = None) -> Camera:
    """The pinhole camera of a camera entry (for a distorted lens: the undistorted camera)."""
    return parse_camera_model(name, c, base).camera


def _calibration_file(c, where: str, base: Path | None) -> DistortedCamera:
    ref = c if isinstance(c, dict) else {"file": c}
    if not isinstance(ref.get("file"), str) or not ref["file"]:
        raise InputError(f"{where}: expected a path (relative to this file) or an object with file, camera")
    _known_keys(ref, ("file", "camera", "imu_frame"), where)
    return load_calibration(Path(base or ".") / ref["file"], camera=ref.get("camera"))


def parse_camera_model(name: str, c: dict, base: Path | None = None) -> CameraModel:
    """A camera entry: pinhole intrinsics, or raw intrinsics + ``distortion``, or a ``calibration`` file
    (relative to ``base``); ``mount`` (default: Kalibr's T_cam_imu if the file has one, else zero) and
    ``time_offset_s`` (default: Kalibr's timeshift_cam_imu, else 0)."""
    where = f"cameras.{name}"
    if not isinstance(c, dict):
        raise InputError(f"{where}: expected an object, got {type(c).__name__}")
    _known_keys(c, CAMERA_KEYS, where)
    if "calibration" in c:
        for k in (*INTRINSIC_KEYS, "distortion"):
            if k in c:
                raise InputError(f"{where}.{k}: the intrinsics come from the calibration file; remove {k!r}")
        dist = _calibration_file(c["calibration"], where + ".calibration", base)
        w, h, fx, fy, cx, cy = dist.width, dist.height, dist.fx, dist.fy, dist.cx, dist.cy
    else:
        w = _num(c, "width", where, positive=True, integer=True)
        h = _num(c, "height", where, positive=True, integer=True)
        fx = _num(c, "fx", where, positive=True)
        fy = _num(c, "fy", where, positive=True)
        cx = _num(c, "cx", where)
        cy = _num(c, "cy", where)
        dist = None
        if "distortion" in c:
            d = c["distortion"]
            if not isinstance(d, dict):
                raise InputError(f"{where}.distortion: expected an object with model and coeffs")
            _known_keys(d, ("model", "coeffs"), where + ".distortion")
            model, coeffs = check_distortion(d.get("model"), d.get("coeffs"), where + ".distortion")
            dist = DistortedCamera(w, h, fx, fy, cx, cy, model, coeffs, source=where + ".distortion")
    mount = c.get("mount", {})
    if not isinstance(mount, dict):
        raise InputError(f"{where}.mount: expected an object with l_m and eps_deg")
    _known_keys(mount, ("l_m", "eps_deg"), where + ".mount")
    l_m = _vec(mount, "l_m", 3, where + ".mount") if "l_m" in mount else np.zeros(3)
    eps = np.deg2rad(_vec(mount, "eps_deg", 3, where + ".mount")) if "eps_deg" in mount else np.zeros(3)
    if "mount" not in c and dist is not None and dist.T_cam_imu is not None:
        imu_frame = c["calibration"].get("imu_frame", "frd") if isinstance(c["calibration"], dict) else "frd"
        l_m, eps = mount_from_T_cam_imu(dist.T_cam_imu, imu_frame, f"{where}.calibration T_cam_imu")
    offset = dist.timeshift_s if dist is not None and dist.timeshift_s is not None else 0.0
    if "time_offset_s" in c:
        offset = _num(c, "time_offset_s", where)
    if dist is None:
        return CameraModel(Camera(name, w, h, fx, fy, cx, cy, l_m, eps), None, offset)
    und = Undistorter.for_camera(dist, name, l_m, eps)
    return CameraModel(und.camera, und, offset)


def parse_frame(i: int, fr: dict, cameras: dict, base: Path) -> dict:
    where = f"frames[{i}]"
    if not isinstance(fr, dict):
        raise InputError(f"{where}: expected an object")
    _known_keys(fr, FRAME_KEYS, where)
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
    _known_keys(doc, PAIR_KEYS, "pair file")
    cams = doc.get("cameras")
    if not isinstance(cams, dict) or not cams:
        raise InputError("cameras: expected a non-empty object of named cameras")
    models = {name: parse_camera_model(name, c, base) for name, c in cams.items()}
    cameras = {name: m.camera for name, m in models.items()}
    frames = doc.get("frames")
    if not isinstance(frames, list) or len(frames) < 2:
        raise InputError("frames: expected a list of at least 2 frames (frame 0 is the reference)")
    return PairFile(cameras, [parse_frame(i, fr, cameras, base) for i, fr in enumerate(frames)],
                    {name: m.undistort for name, m in models.items() if m.undistort is not None})


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


def load_camera_models(path, what: str = "cameras file") -> dict:
    """Named ``CameraModel``s from a JSON file holding a pair file's "cameras" section, or a whole pair file
    (calibration files are relative to it)."""
    doc = read_json(path, what)
    if isinstance(doc, dict) and isinstance(doc.get("cameras"), dict):
        _known_keys(doc, PAIR_KEYS, what)
        doc = doc["cameras"]
    if not isinstance(doc, dict) or not doc:
        raise InputError(f"{what} {path}: expected an object of named cameras")
    return {name: parse_camera_model(name, c, Path(path).parent) for name, c in doc.items()}


def load_cameras(path, what: str = "cameras file") -> dict:
    """Named pinhole cameras (undistorted ones for distorted lenses) of a cameras file (``load_camera_models``)."""
    return {name: m.camera for name, m in load_camera_models(path, what).items()}


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
