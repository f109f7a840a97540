"""Left-right (forward-backward) consistency of a pair: the dense method run both ways, a -> b and b -> a, and the
pixels of a whose two estimates disagree flagged OCCLUDED.

One inverse range per window: where a window straddles a depth edge the dense method ranges the far side's pixels
next to the edge at the near side's range (the near object "fattens"), most of all where the far side is hidden in
image b (an occlusion). Those pixels match nothing in b, so the pair b -> a, ranging b's own pixels, does not
confirm them. The classic stereo check (OpenCV StereoSGBM's ``disp12MaxDiff``: a left pixel whose disparity, looked
up again in the right-to-left map at its match, does not come back within that many pixels) in the general
two-view form:

- pixel p of a at its inverse range rho_a lands in b at q = map(rho_a) (eqs. 25-26, ``EpipolarMap``), where the
  point's inverse range seen from b is rho_b' = rho_a / den with den = A0 + B0 rho_a (x_c,b / x_c,a, eq. 24), its
  sigma A0 / den^2 x sigma_a (the derivative of rho_a / den);
- the pair b -> a measured rho_b(q') with sigma_b(q') at the four pixels q' of b around q;
- p agrees with q' where |rho_b' - rho_b(q')| <= k sqrt(sigma_b'^2 + sigma_b(q')^2) + floor_px / S_ba(q'), S_ba
  the b -> a map's sensitivity |d(u_a, v_a)/d rho_b| (pixels per 1/m): within the two estimates' combined sigma
  or ``floor_px`` pixels of a (the classic check's pixel tolerance, which the sub-pixel interpolation at strong
  edges needs); p is inconsistent where it agrees with none of them that b measured. The four, not the nearest:
  a point on a depth edge lands between a near and a far pixel of b, and b's own edge pixel is often unmeasured.

Only pixels of a that carry a measurement (finite rho and sigma, not FILLED) are judged, and only against a VALID
pixel of b (not FILLED): where b has nothing to say, a keeps its estimate. An inconsistent pixel loses VALID (and
AT_INFINITY) and gets OUT_OF_VIEW | OCCLUDED, range NaN, confidence 0, its rho kept, as the dense method's own
occlusion test leaves it; a filter fusing measurements (``eonav.fusion.update.measured``) then skips it. The cost is
a second dense locate per pair.

The two-sided test flags a's pixels hidden in b even where a ranged them right (b sees the occluder in front). The
one-sided test (``farther``: p is contradicted only where b sees farther than rho_b' by more than the tolerance)
is the free-space argument of multi-view fusion: b looking through the point a claims means nothing is there, while
b seeing something nearer may just hide it. It judges an estimate a pair did not make, e.g. a fused state whose
cell still holds a moving object that has left it (``eonav.fusion.sequence``, ``stereo_free_space``).
"""
from __future__ import annotations

import math
import time
from dataclasses import dataclass, replace

import numpy as np

from eonav import InputError
from eonav.geometry.camera import PairGeometry, View, pair_geometry
from eonav.ranging import _consistency_kernels as _K
from eonav.ranging.rangemap import AT_INFINITY, OCCLUDED, OUT_OF_VIEW, VALID, RangeResult

F32 = np.float32


@dataclass(frozen=True)
class LRCheckConfig:
    """k: sigmas of the two estimates' combined 1-sigma they may differ by; floor_px: and pixels of image a
    (module docstring); farther: one-sided, the free-space test (module docstring)."""
    k: float = 3.0
    floor_px: float = 1.0
    farther: bool = False          # only b seeing farther than a's estimate contradicts it (free space, below)

    def __post_init__(self):
        for name in ("k", "floor_px"):
            v = getattr(self, name)
            if not (isinstance(v, (int, float)) and math.isfinite(v) and v >= 0):
                raise InputError(f"lr check: {name} must be a finite number >= 0, got {v!r}")


def _reverse(geo: PairGeometry) -> PairGeometry:
    """The pair b -> a of the pair a -> b: X_a = R^T X_b - R^T t."""
    R = np.asarray(geo.R_ba, float)
    return PairGeometry(geo.cam_b, geo.cam_a, R.T, -R.T @ np.asarray(geo.t_ba_m, float))


def _check_shapes(res, cam, what: str) -> None:
    if res.inv_range_per_m is None or res.inv_range_std_per_m is None or res.flags is None:
        raise InputError(f"lr check: the {what} result must carry inv_range_per_m, inv_range_std_per_m and flags "
                         f"(the dense method's), got method {res.method!r} without them")
    if res.inv_range_per_m.shape != (cam.height, cam.width):
        raise InputError(f"lr check: the {what} result is {res.inv_range_per_m.shape[1]}x"
                         f"{res.inv_range_per_m.shape[0]} but its camera {cam.name!r} is {cam.width}x{cam.height}")


