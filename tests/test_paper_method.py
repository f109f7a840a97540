"""The paper's derivative estimators (eqs. 34-42) and locator (eqs. 24-33, 7) against independent truth:
analytic images with known derivatives, and textured planes rendered by exact ray intersection (known
range at every pixel). Tolerances are measured behaviour (figures in the comments) with some margin."""
import numpy as np
import pytest

from eonav import InputError
from eonav.geometry.camera import Camera, VehicleState, View, pair_geometry
from eonav.ranging.derivatives import estimate_derivatives, noise_gains
from eonav.geometry.frames import k_coefficients
from eonav.ranging.methods.paper import (camera_points_eq32, disparity, locate_paper, ned_point_cloud, range_eq28)
from eonav.ranging.rangemap import LOW_TEXTURE, OUT_OF_VIEW, TRUNCATION, VALID, RangeResult

# ----------------------------------------------------------------------------------------------------------
# analytic scenes


def random_texture(seed, n=12, wl=(0.4, 4.0), amp=60.0, mean=120.0):
    """Non-separable band-limited texture on a plane: a sum of n oriented sinusoids (plane metres)."""
    rng = np.random.default_rng(seed)
    ang = rng.uniform(0, np.pi, n)
    lam = np.exp(rng.uniform(np.log(wl[0]), np.log(wl[1]), n))
    ph = rng.uniform(0, 2 * np.pi, n)
    a = amp / np.sqrt(n) * rng.uniform(0.5, 1.5, n)
    kx, ky = 2 * np.pi / lam * np.cos(ang), 2 * np.pi / lam * np.sin(ang)

    def tex(s, t):
        return mean + sum(a[i] * np.sin(kx[i] * s + ky[i] * t + ph[i]) for i in range(n))
    return tex


def separable_texture(s, t):
    """e1(s) e2(t), positive everywhere (so eq. 40 needs no bias)."""
    return 60 * (1.6 + np.sin(1.7 * s + 0.3) + 0.4 * np.sin(4.1 * s)) * (1.6 + np.cos(2.3 * t) + 0.3 * np.sin(5.3 * t + 1)) / 2.6


def render_planes(cam, state, planes, noise=0.0, seed=0, sky=200.0):
    """Ray-traced image and true range x_c. planes: (p0_ned, e_s, e_t, texture(s, t))."""
    m0, m1, m2 = (r.astype(float) for r in cam.rays())
    dirs = np.stack([m0, m1, m2], -1) @ cam.T_cam_body @ state.T_body_ned     # T2^T T1^T [1, xp/f, yp/f]
    org = state.position_ned_m + cam.l_body_m @ state.T_body_ned
    best = np.full(m0.shape, np.inf)
    img = np.full(m0.shape, sky)
    for p0, es, et, tex in planes:
        n = np.cross(es, et)
        with np.errstate(divide="ignore", invalid="ignore"):
            t = ((np.asarray(p0) - org) @ n) / (dirs @ n)
        P = org + t[..., None] * dirs
        upd = np.isfinite(t) & (t > 0) & (t < best)
        best[upd] = t[upd]
        img[upd] = tex(((P - p0) @ es)[upd], ((P - p0) @ et)[upd])
    if noise > 0:
        img = img + np.random.default_rng(seed).normal(0, noise, img.shape)
    return np.clip(img, 0, 255), best           # ray x-component is 1, so t is x_c


CAM = Camera("c", 192, 192, 240.0, 240.0, 95.5, 95.5)
S_A = VehicleState.from_ypr([0, 0, 0], [0, 0, 0])
S_SMALL = VehicleState.from_ypr([0.2, 0.04, 0.0], [0.0005, 0, 0.001])     # |d| median 0.61 px, max 1.3 px
S_LARGE = VehicleState.from_ypr([0.5, 0.5, 0.1], [0.003, 0, 0.002])       # |d| median 5.0 px, max 7.1 px


def wall(tex, north_m=30.0):
    """A fronto-parallel wall north_m ahead (the camera looks north)."""
    return (np.array([north_m, -50.0, -50.0]), np.array([0, 1.0, 0]), np.array([0, 0, 1.0]), tex)


def pair(state_b, tex=None, cam_b=CAM, noise=1.0):
    planes = [wall(tex or random_texture(1))]
    ia, ra = render_planes(CAM, S_A, planes, noise=noise, seed=1)
    ib, _ = render_planes(cam_b, state_b, planes, noise=noise, seed=2)
    return View(CAM, S_A, ia), View(cam_b, state_b, ib), ra


# ----------------------------------------------------------------------------------------------------------
# derivative estimators, eqs. (34)-(42)

