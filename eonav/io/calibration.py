"""Real lenses: calibration files -> the distorted camera model, and the undistorter to the pinhole camera that
every range estimator uses.

Files read by ``load_calibration`` (docs/pair-file.md, "Distorted cameras"):

- OpenCV ``cv2.FileStorage`` YAML or XML as the calibration samples write it: ``camera_matrix``,
  ``distortion_coefficients``, ``image_width``, ``image_height``, optional ``fisheye_model`` (non-zero: fisheye);
- ROS ``camera_info`` YAML: ``image_width``, ``image_height``, ``camera_matrix.data``, ``distortion_model``
  (``plumb_bob``, ``rational_polynomial``, ``equidistant``), ``distortion_coefficients.data``;
- Kalibr camchain YAML (``camN`` entries): ``camera_model: pinhole`` with ``distortion_model`` ``radtan`` or
  ``equidistant``, ``intrinsics`` [fu, fv, pu, pv], ``distortion_coeffs``, ``resolution`` [w, h], and from a
  camera-IMU calibration ``T_cam_imu`` (IMU -> camera optical frame) and ``timeshift_cam_imu`` (t_imu = t_cam + shift).

Distortion models: ``radtan`` = OpenCV's standard model (k1, k2, p1, p2[, k3[, k4, k5, k6[, s1..s4[, tx, ty]]]]:
4, 5, 8, 12 or 14 coefficients; ROS plumb_bob / rational_polynomial, Kalibr radtan), undistorted by
``cv2.initUndistortRectifyMap``; ``equidistant`` = OpenCV's fisheye model (k1..k4; ROS and Kalibr equidistant),
undistorted by ``cv2.fisheye.initUndistortRectifyMap``. Pixel centres are at integers in all three tools, as here.

``Undistorter`` picks the output pinhole camera once (same size, square pixels, no black border: the largest
field whose every pixel maps inside the source image) and builds the remap tables on first use; each frame is
one ``cv2.remap``. ``mount_from_T_cam_imu`` turns Kalibr's extrinsics into the pair file's mount (l_m, eps).
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field
from pathlib import Path

import cv2
import numpy as np

from eonav import InputError
from eonav.geometry.camera import Camera
from eonav.geometry.frames import T_PAPERCAM_OPTICAL, ypr_from_T_body_ned
from eonav.io.images import MAX_IMAGE_PIXELS

MODELS = ("radtan", "equidistant")
RADTAN_LENGTHS = (4, 5, 8, 12, 14)
ROS_MODELS = {"plumb_bob": "radtan", "rational_polynomial": "radtan", "radtan": "radtan",
              "equidistant": "equidistant", "fisheye": "equidistant"}
IMU_FRAMES = {"frd": np.eye(3), "flu": np.diag([1.0, -1.0, -1.0])}   # R_imu_body: body FRD -> IMU axes
_UNDISTORT_CRITERIA = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 100, 1e-12)


@dataclass(frozen=True)
class DistortedCamera:
    """A real camera as calibrated: raw-image intrinsics (pixels), a distortion ``model`` and its ``coeffs``;
    from Kalibr also ``T_cam_imu`` (4 x 4, IMU -> optical camera frame, metres) and ``timeshift_s``."""
    width: int
    height: int
    fx: float
    fy: float
    cx: float
    cy: float
    model: str
    coeffs: tuple
    T_cam_imu: np.ndarray | None = None
    timeshift_s: float | None = None
    source: str = "distortion"

    def __post_init__(self):
        check_distortion(self.model, self.coeffs, self.source)
        if self.width <= 0 or self.height <= 0 or not (self.fx > 0 and self.fy > 0):
            raise InputError(f"{self.source}: expected a positive image size and focal lengths, got "
                             f"{self.width}x{self.height}, fx={self.fx}, fy={self.fy}")
        if not np.all(np.isfinite([self.fx, self.fy, self.cx, self.cy])):
            raise InputError(f"{self.source}: intrinsics must be finite")

    @property
    def K(self) -> np.ndarray:
        return np.array([[self.fx, 0.0, self.cx], [0.0, self.fy, self.cy], [0.0, 0.0, 1.0]])

    @property
    def D(self) -> np.ndarray:
        return np.asarray(self.coeffs, float).reshape(-1, 1) if self.model == "equidistant" \
            else np.asarray(self.coeffs, float)


def check_distortion(model, coeffs, where: str) -> tuple:
    """A (model, coefficients) pair as ``DistortedCamera`` takes it, or an InputError naming ``where``."""
    if model not in MODELS:
        raise InputError(f"{where}.model: {model!r} is not one of {list(MODELS)}")
    if (not isinstance(coeffs, (list, tuple)) or not all(isinstance(x, (int, float)) and not isinstance(x, bool)
                                                          for x in coeffs)):
        raise InputError(f"{where}.coeffs: expected a list of numbers, got {coeffs!r}")
    n = len(coeffs)
    if model == "radtan" and n not in RADTAN_LENGTHS:
        raise InputError(f"{where}.coeffs: radtan takes {', '.join(map(str, RADTAN_LENGTHS))} coefficients "
                         f"(k1, k2, p1, p2[, k3[, k4, k5, k6 ...]]), got {n}")
    if model == "equidistant" and n != 4:
        raise InputError(f"{where}.coeffs: equidistant takes 4 coefficients (k1, k2, k3, k4), got {n}")
    try:
        values = tuple(float(x) for x in coeffs)       # (JSON integers have no limit; floats do)
    except OverflowError:
        raise InputError(f"{where}.coeffs: expected finite numbers, got an integer beyond the float range") from None
    if not np.all(np.isfinite(values)):
        raise InputError(f"{where}.coeffs: expected finite numbers, got {coeffs!r}")
    return model, values


# --------------------------------------------------------------------------------------------------
# calibration files

def load_calibration(path, camera: str | None = None) -> DistortedCamera:
    """The camera of an OpenCV, ROS camera_info or Kalibr camchain file (``camera``: the Kalibr entry, default
    the only one or ``cam0``). Errors name the file and the field."""
    p = Path(path)
    if not p.is_file():
        raise InputError(f"calibration file not found: {p}")
    if p.suffix.lower() == ".xml":
        return _from_opencv(p)
    import yaml
    text = p.read_text()
    if text.lstrip().startswith("%YAML:") or "!!opencv-matrix" in text:     # cv2.FileStorage's own YAML
        return _from_opencv(p)
    try:
        doc = yaml.safe_load(text)
    except yaml.YAMLError as e:
        raise InputError(f"calibration file {p}: not valid YAML ({e})") from None
    if not isinstance(doc, dict):
        raise InputError(f"calibration file {p}: expected a YAML map")
    if isinstance(doc.get("camera_matrix"), dict):
        return _from_ros(doc, p)
    cams = {k: v for k, v in doc.items() if isinstance(v, dict) and "intrinsics" in v}
    if cams:
        return _from_kalibr(cams, p, camera)
    raise InputError(f"calibration file {p}: not an OpenCV (camera_matrix, distortion_coefficients), ROS "
                     "camera_info (camera_matrix.data) or Kalibr camchain (camN.intrinsics) file")


def _numbers(v, n, where, exact=True) -> list:
    flat = np.asarray(v, dtype=object).ravel().tolist() if isinstance(v, (list, tuple)) else None
    if (flat is None or (exact and len(flat) != n) or not all(isinstance(x, (int, float))
                                                               and not isinstance(x, bool) for x in flat)):
        raise InputError(f"{where}: expected {n if exact else 'a list of'} numbers, got {v!r}")
    try:
        return [float(x) for x in flat]
    except OverflowError:
        raise InputError(f"{where}: expected finite numbers, got an integer beyond the float range") from None


def _size(w, h, where) -> tuple:
    """A calibration's image size: positive whole numbers, at most ``MAX_IMAGE_PIXELS`` pixels in all (the largest
    image eonav decodes; the undistortion maps are built at this size before any image is read)."""
    if not all(isinstance(x, (int, float)) and not isinstance(x, bool) and (isinstance(x, int) or math.isfinite(x))
               and int(x) == x and x > 0 for x in (w, h)):
        raise InputError(f"{where}: expected a positive whole image width and height, got {w!r} x {h!r}")
    if int(w) * int(h) > MAX_IMAGE_PIXELS:
        raise InputError(f"{where}: {int(w)} x {int(h)} is more than the {MAX_IMAGE_PIXELS} pixels of the largest "
                         f"image eonav reads")
    return int(w), int(h)


def _from_opencv(p: Path) -> DistortedCamera:
    try:
        fs = cv2.FileStorage(str(p), cv2.FILE_STORAGE_READ)
    except cv2.error as e:
        raise InputError(f"calibration file {p}: cv2.FileStorage cannot parse it ({str(e).strip()[-120:]})") from None
    try:
        def mat(key):
            node = fs.getNode(key)
            m = None if node.empty() else node.mat()
            if m is None:
                raise InputError(f"{p}: {key}: missing (expected an OpenCV matrix)")
            return np.asarray(m, float)

        K = mat("camera_matrix")
        if K.shape != (3, 3):
            raise InputError(f"{p}: camera_matrix: expected 3 x 3, got {K.shape}")
        D = mat("distortion_coefficients").ravel().tolist()
        w, h = (fs.getNode(k).real() if not fs.getNode(k).empty() else None for k in ("image_width", "image_height"))
        fisheye = not fs.getNode("fisheye_model").empty() and fs.getNode("fisheye_model").real() != 0
    finally:
        fs.release()
    w, h = _size(w, h, f"{p}: image_width, image_height")
    model = "equidistant" if fisheye else "radtan"
    return DistortedCamera(w, h, K[0, 0], K[1, 1], K[0, 2], K[1, 2], model, tuple(D), source=str(p))


def _from_ros(doc: dict, p: Path) -> DistortedCamera:
    K = _numbers(doc["camera_matrix"].get("data"), 9, f"{p}: camera_matrix.data")
    name = doc.get("distortion_model")
    if name not in ROS_MODELS:
        raise InputError(f"{p}: distortion_model: {name!r} is not one of {sorted(ROS_MODELS)}")
    dist = doc.get("distortion_coefficients")
    D = _numbers(dist.get("data") if isinstance(dist, dict) else None, 0, f"{p}: distortion_coefficients.data",
                 exact=False)
    w, h = _size(doc.get("image_width"), doc.get("image_height"), f"{p}: image_width, image_height")
    return DistortedCamera(w, h, K[0], K[4], K[2], K[5], ROS_MODELS[name], tuple(D), source=str(p))


def _from_kalibr(cams: dict, p: Path, camera: str | None) -> DistortedCamera:
    if camera is None:
        camera = next(iter(cams)) if len(cams) == 1 else "cam0"
    if camera not in cams:
        raise InputError(f"{p}: camera {camera!r} is not one of {sorted(cams)}")
    c, where = cams[camera], f"{p}: {camera}"
    if c.get("camera_model") != "pinhole":
        raise InputError(f"{where}.camera_model: {c.get('camera_model')!r} is not supported (expected pinhole)")
    model = c.get("distortion_model")
    if model not in ("radtan", "equidistant", "equi"):
        raise InputError(f"{where}.distortion_model: {model!r} is not supported (expected radtan or equidistant)")
    fu, fv, pu, pv = _numbers(c.get("intrinsics"), 4, f"{where}.intrinsics")
    D = _numbers(c.get("distortion_coeffs"), 0, f"{where}.distortion_coeffs", exact=False)
    res = c.get("resolution")
    if not isinstance(res, (list, tuple)) or len(res) != 2:
        raise InputError(f"{where}.resolution: expected [width, height], got {res!r}")
    w, h = _size(res[0], res[1], f"{where}.resolution")
    T = None
    if "T_cam_imu" in c:
        T = np.asarray(_numbers(c["T_cam_imu"], 16, f"{where}.T_cam_imu"), float).reshape(4, 4)
    shift = None
    if "timeshift_cam_imu" in c:
        shift = _numbers([c["timeshift_cam_imu"]], 1, f"{where}.timeshift_cam_imu")[0]
    return DistortedCamera(w, h, fu, fv, pu, pv, "equidistant" if model == "equi" else model, tuple(D),
                           T_cam_imu=T, timeshift_s=shift, source=f"{p}: {camera}")


# --------------------------------------------------------------------------------------------------
# extrinsics

def mount_from_T_cam_imu(T_cam_imu, imu_frame: str = "frd", where: str = "T_cam_imu"):
    """(l_body_m, eps_rad) of the pair file's mount from Kalibr's T_cam_imu (p_optical = R p_imu + t).

    The IMU axes are taken to be the body's FRD axes (``imu_frame="frd"``) or ROS FLU (``"flu"``: x forward,
    y left, z up); the body origin is at the IMU. Then T1 = T_PAPERCAM_OPTICAL R R_imu_body (camera Xc = optical
    z, Yc = x, Zc = y, docs/conventions.md), the lens centre in the body is l = R_imu_body^T (-R^T t), and eps are
    T1's angles in the form of eq. (11)."""
    if imu_frame not in IMU_FRAMES:
        raise InputError(f"{where}: imu_frame {imu_frame!r} is not one of {sorted(IMU_FRAMES)}")
    T = np.asarray(T_cam_imu, float)
    if T.shape != (4, 4) or not np.all(np.isfinite(T)) or np.abs(T[3] - [0, 0, 0, 1]).max() > 1e-9:
        raise InputError(f"{where}: expected a 4 x 4 rigid transform with last row [0, 0, 0, 1]")
    R, t = T[:3, :3], T[:3, 3]
    if np.abs(R @ R.T - np.eye(3)).max() > 1e-5 or np.linalg.det(R) < 0:
        raise InputError(f"{where}: the rotation block is not a proper rotation matrix")
    R_ib = IMU_FRAMES[imu_frame]
    T1 = T_PAPERCAM_OPTICAL @ R @ R_ib
    l_body_m = R_ib.T @ (-R.T @ t)
    return l_body_m, ypr_from_T_body_ned(T1)