def inconsistent(res_ab: RangeResult, res_ba: RangeResult, geo: PairGeometry,
                 cfg: LRCheckConfig = LRCheckConfig()) -> tuple[np.ndarray, np.ndarray]:
    """(inconsistent, checked): bool masks on a's grid of the pixels of ``res_ab`` (the pair a -> b of ``geo``)
    whose estimate ``res_ba`` (the pair b -> a, on b's grid) contradicts, and of those it could judge at all
    (module docstring). One pass of a numba kernel (``_consistency_kernels.check``)."""
    _check_shapes(res_ab, geo.cam_a, "a -> b")
    _check_shapes(res_ba, geo.cam_b, "b -> a")
    bad = np.empty(res_ab.inv_range_per_m.shape, np.uint8)
    checked = np.empty_like(bad)
    cam = lambda c: np.array([c.fx, c.fy, c.cx, c.cy], np.float64)
    c32 = lambda a, t: np.ascontiguousarray(a, t)
    _K.check(c32(res_ab.inv_range_per_m, F32), c32(res_ab.inv_range_std_per_m, F32), c32(res_ab.flags, np.uint8),
             c32(res_ba.inv_range_per_m, F32), c32(res_ba.inv_range_std_per_m, F32), c32(res_ba.flags, np.uint8),
             np.ascontiguousarray(geo.R_ba, np.float64), np.ascontiguousarray(geo.t_ba_m, np.float64),
             cam(geo.cam_a), cam(geo.cam_b), float(cfg.k), float(cfg.floor_px), bool(cfg.farther), bad, checked)
    return bad.view(bool), checked.view(bool)


def flag_inconsistent(res: RangeResult, bad: np.ndarray) -> RangeResult:
    """``res`` with the ``bad`` pixels flagged OUT_OF_VIEW | OCCLUDED, not VALID / AT_INFINITY, range NaN and
    confidence 0 (rho and sigma kept); new range, confidence and flag arrays, the rest shared."""
    flags = res.flags.copy()
    flags[bad] = (flags[bad] & np.uint8(~(VALID | AT_INFINITY) & 0xFF)) | np.uint8(OUT_OF_VIEW | OCCLUDED)
    rng = res.range_m.copy()
    rng[bad] = np.nan
    conf = res.confidence.copy()
    conf[bad] = 0.0
    info = dict(res.info)
    n = max(int(bad.size), 1)
    if "valid_fraction" in info:
        info["valid_fraction"] = float(((flags & VALID) != 0).sum() / n)
    return replace(res, range_m=rng, confidence=conf, flags=flags, info=info)


def lr_checked(res_ab: RangeResult, res_ba: RangeResult, geo: PairGeometry,
               cfg: LRCheckConfig = LRCheckConfig()) -> RangeResult:
    """``res_ab`` with the pixels ``res_ba`` contradicts flagged (``inconsistent``, ``flag_inconsistent``);
    ``info["lr_check"]``: checked and flagged pixel counts."""
    t0 = time.perf_counter()
    bad, chk = inconsistent(res_ab, res_ba, geo, cfg)
    out = flag_inconsistent(res_ab, bad)
    out.info["lr_check"] = {"checked": int(chk.sum()), "flagged": int(bad.sum()),
                            "check_seconds": time.perf_counter() - t0}
    return out


def locate_dense_lr(view_a: View, view_b: View, *, lr_k: float = LRCheckConfig.k,
                    lr_floor_px: float = LRCheckConfig.floor_px, **dense_params) -> RangeResult:
    """The dense method on (a, b) (with ``dense_params``, its fill included unless ``fill=False``) checked against
    the dense method on (b, a) without its fill (module docstring). Method "dense_lr" of ``eonav.ranging.locate``;
    ``info["lr_check"]["seconds"]``: the second locate and the check."""
    from eonav.ranging.methods.dense import locate_dense
    cfg = LRCheckConfig(lr_k, lr_floor_px)
    res_ab = locate_dense(view_a, view_b, **dense_params)
    t0 = time.perf_counter()
    back = {k: v for k, v in dense_params.items() if k not in ("prior", "fill")}
    res_ba = locate_dense(view_b, view_a, fill=False, **back)
    out = lr_checked(res_ab, res_ba, pair_geometry(view_a, view_b), cfg)
    out.info["lr_check"]["seconds"] = time.perf_counter() - t0
    return out


def prepare_kernels() -> None:
    """Compile the check's kernel (or load it from numba's cache) now, for the argument types ``inconsistent``
    passes it, instead of in the first check: a tiny hand-made pair of results, both sides."""
    from eonav.geometry.camera import Camera
    cam = Camera("probe", 8, 8, 8.0, 8.0, 3.5, 3.5)
    geo = PairGeometry(cam, cam, np.eye(3), np.array([0.0, 0.1, 0.0]))
    res = RangeResult(range_m=np.full((8, 8), 10.0, F32), confidence=np.ones((8, 8), F32), method="probe",
                      inv_range_per_m=np.full((8, 8), 0.1, F32), inv_range_std_per_m=np.full((8, 8), 0.01, F32),
                      flags=np.full((8, 8), VALID, np.uint8))
    for farther in (False, True):
        inconsistent(res, res, geo, LRCheckConfig(farther=farther))


__all__ = ["LRCheckConfig", "inconsistent", "flag_inconsistent", "lr_checked", "locate_dense_lr", "prepare_kernels"]