GRID_V, GRID_U = np.mgrid[0:160, 0:160].astype(float)


def blobs(u, v, seed=3, n=30):
    """Sum of Gaussians (sigma 5-10 px) and its exact first and second derivatives."""
    rng = np.random.default_rng(seed)
    cu, cv = rng.uniform(0, 160, n), rng.uniform(0, 160, n)
    sg, A = rng.uniform(5, 10, n), rng.uniform(-50, 50, n)
    out = [np.full(u.shape, 120.0)] + [np.zeros(u.shape) for _ in range(5)]
    for i in range(n):
        du, dv, s2 = u - cu[i], v - cv[i], sg[i] ** 2
        g = A[i] * np.exp(-(du ** 2 + dv ** 2) / (2 * s2))
        for j, term in enumerate([g, -du / s2 * g, -dv / s2 * g, (du ** 2 / s2 - 1) / s2 * g,
                                  (dv ** 2 / s2 - 1) / s2 * g, du * dv / s2 ** 2 * g]):
            out[j] += term
    return out          # E, Ex, Ey, Exx, Eyy, Exy


def _rel(est, tru, sl=np.s_[30:, 30:]):
    return np.sqrt(np.mean((est - tru)[sl] ** 2)) / np.sqrt(np.mean(tru[sl] ** 2))


@pytest.mark.parametrize("disc", ["foh", "bilinear"])
@pytest.mark.parametrize("order", [1, 2])
@pytest.mark.parametrize("bw", [0.5, 2.0, 5.0])
def test_ramp_is_exact_with_foh_and_bilinear(disc, order, bw):
    """A ramp is the one image every consistent estimator must get exactly: dE/dx = 0.7, dE/dy = -0.4
    everywhere, E_hat = E delayed by order/a in x and y (the documented delay)."""
    E = 0.7 * GRID_U - 0.4 * GRID_V + 50
    d = estimate_derivatives(E, bandwidth_per_px=bw, order=order, discretisation=disc, combine="linear")
    sl = np.s_[60:, 60:]                                  # past the start-up of the ramp
    assert d.delay_px == pytest.approx(order / bw)
    np.testing.assert_allclose(d.Ex[sl], 0.7, atol=1e-9)
    np.testing.assert_allclose(d.Ey[sl], -0.4, atol=1e-9)
    np.testing.assert_allclose(d.E[sl], (0.7 * (GRID_U - d.delay_px) - 0.4 * (GRID_V - d.delay_px) + 50)[sl], atol=1e-9)


def test_zoh_point_sampled_derivative_overshoots_ramps():
    """Why FOH is the default: exact ZOH discretisation, output sampled at the pixel, gives the slope of a
    ramp times a / (1 - exp(-a)) (the input steps at each pixel and the derivative output sees the step)."""
    E = 0.7 * GRID_U + 50
    for bw in (0.5, 2.0):
        d = estimate_derivatives(E, bandwidth_per_px=bw, order=1, discretisation="zoh", combine="linear")
        np.testing.assert_allclose(d.Ex[60:, 60:], 0.7 * bw / (1 - np.exp(-bw)), rtol=1e-9)


def test_eq40_exact_for_separable_image_without_bias_and_bias_matters_otherwise():
    """Eq. (40) combines the passes exactly when E = e1(x) e2(y) (eq. 34): with no bias it equals the
    linear combination (column pass applied to r2) to rounding. The paper's note that a bias 'does not
    alter the partial derivative estimates' is not true: the biased image is no longer separable."""
    E = 20 * (2 + np.sin(0.2 * GRID_U)) * (3 + np.cos(0.15 * GRID_V))
    a = estimate_derivatives(E, bandwidth_per_px=1.0, order=2, bias=0.0, combine="eq40")
    b = estimate_derivatives(E, bandwidth_per_px=1.0, order=2, bias=0.0, combine="linear")
    for n in ("E", "Ex", "Ey", "Exx", "Eyy", "Exy"):
        np.testing.assert_allclose(getattr(a, n), getattr(b, n), atol=1e-9 * np.abs(getattr(b, n)).max())
    c = estimate_derivatives(E, bandwidth_per_px=1.0, order=2, combine="eq40")       # default bias
    sl = np.s_[20:, 20:]
    assert np.abs(c.Ex - b.Ex)[sl].max() > 0.02 * np.abs(b.Ex[sl]).max()            # measured 4.9 %
    assert np.abs(c.Exy - b.Exy)[sl].max() > 0.3 * np.abs(b.Exy[sl]).max()          # measured 66 %
    np.testing.assert_allclose(c.Ey, b.Ey, atol=1e-9)          # s2 does not involve r1: unaffected


