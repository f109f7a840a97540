"""The per-pixel inverse-range filter (eonav.fusion) against hand-derived values and simulated truth."""
import copy
import math

import numpy as np
import pytest

from eonav import InputError
from eonav.geometry.camera import Camera, VehicleState, View
from eonav.fusion.fused_map import MapConfig, fused_map
from eonav.fusion.predict import ProcessNoise, predict
from eonav.fusion.schedule import ScheduleConfig
from eonav.fusion.sequence import FusionConfig, FusionRunner, frame
from eonav.fusion.state import InverseRangeState, optional_kernels
from eonav.fusion.update import UpdateConfig, update
from eonav.ranging.rangemap import FILLED, ILL_CONDITIONED, LOW_TEXTURE, OCCLUDED, OUT_OF_VIEW, TRUNCATION, VALID

NO_NOISE = ProcessNoise(0.0, 0.0, 0.0)
PATHS = [False] + ([True] if optional_kernels() is not None else [])
F = 40.0


def cam(w=64, h=48, f=F):
    return Camera("c", w, h, f, f, (w - 1) / 2, (h - 1) / 2)


def pose(north=0.0, east=0.0, t=0.0):
    return VehicleState.from_ypr([north, east, 0.0], [0.0, 0.0, 0.0], t)


def planar_state(c, rho, var=1e-6):
    st = InverseRangeState.empty(c, pose(), 0.0)
    st.rho[...] = rho
    st.var[...] = var
    st.a[...] = 5.0
    st.b[...] = 1.0
    st.n[...] = 3
    return st


def converged_plane(empty=None):
    """A 64 x 48 camera and a converged state on the plane rho = 0.05 + 0.0004 u - 0.0003 v (sigma 1e-4), the cells
    of ``empty`` (an index) emptied; returns (camera, plane, state)."""
    c = cam(64, 48)
    vs, us = np.mgrid[0:48, 0:64].astype(np.float32)
    plane = (0.05 + 0.0004 * us - 0.0003 * vs).astype(np.float32)
    st = planar_state(c, plane, var=1e-8)
    if empty is not None:
        st.rho[empty], st.var[empty], st.a[empty], st.b[empty], st.n[empty] = np.nan, np.inf, 0.0, 0.0, 0
    return c, plane, st



@pytest.mark.parametrize("kernels", PATHS)
def test_forward_motion_carries_a_plane_to_the_pixels_and_inverse_ranges_derived_by_hand(kernels):
    # fronto-parallel plane at 20 m, camera 2 m forward (no rotation): every point is at 18 m in the new frame,
    # rho' = (1/20) / (1 - 2/20) = 1/18, and pixel u goes to cx + (u - cx) * 20/18; var' = var / 0.9^4 (Jacobian
    # d rho'/d rho = 1/den^2 with den = 0.9)
    c = cam()
    st = planar_state(c, 1 / 20.0)
    p = predict(st, c, pose(north=2.0, t=0.1), 0.1, NO_NOISE, kernels=kernels)
    inner = (slice(3, -3), slice(3, -3))
    assert np.isfinite(p.rho[inner]).all()                # stretching leaves cracks: closed, their neighbours agree
    assert np.allclose(p.rho[inner], 1 / 18.0, rtol=1e-6)
    assert np.allclose(p.var[inner], 1e-6 / 0.9 ** 4, rtol=1e-5)
    # cx = 31.5: the point of source pixel 41 (x_p = 9.5) lands at x_p' = 9.5 * 20/18 = 10.556, pixel 42 with a
    # remainder of 0.056 px, and keeps its evidence (no other point lands there: 40 -> 40.94, 42 -> 43.17)
    assert p.du[24, 42] == pytest.approx(31.5 + 9.5 * 20 / 18 - 42, abs=1e-4)
    assert p.dv[24, 42] == pytest.approx((24 - 23.5) * 20 / 18 + 23.5 - 24, abs=1e-4)
    assert p.a[24, 42] == 5.0 and p.b[24, 42] == 1.0 and p.n[24, 42] == 3
    # moving forward the new view lies inside the old one; moving back 2 m it is wider: its border saw nothing
    # (x_p' = x_p * 20/22: the old image's edge x_p = -31.5 lands at -28.6, so new columns 0..2 start empty)
    back = predict(st, c, pose(north=-2.0, t=0.1), 0.1, NO_NOISE, kernels=kernels)
    assert np.allclose(back.rho[np.isfinite(back.rho)], 1 / 22.0, rtol=1e-6)
    assert not np.isfinite(back.rho[:, :3]).any() and np.isfinite(back.rho[5:-5, 3]).all()


@pytest.mark.parametrize("kernels", PATHS)
def test_process_noise_terms_derived_by_hand(kernels):
    """Each term of the predicted variance (module docstring): var' = J^2 var + rho'^2 (q_s^2 dt + q_m^2 |t|) +
    q_abs^2 dt. Plane at 20 m, camera 2 m forward: rho' = 1/18, J^2 var = 1e-6 / 0.9^4 = 1.5242e-6 (the first
    test). Each noise alone: q_m = 0.01 with dt = 0 adds (1/18)^2 1e-4 2 m = 6.173e-7; q_s = 0.02 over 0.25 s adds
    (1/18)^2 4e-4 0.25 = 3.086e-7; q_abs = 1e-3 over 0.25 s adds 2.5e-7. Catches a dropped term (the distance one
    is otherwise only checked against the numba kernel) or one in other units."""
    c = cam()
    st = planar_state(c, 1 / 20.0)
    inner = (slice(3, -3), slice(3, -3))
    base = 1e-6 / 0.9 ** 4
    for noise, t, add in ((ProcessNoise(0.0, 0.01, 0.0), 0.0, 6.1728395e-7),
                          (ProcessNoise(0.02, 0.0, 0.0), 0.25, 3.0864198e-7),
                          (ProcessNoise(0.0, 0.0, 1e-3), 0.25, 2.5e-7)):
        p = predict(st, c, pose(north=2.0, t=t), t, noise, kernels=kernels)
        assert np.allclose(p.rho[inner], 1 / 18.0, rtol=1e-6)
        assert np.allclose(p.var[inner], base + add, rtol=1e-5), noise


@pytest.mark.parametrize("kernels", PATHS)
def test_sub_pixel_motion_is_not_rounded_away(kernels):
    # one point at 20 m, camera 0.55 m to starboard per frame: the image moves 40 * 0.55 / 20 = 1.1 px left per
    # frame; after 5 frames the point must be 5.5 px left (rounding each step without the remainder: 5 px)
    c = cam()
    st = InverseRangeState.empty(c, pose(), 0.0)
    st.rho[20, 40], st.var[20, 40], st.a[20, 40], st.b[20, 40] = 0.05, 1e-6, 3.0, 1.0
    for k in range(1, 6):
        st = predict(st, c, pose(east=0.55 * k, t=0.1 * k), 0.1 * k, NO_NOISE, crack_k=0, kernels=kernels)
    ys, xs = np.nonzero(np.isfinite(st.rho))
    assert list(ys) == [20] and len(xs) == 1
    assert xs[0] + st.du[20, xs[0]] == pytest.approx(40 - 5.5, abs=1e-4)
    assert st.rho[20, xs[0]] == pytest.approx(0.05, rel=1e-6)        # lateral motion: range unchanged


@pytest.mark.parametrize("kernels", PATHS)
def test_z_buffer_keeps_the_nearest_point(kernels):
    # camera 1 m to starboard: a point at 10 m moves 4 px left, one at 20 m 2 px: from columns 30 and 28 both land
    # on column 26; the nearer one (rho' = 0.1) must win
    c = cam()
    st = InverseRangeState.empty(c, pose(), 0.0)
    for x, rho, a in ((30, 0.1, 7.0), (28, 0.05, 2.0)):
        st.rho[10, x], st.var[10, x], st.a[10, x], st.b[10, x] = rho, 1e-6, a, 1.0
    p = predict(st, c, pose(east=1.0, t=0.1), 0.1, NO_NOISE, crack_k=0, kernels=kernels)
    assert np.isfinite(p.rho).sum() == 1
    assert p.rho[10, 26] == pytest.approx(0.1) and p.a[10, 26] == 7.0


@pytest.mark.parametrize("kernels", PATHS)
def test_z_buffer_keeps_the_nearest_point_also_when_it_is_scattered_first(kernels):
    """The mirror of the test above: camera 1 m to port, the point at 10 m (column 26) moves 4 px right, the one at
    20 m (column 28) 2 px: both land on column 30, the nearer one now the first in scan order. It must win there
    too, not by being written last. Catches a z-buffer keeping the farthest (np.minimum.at: every point then
    'wins' and the last one scattered overwrites)."""
    c = cam()
    st = InverseRangeState.empty(c, pose(), 0.0)
    for x, rho, a in ((26, 0.1, 7.0), (28, 0.05, 2.0)):
        st.rho[10, x], st.var[10, x], st.a[10, x], st.b[10, x] = rho, 1e-6, a, 1.0
    p = predict(st, c, pose(east=-1.0, t=0.1), 0.1, NO_NOISE, crack_k=0, kernels=kernels)
    assert np.isfinite(p.rho).sum() == 1
    assert p.rho[10, 30] == pytest.approx(0.1) and p.a[10, 30] == 7.0


@pytest.mark.parametrize("kernels", PATHS)
def test_forward_motion_fills_the_new_view_to_its_last_row_and_column(kernels):
    """Plane at 20 m, camera 2 m forward (the first test): x_p' = x_p 20/18, the new view is the old one's inner
    90 %, so every new pixel, the border ones included, gets a point: source column 60 (x_p = 28.5) lands at
    u' = 31.5 + 31.67 = 63.17 (column 63, remainder 0.167), column 3 at -0.17 (column 0); source row 45
    (y_p = 21.5) at v' = 23.5 + 23.89 = 47.39 (row 47), row 2 at -0.39 (row 0). Catches an off-by-one in the
    in-view test (``ui < w - 1``: the last column, or row, dropped as if out of view)."""
    c = cam()
    st = planar_state(c, 1 / 20.0)
    p = predict(st, c, pose(north=2.0, t=0.1), 0.1, NO_NOISE, kernels=kernels)
    assert np.isfinite(p.rho).all() and np.allclose(p.rho, 1 / 18.0, rtol=1e-6)
    assert p.du[24, 63] == pytest.approx(31.5 + 28.5 * 20 / 18 - 63, abs=1e-4)
    assert p.dv[47, 10] == pytest.approx(23.5 + 21.5 * 20 / 18 - 47, abs=1e-4)
    assert p.du[24, 0] == pytest.approx(31.5 - 28.5 * 20 / 18, abs=1e-4)


@pytest.mark.parametrize("kernels", PATHS)
def test_a_yaw_carries_the_variance_by_the_transfers_jacobian_derived_by_hand(kernels):
    """A point straight ahead at 20 m (pixel 32, 24 of a 65 x 49 camera, f 40), camera yawed 30 deg to starboard in
    place: the point is now 30 deg to port, at x_c = 20 cos 30, so rho' = 0.05 / cos 30 = 0.057735 at
    u' = 32 - 40 tan 30 = 8.906 (pixel 9, remainder -0.094), row unchanged. The Jacobian d rho'/d rho = A0 / den^2
    = 1 / cos 30 (A0 = den = cos 30, no translation): var' = 1e-6 / cos^2 30 = 1.3333e-6. Catches the Jacobian's
    A0 factor dropped (1 / den^2: var / cos^4 30 = 1.78e-6; a pure translation has A0 = 1 and cannot tell)."""
    c = cam(65, 49)
    st = InverseRangeState.empty(c, pose(), 0.0)
    st.rho[24, 32], st.var[24, 32], st.a[24, 32], st.b[24, 32], st.n[24, 32] = 0.05, 1e-6, 3.0, 1.0, 2
    yawed = VehicleState.from_ypr([0.0, 0.0, 0.0], np.deg2rad([30.0, 0.0, 0.0]), 0.1)
    p = predict(st, c, yawed, 0.1, NO_NOISE, crack_k=0, kernels=kernels)
    ys, xs = np.nonzero(np.isfinite(p.rho))
    assert list(ys) == [24] and list(xs) == [9]
    cos30 = np.cos(np.deg2rad(30.0))
    assert p.rho[24, 9] == pytest.approx(0.05 / cos30, rel=1e-6)
    assert p.var[24, 9] == pytest.approx(1e-6 / cos30 ** 2, rel=1e-5)
    assert p.du[24, 9] == pytest.approx(32 - 40 * np.tan(np.deg2rad(30.0)) - 9, abs=1e-4) and p.dv[24, 9] == 0.0
    assert p.a[24, 9] == 3.0 and p.n[24, 9] == 2


