"""The dense method's sigma along a straight edge nearly parallel to the epipolar direction (the aperture problem).

A rectified pair (epipolar direction: the image rows) of a fronto-parallel plane at disparity d carrying weak
band-limited texture and one strong straight edge (a tanh step of +-60 grey levels) at angle theta to the rows.
Image b is image a shifted by d along the rows and, where a pose error is simulated, by ``shift`` px across them (the
epipolar line's position error). For the edge alone the across shift moves the match along the row by
shift / tan(theta) (its gradient g = |g| (-sin theta, cos theta) only sees the motion along itself); the window's
weak texture pulls it back part of the way. ``locate_dense(aperture_px=...)`` puts the window's gain from such a shift
to its disparity into the sigma (``dense._aperture_gain``, ``dense._apply_aperture``).
"""
from __future__ import annotations

import numpy as np
import pytest

from eonav.geometry.camera import Camera, VehicleState, View
from eonav.ranging.methods.dense import locate_dense
from eonav.ranging.rangemap import AT_INFINITY, VALID
from test_dense import infinity_pair

F, B = 500.0, 0.1          # focal length (px) and baseline (m): rho = d / (F B)
H, W = 120, 160


def texture(x, y, seed=3, k=60):
    """Band-limited analytic texture (random plane waves, as tests/test_dense.py's), zero mean, unit-ish scale."""
    rng = np.random.default_rng(seed)
    fr, th, ph = rng.uniform(0.02, 0.2, k), rng.uniform(0, 2 * np.pi, k), rng.uniform(0, 2 * np.pi, k)
    s = np.zeros_like(x, dtype=np.float64)
    for f, t, p in zip(fr, th, ph):
        s += np.cos(2 * np.pi * f * (x * np.cos(t) + y * np.sin(t)) + p)
    return s / np.sqrt(k / 2)


def edge_pair(theta_deg, d=4.0, shift=0.0, tex=6.0, edge=60.0, seed=1):
    """Views of the edge scene and each pixel's distance to the edge line (px)."""
    y, x = np.mgrid[0:H, 0:W].astype(np.float64)
    th = np.radians(theta_deg)

    def img(xx, yy):
        s = -(xx - W / 2) * np.sin(th) + (yy - H / 2) * np.cos(th)     # signed distance to the edge
        return 128.0 + tex * texture(xx, yy) + edge * np.tanh(s / 0.8)

    rng = np.random.default_rng(seed)
    a = (img(x, y) + rng.normal(0, 1.0, (H, W))).astype(np.float32)
    b = (img(x + d, y + shift) + rng.normal(0, 1.0, (H, W))).astype(np.float32)   # b(u - d, v - shift) = a(u, v)
    st = VehicleState.from_ypr([0, 0, 0], [0, 0, 0])
    ca = Camera("L", W, H, F, F, (W - 1) / 2, (H - 1) / 2, [0, 0, 0], [0, 0, 0])
    cb = Camera("R", W, H, F, F, (W - 1) / 2, (H - 1) / 2, [0, B, 0], [0, 0, 0])
    dist = np.abs(-(x - W / 2) * np.sin(th) + (y - H / 2) * np.cos(th))
    return (View(ca, st, a), View(cb, st, b)), dist


def core_mask(dist, near=True):
    m = np.zeros_like(dist, bool)
    m[15:-15, 25:-15] = True
    return m & (dist < 2.5) if near else m & (dist > 8)


def z_of(res, mask, d):
    v = mask & ((res.flags & VALID) > 0)
    z = (res.inv_range_per_m[v] - d / (F * B)) / res.inv_range_std_per_m[v]
    return z, v


@pytest.mark.parametrize("theta,cot", [(45.0, 1.0), (30.0, 3 ** 0.5)])
def test_aperture_term_is_the_edges_cotangent(theta, cot):
    """On an edge with faint texture (tex 2 grey levels against a 120-level step) the window's gain is the edge's
    own, cot(theta): the term adds std_scale x aperture_px x cot(theta) px of disparity in quadrature (1.35 x 0.1 x
    1 = 0.135 px at 45 deg, measured 0.1347; 0.234 px at 30 deg), and leaves the estimate as it was."""
    views, dist = edge_pair(theta, tex=2.0)
    r0 = locate_dense(*views, aperture_px=0.0)
    r1 = locate_dense(*views, aperture_px=0.1)
    m = core_mask(dist) & ((r0.flags & VALID) > 0) & ((r1.flags & VALID) > 0)
    assert m.sum() > 200
    added = np.sqrt(r1.inv_range_std_per_m[m] ** 2 - r0.inv_range_std_per_m[m] ** 2) * F * B
    assert np.median(added) == pytest.approx(1.35 * 0.1 * cot, rel=0.05)
    np.testing.assert_array_equal(r0.inv_range_per_m, r1.inv_range_per_m)


