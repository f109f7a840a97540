"""The pair checks of the fusion's measurement: sparse tracks, the pose error they show (eonav.ranging.tracks), the
affine brightness fit (eonav.ranging.photometric) and the pose term of the sigma (eonav.fusion.measure), against
synthetic pairs of known geometry and brightness, and the real HoloLens sequence's one inconsistent pose."""
import math
from dataclasses import replace
from types import SimpleNamespace

import cv2
import numpy as np
import pytest
from scipy.stats import norm

from eonav import InputError
from eonav.fusion.measure import add_pose_sigma, checked_dense
from eonav.geometry.camera import Camera, VehicleState, View, pair_geometry
from eonav.ranging.methods.dense import _plane_pair, locate_dense
from eonav.ranging.photometric import fit_brightness, match_brightness
from eonav.ranging.rangemap import VALID
from eonav.ranging.tracks import Tracks, epipolar_residual_px, pose_shift_px, track_points, tukey_weights


def texture(h, w, seed=0):
    rng = np.random.default_rng(seed)
    t = cv2.GaussianBlur(rng.standard_normal((h, w)).astype(np.float32), (0, 0), 2.0)
    return (t / t.std() * 35.0 + 120.0).astype(np.float32)


@pytest.mark.parametrize("shape", [(240, 320), (400, 720)])     # full-size tracking and on a coarser level
def test_tracks_of_a_known_shift(shape):
    img = texture(*shape)
    M = np.float32([[1, 0, 3.4], [0, 1, -2.2]])                  # b(x + 3.4, y - 2.2) = a(x, y)
    b = cv2.warpAffine(img, M, (shape[1], shape[0]), flags=cv2.INTER_LINEAR, borderMode=cv2.BORDER_REFLECT)
    tr = track_points(img, b)
    assert len(tr) >= 50
    d = tr.pts_b - tr.pts_a
    assert np.allclose(np.median(d, axis=0), [3.4, -2.2], atol=0.1)


def test_epipolar_distance_by_hand():
    # camera b 0.5 m to the right (paper frame y right), no rotation: epipolar lines are the rows, the normal is
    # +-v, a match's distance from its line is its row offset; moving along the row (another depth) changes nothing
    cam = Camera("c", 100, 80, 100.0, 100.0, 49.5, 39.5)
    a = View(cam, VehicleState.from_ypr([0, 0, 0], [0, 0, 0]), np.zeros((80, 100), np.float32))
    b = View(cam, VehicleState.from_ypr([0, 0.5, 0], [0, 0, 0]), np.zeros((80, 100), np.float32))
    geo = pair_geometry(a, b)
    pa = np.float32([[10, 20], [60, 50], [80, 10]])
    pb = pa + np.float32([[-5, 0], [-20, 0.7], [-1, -0.3]])
    d, n = epipolar_residual_px(geo, Tracks(pa, pb))
    assert np.allclose(np.abs(d), [0, 0.7, 0.3], atol=1e-4)
    assert np.allclose(np.abs(n[:, 1]), 1.0) and np.allclose(n[:, 0], 0.0, atol=1e-6)


def _rotated(view, yaw_deg):
    st = view.state
    R = cv2.Rodrigues(np.array([0.0, 0.0, np.radians(yaw_deg)]))[0]      # about body z (down): a yaw
    return replace(view, state=VehicleState(st.position_ned_m, R @ st.T_body_ned, st.t_s))


def test_pose_shift_of_exact_and_of_rotated_poses():
    # the plane pair's poses are exact: the shift is the tracks' noise only; a yaw error of delta moves every point
    # of b by about f delta across the image, and the shift finds it, with the truth on either side of it
    va, vb = _plane_pair(192)
    f = va.camera.fx
    tr = track_points(va.image, vb.image)
    exact = pose_shift_px(pair_geometry(va, vb), tr)
    assert exact < 0.1
    for yaw_deg in (0.4, -0.8):
        expect = f * np.radians(abs(yaw_deg))
        got = pose_shift_px(pair_geometry(va, _rotated(vb, yaw_deg)), tr)
        assert 0.85 * expect < got < 1.15 * expect, (yaw_deg, got, expect)


def test_pose_shift_needs_enough_tracks():
    va, vb = _plane_pair(96)
    tr = track_points(va.image, vb.image)
    few = Tracks(tr.pts_a[:10], tr.pts_b[:10])
    assert np.isnan(pose_shift_px(pair_geometry(va, vb), few))
    assert np.isnan(pose_shift_px(pair_geometry(va, vb), Tracks(np.zeros((0, 2)), np.zeros((0, 2)))))


def _gain_pair(gain, offset, shape=(240, 320)):
    # I_a = gain I_b + offset, b also shifted by (3, 2) px (whole pixels: no interpolation blur) and with unit noise
    a = texture(*shape)
    M = np.float32([[1, 0, 3.0], [0, 1, 2.0]])
    b = cv2.warpAffine(a, M, (shape[1], shape[0]), flags=cv2.INTER_LINEAR, borderMode=cv2.BORDER_REFLECT)
    rng = np.random.default_rng(1)
    b = (b - offset) / gain + rng.standard_normal(shape).astype(np.float32)
    return a, b.astype(np.float32)


def test_brightness_fit_recovers_a_known_gain_and_offset():
    a, b = _gain_pair(1.2, -15.0)
    fit = fit_brightness(a, b)
    assert fit.used and fit.reason == "ok"
    assert abs(fit.gain - 1.2) < 0.02 and abs(fit.offset + 15.0) < 2.0


def test_brightness_change_below_and_above_min_change():
    # an offset of 1 grey level is left alone (below min_change = 2), one of 4 is corrected
    a, b = _gain_pair(1.0, 1.0)
    assert not fit_brightness(a, b).used
    a, b = _gain_pair(1.0, 4.0)
    fit = fit_brightness(a, b)
    assert fit.used and abs(fit.gain * 120.0 + fit.offset - 124.0) < 0.6     # the change at the mean grey 120


def test_brightness_gain_beyond_max_gain_ratio_is_not_trusted():
    a, b = _gain_pair(1.3, 0.0)
    assert fit_brightness(a, b, max_gain_ratio=1.5).used
    fit = fit_brightness(a, b, max_gain_ratio=1.2)
    assert not fit.used and "outside" in fit.reason


def _block_pair(values_b, gain, offset, block=16):
    """Image b of constant block x block squares (row-major ``values_b``, 15 x 20 of them), image a = gain b + offset,
    and tracks at the block centres: every window mean at a point is its block's value, so the fit's data are known
    exactly."""
    vb = np.asarray(values_b, np.float32).reshape(15, 20)
    b = np.kron(vb, np.ones((block, block), np.float32))
    a = (np.float32(gain) * b + np.float32(offset)).astype(np.float32)
    y, x = np.mgrid[0:15, 0:20] * block + block // 2
    pts = np.stack([x.ravel(), y.ravel()], 1).astype(np.float32)
    return a, b, Tracks(pts, pts.copy())


