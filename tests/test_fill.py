"""Filling the pixels a pair cannot measure (eonav.ranging.methods.fill): against planes whose inverse range is known in
closed form, depth steps, and the dense method on simulator scenes with ground truth."""
import cv2
import numpy as np
import pytest

import fill_reference
from eonav.ranging.methods.dense import locate_dense
from eonav.ranging.methods.fill import fill_unmeasured
from eonav.ranging.rangemap import FILLED, ILL_CONDITIONED, LOW_TEXTURE, OCCLUDED, OUT_OF_VIEW, TRUNCATION, VALID
from eonav.sim.presets import make_pair

H, W = 240, 320
F_PX, CX, CY = 300.0, 159.5, 119.5


def plane_rho(n_cam, d_m):
    """rho = 1/x_c of the plane n . X = d seen by a pinhole camera (x_c along the optical axis, x_n = (u - cx)/f
    right, y_n = (v - cy)/f down): rho = (n1 + n2 x_n + n3 y_n) / d."""
    v, u = np.mgrid[0:H, 0:W].astype(np.float64)
    xn, yn = (u - CX) / F_PX, (v - CY) / F_PX
    return ((n_cam[0] + n_cam[1] * xn + n_cam[2] * yn) / d_m).astype(np.float32)


def outputs(rho, flags):
    std = np.full(rho.shape, 1e-5, np.float32)
    rng = np.where((flags & VALID) != 0, 1 / rho, np.nan).astype(np.float32)
    conf = np.where((flags & VALID) != 0, rho / std, 0).astype(np.float32)
    return rho.copy(), std, flags.copy(), rng, conf


def test_plane_holes_are_filled_with_the_plane():
    """Ground seen from 20 m up, pitched down (rho grows downwards in the image): holes inside the measured
    region get the plane's own rho; their sigma is small and covers the error."""
    rho = plane_rho((0.3, 0.05, 0.9), 20.0)
    rng = np.random.default_rng(0)
    noisy = rho * (1 + 0.002 * rng.standard_normal(rho.shape)).astype(np.float32)
    flags = np.full(rho.shape, VALID, np.uint8)
    holes = np.zeros(rho.shape, bool)
    holes[60:75, 40:70] = True         # low texture
    holes[150:160, 200:230] = True     # near the focus of expansion
    flags[60:75, 40:70] = LOW_TEXTURE
    flags[150:160, 200:230] = 4        # ILL_CONDITIONED
    r, s, f, rg, cf = outputs(noisy, flags)
    n = fill_unmeasured(r, s, f, rg, cf, max_rel_std=0.34)
    assert n == holes.sum()
    assert ((f[holes] & FILLED) != 0).all() and not ((f[holes] & VALID) != 0).any()
    assert not ((f[~holes] & FILLED) != 0).any()
    err = np.abs(r[holes] / rho[holes] - 1)
    assert err.max() < 0.01                               # measured 0.1 %: cells of 4 px, noise 0.2 %
    np.testing.assert_allclose(rg[holes], 1 / r[holes], rtol=1e-6)
    np.testing.assert_allclose(cf[holes], r[holes] / s[holes], rtol=1e-6)
    z = (r[holes] - rho[holes]) / s[holes]
    assert np.mean(np.abs(z) < 3) > 0.9


def test_out_of_view_band_is_extrapolated_but_low_texture_beyond_support_is_not():
    """A band that has left image b (OUT_OF_VIEW, not OCCLUDED) is extrapolated along the plane; a textureless
    band beyond the measured pixels (which may be sky) is left without an estimate."""
    rho = plane_rho((0.6, 0.0, 0.9), 15.0)
    flags = np.full(rho.shape, VALID, np.uint8)
    flags[:, :24] = OUT_OF_VIEW                      # left the image
    flags[:20, :] = LOW_TEXTURE                      # top rows: nothing measured above them
    r, s, f, rg, cf = outputs(rho, flags)
    fill_unmeasured(r, s, f, rg, cf, max_rel_std=0.34)
    band = np.zeros(rho.shape, bool)
    band[20:, :24] = True
    assert ((f[band] & FILLED) != 0).mean() > 0.95
    assert np.abs(r[band & ((f & FILLED) != 0)] / rho[band & ((f & FILLED) != 0)] - 1).max() < 0.01
    top = np.zeros(rho.shape, bool)
    top[:12, 24:] = True                              # more than a few pixels beyond the support
    assert not ((f[top] & FILLED) != 0).any()
    assert np.isnan(rg[top]).all()


