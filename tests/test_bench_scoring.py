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



def test_scale_line_is_the_median_range_over_the_reference():
    # reference 10, 20, 40, 80 m (the last pixel not scored); dense ranges 11, 22, 44 and 0 m (no range): x1.100;
    # dis 5, 10, 20 m: x0.500 (a reversed ratio would say x0.909 and x2.000)
    from types import SimpleNamespace

    from eonav.app.bench_locate import scale_line
    truth = np.array([[10.0, 20.0, 40.0, 80.0]])
    case = SimpleNamespace(truth_m=truth, mask=np.array([[True, True, True, False]]))
    per = {"dense": SimpleNamespace(range_m=np.array([[11.0, 22.0, 44.0, 0.0]])),
           "dis": SimpleNamespace(range_m=np.array([[5.0, 10.0, 20.0, 40.0]]))}
    assert scale_line(case, per) == "   median range / reference: dense x1.100, dis x0.500"


def test_common_pixel_line_scores_the_pixels_every_method_ranges_against_the_truth():
    # truth 10 m on five pixels and a sky pixel both methods range (not scored); dense ranges pixels 0-3, dis 1-4:
    # the common ones are 1-3, dense 11, 11, 12 m (10, 10, 20 %: median 10 %), dis 8, 8, 9 m (20, 20, 10 %: 20 %);
    # relative to the estimate they would read 9.09 % and 25 %
    from types import SimpleNamespace

    from eonav.app.bench_locate import common_pixel_line
    truth = np.array([[10.0, 10.0, 10.0, 10.0, 10.0, np.inf]])
    case = SimpleNamespace(truth_m=truth, mask=np.ones(truth.shape, bool))
    per = {"dense": SimpleNamespace(range_m=np.array([[13.0, 11.0, 11.0, 12.0, np.nan, 500.0]])),
           "dis": SimpleNamespace(range_m=np.array([[0.0, 8.0, 8.0, 9.0, 30.0, 500.0]]))}
    assert common_pixel_line(case, per) == "   same 3 pixels for dense and dis: dense 10.00 %, dis 20.00 %"
    assert common_pixel_line(case, {"dense": per["dense"]}) is None          # a method missing: no line

# --- bench fuse: its error / coverage, the widest partner and the target lines ----------------------------------

def test_fuse_errors_leave_zero_and_negative_ranges_uncovered():
    # four pixels with truth 10 m: 11 m (+10 %), 0 m, -5 m, none: only the first has a range (coverage 1/4, error
    # 10 %); counting 0 and -5 m as ranges would report 3/4 at a median error of 100 %
    from eonav.app.bench_fuse import errors
    e, c = errors(np.array([[11.0, 0.0, -5.0, np.nan]]), np.full((1, 4), 10.0), np.ones((1, 4), bool))
    assert np.isclose(e, 0.10) and c == 0.25
    e, c = errors(np.array([[11.0, 0.0]]), np.full((1, 2), 10.0), np.zeros((1, 2), bool))   # nothing scored
    assert np.isnan(e) and c == 0.0


def test_widest_partner_takes_the_longest_baseline_within_age_and_rotation():
    # frame 4 at t 1.0 s, north 5 m, level; candidates (policy: max_age_s 1, max_rotation_deg 10):
    #   0: t -0.05 s (1.05 s old), north -20 m: too old
    #   1: t  0.0 s (exactly 1 s old: accepted), north 1.5 m: 3.5 m baseline, 0 deg
    #   2: t  0.5 s, north 0 m, yawed 15 deg: 5 m but rotated beyond 10 deg (0.26 rad: not a limit in radians)
    #   3: t  0.9 s, north 3 m, yawed 9 deg: 2 m
    from eonav.app.bench_fuse import widest_partner
    from eonav.fusion.sequence import FusionConfig
    from eonav.geometry.camera import Camera, VehicleState, View
    cfg = FusionConfig()
    assert (cfg.schedule.policy.max_age_s, cfg.schedule.policy.max_rotation_deg) == (1.0, 10.0)
    cam = Camera("c", 8, 8, 10.0, 10.0, 3.5, 3.5)
    img = np.zeros((8, 8), np.float32)
    poses = [(-0.05, -20.0, 0.0), (0.0, 1.5, 0.0), (0.5, 0.0, 15.0), (0.9, 3.0, 9.0), (1.0, 5.0, 0.0)]
    views = [View(cam, VehicleState.from_ypr([n, 0.0, -10.0], [np.radians(yaw), 0.0, 0.0], t), img)
             for t, n, yaw in poses]
    assert widest_partner(views, 4, cfg) == 1
    assert widest_partner(views[1:], 3, cfg) == 0          # the same frames without the old one
    assert widest_partner(views[2:], 2, cfg) == 1          # without frame 1: frame 3, the one within 10 deg
    assert widest_partner(views[2:3] + views[4:], 1, cfg) is None      # only the turned frame: none


def _fuse_summary(fused_err, dense_err, coverage=0.96, z=1.0):
    return {10: {"fused": (fused_err, coverage), "dense newest": (dense_err, 0.9), "z": z, "z_filled": 1.1}}