def test_brightness_gain_below_one_over_max_gain_ratio_is_not_trusted():
    """A darkening gain is bounded as a brightening one is: with max_gain_ratio 1.5 the gains 0.70 and 1.45 are
    fitted exactly and applied, 0.60 (< 1 / 1.5) and 1.60 are not."""
    vals = np.random.default_rng(6).uniform(60.0, 200.0, 300)
    for gain, used in ((0.70, True), (1.45, True), (0.60, False), (1.60, False)):
        fit = fit_brightness(*_block_pair(vals, gain, 10.0), max_gain_ratio=1.5)
        assert fit.gain == pytest.approx(gain, abs=1e-4) and fit.offset == pytest.approx(10.0, abs=0.02)
        assert fit.used == used, (gain, fit)
        assert used or "outside [1/1.5, 1.5]" in fit.reason


def test_brightness_spread_threshold_is_the_robust_sigma():
    """min_spread compares the points' robust spread in b, 1.4826 MAD: b's blocks half at 100 - s, half at 100 + s
    have median 100 and MAD s. s = 6 spreads 8.9 grey levels (>= 8: fitted, gain 1.25 found); s = 5 spreads 7.4
    (< 8: not fitted)."""
    for s, used in ((6.0, True), (5.0, False)):
        vals = np.where(np.arange(300) % 2 == 0, 100.0 - s, 100.0 + s)
        fit = fit_brightness(*_block_pair(vals, 1.25, -20.0), min_spread=8.0)
        assert fit.used == used, (s, fit)
        if used:
            assert fit.gain == pytest.approx(1.25, abs=1e-3) and fit.offset == pytest.approx(-20.0, abs=0.1)
        else:
            assert "brightness spread of the points below 8" in fit.reason


def test_brightness_fit_drops_occluded_points():
    """A bright object (250 grey levels) covers 60 of the 300 blocks in image a only, the occlusion the biweight is
    there for: the fit finds the other 240 blocks' exact gain 1.2 and offset -10 (a plain least-squares fit through
    all 300 is pulled towards the occluder). Catches a planted single pass of the IRLS loop (no reweighting)."""
    vals = np.random.default_rng(7).uniform(60.0, 200.0, 300)
    a, b, tr = _block_pair(vals, 1.2, -10.0)
    for k in np.random.default_rng(8).choice(300, 60, replace=False):
        r, c = divmod(int(k), 20)
        a[16 * r:16 * (r + 1), 16 * c:16 * (c + 1)] = 250.0
    fit = fit_brightness(a, b, tr)
    assert fit.used and fit.gain == pytest.approx(1.2, abs=1e-4) and fit.offset == pytest.approx(-10.0, abs=0.02)


def test_brightness_change_is_judged_at_both_ends_of_the_points_brightness():
    """min_change takes the larger change at the points' 10th and 90th percentile of b: with b's blocks half at 80,
    half at 180, the gain 0.9 and offset 18 leave 180 unchanged but darken 80 by 10 grey levels, and the gain 1.1 and
    offset -8 leave 80 unchanged but brighten 180 by 10: both are applied. Catches a planted change judged at one
    end only (the 90th percentile: the first pair, a real change, would not be corrected)."""
    vals = np.where(np.arange(300) % 2 == 0, 80.0, 180.0)
    for gain, offset in ((0.9, 18.0), (1.1, -8.0)):
        fit = fit_brightness(*_block_pair(vals, gain, offset))
        assert fit.used and fit.reason == "ok", (gain, fit)
        assert fit.gain == pytest.approx(gain, abs=1e-4) and fit.offset == pytest.approx(offset, abs=0.02)


def test_brightness_fit_with_exactly_min_points_tracks():
    """min_points is the least number of tracks a fit takes: 30 of the block pair's tracks with min_points = 30 are
    fitted (gain 1.2, offset -10 exactly), 29 are not. Catches a planted <= for < in the track count."""
    a, b, tr = _block_pair(np.random.default_rng(6).uniform(60.0, 200.0, 300), 1.2, -10.0)
    fit = fit_brightness(a, b, Tracks(tr.pts_a[:30], tr.pts_b[:30]), min_points=30)
    assert fit.used and fit.n_points == 30 and fit.gain == pytest.approx(1.2, abs=1e-4)
    fit = fit_brightness(a, b, Tracks(tr.pts_a[:29], tr.pts_b[:29]), min_points=30)
    assert not fit.used and fit.reason == "29 tracked points (< 30)"


def test_brightness_fit_through_the_memo_of_box_means_is_the_direct_fit():
    """Along a stream of gain-changed frames (each fitted against the one before) the memo blurs each image once
    and the fits are the direct ones exactly; the match's image b is gain * b + offset in float32."""
    from eonav.ranging.photometric import RecentMeans
    a, _ = _gain_pair(1.0, 0.0)
    frames = [(a * np.float32(g) + np.float32(o)).astype(np.float32) for g, o in ((1.0, 0), (1.1, -5), (1.25, -20))]
    memo = RecentMeans(4)
    for k in (1, 2):
        tr = track_points(frames[k], frames[k - 1])
        assert fit_brightness(frames[k], frames[k - 1], tr, means=memo) == fit_brightness(frames[k], frames[k - 1], tr)
    assert memo.hits == 1                           # frame 1 blurred once, as image a and then as image b
    va, vb = _plane_pair(192)
    bright = replace(vb, image=vb.image * np.float32(1.3) + np.float32(4.0))
    vb2, fit = match_brightness(va, bright)
    assert fit.used
    want = bright.image.astype(np.float32) * np.float32(fit.gain) + np.float32(fit.offset)
    assert vb2.image.dtype == np.float32 and np.array_equal(vb2.image, want)


def test_brightness_of_a_flat_pair_and_bad_input():
    flat = np.full((120, 160), 100.0, np.float32)
    fit = fit_brightness(flat, flat)
    assert not fit.used and "tracked points" in fit.reason
    with pytest.raises(InputError):
        fit_brightness(np.zeros((4, 4, 3), np.float32), flat)


def test_match_brightness_and_dense_on_a_gain_changed_pair():
    # the plane pair (wall at 20 m) with image b darkened by a gain of 0.75: the dense method's VALID error
    # against the wall's truth and its coverage are better after the match than without it
    va, vb = _plane_pair(192)
    dark = replace(vb, image=(vb.image - 128.0) * np.float32(0.75) + np.float32(100.0))
    vb2, fit = match_brightness(va, dark)
    # the wall's fine texture spreads the window means little against the noise: the fit is attenuated (1.26 for
    # 1.33), still most of the change
    assert fit.used and 1.2 < fit.gain < 1 / 0.75 + 0.02
    assert np.median(np.abs(vb2.image - vb.image)) < 0.5 * np.median(np.abs(dark.image - vb.image))
    truth = 20.0

    def err(res):
        ok = (res.flags & VALID) != 0
        return float(np.median(np.abs(res.range_m[ok] - truth) / truth)), float(ok.mean())
    e_ref, _ = err(locate_dense(va, vb, fill=False))
    e_dark, c_dark = err(locate_dense(va, dark, fill=False))
    e_fixed, c_fixed = err(checked_dense(va, dark, pose_sigma=False))
    assert e_fixed < e_dark and c_fixed > c_dark + 0.2          # measured: 1.7 % over 56 % -> 1.1 % over 89 %
    assert e_fixed - e_ref < e_dark - e_fixed                    # nearer the unchanged pair's 0.7 % than the dark one's


