"""The dense method's resolution match (``locate_dense(match_blur=True)``, off by default; ``dense._match_blur``): image a blurred
per pixel by the blur image b's texture carries in a's pixels (b's pixel box, pre-smoothing and bilinear warp,
scaled by the map's magnification), so that brightness constancy holds between a near and a far view of the same
texture. Checked against hand-derived magnifications and blur variances, and on a textured wall rendered by a
camera whose pixels integrate the scene (a box per pixel, supersampled), seen from farther back, from the side and
from nearer."""
from __future__ import annotations

import math

import cv2
import numpy as np
import pytest

from eonav.geometry.camera import Camera, VehicleState, View, pair_geometry
from eonav.ranging.methods import dense
from eonav.ranging.methods.dense import locate_dense
from eonav.ranging.rangemap import VALID

F32 = np.float32
WALL_M = 20.0
SIZE = 128


def _camera(size=SIZE):
    f = 0.8 * size
    c = (size - 1) / 2.0
    return Camera("wall", size, size, f, f, c, c)


def _render_wall(cam, pos_m, texture, cell_m=0.01, ss=4, noise=0.0, rng=None):
    """The wall x = WALL_M (texture on a cell_m grid, centred on y = z = 0) seen by ``cam`` at NED position pos_m
    looking north: every pixel the mean of ss x ss samples of its footprint (a camera's pixel integrates)."""
    d = WALL_M - pos_m[0]
    g = (np.arange(cam.width * ss) + 0.5) / ss - 0.5
    u, v = np.meshgrid(g, g)
    n = texture.shape[0]
    mx = ((pos_m[1] + (u - cam.cx) / cam.fx * d) / cell_m + n / 2).astype(F32)
    my = ((pos_m[2] + (v - cam.cy) / cam.fy * d) / cell_m + n / 2).astype(F32)
    img = cv2.resize(cv2.remap(texture, mx, my, cv2.INTER_LINEAR), (cam.width, cam.height), interpolation=cv2.INTER_AREA)
    if noise:
        img = img + F32(noise) * rng.standard_normal(img.shape).astype(F32)
    return img.astype(F32)


def wall_pair(b_pos_m, seed=0, noise=1.0):
    """View a at the origin, WALL_M from a textured wall, and view b at ``b_pos_m`` (NED), both looking north."""
    rng = np.random.default_rng(seed)
    tex = cv2.GaussianBlur(rng.standard_normal((3000, 3000)).astype(F32), (0, 0), 12.0) * F32(3000.0) + F32(128.0)
    cam = _camera()
    views = []
    for pos in ((0.0, 0.0, 0.0), tuple(b_pos_m)):
        views.append(View(cam, VehicleState.from_ypr(list(pos), [0.0, 0.0, 0.0]),
                          _render_wall(cam, pos, tex, noise=noise, rng=rng)))
    return views


def _interior(shape, k=16):
    m = np.zeros(shape, bool)
    m[k:-k, k:-k] = True
    return m


def test_magnification_is_the_ratio_of_distances_for_a_wall():
    # b 2 m farther back from the wall: the map a -> b scales the image by 20 / 22 about the principal point
    a, b = wall_pair((-2.0, 0.0, 0.0), noise=0.0)
    m = dense._magnification(pair_geometry(a, b), np.full(a.image.shape, 1.0 / WALL_M, F32))
    assert np.allclose(m[_interior(m.shape, 2)], WALL_M / (WALL_M + 2.0), atol=1e-4)
    # moved sideways, parallel to the wall: no scale change
    a, b = wall_pair((0.0, 1.0, 0.0), noise=0.0)
    m = dense._magnification(pair_geometry(a, b), np.full(a.image.shape, 1.0 / WALL_M, F32))
    assert np.allclose(m[_interior(m.shape, 2)], 1.0, atol=1e-4)
    # b nearer: magnified (and a, the coarser view, is not blurred for the scale below)
    a, b = wall_pair((3.0, 0.0, 0.0), noise=0.0)
    m = dense._magnification(pair_geometry(a, b), np.full(a.image.shape, 1.0 / WALL_M, F32))
    assert np.allclose(m[_interior(m.shape, 2)], WALL_M / (WALL_M - 3.0), atol=1e-4)


