"""The state as a range map: the arrays of ``eonav locate`` (range_m, confidence, inv_range_per_m,
inv_range_std_per_m, flags) plus the number of measurements fused per pixel.

The reported sigma adds to the filter's variance an error that fusion cannot average away: where the dense method
fits one inverse range per window (its slanted window, slant=True, removes most of this where rho's gradient is moderate, not
across steep ones), weighting its pixels by their squared epipolar gradient, on a surface whose rho varies across
the window it measures rho at the texture-weighted centre of the window, not at the pixel. The offset
is fixed to the scene's texture, so every pair of the sequence makes the same error: the measurements agree with
each other (the filter's variance shrinks as 1/N) but not with the truth. Its size is |grad rho| x the spread of
that offset (``slant_px``), grad rho taken from the state itself on the cell's own surface (``slant_g2``):

    sigma^2 = var + slant_px^2 |grad rho|^2.

A cell is VALID when its evidence agrees (E[inlier ratio] >= ``eta_inlier``) and, by the rules of a single pair
(``eonav.ranging.methods._common.classify_into``), its relative sigma is within ``max_rel_std`` -- or it is AT_INFINITY (rho
within 2 sigma of 0 and 2 sigma below the state's far limit). A cell whose evidence disagrees is ILL_CONDITIONED
(no range: never a confident range where the measurements contradict each other); an empty cell keeps the last
measurement's reason bits (LOW_TEXTURE, OUT_OF_VIEW, OCCLUDED, ...). Then, as a single pair does, pixels without a
fused range are filled from the VALID ones around them (``eonav.ranging.methods.fill``, flagged FILLED, with their own
sigma). Two kinds of cell are contested -- those whose evidence disagrees, and empty cells the last measurement saw
OCCLUDED (``NO_FILL_FUSED``: hidden in its image b, behind a nearer surface) -- and the neighbours' plane stands in
for them only where it is far tighter than the rule (relative sigma within ``contested_rel_std``): there the cell's
neighbourhood is one surface whose plane the stream has pinned down; a looser plane there mixes the two sides of
the edge that hides or contradicts the cell, and its sigma does not say so. An empty cell within ``border_px`` of
the image border (content that entered the view and no pair has measured yet) is extrapolated to like a pixel out
of view of b -- the neighbours' plane carried on for those few pixels -- unless it is LOW_TEXTURE (may be sky).
A VALID cell from a single measurement that the last measurement looked at and did not range (``held_single``: one
pair's guess the stream has not repeated, such as faint sky ranged once and LOW_TEXTURE after) is reported without a
range (``MapConfig.held_single``); the fill may stand in for it.
"""
from __future__ import annotations

import math
from dataclasses import dataclass
from functools import lru_cache

import numpy as np

from eonav import InputError
from eonav.ranging.methods._common import classify_into, make_result
from eonav.ranging.methods.fill import fill_unmeasured
from eonav.ranging.rangemap import (AT_INFINITY, FILLED, ILL_CONDITIONED, LOW_TEXTURE, OCCLUDED, OUT_OF_VIEW,
                                   TRUNCATION, VALID, RangeResult)
from eonav.fusion.state import F32, InverseRangeState, optional_kernels
from eonav.fusion.update import (UpdateConfig, check_shape, counts_dict, kernel_params, measurement_arrays,
                                 update, update_rho_far)

METHOD = "fused"
# empty cells contested (filled only from a plane tighter than contested_rel_std): those the last measurement saw
# hidden in its image b (a depth edge, where a loose plane through the neighbours mixes two surfaces). Not TRUNCATION, which a single pair does not fill either: in the
# fused map it is one pair's verdict on its own Gauss-Newton step, and the fill's sigma (the plane's residual and
# its disagreement across scales) judges the neighbours, which the stream has converged
NO_FILL_FUSED = OCCLUDED
REASON_BITS = np.uint8(TRUNCATION | ILL_CONDITIONED | OUT_OF_VIEW | LOW_TEXTURE | OCCLUDED)
_BITS = np.array([REASON_BITS, ILL_CONDITIONED, OUT_OF_VIEW | LOW_TEXTURE | ILL_CONDITIONED | TRUNCATION,
                  AT_INFINITY, VALID, VALID | FILLED, OUT_OF_VIEW], np.uint8)       # for _kernels.classify_state


