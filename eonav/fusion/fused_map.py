"""The state as a range map: the arrays of ``eonav locate`` (range_m, confidence, inv_range_per_m,
inv_range_std_per_m, flags) plus the number of measurements fused per pixel.

A cell is VALID when its evidence agrees (E[inlier ratio] >= ``eta_inlier``) and, by the rules of a single pair
(``eonav.ranging.methods._common.classify_into``), its relative sigma is within ``max_rel_std`` -- or it is AT_INFINITY (rho
within 2 sigma of 0 and 2 sigma below the state's far limit). A cell whose evidence disagrees is ILL_CONDITIONED
(no range: never a confident range where the measurements contradict each other); an empty cell keeps the last
measurement's reason bits (LOW_TEXTURE, OUT_OF_VIEW, OCCLUDED, ...). Then, as a single pair does, pixels without a
fused range are filled from the VALID ones around them (``eonav.ranging.methods.fill``, flagged FILLED, with their own
sigma); cells whose evidence disagrees are not filled.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from eonav import InputError
from eonav.ranging.methods._common import classify_into, make_result
from eonav.ranging.methods.fill import fill_unmeasured
from eonav.ranging.rangemap import ILL_CONDITIONED, LOW_TEXTURE, OCCLUDED, OUT_OF_VIEW, TRUNCATION, RangeResult
from eonav.fusion.state import F32, InverseRangeState

METHOD = "fused"
REASON_BITS = np.uint8(TRUNCATION | ILL_CONDITIONED | OUT_OF_VIEW | LOW_TEXTURE | OCCLUDED)


@dataclass(frozen=True)
class MapConfig:
    eta_inlier: float = 0.65       # least E[inlier ratio] of a VALID cell
    max_rel_std: float = 0.34      # largest relative sigma of a VALID cell (the dense method's rule)
    fill: bool = True              # fill the cells without a fused range from the VALID ones around them

    def __post_init__(self):
        if not 0 < self.eta_inlier < 1:
            raise InputError(f"fused map: eta_inlier must be in (0, 1), got {self.eta_inlier!r}")
        if not (math.isfinite(self.max_rel_std) and self.max_rel_std > 0):
            raise InputError(f"fused map: max_rel_std must be > 0, got {self.max_rel_std!r}")


def fused_map(state: InverseRangeState, cfg: MapConfig = MapConfig()) -> RangeResult:
    """A RangeResult of the state (method "fused"); ``info`` holds the counts and ``n_fused`` (uint16 H x W)."""
    rho = state.rho.copy()
    std = np.sqrt(state.var).astype(F32)
    occ = state.occupied()
    with np.errstate(invalid="ignore", divide="ignore"):
        agree = occ & (state.a >= F32(cfg.eta_inlier) * (state.a + state.b))
    flags = np.where(occ, np.uint8(0), state.flags & REASON_BITS).astype(np.uint8)
    flags[occ & ~agree] |= np.uint8(ILL_CONDITIONED)
    flags[~occ & (flags == 0)] = np.uint8(ILL_CONDITIONED)
    rng = np.empty(rho.shape, F32)
    conf = np.empty(rho.shape, F32)
    n_val, n_inf = classify_into(rho, std, flags, rng, conf, rho_far=state.rho_far, max_rel_std=cfg.max_rel_std)
    # a cell whose measurements disagree gets no range from its neighbours either
    n_filled = (fill_unmeasured(rho, std, flags, rng, conf, cfg.max_rel_std, rho_far=state.rho_far,
                                exclude=occ & ~agree) if cfg.fill else 0)
    info = {"occupied_fraction": float(occ.mean()), "disagree_fraction": float((occ & ~agree).mean()),
            "filled_fraction": n_filled / max(rho.size, 1), "n_fused": state.n.copy()}
    return make_result(rho, std, flags, rng, conf, METHOD, n_val, n_inf, info)