def test_first_order_estimates_on_gaussians():
    """Gradients of a Gaussian field vs the analytic ones at the delayed position. Relative rms error
    measured: linear a=1: 3.4 % (x), 3.5 % (y); eq40 a=2: 6.4 % (x), 3.2 % (y). What remains is the
    low-pass attenuation of the estimator at the blobs' frequencies (~(w/a)^2/2 per axis)."""
    T0 = blobs(GRID_U, GRID_V)
    d = estimate_derivatives(T0[0], bandwidth_per_px=1.0, order=1, combine="linear")
    T = blobs(GRID_U - d.delay_px, GRID_V - d.delay_px)
    assert _rel(d.Ex, T[1]) < 0.05 and _rel(d.Ey, T[2]) < 0.05
    assert np.sqrt(np.mean((d.E - T[0])[30:, 30:] ** 2)) < 0.25          # measured 0.15 grey levels
    # not a test that cannot fail: without the delay correction (1 px here) the error is far larger
    assert _rel(d.Ex, T0[1]) > 4 * _rel(d.Ex, T[1])
    d = estimate_derivatives(T0[0], bandwidth_per_px=2.0, order=1, combine="eq40")
    T = blobs(GRID_U - d.delay_px, GRID_V - d.delay_px)
    assert _rel(d.Ex, T[1]) < 0.09 and _rel(d.Ey, T[2]) < 0.05


def test_second_order_estimates_on_gaussians():
    """Order-2 estimator, a=1 (linear): measured relative rms 6.4 % / 6.7 % (first), 16 % (xx, yy),
    10 % (xy). (At a >= 2 the second derivative of a first-order-hold input is sampled at its kinks:
    30-80 % errors; order 2 wants a <= 1.)"""
    T0 = blobs(GRID_U, GRID_V)
    d = estimate_derivatives(T0[0], bandwidth_per_px=1.0, order=2, combine="linear")
    T = blobs(GRID_U - d.delay_px, GRID_V - d.delay_px)
    assert _rel(d.Ex, T[1]) < 0.09 and _rel(d.Ey, T[2]) < 0.09
    assert _rel(d.Exx, T[3]) < 0.2 and _rel(d.Eyy, T[4]) < 0.2 and _rel(d.Exy, T[5]) < 0.13


@pytest.mark.parametrize("bw,order", [(0.5, 1), (1.0, 1), (2.0, 1), (1.0, 2)])
def test_noise_gains_predict_output_noise(bw, order):
    """White noise sigma=1: measured output std within 1 % of noise_gains (impulse-response energy)."""
    N = np.random.default_rng(5).normal(0, 1, (300, 300)) + 100
    d = estimate_derivatives(N, bandwidth_per_px=bw, order=order, combine="linear")
    sl = np.s_[50:, 50:]
    np.testing.assert_allclose([d.E[sl].std(), d.Ex[sl].std(), d.Ey[sl].std()], noise_gains(bw, order), rtol=0.04)


def test_derivative_input_errors():
    with pytest.raises(InputError, match="2-D"):
        estimate_derivatives(np.zeros(10))
    with pytest.raises(InputError, match="non-finite"):
        estimate_derivatives(np.full((5, 5), np.nan))
    with pytest.raises(InputError, match="bandwidth"):
        estimate_derivatives(np.zeros((5, 5)), bandwidth_per_px=0)
    with pytest.raises(InputError, match="order"):
        estimate_derivatives(np.zeros((5, 5)), order=3)
    with pytest.raises(InputError, match="discretisation"):
        estimate_derivatives(np.zeros((5, 5)), discretisation="euler")
    with pytest.raises(InputError, match="combine"):
        estimate_derivatives(np.zeros((5, 5)), combine="x")


# ----------------------------------------------------------------------------------------------------------
# the locator


def test_recovers_range_where_disparities_are_subpixel():
    """Wall 30 m ahead, |d| 0.6 px median. Measured median |relative error| over VALID pixels:
    linear combine a=0.5: 7.1 % (65 % of pixels); eq. (40) (paper) on a separable texture without bias:
    5.6 %; eq. (40) with its default bias on a non-separable texture: 47 % (docs: the bias breaks eq. 40)."""
    va, vb, ra = pair(S_SMALL)
    res = locate_paper(va, vb, bandwidth=0.5, combine="linear")
    ok = (res.flags & VALID) > 0
    err = np.abs(res.range_m / ra - 1)
    assert ok.mean() > 0.5
    assert np.median(err[ok]) < 0.10
    # confident points are the better ones
    hi, lo = ok & (res.confidence >= 10), ok & (res.confidence < 2)
    assert np.median(err[hi]) < 0.5 * np.median(err[lo])
    va, vb, ra = pair(S_SMALL, tex=separable_texture)
    res = locate_paper(va, vb, bandwidth=0.5, bias=0.0)                  # eq. (40), its own assumption met
    ok = (res.flags & VALID) > 0
    assert np.median(np.abs(res.range_m / ra - 1)[ok]) < 0.09