@pytest.mark.parametrize("kernels", PATHS)
def test_a_camera_with_non_square_pixels_carries_a_point_by_fx_across_and_fy_down(kernels):
    """fx 40, fy 60 (cx 31.5, cy 23.5): a point at 20 m on pixel (u 50, v 40). 2 m forward: both image offsets grow
    by 20/18 whatever the focal lengths, u' = 31.5 + 18.5 x 20/18 = 52.056, v' = 23.5 + 16.5 x 20/18 = 41.833;
    1 m to starboard and 1 m down: u' = 50 - 40 x 1/20 = 48, v' = 40 - 60 x 1/20 = 37 (rho unchanged). Catches fx
    and fy swapped in the transfer's ray (m1 = x_p / fy: u' 45.2) or projection (test cameras have fx = fy)."""
    c = Camera("c", 64, 48, 40.0, 60.0, 31.5, 23.5)
    st = InverseRangeState.empty(c, pose(), 0.0)
    st.rho[40, 50], st.var[40, 50], st.a[40, 50], st.b[40, 50], st.n[40, 50] = 0.05, 1e-6, 3.0, 1.0, 2
    fwd = predict(st, c, pose(north=2.0, t=0.1), 0.1, NO_NOISE, crack_k=0, kernels=kernels)
    ys, xs = np.nonzero(np.isfinite(fwd.rho))
    assert list(ys) == [42] and list(xs) == [52]
    assert fwd.rho[42, 52] == pytest.approx(1 / 18.0, rel=1e-6)
    assert fwd.du[42, 52] == pytest.approx(31.5 + 18.5 * 20 / 18 - 52, abs=1e-4)
    assert fwd.dv[42, 52] == pytest.approx(23.5 + 16.5 * 20 / 18 - 42, abs=1e-4)
    side = predict(st, c, VehicleState.from_ypr([0.0, 1.0, 1.0], [0.0, 0.0, 0.0], 0.1), 0.1, NO_NOISE, crack_k=0,
                   kernels=kernels)
    ys, xs = np.nonzero(np.isfinite(side.rho))
    assert list(ys) == [37] and list(xs) == [48]
    assert side.rho[37, 48] == pytest.approx(0.05, rel=1e-6)
    assert abs(side.du[37, 48]) < 1e-4 and abs(side.dv[37, 48]) < 1e-4


@pytest.mark.parametrize("kernels", PATHS)
def test_a_one_pixel_crack_takes_its_neighbours_mean_and_their_weaker_evidence_derived_by_hand(kernels):
    """Crack closing (``close_cracks``, run by predict; here with the camera standing still, so the points stay on
    their pixels). A row crack between rho 0.05 (var 1e-6, Beta(6, 1), n 4, VALID | OCCLUDED) and 0.054 (var 2e-6,
    Beta(3, 2), n 2, VALID): they agree (0.004^2 = 1.6e-5 <= 3^2 (3e-6)), so it takes rho 0.052, var = the larger
    2e-6 + (0.004 / 2)^2 = 6e-6, the weaker evidence Beta(3, 2), n 2, the flags both have (VALID), offset 0. A
    column crack closes the same way; one between 0.05 and 0.07 (0.02^2 = 4e-4 > 9 (2e-6)) stays empty. Catches
    the half-difference term of the variance dropped, or the stronger evidence taken (max of a)."""
    c = cam(12, 7)
    st = InverseRangeState.empty(c, pose(), 0.0)
    cells = {(1, 1): (0.05, 1e-6, 6.0, 1.0, 4, VALID | OCCLUDED), (1, 3): (0.054, 2e-6, 3.0, 2.0, 2, VALID),
             (1, 6): (0.05, 1e-6, 6.0, 1.0, 4, VALID | OCCLUDED), (3, 6): (0.054, 2e-6, 3.0, 2.0, 2, VALID),
             (5, 8): (0.05, 1e-6, 6.0, 1.0, 4, VALID), (5, 10): (0.07, 1e-6, 6.0, 1.0, 4, VALID)}
    for (y, x), (rho, var, a, b, n, fl) in cells.items():
        st.rho[y, x], st.var[y, x], st.a[y, x], st.b[y, x], st.n[y, x], st.flags[y, x] = rho, var, a, b, n, fl
        st.du[y, x], st.dv[y, x] = 0.2, -0.1
    p = predict(st, c, pose(t=0.1), 0.1, NO_NOISE, kernels=kernels)
    assert np.isfinite(p.rho).sum() == len(cells) + 2 and not np.isfinite(p.rho[5, 9])
    for y, x in ((1, 2), (2, 6)):
        assert p.rho[y, x] == pytest.approx(0.052, rel=1e-6)
        assert p.var[y, x] == pytest.approx(2e-6 + 0.002 ** 2, rel=1e-5)
        assert (p.a[y, x], p.b[y, x], p.n[y, x], p.flags[y, x]) == (3.0, 2.0, 2, VALID)
        assert p.du[y, x] == 0.0 and p.dv[y, x] == 0.0


@pytest.mark.parametrize("kernels", PATHS)
def test_disoccluded_region_starts_fresh(kernels):
    # background at 20 m, a foreground block at 5 m in columns 20..35; camera 2 m to starboard: the background
    # moves 4 px left (f b / 20), the block 16 px (f b / 5): the block goes to columns 4..19 and the background
    # right of it to 32..59; in between a 12 px strip shows background that the block hid (old columns 24..35)
    c = cam()
    st = planar_state(c, 1 / 20.0)
    st.rho[:, 20:36] = 1 / 5.0
    p = predict(st, c, pose(east=2.0, t=0.1), 0.1, NO_NOISE, kernels=kernels)
    rows = slice(5, -5)
    assert np.allclose(p.rho[rows, 4:20], 1 / 5.0)                 # the block: columns 20..35 - 16
    assert not np.isfinite(p.rho[rows, 20:32]).any()              # hidden by the block before, in view now
    assert np.allclose(p.rho[rows, 32:60], 1 / 20.0)               # background from columns 36..63
    assert (p.n[rows, 20:32] == 0).all()
    # a measurement there starts those cells from it: its value, its sigma, one measurement, the initial evidence
    m_rho = np.full(c.height * c.width, 1 / 20.0, np.float32).reshape(c.height, c.width)
    m_std = np.full_like(m_rho, 2e-4)
    flags = np.full(m_rho.shape, VALID, np.uint8)
    update(p, m_rho, m_std, flags, UpdateConfig(), kernels=kernels)
    assert np.allclose(p.rho[rows, 20:32], 1 / 20.0) and np.allclose(p.var[rows, 20:32], 4e-8)
    assert (p.n[rows, 20:32] == 1).all() and np.allclose(p.a[rows, 20:32], UpdateConfig().a_init)
    assert (p.n[rows, 40] == 4).all()                             # the rest fused: 3 before + this one


def one_cell_state():
    return InverseRangeState.empty(cam(4, 4), pose(), 0.0)


def measure(st, x, tau, kernels, cfg=UpdateConfig(), flags=VALID):
    shape = st.shape
    return update(st, np.full(shape, x, np.float32), np.full(shape, tau, np.float32),
                  np.full(shape, flags, np.uint8), cfg, kernels=kernels)


@pytest.mark.parametrize("kernels", PATHS)
def test_repeated_measurements_shrink_the_variance_as_a_kalman_filter(kernels):
    # N consistent measurements of sigma tau: 1/var = N / tau^2 and the mean is their average (the outlier
    # component is negligible: the Gaussian density at one sigma is ~240 /m, the uniform 0.5 /m)
    st = one_cell_state()
    tau = 1e-3
    xs = [0.050, 0.0508, 0.0494, 0.0503, 0.0497, 0.0501]
    for n, x in enumerate(xs, 1):
        measure(st, x, tau, kernels)
        assert st.var[0, 0] == pytest.approx(tau ** 2 / n, rel=3e-3)
        assert st.rho[0, 0] == pytest.approx(np.mean(xs[:n]), abs=2e-6)
        assert st.n[0, 0] == n
    ratio = st.a[0, 0] / (st.a[0, 0] + st.b[0, 0])
    assert ratio > 0.85                       # every measurement was an inlier: the evidence says so


@pytest.mark.parametrize("kernels", PATHS)
def test_sigma_scale_widens_the_measurement_of_a_fused_cell_as_of_a_started_one(kernels):
    """sigma_scale 2, two measurements 0.04 +- 1e-3 of one cell. The first starts it with s^2 = (2 x 1e-3)^2 =
    4e-6; the second agrees exactly (x = mu) with tau^2 = 4e-6 too: s'^2 = 2e-6, C1 from a / (a + b) = 3/4 times
    N(0; 0, 8e-6) against b / (a + b) = 1/4 times the uniform 1/2, and s^2 = C1 s'^2 + C2 s^2 (no spread: m = mu),
    2.0024e-6. Catches sigma_scale applied to started cells only (the fused one with tau 1e-3: s'^2 = 0.8e-6)."""
    cfg = UpdateConfig(sigma_scale=2.0)
    st = one_cell_state()
    measure(st, 0.04, 1e-3, kernels, cfg)
    assert np.allclose(st.var, 4e-6, rtol=1e-6)
    measure(st, 0.04, 1e-3, kernels, cfg)
    g = 0.75 / math.sqrt(2 * math.pi * 8e-6)
    c1 = g / (g + 0.25 * 0.5)
    assert np.allclose(st.rho, 0.04, rtol=1e-6) and (st.n == 2).all()
    assert np.allclose(st.var, c1 * 2e-6 + (1 - c1) * 4e-6, rtol=1e-5)


@pytest.mark.parametrize("kernels", PATHS)
def test_the_state_keeps_the_smallest_far_limit_of_the_pairs_and_at_infinity_needs_2_sigma_below_it(kernels):
    """A converged cell at rho 0.001 +- 0.0075 (2 sigma 0.015). Pairs with far limits 0.02, 0.01 then 0.02 again
    (none, 0: no limit): the state keeps 0.01, so the cell is not AT_INFINITY (0.015 > 0.01; relative sigma 7.5:
    ILL_CONDITIONED, no range); a state that only saw the 0.02 pair reports it at infinity (confidence 0.02 /
    0.0075). Catches the state keeping the largest limit (the cell called clear to infinity on the weaker claim)."""
    def unmeasured(st, rho_far):
        shape = st.shape
        update(st, np.full(shape, np.nan, np.float32), np.full(shape, 1e-3, np.float32),
               np.full(shape, OUT_OF_VIEW, np.uint8), rho_far=rho_far, kernels=kernels)

    st = planar_state(cam(4, 4), 0.001, var=0.0075 ** 2)
    for rho_far, want in ((0.02, 0.02), (0.01, 0.01), (0.02, 0.01), (None, 0.01), (0.0, 0.01)):
        unmeasured(st, rho_far)
        assert st.rho_far == pytest.approx(want), rho_far
    m = fused_map(st, MapConfig(fill=False), kernels=kernels)
    assert (m.flags == ILL_CONDITIONED).all() and np.isnan(m.range_m).all()
    st = planar_state(cam(4, 4), 0.001, var=0.0075 ** 2)
    unmeasured(st, 0.02)
    m = fused_map(st, MapConfig(fill=False), kernels=kernels)
    assert (m.flags & VALID).all() and np.isinf(m.range_m).all()
    assert np.allclose(m.confidence, 0.02 / 0.0075, rtol=1e-4)


@pytest.mark.parametrize("kernels", PATHS)
def test_an_outlier_leaves_a_converged_cell_where_it_was(kernels):
    st = one_cell_state()
    for _ in range(8):
        measure(st, 0.05, 1e-3, kernels)
    mu, var, a, b = (float(getattr(st, k)[0, 0]) for k in ("rho", "var", "a", "b"))
    c = measure(st, 0.20, 1e-3, kernels)                 # an occlusion / mismatch: 150 sigma off
    assert c["outliers"] == 16 and c["inliers"] == 0
    assert st.rho[0, 0] == pytest.approx(mu, abs=1e-9) and st.var[0, 0] == pytest.approx(var, rel=1e-4)
    assert st.b[0, 0] / (st.a[0, 0] + st.b[0, 0]) > b / (a + b)      # only the evidence moved
    m = fused_map(st, MapConfig(fill=False))
    assert (m.flags & VALID).all() and np.allclose(m.range_m, 20.0, rtol=1e-4)   # one outlier: still confident


@pytest.mark.parametrize("kernels", PATHS)
def test_disagreeing_evidence_gives_no_confident_range_then_restarts(kernels):
    # a converged cell whose point changed (a moving object): a few outliers in a row take its confidence away
    # (no range, ILL_CONDITIONED), more make it diverge and restart from the new value
    cfg, mcfg = UpdateConfig(), MapConfig(fill=False)
    st = one_cell_state()
    for _ in range(8):
        measure(st, 0.05, 1e-3, kernels, cfg)
    seen = []
    for k in range(1, 12):
        measure(st, 0.10, 1e-3, kernels, cfg)
        m = fused_map(st, mcfg)
        seen.append((k, bool(m.flags[0, 0] & VALID), float(st.rho[0, 0]), int(st.n[0, 0])))
        if not seen[-1][1] and st.n[0, 0] > 1:
            assert m.flags[0, 0] & ILL_CONDITIONED and np.isnan(m.range_m[0, 0])
        if st.n[0, 0] == 1:
            break
    valid = [s[1] for s in seen]
    assert valid[0] and not all(valid)                   # confident after one outlier, not after several
    k_off = valid.index(False)
    assert all(s[2] == pytest.approx(0.05, abs=1e-6) for s in seen[:-1])   # never pulled towards the outliers
    assert seen[-1][3] == 1 and seen[-1][2] == pytest.approx(0.10)         # diverged: restarted from the new value
    assert k_off < len(seen) - 1                         # the unconfident frames come before the restart