def test_occluded_and_truncated_pixels_are_not_filled():
    rho = plane_rho((1.0, 0.0, 0.0), 30.0)
    flags = np.full(rho.shape, VALID, np.uint8)
    flags[50:60, 50:60] = OUT_OF_VIEW | OCCLUDED
    flags[100:110, 100:110] = TRUNCATION
    r, s, f, rg, cf = outputs(rho, flags)
    assert fill_unmeasured(r, s, f, rg, cf, max_rel_std=0.34) == 0
    assert np.isnan(rg[50:60, 50:60]).all() and np.isnan(rg[100:110, 100:110]).all()


def test_hole_across_a_depth_step_has_an_honest_sigma():
    """A hole straddling a depth step (10 m left, 40 m right): whatever a plane puts there, the sigma either keeps
    the pixel out (relative sigma above the VALID rule) or covers the error (no |z| beyond 3)."""
    rho = np.where(np.arange(W)[None, :] < 160, 1 / 10.0, 1 / 40.0) * np.ones((H, 1))
    rho = rho.astype(np.float32)
    flags = np.full(rho.shape, VALID, np.uint8)
    flags[100:140, 140:180] = LOW_TEXTURE
    r, s, f, rg, cf = outputs(rho, flags)
    fill_unmeasured(r, s, f, rg, cf, max_rel_std=0.34)
    filled = (f & FILLED) != 0
    z = (r[filled] - rho[filled]) / s[filled]
    assert (np.abs(z) < 3).all()


def test_no_support_no_fill():
    """Nothing measured (every pixel LOW_TEXTURE): nothing is filled, the outputs stay as they were."""
    rho = np.full((H, W), np.nan, np.float32)
    flags = np.full((H, W), LOW_TEXTURE, np.uint8)
    r, s, f, rg, cf = outputs(rho, flags)
    assert fill_unmeasured(r, s, f, rg, cf, max_rel_std=0.34) == 0
    assert np.isnan(r).all() and np.isnan(rg).all() and (f == LOW_TEXTURE).all() and (cf == 0).all()



@pytest.mark.parametrize("dist_m", [60.0, 150.0])
def test_a_hole_in_a_wall_beyond_the_pairs_far_limit_is_not_filled(dist_m):
    """A textured wall dist_m ahead of a rectified pair (f 500 px, baseline 0.1 m) with a textureless 40 x 40 px
    square in its middle. The pair's far limit is rho_far = 0.5 px / (f b) = 0.01 /m (100 m, far_inverse_range):
    at 60 m the square is filled with the wall's plane (measured: 99 % of its inner 30 x 30, median error 3.8 %, as
    the measured wall's own 5 % at 0.8 px of disparity); at 150 m the wall itself is still measured (VALID), but
    nothing is filled, a fill farther than the limit meaning nothing (the dense method passes its rho_far to the
    fill; without it the square was filled at 150 m)."""
    from test_dense import rectified_views, sine_texture
    h, w = 120, 160
    y, x = np.mgrid[0:h, 0:w].astype(np.float64)
    square = (np.abs(x - 79.5) < 20) & (np.abs(y - 59.5) < 20)
    rng = np.random.default_rng(0)
    img = lambda xx: (np.where(square, 128.0, sine_texture(xx, y, 3)) + rng.normal(0, 1, (h, w))).astype(np.float32)
    a, b = rectified_views(img(x), img(x + 500.0 * 0.1 / dist_m))      # b: a point at column x of a is at x - d
    res = locate_dense(a, b)
    inner = np.zeros((h, w), bool)
    inner[45:75, 65:95] = True
    assert ((res.flags & LOW_TEXTURE) != 0)[inner].all()
    assert ((res.flags & VALID) != 0)[~square].mean() > 0.8              # measured 0.95 and 0.89
    filled = (res.flags & FILLED) != 0
    if dist_m < 100.0:
        assert filled[inner].mean() > 0.9
        assert np.median(np.abs(res.inv_range_per_m[filled & square] * dist_m - 1)) < 0.05
    else:
        assert not filled.any()
        assert np.isnan(res.range_m[inner]).all()