def test_checked_dense_adds_the_pose_term_of_the_pair_from_a_to_b():
    """checked_dense's pose term on the pair's own geometry, a to b. The plane pair: b 1 m nearer the wall and 0.3 m
    right, R = I, so t_ba = (-1, -0.3, 0), den = 1 - rho and C = f (m1 - 0.3, m2) by hand: every VALID pixel's
    sigma^2 gains (s den^2 / |C|)^2 over the plain dense method's, s the pair's pose shift (its tracks' noise with
    exact poses). With b's attitude 0.4 deg off in yaw the shift is about f delta = 1.07 px and the same form holds
    within 2 % (the yaw turns the rays by 0.007 rad, which the R = I values leave out). Catches the geometry taken
    from b to a (den = 1 + rho: the term 22 % too large at 20 m)."""
    va, vb = _plane_pair(192)
    c = va.camera
    v, u = np.mgrid[0:192, 0:192]
    m1, m2 = (u - c.cx) / c.fx, (v - c.cy) / c.fy
    for yaw_deg, rtol in ((0.0, 1e-3), (0.4, 0.02)):
        b = _rotated(vb, yaw_deg) if yaw_deg else vb
        res = checked_dense(va, b, brightness=False)
        plain = locate_dense(va, b, fill=False)
        s = res.info["pair_check"]["pose_shift_px"]
        if yaw_deg:
            assert 0.85 * c.fx * np.radians(yaw_deg) < s < 1.15 * c.fx * np.radians(yaw_deg)
        rho = res.inv_range_per_m.astype(np.float64)
        after, before = (r.inv_range_std_per_m.astype(np.float64) for r in (res, plain))
        ok = ((res.flags & VALID) != 0) & np.isfinite(after)
        assert ok.mean() > 0.7
        extra = np.sqrt(after[ok] ** 2 - before[ok] ** 2)
        expect = s * (1.0 - rho[ok]) ** 2 / (c.fx * np.hypot(m1[ok] - 0.3, m2[ok]))
        np.testing.assert_allclose(extra, expect, rtol=rtol)


def test_pose_sigma_term_by_hand():
    # sideways pair (b 0.5 m right, R = I): den = 1, sensitivity = fx b, so sigma^2 gains (shift / (fx b))^2
    cam = Camera("c", 64, 48, 80.0, 80.0, 31.5, 23.5)
    a = View(cam, VehicleState.from_ypr([0, 0, 0], [0, 0, 0]), np.zeros((48, 64), np.float32))
    b = View(cam, VehicleState.from_ypr([0, 0.5, 0], [0, 0, 0]), np.zeros((48, 64), np.float32))
    geo = pair_geometry(a, b)
    rho = np.full((48, 64), 0.1, np.float32)
    rho[0, 0] = np.nan
    std = np.full((48, 64), 0.004, np.float32)

    def Res():
        return SimpleNamespace(inv_range_per_m=rho, inv_range_std_per_m=std.copy())
    r = Res()
    add_pose_sigma(r, geo, 0.6)
    expect = np.sqrt(0.004 ** 2 + (0.6 / (80.0 * 0.5)) ** 2)
    assert np.allclose(r.inv_range_std_per_m[1:], expect, rtol=1e-3)
    assert r.inv_range_std_per_m[0, 0] == np.float32(0.004)          # no rho: untouched
    for s in (0.0, float("nan")):
        r2 = Res()
        add_pose_sigma(r2, geo, s)
        assert np.array_equal(r2.inv_range_std_per_m, std)


def test_pose_sigma_term_of_a_vertical_baseline_by_hand_with_non_square_pixels():
    """fx 80, fy 60 (non-square pixels), R = I: b 0.5 m below a (the lines are columns) moves a pixel fy b rho, the
    sensitivity is fy b = 30 px per 1/m, and sigma^2 gains (shift / 30)^2; b 0.5 m to the right: fx b = 40. The
    numba pass (``add_pose_sigma``) and the numpy reference alike. Catches the vertical component scaled by fx
    (the square-pixel tests cannot tell it; the bit-for-bit test only that the two paths differ)."""
    from eonav.fusion.measure import _pose_sigma_numpy
    cam = Camera("c", 64, 48, 80.0, 60.0, 31.5, 23.5)
    a = View(cam, VehicleState.from_ypr([0, 0, 0], [0, 0, 0]), np.zeros((48, 64), np.float32))
    rho = np.full((48, 64), 0.1, np.float32)
    std = np.full((48, 64), 0.004, np.float32)
    for offset_ned, sens in (([0, 0, 0.5], 60.0 * 0.5), ([0, 0.5, 0], 80.0 * 0.5)):
        geo = pair_geometry(a, View(cam, VehicleState.from_ypr(offset_ned, [0, 0, 0]), np.zeros((48, 64), np.float32)))
        r = SimpleNamespace(inv_range_per_m=rho, inv_range_std_per_m=std.copy())
        add_pose_sigma(r, geo, 0.6)
        ref = std.copy()
        _pose_sigma_numpy(rho, ref, geo, 0.6)
        expect = np.sqrt(0.004 ** 2 + (0.6 / sens) ** 2)
        assert np.allclose(r.inv_range_std_per_m, expect, rtol=1e-4), offset_ned
        assert np.allclose(ref, expect, rtol=1e-4), offset_ned


@pytest.mark.realdata
def test_real_indoor_sequence_frame0_pose_is_the_inconsistent_one():
    # HoloLens sequence: the headset's pose of frame 0 disagrees with its images (its pairs' tracks lie off the
    # epipolar lines by about a pixel), the pairs of the next frames agree to a few tenths
    from shared_data import hololens_or_skip
    views, _ = hololens_or_skip()

    def shift(k, j):
        return pose_shift_px(pair_geometry(views[k], views[j]), track_points(views[k].image, views[j].image))
    assert shift(1, 0) > 0.8 and shift(3, 0) > 0.6
    assert shift(2, 1) < 0.3 and shift(4, 3) < 0.3
    # the indoor schedule passes over frame 0 and over no other frame
    from eonav.app.bench_fuse import indoor_config
    from eonav.fusion.schedule import Scheduler
    from eonav.fusion.sequence import frame
    sch = Scheduler(indoor_config().schedule)
    for k, v in enumerate(views):
        sch.offer(frame("hololens", v, int(round(v.state.t_s * 1e6)), k))
    assert [f.seq for f in sch._hist["hololens"] if not sch.pose_ok(f)] == [0]


def test_pose_sigma_term_against_a_numerical_derivative_of_the_map():
    # a general pair (forward, sideways and down, rotated): the sensitivity |d(u_b, v_b)/d rho| by central
    # differences of pair_geometry's exact map, independent of EpipolarMap and of the coarse-level fields
    cam = Camera("c", 96, 72, 90.0, 90.0, 47.5, 35.5)
    a = View(cam, VehicleState.from_ypr([0, 0, 0], [0, 0, 0]), np.zeros((72, 96), np.float32))
    b = View(cam, VehicleState.from_ypr([0.8, 0.3, 0.1], np.radians([2.0, -1.0, 0.5])), np.zeros((72, 96), np.float32))
    geo = pair_geometry(a, b)
    v, u = np.mgrid[0:72, 0:96]
    rho = (0.05 + 0.001 * u + 0.0005 * v).astype(np.float32)
    h = 1e-4
    up, vp, _ = geo.map_to_b(rho.astype(np.float64) + h)
    um, vm, _ = geo.map_to_b(rho.astype(np.float64) - h)
    sens = np.hypot(up.astype(np.float64) - um, vp.astype(np.float64) - vm) / (2 * h)
    std = np.full(rho.shape, 0.002, np.float32)
    r = SimpleNamespace(inv_range_per_m=rho, inv_range_std_per_m=std.copy())
    add_pose_sigma(r, geo, 0.5)
    expect = np.sqrt(0.002 ** 2 + (0.5 / sens) ** 2)
    inner = (slice(4, -4), slice(4, -4))
    assert np.allclose(r.inv_range_std_per_m[inner], expect[inner], rtol=0.02)