@pytest.mark.parametrize("kernels", PATHS)
def test_unmeasured_pixels_keep_their_prediction_and_the_reason(kernels):
    st = one_cell_state()
    measure(st, 0.05, 1e-3, kernels)
    before = st.rho.copy(), st.var.copy(), st.n.copy()
    c = measure(st, 0.3, 1e-3, kernels, flags=LOW_TEXTURE)
    assert c["measured"] == 0
    assert np.array_equal(st.rho, before[0]) and np.array_equal(st.var, before[1]) and np.array_equal(st.n, before[2])
    assert (st.flags == LOW_TEXTURE).all()


@pytest.mark.parametrize("kernels", PATHS)
def test_filled_pixels_of_a_measurement_are_not_fused(kernels):
    """A FILLED pixel (VALID | FILLED: interpolated from its neighbours, not measured) carries no measurement: fusing
    it would let the fill confirm itself frame after frame. It neither moves a cell nor starts an empty one; the same
    value flagged VALID alone does."""
    st = one_cell_state()
    for _ in range(3):
        measure(st, 0.05, 1e-3, kernels)
    before = st.rho.copy(), st.var.copy(), st.n.copy()
    c = measure(st, 0.0505, 1e-3, kernels, flags=VALID | FILLED)
    assert c["measured"] == 0
    assert np.array_equal(st.rho, before[0]) and np.array_equal(st.var, before[1]) and np.array_equal(st.n, before[2])
    empty = one_cell_state()
    assert measure(empty, 0.0505, 1e-3, kernels, flags=VALID | FILLED)["started"] == 0 and not empty.occupied().any()
    c = measure(st, 0.0505, 1e-3, kernels, flags=VALID)
    assert c["measured"] == 16 and (st.n == 4).all() and (st.rho > before[0]).all()


@pytest.mark.parametrize("kernels", PATHS)
def test_a_pixel_without_a_usable_sigma_or_range_carries_no_measurement(kernels):
    """A VALID pixel whose sigma is 0 (a degenerate fit), infinite or NaN, or whose rho is NaN, is no measurement
    (``update.measured``: finite rho, finite sigma > 0): it neither starts an empty cell nor moves a converged one.
    Fused, a sigma of 0 would start a cell with variance 0 (an infinitely confident range) or collapse a converged
    cell's variance onto the measurement, which then rejects every later one as an outlier. Catches the sigma > 0
    test dropped."""
    for x, tau in ((0.05, 0.0), (0.05, np.inf), (0.05, np.nan), (np.nan, 1e-3)):
        empty = one_cell_state()
        c = measure(empty, x, tau, kernels)
        assert c["measured"] == 0 and c["started"] == 0 and not empty.occupied().any(), (x, tau)
        st = planar_state(cam(4, 4), 0.04)
        c = measure(st, x, tau, kernels)
        assert c["measured"] == 0, (x, tau)
        assert (st.rho == np.float32(0.04)).all() and (st.var == np.float32(1e-6)).all() and (st.n == 3).all()


@pytest.mark.parametrize("kernels", PATHS)
def test_one_update_of_a_doubtful_measurement_matches_the_published_moment_match_derived_by_hand(kernels):
    """One Gaussian x uniform update (Vogiatzis & Hernandez) where the measurement may be either (C1 ~ 0.6), so that
    every term counts: the Gaussian's normalisation, the uniform density 1 / rho_max, the mixture's spread in the
    variance, the Beta moments. Cell mu 0.05, s 0.002, Beta(3, 1); x 0.06, tau 0.002; rho_max 2 /m.
    S = s^2 + tau^2 = 8e-6, d^2 / S = 12.5: N(x) = e^-6.25 / sqrt(2 pi 8e-6) = 0.0019305 / 0.0070898 = 0.27229 /m;
    C1 ~ 3/4 x 0.27229 = 0.20422, C2 ~ 1/4 x 1/2 = 0.125: C1 = 0.62031, C2 = 0.37969. s'^2 = 2e-6, m = 0.055:
    mu = 0.05 + 0.005 C1 = 0.053102; s^2 = C1 2e-6 + C2 4e-6 + C1 C2 0.005^2 = 8.6475e-6.
    f = (4 C1 + 3 C2) / 5 = 0.72406, e = (20 C1 + 12 C2) / 30 = 0.56541: a = (e - f) / (f - e / f) = 2.7915,
    b = a (1 - f) / f = 1.0638 (a + b below the evidence cap: not scaled)."""
    st = one_cell_state()
    st.rho[...], st.var[...], st.a[...], st.b[...], st.n[...] = 0.05, 0.002 ** 2, 3.0, 1.0, 2
    c = measure(st, 0.06, 0.002, kernels)
    assert c["inliers"] == 16 and c["restarted"] == 0                    # C1 > 0.5
    assert st.rho[0, 0] == pytest.approx(0.053102, rel=2e-5)
    assert st.var[0, 0] == pytest.approx(8.6475e-6, rel=1e-4)
    assert st.a[0, 0] == pytest.approx(2.7915, rel=1e-4) and st.b[0, 0] == pytest.approx(1.0638, rel=1e-4)
    assert (st.n == 3).all()
    # at the evidence cap (8): a converged Beta(7, 1) and a measurement on its estimate (C1 = 1 - 2.5e-4) give the
    # conjugate Beta(a + 1, b) = Beta(8, 1), a + b = 9 scaled to 8 keeping the ratio: a = 64/9, b = 8/9 (C2 moves
    # them by less than 3e-4 relative)
    st = one_cell_state()
    st.rho[...], st.var[...], st.a[...], st.b[...], st.n[...] = 0.05, 1e-6, 7.0, 1.0, 9
    measure(st, 0.05, 1e-3, kernels)
    assert st.a[0, 0] == pytest.approx(64 / 9, rel=3e-4) and st.b[0, 0] == pytest.approx(8 / 9, rel=3e-4)
    assert st.a[0, 0] + st.b[0, 0] == pytest.approx(8.0, rel=1e-6)


@pytest.mark.parametrize("kernels", PATHS)
def test_a_cell_whose_inlier_ratio_falls_below_eta_restarts_from_the_measurement_and_one_just_above_does_not(kernels):
    """A far outlier (C1 = 0 exactly: 125 sigma off) takes Beta(a, b) to the conjugate Beta(a, b + 1). Beta(4, 4)
    -> 4/9 = 0.444 < eta_outlier 0.45: diverged, restarted from the measurement (mu = x, s^2 = tau^2, Beta(a_init,
    b_init), n 1, no sub-pixel remainder); Beta(5, 5) -> 5/11 = 0.4545: kept (mu, s^2 unchanged, n + 1), its
    Beta(5, 6) scaled to the evidence cap 8: (40/11, 48/11)."""
    st = InverseRangeState.empty(cam(2, 1), pose(), 0.0)
    st.rho[...], st.var[...], st.n[...], st.du[...], st.dv[...] = 0.05, 1e-6, 5, 0.3, -0.2
    st.a[0], st.b[0] = [4.0, 5.0], [4.0, 5.0]
    cfg = UpdateConfig()
    c = measure(st, 0.3, 2e-3, kernels, cfg)
    assert (c["outliers"], c["inliers"], c["restarted"]) == (2, 0, 1)
    assert st.rho[0, 0] == np.float32(0.3) and st.var[0, 0] == pytest.approx(2e-3 ** 2, rel=1e-6)
    assert (st.a[0, 0], st.b[0, 0], st.n[0, 0]) == (cfg.a_init, cfg.b_init, 1)
    assert st.du[0, 0] == 0.0 and st.dv[0, 0] == 0.0
    assert st.rho[0, 1] == np.float32(0.05) and st.var[0, 1] == np.float32(1e-6) and st.n[0, 1] == 6
    assert st.a[0, 1] == pytest.approx(40 / 11, rel=1e-5) and st.b[0, 1] == pytest.approx(48 / 11, rel=1e-5)
    assert st.du[0, 1] == np.float32(0.3) and st.dv[0, 1] == np.float32(-0.2)


@pytest.mark.parametrize("kernels", PATHS)
def test_cells_emptied_by_a_mask_keep_the_last_measurements_reason_and_a_full_clear_forgets_it(kernels):
    """A converged cell the last measurement saw hidden in b (OUT_OF_VIEW | OCCLUDED: it kept its prediction),
    then emptied (``clear_cells``, as the stereo free-space rules do): the map reports it empty for that reason
    (contested: not filled from a loose plane), not as a bare ILL_CONDITIONED; its neighbours are untouched. A
    state cleared whole (a camera restarting) forgets every reason."""
    from eonav.fusion.update import clear_cells
    st = one_cell_state()
    for _ in range(3):
        measure(st, 0.05, 1e-3, kernels)
    hidden = np.uint8(OUT_OF_VIEW | OCCLUDED)
    flags = np.full(st.shape, VALID, np.uint8)
    flags[1, 2] = hidden
    update(st, np.full(st.shape, 0.05, np.float32), np.full(st.shape, 1e-3, np.float32), flags, kernels=kernels)
    mask = np.zeros(st.shape, bool)
    mask[1, 2] = mask[0, 0] = True
    assert clear_cells(st, mask) == 2
    assert np.isnan(st.rho[mask]).all() and (st.var[mask] == np.inf).all() and (st.n[mask] == 0).all()
    assert st.flags[1, 2] == hidden and st.flags[0, 0] == VALID
    m = fused_map(st, MapConfig(fill=False), kernels=kernels)
    assert m.flags[1, 2] & hidden == hidden and not m.flags[1, 2] & VALID and np.isnan(m.range_m[1, 2])
    # the one the last pair ranged (VALID) and the free-space rule then emptied: no range, and not reported
    # VALID either (an empty cell keeps only the reason bits; catches the map taking every last-measurement bit)
    assert m.flags[0, 0] == ILL_CONDITIONED and np.isnan(m.range_m[0, 0]) and m.confidence[0, 0] == 0
    assert (m.flags[~mask] == VALID).all() and np.allclose(m.range_m[~mask], 20.0, rtol=1e-4)
    st.clear()
    assert not st.occupied().any() and (st.flags == 0).all() and (st.n == 0).all()


def _random_state(c, rng, rho_lo: float, var_hi: float):
    """A state with 80 % of its cells occupied by random estimates (inverse range rho_lo..0.3, variance up to
    var_hi, Beta evidence); returns it and the occupied mask."""
    st = InverseRangeState.empty(c, pose(), 0.0)
    occ = rng.random(st.shape) < 0.8
    st.rho[occ] = rng.uniform(rho_lo, 0.3, occ.sum())
    st.var[occ] = rng.uniform(1e-7, var_hi, occ.sum())
    st.a[occ], st.b[occ] = rng.uniform(1, 6, occ.sum()), rng.uniform(0.5, 3, occ.sum())
    return st, occ


@pytest.mark.skipif(optional_kernels() is None, reason="numba not installed")
def test_numba_and_numpy_paths_agree_on_a_random_state():
    rng = np.random.default_rng(3)
    c = cam(96, 72)
    st, occ = _random_state(c, rng, rho_lo=0.01, var_hi=1e-4)
    st.du[occ], st.dv[occ] = rng.uniform(-0.5, 0.5, (2, occ.sum()))
    new = VehicleState.from_ypr([1.0, 0.3, -0.2], np.deg2rad([1.0, -0.5, 2.0]), 0.1)
    noise = ProcessNoise(0.02, 0.01, 1e-5)
    p0, p1 = (predict(st, c, new, 0.1, noise, kernels=k) for k in (False, True))
    for name in ("rho", "var", "a", "b", "n", "du", "dv", "flags"):
        a0, a1 = getattr(p0, name), getattr(p1, name)
        assert np.array_equal(np.isfinite(a0), np.isfinite(a1)) if a0.dtype.kind == "f" else True
        ok = np.isfinite(a0) if a0.dtype.kind == "f" else np.ones(a0.shape, bool)
        assert np.allclose(a0[ok], a1[ok], rtol=1e-5, atol=1e-7), name
    m_rho = np.where(rng.random(st.shape) < 0.1, rng.uniform(0, 0.3, st.shape), p0.rho + 1e-3).astype(np.float32)
    m_std = rng.uniform(5e-4, 3e-3, st.shape).astype(np.float32)
    flags = np.where(rng.random(st.shape) < 0.7, VALID, LOW_TEXTURE).astype(np.uint8)
    u0, u1 = copy.deepcopy(p0), copy.deepcopy(p0)
    c0 = update(u0, m_rho, m_std, flags, kernels=False)
    c1 = update(u1, m_rho, m_std, flags, kernels=True)
    assert c0 == c1
    for name in ("rho", "var", "a", "b", "n"):
        a0, a1 = getattr(u0, name), getattr(u1, name)
        ok = np.isfinite(a0)
        assert np.array_equal(ok, np.isfinite(a1))
        assert np.allclose(a0[ok], a1[ok], rtol=2e-4, atol=1e-9), name