def test_pixels_the_infinity_test_takes_are_not_filled():
    """The dense method's infinity test takes VALID away where a point at infinity explains the window as well
    (ILL_CONDITIONED): the data do not support the range there. The fill must not hand those pixels a range from
    their neighbours' plane either (``exclude``). Turning preset at 256 px (rho the same with and without the test,
    which only flags): it takes 125 pixels whose estimates are off by a median 10.6 % against the simulator's truth
    (11 of them sky); with the exclusion dropped 51 of them were FILLED (median error 11 %)."""
    sp = make_pair("turning", seed=0, size=256)
    a, b = sp.views[:2]
    untested = locate_dense(a, b, fill=False, inf_test=False)
    bare = locate_dense(a, b, fill=False)
    res = locate_dense(a, b)
    taken = ((untested.flags & VALID) != 0) & ((bare.flags & (VALID | ILL_CONDITIONED)) == ILL_CONDITIONED)
    assert taken.sum() > 50
    with np.errstate(invalid="ignore", divide="ignore"):
        err = np.abs(untested.range_m[taken] / sp.truth[0].range_m[taken] - 1)
    assert np.median(err) > 0.05                                    # the test took poor estimates, not good ones
    assert not ((res.flags & FILLED) != 0)[taken].any()
    assert np.isnan(res.range_m[taken]).all()

@pytest.fixture(scope="module")
def turning():
    sp = make_pair("turning", seed=0, size=512)
    return sp, locate_dense(*sp.views[:2])


def test_dense_fill_on_a_turning_flight(turning):
    """The issue's target on the turning flight: a finite range for >= 90 % of the non-sky pixels at a median error
    <= 1 % (measured 90.8 % at 0.74 %; measured only: 75.3 % at 0.76 %); the FILLED pixels' sigma is not too small
    (robust z spread 0.79 <= 1, 98.3 % within 2 sigma; with the sigma scaled by 0.75 the spread would be 1.05). It is
    too large: see test_filled_sigma_is_calibrated."""
    sp, res = turning
    truth = sp.truth[0].range_m
    ground = np.isfinite(truth)
    est = ground & np.isfinite(res.range_m)
    assert est.sum() / ground.sum() >= 0.90
    rel = np.abs(res.range_m[est] / truth[est] - 1)
    assert np.median(rel) <= 0.01
    filled = ground & ((res.flags & FILLED) != 0)
    assert filled.sum() / ground.sum() > 0.10
    z = (res.inv_range_per_m[filled] - 1 / truth[filled]) / res.inv_range_std_per_m[filled]
    spread = 1.4826 * np.median(np.abs(z - np.median(z)))
    assert 0.5 < spread <= 1.0
    assert np.mean(np.abs(z) < 2) > 0.954                 # a Gaussian's share within 2 sigma
    assert not (((res.flags & FILLED) != 0) & ((res.flags & VALID) != 0)).any()     # (as bits: FILLED & VALID is 0)


@pytest.mark.xfail(strict=True, reason="the FILLED sigma over-reports: z spread 0.79 here, 0.56-1.07 over the sim "
                                       "presets at 256 and 512 px (geometric means 0.75 and 0.67), 0.14 on a plane "
                                       "with white noise of known sigma")
def test_filled_sigma_is_calibrated(turning):
    """A calibrated sigma gives a robust z spread of 1 (band 0.85-1.18 fails for a sigma 25 % off either way)."""
    sp, res = turning
    truth = sp.truth[0].range_m
    filled = np.isfinite(truth) & ((res.flags & FILLED) != 0)
    z = (res.inv_range_per_m[filled] - 1 / truth[filled]) / res.inv_range_std_per_m[filled]
    assert 0.85 < 1.4826 * np.median(np.abs(z - np.median(z))) < 1.18


