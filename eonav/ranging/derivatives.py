"""Causal recursive irradiance and partial-derivative estimators, eqs. (34)-(42) of the paper.

The image is factored as E = e1(x_p) e2(y_p) (eq. 34): a linear process runs along each scan line (eqs. 36-37) with
the measured irradiance as input, its smoothed output r1 drives a second process along each column (eqs. 38-39), and
the outputs combine by eq. (40) into E_hat, dE/dx_p, dE/dy_p. With a = ``bandwidth_per_px`` (the paper's 5.0 has no
stated units):

- order 1, eqs. (41)-(42): dp/dx = -a p + a E, r = [1, -a]^T p + [0, a]^T E (eq. 42 prints ``-5.0 p`` where it
  means ``-5.0 q``: a transcription slip);
- order 2, a critically damped pair, so that the second derivative is an output of the dynamics and stays smooth.

Decisions: the continuous system is discretised exactly under a first-order hold (``"foh"``, the default; ``"zoh"``
and ``"bilinear"`` for comparison), so the outputs are exact samples of the continuous ones at the pixel centres. A
causal low-pass delays by 1/a (order 1) or 2/a (order 2) pixels along x and y: the SAME estimator on both images
makes the delay common, and ``Derivatives.delay_px`` lets the caller evaluate the geometry at the delayed
coordinate. ``bias`` (note under eq. 40) keeps r1 away from zero; ``combine="linear"`` (not the paper's) is the exact
x-derivative for non-separable images. Runs with ``scipy.signal.lfilter``, each line started at steady state.
"""
from __future__ import annotations

from dataclasses import dataclass
from functools import lru_cache

import numpy as np
from scipy import signal

from eonav import InputError

DISCRETISATIONS = ("foh", "zoh", "bilinear")
COMBINES = ("eq40", "linear")


def estimator_state_space(bandwidth_per_px: float, order: int):
    """(A, B, C, D) of eqs. (36)-(37) for the order-1 estimator of eq. (41) or the order-2 one.

    Outputs: order 1 -> [smoothed E, dE/dx]; order 2 -> [smoothed E, dE/dx, d2E/dx2].
    """
    a = float(bandwidth_per_px)
    if order == 1:                                  # eq. (41)
        A = np.array([[-a]])
        B = np.array([[a]])
        C = np.array([[1.0], [-a]])
        D = np.array([[0.0], [a]])
    elif order == 2:
        A = np.array([[0.0, 1.0], [-a * a, -2.0 * a]])
        B = np.array([[0.0], [a * a]])
        C = np.array([[1.0, 0.0], [0.0, 1.0], [-a * a, -2.0 * a]])
        D = np.array([[0.0], [0.0], [a * a]])
    else:
        raise InputError(f"estimator order must be 1 or 2, got {order!r}")
    return A, B, C, D


@lru_cache(maxsize=64)
def discrete_filters(bandwidth_per_px: float, order: int, discretisation: str = "foh"):
    """Per-output discrete transfer functions (b_i, a) of the estimator, pixel step 1.

    Returns (bs, a): bs is a list of numerator arrays (one per output), a the common denominator.
    """
    _check_params(bandwidth_per_px, order, discretisation)
    A, B, C, D = estimator_state_space(bandwidth_per_px, order)
    Ad, Bd, Cd, Dd, _ = signal.cont2discrete((A, B, C, D), 1.0, method=discretisation)
    num, den = signal.ss2tf(Ad, Bd, Cd, Dd)
    num = np.where(np.abs(num) < 1e-14, 0.0, num)
    return [np.asarray(n, float) for n in num], np.asarray(den, float)


def _check_params(bandwidth_per_px, order, discretisation):
    if not (np.isfinite(bandwidth_per_px) and bandwidth_per_px > 0):
        raise InputError(f"bandwidth_per_px must be a positive finite number, got {bandwidth_per_px!r}")
    if order not in (1, 2):
        raise InputError(f"estimator order must be 1 or 2, got {order!r}")
    if discretisation not in DISCRETISATIONS:
        raise InputError(f"discretisation must be one of {DISCRETISATIONS}, got {discretisation!r}")


def _run(bs, a, x: np.ndarray, axis: int):
    """Apply every output filter (b_i, a) along ``axis``, each line starting in steady state at its
    first sample (the state a constant input equal to that sample would have reached)."""
    first = np.take(x, [0], axis=axis)              # keeps dims: the per-line initial level
    outs = []
    for b in bs:
        zi1 = signal.lfilter_zi(b, a)               # steady state for a unit step
        shape = [1] * x.ndim
        shape[axis] = zi1.size
        zi = zi1.reshape(shape) * first
        y, _ = signal.lfilter(b, a, x, axis=axis, zi=zi)
        outs.append(y)
    return outs