def test_pose_sigma_pass_equals_the_numpy_reference_bit_for_bit():
    # a general pair moving towards the scene (den <= 0 for the nearest rho), with NaN rho, inf and NaN sigma, rho
    # beyond the den limit: the numba pass gives the numpy reference's float32 values exactly, pixel by pixel
    from eonav.fusion.measure import _pose_sigma_numpy
    from eonav.fusion.state import optional_kernels
    if optional_kernels() is None:
        pytest.skip("numba not installed: the numpy path is the only one")
    cam_a = Camera("a", 97, 71, 90.0, 91.0, 47.3, 35.6)
    cam_b = Camera("b", 97, 71, 88.0, 89.5, 48.1, 34.9)
    a = View(cam_a, VehicleState.from_ypr([0, 0, 0], [0, 0, 0]), np.zeros((71, 97), np.float32))
    b = View(cam_b, VehicleState.from_ypr([1.2, 0.3, -0.2], np.radians([3.0, -2.0, 1.0])), np.zeros((71, 97), np.float32))
    geo = pair_geometry(a, b)
    rng = np.random.default_rng(5)
    rho = rng.uniform(0.0, 1.5, (71, 97)).astype(np.float32)      # den = A0 + B0 rho < 0 beyond ~0.8 (B0 -1.2)
    std = rng.uniform(1e-4, 0.05, (71, 97)).astype(np.float32)
    rho[rng.random(rho.shape) < 0.05] = np.nan
    std[rng.random(std.shape) < 0.05] = np.inf
    std[rng.random(std.shape) < 0.02] = np.nan
    for shift in (0.37, 2.5):
        r = SimpleNamespace(inv_range_per_m=rho, inv_range_std_per_m=std.copy())
        add_pose_sigma(r, geo, shift)
        ref = std.copy()
        _pose_sigma_numpy(rho, ref, geo, shift)
        assert np.array_equal(r.inv_range_std_per_m.view(np.uint32), ref.view(np.uint32))
        assert (ref > std).sum() > 0.3 * rho.size and (ref == std).sum() > 0.3 * rho.size   # both kinds of pixel


def test_bench_reason_for_a_pair_without_output():
    # camera b 0.5 m to the right of a (R = I), a wall 5 m ahead: every pixel moves f b / 5 = 8 px along the row
    from eonav.app.bench_fuse import no_output_reason
    cam = Camera("c", 64, 48, 80.0, 80.0, 31.5, 23.5)
    a = View(cam, VehicleState.from_ypr([0, 0, 0], [0, 0, 0]), np.zeros((48, 64), np.float32))
    b = View(cam, VehicleState.from_ypr([0, 0.5, 0], [0, 0, 0]), np.zeros((48, 64), np.float32))
    truth = np.full((48, 64), 5.0, np.float32)
    truth[:4] = np.nan
    why = no_output_reason(a, b, truth, SimpleNamespace(info={"flow_sigma_px": 37.0}))
    assert "baseline 0.500 m, rotation 0.0 deg" in why and "true motion median 8 px (90 % 8 px)" in why
    assert f"{100 * (64 - 8) / 64:.0f} % of the pixels with truth still in view b" in why
    assert "a robust 37 px off their epipolar lines" in why
    assert "epipolar" not in no_output_reason(a, b, truth, SimpleNamespace(info={}))


@pytest.mark.parametrize("limit_px, frame2_used", [(0.5, False), (5.0, True)])
def test_schedule_passes_over_a_frame_whose_pose_disagrees(limit_px, frame2_used):
    # sim frames (exact poses: shifts ~0.05 px) with frame 2's attitude turned by 0.6 deg: its pairs' tracks lie
    # f x 0.0105 ~ 1.3 px off their lines; below that limit frame 2 is nobody's partner, above it it is
    from eonav.fusion.schedule import ScheduleConfig, Scheduler
    from eonav.fusion.sequence import frame
    from eonav.ranging.pair_policy import PairPolicyConfig
    from eonav.sim.sequence import render_sequence
    seq = render_sequence("fast", n_frames=5, rate_hz=30.0, size=160, seed=0)
    views = list(seq.views)
    views[2] = _rotated(views[2], 0.6)
    expect = views[2].camera.fx * np.radians(0.6)
    sch = Scheduler(ScheduleConfig(policy=PairPolicyConfig(min_disparity_px=0.01), max_pose_shift_px=limit_px))
    partners = {}
    for k, v in enumerate(views):
        ms, _ = sch.offer(frame("cam", v, 1_000_000 + 33_333 * k, k))
        partners[k] = [m.b.seq for m in ms]
    used = any(2 in p for p in partners.values())
    assert used == frame2_used, partners
    hist = list(sch._hist["cam"])
    assert partners[3] and partners[4]                    # the frames after it still find partners
    assert [sch.pose_ok(f) for f in hist] == [True, True, frame2_used, True, True]
    shifts = [sch._shift[id(f)][1] for f in hist]
    assert 0.7 * expect < shifts[2] < 1.3 * expect and 0.7 * expect < shifts[3] < 1.3 * expect
    assert shifts[1] < 0.2 and shifts[4] < 0.2


@pytest.mark.parametrize("checks", [False, True])
def test_locator_pair_checks_flag_drives_the_measure_and_the_schedule(checks):
    # the locator service's --pair-checks: each measurement goes through the checks (its info says so) and the
    # frame whose attitude is 0.6 deg off (~1.3 px on its tracks, above the 0.75 px default) is nobody's partner;
    # without the flag the plain method measures and that frame is used
    import argparse

    from eonav.fusion.sequence import frame
    from eonav.services import locator
    from eonav.sim.sequence import render_sequence
    p = argparse.ArgumentParser()
    locator.add_arguments(p)
    args = p.parse_args(["--min-disparity-px", "0.01"] + (["--pair-checks"] if checks else []))
    runner = locator.fusion_runner(args, {})
    seq = render_sequence("fast", n_frames=5, rate_hz=30.0, size=160, seed=0)
    views = list(seq.views)
    views[2] = _rotated(views[2], 0.6)
    seen_info, partners = [], []
    measure = runner.measure

    def spy(va, vb, **kw):
        res = measure(va, vb, **kw)
        seen_info.append("pair_check" in res.info)
        partners.append(next(i for i, v in enumerate(views) if v is vb))
        return res
    runner.measure = spy
    for k, v in enumerate(views):
        runner.push(frame("cam", v, 1_000_000 + 33_333 * k, k))
    assert seen_info and all(s == checks for s in seen_info)
    assert len(partners) >= 3 and (2 in partners) == (not checks), partners