@pytest.mark.skipif(optional_kernels() is None, reason="numba not installed")
def test_crack_closing_kernel_equals_the_numpy_passes_bit_for_bit():
    """The one-sweep kernel closes the same cells with the same values as predict.close_cracks' two passes, on
    random states with cracks of both axes, runs of empty cells and one-row / one-column grids."""
    from eonav.fusion.predict import close_cracks
    K = optional_kernels()
    rng = np.random.default_rng(11)
    total = 0
    for h, w in [(1, 9), (9, 1), (2, 2), (3, 3), (17, 23), (48, 64)] + [tuple(rng.integers(1, 40, 2)) for _ in range(40)]:
        st, _ = _random_state(cam(int(w), int(h)), rng, rho_lo=0.01, var_hi=1e-3)
        st.rho[rng.random(st.shape) < rng.uniform(0.1, 0.6)] = np.nan         # empty cells: singles and runs
        st.var[~np.isfinite(st.rho)] = np.inf
        st.n[...] = rng.integers(0, 9, st.shape)
        st.du[...], st.dv[...] = rng.uniform(-0.5, 0.5, (2,) + st.shape)
        st.flags[...] = rng.integers(0, 256, st.shape)
        ref, ker = copy.deepcopy(st), copy.deepcopy(st)
        n_ref = close_cracks(ref, 3.0)
        n_ker = K.close_cracks(ker.rho, ker.var, ker.a, ker.b, ker.n, ker.du, ker.dv, ker.flags, np.float32(9.0))
        assert n_ker == n_ref
        for name in ("rho", "var", "a", "b", "n", "du", "dv", "flags"):
            assert np.array_equal(getattr(ref, name), getattr(ker, name), equal_nan=True), name
        total += n_ref
    assert total > 500                     # the states had cracks to close


@pytest.mark.skipif(optional_kernels() is None, reason="numba not installed")
def test_the_update_kernels_inline_exp_is_the_float32_exp():
    """The update's inline exp (of x <= 0) against exp in float64 rounded to float32: at most 1 ulp apart (the
    rounding of the float32 result), and its special values exact."""
    from numba import njit
    exp32 = optional_kernels().exp_nonpositive

    @njit(cache=False)
    def apply(xs, out):
        for i in range(xs.size):
            out[i] = exp32(xs[i])

    rng = np.random.default_rng(11)
    xs = np.concatenate([-rng.exponential(2.0, 200_000), -rng.uniform(0, 103.9, 200_000),
                         -rng.uniform(0, 1e-6, 1000)]).astype(np.float32)
    got = np.empty_like(xs)
    apply(xs, got)
    want = np.exp(xs.astype(np.float64)).astype(np.float32)
    ulps = np.abs(got.view(np.int32).astype(np.int64) - want.view(np.int32))
    assert ulps.max() <= 1 and (ulps == 0).mean() > 0.999
    special = np.array([0.0, -0.0, -104.0, -110.0, -1e30, -np.inf, np.nan], np.float32)
    out = np.empty_like(special)
    apply(special, out)
    assert out[0] == 1.0 and out[1] == 1.0
    assert (out[2:6] == 0.0).all() and np.isnan(out[6])


@pytest.fixture(scope="module")
def fast_sequence():
    from eonav.sim.sequence import render_sequence
    return render_sequence("fast", n_frames=4, rate_hz=10.0, size=128, supersample=2, seed=0)


def median_error(range_m, truth):
    ok = np.isfinite(truth) & np.isfinite(range_m) & (range_m > 0)
    return float(np.median(np.abs(range_m[ok] - truth[ok]) / truth[ok])), float(ok.sum() / np.isfinite(truth).sum())


def test_fused_simulated_sequence_beats_the_single_pairs():
    # the paper replica flown at 30 fps, 10 frames at 160 x 160: the fused last frame against its truth, beside the
    # dense method on the newest pair and on the widest (first frame, 0.3 s back) of the same frame
    from eonav.ranging.methods.dense import locate_dense
    from eonav.sim.sequence import render_sequence
    seq = render_sequence("paper", n_frames=10, rate_hz=30.0, size=160, supersample=2, seed=0)
    runner = FusionRunner(FusionConfig())
    maps = []
    for k, v in enumerate(seq.views):
        maps += runner.push(frame("nose", v, int(round(v.state.t_s * 1e6)), k))
    first = maps[0].frame.seq                   # the first frame with enough parallax to the first one, then all
    assert [m.frame.seq for m in maps] == list(range(first, 10)) and first <= 6
    last = maps[-1]
    truth = seq.truth[-1].range_m
    e_fused, cov_fused = median_error(last.result.range_m, truth)
    e_newest, cov_newest = median_error(locate_dense(seq.views[-1], seq.views[-2]).range_m, truth)
    e_widest, cov_widest = median_error(locate_dense(seq.views[-1], seq.views[0]).range_m, truth)
    assert e_fused < 0.7 * e_newest and e_fused < 0.95 * e_widest
    assert cov_fused > max(cov_newest, cov_widest) + 0.05
    kinds = {ms["kind"] for m in maps for ms in m.measurements}
    assert kinds == {"near", "wide"}
    assert int(np.median(last.n_fused[np.isfinite(truth)])) >= 4


def test_runner_drops_out_of_order_frames_and_resets_after_a_gap(fast_sequence):
    seq = fast_sequence
    runner = FusionRunner(FusionConfig(max_gap_s=0.5))
    v = seq.views
    us = [int(round(x.state.t_s * 1e6)) for x in v]
    runner.push(frame("nose", v[0], us[0], 0))
    assert len(runner.push(frame("nose", v[1], us[1], 1))) == 1
    assert runner.push(frame("nose", v[0], us[0], 0)) == [] and runner.counts["out_of_order"] == 1
    late = frame("nose", v[2], us[1] + 600_000, 2)                   # 0.6 s later: a gap, the state starts over
    maps = runner.push(late)                 # (measured against an earlier frame still within the pair policy's age)
    assert runner.counts["gap_resets"] == 1
    st = runner.states["nose"]
    assert st.occupied().any() and (st.n[st.occupied()] == 1).all()  # nothing carried over: one measurement each
    assert [m.frame.seq for m in maps] == [2]


def test_a_state_exactly_max_gap_s_old_is_predicted_and_one_a_microsecond_older_is_dropped(fast_sequence):
    """``max_gap_s`` is the oldest a state may be and still be carried into the next frame: a camera whose frames
    come exactly max_gap_s apart (0.5 s: 2 fps) keeps fusing (its cells' n grows to 2), a frame 0.5 s + 1 us after
    the state starts fresh (n 1, counted gap_resets). Catches a planted ``>=`` for ``>`` in push's gap test (such a
    camera would never fuse two frames)."""
    v = fast_sequence.views
    runner = FusionRunner(FusionConfig(max_gap_s=0.5))
    runner.push(frame("nose", v[0], 1_000_000, 0))
    m1, = runner.push(frame("nose", v[1], 1_500_000, 1))
    m2, = runner.push(frame("nose", v[2], 2_000_000, 2))
    assert "gap_resets" not in runner.counts
    assert m1.n_fused.max() == 1 and m2.n_fused.max() == 2
    m3, = runner.push(frame("nose", v[3], 2_500_001, 3))
    assert runner.counts["gap_resets"] == 1
    st = runner.states["nose"]
    assert m3.n_fused.max() == 1 and (st.n[st.occupied()] == 1).all()


def test_runner_drops_a_frame_delivered_twice_and_leaves_the_state_alone(fast_sequence):
    """A frame with the same stamp as its camera's state (the same instant delivered twice) is not newer: dropped and
    counted out_of_order, no second map of that instant (it would be published again) and the state untouched (not
    predicted, its frame kept). Catches a planted ``<`` for ``<=`` in push's out-of-order test."""
    v = fast_sequence.views
    us = [int(round(x.state.t_s * 1e6)) for x in v]
    runner = FusionRunner(FusionConfig())
    runner.push(frame("nose", v[0], us[0], 0))
    first = frame("nose", v[1], us[1], 1)
    assert len(runner.push(first)) == 1
    st = runner.states["nose"]
    before = {k: getattr(st, k).copy() for k in ("rho", "var", "a", "b", "n")}
    assert runner.push(frame("nose", v[1], us[1], 1)) == [] and runner.counts["out_of_order"] == 1
    assert runner.states["nose"] is st and runner.frames["nose"] is first
    for k, x in before.items():
        assert np.array_equal(getattr(st, k), x, equal_nan=True), k


def test_reset_of_one_camera_leaves_the_other_cameras_state(fast_sequence):
    """``reset(camera_id)`` (the locator's answer to a frame whose fusion failed) forgets that camera's state and no
    other: the next frame of the reset camera starts fresh (one measurement per cell), the other camera's next frame
    fuses on top of what it had (its cells' n grows). Catches a planted reset of every camera."""
    v = fast_sequence.views
    us = [int(round(x.state.t_s * 1e6)) for x in v]
    runner = FusionRunner(FusionConfig())
    for k in range(3):
        for cid in ("nose", "tail"):
            runner.push(frame(cid, v[k], us[k], k))
    tail = runner.states["tail"]
    n_tail = int(tail.n.max())
    assert n_tail >= 2
    runner.reset("nose")
    assert "nose" not in runner.states and "nose" not in runner.frames
    assert runner.states.get("tail") is tail and int(tail.n.max()) == n_tail
    nose, = runner.push(frame("nose", v[3], us[3], 3))
    assert nose.n_fused.max() == 1 and (nose.n_fused[runner.states["nose"].occupied()] == 1).all()
    tail_map, = runner.push(frame("tail", v[3], us[3], 3))
    assert tail_map.n_fused.max() == n_tail + 1


def test_stereo_partner_updates_the_rig_reference():
    from eonav.sim.presets import make_pair
    sp = make_pair("stereo", size=96, supersample=1)
    left, right = sp.views
    runner = FusionRunner(FusionConfig(schedule=ScheduleConfig(stereo_rig=("left", "right"))))
    assert runner.push(frame("left", left, 1_000_000, 0)) == []      # first frame, partner not there yet
    maps = runner.push(frame("right", right, 1_000_500, 0))
    assert [m.frame.camera_id for m in maps] == ["left"] and maps[0].measurements[0]["kind"] == "stereo"
    e, cov = median_error(maps[0].result.range_m, sp.truth[0].range_m)
    assert e < 0.03 and cov > 0.5


@pytest.mark.realdata
def test_real_indoor_sequence_fused_beats_single_pair_dense():
    # the real HoloLens sequence (depth-sensor reference): the fused last frame against the dense method on the
    # newest pair and the widest pair of the same frame
    from eonav.app.bench_fuse import indoor_config, widest_partner
    from eonav.ranging.methods.dense import locate_dense
    from shared_data import hololens_or_skip
    views, truth = hololens_or_skip()
    cfg = indoor_config()
    runner = FusionRunner(cfg)
    for k, v in enumerate(views):
        maps = runner.push(frame("hololens", v, int(round(v.state.t_s * 1e6)), k))
    k = len(views) - 1
    assert maps[0].frame.seq == k
    e_fused, cov = median_error(maps[0].result.range_m, truth[k])
    e_newest, _ = median_error(locate_dense(views[k], views[k - 1]).range_m, truth[k])
    e_widest, _ = median_error(locate_dense(views[k], views[widest_partner(views, k, cfg)]).range_m, truth[k])
    assert e_fused < e_newest and e_fused < e_widest and cov > 0.5


# --- the fused map's sigma: the slant term ---------------------------------------------------------------------

def same_info(m0, m1):
    i0, i1 = dict(m0.info), dict(m1.info)
    return np.array_equal(i0.pop("n_fused"), i1.pop("n_fused")) and i0 == i1


@pytest.mark.parametrize("kernels", PATHS)
def test_slant_term_of_a_tilted_plane_and_at_a_depth_edge_derived_by_hand(kernels):
    # rho = 0.05 + 0.002 y (a surface tilted along v: 0.002 /m per pixel) in columns 0..31, a near wall (rho 0.2)
    # in columns 32..63: sigma^2 = var + slant_px^2 |grad rho|^2 with grad rho = 0.002 along v everywhere (the
    # cells beside the edge take their own side: 0 along u); rows 0 and 47 have one vertical neighbour, same
    # difference. Var 1e-8: the slant term (1.5 * 0.002 = 3e-3) dominates.
    c = cam(64, 48)
    st = planar_state(c, 0.0, var=1e-8)
    ys = np.arange(48, dtype=np.float32)[:, None]
    st.rho[:, :32] = 0.05 + 0.002 * ys
    st.rho[:, 32:] = 0.2 + 0.002 * ys
    m = fused_map(st, MapConfig(fill=False, slant_px=1.5), kernels=kernels)
    want = np.sqrt(1e-8 + (1.5 * 0.002) ** 2)
    assert np.allclose(m.inv_range_std_per_m, want, rtol=1e-4)
    flat = fused_map(st, MapConfig(fill=False, slant_px=0.0), kernels=kernels)
    assert np.allclose(flat.inv_range_std_per_m, 1e-4, rtol=1e-4)     # no slant term: the filter's own sigma
    # an empty neighbour is not used: the row above the hole has the difference to the row above it only
    st.rho[20, :], st.var[20, :] = np.nan, np.inf                # empty cells
    m2 = fused_map(st, MapConfig(fill=False, slant_px=1.5), kernels=kernels)
    assert np.allclose(m2.inv_range_std_per_m[19], want, rtol=1e-4)
    assert np.isinf(m2.inv_range_std_per_m[20]).all()