def test_aperture_term_leaves_isotropic_texture_alone():
    """Away from the edge the texture has no preferred orientation: its gradients' cross-products cancel over a
    window up to the few independent gradients a 7 x 7 window of smooth texture holds (gain ~ 0.2), so the term adds
    little (median 0.026 px of disparity in quadrature to the texture's own ~0.1 px, against the 0.135 px a 45 deg
    edge gets)."""
    views, dist = edge_pair(45.0)
    r0 = locate_dense(*views, aperture_px=0.0)
    r1 = locate_dense(*views, aperture_px=0.1)
    m = core_mask(dist, near=False) & ((r0.flags & VALID) > 0)
    added = np.sqrt(np.maximum(r1.inv_range_std_per_m[m] ** 2 - r0.inv_range_std_per_m[m] ** 2, 0)) * F * B
    assert m.sum() > 0.9 * core_mask(dist, near=False).sum() and np.median(added) < 0.04


def test_shifted_epipolar_line_on_a_10_deg_edge():
    """b shifted 0.1 px across the epipolar line: the 10 deg edge's VALID pixels are ranged too far (disparity
    -0.31 px median; the edge alone would give -0.1 / tan 10 deg = -0.57 px). Without the term their z median is
    -3.1 (a bias the fusion would multiply), with it (aperture_px 0.1 = the shift) -0.75; with the exact pose the
    term only widens the sigma (z median within 0.5 either way)."""
    views, dist = edge_pair(10.0, shift=0.1)
    m = core_mask(dist)
    z0, v0 = z_of(locate_dense(*views, aperture_px=0.0), m, 4.0)
    z1, v1 = z_of(locate_dense(*views, aperture_px=0.1), m, 4.0)
    assert v0.sum() > 50 and np.median(z0) < -2.0
    assert v1.sum() == v0.sum() and abs(np.median(z1)) < 1.0
    views, _ = edge_pair(10.0, shift=0.0)
    z2, v2 = z_of(locate_dense(*views, aperture_px=0.1), m, 4.0)
    assert v2.sum() > 50 and abs(np.median(z2)) < 0.5


def test_aperture_term_takes_valid_away_above_max_rel_std():
    """The relative-sigma rule applies after the term: at aperture_px 1 the 10 deg edge's sigma is about 1.35 x 1 x
    4.4 px (its gain, the texture's pull included) on 4 px of disparity, far above max_rel_std 0.34, so its pixels
    lose VALID; at 0.1 px (0.6 px, 15 %) they keep it. The texture away from the edge keeps it at both."""
    views, dist = edge_pair(10.0)
    for ap, edge_valid in ((0.1, True), (1.0, False)):
        res = locate_dense(*views, aperture_px=ap)
        on = ((res.flags & VALID) > 0)[core_mask(dist)].mean()
        off = ((res.flags & VALID) > 0)[core_mask(dist, near=False)].mean()
        assert (on > 0.5) == edge_valid and off > 0.95


# measured z median of the edge's VALID pixels under the 0.1 px shift, term off (the default): the limit
OFF_Z = {10.0: -3.06, 45.0: -1.52}


@pytest.mark.parametrize("theta", [0.2, 1.0, 3.0, 10.0, 45.0])
@pytest.mark.parametrize("shift", [0.0, 0.1])
def test_edge_z_by_angle(theta, shift):
    """The measurement by angle (d 4 px, texture 6 grey levels, edge pixels within 2.5 px of the line). Below ~3 deg
    the window's epipolar share of the gradient energy is under orient_min and almost no edge pixel is VALID (0-6 %,
    ILL_CONDITIONED and filled). At 10 and 45 deg, with the exact pose, the default sigma holds (z median within
    0.1); under the 0.1 px shift across the epipolar line the default is biased (z median -3.06 at 10 deg, -1.52 at
    45 deg: the limit, docs/methods.md "Known limits"), and aperture_px 0.1 brings every angle's z median within 1
    (-0.37 / -0.63 / -0.75 / -0.72 at 1 / 3 / 10 / 45 deg)."""
    views, dist = edge_pair(theta, shift=shift)
    z_off, v_off = z_of(locate_dense(*views), core_mask(dist), 4.0)
    z_on, v_on = z_of(locate_dense(*views, aperture_px=0.1), core_mask(dist), 4.0)
    if theta < 5:
        assert v_off.sum() <= 0.1 * core_mask(dist).sum()
    else:
        assert v_off.sum() > 50 and v_on.sum() == v_off.sum()
        if shift == 0.0:
            assert abs(np.median(z_off)) < 0.1
        else:
            assert np.median(z_off) == pytest.approx(OFF_Z[theta], abs=0.3)
    if v_on.sum():
        assert abs(np.median(z_on)) < 1.0