def _lerp_blurs(img, need):
    """What a's level-0 image should be for the blur variance ``need`` (level-0 px^2), by hand: the linear
    interpolation in variance between the Gaussian blurs of the ladder 0, 0.25, 0.5, 1, 2 around it."""
    ladder = (0.0, 0.25, 0.5, 1.0, 2.0)
    k = next(i for i in range(len(ladder) - 1) if ladder[i] < need <= ladder[i + 1])
    lo = img if k == 0 else cv2.GaussianBlur(img, (0, 0), math.sqrt(ladder[k]), borderType=cv2.BORDER_REFLECT)
    hi = cv2.GaussianBlur(img, (0, 0), math.sqrt(ladder[k + 1]), borderType=cv2.BORDER_REFLECT)
    w = (need - ladder[k]) / (ladder[k + 1] - ladder[k])
    return lo + F32(w) * (hi - lo)


@pytest.mark.parametrize("b_pos, need", [
    # sideways (m = 1): b's bilinear interpolation alone, variance 1/6
    ((0.0, 1.0, 0.0), 1.0 / 6.0),
    # 2 m farther: (1/12 + 0.6^2 + 1/6) (22 / 20)^2 - (1/12 + 0.6^2) = 0.29483
    ((-2.0, 0.0, 0.0), (1.0 / 12 + 0.36 + 1.0 / 6) * 1.21 - (1.0 / 12 + 0.36)),
    # 5 m farther: 0.61 x 1.5625 - 0.44333 = 0.5098 (the third rung)
    ((-5.0, 0.0, 0.0), (1.0 / 12 + 0.36 + 1.0 / 6) * 1.5625 - (1.0 / 12 + 0.36)),
])
def test_match_blur_gives_a_the_blur_variance_b_carries(b_pos, need):
    a, b = wall_pair(b_pos, noise=0.0)
    ia = np.ascontiguousarray(a.image)
    out = dense._match_blur(pair_geometry(a, b), ia, np.full(ia.shape, 1.0 / WALL_M, F32), 0.6)
    want = _lerp_blurs(ia, need)
    inner = _interior(ia.shape, 8)
    assert np.max(np.abs(out[inner] - want[inner])) < 0.02 * np.std(ia)


def test_match_blur_leaves_a_coarser_view_alone():
    # b 3 m nearer (m = 20 / 17): b's blur in a's pixels, 0.61 (17 / 20)^2 = 0.4407, is below a's own 0.4433
    a, b = wall_pair((3.0, 0.0, 0.0), noise=0.0)
    ia = np.ascontiguousarray(a.image)
    out = dense._match_blur(pair_geometry(a, b), ia, np.full(ia.shape, 1.0 / WALL_M, F32), 0.6)
    assert np.array_equal(out[_interior(ia.shape, 2)], ia[_interior(ia.shape, 2)])


def _wall_error(a, b, **kw):
    res = locate_dense(a, b, fill=False, **kw)
    ok = ((res.flags & VALID) != 0) & np.isfinite(res.range_m) & _interior(a.image.shape)
    assert ok.mean() > 0.5
    return float(np.median(np.abs(res.range_m[ok] - WALL_M) / WALL_M))


@pytest.mark.parametrize("back_m", [2.0, 4.0])
def test_match_blur_lowers_the_error_of_a_wall_seen_from_farther_back(back_m):
    # forward flight: the newer view a is nearer, b sees the texture smaller and blurrier; unmatched, the window's
    # match is off by ~0.8-1 % of the range (measured 0.99 / 0.80 %), matched 0.65 / 0.42 %
    a, b = wall_pair((-back_m, 0.4, 0.0))
    before, after = _wall_error(a, b), _wall_error(a, b, match_blur=True)
    assert after < 0.7 * before


def test_match_blur_changes_little_without_scale_change():
    # sideways (only the interpolation's blur; measured 0.40 -> 0.36 %) and b nearer (a not blurred; 0.22 % both):
    # within 0.05 points either way
    for pos in ((0.0, 1.0, 0.0), (3.0, 0.3, 0.0)):
        a, b = wall_pair(pos)
        before, after = _wall_error(a, b), _wall_error(a, b, match_blur=True)
        assert abs(after - before) < 5e-4