def test_fill_off_leaves_unmeasured_pixels_empty(turning):
    sp, res = turning
    bare = locate_dense(*sp.views[:2], fill=False)
    assert not (bare.flags & FILLED).any()
    measured = (res.flags & VALID) != 0
    np.testing.assert_array_equal(measured, (bare.flags & VALID) != 0)
    np.testing.assert_array_equal(res.range_m[measured], bare.range_m[measured])
    assert np.isnan(bare.range_m[(res.flags & FILLED) != 0]).all()


def test_sky_beside_a_pole_is_not_filled():
    """The fast preset's faint sky beside the far pole and buildings: filling it from their plane fattened their
    silhouettes (deep sky FILLED: 2.3 % with no leverage rule, 1.2 % at leverage <= 3, 0.30 % at <= 1)."""
    sp = make_pair("fast", seed=0, size=512)
    res = locate_dense(*sp.views[:2])
    sky = np.isinf(sp.truth[0].range_m).astype(np.uint8)
    deep = cv2.erode(sky, np.ones((9, 9), np.uint8)) > 0
    filled_sky = deep & ((res.flags & FILLED) != 0)
    assert filled_sky.sum() / deep.sum() < 0.005


def fill_both_ways(bare, monkeypatch):
    """fill_unmeasured on copies of an unfilled result's arrays, by the numba kernels and by their numpy formulation
    (tests/fill_reference.py): [(n_filled, [rho, std, flags, range, confidence])] for each."""
    outs = []
    for reference in (False, True):
        if reference:
            fill_reference.use_reference(monkeypatch)
        arrs = [a.copy() for a in (bare.inv_range_per_m, bare.inv_range_std_per_m, bare.flags, bare.range_m,
                                   bare.confidence)]
        outs.append((fill_unmeasured(*arrs, max_rel_std=0.34, rho_far=1e-4), arrs))
    return outs


def test_fill_kernels_match_reference(turning, monkeypatch):
    """The numba passes and the numpy reference fill the same pixels with the same values (float rounding apart)."""
    sp, _ = turning
    bare = locate_dense(*sp.views[:2], fill=False)
    (n1, a1), (n0, a0) = fill_both_ways(bare, monkeypatch)
    assert n1 > 10000 and abs(n1 - n0) <= 1e-3 * n0
    both = ((a1[2] & FILLED) != 0) & ((a0[2] & FILLED) != 0)
    assert both.sum() >= 0.999 * n0
    np.testing.assert_allclose(a1[0][both], a0[0][both], rtol=5e-4)      # float64 vs float32 fits
    # sigma: the kernel fits in float64, the reference in float32, and the residual variance is a difference of
    # near-equal window sums (measured: within 1.5 %)
    np.testing.assert_allclose(a1[1][both], a0[1][both], rtol=0.03)


@pytest.mark.parametrize("size", [97, 333])
def test_fill_kernels_match_reference_at_sizes_not_divisible(size, monkeypatch):
    """Partial cells at the right and bottom edges: the kernels and the reference index cells as y >> k, x >> k
    and sum a partial cell exactly (maps that follow the size ratio, as cv2.resize's, were 38 % apart at 97 x 97)."""
    sp = make_pair("turning", seed=0, size=size)
    bare = locate_dense(*sp.views[:2], fill=False)
    (n1, a1), (n0, a0) = fill_both_ways(bare, monkeypatch)
    assert n1 == n0 > 100
    np.testing.assert_array_equal(a1[2], a0[2])
    filled = (a1[2] & FILLED) != 0
    # (the kernels fit in float64, the reference in float32: measured up to 2.4e-4 apart)
    np.testing.assert_allclose(a1[0][filled], a0[0][filled], rtol=5e-4)