@pytest.mark.parametrize("kernels", PATHS)
def test_slant_term_of_a_plane_tilted_along_the_rows_reaches_the_first_and_last_column(kernels):
    """The test above turned a quarter: rho = 0.05 + 0.002 u, one surface tilted along u (0.002 /m per pixel), so
    every cell, the first and last columns included (one horizontal neighbour each, the same difference), reports
    sigma^2 = var + (1.5 x 0.002)^2. Catches a border column's missing neighbour taken as the cell itself (a zero
    difference: the first or last column reported with the filter's sigma alone, 30 x too tight)."""
    st = planar_state(cam(64, 48), 0.05 + 0.002 * np.arange(64, dtype=np.float32)[None, :], var=1e-8)
    m = fused_map(st, MapConfig(fill=False, slant_px=1.5), kernels=kernels)
    want = np.sqrt(1e-8 + (1.5 * 0.002) ** 2)
    assert np.allclose(m.inv_range_std_per_m[:, [0, 1, 62, 63]], want, rtol=1e-4)
    assert np.allclose(m.inv_range_std_per_m, want, rtol=1e-4)


@pytest.mark.parametrize("kernels", PATHS)
def test_an_empty_cell_is_filled_from_converged_neighbours_and_an_occluded_one_only_from_a_tight_plane(kernels):
    # a converged plane rho = 0.05 + 0.0004 u - 0.0003 v with a 6 x 6 hole of empty cells: the fill's plane through
    # the neighbours gives the hole the plane's own rho (FILLED, a finite sigma); the hole's last measurement
    # flagged TRUNCATION (one pair's verdict on its step): filled; OCCLUDED (contested): filled too, the plane
    # being exact (relative sigma ~0 <= contested_rel_std), but not when contested cells are never filled
    # (contested_rel_std 0), nor TRUNCATION when the config names it among the contested bits then
    hole = (slice(20, 26), slice(30, 36))
    c, plane, st = converged_plane(hole)
    never = dict(contested_rel_std=0.0)
    for bits, cfg, filled in ((TRUNCATION, MapConfig(), True), (OCCLUDED, MapConfig(), True),
                              (OCCLUDED, MapConfig(**never), False),
                              (TRUNCATION, MapConfig(no_fill=OCCLUDED | TRUNCATION, **never), False)):
        st.flags[...] = 0
        st.flags[hole] = bits
        m = fused_map(st, cfg, kernels=kernels)
        got = m.flags[hole]
        if filled:
            assert ((got & FILLED) != 0).all() and ((got & bits) != 0).all()
            assert np.allclose(m.inv_range_per_m[hole], plane[hole], rtol=1e-3)
            assert np.isfinite(m.inv_range_std_per_m[hole]).all()
        else:
            assert not ((got & FILLED) != 0).any() and not np.isfinite(m.range_m[hole]).any()


@pytest.mark.parametrize("kernels", PATHS)
def test_a_cell_occluded_beside_a_depth_edge_is_not_filled_from_the_plane_across_it(kernels):
    # a wall at 10 m (rho 0.10, columns < 32) in front of a background at 20 m (0.05); the last pair saw the 6
    # background columns beside the edge hidden (OCCLUDED), as a nearer surface hides what is behind it. The
    # neighbours' plane spans both sides: it puts the hole between them, 1.4-1.8 x too near, with a relative sigma
    # (its residual) of ~0.16 -- inside the rule for an unmeasured cell (0.34), yet the truth (0.05) is ~2 of those
    # sigmas away. Contested, it is filled only from a plane tighter than contested_rel_std: left empty at 0.05,
    # filled (and wrong) when the limit is the rule's own
    c = cam(64, 48)
    rho = np.where(np.arange(64)[None, :] < 32, 0.10, 0.05).astype(np.float32) * np.ones((48, 1), np.float32)
    st = planar_state(c, rho, var=1e-8)
    hole = (slice(18, 30), slice(32, 38))
    st.rho[hole], st.var[hole], st.a[hole], st.b[hole], st.n[hole] = np.nan, np.inf, 0.0, 0.0, 0
    st.flags[hole] = OCCLUDED
    m = fused_map(st, MapConfig(), kernels=kernels)
    assert not ((m.flags[hole] & FILLED) != 0).any() and not np.isfinite(m.range_m[hole]).any()
    loose = fused_map(st, MapConfig(contested_rel_std=0.34), kernels=kernels)
    r, sd = loose.inv_range_per_m[hole], loose.inv_range_std_per_m[hole]
    assert ((loose.flags[hole] & FILLED) != 0).all()
    assert (r > 1.3 * 0.05).all() and 0.05 < np.median(sd / r) <= 0.34
    assert np.median(np.abs(r - 0.05) / sd) > 1.5          # the mixed plane's sigma does not cover its error


@pytest.mark.parametrize("kernels", PATHS)
def test_a_disagreeing_cell_takes_a_tight_plane_of_its_neighbours_not_a_loose_one(kernels):
    # a 4 x 4 block of cells whose evidence disagrees (a/(a+b) = 1/6), their own rho 1.5 x the truth, inside a
    # converged plane: no range of their own (ILL_CONDITIONED); the exact plane of the neighbours (relative sigma
    # ~0.3 %) stands in for them, with the truth's rho; with noisy neighbours (2 % per cell, so the plane's
    # scatter gives a sigma well above a 0.1 % limit) they stay empty
    dis = (slice(20, 24), slice(30, 34))
    c, plane, st = converged_plane()
    st.rho[dis] = 1.5 * plane[dis]
    st.a[dis], st.b[dis] = 1.0, 5.0
    for cfg, filled in ((MapConfig(), True), (MapConfig(contested_rel_std=0.0), False)):
        m = fused_map(st, cfg, kernels=kernels)
        got = m.flags[dis]
        assert ((got & ILL_CONDITIONED) != 0).all() and not ((got & VALID) != 0).any()
        if filled:
            assert ((got & FILLED) != 0).all()
            np.testing.assert_allclose(m.inv_range_per_m[dis], plane[dis], rtol=1e-3)
            assert (m.inv_range_std_per_m[dis] < 0.05 * plane[dis]).all()
        else:
            assert not ((got & FILLED) != 0).any() and not np.isfinite(m.range_m[dis]).any()
    noisy = planar_state(c, plane * (1 + 0.02 * np.random.default_rng(3).standard_normal(plane.shape)).astype(
        np.float32), var=(0.02 * plane) ** 2)
    noisy.rho[dis] = 1.5 * plane[dis]
    noisy.a[dis], noisy.b[dis] = 1.0, 5.0
    loose = fused_map(noisy, MapConfig(), kernels=kernels)
    assert ((loose.flags[dis] & FILLED) != 0).all()                  # 2 % noise: the plane is still within 5 %
    tight = fused_map(noisy, MapConfig(contested_rel_std=0.001), kernels=kernels)
    assert not ((tight.flags[dis] & FILLED) != 0).any()


@pytest.mark.parametrize("kernels", PATHS)
def test_empty_cells_at_the_image_border_are_extrapolated_unless_textureless(kernels):
    # the converged plane rho = 0.05 + 0.0004 u - 0.0003 v with its last 6 columns empty (content that entered the
    # view, not measured yet; last pair ILL_CONDITIONED): the 4 columns within border_px (4) of the border take the
    # plane's own rho, the 2 further in (5-6 px from the border, outside the support: an extrapolation) do not,
    # but in the top and bottom 4 rows, which are in the ring too; none
    # with border_px 0, nor where the last pair saw no texture (LOW_TEXTURE: may be sky)
    strip = (slice(None), slice(58, 64))
    c, plane, st = converged_plane(strip)
    for bits, cfg, cols in ((ILL_CONDITIONED, MapConfig(), slice(60, 64)), (ILL_CONDITIONED, MapConfig(border_px=0), None),
                            (LOW_TEXTURE, MapConfig(), None)):
        st.flags[...] = 0
        st.flags[strip] = bits
        m = fused_map(st, cfg, kernels=kernels)
        filled = (m.flags & FILLED) != 0
        if cols is None:
            assert not filled[strip].any()
            continue
        assert filled[:, cols].all() and not filled[4:-4, 58:60].any()     # (rows < 4 from top / bottom: ring)
        np.testing.assert_allclose(m.inv_range_per_m[:, cols], plane[:, cols], rtol=1e-3)
        assert ((m.flags[:, cols] & OUT_OF_VIEW) == 0).all()      # the flag the fill saw is not reported
        assert (m.inv_range_std_per_m[:, cols] < 0.34 * plane[:, cols]).all()


@pytest.mark.parametrize("kernels", PATHS)
def test_a_contested_empty_cell_at_the_image_border_is_not_extrapolated_even_from_an_exact_plane(kernels):
    """The border strip of the test above, its last pair's verdict TRUNCATION: not contested by default, so the 4
    columns within border_px take the (exact) plane; with TRUNCATION among the contested bits (no_fill) the strip
    is a contested cell's, never extrapolated to -- the plane's tightness (relative sigma ~0 <= contested_rel_std)
    lets it stand in only inside its support, which the strip is beyond -- so none of it is filled. Catches the
    contested bits dropped from the border ring's exclusions (with the default no_fill, OCCLUDED alone, the fill
    itself refuses to extrapolate to an OCCLUDED pixel: only a configured no_fill shows it)."""
    strip = (slice(None), slice(58, 64))
    c, plane, st = converged_plane(strip)
    st.flags[strip] = TRUNCATION
    m = fused_map(st, MapConfig(), kernels=kernels)
    assert ((m.flags[:, 60:64] & FILLED) != 0).all()
    np.testing.assert_allclose(m.inv_range_per_m[:, 60:64], plane[:, 60:64], rtol=1e-3)
    contested = fused_map(st, MapConfig(no_fill=OCCLUDED | TRUNCATION), kernels=kernels)
    assert not ((contested.flags[strip] & FILLED) != 0).any() and not np.isfinite(contested.range_m[strip]).any()
    assert ((contested.flags[strip] & TRUNCATION) != 0).all()


def test_map_config_rejects_bad_no_fill_bits():
    with pytest.raises(InputError, match="no_fill"):
        MapConfig(no_fill=256)
    for bad in (-0.01, 0.5, float("nan")):                # above max_rel_std (0.34): looser than the rule itself
        with pytest.raises(InputError, match="contested_rel_std"):
            MapConfig(contested_rel_std=bad)
    for bad in (-1, 2.5):
        with pytest.raises(InputError, match="border_px"):
            MapConfig(border_px=bad)


@pytest.mark.skipif(optional_kernels() is None, reason="numba not installed")
def test_numba_and_numpy_fused_maps_agree_on_a_random_state():
    rng = np.random.default_rng(5)
    st, _ = _random_state(cam(96, 72), rng, rho_lo=0.0, var_hi=1e-2)
    st.flags[...] = rng.choice([0, LOW_TEXTURE, ILL_CONDITIONED, 2 | 4], st.shape)
    st.rho_far = 0.01
    m0, m1 = (fused_map(st, MapConfig(), kernels=k) for k in (False, True))
    assert np.array_equal(m0.flags, m1.flags)
    for name in ("inv_range_per_m", "inv_range_std_per_m", "range_m", "confidence"):
        a0, a1 = getattr(m0, name), getattr(m1, name)
        assert np.array_equal(np.isnan(a0), np.isnan(a1)), name
        ok = np.isfinite(a0)
        assert np.array_equal(ok, np.isfinite(a1)) and np.allclose(a0[ok], a1[ok], rtol=1e-5), name
    assert same_info(m0, m1)


@pytest.mark.parametrize("kernels", PATHS)
def test_update_and_map_in_one_sweep_equals_update_then_map(kernels):
    # also when the map is written into the measurement's own arrays (reuse): rows are read before they are written
    from eonav.fusion.fused_map import update_and_map
    from eonav.ranging.rangemap import RangeResult
    rng = np.random.default_rng(7)
    c = cam(80, 60)
    st = InverseRangeState.empty(c, pose(), 0.0)
    occ = rng.random(st.shape) < 0.7
    st.rho[occ] = rng.uniform(0.02, 0.2, occ.sum())
    st.var[occ] = rng.uniform(1e-7, 1e-5, occ.sum())
    st.a[occ], st.b[occ], st.n[occ] = 4.0, 1.0, 3
    m_rho = (np.where(occ, st.rho, 0.1) * rng.uniform(0.97, 1.03, st.shape)).astype(np.float32)
    m_std = rng.uniform(5e-4, 3e-2, st.shape).astype(np.float32)
    flags = rng.choice([VALID, ILL_CONDITIONED, LOW_TEXTURE], st.shape).astype(np.uint8)
    s0, s1 = copy.deepcopy(st), copy.deepcopy(st)
    c0 = update(s0, m_rho, m_std, flags, kernels=kernels)
    r0 = fused_map(s0, kernels=kernels)
    meas = RangeResult(range_m=np.empty(st.shape, np.float32), confidence=np.empty(st.shape, np.float32),
                       method="dense", inv_range_per_m=m_rho.copy(), inv_range_std_per_m=m_std.copy(),
                       flags=flags.copy(), info={})
    c1, r1 = update_and_map(s1, meas.inv_range_per_m, meas.inv_range_std_per_m, meas.flags, kernels=kernels,
                            reuse=meas)
    assert c0 == c1 and same_info(r0, r1)
    for name in ("rho", "var", "a", "b", "n"):
        assert np.array_equal(getattr(s0, name), getattr(s1, name), equal_nan=True), name
    for name in ("flags", "inv_range_per_m", "inv_range_std_per_m", "range_m", "confidence"):
        assert np.array_equal(getattr(r0, name), getattr(r1, name), equal_nan=True), name
    if kernels:
        assert r1.inv_range_per_m is meas.inv_range_per_m          # written into the measurement's arrays