# --------------------------------------------------------------------------------------------------
# undistortion

def _normalised(dist: DistortedCamera, pts_px: np.ndarray) -> np.ndarray:
    """Undistorted normalised coordinates (x, y) = (Yc/Xc, Zc/Xc) of raw pixels (N x 2)."""
    src = np.ascontiguousarray(pts_px, np.float64).reshape(-1, 1, 2)
    if dist.model == "equidistant":
        out = cv2.fisheye.undistortPoints(src, dist.K, dist.D, criteria=_UNDISTORT_CRITERIA)
    else:
        out = cv2.undistortPoints(src, dist.K, dist.D, criteria=_UNDISTORT_CRITERIA)
    return out.reshape(-1, 2)


def output_camera_matrix(dist: DistortedCamera) -> np.ndarray:
    """The pinhole K of the undistorted image: same size, square pixels, no black border.

    The raw image border, undistorted, encloses the field the camera sees; the largest axis-aligned rectangle
    inside it (its left/right/top/bottom edges at the innermost border points) is scaled onto the image with
    one focal length, the larger of the two that fit it horizontally and vertically, and centred on it."""
    w, h = dist.width, dist.height
    us, vs = np.arange(w, dtype=float), np.arange(h, dtype=float)
    left = _normalised(dist, np.c_[np.zeros(h), vs])[:, 0].max()
    right = _normalised(dist, np.c_[np.full(h, w - 1.0), vs])[:, 0].min()
    top = _normalised(dist, np.c_[us, np.zeros(w)])[:, 1].max()
    bottom = _normalised(dist, np.c_[us, np.full(w, h - 1.0)])[:, 1].min()
    if not (np.all(np.isfinite([left, right, top, bottom])) and right > left and bottom > top):
        raise InputError(f"{dist.source}: the distortion model does not map the image border to a usable field "
                         f"(inner field x {left:.3f}..{right:.3f}, y {top:.3f}..{bottom:.3f})")
    f = max((w - 1) / (right - left), (h - 1) / (bottom - top))
    cx = (w - 1) / 2 - f * (left + right) / 2
    cy = (h - 1) / 2 - f * (top + bottom) / 2
    return np.array([[f, 0.0, cx], [0.0, f, cy], [0.0, 0.0, 1.0]])