def z_spread(res, ra):
    """Robust spread (1.4826 x MAD) of z = (rho - rho_true) / sigma over VALID pixels: 1 for a calibrated sigma."""
    ok = (res.flags & VALID) > 0
    z = ((res.inv_range_per_m - 1 / ra) / res.inv_range_std_per_m)[ok]
    assert ok.sum() > 15000
    return 1.4826 * np.median(np.abs(z - np.median(z)))


def test_sigma_is_the_image_noise_propagated():
    """The reported sigma is white image noise propagated to first order through the estimators and eq. (28)
    (module docstring, item 6). Where that noise dominates the error (4 grey levels on the textured wall, small
    motion) it is the error's size: z spread measured 0.98-1.01 over three noise seeds. The band fails for a sigma
    25 % off either way."""
    va, vb, ra = pair(S_SMALL, noise=4.0)
    res = locate_paper(va, vb, bandwidth=0.5, combine="linear", noise_sigma=4.0)
    assert 0.85 < z_spread(res, ra) < 1.18


@pytest.mark.xfail(strict=True, reason="the sigma models image noise only: at 1 grey level the model error (Taylor "
                                       "truncation, estimator bias) dominates: z spread 1.58-1.60, median z -0.66 to -0.71")
def test_sigma_is_calibrated_at_low_noise():
    va, vb, ra = pair(S_SMALL)
    assert 0.85 < z_spread(locate_paper(va, vb, bandwidth=0.5, combine="linear"), ra) < 1.18


def test_c1_sign_e1_minus_e2_is_right():
    """Eq. (31) prints c1 = E2 - E1; eq. (27) implies E1 - E2. The scene decides: with E1 - E2 the
    closed form (28) gives the true range, with E2 - E1 it gives nonsense (mostly negative ranges)."""
    va, vb, ra = pair(S_SMALL)
    d1 = estimate_derivatives(va.image, bandwidth_per_px=0.5, combine="linear")
    d2 = estimate_derivatives(vb.image, bandwidth_per_px=0.5, combine="linear")
    pg = pair_geometry(va, vb)
    u, v = CAM.pixel_grid()
    xp, yp = u - CAM.cx - d1.delay_px, v - CAM.cy - d1.delay_px
    k = k_coefficients(pg.R_ba, pg.t_ba_m, xp, yp, CAM.fx)
    a1, b1 = 0.5 * (d1.Ex + d2.Ex), 0.5 * (d1.Ey + d2.Ey)
    s = 2                                                       # round(delay): compare on the shifted grid
    truth = ra[:-s, :-s]
    sel = (np.abs(d1.E - d2.E) > 2)[s:, s:]
    for c1, good in ((d1.E - d2.E, True), (d2.E - d1.E, False)):
        xc = range_eq28(a1, b1, c1, k, xp, yp, CAM.fx)[0][s:, s:]
        med = np.median((xc / truth - 1)[sel])
        if good:
            assert abs(med) < 0.05                            # measured -0.4 %
        else:
            assert med < -1.0                                 # x_c ~ -x_true: measured -1.9
            assert np.mean(xc[sel] > 0) < 0.25