@pytest.mark.parametrize("kernels", PATHS)
def test_predict_into_a_used_state_equals_predict_into_a_fresh_one(kernels):
    rng = np.random.default_rng(9)
    c = cam(64, 48)
    st = planar_state(c, 1 / 20.0)
    st.rho[rng.random(st.shape) < 0.3] = np.nan
    dirty = planar_state(c, 0.3, var=0.5)                     # a previous state's arrays, full of other values
    new = pose(north=1.0, east=0.3, t=0.1)
    p0 = predict(st, c, new, 0.1, kernels=kernels)
    p1 = predict(st, c, new, 0.1, kernels=kernels, out=dirty)
    assert p1 is dirty
    for name in ("rho", "var", "a", "b", "n", "du", "dv", "flags"):
        assert np.array_equal(getattr(p0, name), getattr(p1, name), equal_nan=True), name


@pytest.mark.skipif(optional_kernels() is None, reason="numba not installed")
def test_a_warp_across_many_rows_into_a_used_state_equals_one_into_a_fresh_one():
    # the warp empties its output rows as its scatter reaches them: points that move many rows up and down (a roll
    # of 25 deg about the optical axis, a yaw of 10 deg) must meet emptied cells, not the used state's contents
    rng = np.random.default_rng(4)
    c = cam(80, 60)
    st = planar_state(c, 1 / 15.0)
    st.rho[rng.random(st.shape) < 0.3] = np.nan
    new = VehicleState.from_ypr([0.5, 0.2, 0.0], np.deg2rad([10.0, 3.0, 25.0]), 0.1)
    dirty = planar_state(c, 0.4, var=0.5)
    dirty.n[...], dirty.flags[...], dirty.du[...] = 9, 255, 0.3
    p0 = predict(st, c, new, 0.1, kernels=True)
    p1 = predict(st, c, new, 0.1, kernels=True, out=dirty)
    ref = predict(st, c, new, 0.1, kernels=False)
    assert np.isnan(p0.rho).any() and np.isfinite(p0.rho).any()
    for name in ("rho", "var", "a", "b", "n", "du", "dv", "flags"):
        assert np.array_equal(getattr(p0, name), getattr(p1, name), equal_nan=True), name
    assert np.array_equal(np.isfinite(p0.rho), np.isfinite(ref.rho))
    assert np.allclose(p0.rho[np.isfinite(ref.rho)], ref.rho[np.isfinite(ref.rho)], rtol=1e-5)


# --- weak measurements -------------------------------------------------------------------------------------------

@pytest.mark.parametrize("kernels", PATHS)
def test_weak_measurements_are_fused_only_when_their_sigma_explains_the_flag(kernels):
    # ILL_CONDITIONED at a relative sigma of 0.5 (above the dense method's 0.34): fused; ILL_CONDITIONED at a tight
    # sigma (flagged for another reason): not; with another fault bit too: not; weak=False: only VALID
    cases = [(ILL_CONDITIONED, 0.025, True), (ILL_CONDITIONED, 0.005, False),
             (ILL_CONDITIONED | LOW_TEXTURE, 0.025, False), (VALID, 0.005, True)]
    for flags, tau, fused in cases:
        for cfg, want in ((UpdateConfig(), fused), (UpdateConfig(weak=False), fused and flags == VALID)):
            st = one_cell_state()
            c = measure(st, 0.05, tau, kernels, cfg, flags)
            assert (c["measured"] == 16) == want and (c["measured"] == 0) == (not want), (flags, tau, cfg.weak)
    # rho within 2 sigma of 0 (far, or near the focus of expansion): weak too
    st = one_cell_state()
    assert measure(st, 0.001, 0.002, kernels, UpdateConfig(), ILL_CONDITIONED)["measured"] == 16


@pytest.mark.parametrize("kernels", PATHS)
def test_a_weak_measurement_with_any_other_fault_bit_is_not_fused(kernels):
    """"Weak" is ILL_CONDITIONED whose only fault is its own sigma: at a relative sigma of 0.5 an ILL_CONDITIONED
    pixel alone is fused, but with any other fault (a failed truncation test, hidden or out of view in b, no
    texture, filled by the plane fit) it carries no measurement, neither moving a converged cell nor starting an
    empty one."""
    for bit in (TRUNCATION, OUT_OF_VIEW, OUT_OF_VIEW | OCCLUDED, OCCLUDED, LOW_TEXTURE, FILLED):
        st = one_cell_state()
        assert measure(st, 0.05, 0.025, kernels, UpdateConfig(), ILL_CONDITIONED | bit)["measured"] == 0, bit
        assert not st.occupied().any()
        st = planar_state(cam(4, 4), 0.04)
        assert measure(st, 0.05, 0.025, kernels, UpdateConfig(), ILL_CONDITIONED | bit)["measured"] == 0, bit
        assert (st.rho == np.float32(0.04)).all() and (st.n == 3).all()
    st = one_cell_state()
    assert measure(st, 0.05, 0.025, kernels, UpdateConfig(), ILL_CONDITIONED)["started"] == 16


@pytest.mark.parametrize("kernels", PATHS)
def test_a_weak_measurement_within_2_sigma_of_0_is_fused_also_under_a_loose_relative_sigma_limit(kernels):
    """"Weak" is a relative sigma above max_rel_std OR rho within 2 sigma of 0; the second alone counts once
    max_rel_std >= 0.5. With max_rel_std 0.8: ILL_CONDITIONED at 0.05 +- 0.0275 (relative 0.55 < 0.8, but 2 sigma
    0.055 > 0.05) is weak and fused; at 0.05 +- 0.0225 (2 sigma 0.045 < 0.05, relative 0.45) it is tight, flagged
    for another reason, and not fused. Catches the near-0 test written rho >= sigma (1 sigma)."""
    cfg = UpdateConfig(max_rel_std=0.8)
    for tau, fused in ((0.0275, True), (0.0225, False)):
        st = one_cell_state()
        c = measure(st, 0.05, tau, kernels, cfg, ILL_CONDITIONED)
        assert c["measured"] == (16 if fused else 0) and st.occupied().all() == fused, tau


@pytest.mark.parametrize("kernels", PATHS)
def test_many_weak_measurements_add_up_to_a_confident_range(kernels):
    # 20 measurements of rho = 0.01 (100 m) with a relative sigma of 0.5 each (no single pair could range it):
    # the fused sigma is 0.5 / sqrt(20) = 0.11 relative (a little more: at this sigma the Gaussian's density, ~50 /m,
    # is not far above the outlier density of 0.5 /m, so each update keeps some of the mixture's spread), VALID,
    # within 3 sigma of the truth
    rng = np.random.default_rng(11)
    st = one_cell_state()
    tau = 0.005
    xs = 0.01 + tau * rng.standard_normal(20)
    for k, x in enumerate(xs, 1):
        measure(st, float(x), tau, kernels, UpdateConfig(), ILL_CONDITIONED)
        m = fused_map(st, MapConfig(fill=False))
        if k == 1:
            assert not (m.flags & VALID).any()                 # one weak measurement: no range
    assert tau ** 2 / 20 <= st.var[0, 0] <= 1.3 * tau ** 2 / 20
    assert (m.flags & VALID).all() and abs(st.rho[0, 0] - 0.01) < 3 * tau / np.sqrt(20)


def test_fused_sigma_is_calibrated_on_a_flight_it_was_not_tuned_on():
    # slant_px was calibrated on the approach flight at 320 x 320, noise seed 0; here 160 x 160, seed 3: the robust
    # z spread of the fused last frame's VALID pixels is within 0.8-1.2 (measured 0.86); without the slant term the
    # sigma is too small (1.21; above 1.3 before the window's own residual went into the pairs' sigma, which now
    # carries part of the window's error): the pairs share the window's error. Held: in the band with it, and
    # without it more than 1.25 x that
    from dataclasses import replace

    from eonav.app.bench_fuse import z_spread
    from eonav.sim.sequence import render_sequence
    seq = render_sequence("flight:approach", n_frames=12, rate_hz=30.0, size=160, supersample=2, seed=3)
    truth = seq.truth[-1].range_m
    mask = np.isfinite(truth) & (truth > 0)
    z = {}
    for slant in (MapConfig().slant_px, 0.0):
        runner = FusionRunner(replace(FusionConfig(), output=MapConfig(slant_px=slant)))
        for k, v in enumerate(seq.views):
            maps = runner.push(frame("nose", v, int(round(v.state.t_s * 1e6)), k))
        z[slant] = z_spread(maps[0].result, truth, mask)
    assert 0.8 <= z[MapConfig().slant_px] <= 1.2 and z[0.0] > 1.25 * z[MapConfig().slant_px], z


def test_wide_partner_metrics_of_the_whole_history_equal_the_pair_policys():
    # wide_metrics (all candidates at once) against pair_metrics one by one: a turning, climbing camera with a lever
    # arm, and one frame turned 100 deg away (some probes behind it: the median over the rest, as pair_metrics)
    from dataclasses import replace as dc_replace

    from eonav.fusion.schedule import wide_metrics
    from eonav.ranging.pair_policy import pair_metrics
    c = dc_replace(cam(640, 480, 500.0), l_body_m=np.array([2.0, 0.5, -0.3]))
    rng = np.random.default_rng(13)
    views = [View(c, VehicleState.from_ypr(rng.normal(0, 5, 3) + [3.0 * k, 0, 0], np.deg2rad(rng.normal(0, 3, 3)),
                                           0.1 * k), np.zeros((480, 640))) for k in range(8)]
    views.append(View(c, VehicleState.from_ypr([30.0, 0, 0], np.deg2rad([100.0, 0, 0]), 0.8), np.zeros((480, 640))))
    fs = [frame("c", v, int(round(v.state.t_s * 1e6)), k) for k, v in enumerate(views)]
    a = fs[4]
    rot, disp, base = wide_metrics(a, fs, 50.0)
    for i, b in enumerate(fs):
        m = pair_metrics(a, b, 50.0)
        assert rot[i] == pytest.approx(m.rotation_deg, abs=1e-9)
        assert disp[i] == pytest.approx(m.disparity_px, rel=1e-9, abs=1e-9)
        assert base[i] == pytest.approx(m.baseline_m, rel=1e-12)
    assert 0 < disp[-1] and rot[-1] > 90


def test_a_custom_measurement_is_left_alone_unless_declared_fresh():
    # the fused map is written into the measurement's arrays only when nobody else holds them: the default dense
    # measurement, or a custom one declared fresh_measurements=True; a custom one that keeps its results is not touched
    from eonav.ranging.rangemap import RangeResult
    c = cam(32, 24)
    kept = []

    def plane(va, vb):
        sh = (c.height, c.width)
        r = RangeResult(range_m=np.full(sh, 20.0, np.float32), confidence=np.full(sh, 20.0, np.float32),
                        method="test", inv_range_per_m=np.full(sh, 0.05, np.float32),
                        inv_range_std_per_m=np.full(sh, 1e-3, np.float32), flags=np.full(sh, VALID, np.uint8),
                        info={})
        kept.append(r)
        return r

    views = [View(c, pose(east=5.0 * k, t=0.1 * k), np.zeros((24, 32), np.float32)) for k in range(3)]
    for fresh in (None, True):
        kept.clear()
        runner = FusionRunner(FusionConfig(), measure=plane, fresh_measurements=fresh)
        maps = []
        for k, v in enumerate(views):
            maps += runner.push(frame("c", v, int(round(v.state.t_s * 1e6)), k))
        assert len(maps) == 2 and len(kept) == 2
        shared = [m.result.inv_range_std_per_m is r.inv_range_std_per_m for m, r in zip(maps, kept)]
        if fresh:
            assert all(shared)
        else:
            assert not any(shared)
            assert all(np.all(r.inv_range_std_per_m == 1e-3) and np.all(r.range_m == 20.0) for r in kept)