def delay_px(bandwidth_per_px: float, order: int) -> float:
    """Low-frequency group delay of the estimator, pixels, along each axis: order / a."""
    return float(order) / float(bandwidth_per_px)


@dataclass
class Derivatives:
    """Estimated irradiance and partial derivatives (per pixel, image units per pixel^k).

    Each array at index (v, u) describes the image at (u - delay_px, v - delay_px).
    Second derivatives are None for order 1."""
    E: np.ndarray
    Ex: np.ndarray
    Ey: np.ndarray
    Exx: np.ndarray | None
    Eyy: np.ndarray | None
    Exy: np.ndarray | None
    delay_px: float
    bandwidth_per_px: float
    order: int


def estimate_derivatives(image, *, bandwidth_per_px: float = 1.0, order: int = 1, bias: float | None = None,
                         discretisation: str = "foh", combine: str = "eq40") -> Derivatives:
    """Run the estimators of eqs. (36)-(39) on ``image`` and combine them by eq. (40).

    image: 2-D array (grey, any linear scale). bias: constant added to the input to keep r1 away from
    zero (eq. 40 note); default ``max(0, -min(E)) + max(1, ptp(E))``: r1 stays at least one image
    range above zero. It is removed from E_hat; with ``combine="eq40"`` it does change dE/dx on
    non-separable images (module docstring).
    """
    E = np.asarray(image)
    if E.ndim != 2 or min(E.shape) < 2:
        raise InputError(f"image must be 2-D with at least 2x2 pixels, got shape {E.shape}")
    E = E.astype(np.float64)
    if not np.all(np.isfinite(E)):
        raise InputError("image has non-finite values")
    _check_params(bandwidth_per_px, order, discretisation)
    if combine not in COMBINES:
        raise InputError(f"combine must be one of {COMBINES}, got {combine!r}")
    if bias is None:
        bias = max(0.0, -float(E.min())) + max(1.0, float(np.ptp(E)))
    if not np.isfinite(bias):
        raise InputError(f"bias must be finite, got {bias!r}")

    bs, a = discrete_filters(float(bandwidth_per_px), int(order), discretisation)
    Eb = E + bias
    # eqs. (36)-(37): along the scan lines (x_p, axis 1). r = e2 [e1_hat, e1_hat', e1_hat'']
    r = _run(bs, a, Eb, axis=1)
    # eqs. (38)-(39): along the columns (y_p, axis 0), input r1 = e1_hat e2. s = e1_hat [e2_hat, e2_hat', ...]
    s = _run(bs, a, r[0], axis=0)
    r1 = r[0]
    if np.any(np.abs(r1) < 1e-9 * max(1.0, abs(bias))):
        raise InputError("r1 of eq. (40) reached zero: increase the bias")
    Ehat = s[0] - bias                               # eq. (40): E_hat = s1 (bias removed)
    if combine == "eq40":
        ratio = s[0] / r1
        Ex = ratio * r[1]                            # eq. (40): dE/dx = s1 r2 / r1
        Exx = ratio * r[2] if order == 2 else None   # eq. (40): d2E/dx2 = s1 r3 / r1
        Exy = r[1] * s[1] / r1 if order == 2 else None   # eq. (40): d2E/dxdy = r2 s2 / r1
    else:
        sx = _run(bs, a, r[1], axis=0)               # column process applied to r2 (and r3)
        Ex = sx[0]
        Exy = sx[1] if order == 2 else None
        Exx = _run(bs[:1], a, r[2], axis=0)[0] if order == 2 else None
    Ey = s[1]                                        # eq. (40): dE/dy = s2
    Eyy = s[2] if order == 2 else None               # eq. (40): d2E/dy2 = s3
    return Derivatives(E=Ehat, Ex=Ex, Ey=Ey, Exx=Exx, Eyy=Eyy, Exy=Exy,
                       delay_px=delay_px(bandwidth_per_px, order),
                       bandwidth_per_px=float(bandwidth_per_px), order=int(order))


def noise_gains(bandwidth_per_px: float, order: int = 1, discretisation: str = "foh", n: int | None = None):
    """Standard deviations of (E_hat, dE/dx, dE/dy) per unit white pixel noise, from the impulse
    responses of the separable estimator (linearised eq. 40: x-derivative = column low-pass of r2).

    Returns (gain_E, gain_dx, gain_dy)."""
    bs, a = discrete_filters(float(bandwidth_per_px), int(order), discretisation)
    if n is None:
        n = int(60.0 * order / bandwidth_per_px) + 64
    imp = np.zeros(n)
    imp[0] = 1.0
    h_lp = signal.lfilter(bs[0], a, imp)
    h_d = signal.lfilter(bs[1], a, imp)
    e_lp = float(np.sqrt(np.sum(h_lp ** 2)))
    e_d = float(np.sqrt(np.sum(h_d ** 2)))
    return e_lp * e_lp, e_d * e_lp, e_lp * e_d