def test_eq28_inverts_exact_disparities_with_unequal_focal_lengths():
    """Eq. (28) is the exact solution of c1 = a1 dx + b1 dy (eq. 27 to first order) with dx, dy of eqs. (25)-(26):
    given c1 built from the true disparities of 3-D points (projected with eqs. 8, 9, 12, 15 by a camera with
    fx != fy and a translation down as well as forward) and any gradient, it returns the true x_c. Its y-rows take
    fy (My = fy k5 - yp k3, Ny = fy k2 - yp k0): with fx in My the median error is 19 %, in Ny 9 % (measured)."""
    from eonav.geometry.frames import T_body_ned_from_ypr, T_cam_body_from_eps, camera_from_ned, relative_pose
    rng = np.random.default_rng(28)
    fx, fy = 240.0, 300.0
    T1, l_m = T_cam_body_from_eps(np.deg2rad([1.0, -2.0, 0.5])), np.array([2.0, 0.3, 0.5])
    T2a, T2b = T_body_ned_from_ypr(0.1, 0.02, -0.01), T_body_ned_from_ypr(0.102, 0.023, -0.006)
    xva, xvb = np.zeros(3), np.array([0.4, 0.1, 0.3])
    x_true = np.exp(rng.uniform(np.log(5), np.log(300), 200))
    Xa = np.stack([x_true, x_true * rng.uniform(-0.4, 0.4, 200), x_true * rng.uniform(-0.3, 0.3, 200)], 1)
    world = Xa @ T1 @ T2a + l_m @ T2a + xva                     # eq. (33): x = x_v + T2^T (T1^T x_c + l)
    Xb = camera_from_ned(world, T1, T2b, xvb, l_m)
    xp, yp = fx * Xa[:, 1] / Xa[:, 0], fy * Xa[:, 2] / Xa[:, 0]
    dx, dy = fx * Xb[:, 1] / Xb[:, 0] - xp, fy * Xb[:, 2] / Xb[:, 0] - yp
    a1, b1 = rng.normal(0, 5, 200), rng.normal(0, 5, 200)
    c1 = a1 * dx + b1 * dy
    R, t = relative_pose(T1, T2a, xva, l_m, T1, T2b, xvb, l_m)
    k = k_coefficients(R, t, xp, yp * fx / fy, fx)              # m2 = y_p / fy, as locate_paper passes it
    xc = range_eq28(a1, b1, c1, k, xp, yp, fx, fy)[0]
    np.testing.assert_allclose(xc, x_true, rtol=1e-8)


def test_truncation_flag_fires_where_disparities_are_large():
    """Eq. (7) test with the default (paper) settings: share of computed pixels flagged, measured
    ~17 % at |d| ~ 0.6 px and ~89 % at |d| ~ 5 px."""
    fr = []
    for st in (S_SMALL, S_LARGE):
        va, vb, ra = pair(st)
        res = locate_paper(va, vb)
        comp = np.isfinite(res.range_m)
        fr.append(np.mean((res.flags[comp] & TRUNCATION) > 0))
        assert not np.any(((res.flags & TRUNCATION) > 0) & ((res.flags & VALID) > 0))    # (bits: not flags & flags)
        assert np.all(res.confidence[(res.flags & TRUNCATION) > 0] == 0)
    assert fr[0] < 0.3 and fr[1] > 0.75


def test_truncation_ratio_vanishes_on_a_quadratic_image():
    """Eq. (7) with the averaged gradient is the whole second-order Taylor remainder: for an image quadratic in
    (x_p, y_p) shifted by a uniform disparity it is exactly zero (hand: (grad E2 - grad E1).d = -d'H d and the
    Hessian term gives +d'H d). Wall texture 110 + 3 s + 3 t + 0.4 s t (metres) seen 0.5 m right and down (d = -4 px
    on both axes); the order-1 estimators are exact on it (linear along every row and column) and so is eq. (28).
    Measured past the start-up: ratio median 3e-7, max 4e-6, range error <= 1.5e-6 (float32). Catches the cross
    term of eq. (7) without its factor 2 (ratio median 0.027) and any other term off."""
    def quad(s, t):
        s, t = s - 50.0, t - 50.0
        return 110 + 3 * s + 3 * t + 0.4 * s * t
    va, vb, ra = pair(VehicleState.from_ypr([0.0, 0.5, 0.5], [0, 0, 0]), tex=quad, noise=0.0)
    res = locate_paper(va, vb, combine="linear", min_gradient=0.5, min_change=0.5)
    inner = np.zeros(ra.shape, bool)
    inner[50:, 50:] = True                # past the causal estimators' start-up (exp(-0.25 n): 2e-4 left at 30 px)
    sel = inner & np.isfinite(res.range_m)
    assert sel.sum() > 15000
    np.testing.assert_allclose(res.range_m[sel], ra[sel], rtol=1e-5)
    tr = res.info["truncation_ratio"][sel]
    assert tr.max() < 1e-4
    assert np.all(res.flags[sel] & VALID)


