"""Helpers shared by the dense method and the flow baseline: pyramid-level geometry, the exact epipolar map
and its derivative in inverse range, the final classification of per-pixel estimates into a RangeResult, and the
loading of the numba kernels.

Pyramid convention: ``cv2.pyrDown`` puts level-L pixel x at level-0 pixel 2^L x (kernel centred on the even
pixels), so the level-L intrinsics are simply f / 2^L and c / 2^L; inverse range rho = 1/x_c is the same
at every level (it is a property of the scene point, not of the image resolution).
"""
from __future__ import annotations

import importlib
from dataclasses import dataclass, replace
from functools import lru_cache

import cv2
import numpy as np

from eonav.geometry.camera import Camera, PairGeometry, View, pair_geometry
from eonav.ranging.rangemap import (AT_INFINITY, ILL_CONDITIONED, LOW_TEXTURE, OUT_OF_VIEW, TRUNCATION, VALID,
                        RangeResult)

F32 = np.float32


def level_camera(cam: Camera, level: int, shape) -> Camera:
    """The camera seen by pyramid level ``level`` (pyrDown alignment: u_L = u / 2^L), image ``shape`` (h, w)."""
    s = 0.5 ** level
    return replace(cam, width=int(shape[1]), height=int(shape[0]), fx=cam.fx * s, fy=cam.fy * s,
                   cx=cam.cx * s, cy=cam.cy * s)


def pyramid(img: np.ndarray, n_levels: int) -> list:
    """Gaussian pyramid [level 0, level 1, ...] of a float32 image (pyrDown alignment)."""
    out = [img]
    for _ in range(1, n_levels):
        out.append(cv2.pyrDown(out[-1]))
    return out


def pyr_up_to(field: np.ndarray, shape) -> np.ndarray:
    """Upsample a per-pixel field one pyramid level (pyrUp alignment, consistent with pyrDown) to ``shape``."""
    h, w = field.shape
    up = cv2.pyrUp(field, dstsize=(2 * w, 2 * h))
    return np.ascontiguousarray(up[:shape[0], :shape[1]])


@dataclass
class EpipolarMap:
    """Exact map of pixels of a (one pyramid level) into image b as a function of inverse range rho:

        u_b = cx_b + fx_b (A1 + B1 rho) / den,   v_b = cy_b + fy_b (A2 + B2 rho) / den,   den = A0 + B0 rho

    (general two-camera form of eqs. 25-26), and its derivative d(u_b, v_b)/d rho = (C1, C2) / den^2 with
    C1 = fx_b (B1 A0 - B0 A1), C2 = fy_b (B2 A0 - B0 A2) (the rational map's analytic derivative).
    """
    A0: np.ndarray
    A1: np.ndarray
    A2: np.ndarray
    B: np.ndarray
    C1: np.ndarray
    C2: np.ndarray
    cam_b: Camera
    rho_cap: np.ndarray      # largest rho keeping den >= den_min (inf where B0 >= 0)

    @classmethod
    def build(cls, geo: PairGeometry, level: int, shape_a, shape_b, den_min: float = 0.05) -> "EpipolarMap":
        ca = level_camera(geo.cam_a, level, shape_a)
        cb = level_camera(geo.cam_b, level, shape_b)
        # A = R m with m = [1, x_p/fx, y_p/fy] (as PairGeometry.ray_terms), by broadcasting row/column terms
        m1 = ((np.arange(ca.width, dtype=np.float64) - ca.cx) / ca.fx)[None, :]
        m2 = ((np.arange(ca.height, dtype=np.float64) - ca.cy) / ca.fy)[:, None]
        R = np.asarray(geo.R_ba, float)
        A0, A1, A2 = [np.add((R[i, 0] + R[i, 1] * m1).astype(F32), (R[i, 2] * m2).astype(F32))
                      for i in range(3)]
        B = np.asarray(geo.t_ba_m, float).astype(F32)
        C1 = (F32(cb.fx) * (B[1] * A0 - B[0] * A1)).astype(F32)
        C2 = (F32(cb.fy) * (B[2] * A0 - B[0] * A2)).astype(F32)
        if B[0] < 0:
            rho_cap = ((A0 - F32(den_min)) / (-B[0])).astype(F32)
            rho_cap = np.maximum(rho_cap, F32(0))
        else:
            rho_cap = np.full(A0.shape, np.inf, F32)
        return cls(A0, A1, A2, B, C1, C2, cb, rho_cap)

    def __call__(self, rho):
        """(u_b, v_b, inv_den) at inverse range rho (array or scalar)."""
        B = self.B
        inv = 1.0 / (self.A0 + B[0] * rho)
        ub = (self.A1 + B[1] * rho) * inv
        ub *= F32(self.cam_b.fx)
        ub += F32(self.cam_b.cx)
        vb = (self.A2 + B[2] * rho) * inv
        vb *= F32(self.cam_b.fy)
        vb += F32(self.cam_b.cy)
        return ub.astype(F32, copy=False), vb.astype(F32, copy=False), inv.astype(F32, copy=False)

    def sensitivity(self, inv_den):
        """|d(u_b, v_b)/d rho| in pixels per (1/m) at the given 1/den."""
        return np.sqrt(self.C1 * self.C1 + self.C2 * self.C2) * (inv_den * inv_den)