def test_fill_kernels_match_reference_where_the_noise_floor_binds(monkeypatch):
    """An exact plane measured with a 1 % sigma: the plane fits leave no scatter, so a filled sigma is the support's
    own noise floor (the cells' mean noise variance). Kernels and reference agree on it."""
    rho = plane_rho((0.3, 0.05, 0.9), 20.0)
    flags = np.full(rho.shape, VALID, np.uint8)
    flags[60:75, 40:70] = LOW_TEXTURE
    outs = []
    for reference in (False, True):
        if reference:
            fill_reference.use_reference(monkeypatch)
        r, s, f, rg, cf = outputs(rho, flags)
        s[:] = 0.01 * rho
        outs.append((fill_unmeasured(r, s, f, rg, cf, max_rel_std=0.34), r, s))
    (n1, r1, s1), (n0, r0, s0) = outs
    hole = flags == LOW_TEXTURE
    assert n1 == n0 == hole.sum()
    np.testing.assert_allclose(r1[hole], r0[hole], rtol=1e-4)
    np.testing.assert_allclose(s1[hole], s0[hole], rtol=1e-3)
    # the floor: a cell mean's sigma, 1 % / sqrt(16 pixels per cell) = 0.25 % of rho, times sqrt(1 + (1 + leverage)
    # / n) (measured 0.25-0.32 %; without the floor the plane's float rounding alone: 0-0.07 %)
    rel = s1[hole] / rho[hole]
    assert rel.min() > 0.0024 and rel.max() < 0.0035, (rel.min(), rel.max())


def test_strict_pixels_are_filled_only_within_their_own_limit_by_kernels_and_reference(turning, monkeypatch):
    """A caller's strict pixels (here the OCCLUDED ones, never filled otherwise) are filled despite their no_fill
    bits, but only where the fill's relative sigma is within strict_rel_std; the other pixels exactly as without
    the mask. Kernels and reference agree."""
    sp, _ = turning
    bare = locate_dense(*sp.views[:2], fill=False)
    occ = (bare.flags & OCCLUDED) != 0
    runs = {}
    for reference in (False, True):
        if reference:
            fill_reference.use_reference(monkeypatch)
        for lim in (0.0, 0.05, 0.34):
            arrs = [a.copy() for a in (bare.inv_range_per_m, bare.inv_range_std_per_m, bare.flags, bare.range_m,
                                       bare.confidence)]
            n = fill_unmeasured(*arrs, max_rel_std=0.34, rho_far=1e-4, strict=occ if lim else None,
                                strict_rel_std=lim)
            runs[reference, lim] = n, arrs
    for lim in (0.05, 0.34):
        (n1, a1), (n0, a0) = runs[False, lim], runs[True, lim]
        assert abs(n1 - n0) <= 1e-3 * n0
        f1, f0 = (a1[2] & FILLED) != 0, (a0[2] & FILLED) != 0
        assert (f1 & occ).sum() > 20 and abs(int((f1 & occ).sum()) - int((f0 & occ).sum())) <= 5
        assert (a1[1][f1 & occ] <= lim * a1[0][f1 & occ] * (1 + 1e-6)).all()
        plain = (runs[False, 0.0][1][2] & FILLED) != 0               # the others: as without a strict mask
        np.testing.assert_array_equal(f1 & ~occ, plain)
    # both sides of the limit: 0.05 keeps a part of what 0.34 fills, the rest has a sigma between them
    tight, loose = (((runs[False, lim][1][2] & FILLED) != 0) & occ for lim in (0.05, 0.34))
    assert (tight <= loose).all() and 0 < tight.sum() < loose.sum()
    a = runs[False, 0.34][1]
    rel = a[1][loose & ~tight] / a[0][loose & ~tight]
    assert (rel > 0.05 * (1 - 1e-6)).all() and (rel <= 0.34 * (1 + 1e-6)).all()


