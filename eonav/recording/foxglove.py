"""The project's bus messages as Foxglove-known messages (``foxglove.messages`` of the foxglove-sdk package).

:meth:`FoxgloveConverter.convert` takes one decoded message (``eonav.bus.schema.decode``) and returns
``[(topic, message), ...]``; each message knows its protobuf encoding (``message.encode()``) and its schema
(``type(message).get_schema()``: the FileDescriptorSet of the ``foxglove.*`` type), which is what the recorder
writes into the MCAP file beside the raw channels. Nothing here is hand-encoded.

Topics (no vehicle in them: a recording holds one vehicle, and docs/foxglove-layout.json works for any):

    /camera/<id>/image         frame              RawImage (mono8 / bgr8) or CompressedImage (jpeg / png)
    /camera/<id>/calibration   posed_frame        CameraCalibration (pinhole, no distortion) in cam_<id>_optical
    /range/<id>/image          range_map          colour-mapped range: TURBO on inverse range, near = red; FILLED
                                                  pixels at half brightness; no estimate and infinity = black
    /range/<id>/points         range_map          PointCloud in cam_<id>: x, y, z, range (float32)
    /pose                      nav_state          PoseInFrame of the body in "ned"
    /tf                        nav_state, posed_frame, range_map
                                                  FrameTransform ned -> body (pose), body -> cam_<id> (mount),
                                                  cam_<id> -> cam_<id>_optical (axes)
    /obstacles                 obstacle_list      SceneUpdate: one cube per obstacle (5..95 % extent) + its range

Frames (docs/conventions.md): ``ned`` (X north, Y east, Z down), ``body`` (FRD), ``cam_<id>`` (the paper's camera
frame: Xc optical axis, Yc right, Zc down), ``cam_<id>_optical`` (Foxglove's image frame: x right, y down,
z forward). A FrameTransform gives the child's pose in the parent (p_parent = R p_child + t): ned -> body is
(position_ned_m, q_wxyz) itself, body -> cam_<id> is (l_m, T1^T) (eq. 12 inverted), cam -> optical is
``geometry.T_PAPERCAM_OPTICAL``.

Point cloud, from the range map's own camera (the grid the arrays are on): a pixel (u, v) with range r = x_c is
``x_c = r [1, (u - cx)/fx, (v - cy)/fy]`` (inverse of eqs. 8-9). Pixels with a finite range that is VALID or FILLED
become points; every ``stride``-th row and column is used, the stride chosen so that the grid has at most
``max_points`` cells.
"""
from __future__ import annotations

import math

import numpy as np
from foxglove import messages as fm

from eonav.geometry.frames import T_PAPERCAM_OPTICAL, T_cam_body_from_eps, quat_wxyz_from_rotation
from eonav.ranging.rangemap import FILLED, VALID
from eonav.io.viz import inverse_range_colours

IMAGE_FORMATS = ("raw", "jpeg", "png")
DEFAULT_MAX_POINTS = 20000
WORLD, BODY = "ned", "body"


def cam_frame(camera_id: str) -> str:
    return f"cam_{camera_id}"


def optical_frame(camera_id: str) -> str:
    return f"cam_{camera_id}_optical"


def timestamp(stamp_us: int) -> fm.Timestamp:
    s, us = divmod(int(stamp_us), 1_000_000)
    return fm.Timestamp(sec=s, nsec=us * 1000)


def quaternion(q_wxyz) -> fm.Quaternion:
    w, x, y, z = (float(v) for v in q_wxyz)
    return fm.Quaternion(x=x, y=y, z=z, w=w)


def vector3(v) -> fm.Vector3:
    return fm.Vector3(x=float(v[0]), y=float(v[1]), z=float(v[2]))


def transform(stamp_us: int, parent: str, child: str, translation, q_wxyz) -> fm.FrameTransform:
    return fm.FrameTransform(timestamp=timestamp(stamp_us), parent_frame_id=parent, child_frame_id=child,
                             translation=vector3(translation), rotation=quaternion(q_wxyz))


def point_stride(height: int, width: int, max_points: int) -> int:
    """Smallest s with ceil(H/s) * ceil(W/s) <= max_points."""
    s = max(1, int(math.sqrt(height * width / max(1, max_points))))
    while math.ceil(height / s) * math.ceil(width / s) > max_points:
        s += 1
    return s