def no_motion_result(shape, method: str, reason: str) -> RangeResult:
    """All NaN, nothing VALID: the pair has no parallax to measure range with."""
    h, w = shape
    return RangeResult(range_m=np.full((h, w), np.nan, F32), confidence=np.zeros((h, w), F32), method=method,
                       inv_range_per_m=np.full((h, w), np.nan, F32),
                       inv_range_std_per_m=np.full((h, w), np.inf, F32),
                       flags=np.full((h, w), ILL_CONDITIONED, np.uint8), info={"no_parallax": reason})


def classify_into(rho, std, flags, rng, conf, *, rho_far: float, max_rel_std: float, work=None):
    """The per-pixel rules of ``classify`` in place, on any block of pixels (whole image or a strip):
    ``flags`` (uint8, with the method's bad bits already set) gains ILL_CONDITIONED / AT_INFINITY / VALID,
    ``rng`` and ``conf`` (float32, same shape) are written. Returns (n_valid, n_at_infinity).
    Full-array arithmetic only (no boolean indexing, masked ufuncs or masked copies: ~5x faster).
    ``work``: optional three float32 scratch arrays of the block's shape (e.g. a caller's reused work
    buffers; same result): fresh float temporaries page-fault when the allocator has trimmed them."""
    w0, w1, w2 = work if work is not None else (np.empty(rho.shape, F32) for _ in range(3))
    with np.errstate(divide="ignore", invalid="ignore", over="ignore"):
        two = np.multiply(std, F32(2.0), out=w0)
        inf_ok = two < F32(rho_far)
        near0 = rho < two
        inf_ok &= near0                                   # rho within 2 sigma of 0, and sigma tight
        rel = np.divide(std, rho, out=two)
        good = rel <= F32(max_rel_std)                    # relative std small enough (rho > 0 not near 0)
        good &= ~near0
        good |= inf_ok
        good &= np.isfinite(rho)
        good &= np.isfinite(std)                          # ILL_CONDITIONED = not good (NaN/inf included)
        flags |= np.subtract(np.uint8(ILL_CONDITIONED), good.view(np.uint8) * np.uint8(ILL_CONDITIONED))
        ok = (flags & np.uint8(OUT_OF_VIEW | LOW_TEXTURE | ILL_CONDITIONED | TRUNCATION)) == 0
        at_inf = ok & inf_ok
        val = inf_ok
        np.logical_not(inf_ok, out=val)
        val &= ok
        flags |= at_inf.view(np.uint8) * np.uint8(AT_INFINITY | VALID)
        flags |= val.view(np.uint8) * np.uint8(VALID)
        # branch-free outputs (masked copies cost ~20x an arithmetic pass on fragmented masks):
        # range = ok / |rho * val|: 1/rho where VALID, +inf at infinity (1/0), NaN elsewhere (0/0);
        # confidence = max((rho * val + rho_far * at_inf) / std, 0): 0 elsewhere (0/std, or NaN -> 0)
        valf, inff = w1, w2
        np.copyto(valf, val)
        np.copyto(inff, at_inf)
        den = np.multiply(rho, valf, out=w0)
        np.abs(den, out=den)
        np.divide(np.add(valf, inff, out=rng), den, out=rng)
        num = np.multiply(rho, valf, out=valf)
        num += np.multiply(inff, F32(rho_far), out=inff)
        np.divide(num, std, out=conf)
        np.fmax(conf, F32(0), out=conf)
        nv, ni = int(np.count_nonzero(val)), int(np.count_nonzero(at_inf))
    return nv, ni