def test_a_hovering_cameras_frames_without_a_partner_still_give_the_predicted_map():
    """A camera that stops (hovers) keeps pairing with its frames of before the stop until they are older than the
    pair policy's max_age_s (1 s); its frames after that have no partner and are measured against nothing, yet each
    still gives the map of its predicted state (what the obstacle service publishes from): the 20 m the stub
    measurement ranged, no measurement, n_fused as the frame before's. Catches a planted map condition that wants a
    measurement of the frame (a hovering vehicle's maps would stop 1 s after it stopped)."""
    from eonav.ranging.rangemap import RangeResult
    c = cam(32, 24)

    def plane(va, vb):               # every pixel 20 m (1 / 0.05), sigma 1e-3 per m
        sh = (c.height, c.width)
        return RangeResult(range_m=np.full(sh, 20.0, np.float32), confidence=np.full(sh, 20.0, np.float32),
                           method="test", inv_range_per_m=np.full(sh, 0.05, np.float32),
                           inv_range_std_per_m=np.full(sh, 1e-3, np.float32), flags=np.full(sh, VALID, np.uint8),
                           info={})

    # 5 m to the right a frame (0.1 s), then still at 10 m east from 0.2 s to 1.5 s
    views = [View(c, pose(east=5.0 * min(k, 2), t=0.1 * k), np.zeros((24, 32), np.float32)) for k in range(16)]
    runner = FusionRunner(FusionConfig(), measure=plane, fresh_measurements=True)
    maps = {}
    for k, v in enumerate(views):
        out = runner.push(frame("c", v, int(round(v.state.t_s * 1e6)), k))
        assert [m.frame.seq for m in out] == ([k] if k else []), k
        maps[k] = out[0] if out else None
    alone = [k for k in range(1, 16) if not maps[k].measurements]
    assert alone == list(range(12, 16))       # frame 11 (1.1 s) pairs with frame 1 (0.1 s): 1 s old, still in age
    for k in alone:
        m, before = maps[k], maps[k - 1]
        ok = (m.result.flags & VALID) != 0
        assert ok.mean() > 0.9 and np.allclose(m.result.range_m[ok], 20.0, rtol=1e-3)
        assert np.array_equal(m.n_fused, before.n_fused)
        assert m.n_fused.max() >= 2


def test_schedulers_batched_pair_policy_decides_as_the_pair_policy():
    # the scheduler's pair policy takes its candidates' metrics from one wide_metrics pass per frame: on a stream of
    # a turning (some pairs beyond 10 deg), climbing camera at varying speed and with a gap older than the age limit,
    # its reasons, partners and metrics are those of PairPolicy's one pair_metrics at a time
    from dataclasses import replace as dc_replace

    from eonav.fusion.schedule import Scheduler
    from eonav.ranging.pair_policy import OK_MOTION, TOO_LITTLE_PARALLAX, TOO_MUCH_ROTATION, TOO_OLD, PairPolicy
    c = dc_replace(cam(640, 480, 500.0), l_body_m=np.array([2.0, 0.5, -0.3]))
    rng = np.random.default_rng(17)
    t, north, yaw, views = 0.0, 0.0, 0.0, []
    for k in range(40):
        t += 1.5 if k == 20 else 1 / 30
        north += float(rng.choice([0.05, 0.5, 3.0]))
        yaw += float(rng.choice([0.0, 0.5, 12.0], p=[0.5, 0.35, 0.15]))
        views.append(View(c, VehicleState.from_ypr([north, 0.2 * k, -0.1 * k], np.deg2rad([yaw, 1.0, 0.0]), t),
                          np.zeros((480, 640))))
    fs = [frame("c", v, int(round(v.state.t_s * 1e6)), k) for k, v in enumerate(views)]
    sched, plain = Scheduler(ScheduleConfig()), PairPolicy(ScheduleConfig().policy)
    reasons = set()
    for f in fs:
        got, want = sched.policy.offer(f), plain.offer(f)
        assert (got.reason, got.b and got.b.seq) == (want.reason, want.b and want.b.seq), f.seq
        for name in ("disparity_px", "baseline_m", "rotation_deg", "dt_s"):
            assert getattr(got, name) == pytest.approx(getattr(want, name), rel=1e-9, abs=1e-9, nan_ok=True)
        reasons.add(want.reason)
    assert {OK_MOTION, TOO_LITTLE_PARALLAX, TOO_MUCH_ROTATION, TOO_OLD} <= reasons, reasons


def _sideways(n, yaw_deg=None, speed_mps=1.0):
    """n frames of a 256 x 256 camera (f 256 px) looking north and flying east at ``speed_mps`` (1 m/s), 0.25 s
    apart (frame k at 0.25 k s, 0.25 k speed_mps m east; ``yaw_deg``: {k: yaw}). A sideways baseline B moves every
    pixel by f B / Z: at the policy's 50 m reference 5.12 px per metre, the same at every probe pixel, so the pair's
    median disparity is 5.12 B px."""
    from eonav.ranging.pair_policy import PosedFrameInfo
    c = Camera("nose", 256, 256, 256.0, 256.0, 127.5, 127.5)
    yaw_deg = yaw_deg or {}
    return [PosedFrameInfo("nose", k, 1_700_000_000_000_000 + 250_000 * k, c,
                           VehicleState.from_ypr([0.0, 0.25 * k * speed_mps, -10.0],
                                                 np.deg2rad([yaw_deg.get(k, 0.0), 0, 0]), 0.25 * k)) for k in range(n)]


def test_the_wide_partner_keeps_the_pair_policys_age_and_rotation_limits():
    """The wide partner is the earlier frame with the most parallax (up to wide_max_disparity_px) *within* the pair
    policy's age (1 s) and rotation (10 deg) limits: an older frame, or one turned 15 deg, has more parallax but is
    no partner (appearance and pose error grow with the gap). Hand values: 5.12 px per metre sideways (_sideways).
    Catches a planted us -> s slip in the wide candidates' age (1e-9 for 1e-6: every frame of the 48 kept within
    age) and a dropped rotation term in the wide test."""
    from eonav.fusion.schedule import WIDE, Scheduler
    fs = _sideways(7)                                  # the last at 1.5 s: frames 1.5, 1.25 (7.68, 6.4 px) too old
    sch = Scheduler(ScheduleConfig(pattern=(WIDE,)))
    for f in fs[:-1]:
        sch.offer(f)
    ms, _ = sch.offer(fs[-1])
    assert [(m.kind, m.b.seq) for m in ms] == [("wide", 2)]          # exactly 1.0 s back: at the limit, taken
    assert ms[0].disparity_px == pytest.approx(5.12, rel=1e-9) and ms[0].baseline_m == pytest.approx(1.0)
    fs = _sideways(5, yaw_deg={0: 15.0})               # the last at 1.0 s: frame 0 within age, but turned 15 deg
    sch = Scheduler(ScheduleConfig(pattern=(WIDE,)))
    for f in fs[:-1]:
        sch.offer(f)
    ms, _ = sch.offer(fs[-1])
    assert [(m.kind, m.b.seq) for m in ms] == [("wide", 1)]          # 0.75 m: 3.84 px (frame 0 would give 5.47)
    assert ms[0].disparity_px == pytest.approx(3.84, rel=1e-9) and ms[0].baseline_m == pytest.approx(0.75)


def test_the_wide_partner_is_the_one_with_the_most_parallax_up_to_the_disparity_cap():
    """Flying at 6 m/s (1.5 m, 7.68 px a frame): frame 4's candidates within the 1 s age are frames 3, 2, 1, 0 with
    7.68, 15.36, 23.04 and 30.72 px. The wide partner is the one with the most parallax up to wide_max_disparity_px
    (15): frame 3; with the cap at 16 px, frame 2 (15.36 px, 3 m). Catches the cap dropped from the wide test
    (frame 0 at 30.72 px: a pair the dense search's range and the pose error cannot serve)."""
    from eonav.fusion.schedule import WIDE, Scheduler
    fs = _sideways(5, speed_mps=6.0)
    for cap, seq, disp, base in ((15.0, 3, 7.68, 1.5), (16.0, 2, 15.36, 3.0)):
        sch = Scheduler(ScheduleConfig(pattern=(WIDE,), wide_max_disparity_px=cap))
        for f in fs[:-1]:
            sch.offer(f)
        ms, _ = sch.offer(fs[-1])
        assert [(m.kind, m.b.seq) for m in ms] == [("wide", seq)], cap
        assert ms[0].disparity_px == pytest.approx(disp, rel=1e-9) and ms[0].baseline_m == pytest.approx(base)


def test_near_and_wide_partners_alternate_frame_by_frame_derived_by_hand():
    """The default pattern (near, wide) at 1 m/s (1.28 px a frame, _sideways): frame 1 has no partner (1.28 px
    < the policy's 2 px, near and wide alike) and uses no turn; then near = the newest frame with >= 2 px (two
    back, 2.56 px), wide = the most parallax within 1 s (up to four back, 5.12 px), in turn: frame 2 near 0, 3 wide
    0 (3.84 px), 4 near 2, 5 wide 1 (5.12 px), 6 near 4. Catches the alternation lost (every frame near: a
    far point never gets the wide baseline it needs)."""
    from eonav.fusion.schedule import Scheduler
    fs = _sideways(7)
    sch = Scheduler(ScheduleConfig())
    got = [[(m.kind, m.b.seq, round(m.disparity_px, 6)) for m in sch.offer(f)[0]] for f in fs]
    assert got == [[], [], [("near", 0, 2.56)], [("wide", 0, 3.84)], [("near", 2, 2.56)], [("wide", 1, 5.12)],
                   [("near", 4, 2.56)]]


def test_a_stereo_pair_below_the_parallax_limit_qualifies_by_its_baseline():
    """A rig of two 256 px cameras 0.5 m apart (lever arms -0.25 / +0.25 m to the right): f B / Z at the 50 m
    reference is 2.56 px, below a 5 px parallax limit, so with min_baseline_m 0 there is no stereo measurement; a
    min_baseline_m of 0.4 m lets the 0.5 m baseline qualify (as it does a motion pair: PairPolicy), 0.6 m does not.
    Hand values: the reference frame (left) against the partner's frame 0.5 ms later, 2.56 px, 0.5 m. Catches the
    scheduler's stereo test dropping the baseline alternative."""
    from eonav.fusion.schedule import Scheduler
    from eonav.ranging.pair_policy import PairPolicyConfig, PosedFrameInfo
    left = Camera("left", 256, 256, 256.0, 256.0, 127.5, 127.5, l_body_m=[1.0, -0.25, 0.0])
    right = Camera("right", 256, 256, 256.0, 256.0, 127.5, 127.5, l_body_m=[1.0, 0.25, 0.0])
    t0 = 1_700_000_000_000_000
    st = VehicleState.from_ypr([0.0, 0.0, -10.0], [0.0, 0.0, 0.0], 0.0)
    for min_base, want in ((0.0, []), (0.4, [("stereo", "left", "right")]), (0.6, [])):
        sch = Scheduler(ScheduleConfig(policy=PairPolicyConfig(min_disparity_px=5.0, min_baseline_m=min_base),
                                       stereo_rig=("left", "right")))
        assert sch.offer(PosedFrameInfo("left", 0, t0, left, st))[0] == []
        ms, _ = sch.offer(PosedFrameInfo("right", 0, t0 + 500, right, st))
        assert [(m.kind, m.a.camera_id, m.b.camera_id) for m in ms] == want, min_base
        if ms:
            assert ms[0].disparity_px == pytest.approx(2.56, rel=1e-9) and ms[0].baseline_m == pytest.approx(0.5)


def _push_all(runner, views, camera_id="nose"):
    return [m for k, v in enumerate(views) for m in runner.push(frame(camera_id, v, int(round(v.state.t_s * 1e6)), k))]


@pytest.mark.skipif(optional_kernels() is None, reason="numba not installed")
def test_predict_beside_the_measurement_gives_the_same_maps_as_in_turn(fast_sequence):
    serial = _push_all(FusionRunner(FusionConfig(overlap_predict=False)), fast_sequence.views)
    overlap = _push_all(FusionRunner(FusionConfig(overlap_predict=True, overlap_min_cells=0)), fast_sequence.views)
    assert len(serial) == len(overlap) == len(fast_sequence.views) - 1
    for a, b in zip(serial, overlap):
        assert a.frame.seq == b.frame.seq and a.measurements == b.measurements
        for name in ("range_m", "inv_range_per_m", "inv_range_std_per_m", "confidence", "flags"):
            assert np.array_equal(getattr(a.result, name), getattr(b.result, name), equal_nan=True), name
        assert np.array_equal(a.n_fused, b.n_fused)