def range_points(range_m, flags, cam: dict, max_points: int = DEFAULT_MAX_POINTS) -> np.ndarray:
    """(n, 4) float32 [x, y, z, range] in the camera frame (see the module docstring)."""
    r_full = np.asarray(range_m, np.float32)
    s = point_stride(*r_full.shape, max_points)
    r = r_full[::s, ::s]
    v, u = np.mgrid[0:r_full.shape[0]:s, 0:r_full.shape[1]:s].astype(np.float32)
    ok = np.isfinite(r) & (r > 0)
    if flags is not None:
        ok &= (np.asarray(flags)[::s, ::s] & (VALID | FILLED)) != 0
    r, u, v = r[ok], u[ok], v[ok]
    y = r * (u - np.float32(cam["cx"])) / np.float32(cam["fx"])
    z = r * (v - np.float32(cam["cy"])) / np.float32(cam["fy"])
    return np.stack([r, y, z, r], axis=-1).astype("<f4")


_F32 = fm.PackedElementFieldNumericType.Float32
POINT_FIELDS = [fm.PackedElementField(name=n, offset=4 * i, type=_F32) for i, n in enumerate(("x", "y", "z", "range"))]


def range_colours(range_m, flags, near_m: float, far_m: float) -> np.ndarray:
    """BGR uint8 picture of a range map (see the module docstring)."""
    r = np.asarray(range_m, np.float32)
    shown = np.isfinite(r) & (r > 0)
    filled = np.zeros_like(shown)
    if flags is not None:
        f = np.asarray(flags)
        shown &= (f & (VALID | FILLED)) != 0
        filled = shown & ((f & VALID) == 0)
    img = inverse_range_colours(r, shown, near_m, far_m)
    img[filled] //= 2
    return img