def _approach_clear_frame(i: int, seed: int, supersample: int):
    """Frame i of the approach-clear scenario (15 Hz, 320 x 240) rendered as bench_tracking renders it, at the
    given supersampling (bench_tracking: 1)."""
    from eonav.app.bench_tracking import scenario, scene_at
    from eonav.sim.flight import flight, flight_states
    from eonav.sim.presets import scale_camera
    from eonav.sim.render import render
    sc = scenario("approach-clear", 30.0)
    fl = flight(sc.flight)
    cam = scale_camera(fl.camera, (320, 240))
    t = i / 15.0
    st = flight_states(sc.flight, np.array([t]))[0]
    r = render(scene_at(sc, fl.scene, t), cam, st, supersample=supersample, noise_sigma=1.0,
               seed=int(np.random.SeedSequence([seed, i]).generate_state(1)[0]))
    return View(cam, st, r.image), r


def test_runway_edge_false_range_is_the_renderers_aliasing():
    """The box-free approach's false track (docs/guidance.md, issue 12): the runway's edge 118-170 m out, just below
    the horizon (rows 110-119, columns 92-117 of frame 247, seed 0), within a degree of the epipolar direction. The
    motion pair 4 frames apart ranges 18 % of its pixels VALID at 0.54 of the truth (sigma 19 %, measured), while far
    ground beside it (columns 200-259, a third of it VALID) is within 4 %. The aperture term leaves the edge as it is
    (the window's gain from a shift across the epipolar line is small there: the edge's jagged rendering has
    gradient along it too). Started from the true rho at level 1 (a prior; the pair 2 frames apart, 0.60 searched)
    the window converges to 0.62, so neither the coarse search nor the coarse levels cause it. Rendered with 3 x 3
    supersampling instead of point sampling, the same pair ranges the edge at 0.90 on its 2 VALID pixels (0.8 % of
    the patch), far ground still within 2 %: the point-sampled edge's staircase does not move as the scene does."""
    def measure(supersample, **kw):
        va, ra = _approach_clear_frame(247, 0, supersample)
        vb, _ = _approach_clear_frame(243, 0, supersample)
        res = locate_dense(va, vb, **kw)
        out = []
        for cols in (slice(92, 118), slice(200, 260)):
            m = np.zeros(va.image.shape, bool)
            m[110:120, cols] = True
            m &= ra.object_id == 1
            v = m & ((res.flags & VALID) > 0)
            out.append((v.sum() / m.sum(), np.median(res.range_m[v] / ra.range_m[v]) if v.any() else np.nan))
        return out

    (edge_share, edge_ratio), (ctrl_share, ctrl_ratio) = measure(1)
    assert edge_share > 0.1 and edge_ratio < 0.7
    assert ctrl_share > 0.25 and abs(ctrl_ratio - 1.0) < 0.05
    (edge_share_a, edge_ratio_a), _ = measure(1, aperture_px=0.1)
    assert edge_share_a > 0.1 and edge_ratio_a < 0.7
    (edge_share, edge_ratio), (ctrl_share, ctrl_ratio) = measure(3)
    assert edge_share < 0.05 and (edge_share == 0 or edge_ratio > 0.85)
    assert ctrl_share > 0.25 and abs(ctrl_ratio - 1.0) < 0.05


def test_aperture_term_leaves_points_at_infinity_at_infinity():
    """The term is a disparity error of a finite range, so AT_INFINITY pixels (VALID, range +inf: rho within 2 sigma
    of 0) are left alone (``dense._apply_aperture``): on a textured scene at infinity (both images one texture, a
    0.5 m baseline: truth rho = 0 everywhere, tests/test_dense.py's infinity_pair) aperture_px 0.1 changes no flag,
    range or sigma. Applied to them, the relative-sigma rule (sigma <= max_rel_std x rho, never true at rho ~ 0)
    would take VALID from every one of them (measured 99.6 % of the image) and their range +inf with it."""
    views = infinity_pair()
    r0 = locate_dense(*views, aperture_px=0.0)
    r1 = locate_dense(*views, aperture_px=0.1)
    at_inf = (r0.flags & AT_INFINITY) > 0
    assert at_inf.mean() > 0.9 and np.all((r0.flags[at_inf] & VALID) > 0)        # the scene is what it claims
    np.testing.assert_array_equal(r1.flags, r0.flags)
    assert np.all(np.isposinf(r1.range_m[at_inf]))
    np.testing.assert_array_equal(r1.inv_range_std_per_m, r0.inv_range_std_per_m)