@pytest.mark.skipif(optional_kernels() is None, reason="numba not installed")
@pytest.mark.parametrize("full_every, min_cells", [(1, 128 * 128), (3, 0), (1, 128 * 128 + 1)])
def test_predict_runs_beside_the_measurement_unless_the_measurement_may_start_from_it(fast_sequence, monkeypatch,
                                                                                      full_every, min_cells):
    """Each predict and measurement of a push wait (a bounded time) for the other to have started: they see each
    other only if they run at the same time. With the prior on (full_every 3) a measurement may start from the
    predicted state, so predict runs first, on the caller's thread, and never sees its measurement start; so it
    does for a state (128 x 128) smaller than overlap_min_cells. Beside, the worker runs predict's kernels
    (``predict_job``'s function), its Python part runs before on the caller's thread."""
    import threading

    import eonav.fusion.sequence as seq_mod
    from eonav.fusion.sequence import PriorConfig, dense_measurement
    beside = full_every == 1 and min_cells <= 128 * 128
    wait_s = 10.0 if beside else 0.3
    seen = {"predict": [], "measure": []}
    started = {}

    def meeting(name, other, fn):
        def run(*a, **kw):
            started[name].set()
            seen[name].append((started[other].wait(wait_s), threading.get_ident()))
            return fn(*a, **kw)
        return run

    job_of = seq_mod.predict_job
    monkeypatch.setattr(seq_mod, "predict", meeting("predict", "measure", seq_mod.predict))       # in turn
    monkeypatch.setattr(seq_mod, "predict_job",                                                  # beside: its kernels
                        lambda *a, **kw: meeting("predict", "measure", job_of(*a, **kw)))
    runner = FusionRunner(FusionConfig(prior=PriorConfig(full_every=full_every), overlap_min_cells=min_cells),
                          measure=meeting("measure", "predict", dense_measurement),
                          fresh_measurements=True, takes_prior=True)
    views = fast_sequence.views[:3]
    maps = []
    for k, v in enumerate(views):
        started.update(predict=threading.Event(), measure=threading.Event())
        maps += runner.push(frame("nose", v, int(round(v.state.t_s * 1e6)), k))
    assert len(maps) == 2 and len(seen["predict"]) == 2 and len(seen["measure"]) == 2     # frames 1 and 2
    main = threading.get_ident()
    for (p_saw, p_thread), (m_saw, m_thread) in zip(seen["predict"], seen["measure"]):
        assert m_thread == main
        if beside:
            assert p_saw and m_saw and p_thread != main      # at the same time, predict on the worker
        else:
            assert not p_saw and m_saw and p_thread == main  # predict first, on the caller's thread
    assert runner.worker_cpu_s > 0 if beside else runner.worker_cpu_s == 0


def test_bench_fusion_time_reports_both_runners_against_the_plain_locate():
    """``eonav bench pipeline --fusion-time``: the same fused maps with predict before and beside the measurements
    (it raises otherwise), and per scale the wall and CPU times of both and of the plain locate."""
    import io

    from eonav.app.bench_pipeline import fusion_time
    out = io.StringIO()
    rows = fusion_time((160, 120), scales=(1.0, 0.5), n_frames=5, repeats=1, stream=out)
    # at 80 x 60 the approach flight's frames 1/30 s apart have too little parallax for a pair: said so, no row
    assert [(r["width"], r["height"]) for r in rows] == [(160, 120)]
    assert 1 <= rows[0]["frames"] <= 3           # frames 2-4 where the pair policy found a pair
    assert all(rows[0][f"{n}_{k}_ms"] > 0 for n in ("plain", "serial", "beside") for k in ("wall", "cpu"))
    assert out.getvalue().count("the same maps") == 1 and "80x60 (scale 0.5): no frame" in out.getvalue()


@pytest.mark.parametrize("kernels", PATHS)
def test_a_long_run_of_agreeing_measurements_keeps_the_cells_evidence_finite(kernels):
    # 300 tight measurements in a row that all agree: b decays by ~8/9 a step; below ~1e-5 the Beta's moment match
    # cancels in float32 (a_new inf, then NaN: the cell emptied itself) unless b is kept at least B_MIN
    rng = np.random.default_rng(7)
    w, h = 20, 16
    cam = Camera("c", w, h, 40.0, 40.0, (w - 1) / 2, (h - 1) / 2)
    st = InverseRangeState.empty(cam, VehicleState.from_ypr([0.0, 0.0, 0.0], [0.0, 0.0, 0.0], 0.0), 0.0)
    st.rho[...], st.var[...] = 0.02, 0.001 ** 2
    st.a[...], st.b[...], st.n[...] = 7.0, 1.0, 30
    flags = np.full(st.shape, VALID, np.uint8)
    std_m = np.full(st.shape, 0.0002, np.float32)
    for _ in range(300):
        rho_m = (0.02 + 0.0002 * rng.standard_normal(st.shape)).astype(np.float32)
        update(st, rho_m, std_m, flags, UpdateConfig(), kernels=kernels)
    assert np.isfinite(st.rho).all() and np.isfinite(st.a).all() and np.isfinite(st.b).all()
    assert (st.n == 330).mean() >= 0.98
    assert (st.a / (st.a + st.b) > 0.99).all()
    assert np.abs(st.rho - 0.02).max() < 0.0002


@pytest.mark.parametrize("kernels", PATHS)
def test_a_cells_measurement_count_stays_at_its_largest_value_and_the_cell_stays_reported(kernels):
    """n (uint16) stops at 65535 (36 min of 30 Hz frames on one cell: a hover): further measurements keep it there.
    Wrapped round to 0, then 1, a converged cell would count as one fresh measurement, and the held-single rule
    would withdraw its range the first time a pair did not range it (here: LOW_TEXTURE). Catches the saturation
    dropped (n + 1)."""
    st = one_cell_state()
    st.rho[...], st.var[...], st.a[...], st.b[...], st.n[...] = 0.04, 1e-6, 7.0, 1.0, 65534
    for _ in range(3):
        c = measure(st, 0.04, 2e-3, kernels)
        assert c["measured"] == 16 and (st.n == 65535).all()
    measure(st, 0.04, 2e-3, kernels, flags=LOW_TEXTURE)
    m = fused_map(st, MapConfig(fill=False), kernels=kernels)
    assert (st.n == 65535).all() and m.info["held_fraction"] == 0
    assert (m.flags == VALID).all() and np.allclose(m.range_m, 25.0, rtol=1e-4)


def _held_cell(kernels, n_valid, last_flags, mcfg=MapConfig(fill=False)):
    """One cell ranged 25 m by ``n_valid`` VALID measurements, then one with ``last_flags``, mapped with ``mcfg``
    by update_and_map (the locator's sweep) and by update then fused_map; both maps returned."""
    from eonav.fusion.fused_map import update_and_map
    st = one_cell_state()
    for _ in range(n_valid):
        measure(st, 0.04, 2e-3, kernels)
    s2 = copy.deepcopy(st)
    shape = st.shape
    args = (np.full(shape, 0.04, np.float32), np.full(shape, 2e-3, np.float32), np.full(shape, last_flags, np.uint8))
    update(st, *args, kernels=kernels)
    _, m2 = update_and_map(s2, *args, mcfg=mcfg, kernels=kernels)
    return fused_map(st, mcfg, kernels=kernels), m2, st


@pytest.mark.skipif(optional_kernels() is None, reason="numba not installed")
def test_held_single_rule_in_the_classification_kernel_matches_the_numpy_reference():
    """The held-single rule inside the numba classification (``_kernels.classify_state`` and ``update_classify``)
    against the numpy path (``_demote_held``), on seeded random states (every flag byte, n 0-3, empty cells): the
    same flags and counts, the same values to float rounding (the slant term's), with the rule on and off, by fused_map and by update_and_map."""
    from eonav.fusion.fused_map import update_and_map
    rng = np.random.default_rng(11)
    held_seen = 0
    for trial in range(12):
        h, w = 37 + trial, 53
        st, occ = _random_state(cam(w, h), rng, rho_lo=0.0, var_hi=1e-4)
        st.n[...] = np.where(occ, rng.integers(0, 4, (h, w)), 0)
        st.flags[...] = rng.integers(0, 256, (h, w))
        st.rho_far = 0.01
        m_rho = np.where(rng.random((h, w)) < 0.2, np.nan, rng.uniform(0.01, 0.3, (h, w))).astype(np.float32)
        m_std = rng.uniform(1e-3, 5e-2, (h, w)).astype(np.float32)
        m_flags = rng.integers(0, 256, (h, w)).astype(np.uint8)
        for cfg in (MapConfig(fill=False), MapConfig(), MapConfig(fill=False, held_single=False)):
            maps = [fused_map(st, cfg, kernels=k) for k in (False, True)]
            for k in (False, True):
                s2 = copy.deepcopy(st)
                maps.append(update_and_map(s2, m_rho, m_std, m_flags, mcfg=cfg, kernels=k)[1])
            for m0, m1 in (maps[:2], maps[2:]):
                assert same_info(m0, m1) and np.array_equal(m0.flags, m1.flags)
                for name in ("inv_range_per_m", "inv_range_std_per_m", "range_m", "confidence"):
                    a0, a1 = getattr(m0, name), getattr(m1, name)
                    ok = np.isfinite(a0)
                    assert np.array_equal(ok, np.isfinite(a1)) and np.allclose(a0[ok], a1[ok], rtol=1e-5), name
            held_seen += maps[0].info["held_fraction"] > 0
    assert held_seen >= 12                       # the rule demoted cells in the trials where it was on


@pytest.mark.parametrize("kernels", PATHS)
def test_a_single_measurement_no_later_pair_repeated_is_not_reported(kernels):
    # ranged once (n 1), then LOW_TEXTURE (faint sky ranged by one pair's mismatch, then never again): held, not
    # VALID (ILL_CONDITIONED, no range, confidence 0, counted as held; not contested); the rule off reports it at 25 m
    for m in _held_cell(kernels, 1, LOW_TEXTURE)[:2]:
        assert (m.flags == ILL_CONDITIONED).all() and np.isnan(m.range_m).all() and (m.confidence == 0).all()
        assert m.info["valid_fraction"] == 0 and m.info["held_fraction"] == 1.0
        assert m.info["disagree_fraction"] == 0            # its evidence itself agrees
    st = one_cell_state()                                # one loose (weak) measurement, then LOW_TEXTURE: held,
    measure(st, 0.04, 0.02, kernels, flags=ILL_CONDITIONED)  # but no range to withdraw (relative sigma 0.5)
    measure(st, 0.04, 0.02, kernels, flags=LOW_TEXTURE)
    m = fused_map(st, MapConfig(fill=False), kernels=kernels)
    assert (st.n == 1).all() and (m.flags == ILL_CONDITIONED).all() and m.info["held_fraction"] == 0
    # the pair looked and could not range it: held as well; a FILLED pixel (its neighbours' plane, not its own
    # match) is no range either (catches the held rule testing the VALID bit alone, which takes it for one)
    for last in (ILL_CONDITIONED, TRUNCATION, VALID | FILLED):
        for m in _held_cell(kernels, 1, last)[:2]:
            assert (m.flags == ILL_CONDITIONED).all() and m.info["held_fraction"] == 1.0
    for m in _held_cell(kernels, 1, ILL_CONDITIONED | TRUNCATION, MapConfig(fill=False, held_single=False))[:2]:
        assert (m.flags == VALID).all() and np.allclose(m.range_m, 25.0) and m.info["held_fraction"] == 0


@pytest.mark.parametrize("kernels", PATHS)
def test_a_fresh_single_measurement_and_two_held_ones_are_reported(kernels):
    # a cell started by this frame's pair (n 1, VALID in the last measurement): fresh, reported; one the last pair
    # did not see (OUT_OF_VIEW, or OCCLUDED in its image b: a partner that says nothing of the point): reported; two
    # measurements then one LOW_TEXTURE pair (n 2, held): the stream repeated it, reported
    for n_valid, last, n in ((0, VALID, 1), (1, OUT_OF_VIEW, 1), (1, OUT_OF_VIEW | OCCLUDED, 1), (1, VALID, 2),
                             (2, LOW_TEXTURE, 2)):
        m1, m2, st = _held_cell(kernels, n_valid, last)
        assert (st.n == n).all()
        for m in (m1, m2):
            assert (m.flags == VALID).all() and np.allclose(m.range_m, 25.0, rtol=1e-5)
            assert m.info["held_fraction"] == 0


@pytest.mark.parametrize("kernels", PATHS)
def test_a_held_cell_in_a_converged_plane_is_filled_from_it_not_its_own_range(kernels):
    # a cell of the converged plane restarted 10 % nearer by one measurement the last pair did not range: the plane
    # stands in for it (as for any cell without a range, also with contested cells never filled); without the fill it
    # has no range at all
    c, plane, st = converged_plane()
    st.flags[...] = VALID
    st.rho[20, 30], st.var[20, 30], st.n[20, 30] = plane[20, 30] / 0.9, 1e-8, 1
    st.flags[20, 30] = LOW_TEXTURE
    m = fused_map(st, MapConfig(), kernels=kernels)
    assert m.flags[20, 30] & FILLED and not m.flags[20, 30] & VALID
    assert m.range_m[20, 30] == pytest.approx(1 / plane[20, 30], rel=1e-3)
    never = fused_map(st, MapConfig(contested_rel_std=0.0), kernels=kernels)
    assert never.flags[20, 30] & FILLED and never.range_m[20, 30] == pytest.approx(1 / plane[20, 30], rel=1e-3)
    bare = fused_map(st, MapConfig(fill=False), kernels=kernels)
    assert np.isnan(bare.range_m[20, 30]) and bare.flags[20, 30] == ILL_CONDITIONED
    assert bare.info["held_fraction"] == pytest.approx(1 / st.rho.size) and bare.info["disagree_fraction"] == 0
    off = fused_map(st, MapConfig(held_single=False), kernels=kernels)
    assert off.flags[20, 30] & VALID and off.range_m[20, 30] == pytest.approx(0.9 / plane[20, 30], rel=1e-4)