@dataclass(frozen=True)
class MapConfig:
    eta_inlier: float = 0.65       # least E[inlier ratio] of a VALID cell
    max_rel_std: float = 0.34      # largest relative sigma of a VALID cell (the dense method's rule)
    fill: bool = True              # fill the cells without a fused range from the VALID ones around them
    slant_px: float = 1.5          # spread (px) of the window's effective centre (one rho per window's, also with the
                                   # dense slant=True: its gate keeps one rho per window on far ground and at edges)
    no_fill: int = NO_FILL_FUSED   # flag bits of the empty cells contested (module docstring)
    contested_rel_std: float = 0.05  # largest relative sigma of a contested cell's fill (0: never filled)
    border_px: int = 4             # empty cells this near the image border are extrapolated to (0: not)
    held_single: bool = True       # a VALID cell from one measurement the last pair looked at and did not range is
                                   # not reported (``held_single``; docs/methods.md, "Fusion over the stream")

    def __post_init__(self):
        if not 0 < self.eta_inlier < 1:
            raise InputError(f"fused map: eta_inlier must be in (0, 1), got {self.eta_inlier!r}")
        if not (math.isfinite(self.max_rel_std) and self.max_rel_std > 0):
            raise InputError(f"fused map: max_rel_std must be > 0, got {self.max_rel_std!r}")
        if not (math.isfinite(self.slant_px) and self.slant_px >= 0):
            raise InputError(f"fused map: slant_px must be a finite number >= 0, got {self.slant_px!r}")
        if not (math.isfinite(self.contested_rel_std) and 0 <= self.contested_rel_std <= self.max_rel_std):
            raise InputError(f"fused map: contested_rel_std must be in [0, max_rel_std], got {self.contested_rel_std!r}")
        if not (isinstance(self.border_px, int) and self.border_px >= 0):
            raise InputError(f"fused map: border_px must be a whole number of pixels >= 0, got {self.border_px!r}")
        if not (isinstance(self.no_fill, int) and 0 <= self.no_fill <= 255):
            raise InputError(f"fused map: no_fill must be flag bits (an integer 0..255), got {self.no_fill!r}")


def slant_g2(rho: np.ndarray, var: np.ndarray) -> np.ndarray:
    """The squared inverse-range gradient ((1/m per pixel)^2) of the surface each cell lies on: per axis the smaller
    of its two one-sided squared differences (the side across a depth edge is not its surface); sides with an empty
    neighbour are not used, an axis with none adds 0. Not less the two cells' noise: neighbours share most of their
    windows, so their errors are nearly the same. (``_kernels.slant_g2`` per cell.)"""
    g2 = np.zeros(rho.shape, F32)
    with np.errstate(invalid="ignore"):
        for axis in (0, 1):
            best = np.full(rho.shape, np.inf, F32)
            n = rho.shape[axis]
            for lo, hi in ((slice(1, n), slice(0, n - 1)), (slice(0, n - 1), slice(1, n))):
                me = [slice(None)] * 2
                nb = [slice(None)] * 2
                me[axis], nb[axis] = lo, hi
                me, nb = tuple(me), tuple(nb)
                d = rho[nb] - rho[me]
                e = (d * d).astype(F32)
                e = np.where(np.isfinite(e), e, np.inf)
                np.minimum(best[me], e, out=best[me])
            g2 += np.where(np.isfinite(best) & (best > 0), best, F32(0))
    return np.where(np.isfinite(rho), g2, F32(0)).astype(F32)


def fused_map(state: InverseRangeState, cfg: MapConfig = MapConfig(), kernels: bool | None = None,
              reuse: RangeResult | None = None) -> RangeResult:
    """A RangeResult of the state (method "fused"); ``info`` holds the counts and ``n_fused`` (uint16 H x W).
    kernels: the numba pass (``_kernels.classify_state``, the held single cells included; None: when numba is
    installed; False: the numpy path, the reference). reuse: a range map of the state's shape that nobody holds any more (the measurement just fused)
    whose arrays to overwrite with the result (numba pass): no fresh memory to page in."""
    K = optional_kernels() if kernels is None or kernels else None
    if kernels and K is None:
        raise ImportError("fused_map(kernels=True) needs numba")
    if K is None:
        rho, std, flags, rng, conf, n_val, n_inf, occ, exclude = _classify_numpy(state, cfg)
        return _finish(state, cfg, rho, std, flags, rng, conf, n_val, n_inf, int(occ.sum()),
                       int(np.count_nonzero(exclude)), 0, exclude, False)
    out = _outputs(state.shape, reuse)
    counts = K.classify_state(state.rho, state.var, state.a, state.b, state.n, state.flags,
                              *_classify_params(state, cfg), *out)
    return _finish(state, cfg, *out[:5], *counts, out[5], True)