@pytest.mark.parametrize("shape", [(60, 80), (25, 33), (7, 5), (1, 9)])
def test_moment_and_window_kernels_equal_numpy_and_opencv_bit_for_bit(shape):
    """The cells' moments, their 2 x 2 sums into the next octave and the 7 x 7 window sums (numba) give the very
    float32 values of numpy's array formulas and of OpenCV's box filter (tests/fill_reference.py), also at odd
    sizes and on grids smaller than the window: the fill's results do not depend on which computes them. Cell
    sums as the fill makes them: counts of 0..16 pixels, coordinate sums spread over [-16, 16], rho in units of
    its mean with some empty cells."""
    from eonav.ranging.methods._fill_kernels import down, moments, window_sums
    rng = np.random.default_rng(3)
    h, w = shape
    n = rng.integers(0, 17, shape).astype(np.float32)
    sr = (n * rng.lognormal(0, 0.5, shape)).astype(np.float32)
    sx = (n * rng.uniform(-1, 1, shape)).astype(np.float32)
    sy = (n * rng.uniform(-1, 1, shape)).astype(np.float32)
    sv = (n * rng.uniform(0, 1e-3, shape)).astype(np.float32)
    h_px, w_px = 4 * h - 1, 4 * w - 3          # partial last cells
    got, want = np.empty((12,) + shape, np.float32), np.empty((12,) + shape, np.float32)
    moments(n, sr, sx, sy, sv, 4, h_px, w_px, got)
    fill_reference.moments(n, sr, sx, sy, sv, 4, h_px, w_px, want)
    assert np.array_equal(got.view(np.uint32), want.view(np.uint32))
    assert want[11, -1, -1] == 3 * 1 and want[11, 0, 0] == min(4, h_px) * 4 and want[0].sum() == n.sum()
    S1, S0 = np.empty_like(want), np.empty_like(want)
    window_sums(want, S1)
    fill_reference.window_sums(want, S0)
    assert np.array_equal(S1.view(np.uint32), S0.view(np.uint32))
    assert S0[0, h // 2, w // 2] == n[max(h // 2 - 3, 0):h // 2 + 4, max(w // 2 - 3, 0):w // 2 + 4].sum()
    dshape = (12, -(-h // 2), -(-w // 2))
    D1, D0 = np.empty(dshape, np.float32), np.empty(dshape, np.float32)
    down(want, D1)
    fill_reference.down(want, D0)
    assert np.array_equal(D1.view(np.uint32), D0.view(np.uint32))
    assert D0[0].sum() == n.sum()


def test_a_valid_pixel_without_a_finite_rho_is_no_support():
    """A pixel flagged VALID whose rho is NaN or infinite (a caller's bad value) is not a measurement: it must not
    enter the sums. The holes of the plane are filled with the plane as without those pixels, and the bad pixels
    themselves are left as they came (VALID, not FILLED). Counted as support, one NaN made the measured mean, and so
    every window's plane, NaN: nothing was filled anywhere."""
    rho = plane_rho((0.3, 0.05, 0.9), 20.0)
    flags = np.full(rho.shape, VALID, np.uint8)
    holes = np.zeros(rho.shape, bool)
    holes[60:75, 40:70] = True
    flags[holes] = LOW_TEXTURE
    r, s, f, rg, cf = outputs(rho, flags)
    bad = [(30, 200), (100, 100), (180, 50), (220, 300)]
    for (y, x), val in zip(bad, (np.nan, np.inf, np.nan, -np.inf)):
        r[y, x] = val
    assert fill_unmeasured(r, s, f, rg, cf, max_rel_std=0.34) == holes.sum()
    assert ((f[holes] & FILLED) != 0).all()
    assert np.abs(r[holes] / rho[holes] - 1).max() < 1e-3             # an exact plane: float rounding only
    for y, x in bad:
        assert f[y, x] == VALID and not np.isfinite(r[y, x])


def test_occluded_out_of_view_pixels_are_not_extrapolated_even_when_strict():
    """Only a pixel out of view of image b and NOT occluded is extrapolated beyond the support (the ground band that
    has left the image); one both out of view and occluded sits at a depth edge. The fused map hands its occluded
    cells to the fill as ``strict`` (filled despite their no_fill bits when the plane is tight): an exact plane, a
    24 px band out of view at the left (extrapolated with the plane) and one out of view and occluded at the right,
    strict with a loose limit, whose pixels beyond the support stay empty."""
    rho = plane_rho((0.6, 0.0, 0.9), 15.0)
    flags = np.full(rho.shape, VALID, np.uint8)
    flags[:, :24] = OUT_OF_VIEW
    flags[:, -24:] = OUT_OF_VIEW | OCCLUDED
    r, s, f, rg, cf = outputs(rho, flags)
    strict = (flags & OCCLUDED) != 0
    fill_unmeasured(r, s, f, rg, cf, max_rel_std=0.34, strict=strict, strict_rel_std=0.34)
    left = (f[:, :24] & FILLED) != 0
    assert left.mean() > 0.95
    assert np.abs(r[:, :24][left] / rho[:, :24][left] - 1).max() < 0.01
    assert not ((f[:, -12:] & FILLED) != 0).any()                    # more than a few pixels beyond the support
    assert np.isnan(rg[:, -12:]).all()


@pytest.mark.parametrize("reference", [False, True])
def test_plane_fit_of_four_samples_against_ordinary_least_squares_by_hand(reference):
    """The per-cell plane kernel (and its numpy reference) on the window sums of four unit-weight samples: the
    textbook least-squares plane, derived by hand. Samples (x, y, r): (0, 0, 1), (2, 0, 3), (0, 2, 5), (1, 1, 5),
    i.e. r = 1 + x + 2 y plus 1 at the last. Residual space (orthogonal to 1, x, y): (0, -1, -1, 2)/sqrt 6, so the
    residuals are (0, -1, -1, 2)/3, SSR 2/3 and the fitted plane 1 + 7/6 x + 13/6 y. Centroid (3/4, 3/4),
    covariance [[11, -5], [-5, 11]]/16 (det 3/8); at the cell centre (3, 2): d = (9/4, 5/4), prediction 53/6,
    leverage d^T C^-1 d = (11 81 + 2 5 45 + 11 25)/256 / (3/8) = 101/6; residual variance SSR/(n - 3) = 2/3 and
    the prediction's error variance 2/3 (1 + (1 + 101/6)/4) = 131/36 (OLS: s^2 (1 + x0^T (X^T X)^-1 x0))."""
    from eonav.ranging.methods import _fill_kernels
    pts = np.array([(0, 0, 1), (2, 0, 3), (0, 2, 5), (1, 1, 5)], np.float64)
    x, y, rr = pts.T
    sums = [4, x.sum(), y.sum(), rr.sum(), (x * x).sum(), (x * y).sum(), (y * y).sum(), (x * rr).sum(),
            (y * rr).sum(), (rr * rr).sum(), 0.0, 4]                  # no noise floor; 4 pixels in the image
    S = [np.full((1, 1), s, np.float32) for s in sums]
    out = [np.empty((1, 1), np.float32) for _ in range(5)]           # p, v, b, c, lev
    plane = fill_reference.plane if reference else _fill_kernels.plane
    plane(*S, np.array([3.0], np.float32), np.array([2.0], np.float32), 0.3, 0.0, *out)
    p, v, b, c, lev = (float(a[0, 0]) for a in out)
    np.testing.assert_allclose([p, b, c, lev, v], [53 / 6, 7 / 6, 13 / 6, 101 / 6, 131 / 36], rtol=1e-5)


@pytest.mark.parametrize("corner", ["left", "right"])
def test_low_texture_beyond_a_diagonal_edge_of_the_support_is_not_filled(corner):
    """A sloping horizon: the measured ground ends along a diagonal (45 degrees, down to the left or to the right),
    textureless (maybe sky) beyond it. As beyond a level edge (the out-of-view test above), a pixel more than a few
    pixels past the support is an extrapolation (a half-plane's rim has leverage ~3 > LEV_MAX) and stays empty. Here
    the support's x and y spreads are correlated (either sign): a leverage that got the cross term's sign wrong filled
    870 pixels up to 28 px into the sky (measured: none beyond 5.7 px)."""
    rho = plane_rho((0.6, 0.0, 0.9), 15.0)
    v, u = np.mgrid[0:H, 0:W]
    across = u if corner == "left" else W - 1 - u
    dist = (across + v - 200) / np.sqrt(2)                            # px from the edge, < 0 beyond it
    flags = np.where(dist < 0, LOW_TEXTURE, VALID).astype(np.uint8)
    r, s, f, rg, cf = outputs(rho, flags)
    fill_unmeasured(r, s, f, rg, cf, max_rel_std=0.34)
    filled = (f & FILLED) != 0
    assert not filled[dist < -8].any()
    assert np.isnan(rg[dist < -8]).all()