def test_fuse_targets_ratio_coverage_z_and_time_verdicts(capsys):
    # after 10 frames: fused 2 % against dense 5 % is 0.40 x (<= 0.5: met); 3 % against 5 % 0.60 x (NOT met);
    # exactly 0.5 x, 95 % coverage, z 1.2, 3 % Table I error and +30 % time are on their limits: met
    from eonav.app.bench_fuse import print_targets
    print_targets({"good": _fuse_summary(0.02, 0.05), "worse": _fuse_summary(0.03, 0.05, coverage=0.94, z=1.25),
                   "edge": {**_fuse_summary(0.025, 0.05, coverage=0.95, z=1.2), "table1_max_error": 0.03,
                            "time_added": 0.30},
                   "late": {"table1_max_error": 0.031, "time_added": 0.31}})
    lines = [ln.strip() for ln in capsys.readouterr().out.splitlines()]
    good, worse, edge = (next(ln for ln in lines if ln.startswith(f"{n}: after 10 frames")) for n in
                         ("good", "worse", "edge"))
    assert "= 0.40 x single-pair dense 5.00 % (<= 0.5) -> met;" in good
    assert "coverage 96.0 % (>= 95 %) -> met" in good and "z spread 1.00 (0.8-1.2) -> met" in good
    assert "= 0.60 x single-pair dense 5.00 % (<= 0.5) -> NOT met;" in worse
    assert "(>= 95 %) -> NOT met" in worse and "(0.8-1.2) -> NOT met" in worse
    assert "= 0.50 x" in edge and "(<= 0.5) -> met;" in edge and "(>= 95 %) -> met" in edge
    assert "(0.8-1.2) -> met" in edge
    tab = [ln for ln in lines if "every Table I vehicle" in ln]
    tim = [ln for ln in lines if "to the locator's time" in ln]
    assert [ln.split("-> ")[-1] for ln in tab] == ["met", "NOT met"]
    assert [ln.split("-> ")[-1] for ln in tim] == ["met", "NOT met"]



def test_fuse_z_spread_counts_only_the_pixels_with_the_flag():
    # truth 10 m, sigma 0.001 /m: 10 VALID pixels with z = -2, -1, -1, 0, 0, 0, 0, 1, 1, 2 (median 0, MAD 1: spread
    # 1.4826) and 10 FILLED ones at z = -10, +10 (MAD 10: 14.826). Mixing them would report the VALID spread as
    # 1.4826 x 6; fewer than 10 pixels with the flag: NaN
    from eonav.app.bench_fuse import z_spread
    from eonav.ranging.rangemap import FILLED, VALID
    z = np.array([[-2.0, -1.0, -1.0, 0.0, 0.0, 0.0, 0.0, 1.0, 1.0, 2.0] + [-10.0, 10.0] * 5])
    res = _result(0.1 + 0.001 * z, np.full(z.shape, 0.001))
    res.flags[:, :10], res.flags[:, 10:] = VALID, FILLED
    truth, mask = np.full(z.shape, 10.0), np.ones(z.shape, bool)
    assert np.isclose(z_spread(res, truth, mask), 1.4826, rtol=1e-3)
    assert np.isclose(z_spread(res, truth, mask, FILLED), 14.826, rtol=1e-3)
    mask[0, 0] = False
    assert np.isnan(z_spread(res, truth, mask))


def _real_row(fused, dense_newest, dense_widest, dis_newest, dis_widest):
    return {"fused": fused, "dense newest": dense_newest, "dense widest": dense_widest, "DIS newest": dis_newest,
            "DIS widest": dis_widest}


def test_fuse_targets_of_a_real_sequence_judge_its_last_frame(capsys):
    # frames 1 and 5 scored: the line is frame 5's. "a": fused 2 % beats DIS widest 3 % and DIS newest 4 % (met) but
    # not the better dense pair (newest 1.5 %, widest 2.5 %: NOT met, though it beats the worse one). "b": DIS widest
    # gave no output and the fused map covers 80 % (met); it beats every pair
    from eonav.app.bench_fuse import print_targets
    nan = float("nan")
    first = _real_row((0.30, 0.10), (0.01, 0.5), (0.01, 0.5), (0.01, 0.5), (0.01, 0.5))     # frame 1: all NOT met
    print_targets({"real:a": {1: first, 5: _real_row((0.02, 0.90), (0.015, 0.9), (0.025, 0.9), (0.04, 0.7),
                                                     (0.03, 0.6)), "time_added": 0.1},
                   "real:b": {1: first, 5: _real_row((0.02, 0.80), (0.05, 0.9), (0.06, 0.9), (0.04, 0.7),
                                                     (nan, 0.0))}})
    lines = [ln.strip() for ln in capsys.readouterr().out.splitlines()]
    a, b = (next(ln for ln in lines if ln.startswith(f"real:{n}: last frame")) for n in "ab")
    assert a.startswith("real:a: last frame fused 2.00 % over 90.0 % vs DIS widest 3.00 % -> met;")
    assert "vs DIS newest 4.00 % over 70.0 % -> met;" in a
    assert a.endswith("vs dense newest 1.50 % / widest 2.50 % -> NOT met")
    assert b.startswith("real:b: last frame fused 2.00 % over 80.0 % vs DIS widest no output (above) -> met;")
    assert b.endswith("vs dense newest 5.00 % / widest 6.00 % -> met")

# --- bench pipeline: one measured frame's timeline --------------------------------------------------------------

def test_pipeline_frame_row_is_in_milliseconds_from_capture():
    # captured at 1 000 000 us; the map (compute 30.1 ms, put at age 40.2 ms) received at 1 045 000 us, the obstacle
    # list (put at age 75.5 ms) at 1 080 000 us: [40.2, 45.0, 75.5, 80.0, 30.1] ms; what did not arrive is None
    from eonav.app.bench_pipeline import _frame_row
    m = (1_045_000, 0.0301, 0.002, 1.0, 40.2)
    o = (1_080_000, 75.5)
    assert _frame_row(1_000_000, m, o) == [40.2, 45.0, 75.5, 80.0, 30.1]
    assert _frame_row(1_000_000, m, None) == [40.2, 45.0, None, None, 30.1]
    assert _frame_row(1_000_000, None, None) == [None] * 5
