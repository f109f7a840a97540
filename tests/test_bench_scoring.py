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


def test_coverage_of_measurable_counts_only_the_scored_measurable_pixels():
    # a measurable pixel that is not scored (sky: no truth) is in neither count: of the 2 scored measurable pixels
    # both are estimated (1.0); dividing by every measurable pixel would say 2 / 3
    truth = np.array([[10.0, 10.0, 20.0, np.inf]])
    est = np.array([[11.0, np.nan, 19.0, 5.0]])
    measurable = np.array([[True, False, True, True]])
    s = score(est, truth, np.isfinite(truth), measurable)
    assert s["coverage_of_measurable"] == 1.0 and np.isclose(s["coverage"], 2 / 3)


def test_robust_spread_is_the_deviation_about_the_median():
    # z = 4, 5, 5, 6, 10: median 5, |z - 5| = 1, 0, 0, 1, 5 -> MAD 1 -> 1.4826; a bias (median z 5) is not a spread
    from eonav.app.bench_locate import robust_spread
    assert np.isclose(robust_spread([4.0, 5.0, 5.0, 6.0, 10.0]), 1.4826)
    assert np.isclose(robust_spread([-1.0, 0.0, 0.0, 1.0, 5.0]), 1.4826)      # the same spread, unbiased


def test_z_by_range_puts_a_pixel_on_a_bin_edge_in_the_upper_bin_only():
    # truths 29, 29, 29, 30, 30, 60 m with z = -1, 0, 2, -4, 4, 1 (sigma 0.001 /m): bins [0, 30), [30, 60), [60, inf)
    # hold 3, 2 and 1 pixels; [0, 30): spread 1.4826 (|z - 0| = 1, 0, 2 -> MAD 1), median 0, none beyond 3;
    # [30, 60): median 0, |z - 0| = 4, 4 -> spread 4 x 1.4826, both beyond 3; a pixel without VALID is not counted
    from eonav.app.bench_locate import z_by_range
    from eonav.ranging.rangemap import VALID
    truth = np.array([[29.0, 29.0, 29.0, 30.0, 30.0, 60.0, 45.0]])
    z = np.array([[-1.0, 0.0, 2.0, -4.0, 4.0, 1.0, 0.0]])
    res = _result(1.0 / truth + 0.001 * z, np.full(truth.shape, 0.001))
    res.flags[:] = VALID
    res.flags[0, 6] = 0
    rows = z_by_range(res, truth, np.ones(truth.shape, bool), bins=(0.0, 30.0, 60.0, np.inf), min_pixels=1)
    assert [(lo, hi, n) for lo, hi, n, *_ in rows] == [(0.0, 30.0, 3), (30.0, 60.0, 2), (60.0, np.inf, 1)]
    (_, _, _, s0, m0, f0), (_, _, _, s1, m1, f1), (_, _, _, s2, m2, f2) = rows
    assert np.isclose(s0, 1.4826, rtol=1e-3) and abs(m0) < 1e-3 and f0 == 0.0
    assert np.isclose(s1, 4 * 1.4826, rtol=1e-3) and abs(m1) < 1e-3 and f1 == 1.0
    assert s2 == 0.0 and np.isclose(m2, 1.0, rtol=1e-3) and f2 == 0.0
    # under min_pixels: counted, figures NaN
    lo, hi, n, sp, med, f3 = z_by_range(res, truth, np.ones(truth.shape, bool), bins=(0.0, 30.0), min_pixels=4)[0]
    assert n == 3 and np.isnan(sp) and np.isnan(med) and np.isnan(f3)


def test_table_one_rows_give_the_error_relative_to_the_actual_range():
    # object 2 (vehicle1) at 100 m estimated 80 m on 3 of its 4 pixels: -20 % of the actual range (not of the
    # estimate: 25 %); object 3 at 40 m ranged 42 m: 5 %; ids 0 and 1 (sky, ground) and an object out of view: no row
    from types import SimpleNamespace

    from eonav.app.bench_locate import object_rows
    oid = np.array([[2, 2, 2, 2, 3, 3, 1, 0]])
    truth = np.array([[100.0, 100.0, 100.0, 100.0, 40.0, 40.0, 20.0, np.inf]])
    rng = np.array([[80.0, 80.0, 80.0, np.nan, 42.0, 42.0, 20.0, 1.0]])
    case = SimpleNamespace(objects={0: "sky", 1: "ground", 2: "vehicle1", 3: "vehicle2", 4: "vehicle3"},
                           object_id=oid, truth_m=truth)
    rows = object_rows(case, rng)
    assert [(n, a, e, c) for n, a, e, _, c in rows] == [("vehicle1", 100.0, 80.0, 3), ("vehicle2", 40.0, 42.0, 2)]
    assert np.isclose(rows[0][3], 0.20) and np.isclose(rows[1][3], 0.05)

