"""Ray-traced rendering of a ``Scene`` by one ``Camera`` at one ``VehicleState``, with ground truth.

Rays: for pixel (u, v) the camera-frame ray is m = [1, (u - cx)/fx, (v - cy)/fy] (the inverse of eqs. 8-9),
in NED d = T2^T T1^T m from the lens centre o = x_v + T2^T l (eq. 33). Because the first component of m is 1,
the ray parameter of a hit IS its range x_c along the optical axis.

Anti-aliasing: ``supersample``^2 rays per pixel on a regular sub-grid, averaged (box filter), plus texture
frequency clamping (see ``texture``). Ground truth (range, object id) is traced at the pixel-centre ray.
Image: float32 grey 0..255, Gaussian sensor noise (``noise_sigma`` grey levels, seeded), 8-bit quantised.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from eonav import InputError
from eonav.geometry.camera import Camera, VehicleState
from eonav.sim.scene import FIRST_BOX_ID, GROUND_ID, SKY_ID, Scene
from eonav.sim.texture import fractal_noise

GROUND_LIGHT = 1.0
AMBIENT = 0.45                       # box faces: grey = albedo * (AMBIENT + (1 - AMBIENT) * max(0, n . sun))
_BOX_FACE_OFFSET_M = 173.0           # texture offset between faces of one box (decorrelates them)


@dataclass
class Render:
    """A rendered frame: ``image`` float32 H x W (0..255 grey), ``range_m`` float32 H x W ground-truth x_c at
    the pixel centre (+inf for sky), ``object_id`` int16 H x W (0 sky, 1 ground, 2.. boxes)."""
    image: np.ndarray
    range_m: np.ndarray
    object_id: np.ndarray


def camera_rays_ned(camera: Camera, state: VehicleState):
    """(R_ned_cam, origin_ned_m): NED ray of camera-frame vector m is R_ned_cam @ m, from origin_ned_m (eq. 33)."""
    T1, T2 = camera.T_cam_body, state.T_body_ned
    R_ned_cam = T2.T @ T1.T
    origin = state.position_ned_m + T2.T @ camera.l_body_m
    return R_ned_cam, origin


def project_ned(camera: Camera, state: VehicleState, points_ned_m: np.ndarray):
    """The renderer's own projection of NED points: (u, v, x_c) with u = cx + fx y_c/x_c, v = cy + fy z_c/x_c."""
    R, o = camera_rays_ned(camera, state)
    pc = (np.asarray(points_ned_m, float) - o) @ R        # R^T (p - o), row-vector form
    u = camera.cx + camera.fx * pc[..., 1] / pc[..., 0]
    v = camera.cy + camera.fy * pc[..., 2] / pc[..., 0]
    return u, v, pc[..., 0]


def _trace(scene: Scene, R: np.ndarray, o: np.ndarray, xn: np.ndarray, yn: np.ndarray):
    """Nearest hit along rays m = [1, xn, yn] (1-D float64 arrays). Returns t (= x_c, inf for sky),
    object id (int16), ray directions d (3, N) and, for box hits, the box face axis (int8, -1 elsewhere)."""
    d = R[:, [0]] + R[:, [1]] * xn + R[:, [2]] * yn
    n = xn.size
    t = np.full(n, np.inf)
    oid = np.zeros(n, np.int16)
    with np.errstate(divide="ignore", invalid="ignore"):
        tg = np.where(d[2] > 1e-12, -o[2] / d[2], np.inf)          # ground z = 0, camera above it
    ground = np.isfinite(tg)
    t[ground] = tg[ground]
    oid[ground] = GROUND_ID
    face = np.full(n, -1, np.int8)
    d_norm2 = np.einsum("ij,ij->j", d, d)
    for i, box in enumerate(scene.boxes):
        # bounding-sphere cull: only rays passing within the box's circumradius are slab-tested
        w = np.asarray(box.center_ned_m) - o
        radius = float(np.linalg.norm(box.half_m))
        along = w @ d                                              # (c - o) . d
        miss = (np.dot(w, w) - along * along / d_norm2) > radius * radius
        if np.dot(w, w) > radius * radius:
            miss |= along <= 0
        cand = np.flatnonzero(~miss)
        if cand.size == 0:
            continue
        Rb = box.R_ned_local
        ol = Rb.T @ (o - np.asarray(box.center_ned_m))
        dl = Rb.T @ d[:, cand]
        h = box.half_m
        with np.errstate(divide="ignore", invalid="ignore"):
            inv = 1.0 / np.where(np.abs(dl) < 1e-15, 1e-15, dl)
            ta = (-h[:, None] - ol[:, None]) * inv
            tb = (h[:, None] - ol[:, None]) * inv
        tmin = np.minimum(ta, tb)
        tmax = np.maximum(ta, tb)
        tnear = tmin.max(axis=0)
        tfar = tmax.min(axis=0)
        hit_c = (tnear <= tfar) & (tnear > 0) & (tnear < t[cand])
        if not hit_c.any():
            continue
        hit = cand[hit_c]
        t[hit] = tnear[hit_c]
        oid[hit] = FIRST_BOX_ID + i
        face[hit] = np.argmax(tmin[:, hit_c], axis=0)
    return t, oid, d, face