def _out_of_view_against_map_to_b(cam_b: Camera):
    """The paper method on a wall seen by a 160 x 96 camera a and ``cam_b`` moved right and down (the wall moves ~5 px
    left and ~2 px up): (result, pixels with a range, pixels whose own inverse range maps them outside image b's own
    pixels by PairGeometry.map_to_b), after checking that OUT_OF_VIEW flags exactly those."""
    cam = Camera("wide", 160, 96, 240.0, 240.0, 79.5, 47.5)
    sb = VehicleState.from_ypr([0.0, 0.6, 0.25], [0, 0, 0])
    planes = [wall(random_texture(1))]
    ia, _ = render_planes(cam, S_A, planes, noise=1.0, seed=1)
    ib, _ = render_planes(cam_b or cam, sb, planes, noise=1.0, seed=2)
    va, vb = View(cam, S_A, ia), View(cam_b or cam, sb, ib)
    res = locate_paper(va, vb)
    has = np.isfinite(res.range_m)
    ub, vb_, _ = pair_geometry(va, vb).map_to_b(np.where(has, res.inv_range_per_m, 0.0))
    cb = vb.camera
    leaves = (ub < 0) | (ub > cb.width - 1) | (vb_ < 0) | (vb_ > cb.height - 1)
    np.testing.assert_array_equal(((res.flags & OUT_OF_VIEW) > 0)[has], leaves[has])
    return res, has, leaves


def test_out_of_view_flags_exactly_the_points_that_leave_image_b():
    """OUT_OF_VIEW means the point leaves image b (eonav.ranging.rangemap): a pixel with a range is flagged exactly
    when its own inverse range puts it outside image b by the exact mapping (PairGeometry.map_to_b, eqs. 25-26);
    the left columns and top rows leave. Catches the test done on the estimators' delayed grid at the pixel index
    instead of the delayed position (off by the delay, 4 px: points that left b by up to 4 px kept VALID on the left
    and top, in-view points flagged on the right and bottom) and a width / height swap."""
    res, has, leaves = _out_of_view_against_map_to_b(None)
    assert res.info["delay_px"] == 4.0
    assert (leaves & has)[:, :4].sum() > 50 and (leaves & has)[:2].sum() > 50       # not a vacuous check
    # OUT_OF_VIEW clears VALID and the confidence (as bits: '(flags & OUT_OF_VIEW) & (flags & VALID)' is 0 always)
    oov = (res.flags & OUT_OF_VIEW) > 0
    assert not np.any(oov & ((res.flags & VALID) > 0)) and np.all(res.confidence[oov] == 0)


def test_out_of_view_with_another_camera_b_is_judged_in_image_b():
    """View b from a camera with a narrower view (fx 300 against a's 240, same size): image b is resampled to a's
    intrinsics, and a point is OUT_OF_VIEW exactly when its own inverse range maps it outside image b's own pixels
    (PairGeometry.map_to_b with b's intrinsics, independent of the resampling). Catches the resampling's inside-b
    mask read at the point's pixel of a instead of where the point lands in b (19 % of the flags wrong, measured)."""
    _, has, leaves = _out_of_view_against_map_to_b(Camera("narrow", 160, 96, 300.0, 300.0, 79.5, 47.5))
    assert (leaves & has).sum() > 500 and (~leaves & has).sum() > 500                  # both sides present


def _stripes(w):
    """Stripes across the wall's w coordinate only: the image gradient is along one image axis."""
    return 120 + 50 * np.sin(2 * np.pi * w / 1.3) + 20 * np.sin(2 * np.pi * w / 0.55 + 1.0)


@pytest.mark.parametrize("axis", ["y", "x"])
def test_ranges_where_the_gradient_is_along_one_image_axis_only(axis):
    """The texture test is on the gradient's norm |(a1, b1)|: horizontal stripes seen while descending 0.1 m
    (vertical disparity, a1 ~ 0) and vertical stripes seen while moving 0.1 m right (b1 ~ 0) are both ranged.
    Measured: 77 % of the pixels VALID, median |error| 3.1 % / 3.3 % against the wall's 30 m. Catches the
    threshold on |a1| or |b1| alone (no pixel ranged at all)."""
    if axis == "y":
        tex, st = (lambda s, t: _stripes(t)), VehicleState.from_ypr([0.0, 0.0, 0.1], [0, 0, 0])
    else:
        tex, st = (lambda s, t: _stripes(s)), VehicleState.from_ypr([0.0, 0.1, 0.0], [0, 0, 0])
    va, vb, ra = pair(st, tex=tex)
    res = locate_paper(va, vb)
    ok = (res.flags & VALID) > 0
    assert ok.mean() > 0.6
    assert np.median(np.abs(res.range_m / ra - 1)[ok]) < 0.06


def test_max_range_discards_estimates_beyond_it():
    """max_range_m: an estimate beyond it is no range (NaN, ILL_CONDITIONED, not VALID); nearer ones are kept as
    they are. With the limit at 20 m on the wall at 30 m most computed pixels go (measured 83 %; 4 % of all pixels
    still come out under 20 m, the estimator's error tail)."""
    from eonav.ranging.rangemap import ILL_CONDITIONED
    va, vb, _ = pair(S_SMALL)
    full = locate_paper(va, vb)
    near = locate_paper(va, vb, max_range_m=20.0)
    keep = np.isfinite(full.range_m) & (full.range_m <= 20.0)
    np.testing.assert_array_equal(np.isfinite(near.range_m), keep)
    np.testing.assert_array_equal(near.range_m[keep], full.range_m[keep])
    gone = np.isfinite(full.range_m) & ~keep
    assert gone.sum() > 5000
    assert np.all(near.flags[gone] & ILL_CONDITIONED) and not np.any(near.flags[gone] & VALID)
    assert np.all(near.confidence[gone] == 0)


