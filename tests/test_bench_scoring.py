"""The benchmark's scoring functions against hand-derived values (figures are only as good as these)."""
from __future__ import annotations

import numpy as np

from eonav.app.bench_locate import calibration, score
from eonav.ranging.rangemap import RangeResult


def _result(rho, std):
    rho = np.asarray(rho, np.float32)
    with np.errstate(divide="ignore"):
        rng = np.where(rho > 0, 1.0 / rho, np.nan).astype(np.float32)
    return RangeResult(range_m=rng, confidence=np.zeros_like(rho), method="t", inv_range_per_m=rho,
                       inv_range_std_per_m=np.asarray(std, np.float32), flags=np.zeros(rho.shape, np.uint8),
                       info={})


def test_score_counts_coverage_and_errors_by_hand():
    truth = np.array([[10.0, 10.0, 20.0, np.inf]])
    est = np.array([[11.0, np.nan, 19.0, 5.0]])          # +10 %, none, -5 %, sky pixel (not scored)
    mask = np.isfinite(truth)
    measurable = np.array([[True, True, False, False]])
    s = score(est, truth, mask, measurable)
    assert np.isclose(s["median_rel_error"], 0.075)       # median of 0.10 and 0.05
    assert np.isclose(s["coverage"], 2 / 3)
    assert np.isclose(s["within_5pct_of_scored"], 0.0)    # 0.05 is not < 0.05
    assert np.isclose(s["coverage_of_measurable"], 1 / 2)  # of the 2 measurable pixels, 1 estimated


def test_calibration_of_known_z_scores():
    truth = np.full((1, 8), 10.0)
    sigma = np.full((1, 8), 0.001)
    z = np.array([[-3.0, -1.0, -0.5, 0.0, 0.0, 0.5, 1.0, 3.0]])
    res = _result(0.1 + z * 0.001, sigma)
    c = calibration(res, truth, np.ones_like(truth, bool))
    # |z - median| = 3, 1, .5, 0, 0, .5, 1, 3 -> median 0.75 -> spread 1.4826 * 0.75
    assert np.isclose(c["z_spread"], 1.4826 * 0.75, rtol=1e-3)
    assert np.isclose(c["within_2_sigma"], 6 / 8)