def update_and_map(state: InverseRangeState, rho_m, std_m, flags_m, ucfg: UpdateConfig = UpdateConfig(),
                   mcfg: MapConfig = MapConfig(), rho_far: float | None = None, kernels: bool | None = None,
                   reuse: RangeResult | None = None):
    """``update`` then ``fused_map``: (update counts, RangeResult); with numba in one sweep over the state
    (``_kernels.update_classify``), the same result."""
    K = optional_kernels() if kernels is None or kernels else None
    if kernels and K is None:
        raise ImportError("update_and_map(kernels=True) needs numba")
    if K is None:
        counts = update(state, rho_m, std_m, flags_m, ucfg, rho_far=rho_far, kernels=False)
        return counts, fused_map(state, mcfg, kernels=False)
    check_shape(state, rho_m)
    update_rho_far(state, rho_far)
    meas = measurement_arrays(rho_m, std_m, flags_m)
    out = _outputs(state.shape, reuse)
    r = K.update_classify(state.rho, state.var, state.a, state.b, state.n, state.du, state.dv, state.flags, *meas,
                          *kernel_params(ucfg), *_classify_params(state, mcfg), *out)
    res = _finish(state, mcfg, *out[:5], *r[5:], out[5], True)
    return counts_dict(*r[:5]), res


def _classify_params(state, cfg):
    return (_BITS, F32(cfg.eta_inlier), F32(cfg.max_rel_std), F32(state.rho_far), F32(cfg.slant_px ** 2),
            bool(cfg.held_single))


def _outputs(shape, reuse):
    """(rho, std, flags, rng, conf, exclude) to write: ``reuse``'s arrays where they fit, else fresh."""
    if reuse is not None and _reusable(reuse, shape):
        rho, std, rng, conf, flags = (reuse.inv_range_per_m, reuse.inv_range_std_per_m, reuse.range_m,
                                      reuse.confidence, reuse.flags)
    else:
        rho, std, rng, conf = (np.empty(shape, F32) for _ in range(4))
        flags = np.empty(shape, np.uint8)
    return rho, std, flags, rng, conf, np.empty(shape, np.bool_)


def _finish(state, cfg, rho, std, flags, rng, conf, n_val, n_inf, n_occ, n_dis, n_held, exclude,
            kernels: bool) -> RangeResult:
    """The map's held single cells (unless the kernel did them: ``kernels``), its fill and its RangeResult."""
    if cfg.held_single and not kernels:
        n_held, d_val, d_inf = _demote_held(state, flags, rng, conf)
        n_val, n_inf = int(n_val) - d_val, int(n_inf) - d_inf
    # a cell whose measurements disagree, or that the last pair saw hidden, is filled only by a tight plane
    n_filled = 0
    if cfg.fill:
        strict = (exclude | ((flags & np.uint8(cfg.no_fill)) != 0)) if cfg.contested_rel_std > 0 else None
        edge = _border_cells(state, flags, cfg) if cfg.border_px else None
        if edge is not None:
            flags[edge] |= np.uint8(OUT_OF_VIEW)          # for the fill only: extrapolated to
        n_filled = fill_unmeasured(rho, std, flags, rng, conf, cfg.max_rel_std, rho_far=state.rho_far,
                                   exclude=exclude, no_fill=cfg.no_fill, strict=strict,
                                   strict_rel_std=cfg.contested_rel_std)
        if edge is not None:
            flags[edge] &= np.uint8(~OUT_OF_VIEW & 0xFF)
    size = max(rho.size, 1)
    info = {"occupied_fraction": n_occ / size, "disagree_fraction": int(n_dis) / size,
            "filled_fraction": n_filled / size, "held_fraction": int(n_held) / size, "n_fused": state.n.copy()}
    return make_result(rho, std, flags, rng, conf, METHOD, int(n_val), int(n_inf), info)