def _footprint_m(t, d, n_ned, a_u, a_v):
    """Surface metres per pixel at a hit (plane normal n_ned, rows (3, N) or (3,)): the pixel Jacobian
    dP/du = t (a_u - d (n.a_u)/(n.d)) (and likewise v). Returns max(geometric mean, longest / 2)."""
    n_ned = n_ned if n_ned.ndim == 2 else n_ned[:, None]
    nd = np.sum(n_ned * d, axis=0)
    nd = np.where(np.abs(nd) < 1e-9, 1e-9, nd)
    nau = np.sum(n_ned * a_u[:, None], axis=0)
    nav = np.sum(n_ned * a_v[:, None], axis=0)
    ju = t * np.linalg.norm(a_u[:, None] - d * (nau / nd), axis=0)
    jv = t * np.linalg.norm(a_v[:, None] - d * (nav / nd), axis=0)
    fp = np.maximum(np.sqrt(ju * jv), 0.5 * np.maximum(ju, jv))
    return fp.astype(np.float32)


def _runway_grey(scene: Scene, north, east, fp):
    """Ground grey level (before haze) at NED points on the ground plane."""
    seed = scene.seed
    noise = fractal_noise(north, east, fp, seed)
    grey = (108.0 + 34.0 * noise).astype(np.float32)                    # grass
    rw = scene.runway
    if rw is None:
        return grey
    ae = np.abs(east)
    on = (ae <= rw.half_width_m) & (north >= rw.north0_m) & (north <= rw.north1_m)
    if not on.any():
        return grey
    n_on, ae_on = north[on], ae[on]
    asphalt = 78.0 + 16.0 * noise[on]
    rel = n_on - rw.north0_m
    edge = ae_on >= rw.half_width_m - 0.9
    centre = (ae_on <= 0.45) & (np.mod(rel, 50.0) < 30.0) & (rel > 60.0)
    bars = (rel >= 6.0) & (rel <= 36.0) & (ae_on >= 3.0) & (ae_on <= rw.half_width_m - 3.0) \
        & (np.mod(ae_on - 3.0, 3.6) < 1.8)
    tdz = (np.mod(rel - 150.0, 150.0) < 22.5) & (rel >= 150.0) & (rel <= 610.0) \
        & (ae_on >= 4.0) & (ae_on <= 9.0) & (np.mod(ae_on - 4.0, 2.5) < 1.0)
    paint = edge | centre | bars | tdz
    asphalt = np.where(paint, 205.0 + 8.0 * noise[on], asphalt)
    grey[on] = asphalt
    return grey


def _sky_grey(scene: Scene, d):
    """Sky grey level for ray directions d (3, N): gradient by elevation plus faint clouds (function of
    direction only: the sky is at infinity)."""
    nrm = np.linalg.norm(d, axis=0)
    sin_el = np.clip(-d[2] / nrm, -1.0, 1.0)
    el = np.arcsin(sin_el)
    az = np.arctan2(d[1], d[0])
    base = scene.sky_horizon_grey + (scene.sky_zenith_grey - scene.sky_horizon_grey) * np.sqrt(np.maximum(sin_el, 0))
    # clouds: texture on the (azimuth, elevation) sphere, 1 rad = 1000 "m", large scales only
    fp = np.full(el.shape, 1000.0 / 500.0, np.float32)
    clouds = fractal_noise(az * 1000.0, el * 1000.0, fp, scene.seed + 7, min_lambda_m=80.0, max_lambda_m=700.0)
    return (base + 6.0 * clouds * np.clip(el * 10.0, 0.0, 1.0)).astype(np.float32)