class FoxgloveConverter:
    """Decoded eonav messages -> Foxglove messages. Keeps the latest attitude and position of the nav stream (a
    nav_state may carry only one of them) so every pose it emits is whole."""

    def __init__(self, image_format: str = "jpeg", jpeg_quality: int = 90, near_m: float = 5.0,
                 far_m: float = 150.0, max_points: int = DEFAULT_MAX_POINTS):
        from eonav import InputError
        if image_format not in IMAGE_FORMATS:
            raise InputError(f"image format {image_format!r}: expected one of {IMAGE_FORMATS}")
        if not 0 < near_m < far_m:
            raise InputError(f"range colour scale {near_m}..{far_m} m: expected 0 < near < far")
        if max_points < 1:
            raise InputError(f"max points {max_points}: expected >= 1")
        self.image_format, self.jpeg_quality = image_format, int(jpeg_quality)
        self.near_m, self.far_m, self.max_points = near_m, far_m, int(max_points)
        self._position = None
        self._q = None

    def convert(self, msg: dict) -> list:
        fn = getattr(self, f"_{msg['kind']}", None)
        return fn(msg) if fn is not None else []

    # ---- images -----------------------------------------------------------------------------------
    def image(self, stamp_us: int, frame_id: str, img: np.ndarray, encoding: str):
        """RawImage of a mono8 / bgr8 array, or CompressedImage when the converter compresses."""
        img = np.ascontiguousarray(img)
        if self.image_format == "raw":
            return fm.RawImage(timestamp=timestamp(stamp_us), frame_id=frame_id, width=img.shape[1],
                               height=img.shape[0], encoding=encoding, step=img.strides[0], data=img.tobytes())
        import cv2
        params = [cv2.IMWRITE_JPEG_QUALITY, self.jpeg_quality] if self.image_format == "jpeg" else []
        ok, buf = cv2.imencode(f".{self.image_format}", img, params)
        if not ok:
            raise ValueError(f"cv2.imencode {self.image_format} failed for a {img.shape} {img.dtype} image")
        return fm.CompressedImage(timestamp=timestamp(stamp_us), frame_id=frame_id, data=buf.tobytes(),
                                  format=self.image_format)

    def _frame(self, m: dict) -> list:
        cid = m["camera_id"]
        img = np.asarray(m["image"])
        enc = m["encoding"] if m["encoding"] in ("mono8", "bgr8") else ("bgr8" if img.ndim == 3 else "mono8")
        if img.dtype != np.uint8:
            return []
        return [(f"/camera/{cid}/image", self.image(m["stamp_us"], optical_frame(cid), img, enc))]

    # ---- geometry ---------------------------------------------------------------------------------
    def _camera_transforms(self, stamp_us: int, cid: str, cam: dict) -> list:
        T1 = T_cam_body_from_eps(np.deg2rad(np.asarray(cam.get("eps_deg", [0, 0, 0]), float)))
        return [("/tf", transform(stamp_us, BODY, cam_frame(cid), cam.get("l_m", [0, 0, 0]),
                                  quat_wxyz_from_rotation(T1.T))),
                ("/tf", transform(stamp_us, cam_frame(cid), optical_frame(cid), [0, 0, 0],
                                  quat_wxyz_from_rotation(T_PAPERCAM_OPTICAL)))]

    def _posed_frame(self, m: dict) -> list:
        cid, cam = m["camera_id"], m["camera"]
        K = [cam["fx"], 0.0, cam["cx"], 0.0, cam["fy"], cam["cy"], 0.0, 0.0, 1.0]
        P = [cam["fx"], 0.0, cam["cx"], 0.0, 0.0, cam["fy"], cam["cy"], 0.0, 0.0, 0.0, 1.0, 0.0]
        calib = fm.CameraCalibration(timestamp=timestamp(m["stamp_us"]), frame_id=optical_frame(cid),
                                     width=int(cam["width"]), height=int(cam["height"]), distortion_model="plumb_bob",
                                     D=[0.0] * 5, K=[float(x) for x in K], R=[1.0, 0, 0, 0, 1.0, 0, 0, 0, 1.0],
                                     P=[float(x) for x in P])
        return [(f"/camera/{cid}/calibration", calib), *self._camera_transforms(m["stamp_us"], cid, cam)]

    def _nav_state(self, m: dict) -> list:
        p, q = np.asarray(m["position_ned_m"], float), np.asarray(m["q_wxyz"], float)
        if np.all(np.isfinite(p)):
            self._position = p
        if np.all(np.isfinite(q)) and abs(np.linalg.norm(q) - 1.0) < 1e-3:
            self._q = q
        if self._position is None or self._q is None:
            return []
        st = m["stamp_us"]
        pose = fm.PoseInFrame(timestamp=timestamp(st), frame_id=WORLD,
                              pose=fm.Pose(position=vector3(self._position), orientation=quaternion(self._q)))
        return [("/pose", pose), ("/tf", transform(st, WORLD, BODY, self._position, self._q))]

    # ---- range maps -------------------------------------------------------------------------------
    def _range_map(self, m: dict) -> list:
        cid, cam, st = m["camera_id"], m["camera"], m["stamp_us"]
        pic = range_colours(m["range_m"], m["flags"], self.near_m, self.far_m)
        pts = range_points(m["range_m"], m["flags"], cam, self.max_points)
        cloud = fm.PointCloud(timestamp=timestamp(st), frame_id=cam_frame(cid),
                              pose=fm.Pose(position=vector3([0, 0, 0]), orientation=quaternion([1, 0, 0, 0])),
                              point_stride=16, fields=POINT_FIELDS, data=pts.tobytes())
        return [(f"/range/{cid}/image", self.image(st, optical_frame(cid), pic, "bgr8")),
                (f"/range/{cid}/points", cloud), *self._camera_transforms(st, cid, cam)]

    # ---- obstacles --------------------------------------------------------------------------------
    def _obstacle_list(self, m: dict) -> list:
        st = m["stamp_us"]
        ents = []
        for o in m["obstacles"]:
            try:
                pos = [float(x) for x in o["position_ned_m"]]
                size = [max(0.3, float(x)) for x in o["extent_ned_m"]]
                d = float(o["distance_m"])
            except (KeyError, TypeError, ValueError, IndexError):
                continue
            if not (all(map(math.isfinite, pos + size)) and math.isfinite(d)):
                continue
            near = min(1.0, max(0.0, (d - self.near_m) / (self.far_m - self.near_m)))
            colour = fm.Color(r=1.0, g=near, b=0.0, a=0.6)          # red when near, yellow when far
            centre = fm.Pose(position=vector3(pos), orientation=quaternion([1, 0, 0, 0]))
            label = fm.Pose(position=vector3([pos[0], pos[1], pos[2] - size[2] / 2 - 1.0]),
                            orientation=quaternion([1, 0, 0, 0]))
            ents.append(fm.SceneEntity(
                timestamp=timestamp(st), frame_id=WORLD, id=f"obstacle/{o.get('id', len(ents))}",
                cubes=[fm.CubePrimitive(pose=centre, size=vector3(size), color=colour)],
                texts=[fm.TextPrimitive(pose=label, billboard=True, font_size=14.0, scale_invariant=True,
                                        color=fm.Color(r=1.0, g=1.0, b=1.0, a=1.0),
                                        text=f"#{o.get('id', '?')} {d:.1f} m")],
                metadata=[fm.KeyValuePair(key="distance_m", value=f"{d:.3f}"),
                          fm.KeyValuePair(key="bearing_deg", value=f"{float(o.get('bearing_deg', math.nan)):.2f}")]))
        upd = fm.SceneUpdate(deletions=[fm.SceneEntityDeletion(timestamp=timestamp(st),
                                                               type=fm.SceneEntityDeletionType.All, id="")],
                             entities=ents)
        return [("/obstacles", upd)]