def _smooth_texture():
    """Wall texture of long wavelengths (4-10 m: 32-80 px at 30 m), well under the estimator's bandwidth (0.25 /px),
    where its delay is the documented low-frequency one, order / a = 4 px (finer texture is delayed less)."""
    return random_texture(7, wl=(4.0, 10.0), amp=80.0)


def test_geometry_is_evaluated_at_the_estimators_delayed_position():
    """The estimates at index (v, u) describe the image at (u - delay, v - delay), so eqs. (24)-(28) take x_p, y_p
    there. Forward motion 1 m towards the wall (disparity ~ x_p / 30): x_p off by the 4 px delay scales the range
    by (x_p + 4) / x_p, too near left of the centre and too far right of it, ~2 x 4 / 60 = 13 % apart in bands at
    |x_p| ~ 60 px. Measured right-minus-left (bottom-minus-top) median signed error: -1.0 % (-3.1 %); texture seeds
    8-10 within +-4 %; with x_p (y_p) not delayed +10 to +14 % (+9 to +14 %). All pixels: 4.0 % median |error|."""
    u, v = CAM.pixel_grid()
    xp, yp = u - CAM.cx, v - CAM.cy
    va, vb, ra = pair(VehicleState.from_ypr([1.0, 0.0, 0.0], [0, 0, 0]), tex=_smooth_texture())
    res = locate_paper(va, vb, combine="linear")
    ok = (res.flags & VALID) > 0
    err = res.range_m / ra - 1
    assert ok.mean() > 0.6 and np.median(np.abs(err[ok])) < 0.06
    med = []
    for band in ((xp < -15) & (np.abs(yp) < 25), (xp > 15) & (np.abs(yp) < 25),
                 (yp < -15) & (np.abs(xp) < 25), (yp > 15) & (np.abs(xp) < 25)):
        assert (ok & band).sum() > 2000
        med.append(np.median(err[ok & band]))
    assert abs(med[1] - med[0]) < 0.065 and abs(med[3] - med[2]) < 0.065


def test_locator_with_unequal_focal_lengths():
    """Camera with fx 240, fy 300 px, moving 1 m forward and rolling 0.03 rad: eq. (24) takes m2 = y_p / fy (the
    x-rows fx, the y-rows fy). Measured median |error| against the wall's 30 m: 4.5 % over the 70 % of the pixels
    VALID; with m2 = y_p / fx (the roll's disparity 25 % off in the x-rows) 10.9 %."""
    cam = Camera("fxfy", 192, 192, 240.0, 300.0, 95.5, 95.5)
    sb = VehicleState.from_ypr([1.0, 0.0, 0.0], [0.0, 0.0, 0.03])
    planes = [wall(_smooth_texture())]
    ia, ra = render_planes(cam, S_A, planes, noise=1.0, seed=1)
    ib, _ = render_planes(cam, sb, planes, noise=1.0, seed=2)
    res = locate_paper(View(cam, S_A, ia), View(cam, sb, ib), combine="linear")
    ok = (res.flags & VALID) > 0
    assert ok.mean() > 0.6
    assert np.median(np.abs(res.range_m / ra - 1)[ok]) < 0.07


def test_no_motion_gives_no_confident_ranges():
    va, vb, _ = pair(S_A)                                      # hover: same pose, new noise
    res = locate_paper(va, vb)
    assert not np.any(np.isfinite(res.range_m))
    assert np.all(res.confidence == 0) and not np.any(res.flags & VALID)
    assert np.mean((res.flags & LOW_TEXTURE) > 0) > 0.9        # noise-only change rarely passes min_change


def test_different_intrinsics_resampled_to_reference():
    """View b from another camera (other f, principal point and size): image b is resampled to a's
    intrinsics first. Measured median error 13.6 % (same camera: 7.1 %): the bilinear resampling blurs
    image b (texture and noise) relative to image a, which eq. (27) reads as irradiance change."""
    cam_b = Camera("b", 210, 180, 265.0, 265.0, 101.0, 92.0)
    va, vb, ra = pair(S_SMALL, cam_b=cam_b)
    res = locate_paper(va, vb, bandwidth=0.5, combine="linear")
    ok = (res.flags & VALID) > 0
    assert ok.mean() > 0.4
    assert np.median(np.abs(res.range_m / ra - 1)[ok]) < 0.18


