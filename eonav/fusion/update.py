"""Update: fuse one dense measurement (inverse range and its own sigma per pixel) into the state.

Measurement model of Vogiatzis & Hernandez (2011), used by REMODE (Pizzoli et al. 2014) and SVO's depth filter:
a measurement x of a cell is, with probability pi (the cell's inlier ratio), Gaussian about the true rho with the
measurement's variance tau^2, and otherwise uniform over [0, rho_max] (an occlusion, a mismatch, a moving object).
The posterior of (rho, pi) is approximated by a Gaussian in rho times a Beta(a, b) in pi, matched in moments:

    C1 ~ a / (a + b) N(x; mu, s^2 + tau^2),   C2 ~ b / (a + b) / rho_max,   C1 + C2 = 1
    m = s'^2 (mu / s^2 + x / tau^2),   s'^2 = 1 / (1 / s^2 + 1 / tau^2)
    mu_new = C1 m + C2 mu,   s_new^2 = C1 s'^2 + C2 s^2 + C1 C2 (m - mu)^2
    f = C1 (a + 1) / (a + b + 1) + C2 a / (a + b + 1)
    e = C1 (a + 1)(a + 2) / ((a + b + 1)(a + b + 2)) + C2 a (a + 1) / ((a + b + 1)(a + b + 2))
    a_new = (e - f) / (f - e / f),   b_new = a_new (1 - f) / f

(the variance written as C1 s'^2 + C2 s^2 + C1 C2 (m - mu)^2, the same as the published C1 (s'^2 + m^2) + C2 (s^2
+ mu^2) - mu_new^2 without its cancellation in float32). An outlier (x many sigma off) has C1 ~ 0: the estimate and
its variance stay, only b grows. A measurement that might be either (C1 ~ C2) widens the variance by the spread of
the two: the cell is not confident until the evidence settles.

Beyond the published filter, for a stream that never ends and a scene that may move:
- the evidence is a window: when a + b exceeds ``evidence_cap`` both are scaled down to it (the inlier ratio of
  about the last ``evidence_cap`` measurements, so a cell whose point changed -- a moving object -- loses its
  confidence in a few frames instead of never);
- b is kept at least ``B_MIN``: after ~100 agreeing measurements in a row b falls to ~1e-5, where the Beta's
  variance (~a b / (a + b)^3) is below float32's resolution of f, f - e / f cancels to 0 and a_new becomes inf, then
  NaN (the cell emptied itself);
- a cell whose inlier ratio falls below ``eta_outlier`` (diverged) restarts from the measurement;
- an empty cell starts from its first measurement (mu = x, s^2 = tau^2, Beta(a_init, b_init)).
Measured pixels update, the rest keep their prediction: VALID ones (not FILLED), and, with ``weak`` (default),
ILL_CONDITIONED ones whose only fault is their own sigma (relative sigma above ``max_rel_std`` or rho within 2 sigma
of 0: far or near the focus of expansion, where one pair has too little parallax): a single pair cannot range them,
but their Gaussian measurements add up over the stream, which is the point of fusing (REMODE fuses every pixel with
its own sigma). An ILL_CONDITIONED pixel whose sigma is tight was flagged for another reason (the dense method's
point-at-infinity or orientation tests: its estimate is not to be trusted at that sigma) and is not fused.

Stereo leads (``stereo_lead_k`` > 0). A motion pair (one camera at two times) ranges a point only if it stood still
between the two frames: on an independently moving object its match leaves the epipolar curve, so the pair flags
the pixel OCCLUDED or ranges it wrong, and a filter that assumes a static scene rejects it as an outlier against the
converged background (the mover then never enters the map). A stereo pair (two cameras at one instant) ranges a
mover like anything else. So, when a reference frame has both:
- ``gate_motion``: a motion pixel whose measurement disagrees with the same frame's stereo measurement by more than
  ``stereo_lead_k`` sigma (both sigmas) is not fused (the stereo one is right whatever moved); nor, with
  ``gate_unmatched`` (default), one whose stereo pixel failed to match (OCCLUDED, TRUNCATION): nothing can check
  it there, and that is where a mover's edges are. A motion pair ranges a vehicle closing on the camera at
  v_c / (v_c + v_o) of its range (0.71 x for 20 m/s against 8 m/s) and its window carries that onto the background
  cells along the vehicle's edges, which the stereo pair sees occluded or does not converge on: a skirt of cells
  nearer than anything there, fused frame after frame (docs/guidance.md, "The stereo pair's unmatched pixels gate
  the motion pairs"). A stereo pixel without information (OUT_OF_VIEW, LOW_TEXTURE, ILL_CONDITIONED) does not gate:
  there the motion pairs are all there is;
- ``stereo_restart``: a cell the stereo measurement disagrees with by more than ``stereo_lead_k`` sigma (the cell's
  and the measurement's) starts again from the stereo measurement, instead of counting one more outlier against an
  estimate the motion pairs built from a scene that has since moved; so does a cell whose motion measurement of the
  same frame was fused before the stereo one arrived (the partner camera's frame second) and disagrees with it.
A static cell whose stereo measurement is a mismatch is restarted too; the next frame's stereo measurement disagrees
with that wrong start and restarts it again, so one bad stereo pixel costs its cell a frame or two.

Free space seen past a mover (``skipped_free_k`` > 0, off by default; docs/guidance.md, "Moving obstacles on fused
maps"): a mover leaves its range in the cells it uncovers (its trailing edge), and the motion pairs see those cells
OCCLUDED or with a sigma wide enough to agree with the old range, so nothing corrects them. The same frame's stereo
pair often ranges them -- farther -- on pixels the update skips (``measured`` is False: ILL_CONDITIONED with a tight
sigma from the dense method's orientation or point-at-infinity tests, TRUNCATION, LOW_TEXTURE). Too doubtful to
fuse, such a pixel still says the space up to its range is free: ``stereo_skipped_free`` empties a cell it sees
farther than the cell holds by more than ``skipped_free_k`` sigma (both), one-sided (a skipped pixel nearer than
the cell says nothing). Pixels OCCLUDED or OUT_OF_VIEW in the stereo pair (the partner does not see the point) are
not used.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from eonav import InputError
from eonav.ranging.rangemap import (FILLED, ILL_CONDITIONED, LOW_TEXTURE, OCCLUDED, OUT_OF_VIEW, TRUNCATION,
                                   VALID)
from eonav.fusion.state import F32, InverseRangeState, optional_kernels


B_MIN = 1e-4       # the least b (module docstring): E[inlier ratio] at most 1 - B_MIN / evidence_cap
# a weak measurement: of these bits only ILL_CONDITIONED set
WEAK_BITS = np.uint8(VALID | FILLED | ILL_CONDITIONED | LOW_TEXTURE | OUT_OF_VIEW | OCCLUDED | TRUNCATION)


@dataclass(frozen=True)
class UpdateConfig:
    rho_max_per_m: float = 2.0        # support of the uniform outlier density (nearest range 0.5 m)
    sigma_scale: float = 1.0          # measurement sigma multiplier (the error pairs share: fused_map's slant term)
    a_init: float = 3.0               # Beta evidence of a cell started from one measurement: E[pi] = 0.75
    b_init: float = 1.0
    evidence_cap: float = 8.0         # a + b kept at most this (the last ~8 measurements' inlier ratio)
    eta_outlier: float = 0.45         # E[pi] below this: diverged, restart from the measurement
    weak: bool = True                 # fuse ILL_CONDITIONED pixels whose only fault is their sigma (module docstring)
    max_rel_std: float = 0.34         # the dense method's VALID limit of the relative sigma (what "weak" means)
    stereo_lead_k: float = 3.0        # stereo leads where it disagrees by more sigma than this (0: off; docstring)
    skipped_free_k: float = 0.0       # with stereo leading: skipped stereo pixels farther by this many sigma empty
    #                                   the cell (0: off; module docstring, "Free space seen past a mover")
    gate_unmatched: bool = True       # with stereo leading: a motion pixel whose stereo pixel failed to match
    #                                   (OCCLUDED, TRUNCATION) is not fused (module docstring, "Stereo leads")

    def __post_init__(self):
        for name in ("stereo_lead_k", "skipped_free_k"):
            v = getattr(self, name)
            if not (math.isfinite(v) and v >= 0):
                raise InputError(f"fusion update: {name} must be a finite number >= 0, got {v!r}")
        for name in ("rho_max_per_m", "sigma_scale", "a_init", "b_init", "evidence_cap", "max_rel_std"):
            v = getattr(self, name)
            if not (math.isfinite(v) and v > 0):
                raise InputError(f"fusion update: {name} must be a finite number > 0, got {v!r}")
        if not 0 <= self.eta_outlier < 1:
            raise InputError(f"fusion update: eta_outlier must be in [0, 1), got {self.eta_outlier!r}")
        if self.evidence_cap < self.a_init + self.b_init:
            raise InputError("fusion update: evidence_cap must be at least a_init + b_init")


def measured(rho_m, std_m, flags_m, cfg: UpdateConfig = UpdateConfig()) -> np.ndarray:
    """Pixels of a measurement that carry one (finite rho, finite sigma > 0): VALID (not FILLED), and with
    ``cfg.weak`` ILL_CONDITIONED ones with no other fault whose sigma alone explains the flag (module docstring)."""
    rho_m = np.asarray(rho_m, F32)
    std_m = np.asarray(std_m, F32)
    with np.errstate(invalid="ignore"):
        ok = np.isfinite(rho_m) & np.isfinite(std_m) & (std_m > 0)
        sel = (flags_m & np.uint8(VALID | FILLED)) == np.uint8(VALID)
        if cfg.weak:
            tight = (std_m <= F32(cfg.max_rel_std) * rho_m) & (rho_m >= F32(2.0) * std_m)
            sel |= ((flags_m & WEAK_BITS) == np.uint8(ILL_CONDITIONED)) & ~tight
    return sel & ok


def measurement_arrays(rho_m, std_m, flags_m):
    """The measurement as the kernels take it (float32, float32, uint8)."""
    return np.asarray(rho_m, F32), np.asarray(std_m, F32), np.asarray(flags_m, np.uint8)


def kernel_params(cfg: UpdateConfig):
    """(bits, prm) of ``_kernels.update``."""
    bits = np.array([VALID | FILLED, VALID, WEAK_BITS if cfg.weak else 0, ILL_CONDITIONED], np.uint8)
    prm = np.array([cfg.max_rel_std, cfg.sigma_scale, cfg.rho_max_per_m, cfg.a_init, cfg.b_init, cfg.evidence_cap,
                    cfg.eta_outlier, B_MIN], F32)
    return bits, prm


def counts_dict(n_meas, started, inl, outl, rest) -> dict:
    return {"measured": int(n_meas), "started": int(started), "inliers": int(inl), "outliers": int(outl),
            "restarted": int(rest)}


def update_rho_far(state: InverseRangeState, rho_far: float | None) -> None:
    """The state keeps the smallest far inverse range of the pairs fused."""
    if rho_far is not None and rho_far > 0:
        state.rho_far = rho_far if state.rho_far <= 0 else min(state.rho_far, float(rho_far))


def gaussian_uniform_step(mu, s2, a, b, x, tau2, rho_max: float):
    """One moment-matched update (module docstring) of arrays of cells; returns (mu, s2, a, b, C1): C1 is the
    posterior probability that x was an inlier."""
    S = s2 + tau2
    d = x - mu
    c1 = a / (a + b) * np.exp(F32(-0.5) * d * d / S) / np.sqrt(F32(2 * math.pi) * S)
    c2 = b / (a + b) * F32(1.0 / rho_max)
    norm = c1 + c2
    c1 = c1 / norm
    c2 = F32(1.0) - c1
    sp2 = s2 * tau2 / S
    m = mu + sp2 / tau2 * d                         # = s'^2 (mu / s^2 + x / tau^2) (s^2 finite: cells start finite)
    mu_new = c1 * m + c2 * mu
    dm = m - mu
    s2_new = c1 * sp2 + c2 * s2 + c1 * c2 * dm * dm
    ab1 = a + b + F32(1.0)
    ab2 = ab1 + F32(1.0)
    f = (c1 * (a + F32(1.0)) + c2 * a) / ab1
    e = (c1 * (a + F32(1.0)) * (a + F32(2.0)) + c2 * a * (a + F32(1.0))) / (ab1 * ab2)
    a_new = (e - f) / (f - e / f)
    b_new = a_new * (F32(1.0) - f) / f
    return mu_new, s2_new, a_new, b_new, c1


def _start_cells(state: InverseRangeState, sel, rho, var, cfg: UpdateConfig) -> None:
    """The cells ``sel`` (a flat index or mask of the state's grid) started from a measurement: mu = rho,
    s^2 = var, Beta(a_init, b_init), n = 1, no sub-pixel remainder."""
    for arr, v in ((state.rho, rho), (state.var, var), (state.a, cfg.a_init), (state.b, cfg.b_init), (state.n, 1),
                   (state.du, 0.0), (state.dv, 0.0)):
        arr.ravel()[sel] = v


def check_shape(state: InverseRangeState, rho) -> None:
    """A measurement on another grid than the state's is refused, naming both shapes."""
    if np.shape(rho) != state.shape:
        raise InputError(f"fusion update: measurement shape {np.shape(rho)} differs from the state {state.shape}")


def update(state: InverseRangeState, rho_m, std_m, flags_m, cfg: UpdateConfig = UpdateConfig(),
           rho_far: float | None = None, kernels: bool | None = None) -> dict:
    """Fuse a measurement on the state's grid into ``state`` (in place). ``rho_far``: the pair's far inverse range
    (the state keeps the smallest seen). Returns counts: measured, started (empty cells), inliers (C1 > 0.5),
    outliers, restarted (diverged cells started again from the measurement). kernels: the numba pass
    (``_kernels.update``; None: when numba is installed; False: the numpy path, the reference)."""
    check_shape(state, rho_m)
    flags_m = np.asarray(flags_m, np.uint8)
    update_rho_far(state, rho_far)
    K = optional_kernels() if kernels is None or kernels else None
    if kernels and K is None:
        raise ImportError("update(kernels=True) needs numba")
    if K is not None:
        n_meas, started, inl, outl, rest = K.update(
            state.rho, state.var, state.a, state.b, state.n, state.du, state.dv, state.flags,
            *measurement_arrays(rho_m, std_m, flags_m), *kernel_params(cfg))
        return counts_dict(n_meas, started, inl, outl, rest)
    meas = measured(rho_m, std_m, flags_m, cfg)
    state.flags[...] = flags_m
    occ = state.occupied()
    s = F32(cfg.sigma_scale)
    start = np.flatnonzero(meas & ~occ)
    fuse = np.flatnonzero(meas & occ)
    rho_m = np.asarray(rho_m, F32).ravel()
    std_m = np.asarray(std_m, F32).ravel()
    R, V, A, B, N = (x.ravel() for x in (state.rho, state.var, state.a, state.b, state.n))
    x = rho_m[fuse]
    tau = std_m[fuse] * s
    mu, s2, a, b, c1 = gaussian_uniform_step(R[fuse], V[fuse], A[fuse], B[fuse], x, tau * tau, cfg.rho_max_per_m)
    tot = a + b
    over = tot > F32(cfg.evidence_cap)
    k = np.where(over, F32(cfg.evidence_cap) / tot, F32(1.0))
    a *= k
    b = np.maximum(b * k, F32(B_MIN))
    diverged = a / (a + b) < F32(cfg.eta_outlier)
    mu = np.where(diverged, x, mu)
    s2 = np.where(diverged, tau * tau, s2)
    a = np.where(diverged, F32(cfg.a_init), a)
    b = np.where(diverged, F32(cfg.b_init), b)
    R[fuse], V[fuse], A[fuse], B[fuse] = mu, s2, a, b
    n = N[fuse]
    N[fuse] = np.where(diverged, 1, np.minimum(n.astype(np.int64) + 1, np.iinfo(np.uint16).max)).astype(np.uint16)
    restart = fuse[diverged]
    state.du.ravel()[restart] = 0.0
    state.dv.ravel()[restart] = 0.0
    _start_cells(state, start, rho_m[start], (std_m[start] * s) ** 2, cfg)
    inl = c1 > F32(0.5)
    return counts_dict(meas.sum(), start.size, inl.sum(), (~inl).sum(), diverged.sum())


def _lead_k(cfg: UpdateConfig) -> F32:
    return F32(cfg.stereo_lead_k)


def gate_motion(rho_m, std_m, flags_m, rho_s, std_s, flags_s, cfg: UpdateConfig = UpdateConfig()) -> np.ndarray:
    """Pixels of a motion measurement that disagree with the stereo measurement of the same frame by more than
    ``cfg.stereo_lead_k`` sigma (module docstring): both measured (``measured``), |rho_m - rho_s| > k sqrt(tau_m^2 +
    tau_s^2) with the sigmas scaled by ``sigma_scale``; with ``cfg.gate_unmatched`` also those with an inverse range
    whose stereo pixel failed to match (OCCLUDED or TRUNCATION, not ``measured``). Their inverse range is set to NaN
    in ``rho_m`` (in place, a float32 array): they are not fused. Returns the mask (none with k = 0)."""
    if np.shape(rho_m) != np.shape(rho_s):
        raise InputError(f"fusion gate: motion measurement shape {np.shape(rho_m)} differs from the stereo one "
                         f"{np.shape(rho_s)}")
    if cfg.stereo_lead_k == 0:
        return np.zeros(np.shape(rho_m), bool)
    stereo = measured(rho_s, std_s, flags_s, cfg)
    both = measured(rho_m, std_m, flags_m, cfg) & stereo
    s = F32(cfg.sigma_scale)
    with np.errstate(invalid="ignore"):
        tau2 = (np.asarray(std_m, F32) * s) ** 2 + (np.asarray(std_s, F32) * s) ** 2
        d = np.asarray(rho_m, F32) - np.asarray(rho_s, F32)
        off = both & (d * d > _lead_k(cfg) ** 2 * tau2)
    if cfg.gate_unmatched:
        failed = (np.asarray(flags_s, np.uint8) & np.uint8(OCCLUDED | TRUNCATION)) != 0
        off |= failed & ~stereo & np.isfinite(rho_m)
    rho_m[off] = np.nan
    return off


def clear_cells(state: InverseRangeState, mask) -> int:
    """Empty the ``mask`` cells of ``state`` (in place: rho NaN, variance inf, no evidence); returns how many held
    an estimate."""
    m = np.asarray(mask, bool) & state.occupied()
    state.clear(m)
    return int(m.sum())


def stereo_restart(state: InverseRangeState, rho_s, std_s, flags_s, cfg: UpdateConfig = UpdateConfig(),
                   also=None) -> np.ndarray:
    """Cells the stereo measurement disagrees with by more than ``cfg.stereo_lead_k`` sigma, |x - mu| > k sqrt(s^2 +
    tau^2), restarted from it (mu = x, s^2 = tau^2, Beta(a_init, b_init), n = 1; module docstring), in place;
    ``also``: a mask of further cells to restart where the stereo measurement has a value (those where the same
    frame's motion measurement, fused before the stereo one arrived, disagreed with it: ``gate_motion``). The
    measurement is to be fused into the other cells as usual: its inverse range is set to NaN in ``rho_s`` (in
    place, a float32 array) where a cell restarted. Returns the mask of restarted cells (none with k = 0)."""
    check_shape(state, rho_s)
    if cfg.stereo_lead_k == 0:
        return np.zeros(state.shape, bool)
    meas = measured(rho_s, std_s, flags_m=np.asarray(flags_s, np.uint8), cfg=cfg) & state.occupied()
    tau = np.asarray(std_s, F32) * F32(cfg.sigma_scale)
    with np.errstate(invalid="ignore"):
        d = np.asarray(rho_s, F32) - state.rho
        off = meas & (d * d > _lead_k(cfg) ** 2 * (state.var + tau * tau))
    if also is not None:
        off |= meas & np.asarray(also, bool)
    _start_cells(state, off.ravel(), rho_s[off], tau[off] ** 2, cfg)
    state.flags[off] = np.asarray(flags_s, np.uint8)[off]
    rho_s[off] = np.nan
    return off


def stereo_skipped_free(state: InverseRangeState, rho_s, std_s, flags_s, cfg: UpdateConfig = UpdateConfig()) -> np.ndarray:
    """Empty the cells of ``state`` (in place) that a stereo pixel the update skips sees farther than they hold
    (module docstring, "Free space seen past a mover"): the pixel not ``measured`` but with a finite inverse range
    and sigma > 0, neither OCCLUDED nor OUT_OF_VIEW, and x < mu - k sqrt(s^2 + tau^2) with k = ``cfg.skipped_free_k``
    and tau the pixel's sigma scaled by ``sigma_scale``. Returns the mask of emptied cells (none with k = 0)."""
    check_shape(state, rho_s)
    if cfg.skipped_free_k == 0:
        return np.zeros(state.shape, bool)
    flags_s = np.asarray(flags_s, np.uint8)
    rho_s = np.asarray(rho_s, F32)
    tau = np.asarray(std_s, F32) * F32(cfg.sigma_scale)
    with np.errstate(invalid="ignore"):
        skipped = (~measured(rho_s, std_s, flags_s, cfg) & np.isfinite(rho_s) & np.isfinite(tau) & (tau > 0)
                   & ((flags_s & np.uint8(OCCLUDED | OUT_OF_VIEW)) == 0) & state.occupied())
        d = state.rho - rho_s                            # > 0: the pixel sees past the cell's point
        free = skipped & (d > 0) & (d * d > F32(cfg.skipped_free_k) ** 2 * (state.var + tau * tau))
    state.clear(free)
    return free