@dataclass
class Undistorter:
    """Raw frames of ``dist`` -> images of the pinhole ``camera`` (same size). Tables built once, on first use."""
    dist: DistortedCamera
    camera: Camera
    interpolation: int = cv2.INTER_LINEAR
    _maps: tuple | None = field(default=None, repr=False)

    @classmethod
    def for_camera(cls, dist: DistortedCamera, name: str, l_body_m=(0.0, 0.0, 0.0), eps_rad=(0.0, 0.0, 0.0)):
        K = output_camera_matrix(dist)
        cam = Camera(name, dist.width, dist.height, *(float(x) for x in K[[0, 1, 0, 1], [0, 1, 2, 2]]),
                     l_body_m, eps_rad)
        return cls(dist, cam)

    @property
    def K_new(self) -> np.ndarray:
        c = self.camera
        return np.array([[c.fx, 0.0, c.cx], [0.0, c.fy, c.cy], [0.0, 0.0, 1.0]])

    def maps(self) -> tuple:
        """(map_u, map_v) float32 H x W: the raw pixel each output pixel samples."""
        if self._maps is None:
            d, size = self.dist, (self.dist.width, self.dist.height)
            if d.model == "equidistant":
                self._maps = cv2.fisheye.initUndistortRectifyMap(d.K, d.D, np.eye(3), self.K_new, size, cv2.CV_32FC1)
            else:
                self._maps = cv2.initUndistortRectifyMap(d.K, d.D, None, self.K_new, size, cv2.CV_32FC1)
        return self._maps

    def __call__(self, image: np.ndarray) -> np.ndarray:
        img = np.asarray(image)
        if img.shape[:2] != (self.dist.height, self.dist.width):
            raise InputError(f"camera {self.camera.name!r}: frame is {img.shape[1]}x{img.shape[0]} but its "
                             f"calibration is {self.dist.width}x{self.dist.height}")
        mu, mv = self.maps()
        return cv2.remap(img, mu, mv, self.interpolation, borderMode=cv2.BORDER_REPLICATE)