def test_locator_pair_checks_rejects_a_bad_limit():
    import argparse

    from eonav import InputError
    from eonav.services import locator
    p = argparse.ArgumentParser()
    locator.add_arguments(p)
    args = p.parse_args(["--pair-checks", "--max-pose-shift-px", "0"])
    with pytest.raises(InputError, match="--max-pose-shift-px must be > 0"):
        locator.fusion_runner(args, {})


def test_recent_tracks_reuses_only_the_same_arrays():
    """The memo returns the tracks of the same two arrays (equal to track_points' own), tracks an equal copy or
    the swapped pair anew, and forgets the oldest pair beyond its size."""
    from eonav.ranging.tracks import RecentTracks
    img = texture(120, 160, seed=3)
    b = np.roll(img, 2, axis=1)
    memo = RecentTracks(size=2)
    t1 = memo(img, b)
    direct = track_points(img, b)
    assert np.array_equal(t1.pts_a, direct.pts_a) and np.array_equal(t1.pts_b, direct.pts_b)
    assert memo(img, b) is t1 and memo.hits == 1
    assert memo(img.copy(), b) is not t1 and memo.hits == 1        # an equal copy is another image
    t_other = memo(img, np.roll(img, 3, axis=0))                   # the same image a, another image b
    assert t_other is not t1 and memo.hits == 1
    assert np.median(t_other.pts_b[:, 1] - t_other.pts_a[:, 1]) == pytest.approx(3.0, abs=0.2)
    assert memo(img, b) is not t1                                  # pushed out by the two after it
    assert RecentTracks(size=0)(img, b) is not RecentTracks(size=0)(img, b)


def test_recent_tracks_of_a_stream_reuse_each_images_level_and_corners_with_the_same_tracks():
    """Along a stream (each frame tracked against the one before, then the newest against an older one) the memo
    prepares each image once and finds the newest image's corners once, and every pair's tracks are track_points'
    own, bit for bit; a 360-row image is tracked a level down (the level is memoised, not the full image)."""
    from eonav.ranging.tracks import RecentTracks
    base = texture(360, 480, seed=5)
    frames = [np.roll(base, (k, 2 * k), axis=(0, 1)) for k in range(5)]
    memo = RecentTracks(size=2)
    for k in range(1, 5):
        for j in ([k - 1, 0] if k >= 2 else [k - 1]):
            t = memo(frames[k], frames[j])
            direct = track_points(frames[k], frames[j])
            assert len(t) > 50
            assert np.array_equal(t.pts_a, direct.pts_a) and np.array_equal(t.pts_b, direct.pts_b)
    levels, corners = memo.images._levels, memo.images._corners
    assert levels.hits == 14 - 5 and corners.hits == 3      # 14 look-ups, each of the 5 images prepared once
    assert all(lv.shape == (180, 240) and lv.dtype == np.uint8 for _, _, lv in levels._held)


def test_recent_pose_shifts_reuse_only_the_same_tracks_and_geometry():
    """The memo returns pose_shift_px's own value, again for the same tracks with an equal geometry (a fresh
    pair_geometry of the same views), and fits anew for equal-valued copies of the tracks or another pose."""
    from eonav.ranging.tracks import RecentShifts
    va, vb = _plane_pair(192)
    vr = _rotated(vb, 0.5)
    tr = track_points(va.image, vr.image)
    memo = RecentShifts(size=2)
    s1 = memo(pair_geometry(va, vr), tr)
    assert s1 == pose_shift_px(pair_geometry(va, vr), tr) and s1 > 0.5        # 0.5 deg of yaw: ~1.3 px
    assert memo(pair_geometry(va, vr), tr) == s1 and memo.hits == 1
    copy = Tracks(tr.pts_a.copy(), tr.pts_b.copy())
    assert memo(pair_geometry(va, vr), copy) == s1 and memo.hits == 1          # same values, fitted anew
    other = memo(pair_geometry(va, vb), tr)                                     # the exact pose: another shift
    assert other == pose_shift_px(pair_geometry(va, vb), tr) and other < 0.5 * s1 and memo.hits == 1
    memo(pair_geometry(va, vr), tr)
    assert memo.hits == 1                                                       # pushed out by the two after it


def _sideways_wall_pair(size=192, baseline_m=0.3, range_m=20.0, seed=3):
    """A textured wall range_m ahead, camera b baseline_m to the right of a, same attitude: every epipolar line is a
    row, so a pose error that moves b's points along the rows is invisible across the lines. Image b is image a
    through the wall's homography (as ``_plane_pair``)."""
    f = 0.8 * size
    c = (size - 1) / 2.0
    cam = Camera("wall", size, size, f, f, c, c)
    img = texture(size, size, seed)
    a = View(cam, VehicleState.from_ypr([0.0, 0.0, 0.0], [0.0, 0.0, 0.0]), img)
    st_b = VehicleState.from_ypr([0.0, baseline_m, 0.0], [0.0, 0.0, 0.0])
    geo = pair_geometry(a, View(cam, st_b, img))
    to_m = np.array([[0.0, 0.0, 1.0], [1.0 / f, 0.0, -c / f], [0.0, 1.0 / f, -c / f]])
    to_px = np.array([[c, f, 0.0], [c, 0.0, f], [1.0, 0.0, 0.0]])
    H = to_px @ (geo.R_ba + np.outer(geo.t_ba_m, [1.0 / range_m, 0.0, 0.0])) @ to_m
    img_b = cv2.warpPerspective(img, H, (size, size), flags=cv2.INTER_LINEAR, borderMode=cv2.BORDER_REFLECT)
    return a, View(cam, st_b, img_b.astype(np.float32))


def _wall_state(shape, range_m=20.0, sigma_rel=0.001, n=3):
    rho = np.full(shape, 1.0 / range_m, np.float32)
    return rho, (rho * np.float32(sigma_rel)) ** 2, np.full(shape, n, np.uint16)


def _yaw_shift_px(va, vb, yaw_deg, pts_a, range_m=20.0, of_a=False):
    """Mean displacement (px of b, 2-vector) that a yaw error of b (of a: ``of_a``) puts on the wall's points at
    pts_a: the place under the wrong pose minus the place under the right one (a yaw moves a point f delta
    (1 + x_n^2) sideways)."""
    def place(geo):
        c = va.camera
        m = np.stack([np.ones(len(pts_a)), (pts_a[:, 0] - c.cx) / c.fx, (pts_a[:, 1] - c.cy) / c.fy], 1)
        X = m @ geo.R_ba.T + geo.t_ba_m / range_m
        return np.stack([c.cx + c.fx * X[:, 1] / X[:, 0], c.cy + c.fy * X[:, 2] / X[:, 0]], 1)
    wrong = pair_geometry(_rotated(va, yaw_deg), vb) if of_a else pair_geometry(va, _rotated(vb, yaw_deg))
    return (place(wrong) - place(pair_geometry(va, vb))).mean(axis=0)