def held_single(state: InverseRangeState) -> np.ndarray:
    """Cells holding a single measurement (n == 1) that the last measurement looked at and did not range: the
    state's flags (the last measurement's, carried with the cell) not VALID, or FILLED, and not OUT_OF_VIEW (a
    partner that does not see the point, or sees it hidden, says nothing of it). One pair's guess the stream has not
    repeated since: faint sky ranged once, then LOW_TEXTURE pair after pair. A cell (re)started by the last
    measurement is VALID there: fresh, not held. With ``FusionConfig.n_per_instant`` the runner's n counts frames
    (a rig frame's motion and stereo pairs once), so one frame's look by both pairs is held as well."""
    last = state.flags
    said = ((last & np.uint8(VALID | FILLED)) != np.uint8(VALID)) & ((last & np.uint8(OUT_OF_VIEW)) == 0)
    return (state.n == 1) & said & state.occupied()


def _demote_held(state, flags, rng, conf):
    """The ``held_single`` cells the map reports VALID, in place: ILL_CONDITIONED, no range, confidence 0 (held
    cells already without a range, a loose sigma, are left as they are). The fill may stand in for them as for any
    cell without a range. Returns (cells demoted, VALID ones, AT_INFINITY ones). The numpy path's (the kernels do
    it in their classification, ``_kernels.classify_state``)."""
    held = held_single(state)
    held &= (flags & np.uint8(VALID)) != 0
    n_held = int(np.count_nonzero(held))
    if not n_held:
        return 0, 0, 0
    d_inf = int(np.count_nonzero(flags[held] & np.uint8(AT_INFINITY)))
    flags[held] = np.uint8(ILL_CONDITIONED)
    rng[held] = np.nan
    conf[held] = 0.0
    return n_held, n_held - d_inf, d_inf


def _border_cells(state, flags, cfg):
    """(rows, columns) of the empty cells within cfg.border_px of the image border, not yet out of view, with no
    LOW_TEXTURE and none of the contested bits, or None. Only the border ring is read."""
    ring = _ring(flags.shape, cfg.border_px)
    bad = np.uint8(VALID | OUT_OF_VIEW | LOW_TEXTURE | cfg.no_fill)
    sel = ring[((flags.reshape(-1)[ring] & bad) == 0) & ~np.isfinite(state.rho.reshape(-1)[ring])]
    return np.unravel_index(sel, flags.shape) if sel.size else None


@lru_cache(maxsize=16)
def _ring(shape, border_px: int) -> np.ndarray:
    """Flat indices (read-only) of the pixels within border_px of the border of an image of ``shape``."""
    h, w = shape
    k = min(border_px, (h + 1) // 2, (w + 1) // 2)
    inner = np.zeros(shape, bool)
    inner[k:h - k, k:w - k] = True
    ring = np.flatnonzero(~inner)
    ring.setflags(write=False)
    return ring


def _reusable(r: RangeResult, shape) -> bool:
    arrs = (r.inv_range_per_m, r.inv_range_std_per_m, r.range_m, r.confidence)
    return (all(isinstance(a, np.ndarray) and a.shape == shape and a.dtype == F32 and a.flags.c_contiguous
                and a.flags.writeable for a in arrs)
            and isinstance(r.flags, np.ndarray) and r.flags.shape == shape and r.flags.dtype == np.uint8
            and r.flags.flags.writeable and len({id(a) for a in arrs}) == 4)


def _classify_numpy(state: InverseRangeState, cfg: MapConfig):
    rho = state.rho.copy()
    occ = state.occupied()
    std = np.sqrt(state.var + F32(cfg.slant_px ** 2) * slant_g2(state.rho, state.var)).astype(F32)
    with np.errstate(invalid="ignore", divide="ignore"):
        agree = occ & (state.a >= F32(cfg.eta_inlier) * (state.a + state.b))
    flags = np.where(occ, np.uint8(0), state.flags & REASON_BITS).astype(np.uint8)
    flags[occ & ~agree] |= np.uint8(ILL_CONDITIONED)
    flags[~occ & (flags == 0)] = np.uint8(ILL_CONDITIONED)
    rng = np.empty(rho.shape, F32)
    conf = np.empty(rho.shape, F32)
    n_val, n_inf = classify_into(rho, std, flags, rng, conf, rho_far=state.rho_far, max_rel_std=cfg.max_rel_std)
    return rho, std, flags, rng, conf, n_val, n_inf, occ, occ & ~agree