def classify(rho, std, *, bad_flags, method: str, rho_far: float, max_rel_std: float, info: dict,
             extra_flags=None) -> RangeResult:
    """Turn per-pixel inverse range and its 1-sigma into a RangeResult.

    - pixels with any bit of ``bad_flags`` set (out of view, occluded, low texture, ill-conditioned,
      truncation) get no estimate (NaN, confidence 0);
    - AT_INFINITY (range +inf, VALID): rho within 2 sigma of 0 and 2 sigma < rho_far (the measurement is
      precise enough to say "farther than 1/rho_far");
    - rho within 2 sigma of 0 but sigma too large (near the focus of expansion): ILL_CONDITIONED, NaN;
    - relative std sigma/rho > max_rel_std: ILL_CONDITIONED, NaN;
    - otherwise VALID, range 1/rho, confidence rho/sigma (= 1 / relative std of the range).
    Confidence of AT_INFINITY pixels is rho_far / sigma (how far past the "far" threshold the bound lies).
    """
    flags = bad_flags.astype(np.uint8, copy=True)
    if extra_flags is not None:
        flags |= extra_flags
    rho = np.asarray(rho, F32)
    std = np.asarray(std, F32)
    rng = np.empty(rho.shape, F32)
    conf = np.empty(rho.shape, F32)
    n_val, n_inf = classify_into(rho, std, flags, rng, conf, rho_far=rho_far, max_rel_std=max_rel_std)
    return make_result(rho, std, flags, rng, conf, method, n_val, n_inf, info)


def make_result(rho, std, flags, rng, conf, method: str, n_val: int, n_inf: int, info: dict) -> RangeResult:
    info = dict(info)
    n = max(int(rho.size), 1)
    info["valid_fraction"] = float((n_val + n_inf) / n)
    info["at_infinity_fraction"] = float(n_inf / n)
    return RangeResult(range_m=rng, confidence=conf, method=method, inv_range_per_m=rho, inv_range_std_per_m=std,
                       flags=flags, info=info)


def far_inverse_range(geo: PairGeometry, far_parallax_px: float) -> float:
    """Inverse range below which the pair's parallax is under ``far_parallax_px`` even for a point seen
    broadside to the baseline: rho_far = p / (f_max * |t|). AT_INFINITY needs 2 sigma below this."""
    f = max(geo.cam_a.fx, geo.cam_a.fy, geo.cam_b.fx, geo.cam_b.fy)
    b = geo.baseline_m
    return float(far_parallax_px / (f * b)) if b > 0 else 0.0


def to_u8(img: np.ndarray) -> np.ndarray:
    return np.clip(np.rint(img), 0, 255).astype(np.uint8)


def rectified_stereo_baseline(geo: PairGeometry, tol: float = 1e-6):
    """If (a, b) is a rectified horizontal stereo pair (same intrinsics, R = I, t along Yc only, b to the
    right of a), return (f_px, baseline_m); else None. Then disparity d = u_a - u_b = f b rho."""
    ca, cb = geo.cam_a, geo.cam_b
    if (ca.width, ca.height, ca.fx, ca.fy, ca.cx, ca.cy) != (cb.width, cb.height, cb.fx, cb.fy, cb.cx, cb.cy):
        return None
    if np.abs(geo.R_ba - np.eye(3)).max() > tol:
        return None
    t = geo.t_ba_m
    if abs(t[0]) > tol * max(1.0, abs(t[1])) or abs(t[2]) > tol * max(1.0, abs(t[1])) or not t[1] < 0:
        return None
    return float(ca.fx), float(-t[1])


@lru_cache(maxsize=None)
def numba_kernels(name: str):
    """The numba kernel module ``eonav.ranging.methods.<name>``: the methods' only implementation of their per-pixel
    work. numba is a dependency of eonav; without it, an ImportError that says so (not a silent slow path)."""
    try:
        return importlib.import_module(f"{__package__}.{name}")
    except ModuleNotFoundError as e:
        if e.name not in ("numba", "llvmlite"):
            raise
        raise ImportError(f"eonav.ranging.methods.{name} needs numba, a dependency of eonav (pip install 'numba>=0.59'): "
                          f"{e}") from e


__all__ = ["EpipolarMap", "level_camera", "pyramid", "pyr_up_to", "classify", "classify_into", "make_result", "no_motion_result",
           "far_inverse_range", "to_u8", "rectified_stereo_baseline", "pair_geometry", "View",
           "numba_kernels"]