def test_state_shift_sees_the_pose_error_along_the_lines():
    # sideways pair: lines are rows. A yaw error of delta moves b's points along the rows by ~f delta: the
    # across-line shift cannot see it, the state's inverse ranges put every point at one place and the offset shows
    from eonav.fusion.measure import state_shift_px
    va, vb = _sideways_wall_pair()
    f = va.camera.fx
    tr = track_points(va.image, vb.image)
    rho, var, n = _wall_state(va.image.shape)
    assert state_shift_px(rho, var, n, pair_geometry(va, vb), tr) < 0.1
    for yaw_deg in (0.3, -0.6):
        geo = pair_geometry(va, _rotated(vb, yaw_deg))
        expect = float(np.hypot(*_yaw_shift_px(va, vb, yaw_deg, tr.pts_a.astype(float))))
        assert f * np.radians(abs(yaw_deg)) < expect < 1.2 * f * np.radians(abs(yaw_deg))
        got = state_shift_px(rho, var, n, geo, tr)
        assert got == pytest.approx(expect, rel=0.05), (yaw_deg, got, expect)
        assert pose_shift_px(geo, tr) < 0.2 * expect          # across the lines: (almost) nothing


def test_state_shift_uses_only_cells_known_well_enough():
    from eonav.fusion.measure import state_shift_px
    va, vb = _sideways_wall_pair()
    geo = pair_geometry(va, _rotated(vb, 0.3))
    tr = track_points(va.image, vb.image)
    shape = va.image.shape
    # the place's 1-sigma spread is f b sigma_rho = 153.6 px x 0.3 m x sigma_rho: 0.29 px is used, 0.31 px is not
    f, b = va.camera.fx, 0.3
    for spread_px, used in ((0.29, True), (0.31, False)):
        sd = spread_px / (f * b)
        rho, _, n = _wall_state(shape)
        var = np.full(shape, sd * sd, np.float32)
        got = state_shift_px(rho, var, n, geo, tr)
        assert np.isfinite(got) == used, (spread_px, got)
    rho, var, n = _wall_state(shape, n=1)                      # one measurement: not enough
    assert np.isnan(state_shift_px(rho, var, n, geo, tr))
    assert np.isfinite(state_shift_px(rho, var, n, geo, tr, min_fused=1))
    rho, var, n = _wall_state(shape)
    assert np.isnan(state_shift_px(rho, var, n, geo, Tracks(tr.pts_a[:19], tr.pts_b[:19])))
    assert np.isfinite(state_shift_px(rho, var, n, geo, Tracks(tr.pts_a[:40], tr.pts_b[:40])))
    empty = np.full(shape, np.nan, np.float32)
    assert np.isnan(state_shift_px(empty, var, n, geo, tr))


def test_state_shift_counts_points_the_state_holds_at_infinity():
    """rho = 0 (a point at infinity: far terrain, a horizon) is a known inverse range: with b 0.3 m to the right of a
    and the same attitude such a point has the same pixel in b as in a, so tracks offset by (1.5, -0.8) px show a
    shift of hypot(1.5, 0.8) = 1.7 px (the 1.5 along the rows, the epipolar lines, which pose_shift_px cannot see)."""
    from eonav.fusion.measure import state_shift_px
    cam = Camera("c", 192, 192, 153.6, 153.6, 95.5, 95.5)
    a = View(cam, VehicleState.from_ypr([0.0, 0.0, 0.0], [0.0, 0.0, 0.0]), np.zeros((192, 192), np.float32))
    b = View(cam, VehicleState.from_ypr([0.0, 0.3, 0.0], [0.0, 0.0, 0.0]), np.zeros((192, 192), np.float32))
    y, x = np.mgrid[20:180:20, 16:180:24]
    pa = np.stack([x.ravel(), y.ravel()], 1).astype(np.float32)            # 8 x 7 = 56 points
    tr = Tracks(pa, pa + np.float32([1.5, -0.8]))
    rho = np.zeros((192, 192), np.float32)
    var = np.full((192, 192), 1e-4 ** 2, np.float32)                       # place moves f b 1e-4 = 0.005 px
    n = np.full((192, 192), 3, np.uint16)
    assert state_shift_px(rho, var, n, pair_geometry(a, b), tr) == pytest.approx(1.7, abs=1e-3)


def test_state_shift_reads_each_tracks_own_cell_of_the_state():
    """The state's inverse range is read at each track's own pixel (row v, column u). b 0.3 m to the right of a, the
    same attitude: a point at rho has its place in b f b rho = 46.08 rho px left of its pixel in a. On a state that
    varies along u (rho = 0.02 + 0.0005 u: 50 m on the left to 8.7 m on the right) tracks at those places offset by
    (1.5, -0.8) px show 1.7 px. Read at (u, v), transposed, each place would be off by f b 0.0005 (v - u), up to
    3.8 px. Catches the track's row and column swapped (a uniform state, as in the tests above, cannot tell)."""
    from eonav.fusion.measure import state_shift_px
    cam = Camera("c", 192, 192, 153.6, 153.6, 95.5, 95.5)
    a = View(cam, VehicleState.from_ypr([0.0, 0.0, 0.0], [0.0, 0.0, 0.0]), np.zeros((192, 192), np.float32))
    b = View(cam, VehicleState.from_ypr([0.0, 0.3, 0.0], [0.0, 0.0, 0.0]), np.zeros((192, 192), np.float32))
    rho = np.repeat((0.02 + 0.0005 * np.arange(192, dtype=np.float32))[None, :], 192, axis=0)
    y, x = np.mgrid[20:180:20, 16:180:24]
    pa = np.stack([x.ravel(), y.ravel()], 1).astype(np.float32)            # 8 x 7 = 56 points
    at = rho[y.ravel(), x.ravel()].astype(np.float64)
    pb = pa + np.stack([1.5 - 153.6 * 0.3 * at, np.full(len(at), -0.8)], 1)
    var = np.full((192, 192), 1e-4 ** 2, np.float32)
    n = np.full((192, 192), 3, np.uint16)
    assert state_shift_px(rho, var, n, pair_geometry(a, b), Tracks(pa, pb.astype(np.float32))) == pytest.approx(
        1.7, abs=1e-3)


def test_fusion_adds_the_along_line_pose_error_to_the_sigma():
    # four frames of the sideways wall (b, a, b, then a with a yaw error): the fourth push's pair, with the state
    # fused from two measurements on the wall, gets the along-line term, and its sigma grows by the yaw's shift in
    # quadrature
    from eonav.fusion import sequence as seq_mod
    from eonav.fusion.sequence import FusionConfig, FusionRunner, frame
    va, vb = _sideways_wall_pair(size=160)
    f = va.camera.fx
    yaw_deg = 0.4
    seen = {}
    orig = seq_mod.FusionRunner._pose_along

    def spy(self, m, geo, res, state):
        before = res.inv_range_std_per_m.copy()
        orig(self, m, geo, res, state)
        seen[m.a.seq] = (res.info["pair_check"], before, res.inv_range_std_per_m.copy(), m)

    from eonav.fusion.schedule import ScheduleConfig
    from eonav.ranging.pair_policy import PairPolicyConfig
    runner = FusionRunner(FusionConfig(schedule=ScheduleConfig(policy=PairPolicyConfig(ref_range_m=5.0)),
                                       pair_checks=True))
    runner._pose_along = spy.__get__(runner)
    views = [vb, va, vb, _rotated(va, yaw_deg)]
    for k, v in enumerate(views):
        v = replace(v, state=VehicleState(v.state.position_ned_m, v.state.T_body_ned, t_s=0.1 * k))
        runner.push(frame("wall", v, 100_000 * k, k))
    assert np.isnan(seen[2][0]["state_shift_px"])               # one measurement fused so far: no term
    check, before, after, m = seen[3]
    tr = track_points(va.image, vb.image)
    expect = float(np.hypot(*_yaw_shift_px(va, vb, yaw_deg, tr.pts_a.astype(float), of_a=True)))
    assert check["state_shift_px"] == pytest.approx(expect, rel=0.1)
    assert runner.counts.get("pose_along_added") == 1
    ok = np.isfinite(before) & np.isfinite(after) & (before > 0)
    assert ok.sum() > 1000
    assert np.all(after[ok] >= before[ok])
    # the added variance is (shift / sensitivity)^2 with sensitivity f b (px per 1/m) on the fronto-parallel wall
    extra = np.sqrt(np.maximum(after[ok].astype(float) ** 2 - before[ok].astype(float) ** 2, 0))
    along = np.sqrt(max(check["state_shift_px"] ** 2 - np.nan_to_num(check["pose_shift_px"]) ** 2, 0))
    assert np.median(extra) == pytest.approx(along / (f * 0.3), rel=0.05)