def test_point_cloud_eqs_32_33_lies_on_the_wall():
    va, _, ra = pair(S_SMALL)
    res = RangeResult(ra.astype(np.float32), np.ones_like(ra, np.float32), "truth",
                      flags=np.full(ra.shape, VALID, np.uint8))
    ned, vu = ned_point_cloud(res, va)
    assert ned.shape == (ra.size, 3) and vu.shape == (ra.size, 2)
    np.testing.assert_allclose(ned[:, 0], 30.0, atol=1e-3)     # float32 range, 30 m
    pc = camera_points_eq32(ra, CAM)
    np.testing.assert_allclose(pc[..., 1] / pc[..., 0], (CAM.pixel_grid()[0] - CAM.cx) / CAM.fx, atol=1e-6)
    # camera a at the NED origin, level, looking north (FRD = NED): the pixel (u, v) sees the wall point
    # 30 m north, 30 (u - cx) / fx east and 30 (v - cy) / fy down (pinhole): below the centre row is below
    u, v = (g[tuple(vu.T)] for g in CAM.pixel_grid())
    np.testing.assert_allclose(ned[:, 1], 30.0 * (u - CAM.cx) / CAM.fx, atol=1e-3)
    np.testing.assert_allclose(ned[:, 2], 30.0 * (v - CAM.cy) / CAM.fy, atol=1e-3)


def test_locator_input_errors():
    va, vb, _ = pair(S_SMALL)
    with pytest.raises(InputError, match="View"):
        locate_paper(va.image, vb)
    with pytest.raises(InputError, match="min_gradient"):
        locate_paper(va, vb, min_gradient=-1)
    with pytest.raises(InputError, match="truncation_tol"):
        locate_paper(va, vb, truncation_tol=0)
    with pytest.raises(InputError, match="max_range_m"):
        locate_paper(va, vb, max_range_m=0)
    with pytest.raises(InputError, match="order"):
        locate_paper(va, vb, order=3)
    with pytest.raises(InputError, match="shape"):
        camera_points_eq32(np.zeros((3, 3)), CAM)


def test_disparity_matches_map_to_b():
    """eonav.ranging.methods.paper.disparity (eqs. 25-26) agrees with the exact PairGeometry.map_to_b."""
    va, vb, ra = pair(S_LARGE)
    pg = pair_geometry(va, vb)
    u, v = CAM.pixel_grid()
    xp, yp = u - CAM.cx, v - CAM.cy
    dx, dy, _ = disparity(k_coefficients(pg.R_ba, pg.t_ba_m, xp, yp, CAM.fx), xp, yp, CAM.fx, CAM.fy, 1 / ra)
    ub, vb_, _ = pg.map_to_b(1 / ra)
    np.testing.assert_allclose(u + dx, ub, atol=2e-3)
    np.testing.assert_allclose(v + dy, vb_, atol=2e-3)


# ----------------------------------------------------------------------------------------------------------
# the simulator's replica of the paper's flight

def test_paper_preset_table1():
    """Sim "paper" preset, default (paper-faithful) settings. Measured (seed 0, final preset with the
    vehicles at exactly 356.4 / 607.0 / 232.8 ft), median over each vehicle's VALID pixels: vehicle 1
    +20.7 % (184 px), vehicle 2 +36.8 % (68 px), vehicle 3 +67.3 % (129 px); valid coverage 3.2 %.
    Bounds: about 1.3x the measured errors, so a regression shows. True disparities there are ~1.3,
    ~2.5 and ~7 px (with ~1 px from rotation alone), past the first-order model's comfort: the paper's
    own Table I errors were 5.8 / 34.8 / 13.2 %."""
    presets = pytest.importorskip("eonav.sim.presets")
    sp = presets.make_pair("paper", seed=0)
    a, b = sp.views
    gt, oid = sp.truth[0].range_m, sp.truth[0].object_id
    res = locate_paper(a, b)
    ok = (res.flags & VALID) > 0
    ids = {n: i for i, n in sp.objects.items()}
    bounds = {"vehicle1": 0.27, "vehicle2": 0.48, "vehicle3": 0.88}
    for name, bound in bounds.items():
        m = ok & (oid == ids[name])
        assert m.sum() >= 20, name
        err = abs(np.median(res.range_m[m]) / np.median(gt[m]) - 1)
        assert err < bound, (name, err)
    assert 0.01 < ok.mean() < 0.10