# --------------------------------------------------------------------------------------------------
# per-frame correction (camera ingest)

@dataclass(frozen=True)
class FrameCorrection:
    """What camera ingest does to each frame of one camera: undistort (if the camera has a model) and move the
    stamp by ``shift_us`` = time offset + exposure / 2, so it names the middle of the exposure."""
    undistort: Undistorter | None = None
    shift_us: int = 0

    def __call__(self, image: np.ndarray, stamp_us: int):
        return (image if self.undistort is None else self.undistort(image)), int(stamp_us) + self.shift_us


def frame_correction(undistort: Undistorter | None, time_offset_s: float = 0.0,
                     exposure_s: float | None = None) -> FrameCorrection:
    """The ``FrameCorrection`` of a camera: ``time_offset_s`` is added to the source stamp to give the start of
    the exposure on the host clock; half of ``exposure_s`` (when known) moves it to the middle."""
    if not np.isfinite(time_offset_s) or abs(time_offset_s) > 10.0:
        raise InputError(f"time_offset_s {time_offset_s!r}: expected a finite offset of at most 10 s")
    if exposure_s is not None and not (np.isfinite(exposure_s) and 0 <= exposure_s <= 1.0):
        raise InputError(f"exposure {exposure_s!r} s: expected 0 .. 1 s")
    shift_s = time_offset_s + (exposure_s or 0.0) / 2
    return FrameCorrection(undistort, int(round(shift_s * 1e6)))