def test_median_1d_is_np_median():
    from eonav.ranging.photometric import _median
    from eonav.ranging.tracks import median_1d
    rng = np.random.default_rng(5)
    for n in (1, 2, 3, 4, 5, 10, 11, 100, 101):
        for _ in range(50):
            x = rng.standard_normal(n) * rng.uniform(1e-3, 1e3)
            if rng.random() < 0.2:
                x[rng.integers(n)] = np.nan
            if rng.random() < 0.2:
                x = np.round(x) * 0.0          # signed zeros
            a, b = float(np.median(x)), median_1d(x)
            assert (np.isnan(a) and np.isnan(b)) or a.hex() == b.hex()
            x32 = x.astype(np.float32)
            a32, b32 = np.median(x32), _median(x32)
            assert type(a32) is type(b32) and (np.isnan(a32) and np.isnan(b32) or a32.tobytes() == b32.tobytes())
    x = rng.standard_normal((6, 5))
    assert median_1d(x) == float(np.median(x))


def _innovations(n, sigma_true, tau, s_state, seed=5, outliers=0.0):
    """A confident state (mu 0.02 1/m, sigma s_state) and a measurement x = mu + N(0, sigma_true) reporting tau."""
    rng = np.random.default_rng(seed)
    mu = np.full(n, 0.02, np.float32)
    x = (mu + sigma_true * rng.standard_normal(n)).astype(np.float32)
    if outliers:
        k = int(outliers * n)
        x[:k] = rng.uniform(0.0, 0.1, k)                      # gross mismatches anywhere in range
    return (x, np.full(n, tau, np.float32), np.ones(n, bool), mu, np.full(n, s_state ** 2, np.float32),
            np.ones(n, bool))


def test_innovation_scale_recovers_an_under_reported_sigma():
    # true spread 0.002, reported 0.001, state 0.0005: c^2 tau^2 + s^2 = sigma^2 -> c = sqrt(4 - 0.25) = 1.936
    from eonav.fusion.measure import innovation_scale
    want = math.sqrt(0.002 ** 2 - 0.0005 ** 2) / 0.001
    assert innovation_scale(*_innovations(20000, 0.002, 0.001, 0.0005)) == pytest.approx(want, rel=0.03)
    # a tenth of the pixels gross mismatches: the MAD of the rest is read at their 0.5 / 0.9 quantile, 0.765 sigma
    # instead of 0.674 (x 1.134): c = sqrt((1.134 sigma)^2 - s^2) / tau, 2.21, where the plain spread would be 6
    wide = 1.4826 * 0.002 * float(norm.ppf((0.5 / 0.9 + 1) / 2))
    assert innovation_scale(*_innovations(20000, 0.002, 0.001, 0.0005, outliers=0.1)) == pytest.approx(
        math.sqrt(wide ** 2 - 0.0005 ** 2) / 0.001, rel=0.03)


def test_innovation_scale_both_sides_of_an_honest_sigma():
    from eonav.fusion.measure import innovation_scale
    s = 0.0005
    honest = math.sqrt(0.002 ** 2 - s ** 2)
    # reported 10 % wide: never scaled down
    assert innovation_scale(*_innovations(20000, 0.002, 1.1 * honest, s)) == 1.0
    # reported 10 % narrow: scaled up by about as much (the state's part is fixed: a bit more than 1.1)
    c = innovation_scale(*_innovations(20000, 0.002, honest / 1.1, s))
    assert 1.07 < c < 1.14
    # too few confident pixels: no scale; a hopeless sigma: at most max_scale
    assert innovation_scale(*_innovations(400, 0.002, 0.0005, s)) == 1.0
    assert innovation_scale(*_innovations(20000, 0.002, 1e-6, s)) == 10.0


def test_runner_scales_a_measurement_sigma_its_innovations_contradict():
    # a confident state on a 120 x 160 grid (rho 0.05 1/m, sigma 0.5 %, four measurements, evidence agreeing) and a
    # measurement off by 2 % of rho that says 0.5 %: the runner's check scales its sigma by
    # sqrt(2^2 - 0.5^2) / 0.5 = 3.87 in place and counts it; where the state's cells hold one measurement, or their
    # evidence disagrees, it has nothing to judge by and leaves the sigma as it is
    from eonav.fusion.sequence import FusionConfig, FusionRunner
    from eonav.fusion.state import InverseRangeState
    from eonav.ranging.rangemap import VALID
    cam = Camera("c", 160, 120, 100.0, 100.0, 79.5, 59.5)
    rng = np.random.default_rng(12)

    def state(n, a):
        st = InverseRangeState.empty(cam, VehicleState.from_ypr([0.0, 0.0, 0.0], [0.0, 0.0, 0.0]), 0.0)
        st.rho[:] = 0.05
        st.var[:] = (0.05 * 0.005) ** 2
        st.n[:], st.a[:], st.b[:] = n, a, 1.0
        return st

    def measurement():
        rho = (0.05 * (1.0 + 0.02 * rng.standard_normal((120, 160)))).astype(np.float32)
        return SimpleNamespace(inv_range_per_m=rho, inv_range_std_per_m=np.full((120, 160), 0.05 * 0.005, np.float32),
                               flags=np.full((120, 160), VALID, np.uint8), info={"pair_check": {}})

    runner = FusionRunner(FusionConfig(pair_checks=True))
    res = measurement()
    runner._against_state(res, state(4, 7.0))
    c = res.info["pair_check"]["innovation_scale"]
    assert c == pytest.approx(math.sqrt(0.02 ** 2 - 0.005 ** 2) / 0.005, rel=0.03)
    np.testing.assert_allclose(res.inv_range_std_per_m, np.float32(0.05 * 0.005) * np.float32(c), rtol=1e-6)
    assert runner.counts.get("innovation_scaled") == 1
    for st in (state(1, 7.0), state(4, 1.0)):            # one measurement; evidence 1 : 1 (below eta_inlier)
        res = measurement()
        runner._against_state(res, st)
        assert res.info["pair_check"]["innovation_scale"] == 1.0
        assert np.all(res.inv_range_std_per_m == np.float32(0.05 * 0.005))
    assert runner.counts.get("innovation_scaled") == 1


