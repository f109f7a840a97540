"""Predict: carry an inverse-range state into a new frame with the known relative pose.

Every occupied cell's point (pixel plus its sub-pixel offset, at inverse range rho) is moved into the new camera
frame exactly: with m = [1, x_p/fx, y_p/fy] of the point in the old frame and X_new = R X_old + t
(``eonav.geometry.frames.relative_pose``, docs/conventions.md "Two views"), X_new / x_c,old = R m + t rho, so
(eqs. 24-26 in the general form of ``PairGeometry.map_to_b``)

    den = (R m)_0 + t_0 rho,   rho_new = rho / den,
    u_new = cx + fx ((R m)_1 + t_1 rho) / den,   v_new = cy + fy ((R m)_2 + t_2 rho) / den.

The point lands on the nearest pixel and keeps the remainder as its new offset. Where several points land on one
pixel the nearest (largest rho_new) wins: a z-buffer, so a foreground object moving over the background hides it.
Pixels no point reaches start empty (fresh), except one-pixel cracks of a stretching surface whose two opposite
neighbours agree within ``crack_k`` sigma: they take the neighbours' mean.

Variance: the transfer's Jacobian, d rho_new / d rho = (R m)_0 / den^2, plus process noise that grows with the time
and the distance since the last frame (``ProcessNoise``): var_new = J^2 var + rho^2 (q_s^2 dt + q_m^2 |t|) +
q_abs^2 dt. The Beta evidence and the measurement count travel with the point.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from eonav import InputError
from eonav.geometry.camera import Camera, VehicleState
from eonav.geometry.frames import relative_pose
from eonav.fusion.state import F32, InverseRangeState, optional_kernels


@dataclass(frozen=True)
class ProcessNoise:
    """Growth of the variance from one frame to the next: relative sigma of rho per sqrt(second) (``rel_per_sqrt_s``)
    and per sqrt(metre) of camera translation (``rel_per_sqrt_m``: pose errors grow with motion), absolute sigma
    (1/m) per sqrt(second) (``abs_per_sqrt_s``: lets a point at infinity drift into range again)."""
    rel_per_sqrt_s: float = 0.02
    rel_per_sqrt_m: float = 0.01
    abs_per_sqrt_s: float = 1e-5

    def __post_init__(self):
        for name in ("rel_per_sqrt_s", "rel_per_sqrt_m", "abs_per_sqrt_s"):
            v = getattr(self, name)
            if not (np.isfinite(v) and v >= 0):
                raise InputError(f"process noise: {name} must be a finite number >= 0, got {v!r}")


def transfer(state: InverseRangeState, camera: Camera, pose: VehicleState):
    """Where each occupied cell's point goes in (camera, pose): (flat source index, u_new, v_new, rho_new,
    d rho_new / d rho, baseline |t| in metres), only for points in front of the new camera."""
    c0, p0 = state.camera, state.pose
    R, t = relative_pose(c0.T_cam_body, p0.T_body_ned, p0.position_ned_m, c0.l_body_m,
                         camera.T_cam_body, pose.T_body_ned, pose.position_ned_m, camera.l_body_m)
    idx = np.flatnonzero(np.isfinite(state.rho))
    w = state.shape[1]
    rho = state.rho.ravel()[idx]
    u = (idx % w).astype(F32) + state.du.ravel()[idx]
    v = (idx // w).astype(F32) + state.dv.ravel()[idx]
    m1 = (u - F32(c0.cx)) / F32(c0.fx)
    m2 = (v - F32(c0.cy)) / F32(c0.fy)
    R = R.astype(F32)
    t32 = t.astype(F32)
    A0 = R[0, 0] + R[0, 1] * m1 + R[0, 2] * m2
    A1 = R[1, 0] + R[1, 1] * m1 + R[1, 2] * m2
    A2 = R[2, 0] + R[2, 1] * m1 + R[2, 2] * m2
    den = A0 + t32[0] * rho
    front = (den > F32(1e-3)) & (A0 > F32(1e-3))
    idx, rho, den, A0, A1, A2 = idx[front], rho[front], den[front], A0[front], A1[front], A2[front]
    inv = F32(1.0) / den
    u_new = F32(camera.cx) + F32(camera.fx) * (A1 + t32[1] * rho) * inv
    v_new = F32(camera.cy) + F32(camera.fy) * (A2 + t32[2] * rho) * inv
    return idx, u_new, v_new, rho * inv, A0 * inv * inv, float(np.linalg.norm(t))


def predict(state: InverseRangeState, camera: Camera, pose: VehicleState, stamp_s: float,
            noise: ProcessNoise = ProcessNoise(), crack_k: float = 3.0,
            kernels: bool | None = None, out: InverseRangeState | None = None) -> InverseRangeState:
    """``state`` carried into the frame of ``camera`` at ``pose`` (time ``stamp_s``); see the module docstring.
    kernels: the numba pass (``_kernels.warp``, by ``predict_job``; None: when numba is installed; False: the numpy
    path, the reference). out: a state (not ``state``) whose arrays to overwrite (a stream reuses its previous
    state's: no fresh memory per frame); None: a new one."""
    K = optional_kernels() if kernels is None or kernels else None
    if kernels and K is None:
        raise ImportError("predict(kernels=True) needs numba")
    if K is not None:
        return predict_job(state, camera, pose, stamp_s, noise, crack_k, out)()
    out = _target(state, camera, pose, stamp_s, out)
    dt = float(stamp_s) - state.stamp_s
    out.clear()
    idx, u_new, v_new, rho_new, jac, baseline_m = transfer(state, camera, pose)
    ui = np.floor(u_new + F32(0.5))          # the nearest pixel (halves up: cheaper than rint in the kernel)
    vi = np.floor(v_new + F32(0.5))
    h, w = out.shape
    inside = (ui >= 0) & (ui <= w - 1) & (vi >= 0) & (vi <= h - 1)
    idx, ui, vi, u_new, v_new, rho_new, jac = (x[inside] for x in (idx, ui, vi, u_new, v_new, rho_new, jac))
    tgt = vi.astype(np.intp) * w + ui.astype(np.intp)
    # z-buffer: the largest rho_new (the nearest point) per target pixel; ties are the same point, any may win
    zbuf = np.full(h * w, -np.inf, F32)
    np.maximum.at(zbuf, tgt, rho_new)
    win = rho_new >= zbuf[tgt]
    src, tgt = idx[win], tgt[win]
    q = F32(noise.rel_per_sqrt_s ** 2 * dt + noise.rel_per_sqrt_m ** 2 * baseline_m)
    q_abs = F32(noise.abs_per_sqrt_s ** 2 * dt)
    r = rho_new[win]
    j = jac[win]
    for name in ("rho", "var", "a", "b", "n", "flags"):
        getattr(out, name).ravel()[tgt] = getattr(state, name).ravel()[src]
    out.rho.ravel()[tgt] = r
    out.var.ravel()[tgt] = state.var.ravel()[src] * j * j + q * r * r + q_abs
    out.du.ravel()[tgt] = u_new[win] - ui[win]
    out.dv.ravel()[tgt] = v_new[win] - vi[win]
    if crack_k > 0:
        close_cracks(out, crack_k)
    return out


def predict_job(state: InverseRangeState, camera: Camera, pose: VehicleState, stamp_s: float,
                noise: ProcessNoise = ProcessNoise(), crack_k: float = 3.0, out: InverseRangeState | None = None):
    """``predict`` with the numba passes in two steps: this call does the Python part (the relative pose, the
    kernels' arguments, the target state) and returns a function that runs the warp and the crack closing (GIL-free)
    and returns the predicted state. The runner's worker thread runs only that function
    (``FusionConfig.overlap_predict``): it needs the GIL just to start the kernels, not while the caller's
    measurement runs its own Python."""
    K = optional_kernels()
    if K is None:
        raise ImportError("predict_job needs numba")
    out = _target(state, camera, pose, stamp_s, out)
    if out.rho.size >= 2 ** 31:
        raise InputError(f"predict: a grid of {out.rho.size} cells is beyond the warp's int32 pixel index")
    dt = float(stamp_s) - state.stamp_s
    c0, p0 = state.camera, state.pose
    R, t = relative_pose(c0.T_cam_body, p0.T_body_ned, p0.position_ned_m, c0.l_body_m,
                         camera.T_cam_body, pose.T_body_ned, pose.position_ned_m, camera.l_body_m)
    q = F32(noise.rel_per_sqrt_s ** 2 * dt + noise.rel_per_sqrt_m ** 2 * float(np.linalg.norm(t)))
    arrays = (out.rho, out.var, out.a, out.b, out.n, out.du, out.dv, out.flags)
    warp_args = (state.rho, state.var, state.a, state.b, state.n, state.du, state.dv, state.flags,
                 R.astype(F32), t.astype(F32), _intrinsics(c0), _intrinsics(camera), q,
                 F32(noise.abs_per_sqrt_s ** 2 * dt)) + arrays
    k2 = F32(crack_k * crack_k)

    def run() -> InverseRangeState:
        K.warp(*warp_args)
        if crack_k > 0:
            K.close_cracks(*arrays, k2)
        return out
    return run


def _target(state, camera, pose, stamp_s, out):
    """The state predict writes into (``out`` if it fits: its arrays overwritten, else a new one), on the new frame
    (camera, pose, time) with ``state``'s far limit; a frame older than the state is refused."""
    dt = float(stamp_s) - state.stamp_s
    if not dt >= 0:
        raise InputError(f"predict: the new frame ({stamp_s:.6f} s) is older than the state ({state.stamp_s:.6f} s)")
    if (out is None or out is state or out.shape != (camera.height, camera.width)
            or not all(getattr(out, k).flags.c_contiguous for k in _FIELDS)):
        out = InverseRangeState.empty(camera, pose, stamp_s)
    else:
        out.camera, out.pose, out.stamp_s = camera, pose, float(stamp_s)
    out.rho_far = state.rho_far
    return out


_FIELDS = ("rho", "var", "a", "b", "n", "du", "dv", "flags")


def _intrinsics(cam: Camera) -> np.ndarray:
    return np.array([cam.fx, cam.fy, cam.cx, cam.cy], F32)


def close_cracks(state: InverseRangeState, k: float) -> int:
    """In place: every empty pixel whose left and right (or upper and lower) neighbours are occupied and agree
    within k sigma takes their mean (variance: the larger one plus the half difference squared; the weaker
    evidence; offset 0). Returns the number of pixels closed."""
    rho, var = state.rho, state.var
    empty = ~np.isfinite(rho)
    if not empty.any():
        return 0
    closed = 0
    for axis in (1, 0):
        lo = [slice(None)] * 2
        hi = [slice(None)] * 2
        mid = [slice(None)] * 2
        lo[axis], mid[axis], hi[axis] = slice(0, -2), slice(1, -1), slice(2, None)
        lo, mid, hi = tuple(lo), tuple(mid), tuple(hi)
        r0, r1, v0, v1 = rho[lo], rho[hi], var[lo], var[hi]
        with np.errstate(invalid="ignore"):
            d = r1 - r0
            ok = empty[mid] & (d * d <= F32(k * k) * (v0 + v1))      # NaN neighbours: False
        if not ok.any():
            continue
        ys, xs = np.nonzero(ok)
        ys, xs = ys + (1 if axis == 0 else 0), xs + (1 if axis == 1 else 0)
        oy, ox = (1, 0) if axis == 0 else (0, 1)
        ya, xa, yb, xb = ys - oy, xs - ox, ys + oy, xs + ox
        rho[ys, xs] = 0.5 * (rho[ya, xa] + rho[yb, xb])
        var[ys, xs] = np.maximum(var[ya, xa], var[yb, xb]) + 0.25 * (rho[yb, xb] - rho[ya, xa]) ** 2
        state.a[ys, xs] = np.minimum(state.a[ya, xa], state.a[yb, xb])
        state.b[ys, xs] = np.maximum(state.b[ya, xa], state.b[yb, xb])
        state.n[ys, xs] = np.minimum(state.n[ya, xa], state.n[yb, xb])
        state.flags[ys, xs] = state.flags[ya, xa] & state.flags[yb, xb]
        state.du[ys, xs] = 0.0
        state.dv[ys, xs] = 0.0
        empty[ys, xs] = False
        closed += len(ys)
    return closed
