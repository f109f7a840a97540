"""The FILLED pixels' sigma (eonav.ranging.methods.fill) against synthetic surfaces of known inverse range: a plane
measured with white noise, and the same plane carrying bumps (surface structure the holes share). The fill's
variance is the plane's residual (scatter of the cell means about it) as one more sample's, plus the disagreement
across scales: honest where the residual is the surface's structure, large (the safe side) where it is only
measurement noise, which a hole without a measurement does not carry. Both are asserted, so neither a smaller nor
a larger overall scale passes both."""
import numpy as np
import pytest

from eonav.ranging.methods.fill import fill_unmeasured
from eonav.ranging.rangemap import FILLED, LOW_TEXTURE, VALID

H, W = 240, 320
F_PX, CX, CY = 300.0, 159.5, 119.5
V, U = np.mgrid[0:H, 0:W].astype(np.float64)
XN, YN = (U - CX) / F_PX, (V - CY) / F_PX
# ground 20 m below, pitched down: rho = (n1 + n2 x_n + n3 y_n) / d (fill.py's module docstring)
PLANE = (0.3 + 0.05 * XN + 0.9 * YN) / 20.0


def bumps(amp: float, wavelength_px: float) -> np.ndarray:
    """The plane's rho with a relative bump pattern of amplitude amp (egg-crate: sin x sin, wavelength_px across)."""
    return PLANE * (1 + amp * np.sin(2 * np.pi * U / wavelength_px) * np.sin(2 * np.pi * V / (0.8 * wavelength_px)))


def holes(seed: int = 5) -> np.ndarray:
    """40 textureless rectangles of 4-13 px sides at seeded places."""
    m = np.zeros((H, W), bool)
    rng = np.random.default_rng(seed)
    for _ in range(40):
        y, x = rng.integers(10, H - 30), rng.integers(10, W - 30)
        hh, ww = rng.integers(4, 14, 2)
        m[y:y + hh, x:x + ww] = True
    return m


def robust_spread(z: np.ndarray) -> float:
    return float(1.4826 * np.median(np.abs(z - np.median(z))))


def fill_surface(true_rho: np.ndarray, noise_rel: float, seed: int = 0):
    """The surface measured with white noise of relative sigma noise_rel (the sigma reported honestly), holes()
    unmeasured (LOW_TEXTURE), filled: (hole mask, FILLED mask, rho, sigma)."""
    rng = np.random.default_rng(seed)
    hole = holes()
    rho = (true_rho * (1 + noise_rel * rng.standard_normal(true_rho.shape))).astype(np.float32)
    rho[hole] = np.nan
    std = (noise_rel * true_rho).astype(np.float32)
    flags = np.where(hole, LOW_TEXTURE, VALID).astype(np.uint8)
    rng_m = np.where(hole, np.nan, 1 / rho).astype(np.float32)
    conf = (rho / std).astype(np.float32)
    fill_unmeasured(rho, std, flags, rng_m, conf, max_rel_std=0.34)
    return hole, (flags & FILLED) != 0, rho, std


def z_of(true_rho, filled, rho, std) -> np.ndarray:
    return (rho[filled] - true_rho[filled]) / std[filled]


@pytest.mark.parametrize("noise_rel", [0.002, 0.03])
def test_on_a_noisy_plane_the_filled_sigma_errs_large_but_within_bounds(noise_rel):
    """A plane with white noise: the holes are filled with the plane (error ~ the noise / 28: the plane averages
    ~49 cell means of 16 pixels), the sigma is a cell mean's noise (noise / 4): z spread ~0.15, never
    over-confident (every pixel within 2 sigma, z spread under the honest band's top, 1.2), yet not a sigma made
    large for safety's sake (z spread > 0.05: the sigma under 20 x the error)."""
    hole, filled, rho, std = fill_surface(PLANE, noise_rel)
    assert filled.sum() > 0.95 * hole.sum()
    z = z_of(PLANE, filled, rho, std)
    assert np.mean(np.abs(z) < 2) > 0.999
    assert 0.05 < robust_spread(z) < 1.2, robust_spread(z)          # measured 0.14-0.15
    rel_err = np.median(np.abs(rho[filled] / PLANE[filled] - 1))
    assert rel_err < 0.1 * noise_rel                                # measured 0.028 x the noise
    rel_sig = np.median(std[filled] / rho[filled])
    assert 0.2 * noise_rel < rel_sig < 0.35 * noise_rel             # measured 0.27 x: noise / sqrt(16) + fit


@pytest.mark.parametrize("amp, wavelength_px", [(0.01, 24), (0.03, 24), (0.03, 48)])
def test_on_a_bumpy_surface_the_filled_sigma_is_honest(amp, wavelength_px):
    """Bumps of 1-3 % over 24-48 px (6-12 cells) with 0.2 % noise: a hole's truth leaves the window's plane by
    as much as the measured cells do, which the residual reports: z spread 0.8-1.3 and the error ~10 x the noisy
    plane's, so a sigma scaled down to make the plane's honest (1/7 of it) fails here."""
    true_rho = bumps(amp, wavelength_px)
    hole, filled, rho, std = fill_surface(true_rho, 0.002)
    assert filled.sum() > 0.95 * hole.sum()
    z = z_of(true_rho, filled, rho, std)
    assert 0.8 < robust_spread(z) < 1.3, robust_spread(z)           # measured 1.01-1.10
    assert np.mean(np.abs(z) < 2) > 0.85                            # measured 0.89-0.98
    assert np.median(np.abs(rho[filled] / true_rho[filled] - 1)) > 0.25 * amp   # measured 0.31-0.35 x amp


def test_bumps_finer_than_the_window_are_under_reported():
    """The known limit, both sides of it: bumps of 12 px (3 cells) vary inside a cell and between neighbouring
    cells, more than the cell means' scatter about the window's plane says: z spread ~1.7 (over-confident), where
    the same amplitude at 24 px is honest (test above)."""
    for wavelength_px, lo, hi in ((12, 1.4, 2.0), (24, 0.8, 1.3)):
        true_rho = bumps(0.03, wavelength_px)
        _, filled, rho, std = fill_surface(true_rho, 0.002)
        s = robust_spread(z_of(true_rho, filled, rho, std))
        assert lo < s < hi, (wavelength_px, s)