def test_forward_backward_check_drops_tracks_into_an_occluding_surface():
    """Image b is image a shifted by (3, 2) px with its right half replaced by another surface (an occluder): the
    corners of a's right half have no true match in b, and tracking back from wherever they land does not return to
    the start, so the forward-backward check drops them: almost every kept track moves by the known (3, 2) px
    (measured: 1 of 98 off by more than 1 px; without the check 58 of 160)."""
    img = texture(240, 320, seed=0)
    M = np.float32([[1, 0, 3.0], [0, 1, 2.0]])
    b = cv2.warpAffine(img, M, (320, 240), flags=cv2.INTER_LINEAR, borderMode=cv2.BORDER_REFLECT)
    b[:, 160:] = texture(240, 320, seed=7)[:, 160:]
    tr = track_points(img, b)
    assert len(tr) >= 50
    off = np.linalg.norm(tr.pts_b - tr.pts_a - [3.0, 2.0], axis=1) > 1.0
    assert off.mean() < 0.03, (off.sum(), len(tr))


def test_epipolar_distance_by_hand_on_slanted_lines_with_non_square_pixels():
    # fx 100, fy 80, camera b 0.5 m right and 0.5 m down of a, same attitude: the line of a point runs through its own
    # pixel (its image at rho = 0) along (fx, fy) = (5, 4) / sqrt(41); a match moved t along it and e across it
    # (normal (4, -5) / sqrt(41)) is e px from its line, whatever t (another depth)
    cam = Camera("c", 100, 80, 100.0, 80.0, 49.5, 39.5)
    a = View(cam, VehicleState.from_ypr([0, 0, 0], [0, 0, 0]), np.zeros((80, 100), np.float32))
    b = View(cam, VehicleState.from_ypr([0, 0.5, 0.5], [0, 0, 0]), np.zeros((80, 100), np.float32))
    geo = pair_geometry(a, b)
    pa = np.float32([[10, 20], [60, 50], [90, 10], [30, 70]])
    t = np.array([-6.0, -15.0, 0.0, -2.5])
    e = np.array([0.0, 0.7, -0.3, 1.2])
    pb = pa + (t[:, None] * [5, 4] + e[:, None] * [4, -5]) / np.sqrt(41)
    d, n = epipolar_residual_px(geo, Tracks(pa, pb.astype(np.float32)))
    sign = np.sign(n[:, 0])
    assert np.allclose(n * sign[:, None], np.array([4, -5]) / np.sqrt(41), atol=1e-6)
    assert np.allclose(d * sign, e, atol=1e-4)


def test_epipolar_distance_is_nan_for_points_behind_camera_b():
    # camera b 0.5 m right of a and yawed 90 deg right: a's rays right of its centre column are ahead of b (in front
    # half-space), those left of it point behind b and have no epipolar line: NaN, as the lines' normals
    cam = Camera("c", 100, 80, 100.0, 100.0, 49.5, 39.5)
    a = View(cam, VehicleState.from_ypr([0, 0, 0], [0, 0, 0]), np.zeros((80, 100), np.float32))
    b = View(cam, VehicleState.from_ypr([0, 0.5, 0], [np.radians(90), 0, 0]), np.zeros((80, 100), np.float32))
    pa = np.float32([[60, 20], [95, 50], [40, 20], [5, 60]])
    d, n = epipolar_residual_px(pair_geometry(a, b), Tracks(pa, pa + 1))
    assert np.all(np.isfinite(d[:2])) and np.all(np.isfinite(n[:2]))
    assert np.all(np.isnan(d[2:])) and np.all(np.isnan(n[2:]))


def test_tukey_weights_by_hand():
    # r = 0, +-1, +-2, 7, -50: median |r| = 2, robust sigma 1.4826 * 2 = 2.9652, cut at c = 4.685 * 2.9652 = 13.892;
    # w = (1 - (r / c)^2)^2: 1, 0.98966, 0.95898, 0.55666, 0 beyond c. Residuals below the floor: sigma = min_scale
    r = np.array([0.0, 1.0, -1.0, 2.0, -2.0, 7.0, -50.0])
    w = tukey_weights(r, 0.05)
    assert np.allclose(w, [1.0, 0.98966, 0.98966, 0.95898, 0.95898, 0.55666, 0.0], atol=2e-5)
    # r = 0.01 with sigma floored at 0.05: (1 - (0.01 / 0.23425)^2)^2 = 0.99636; 0.3 > 0.23425 is cut
    w = tukey_weights(np.array([0.001, -0.002, 0.01, 0.3]), 0.05)
    assert w[2] == pytest.approx(0.99636, abs=2e-5) and w[3] == 0.0


def _radial_tracks(n, shift):
    """Camera b 1 m straight ahead of a (same attitude): every epipolar line is the ray from the image centre through
    the point's own pixel. n points on a circle of radius 30 px, each moved 10 % outward along its line (some depth)
    and then by ``shift`` (px): the matches' distances from their lines are n_i . shift exactly."""
    cam = Camera("c", 120, 100, 100.0, 100.0, 59.5, 49.5)
    a = View(cam, VehicleState.from_ypr([0, 0, 0], [0, 0, 0]), np.zeros((100, 120), np.float32))
    b = View(cam, VehicleState.from_ypr([1.0, 0, 0], [0, 0, 0]), np.zeros((100, 120), np.float32))
    ang = 2 * np.pi * (np.arange(n) + 0.25) / n
    off = 30.0 * np.stack([np.cos(ang), np.sin(ang)], 1)
    pa = np.array([59.5, 49.5]) + off
    pb = pa + 0.1 * off + shift
    return pair_geometry(a, b), Tracks(pa.astype(np.float32), pb.astype(np.float32))


def test_pose_shift_with_exactly_min_tracks():
    """pose_shift_px fits a known (0.3, -0.4) px shift of radial lines to |s| = 0.5 px (hand value) with exactly
    min_tracks = 20 usable matches; with 19 it gives NaN."""
    geo, tr = _radial_tracks(20, [0.3, -0.4])
    assert pose_shift_px(geo, tr) == pytest.approx(0.5, abs=1e-4)
    geo, tr = _radial_tracks(19, [0.3, -0.4])
    assert np.isnan(pose_shift_px(geo, tr))


@pytest.mark.parametrize("shape, shift", [((240, 320), (0.0, 8.0)), ((320, 240), (8.0, 0.0))])
def test_tracks_end_inside_image_b(shape, shift):
    """Image b is image a moved 8 px down (a landscape image) or right (a portrait one): corners within 8 px of that
    edge of a leave b, and Lucas-Kanade still reports a few of them found a few px beyond b's last row or column
    (measured: 6 of ~960 on the landscape pair with the row bound taken from b's width). None is kept: every match lies
    in b, 0 <= x <= w - 1 and 0 <= y <= h - 1."""
    h, w = shape
    img = texture(h, w, seed=1)
    M = np.float32([[1, 0, shift[0]], [0, 1, shift[1]]])
    b = cv2.warpAffine(img, M, (w, h), flags=cv2.INTER_LINEAR, borderMode=cv2.BORDER_REFLECT)
    tr = track_points(img, b, max_points=1000, min_distance_px=3)
    assert len(tr) > 500
    assert np.all((tr.pts_b >= 0) & (tr.pts_b <= [w - 1, h - 1]))