def _shade(scene: Scene, camera: Camera, R, o, t, oid, d, face):
    """Grey level of every ray (1-D float32)."""
    grey = np.empty(t.shape, np.float32)
    a_u = R[:, 1] / camera.fx
    a_v = R[:, 2] / camera.fy
    sun = np.asarray(scene.sun_ned)

    sky = oid == SKY_ID
    if sky.any():
        grey[sky] = _sky_grey(scene, d[:, sky])

    g = np.flatnonzero(oid == GROUND_ID)
    if g.size:
        tg, dg = t[g], d[:, g]
        p = o[:, None] + dg * tg
        fp = _footprint_m(tg, dg, np.array([0.0, 0.0, -1.0]), a_u, a_v)
        grey[g] = GROUND_LIGHT * _runway_grey(scene, p[0], p[1], fp)

    for i, box in enumerate(scene.boxes):
        b = np.flatnonzero(oid == FIRST_BOX_ID + i)
        if b.size == 0:
            continue
        tb, db, ax = t[b], d[:, b], face[b].astype(np.int64)
        Rb = box.R_ned_local
        dl = Rb.T @ db
        pl = Rb.T @ (o[:, None] + db * tb - np.asarray(box.center_ned_m)[:, None])
        sign = -np.sign(dl[ax, np.arange(b.size)])               # outward normal along the face axis
        n_local = np.zeros((3, b.size))
        n_local[ax, np.arange(b.size)] = sign
        n_ned = Rb @ n_local
        fp = _footprint_m(tb, db, n_ned, a_u, a_v)
        # face coordinates: the two local axes in the face plane, plus a per-face offset
        s_idx = np.where(ax == 0, 1, 0)
        t_idx = np.where(ax == 2, 1, 2)
        cols = np.arange(b.size)
        face_id = ax * 2 + (sign > 0)
        fs = pl[s_idx, cols] + _BOX_FACE_OFFSET_M * face_id + 31.0 * i
        ft = pl[t_idx, cols] - _BOX_FACE_OFFSET_M * face_id + 57.0 * i
        noise = fractal_noise(fs, ft, fp, scene.seed + 1000 + i)
        light = AMBIENT + (1.0 - AMBIENT) * np.maximum(0.0, sun @ n_ned)
        grey[b] = (light * (box.albedo + box.contrast * noise)).astype(np.float32)

    solid = np.flatnonzero(oid != SKY_ID)
    if solid.size:
        dist = t[solid] * np.linalg.norm(d[:, solid], axis=0)
        tau = np.exp(-dist / scene.visibility_m).astype(np.float32)
        grey[solid] = grey[solid] * tau + np.float32(scene.sky_horizon_grey) * (1 - tau)
    return grey


def _check(scene, camera, state, supersample, noise_sigma):
    if not isinstance(scene, Scene):
        raise InputError(f"render: scene must be an eonav.sim.scene.Scene, got {type(scene).__name__}")
    if not isinstance(camera, Camera) or not isinstance(state, VehicleState):
        raise InputError("render: camera must be a Camera and state a VehicleState")
    if int(supersample) != supersample or supersample < 1:
        raise InputError(f"render: supersample must be a whole number >= 1, got {supersample!r}")
    if not (np.isfinite(noise_sigma) and noise_sigma >= 0):
        raise InputError(f"render: noise_sigma must be >= 0 grey levels, got {noise_sigma!r}")
    _, o = camera_rays_ned(camera, state)
    if o[2] >= 0:
        raise InputError(f"render: the lens centre must be above the ground (NED z < 0), got z = {o[2]:.3f} m")


def render(scene: Scene, camera: Camera, state: VehicleState, *, supersample: int = 3, noise_sigma: float = 1.0,
           seed: int = 0, quantize: bool = True) -> Render:
    """Render ``scene`` seen by ``camera`` at ``state``; see the module docstring."""
    _check(scene, camera, state, supersample, noise_sigma)
    S = int(supersample)
    R, o = camera_rays_ned(camera, state)
    H, W = camera.height, camera.width
    v, u = np.mgrid[0:H, 0:W]
    xn0 = ((u - camera.cx) / camera.fx).ravel()
    yn0 = ((v - camera.cy) / camera.fy).ravel()
    offsets = (np.arange(S) + 0.5) / S - 0.5
    acc = np.zeros(H * W, np.float32)
    centre = None
    for dv in offsets:
        for du in offsets:
            xn = xn0 + du / camera.fx
            yn = yn0 + dv / camera.fy
            t, oid, d, face = _trace(scene, R, o, xn, yn)
            acc += _shade(scene, camera, R, o, t, oid, d, face)
            if du == 0.0 and dv == 0.0:
                centre = (t, oid)
    if centre is None:                                    # even supersample: trace the centre ray for truth
        centre = _trace(scene, R, o, xn0, yn0)[:2]
    image = (acc / np.float32(S * S)).reshape(H, W)
    if noise_sigma > 0:
        rng = np.random.default_rng(seed)
        image = image + rng.normal(0.0, noise_sigma, image.shape).astype(np.float32)
    image = np.clip(image, 0.0, 255.0)
    if quantize:
        image = np.round(image)
    return Render(image.astype(np.float32), centre[0].reshape(H, W).astype(np.float32),
                  centre[1].reshape(H, W).astype(np.int16))
