"""Obstacle sectors and obstacle list against hand-made range maps (closed-form geometry) and simulator scenes
with known box positions (distance from the vehicle origin to the solid box, computed from the box itself)."""
import contextlib
import math
import struct
import sys
from dataclasses import replace

import numpy as np
import pytest

from eonav import InputError
from eonav.obstacles import detect as ob
from eonav.geometry.camera import Camera, VehicleState
from eonav.ranging.rangemap import AT_INFINITY, VALID

# 256 x 256, f = 128 px: horizontal FOV exactly 90 deg (pixel edges at -0.5 and 255.5, bearings -45 .. +45 deg)
CAM = Camera("nose", 256, 256, 128.0, 128.0, 127.5, 127.5)
ALT_M = 10.0
LEVEL = VehicleState.from_ypr([0.0, 0.0, -ALT_M], [0.0, 0.0, 0.0])
CFG = ob.ObstacleConfig(ground_down_m=0.0)


def ground_and_sky(cam=CAM, alt_m=ALT_M):
    """Range map of flat ground at NED down 0 seen by a level camera at height alt_m: x_c = h f / (v - cy)
    below the horizon, +inf above it."""
    v = np.arange(cam.height, dtype=np.float64)[:, None] * np.ones((1, cam.width))
    with np.errstate(divide="ignore"):
        r = np.where(v > cam.cy, alt_m * cam.fy / (v - cam.cy), np.inf)
    return r.astype(np.float32)


def add_wall(r, x_c_m, u0, u1, top_down_m=-20.0, cam=CAM, alt_m=ALT_M):
    """A wall facing the camera at x_c = x_c_m over columns u0..u1-1, from the ground up to NED down top_down_m."""
    v = np.arange(cam.height)
    z_ned = -alt_m + x_c_m * (v - cam.cy) / cam.fy          # down coordinate of the wall point seen on row v
    rows = (z_ned <= 0.0) & (z_ned >= top_down_m)
    r = r.copy()
    r[np.ix_(rows, np.arange(u0, u1))] = x_c_m
    return r


def bin_of(bearing_deg):
    """Element of the 72 x 5-degree layout holding a body-relative bearing: element k covers -20 + 5k +- 2.5 deg."""
    return int(math.floor((bearing_deg + 20.0) / 5.0 + 0.5)) % 72


def bins(*centres_deg):
    return sorted(bin_of(c) for c in centres_deg)


def clear_in_view(sectors, cam=CAM):
    """Bins wholly inside the camera's view are clear, all the others unknown (hand-checked in the test below)."""
    whole, _ = ob.bins_in_view(cam)
    want = np.where(whole, sectors.max_distance_cm + 1, ob.UINT16_MAX)
    return np.array_equal(sectors.distances_cm, want)


def test_sector_geometry_is_the_autopilots_layout():
    # element k is centred on -20 + 5k deg (angle_offset = element 0's centre), whatever the camera
    assert ob.sector_geometry(CAM) == (5.0, -20.0)
    yawed = Camera("side", 256, 256, 128.0, 128.0, 127.5, 127.5, eps_rad=np.deg2rad([30.0, -5.0, 0.0]))
    assert ob.sector_geometry(yawed) == (5.0, -20.0)
    s = ob.Sectors(np.zeros(72, np.uint16), 5.0, -20.0, 50, 15000)
    assert s.bin_centres_deg()[[0, 1, 4, 71]] == pytest.approx([-20.0, -15.0, 0.0, 335.0])
    assert [bin_of(b) for b in (-2.6, -2.4, 2.4, 2.6, 177.4, 182.4, -177.6, -22.4, -22.6)] == [3, 4, 4, 5, 39, 40, 40,
                                                                                             0, 71]


def test_bins_in_view_hand_derived():
    # CAM sees -45 .. +45 deg: whole bins are centred -40 .. 40, the bins at +-45 are seen by half
    whole, touched = ob.bins_in_view(CAM)
    assert sorted(np.flatnonzero(whole)) == bins(*range(-40, 41, 5))
    assert sorted(np.flatnonzero(touched)) == bins(*range(-45, 46, 5))
    # yawed 30 deg right: -15 .. 75 deg
    yawed = Camera("side", 256, 256, 128.0, 128.0, 127.5, 127.5, eps_rad=np.deg2rad([30.0, -5.0, 0.0]))
    whole, touched = ob.bins_in_view(yawed)
    assert sorted(np.flatnonzero(whole)) == bins(*range(-10, 71, 5))
    assert sorted(np.flatnonzero(touched)) == bins(*range(-15, 76, 5))
    # yawed 60 deg left with a 60-degree lens (f = 128 / tan 30): -90 .. -30; edges on bin edges? no: on centres
    left = Camera("left", 256, 256, 128.0 / math.tan(math.radians(30)), 128.0, 127.5, 127.5,
                  eps_rad=np.deg2rad([-60.0, 0.0, 0.0]))
    whole, touched = ob.bins_in_view(left)
    assert sorted(np.flatnonzero(whole)) == bins(*range(-85, -34, 5))
    assert sorted(np.flatnonzero(touched)) == bins(*range(-90, -29, 5))


def test_merge_sectors_keeps_nearest_then_clear_then_unknown():
    U, C = ob.UINT16_MAX, 15001
    a = ob.Sectors(np.full(72, U, np.uint16), 5.0, 0.0, 50, 15000)
    b = ob.Sectors(np.full(72, U, np.uint16), 5.0, 0.0, 50, 15000)
    a.distances_cm[[0, 1, 2, 3]] = [900, C, C, U]
    b.distances_cm[[0, 1, 2, 3]] = [700, 400, C, U]
    m = ob.merge_sectors([a, b])
    assert list(m.distances_cm[:5]) == [700, 400, C, U, U]
    with pytest.raises(InputError, match="different layouts"):
        ob.merge_sectors([a, ob.Sectors(b.distances_cm, 5.0, 0.0, 50, 10000)])


def test_merge_sectors_keeps_an_obstacle_at_max_distance():
    """A bin at exactly max_distance_cm is an obstacle (the sectors clip obstacle points farther out to it; the
    autopilots read [min, max] as measured): the merge keeps it alone, against another camera's clear or unknown, and
    a nearer one still wins. Catches the hit test taken as d < max_distance_cm (the bin became unknown)."""
    U, M, C = ob.UINT16_MAX, 15000, 15001
    a = ob.Sectors(np.full(72, U, np.uint16), 5.0, 0.0, 50, M)
    b = ob.Sectors(np.full(72, U, np.uint16), 5.0, 0.0, 50, M)
    a.distances_cm[[0, 1, 2, 3]] = [M, M, M, C]
    b.distances_cm[[0, 1, 2, 3]] = [U, C, 14000, U]
    assert list(ob.merge_sectors([a, b]).distances_cm[:5]) == [M, M, 14000, C, U]
    assert list(ob.merge_sectors([a]).distances_cm[:5]) == [M, M, M, C, U]


def hand_points(bearings_deg, hdist_m, weight):
    """Points at given body-relative bearings and horizontal distances (only what the sectors read)."""
    b = np.radians(np.asarray(bearings_deg, float))
    d = np.broadcast_to(np.asarray(hdist_m, float), b.shape).copy()
    n = b.size
    return ob.Points(np.arange(n), d, np.zeros((n, 3)), np.zeros((n, 3)), d, d, b, None, np.ones(n),
                     np.broadcast_to(np.asarray(weight, float), b.shape).copy())


def test_sector_pixel_thresholds_are_inclusive():
    # min_sector_pixels obstacle pixels (4 by default) report a distance, one fewer reports nothing; a pooled point
    # counts as the pixels it stands for; min_clear_pixels evidence pixels (20) make a bin wholly in view clear, 19
    # do not. Bin of bearing 0 (element 4): the 5th percentile of 12.34 m is 1234 cm.
    cfg, j, e = ob.ObstacleConfig(), bin_of(0.0), bin_of(10.0)
    assert (cfg.min_sector_pixels, cfg.min_clear_pixels) == (4, 20)
    no_inf = np.zeros(CAM.width)

    def sectors(n_obstacle, w_obstacle, n_evidence):
        pts = hand_points([0.0] * n_obstacle + [10.0] * n_evidence, 12.34, [w_obstacle] * n_obstacle + [1] * n_evidence)
        obstacle = np.arange(pts.idx.size) < n_obstacle
        return ob._sectors(pts, obstacle, ~obstacle, CAM, no_inf, cfg).distances_cm
    d = sectors(4, 1, 20)
    assert d[j] == 1234 and d[e] == 15001
    d = sectors(3, 1, 19)
    assert d[j] == ob.UINT16_MAX and d[e] == ob.UINT16_MAX
    assert sectors(1, 4.0, 0)[j] == 1234                  # one 2 x 2 pooling block


def test_ground_only_is_clear_and_nothing_is_an_obstacle():
    res = ob.analyse(ground_and_sky(), CAM, LEVEL, cfg=CFG)
    assert res.obstacles == []
    assert clear_in_view(res.sectors)


def test_unmeasured_columns_are_unknown():
    r = ground_and_sky()
    r[:, :64] = np.nan                                     # left quarter: no estimate at all
    res = ob.analyse(r, CAM, LEVEL, cfg=CFG)
    d = res.sectors.distances_cm
    clear = res.sectors.max_distance_cm + 1
    # columns 0..63 span bearings -45 .. atan(-64/128) = -26.57 deg: bins centred -45 .. -30 see nothing; the bin
    # centred -25 (-27.5 .. -22.5) sees ground; the bins at +-45 are only half in view: never clear
    assert all(d[bin_of(c)] == ob.UINT16_MAX for c in range(-45, -29, 5))
    assert all(d[bin_of(c)] == clear for c in range(-25, 41, 5))
    assert d[bin_of(45)] == ob.UINT16_MAX
    outside = [k for k in range(72) if not -45 <= ((5 * k - 20 + 180) % 360 - 180) <= 45]
    assert np.all(d[outside] == ob.UINT16_MAX)            # outside the camera's view: unknown, never clear


def test_sky_of_a_yawed_camera_clears_the_bins_it_looks_into():
    # only sky measured (the ground unranged): the evidence of free space is the pixels at infinity, binned by their
    # column's body-relative bearing, lens yaw included. A camera yawed 30 deg right sees -15 .. 75 deg: every bin
    # wholly inside that (-10 .. 70, hand-checked in test_bins_in_view_hand_derived) is clear, the others unknown
    yawed = Camera("side", 256, 256, 128.0, 128.0, 127.5, 127.5, eps_rad=np.deg2rad([30.0, 0.0, 0.0]))
    r = ground_and_sky(yawed)
    r[np.isfinite(r)] = np.nan
    res = ob.analyse(r, yawed, LEVEL, cfg=CFG)
    assert res.obstacles == [] and res.n_confident == 0
    d = res.sectors.distances_cm
    assert all(d[bin_of(c)] == 15001 for c in range(-10, 71, 5))
    assert clear_in_view(res.sectors, yawed)


def test_wall_distance_per_sector_hand_derived():
    # wall at x_c = 20 m over columns 128..191: bearings atan((u - 127.5)/128) = 0.22 .. 26.4 deg (edge 26.57)
    r = add_wall(ground_and_sky(), 20.0, 128, 192)
    res = ob.analyse(r, CAM, LEVEL, cfg=CFG)
    s = res.sectors
    clear = s.max_distance_cm + 1
    for c in (0, 5, 10, 15, 20, 25):                      # bins touched by the wall's bearings
        lo_b, hi_b = max(c - 2.5, 0.22), min(c + 2.5, 26.57)
        # horizontal distance of a wall point at bearing b is 20 / cos b: the bin's value lies between its bearings'
        lo_d, hi_d = 20.0 / math.cos(math.radians(lo_b)), 20.0 / math.cos(math.radians(hi_b))
        assert lo_d * 100 - 1 <= s.distances_cm[bin_of(c)] <= hi_d * 100 + 1, c
    assert all(s.distances_cm[bin_of(c)] == clear for c in (-40, -35, -30, -25, -20, -15, -10, -5, 30, 35, 40))
    assert s.distances_cm[bin_of(-45)] == s.distances_cm[bin_of(45)] == ob.UINT16_MAX
    # one obstacle: nearest point of the wall at 20 m straight ahead, to the right, below the vehicle at the bottom
    assert len(res.obstacles) == 1
    o = res.obstacles[0]
    assert o.horizontal_distance_m == pytest.approx(20.0, rel=0.02)
    assert 0.0 < o.bearing_deg < 26.4
    assert o.position_ned_m[0] == pytest.approx(20.0, abs=1e-3)     # the wall plane is x = 20 m north
    assert o.bbox_px[0] == 128 and o.bbox_px[2] == 191
    assert o.id == 1 and o.confidence == 1.0


def test_wall_straddling_a_bin_edge_lands_in_both_bins():
    # a post over columns 136..147: bearings atan((u - 127.5)/128) = 3.80 .. 8.95 deg straddles the edge at 7.5 deg
    # between the bins centred 5 and 10 (the layout that put angle_offset at a bin's left edge filed it half a bin
    # off); the bins on either side stay clear
    r = add_wall(ground_and_sky(), 20.0, 136, 148)
    s = ob.analyse(r, CAM, LEVEL, cfg=CFG).sectors
    clear = s.max_distance_cm + 1
    assert 2000 <= s.distances_cm[bin_of(5)] <= 2010 and 2010 <= s.distances_cm[bin_of(10)] <= 2030
    assert s.distances_cm[bin_of(0)] == clear and s.distances_cm[bin_of(15)] == clear


def test_sectors_report_the_horizontal_distance_of_a_low_wall():
    # a 3 m wall at x_c = 20 m over columns 128..191 seen from 10 m up: all its points are 7 .. 10 m below the
    # vehicle. OBSTACLE_DISTANCE is horizontal: the bins hold 20 / cos b as for a tall wall, not the slant
    # distance (>= hypot(20, 7) = 21.19 m), which the obstacle list's distance_m is
    r = add_wall(ground_and_sky(), 20.0, 128, 192, top_down_m=-3.0)
    res = ob.analyse(r, CAM, LEVEL, cfg=CFG)
    s = res.sectors
    for c in (0, 5, 10, 15, 20, 25):
        lo_b, hi_b = max(c - 2.5, 0.22), min(c + 2.5, 26.57)
        lo_d, hi_d = 20.0 / math.cos(math.radians(lo_b)), 20.0 / math.cos(math.radians(hi_b))
        assert lo_d * 100 - 1 <= s.distances_cm[bin_of(c)] <= hi_d * 100 + 1, c
    o, = res.obstacles
    assert o.horizontal_distance_m == pytest.approx(20.0, rel=0.02)
    assert o.distance_m >= math.hypot(20.0, 7.0)


def test_wall_below_ground_clearance_is_ground():
    # a 0.4 m kerb is within the 0.6 m ground clearance: not an obstacle
    r = add_wall(ground_and_sky(), 20.0, 100, 160, top_down_m=-0.4)
    res = ob.analyse(r, CAM, LEVEL, cfg=CFG)
    assert res.obstacles == [] and clear_in_view(res.sectors)


def test_beyond_max_distance_is_clear():
    r = add_wall(ground_and_sky(), 120.0, 100, 160)
    res = ob.analyse(r, CAM, LEVEL, cfg=ob.ObstacleConfig(ground_down_m=0.0, max_distance_m=100.0))
    assert res.obstacles == [] and clear_in_view(res.sectors) and res.sectors.max_distance_cm + 1 == 10001


def test_near_wall_is_clamped_to_min_distance():
    r = add_wall(ground_and_sky(), 0.3, 100, 160, top_down_m=-10.2)
    res = ob.analyse(r, CAM, LEVEL, cfg=ob.ObstacleConfig(ground_down_m=0.0, min_distance_m=1.0))
    # columns 100..159: bearings -12.1 .. 14.0 deg: the bins centred -10 .. 10 hold the wall at 0.3 m -> clamped to 1 m
    assert all(res.sectors.distances_cm[bin_of(c)] == 100 for c in (-10, -5, 0, 5, 10))


def test_min_obstacle_pixels_is_inclusive():
    # a 3 x 4 px patch 40 m ahead above the horizon (rows 40..42, columns 128..131, full resolution): 12 px =
    # min_obstacle_pixels is an obstacle and fills its bin (bearing 0.2..1.6 deg; horizontal distance 40.00..40.02
    # m); with one pixel of its middle row gone (11 px, the same 0.625 m height) it is speckle, dropped from the list
    # and from the sectors, its bin clear on the ground's evidence
    cfg = replace(CFG, max_width_px=0)
    assert cfg.min_obstacle_pixels == 12
    r = ground_and_sky()
    r[40:43, 128:132] = 40.0
    res = ob.analyse(r, CAM, LEVEL, cfg=cfg)
    o, = res.obstacles
    assert o.pixel_count == 12 and o.bbox_px == [128, 40, 131, 42]
    assert 4000 <= res.sectors.distances_cm[bin_of(0.0)] <= 4002
    r[41, 131] = np.inf
    res = ob.analyse(r, CAM, LEVEL, cfg=cfg)
    assert res.obstacles == [] and clear_in_view(res.sectors)


def test_depth_discontinuity_splits_adjacent_objects():
    r = add_wall(ground_and_sky(), 40.0, 60, 200)
    r = add_wall(r, 20.0, 100, 140)                        # a near post in front of the far wall
    res = ob.analyse(r, CAM, LEVEL, cfg=CFG)
    d = sorted(round(o.horizontal_distance_m) for o in res.obstacles)
    assert len(res.obstacles) == 3 and d[0] == 20          # post, and the wall left and right of it
    assert all(abs(x - 40) <= 2 for x in d[1:])


def test_obstacle_list_is_nearest_first_and_keeps_the_max_obstacles_nearest():
    # three walls facing the camera at x_c 30 m (columns 200..231, up to 10 m above the vehicle: top row 85), 40 m
    # (40..71, top row 96) and 20 m (120..135, up to 2 m above it: top row 115). Scanned row by row their components
    # come as 30, 40, 20 m; the list is nearest first (ids 1, 2, 3 in that order), and max_obstacles 2 keeps the two
    # nearest, 20 and 30 m, not the first two found. A facing wall's median point lies on its plane: north = x_c
    r = add_wall(ground_and_sky(), 30.0, 200, 232, top_down_m=-20.0)
    r = add_wall(r, 40.0, 40, 72, top_down_m=-20.0)
    r = add_wall(r, 20.0, 120, 136, top_down_m=-12.0)
    assert [int(np.flatnonzero(r[:, c] == x)[0]) for c, x in ((200, 30.0), (40, 40.0), (120, 20.0))] == [85, 96, 115]
    every = ob.analyse(r, CAM, LEVEL, cfg=CFG).obstacles
    assert [round(o.position_ned_m[0], 3) for o in every] == [20.0, 30.0, 40.0] and [o.id for o in every] == [1, 2, 3]
    assert every[0].distance_m < every[1].distance_m < every[2].distance_m
    two = ob.analyse(r, CAM, LEVEL, cfg=replace(CFG, max_obstacles=2)).obstacles
    assert [round(o.position_ned_m[0], 3) for o in two] == [20.0, 30.0] and [o.id for o in two] == [1, 2]


def test_flags_confidence_and_std_gate_pixels():
    r = add_wall(ground_and_sky(), 20.0, 128, 192)
    flags = np.full(r.shape, VALID, np.uint8)
    flags[np.isinf(r)] = AT_INFINITY
    flags[:, 128:192] = 0                                  # estimator does not stand behind the wall pixels
    res = ob.analyse(r, CAM, LEVEL, flags=flags, cfg=CFG)
    assert res.obstacles == []
    conf = np.ones(r.shape, np.float32)
    conf[:, 128:192] = 0.1
    res = ob.analyse(r, CAM, LEVEL, confidence=conf, cfg=ob.ObstacleConfig(ground_down_m=0.0, min_confidence=0.5))
    assert res.obstacles == []
    std = np.full(r.shape, 1e-4, np.float32)               # sigma_r / r = sigma_rho * r = 0.002
    std[:, 128:192] = 0.05                                 # 100 % at 20 m
    res = ob.analyse(r, CAM, LEVEL, inv_range_std_per_m=std, cfg=CFG)
    assert res.obstacles == []
    res = ob.analyse(r, CAM, LEVEL, inv_range_std_per_m=np.full(r.shape, 1e-3, np.float32), cfg=CFG)
    assert len(res.obstacles) == 1
    assert res.obstacles[0].range_std_m == pytest.approx(1e-3 * 400, rel=0.01)   # sigma_rho r^2


def test_range_std_without_per_pixel_sigma_is_the_normal_consistent_mad():
    # no inv_range_std_per_m: range_std_m is the ranges' robust spread, 1.4826 x their median absolute deviation (the
    # sigma of a normal distribution). A patch above the horizon (rows 40..79, full resolution) whose x_c grows 0.1 m a
    # column, 40.0 .. 46.3 m over columns 128..191 (no jump, no layer gap: one obstacle): median 43.15 m, deviations
    # 0.05 .. 3.15 m two columns each, their median 1.60 m, so 2.3722 m; with no sigma the range noise is the same
    r = ground_and_sky()
    r[40:80, 128:192] = (40.0 + 0.1 * np.arange(64))[None, :]
    o, = ob.analyse(r, CAM, LEVEL, cfg=replace(CFG, max_width_px=0)).obstacles
    assert o.pixel_count == 40 * 64
    assert o.range_std_m == pytest.approx(1.4826 * 1.60, abs=1e-4)
    assert o.range_noise_std_m == o.range_std_m
    # the same patch at 40 m with seeded normal range noise of sigma 0.5 m: range_std_m is that sigma (the estimate
    # from 2560 samples scatters by 2.3 % at one sigma, the MAD's efficiency being 37 %; 6 % is 2.6 sigma)
    r[40:80, 128:192] = 40.0 + np.random.default_rng(7).normal(0.0, 0.5, (40, 64))
    o, = ob.analyse(r, CAM, LEVEL, cfg=replace(CFG, max_width_px=0)).obstacles
    assert o.range_std_m == pytest.approx(0.5, rel=0.06)


def test_fused_evidence_count_gates_pixels():
    # a fused map: the wall's pixels fused from 2 measurements, the rest from 9
    r = add_wall(ground_and_sky(), 20.0, 128, 192)
    n = np.full(r.shape, 9, np.uint16)
    n[:, 128:192] = 2
    assert len(ob.analyse(r, CAM, LEVEL, cfg=CFG, n_fused=n).obstacles) == 1        # min_fused 1: off
    cfg2 = ob.ObstacleConfig(ground_down_m=0.0, min_fused=2)
    assert len(ob.analyse(r, CAM, LEVEL, cfg=cfg2, n_fused=n).obstacles) == 1       # 2 >= 2: kept
    cfg3 = ob.ObstacleConfig(ground_down_m=0.0, min_fused=3)
    res = ob.analyse(r, CAM, LEVEL, cfg=cfg3, n_fused=n)
    assert res.obstacles == []                                                      # 2 < 3: not trusted
    assert res.n_confident == np.count_nonzero(np.isfinite(r)) - np.count_nonzero(np.isfinite(r[:, 128:192]))
    # a map without n_fused (a single pair) is not affected by min_fused
    assert len(ob.analyse(r, CAM, LEVEL, cfg=cfg3).obstacles) == 1
    with pytest.raises(InputError, match="n_fused has shape"):
        ob.analyse(r, CAM, LEVEL, cfg=cfg3, n_fused=n[:10])
    with pytest.raises(InputError, match="min_fused"):
        ob.ObstacleConfig(min_fused=0)


def test_single_measurement_above_the_horizon_is_not_an_obstacle():
    # fused map: sky over rows 40..79 (rays above the horizon) ranged 40 m by one measurement, as a faint cloud one
    # pair mismatched and no pair measured since; everything else fused from 9
    r = ground_and_sky()
    r[40:80, 128:192] = 40.0
    n = np.full(r.shape, 9, np.uint16)
    n[40:80, 128:192] = 1
    on = replace(CFG, horizon_min_fused=2)
    assert ob.analyse(r, CAM, LEVEL, cfg=on, n_fused=n).obstacles == []            # 1 < horizon_min_fused 2
    off = ob.analyse(r, CAM, LEVEL, cfg=replace(CFG, horizon_min_fused=1), n_fused=n)
    assert len(off.obstacles) == 1                                                  # the rule off: kept
    assert len(ob.analyse(r, CAM, LEVEL, cfg=CFG, n_fused=n).obstacles) == 1       # off by default (the fused
    # map's held-single rule withdraws such a cell before the list sees it: tests/test_fusion.py)
    n[40:80, 128:192] = 2
    res = ob.analyse(r, CAM, LEVEL, cfg=on, n_fused=n)
    assert len(res.obstacles) == 1                                                  # 2 measurements: kept
    # the patch's nearest pixel (row 79, column 128): x_c 40 m, (v - cy, u - cx) = (-48.5, 0.5) px at f = 128 px;
    # distance_m is the 5th percentile, a little farther
    d = 40.0 * math.sqrt(1.0 + (0.5 / 128.0) ** 2 + (48.5 / 128.0) ** 2)
    assert d <= res.obstacles[0].distance_m <= 1.03 * d
    n[40:80, 128:192] = 1
    assert len(ob.analyse(r, CAM, LEVEL, cfg=on).obstacles) == 1                   # a single pair's map: no n_fused
    with pytest.raises(InputError, match="horizon_min_fused"):
        ob.ObstacleConfig(horizon_min_fused=0)


def test_single_measurement_rule_stops_at_the_horizon():
    # a wall 20 m ahead from the ground up to 20 m (rows 64..191), every wall pixel from one measurement: rows below
    # cy = 127.5 look down onto the ground (the ground tests vet them) and stay; rows above it look up and go
    r = add_wall(ground_and_sky(), 20.0, 128, 192)
    n = np.full(r.shape, 9, np.uint16)
    wall = np.zeros(r.shape, bool)
    wall[64:192, 128:192] = True
    assert np.all(r[wall] == 20.0) and not np.any(r[:64, 128:192] == 20.0)
    n[wall] = 1
    full = ob.analyse(r, CAM, LEVEL, cfg=replace(CFG, horizon_min_fused=1), n_fused=n)
    res = ob.analyse(r, CAM, LEVEL, cfg=replace(CFG, horizon_min_fused=2), n_fused=n)
    assert len(full.obstacles) == 1 and len(res.obstacles) == 1
    assert full.obstacles[0].bbox_px[1] == 64                                      # the wall's top row
    assert res.obstacles[0].bbox_px[1] == 128                                      # the first row below the horizon
    assert res.obstacles[0].bbox_px[3] == full.obstacles[0].bbox_px[3]
    assert full.n_confident - res.n_confident == 64 * 64                           # rows 64..127 not confident
    assert not res.data_mask[64:128, 128:192].any() and res.data_mask[128:, 128:192].all()


def test_horizontal_ray_counts_as_at_the_horizon():
    # a camera whose principal row is a whole row (cy = 127): row 127 looks exactly level, its ray never comes down
    # onto the level ground ("at or above its horizon"), so its single-measurement pixels (rows 100..127 ranged 40 m
    # by one measurement, horizon_min_fused 2) are not confident: 28 rows x 64 columns leave the map's data, row
    # 127 with them (its inverse range on the plane is exactly 0)
    cam = Camera("nose", 256, 256, 128.0, 128.0, 127.5, 127.0)
    r = ground_and_sky(cam)
    assert np.isinf(r[127]).all() and np.isfinite(r[128]).all()       # the ground's horizon is row 127
    r[100:128, 128:192] = 40.0
    n = np.full(r.shape, 9, np.uint16)
    n[100:128, 128:192] = 1
    full = ob.analyse(r, cam, LEVEL, cfg=replace(CFG, horizon_min_fused=1), n_fused=n)
    res = ob.analyse(r, cam, LEVEL, cfg=replace(CFG, horizon_min_fused=2), n_fused=n)
    assert full.n_confident - res.n_confident == 28 * 64
    assert full.data_mask[127, 128:192].all() and not res.data_mask[127, 128:192].any()


def test_data_mask_is_the_confident_pixels_and_the_sky():
    # the tracker's visibility mask (FieldOfView.data_mask): pixels with a usable range, confident or at infinity. A
    # level camera over flat ground: sky (rows 0..127, +inf, AT_INFINITY) and ground (rows 128..255, VALID); the left
    # quarter unmeasured (NaN) and a 40 x 20 px ground patch the estimator does not stand behind (flags 0). The mask
    # is columns 64..255 whole, less the patch: a track seen against the sky is visible and missed, not unmeasured
    r = ground_and_sky()
    r[:, :64] = np.nan
    flags = np.where(np.isinf(r), AT_INFINITY, VALID).astype(np.uint8)
    flags[:, :64] = 0
    flags[160:200, 100:120] = 0
    res = ob.analyse(r, CAM, LEVEL, flags=flags, cfg=CFG)
    want = np.zeros(r.shape, bool)
    want[:, 64:] = True
    want[160:200, 100:120] = False
    assert np.array_equal(res.data_mask, want)
    assert res.n_confident == 128 * 192 - 40 * 20                                  # the ground's share of it


def test_obstacle_elevation_is_positive_up():
    # a patch ranged 40 m over rows 40..79, columns 128..191 (above the horizon; full resolution): its median body
    # point is (40, 40 x 32 / 128, 40 x (59.5 - 127.5) / 128) = (40, 10, -21.25) m (FRD: z down), so it stands
    # atan2(21.25, hypot(40, 10)) = 27.26 deg up at bearing atan2(10, 40) = 14.04 deg right
    r = ground_and_sky()
    r[40:80, 128:192] = 40.0
    o, = ob.analyse(r, CAM, LEVEL, cfg=replace(CFG, max_width_px=0)).obstacles
    assert o.elevation_deg == pytest.approx(math.degrees(math.atan2(21.25, math.hypot(40.0, 10.0))), abs=1e-6)
    assert o.bearing_deg == pytest.approx(math.degrees(math.atan2(10.0, 40.0)), abs=1e-6)
    # a 3 m wall on the ground 20 m ahead, 7 .. 10 m below the vehicle and 20 .. 22.4 m away: it is seen down
    o, = ob.analyse(add_wall(ground_and_sky(), 20.0, 128, 192, top_down_m=-3.0), CAM, LEVEL, cfg=CFG).obstacles
    assert -math.degrees(math.atan2(10.0, 20.0)) <= o.elevation_deg <= -math.degrees(math.atan2(7.0, 22.4))


def test_obstacle_width_is_across_the_line_of_sight():
    # a wall facing the camera 20 m ahead over columns 96..159 (symmetric about cx = 127.5, full resolution): its
    # median point is on the nose axis, so "across the line of sight" is east. Each column holds the same number of
    # wall pixels, so the 5th and 95th percentiles of east fall in the 4th column from either edge (u = 99 and 156):
    # width 20 x (156 - 99) / 128 = 8.906 m, the east extent the same and the north extent 0 (a face, no depth)
    o, = ob.analyse(add_wall(ground_and_sky(), 20.0, 96, 160), CAM, LEVEL, cfg=replace(CFG, max_width_px=0)).obstacles
    assert o.bearing_deg == pytest.approx(0.0, abs=1e-9)
    assert o.width_m == pytest.approx(20.0 * (156 - 99) / 128.0, abs=1e-6)
    assert o.extent_ned_m[1] == pytest.approx(o.width_m, abs=1e-6) and o.extent_ned_m[0] == pytest.approx(0.0, abs=1e-9)


def test_points_too_high_above_the_vehicle_are_ignored():
    # the patch above, 40 m ahead: row v stands 40 (127.5 - v) / 128 m above the vehicle, 27.3 m (row 40) .. 15.2 m
    # (row 79). With max_height_above_m 20 only rows 64..79 (19.8 m and lower) are in the band: the obstacle's top
    # row is 64 (63 stands 20.2 m up); with 10 none is, and the bins stay clear (the points are evidence, not
    # obstacles)
    r = ground_and_sky()
    r[40:80, 128:192] = 40.0
    full = ob.analyse(r, CAM, LEVEL, cfg=CFG).obstacles
    assert len(full) == 1 and full[0].bbox_px[1] == 40 and full[0].bbox_px[3] == 79
    cut = ob.analyse(r, CAM, LEVEL, cfg=replace(CFG, max_height_above_m=20.0)).obstacles
    assert len(cut) == 1 and cut[0].bbox_px[1] == 64 and cut[0].bbox_px[3] == 79
    res = ob.analyse(r, CAM, LEVEL, cfg=replace(CFG, max_height_above_m=10.0))
    assert res.obstacles == [] and clear_in_view(res.sectors)


def test_range_jump_cut_in_units_of_the_pixels_sigma():
    # two walls side by side, 20 m (columns 96..127) and 27 m (128..159): a log-range jump of ln 1.35 = 0.300 at
    # their common edge; every pixel with a relative sigma of 0.1, so the cut needs 0.300 > k hypot(0.1, 0.1) =
    # 0.1414 k: k < 2.12 cuts (two obstacles), k > 2.12 joins them (one)
    r = add_wall(add_wall(ground_and_sky(), 20.0, 96, 128), 27.0, 128, 160)
    std = np.where(np.isfinite(r), 0.1 / r, 0.0).astype(np.float32)          # sigma_r / r = sigma_rho r = 0.1
    def n_obstacles(k):                      # the layer split off: it would part them (35 % > 30 %, below)
        return len(ob.analyse(r, CAM, LEVEL, inv_range_std_per_m=std,
                              cfg=replace(CFG, jump_sigma_k=k, layer_gap_rel=0.0)).obstacles)
    assert n_obstacles(2.25) == 1 and n_obstacles(3.0) == 1
    assert n_obstacles(2.0) == 2 and n_obstacles(1.5) == 2
    # k 0: max_rel_jump (8 %) alone decides; 35 % beats it
    assert n_obstacles(0.0) == 2
    with pytest.raises(InputError, match="jump_sigma_k"):
        ob.ObstacleConfig(jump_sigma_k=-1.0)


def test_layer_split_parts_two_ranges_the_jump_test_joins():
    # two walls side by side, 30 m (columns 96..127) and 40 m (128..159), relative sigma 0.1 on every pixel: the jump
    # ln(40 / 30) = 0.288 is below 3 hypot(0.1, 0.1) = 0.424, so the neighbour cut joins them; the two layers lie
    # 33 % apart (the near one's 90th percentile 30 m, the far one's 10th 40 m): two objects below that gap, one above
    r = add_wall(add_wall(ground_and_sky(), 30.0, 96, 128), 40.0, 128, 160)
    std = np.where(np.isfinite(r), 0.1 / r, 0.0).astype(np.float32)

    def obstacles(gap):
        return ob.analyse(r, CAM, LEVEL, inv_range_std_per_m=std, cfg=replace(CFG, layer_gap_rel=gap)).obstacles
    assert len(obstacles(0.0)) == 1 and len(obstacles(0.35)) == 1
    two = obstacles(0.30)
    assert len(two) == 2
    near, far = sorted(two, key=lambda o: o.distance_median_m)
    assert near.bbox_px[0] >= 96 and near.bbox_px[2] <= 127 and far.bbox_px[0] >= 128 and far.bbox_px[2] <= 159
    with pytest.raises(InputError, match="layer_gap_rel"):
        ob.ObstacleConfig(layer_gap_rel=-0.1)


def test_thin_mast_before_a_far_wall_joined_by_a_halo_is_its_own_obstacle():
    # a mast 4 px wide at 30 m (columns 126..129) before a wall at 70 m (96..159); between them, 3 px each side, a
    # halo of intermediate ranges (38, 48, 60 m) with a relative sigma of 0.2 (mast and wall 0.05), as a fused map's
    # window fattens a thin object: no neighbour jump beats 3 hypot of the sigmas, so the cut leaves one component,
    # whose median point is the wall's. Split into layers, the mast is listed at its own range.
    r = add_wall(ground_and_sky(), 70.0, 96, 160)
    rows = np.flatnonzero(r[:, 100] == 70.0)
    r = add_wall(r, 30.0, 126, 130)
    rel = np.where(np.isfinite(r), 0.05, 0.0)
    for c, x in ((125, 38.0), (124, 48.0), (123, 60.0), (130, 38.0), (131, 48.0), (132, 60.0)):
        r[rows, c] = x
        rel[rows, c] = 0.2
    std = (rel / r).astype(np.float32)

    def obstacles(gap):
        return ob.analyse(r, CAM, LEVEL, inv_range_std_per_m=std, cfg=replace(CFG, layer_gap_rel=gap)).obstacles
    assert CFG.layer_gap_rel == 0.4
    one = obstacles(0.0)
    assert len(one) == 1 and one[0].bbox_px[0] <= 96 and one[0].bbox_px[2] >= 159   # mast, halo and wall: one
    assert one[0].position_ned_m[0] > 60.0 and one[0].distance_m < 31.0    # its median point on the wall
    split = obstacles(CFG.layer_gap_rel)
    mast = [o for o in split if o.bbox_px[0] >= 120 and o.bbox_px[2] <= 135]
    assert len(mast) == 1
    assert abs(mast[0].position_ned_m[0] - 30.0) < 0.05 * 30.0           # its median point on the mast
    assert all(o.distance_m > 55.0 for o in split if o is not mast[0])  # the wall is apart


def test_layer_split_leaves_one_surface_receding_smoothly_whole():
    # a wall seen obliquely: its range grows from 30 m (column 96) to 90 m (column 159), 1.8 % a column, relative
    # sigma 0.1; the neighbour cut leaves one component. Its two halves at Otsu's split lie 10-20 % apart at their
    # 90th / 10th percentiles (no gap, only the spread of each half): one obstacle at the default gap and at 20 %,
    # two at 10 % (the two sides of what a ramp over a factor of 3 of range looks like)
    r = ground_and_sky()
    for c in range(96, 160):
        r = add_wall(r, 30.0 * 3.0 ** ((c - 96) / 63.0), c, c + 1)
    std = np.where(np.isfinite(r), 0.1 / r, 0.0).astype(np.float32)

    def obstacles(gap):
        return ob.analyse(r, CAM, LEVEL, inv_range_std_per_m=std, cfg=replace(CFG, layer_gap_rel=gap)).obstacles
    for gap in (CFG.layer_gap_rel, 0.2):
        obs = obstacles(gap)
        assert len(obs) == 1 and obs[0].bbox_px[0] == 96 and obs[0].bbox_px[2] == 159
    near, far = obstacles(0.1)
    assert near.bbox_px[0] == 96 and far.bbox_px[2] == 159 and near.bbox_px[2] + 1 == far.bbox_px[0]


def test_layer_split_loses_no_pixel():
    # a 4 px mast at 30 m before a wall at 70 m, with a patch of 4 x 4 px at 32 m on the wall away from the mast
    # (4 analysis cells, fewer than min_obstacle_pixels), every pixel's relative sigma 0.3 so the neighbour cut joins
    # them all: alone the patch would be dropped as speckle; it goes with the wall's layer, so the split lists every
    # pixel the unsplit component held
    r = add_wall(ground_and_sky(), 70.0, 96, 160)
    rows = np.flatnonzero(r[:, 100] == 70.0)
    r = add_wall(r, 30.0, 126, 130)
    r[rows[4]:rows[4] + 4, 150:154] = 32.0
    std = np.where(np.isfinite(r), 0.3 / r, 0.0).astype(np.float32)      # 3 hypot(0.3, 0.3) = 1.27 > ln(70 / 30)

    def obstacles(gap):
        return ob.analyse(r, CAM, LEVEL, inv_range_std_per_m=std, cfg=replace(CFG, layer_gap_rel=gap)).obstacles
    whole, split = obstacles(0.0), obstacles(CFG.layer_gap_rel)
    assert len(whole) == 1
    mast, left, right = sorted(split, key=lambda o: o.bbox_px[0] != 126 and o.bbox_px[0])  # the mast parts the wall
    assert mast.bbox_px[0] == 126 and mast.bbox_px[2] == 129 and abs(mast.position_ned_m[0] - 30.0) < 0.5
    assert left.bbox_px[0] == 96 and right.bbox_px[2] == 159 and abs(left.position_ned_m[0] - 70.0) < 0.5
    assert right.pixel_count == left.pixel_count                      # the patch's 16 px listed with the wall
    assert sum(o.pixel_count for o in split) == whole[0].pixel_count


def test_ground_estimated_from_points_when_not_configured():
    r = add_wall(ground_and_sky(alt_m=25.0), 30.0, 128, 192, alt_m=25.0)
    st = VehicleState.from_ypr([0.0, 0.0, -25.0], [0.0, 0.0, 0.0])
    # local origin 5 m above the ground (a take-off from a roof): the estimate finds the real ground at down = +5
    st5 = VehicleState.from_ypr([0.0, 0.0, -20.0], [0.0, 0.0, 0.0])
    res = ob.analyse(r, CAM, st5, cfg=ob.ObstacleConfig())
    assert res.ground_down_m == pytest.approx(5.0, abs=0.05)
    assert len(res.obstacles) == 1
    res0 = ob.analyse(r, CAM, st, cfg=ob.ObstacleConfig())
    assert res0.ground_down_m == pytest.approx(0.0, abs=0.05)


def sloped_ground(slope_deg=0.0, near_bias=0.0, cam=CAM, alt_m=ALT_M):
    """Range map of a ground plane down = -tan(slope) north (rising ahead), 0 under the vehicle, seen by a level
    camera looking north at height alt_m: the ray of row v descends by b = (v - cy)/fy per metre of x_c, the plane
    rises by s = tan(slope) per metre north, so x_c = alt / (b + s) where b + s > 0, +inf above that horizon.
    ``near_bias``: ranged too near towards the horizon like the dense and fused maps, x_c times
    1 - near_bias exp(-(b + s) fy / 40) (the full bias at the horizon, 1/e of it 40 rows below)."""
    s = math.tan(math.radians(slope_deg))
    v = np.arange(cam.height, dtype=np.float64)[:, None] * np.ones((1, cam.width))
    d = (v - cam.cy) / cam.fy + s
    with np.errstate(divide="ignore"):
        r = np.where(d > 0, alt_m / d, np.inf)
    r = np.where(d > 0, r * (1.0 - near_bias * np.exp(-d * cam.fy / 40.0)), r)
    return r.astype(np.float32)


def add_post(r, x_c_m, u0, u1, top_m, slope_deg=0.0, cam=CAM, alt_m=ALT_M):
    """A vertical face at x_c = x_c_m over columns u0..u1-1, standing on the ground of ``sloped_ground`` (its foot at
    down -tan(slope) x_c_m) up to top_m above its foot."""
    foot = -math.tan(math.radians(slope_deg)) * x_c_m
    v = np.arange(cam.height)
    z_ned = -alt_m + x_c_m * (v - cam.cy) / cam.fy
    rows = (z_ned <= foot) & (z_ned >= foot - top_m)
    r = r.copy()
    r[np.ix_(rows, np.arange(u0, u1))] = x_c_m
    return r


def overconfident_std(r, rel=0.02):
    """inv_range_std_per_m claiming a 2 % range sigma everywhere (sigma_rho = rel / r): too small for the bias."""
    with np.errstate(divide="ignore"):
        return np.where(np.isfinite(r), rel / r, 0.0).astype(np.float32)


@pytest.mark.parametrize("slope_deg", [0.0, 5.0])
def test_ground_ranged_too_near_towards_the_horizon_is_not_an_obstacle(slope_deg):
    # up to 50 % too near at the horizon with a 2 % sigma: far ground lifted by metres, tens of sigma of its down;
    # its range still grows up its rows as the plane's does (the plane law), so it is ground, with the plane
    # estimated from the map (no ground_down_m) or given
    r = sloped_ground(slope_deg, near_bias=0.5)
    std = overconfident_std(r)
    res = ob.analyse(r, CAM, LEVEL, inv_range_std_per_m=std, cfg=ob.ObstacleConfig())
    assert res.obstacles == []
    assert clear_in_view(res.sectors)
    true_plane = ob.GroundPlane(0.0, -math.tan(math.radians(slope_deg)), 0.0)
    assert ob.analyse(r, CAM, LEVEL, inv_range_std_per_m=std, cfg=ob.ObstacleConfig(), ground=true_plane).obstacles == []
    # the sigma-based clearance alone (plane-law test and window term off) lists the lifted ground; the window term
    # alone does not suffice either: the plane law is what removes it
    old = ob.ObstacleConfig(plane_law_beta=1e9, ground_window_px=0.0)
    assert len(ob.analyse(r, CAM, LEVEL, inv_range_std_per_m=std, cfg=old, ground=true_plane).obstacles) >= 1
    window_only = ob.ObstacleConfig(plane_law_beta=1e9)
    assert len(ob.analyse(r, CAM, LEVEL, inv_range_std_per_m=std, cfg=window_only, ground=true_plane).obstacles) >= 1


def test_sloped_ground_needs_the_fitted_plane():
    # unbiased ground rising 5 degrees ahead: 2.6 m above the level at 30 m. A level ground (configured at 0 m, as
    # the old single-height model) makes the far slope an obstacle; the fitted plane does not
    r = sloped_ground(5.0)
    res = ob.analyse(r, CAM, LEVEL, cfg=ob.ObstacleConfig())
    assert res.obstacles == []
    assert res.ground.b == pytest.approx(-math.tan(math.radians(5.0)), abs=1e-3) and abs(res.ground.c) < 1e-3
    assert res.ground_down_m == pytest.approx(0.0, abs=0.05)
    assert ob.analyse(r, CAM, LEVEL, cfg=ob.ObstacleConfig(ground_down_m=0.0, plane_law_beta=1e9)).obstacles


def platform(h_m=1.0, x0_m=15.0, x1_m=40.0, u0=0, u1=128, cam=CAM, alt_m=ALT_M):
    """``ground_and_sky`` with a flat platform h_m high over columns u0..u1-1 from x0_m to x1_m ahead: a ray of
    descent d = (v - cy) / fy meets its top at x_c = (alt - h) / d when that lies in [x0, x1], else its front face at
    x0 when it passes x0 below the top and above the ground (the ground at alt / d >= x0), else the ground."""
    r = ground_and_sky(cam, alt_m).astype(np.float64)
    v = np.arange(cam.height, dtype=np.float64)
    with np.errstate(divide="ignore"):
        x_ground = np.where(v > cam.cy, alt_m * cam.fy / (v - cam.cy), np.inf)
        x_top = np.where(v > cam.cy, (alt_m - h_m) * cam.fy / (v - cam.cy), np.inf)
    col = np.where((x_top >= x0_m) & (x_top <= x1_m), x_top,
                   np.where((x_top < x0_m) & (x_ground >= x0_m), x0_m, x_ground))
    r[:, u0:u1] = col[:, None]
    return r.astype(np.float32)


def test_ground_fit_keeps_out_a_wide_platform_above_the_ground():
    # level ground at down 0 and, over the left half of the view from 15 to 40 m, a platform 1 m high (a roof, a
    # hedge): the fit keeps the points at most 0.5 m above / 1.5 m below its plane in its last rounds (obstacles stand
    # above the ground), so it settles on the ground, not between it and the platform (a band taken the other
    # way round, 1.5 m above / 0.5 m below, puts it 0.23 m up)
    res = ob.analyse(platform(), CAM, LEVEL, cfg=ob.ObstacleConfig())
    assert res.ground_down_m == pytest.approx(0.0, abs=0.02)
    assert abs(res.ground.b) < 1e-3 and abs(res.ground.c) < 1e-3


def test_ground_plane_is_evaluated_at_the_points_own_north_and_east():
    # down = a + b north + c east: the plane 1 + 0.1 N - 0.2 E is at down 1 + 1 - 4 = -2 at (N, E) = (10, 20) and at
    # 1 + 2 - 2 = 1 at (20, 10). A lens at (10, 20, -12) stands 10 m above it; the ray (0, 1, 0.1) (east, descending
    # 0.1 per metre) comes down onto the plane rising 0.2 per metre east at 0.3 per metre: it meets it at x_c =
    # 10 / 0.3 = 33.3 m, at (10, 53.33, -8.667) where the plane's down is 1 + 1 - 10.667 = -8.667
    plane = ob.GroundPlane(1.0, 0.1, -0.2)
    assert plane.down_m([10.0, 20.0, -5.0]) == pytest.approx(-2.0)
    assert plane.down_m([20.0, 10.0, 0.0]) == pytest.approx(1.0)
    lens, ray = np.array([10.0, 20.0, -12.0]), np.array([0.0, 1.0, 0.1])
    h, descent = plane.height_and_descent(lens, ray)
    assert h == pytest.approx(10.0) and descent == pytest.approx(0.3)
    x_c = 1.0 / plane.inverse_range_per_m(lens, ray)
    assert x_c == pytest.approx(10.0 / 0.3)
    assert (lens + x_c * ray)[2] == pytest.approx(plane.down_m(lens + x_c * ray))
    # the ground rising 5 degrees north seen from 40 m north and 10 m east of the origin, 10 m above it: the ground
    # under the vehicle is at down -40 tan 5 deg = -3.50 m, given or fitted
    s = math.tan(math.radians(5.0))
    st = VehicleState.from_ypr([40.0, 10.0, -40.0 * s - ALT_M], [0.0, 0.0, 0.0])
    given = ob.analyse(sloped_ground(5.0), CAM, st, cfg=ob.ObstacleConfig(), ground=ob.GroundPlane(0.0, -s, 0.0))
    fitted = ob.analyse(sloped_ground(5.0), CAM, st, cfg=ob.ObstacleConfig())
    for res in (given, fitted):
        assert res.ground_down_m == pytest.approx(-40.0 * s, abs=0.02) and res.obstacles == []


@pytest.mark.parametrize("slope_deg", [0.0, 5.0])
@pytest.mark.parametrize("x_c_m, cols, top_m", [(20.0, (120, 160), 5.0), (30.0, (126, 130), 8.0)])  # box, pole
def test_box_and_pole_on_biased_ground_are_found(slope_deg, x_c_m, cols, top_m):
    # on the biased, overconfident ground above: a 5 m box face 40 columns wide at 20 m and an 8 m pole 4 columns
    # wide at 30 m are vertical structure (constant range up their rows) and stay obstacles, at their range; their
    # lower metres are within the ground's tolerance (clearance, window, the plane tilted by the bias)
    r = add_post(sloped_ground(slope_deg, near_bias=0.5), x_c_m, *cols, top_m, slope_deg=slope_deg)
    res = ob.analyse(r, CAM, LEVEL, inv_range_std_per_m=overconfident_std(r), cfg=ob.ObstacleConfig())
    assert len(res.obstacles) == 1
    o = res.obstacles[0]
    assert o.position_ned_m[0] == pytest.approx(x_c_m, abs=0.01)
    # its top row: the ray of row v meets the face at down -alt + x_c (v - cy) / fy = foot - top (2 x 2 pooling)
    v_top = CAM.cy + CAM.fy * (ALT_M - math.tan(math.radians(slope_deg)) * x_c_m - top_m) / x_c_m
    assert math.ceil(v_top) - 2 <= o.bbox_px[1] <= math.ceil(v_top) + 1
    assert cols[0] - 2 <= o.bbox_px[0] and o.bbox_px[2] <= cols[1] + 1


def test_height_above_plane_low_hand_derived():
    # lens 10 m above a level plane, a ray descending 0.05 m per metre of x_c, rho = 1/60: at the estimate 10 - 3 = 7 m;
    # with sigma_rho = rho / 4 and k = 3 the interval is rho x [0.25, 1.75], x_c 240 .. 34.3 m: least 10 - 12 = -2 m
    plane, lens = ob.GroundPlane(0.0), np.array([0.0, 0.0, -10.0])
    down, up = np.array([1.0, 0.0, 0.05]), np.array([1.0, 0.0, -0.05])
    rho = np.array([1 / 60.0])
    assert ob.height_above_plane_low(plane, lens, down, rho)[0] == pytest.approx(7.0)
    assert ob.height_above_plane_low(plane, lens, down, rho, rho / 4, 3.0)[0] == pytest.approx(-2.0)
    # sigma_rho = rho / 2: the interval holds infinity, where a descending ray is below the plane; a rising ray is
    # lowest at its near end, x_c = 60 / 2.5 = 24 m, 10 + 1.2 m
    assert ob.height_above_plane_low(plane, lens, down, rho, rho / 2, 3.0)[0] == -np.inf
    assert ob.height_above_plane_low(plane, lens, up, rho, rho / 2, 3.0)[0] == pytest.approx(11.2)
    # a plane falling 0.05 per metre north, parallel to the ray: 10 m above it wherever the point is, infinity too
    sloped = ob.GroundPlane(0.0, 0.05)
    assert ob.height_above_plane_low(sloped, lens, down, rho, rho / 2, 3.0)[0] == pytest.approx(10.0)


def ground_patch(r, rows_below_horizon, u0, u1, x_c_m, cam=CAM):
    """``r`` with the pixels of the given rows below the horizon (v - cy) and columns u0..u1-1 at x_c = x_c_m."""
    r = r.copy()
    v = np.round(cam.cy + np.asarray(rows_below_horizon, float)).astype(int)
    r[np.ix_(v, np.arange(u0, u1))] = x_c_m
    return r


def rel_std(r, rel):
    """inv_range_std_per_m of a relative sigma ``rel`` (sigma_rho = rel rho), 0 where r is not finite."""
    with np.errstate(divide="ignore"):
        return np.where(np.isfinite(r), rel / r, 0.0).astype(np.float32)


@pytest.mark.parametrize("fitted", [False, True])
def test_far_ground_ranged_too_near_within_its_sigma_is_not_an_obstacle(fitted):
    # the false track of the fused approach flight (seed 1): far ground (rows 6.5..10.5 below the horizon, truly
    # 197..122 m) smoothed to one range, 60 m, with a 25 % sigma (the truth within 2.5 sigma). At 60 m it stands
    # 5-7 m above the ground, above the first-order clearance (0.6 + 3 sigma_r x 0.05..0.08 + 2 x 60 / 128 = 3.8-5.2
    # m); its inverse range's 3-sigma interval reaches 1 / (0.25 rho) = 240 m, past the ground on every row: ground
    r = ground_patch(ground_and_sky(), np.arange(6.5, 11.0), 100, 140, 60.0)
    std = rel_std(r, 0.01)
    std[r == 60.0] = 0.25 / 60.0
    cfg = ob.ObstacleConfig() if fitted else CFG
    res = ob.analyse(r, CAM, LEVEL, inv_range_std_per_m=std, cfg=cfg)
    assert res.obstacles == []
    # without the sigma (k = 0) the patch is an obstacle at 60 m: the interval is what makes it ground
    flat = ob.analyse(r, CAM, LEVEL, inv_range_std_per_m=std, cfg=replace(cfg, ground_sigma_k=0.0)).obstacles
    assert len(flat) == 1 and flat[0].position_ned_m[0] == pytest.approx(60.0, abs=0.01)


@pytest.mark.parametrize("above_band_m, found", [(1.5, True), (-0.3, False)])
def test_low_box_just_above_the_grounds_sigma_band_is_found(above_band_m, found):
    # a box face at 40 m with a 5 % sigma: the far end of its 3-sigma interval is 40 / 0.85 = 47.06 m, the clearance
    # 0.6 + 2 x 40 / 128 = 1.225 m; its row of descent d is above the band iff 10 - 47.06 d > 1.225, where the face
    # stands 10 - 40 d > 10 - 0.85 x 8.775 = 2.541 m. A top 1.5 m above that is an obstacle at 40 m; 0.3 m below, ground
    band_m = ALT_M - 0.85 * (ALT_M - 0.6 - 2 * 40.0 / CAM.fy)
    assert band_m == pytest.approx(2.541, abs=1e-3)
    r = add_wall(ground_and_sky(), 40.0, 100, 140, top_down_m=-(band_m + above_band_m))
    # no least height: the band alone decides (a sliver above it would be an obstacle)
    res = ob.analyse(r, CAM, LEVEL, inv_range_std_per_m=rel_std(r, 0.05), cfg=replace(CFG, min_obstacle_height_m=0.0))
    if found:
        assert len(res.obstacles) == 1
        assert res.obstacles[0].position_ned_m[0] == pytest.approx(40.0, abs=0.01)
    else:
        assert res.obstacles == []


def test_plane_law_slope_hand_derived():
    # ground (rho = rho_g / 0.6, any constant bias): beta 1; a wall (constant rho): 0; above the horizon: NaN;
    # too narrow a span of ln(rho_g): NaN
    g = np.linspace(0.01, 0.05, 20)
    rho = np.concatenate([g / 0.6, np.full(20, 0.03), np.full(20, 0.03), np.full(20, 0.03)])
    rg = np.concatenate([g, g, np.where(np.arange(20) < 5, -0.01, g), np.full(20, 0.02) * (1 + 1e-3 * np.arange(20))])
    beta = ob.plane_law_slope(rho, rg, np.array([0, 20, 40, 60]), np.array([20, 20, 20, 20]), 0.1)
    assert beta[0] == pytest.approx(1.0) and beta[1] == pytest.approx(0.0, abs=1e-12)
    assert np.isnan(beta[2]) and np.isnan(beta[3])


def test_plane_law_is_not_decided_with_a_fifth_of_the_points_at_the_horizon():
    # ground ranged too near (rho = rho_g / 0.6: beta 1) with k of its n points looking above the plane's horizon
    # (rho_g <= 0): decided (beta 1) with fewer than a fifth of them there, not decided (NaN: the component is kept)
    # with a fifth or more (docs/methods.md, "Plane law"): exactly n / 5 of them is the boundary, for every n
    for n in (5, 10, 15, 20, 25, 40, 45, 50):
        for above, decided in ((n // 5 - 1, True), (n // 5, False)):
            g = np.linspace(0.01, 0.05, n)
            g[:above] = -0.01
            beta, = ob.plane_law_slope(g / 0.6, g, np.array([0]), np.array([n]), 0.1)
            assert (beta == pytest.approx(1.0)) if decided else np.isnan(beta), (n, above, beta)


def test_bad_inputs_name_the_problem():
    with pytest.raises(InputError, match="2-D"):
        ob.analyse(np.zeros((4, 4, 3)), CAM, LEVEL)
    with pytest.raises(InputError, match="camera 'nose' is 256x256"):
        ob.analyse(np.zeros((10, 12), np.float32), CAM, LEVEL)
    with pytest.raises(InputError, match="confidence has shape"):
        ob.analyse(ground_and_sky(), CAM, LEVEL, confidence=np.ones((3, 3)))
    with pytest.raises(InputError, match="max_distance_m"):
        ob.ObstacleConfig(max_distance_m=700.0)
    with pytest.raises(InputError, match="min_distance_m"):
        ob.ObstacleConfig(min_distance_m=10.0, max_distance_m=5.0)
    with pytest.raises(InputError, match="distances_cm"):
        ob.Sectors.from_msg({"distances_cm": [1, 2], "increment_deg": 1, "angle_offset_deg": 0,
                             "min_distance_cm": 1, "max_distance_cm": 2})


def test_sectors_message_round_trip():
    res = ob.analyse(add_wall(ground_and_sky(), 20.0, 128, 192), CAM, LEVEL, cfg=CFG)
    back = ob.Sectors.from_msg(res.sectors.to_msg())
    assert np.array_equal(back.distances_cm, res.sectors.distances_cm)
    assert back.increment_deg == 5.0 and back.angle_offset_deg == -20.0


def test_tracker_keeps_ids():
    tr = ob.ObstacleTracker()
    mk = lambda p, d: ob.Obstacle(0, d, d, d, 0, 0, 0, list(p), [0, 0, 0], 1, 1, 10, 1.0, [0, 0, 1, 1])
    a = tr.update([mk((20, 0, -5), 20.0), mk((40, 10, -5), 41.0)], 0)
    ids = {round(o.distance_m): o.id for o in a}
    b = tr.update([mk((39, 10, -5), 40.0), mk((19, 0, -5), 19.0), mk((80, -30, -2), 85.0)], 100_000)
    ids2 = {round(o.distance_m): o.id for o in b}
    assert ids2[19] == ids[20] and ids2[40] == ids[41] and ids2[85] not in ids.values()
    c = tr.update([mk((19, 0, -5), 19.0)], 5_000_000)       # tracks expired
    assert c[0].id not in ids.values()


# -- simulator scenes ---------------------------------------------------------------------------------
def box_distance(box, p_ned):
    """Euclidean distance from p to the solid box (clamp in the box's local frame)."""
    R = box.R_ned_local
    local = R.T @ (np.asarray(p_ned) - np.asarray(box.center_ned_m))
    d = local - np.clip(local, -box.half_m, box.half_m)
    return float(np.linalg.norm(d))


def near_boxes(scene, p_ned, max_m=100.0):
    """(box, its true distance) for the scene's boxes within max_m of p."""
    for box in scene.boxes:
        d = box_distance(box, p_ned)
        if d <= max_m:
            yield box, d


def closest(obstacles, distance_m):
    """The obstacle whose distance is nearest distance_m."""
    return min(obstacles, key=lambda o: abs(o.distance_m - distance_m))


@pytest.fixture(scope="module")
def fast_scene():
    from eonav.sim.presets import make_pair
    return make_pair("fast", size=256)


def test_sim_boxes_found_at_their_distance(fast_scene):
    sp = fast_scene
    v, gt = sp.views[0], sp.truth[0]
    res = ob.analyse(gt.range_m, v.camera, v.state, cfg=ob.ObstacleConfig(ground_down_m=0.0))
    pos = v.state.position_ned_m
    boxes = {b.name: b for b in sp.scene.boxes}
    near = res.obstacles[0]
    # the van is the nearest box; its robust minimum is within 3 % of the distance to the solid box
    assert box_distance(boxes["van"], pos) == pytest.approx(near.distance_m, rel=0.03)
    c = np.asarray(boxes["van"].center_ned_m) - pos
    assert near.bearing_deg == pytest.approx(math.degrees(math.atan2(c[1], c[0])), abs=2.0)
    for name in ("pole", "truck"):
        want = box_distance(boxes[name], pos)
        got = closest(res.obstacles, want)
        assert got.distance_m == pytest.approx(want, rel=0.03), name
    # sectors: the van's bearing bins report its horizontal distance
    s = res.sectors
    b = math.degrees(math.atan2(c[1], c[0]))
    j = bin_of(b)
    hv = box_distance(boxes["van"], [pos[0], pos[1], boxes["van"].center_ned_m[2]])   # horizontal, at its height
    assert s.distances_cm[j] / 100 == pytest.approx(hv, rel=0.05)


def test_sim_noisy_range_map_still_finds_van(fast_scene):
    sp = fast_scene
    v, gt = sp.views[0], sp.truth[0]
    rng = np.random.default_rng(3)
    noisy = gt.range_m * (1 + 0.03 * rng.standard_normal(gt.range_m.shape)).astype(np.float32)
    holes = rng.random(gt.range_m.shape) < 0.2
    noisy[holes] = np.nan
    res = ob.analyse(noisy, v.camera, v.state, cfg=ob.ObstacleConfig(ground_down_m=0.0, max_rel_jump=0.15))
    van = box_distance([b for b in sp.scene.boxes if b.name == "van"][0], v.state.position_ned_m)
    assert res.obstacles[0].distance_m == pytest.approx(van, rel=0.06)


def test_obstacles_module_imports_no_transport():
    import subprocess
    code = "import eonav.obstacles.detect, eonav.ranging.pair_policy, sys; print('zenoh' in sys.modules, 'pymavlink' in sys.modules)"
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True).stdout
    assert out.split() == ["False", "False"]


# -- MAVLink OBSTACLE_DISTANCE out (real bytes through pymavlink) --------------------------------------
def _wall_sectors():
    return ob.analyse(add_wall(ground_and_sky(), 20.0, 128, 192), CAM, LEVEL, cfg=CFG).sectors


def _free_udp_port():
    import socket
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


@contextlib.contextmanager
def udp_sender(**kw):
    """An ``ObstacleDistanceSender`` to a loopback UDP port with an injected clock (``t[0]``, seconds) and wall
    clock (42 us unless given), and the receiving end: yields (tx, t, received); ``received(type)`` returns the
    messages (of ``type``, or all) that arrived, up to the first 0.2 s without one. Both ends closed after."""
    from eonav.nav import mavlink_out as mo
    port = _free_udp_port()
    rx = mo.mavutil().mavlink_connection(f"udpin:127.0.0.1:{port}")
    t = [0.0]
    kw.setdefault("wall_us", lambda: 42)
    tx = mo.ObstacleDistanceSender(f"udpout:127.0.0.1:{port}", clock=lambda: t[0], **kw)

    def received(type=None):
        out = []
        while (m := rx.recv_match(type=type, blocking=True, timeout=0.2)) is not None:
            out.append(m)
        return out
    try:
        yield tx, t, received
    finally:
        tx.close()
        rx.close()


def test_obstacle_distance_bytes_decode_back():
    from eonav.nav import mavlink_out as mo
    mu = mo.mavutil()
    s = _wall_sectors()
    buf = mo.encode_obstacle_distance(s, 1_700_000_000_123_456, system_id=7)
    assert buf[0] == 0xFD                                    # MAVLink 2 frame (extensions survive)
    msgs = mu.mavlink.MAVLink(None).parse_buffer(buf)
    assert len(msgs) == 1
    m = msgs[0]
    assert m.get_type() == "OBSTACLE_DISTANCE" and m.get_msgId() == 330
    assert m.get_srcSystem() == 7 and m.get_srcComponent() == 191
    assert m.frame == mu.mavlink.MAV_FRAME_BODY_FRD == 12
    assert m.increment == 0 and m.increment_f == 5.0 and m.angle_offset == -20.0
    assert list(m.distances) == [int(x) for x in s.distances_cm]
    assert m.min_distance == 50 and m.max_distance == 15000 and m.time_usec == 1_700_000_000_123_456
    assert 15001 in m.distances and 2000 <= min(m.distances) <= 2300


def test_obstacle_distance_rejects_bad_sectors():
    from eonav.nav import mavlink_out as mo
    s = _wall_sectors()
    bad = ob.Sectors(s.distances_cm[:10], s.increment_deg, s.angle_offset_deg, 50, 15000)
    with pytest.raises(InputError, match="72 distances"):
        mo.encode_obstacle_distance(bad, 0)
    with pytest.raises(InputError, match="min_distance_cm"):
        mo.encode_obstacle_distance(ob.Sectors(s.distances_cm, 5.0, 0.0, 500, 100), 0)
    with pytest.raises(InputError, match="min_distance_cm"):
        mo.encode_obstacle_distance(ob.Sectors(s.distances_cm, 5.0, 0.0, 0, 100), 0)   # ArduPilot ignores 0 cm
    mo.encode_obstacle_distance(ob.Sectors(s.distances_cm, 5.0, 0.0, 1, 100), 0)
    # layouts PX4 misreads: a finer increment (it reads past its 72-element map) or bins off its 5-degree grid
    for inc, off in ((1.25, -45.0), (4.99, 0.0), (5.01, 0.0), (5.0, 2.5), (5.0, float("nan")), (5.0, 185.0)):
        with pytest.raises(InputError, match="increment"):
            mo.encode_obstacle_distance(ob.Sectors(s.distances_cm, inc, off, 50, 15000), 0)
    mo.encode_obstacle_distance(ob.Sectors(s.distances_cm, 5.0, -45.0, 50, 15000), 0)
    with pytest.raises(InputError, match="min_distance_m"):
        ob.ObstacleConfig(min_distance_m=0.004)


def test_obstacle_distance_max_distance_leaves_clear_below_unknown():
    """max_distance_cm 65533 is the largest sent: its "clear" value, max + 1 = 65534, is still not UINT16_MAX (65535,
    "unknown"); with 65534 a clear bin would read as unknown, so it is refused. Catches the bound taken as
    max_distance_cm < UINT16_MAX."""
    from eonav.nav import mavlink_out as mo
    mu = mo.mavutil()
    clear = ob.Sectors(np.full(72, 65534, np.uint16), 5.0, 0.0, 50, 65533)
    m, = mu.mavlink.MAVLink(None).parse_buffer(mo.encode_obstacle_distance(clear, 0))
    assert m.max_distance == 65533 and set(m.distances) == {65534}
    with pytest.raises(InputError, match="min_distance_cm"):
        mo.encode_obstacle_distance(ob.Sectors(np.full(72, ob.UINT16_MAX, np.uint16), 5.0, 0.0, 50, 65534), 0)


def test_sender_fresh_then_unknown_over_udp():
    from eonav.nav import mavlink_out as mo
    mu = mo.mavutil()
    with udp_sender(system_id=1, rate_hz=10.0) as (tx, t, drain):
        tx.tick()                                            # t = 0: heartbeat, no data yet -> no OBSTACLE_DISTANCE
        got = drain()
        assert [m.get_type() for m in got] == ["HEARTBEAT"]
        hb = got[0]
        assert hb.get_srcComponent() == 191 and hb.type == mu.mavlink.MAV_TYPE_ONBOARD_CONTROLLER
        assert hb.autopilot == mu.mavlink.MAV_AUTOPILOT_INVALID
        s = _wall_sectors()
        tx.update(s, 1_700_000_000_000_000)
        t[0] = 0.1
        tx.tick()
        t[0] = 0.2
        tx.tick()
        got = [m for m in drain() if m.get_type() == "OBSTACLE_DISTANCE"]
        assert len(got) == 2 and all(list(m.distances) == list(s.distances_cm) for m in got)
        assert got[0].time_usec == 1_700_000_000_000_000
        t[0] = 0.75                                          # 0.65 s after the update: stale
        assert not tx.is_fresh()
        tx.tick()
        got = [m for m in drain() if m.get_type() == "OBSTACLE_DISTANCE"]
        # stale: one all-unknown message clears the autopilot's sectors ...
        assert len(got) == 1 and set(got[0].distances) == {65535} and got[0].time_usec == 42
        assert got[0].increment_f == 5.0 and got[0].angle_offset == -20.0
        for now in (0.85, 0.95, 1.05):                       # ... then silence, so it reports No Data; heartbeat at 1 s
            t[0] = now
            tx.tick()
        assert [m.get_type() for m in drain()] == ["HEARTBEAT"]
        assert tx.counters == {"od_sent_fresh": 2, "od_sent_flush": 1, "heartbeats_sent": 2, "send_errors": 0,
                               "encode_errors": 0}
        tx.update(s, 1_700_000_001_000_000)                  # maps flow again: sent on the next 10 Hz tick
        t[0] = 1.16
        tx.tick()
        got = [m for m in drain() if m.get_type() == "OBSTACLE_DISTANCE"]
        assert len(got) == 1 and got[0].time_usec == 1_700_000_001_000_000


def test_sender_skips_a_message_it_cannot_pack_and_keeps_sending(monkeypatch):
    """A message pymavlink cannot pack (a value outside its field: struct.error, or the encoder's own InputError)
    is counted (``encode_errors``) and skipped; it does not end the sender's loop nor mark the link lost: the next
    tick's OBSTACLE_DISTANCE and the heartbeats go out."""
    from eonav.nav import mavlink_out as mo
    real, fail = mo.obstacle_distance_message, [struct.error("ushort format requires 0 <= number <= 65535"),
                                                InputError("min_distance_cm out of range")]

    def sometimes_bad(*a, **kw):
        if fail:
            raise fail.pop(0)
        return real(*a, **kw)
    monkeypatch.setattr(mo, "obstacle_distance_message", sometimes_bad)
    with udp_sender(system_id=1, rate_hz=10.0) as (tx, t, received):
        s = _wall_sectors()
        tx.update(s, 1_700_000_000_000_000)
        for now in (0.0, 0.1, 0.2):
            t[0] = now
            tx.tick()
        got = received()
        assert [m.get_type() for m in got] == ["HEARTBEAT", "OBSTACLE_DISTANCE"]
        assert list(got[1].distances) == list(s.distances_cm)
        assert tx.counters["encode_errors"] == 2 and tx.counters["od_sent_fresh"] == 1
        assert tx.counters["send_errors"] == 0

def test_sender_merges_every_fresh_camera_and_stamps_the_oldest_capture():
    """Two cameras through one sender: each message is the per-bin merge of the fresh cameras (nearest obstacle,
    else clear, else unknown; hand-written below), stamped with the OLDER of their captures (the picture is no
    newer than its oldest part); a camera gone stale leaves the merge while the other keeps it fresh."""
    U, C = ob.UINT16_MAX, 4001                                   # unknown; clear (max_distance + 1)
    nose, left = np.full(72, U, np.uint16), np.full(72, U, np.uint16)
    nose[[3, 4, 5]] = [C, 1234, C]                               # nose: an obstacle at 12.34 m in bin 4
    left[[4, 5, 60]] = [2000, 800, C]                            # left: farther in bin 4, the only one in bin 5
    lay = (5.0, -20.0, 50, 4000)
    with udp_sender(rate_hz=10.0) as (tx, t, received):
        tx.update(ob.Sectors(nose, *lay), 1_700_000_000_000_000, "nose")       # captured 50 ms before left's
        t[0] = 0.2
        tx.update(ob.Sectors(left, *lay), 1_700_000_000_050_000, "left")
        t[0] = 0.25
        tx.tick()
        want = np.full(72, U)
        want[[3, 4, 5, 60]] = [C, 1234, 800, C]
        m, = received("OBSTACLE_DISTANCE")
        assert list(m.distances) == list(want) and m.time_usec == 1_700_000_000_000_000
        t[0] = 0.45                                              # nose 0.45 s old (stale), left 0.25 s (fresh)
        tx.tick()
        m, = received("OBSTACLE_DISTANCE")
        assert list(m.distances) == [int(x) for x in left] and m.time_usec == 1_700_000_000_050_000
        assert tx.counters["od_sent_flush"] == 0


def test_sender_cadence_after_a_late_call_and_the_stale_limit():
    """Injected clock, 4 Hz (exact binary times). A caller late by a whole period (due at 0.25 s, called at 0.5 s)
    gets one message and the next a period later (0.75 s), not a second one at once (catches '>=' for '>' in
    _next_due: a late call landing on the grid re-armed the send for now, a burst). With stale_s 0.25 a camera is
    fresh at exactly 0.25 s after its update and stale just after (catches '<' for '<=' in _fresh)."""
    with udp_sender(rate_hz=4.0, stale_s=0.25) as (tx, t, received):
        s = _wall_sectors()
        tx.update(s, 1_700_000_000_000_000)
        assert tx.tick() == 0.25 and len(received("OBSTACLE_DISTANCE")) == 1                  # t = 0: sent, next at 0.25
        t[0] = 0.375
        tx.update(s, 1_700_000_000_375_000)
        t[0] = 0.5                                                     # the 0.25 s send was missed
        assert tx.tick() == 0.25                                       # next at 0.75, not now
        assert tx.tick() == 0.25                                       # called again at once: nothing more
        got = received("OBSTACLE_DISTANCE")
        assert len(got) == 1 and got[0].time_usec == 1_700_000_000_375_000
        tx.update(s, 1_700_000_000_500_000)                            # at 0.5 s: fresh up to 0.75 s inclusive
        t[0] = 0.75
        assert tx.is_fresh()
        tx.tick()
        got = received("OBSTACLE_DISTANCE")
        assert len(got) == 1 and got[0].time_usec == 1_700_000_000_500_000
        t[0] = 0.75000001
        assert not tx.is_fresh()
        t[0] = 1.0                                                     # the next send: the flush
        tx.tick()
        got = received("OBSTACLE_DISTANCE")
        assert len(got) == 1 and set(got[0].distances) == {65535}
        assert tx.counters["od_sent_fresh"] == 3 and tx.counters["od_sent_flush"] == 1


def test_sender_real_time_rate():
    import threading
    import time
    from eonav.nav import mavlink_out as mo
    mu = mo.mavutil()
    port = _free_udp_port()
    rx = mu.mavlink_connection(f"udpin:127.0.0.1:{port}")
    tx = mo.ObstacleDistanceSender(f"udpout:127.0.0.1:{port}", rate_hz=15.0)
    stop = threading.Event()
    th = threading.Thread(target=tx.run, args=(stop,))
    try:
        tx.update(_wall_sectors(), 1)
        th.start()
        t0, n_od, n_hb = time.monotonic(), 0, 0
        while time.monotonic() - t0 < 1.0:
            m = rx.recv_match(blocking=True, timeout=0.1)
            if m is not None:
                n_od += m.get_type() == "OBSTACLE_DISTANCE"
                n_hb += m.get_type() == "HEARTBEAT"
        # 15 Hz for 1 s; the first 0.3 s fresh, then one flush and silence
        assert 4 <= n_od <= 7 and 1 <= n_hb <= 2
        assert tx.counters["od_sent_flush"] == 1 and 3 <= tx.counters["od_sent_fresh"] <= 6
    finally:
        stop.set()
        th.join(2.0)
        tx.close()
        rx.close()


def test_sender_rejects_bad_setup():
    from eonav.nav import mavlink_out as mo
    with pytest.raises(InputError, match="2 Hz"):
        mo.ObstacleDistanceSender("udpout:127.0.0.1:9", rate_hz=1.0)
    with pytest.raises(InputError, match="MAVLink output 'tcp:127.0.0.1': not a MAVLink connection string"):
        mo.ObstacleDistanceSender("tcp:127.0.0.1")
    tx = mo.ObstacleDistanceSender("tcp:127.0.0.1:1")         # refused: not an error, retried (tests/test_links.py)
    assert tx.tick() > 0 and tx.link_status()[0] == "down"
    tx.close()


def test_sectors_now_move_with_the_vehicle():
    r = add_wall(ground_and_sky(), 20.0, 128, 192)
    later = VehicleState.from_ypr([2.0, 0.0, -ALT_M], [0.0, 0.0, 0.0])      # 2 m further north
    res = ob.analyse(r, CAM, LEVEL, cfg=CFG, now_state=later)
    j = bin_of(5.0)                                                         # bearings 2.5 .. 7.5 deg
    # robust minimum of the wall's points in the bin: 20 / cos b (18 / cos b' from 2 m nearer), b in 2.5 .. 7.5 deg
    assert 2002 <= int(res.sectors.distances_cm[j]) <= 2017
    assert 1802 <= int(res.sectors_now.distances_cm[j]) <= 1816
    assert res.obstacles[0].horizontal_distance_m == pytest.approx(20.0, rel=0.02)   # list stays at capture pose


def test_sectors_are_body_relative_whatever_the_heading():
    # the wall 20 m ahead of the camera seen from a vehicle heading 30 deg (north-east): the camera turns with the
    # body, so the map is the same as at heading 0 and so are the body-relative sectors (hand-checked in
    # test_wall_distance_per_sector_hand_derived) and the obstacle's bearing; the wall's points lie on the plane
    # 20 m ahead along the heading. 2 m further along the heading the bin at 5 deg holds 18 / cos b
    yaw = math.radians(30.0)
    heading = VehicleState.from_ypr([0.0, 0.0, -ALT_M], [yaw, 0.0, 0.0])
    later = VehicleState.from_ypr([2.0 * math.cos(yaw), 2.0 * math.sin(yaw), -ALT_M], [yaw, 0.0, 0.0])
    r = add_wall(ground_and_sky(), 20.0, 128, 192)
    north = ob.analyse(r, CAM, LEVEL, cfg=CFG)
    res = ob.analyse(r, CAM, heading, cfg=CFG, now_state=later)
    a, b = north.sectors.distances_cm.astype(int), res.sectors.distances_cm.astype(int)
    assert np.array_equal(a >= 15001, b >= 15001) and np.abs(a - b).max() <= 1
    assert 1802 <= int(res.sectors_now.distances_cm[bin_of(5.0)]) <= 1816
    o, = res.obstacles
    assert o.bearing_deg == pytest.approx(north.obstacles[0].bearing_deg, abs=1e-6)
    n, e, _ = o.position_ned_m
    assert n * math.cos(yaw) + e * math.sin(yaw) == pytest.approx(20.0, abs=1e-3)


@pytest.mark.parametrize("max_width_px", [0, 128, 64])
def test_pooled_analysis_keeps_nearest_distances(fast_scene, max_width_px):
    """Pooling to k x k blocks (robust minimum per block) keeps every box at its true distance and the sectors at
    the full-resolution values within a few per cent; 0 = full resolution, 64 = 4 x 4 blocks of the 256 px map."""
    sp = fast_scene
    v, gt = sp.views[0], sp.truth[0]
    full = ob.analyse(gt.range_m, v.camera, v.state, cfg=ob.ObstacleConfig(ground_down_m=0.0, max_width_px=0))
    res = ob.analyse(gt.range_m, v.camera, v.state,
                     cfg=ob.ObstacleConfig(ground_down_m=0.0, max_width_px=max_width_px))
    for b, want in near_boxes(sp.scene, v.state.position_ned_m):
        got = closest(res.obstacles, want)
        assert got.distance_m == pytest.approx(want, rel=0.03), b.name
        assert got.distance_m <= want * 1.01                  # a robust minimum never pushes an obstacle away
    f, p = full.sectors.distances_cm.astype(float), res.sectors.distances_cm.astype(float)
    both = (f < 15001) & (p < 15001)                           # bins with a distance in both (not clear, not unknown)
    assert both.sum() >= 4                                     # the boxes span >= 4 of the 5-degree bins
    np.testing.assert_allclose(p[both], f[both], rtol=0.05)
    assert ((f < 15001) == (p < 15001)).mean() >= 0.9          # same bins report an obstacle
    total = sum(o.pixel_count for o in full.obstacles[:3])
    assert sum(o.pixel_count for o in res.obstacles[:3]) == pytest.approx(total, rel=0.25)   # full-res pixel units


@pytest.fixture(scope="module")
def fast_scene_512():
    from eonav.sim.presets import make_pair
    return make_pair("fast", size=512)


def test_map_on_the_locate_grid_gives_the_obstacles_of_the_upsampled_map(fast_scene_512):
    """A map at scale 0.5 analysed on its own grid (scaled camera, frame size given) against the same map upsampled to
    the frame's grid as the locator did before: the same boxes at the same distance, pixel counts and boxes in frame
    pixels, the same sectors. (The scaled pixels sit between two frame pixels, so distances agree to a fraction of a
    per cent, not bit for bit.)"""
    from eonav.geometry.camera import on_grid, scaled_camera
    from eonav.services.locator import to_full_grid
    sp = fast_scene_512
    v, gt = sp.views[0], sp.truth[0]
    sc = scaled_camera(v.camera, 0.5)
    small = on_grid(gt.range_m, sc.width, sc.height).astype(np.float32)
    up = to_full_grid(small, v.camera)
    cfg = ob.ObstacleConfig(ground_down_m=0.0)
    a = ob.analyse(up, v.camera, v.state, cfg=cfg)
    b = ob.analyse(small, sc, v.state, cfg=cfg, frame_size=(v.camera.width, v.camera.height))
    assert b.n_confident == a.n_confident                          # frame pixels
    assert b.n_obstacle_px == pytest.approx(a.n_obstacle_px, rel=0.05)
    for box, want in near_boxes(sp.scene, v.state.position_ned_m):
        oa, ob_ = closest(a.obstacles, want), closest(b.obstacles, want)
        assert ob_.distance_m == pytest.approx(oa.distance_m, rel=0.005), box.name
        assert ob_.bearing_deg == pytest.approx(oa.bearing_deg, abs=0.2), box.name
        assert ob_.pixel_count == pytest.approx(oa.pixel_count, rel=0.1), box.name
        assert np.abs(np.subtract(ob_.bbox_px, oa.bbox_px)).max() <= 4, (box.name, ob_.bbox_px, oa.bbox_px)
    fa, fb = a.sectors.distances_cm.astype(float), b.sectors.distances_cm.astype(float)
    assert ((fa < 15001) == (fb < 15001)).all() and ((fa == 15001) == (fb == 15001)).all()   # same bins set, clear
    both = fa < 15001
    np.testing.assert_allclose(fb[both], fa[both], rtol=0.02)
    assert (b.sectors.increment_deg, b.sectors.angle_offset_deg) == pytest.approx(
        (a.sectors.increment_deg, a.sectors.angle_offset_deg))


def test_frame_size_is_checked_against_the_map():
    r = ground_and_sky()
    for bad in ((128, 256), (256, 10), ("x", 3), (1,)):
        with pytest.raises(InputError, match="frame size"):
            ob.analyse(r, CAM, LEVEL, cfg=CFG, frame_size=bad)
    same = ob.analyse(r, CAM, LEVEL, cfg=CFG)
    for fs in (None, (0, 0), (256, 256)):
        assert ob.analyse(r, CAM, LEVEL, cfg=CFG, frame_size=fs).n_confident == same.n_confident


def test_frame_bbox_covers_the_map_pixels():
    assert ob._frame_bbox(0, 0, 127, 127, 128, 128, 256, 256) == [0, 0, 255, 255]
    assert ob._frame_bbox(3, 5, 3, 6, 128, 128, 256, 256) == [6, 10, 7, 13]
    assert ob._frame_bbox(3, 5, 3, 6, 8, 8, 8, 8) == [3, 5, 3, 6]
    assert ob._frame_bbox(0, 0, 4, 2, 5, 3, 11, 7) == [0, 0, 10, 6]          # odd sizes: the last pixels reach the edge


def test_warm_up_map_goes_through_the_analysis():
    """The obstacle service's warm-up map: the wall 30 m ahead is found, sky and ground make the other sectors clear."""
    from types import SimpleNamespace

    from eonav.services.obstacles import warm_up
    counted, lat = {}, {}
    node = SimpleNamespace(count=lambda k, n=1: counted.__setitem__(k, counted.get(k, 0) + n),
                           latency=lambda k, s: lat.__setitem__(k, s), log=SimpleNamespace(info=lambda *a: None))
    res = warm_up(node, ob.ObstacleConfig(ground_down_m=0.0), ob)
    assert counted == {} and "warmup" in lat
    assert len(res.obstacles) == 1 and res.obstacles[0].distance_m == pytest.approx(30.0, rel=0.01)
    d = res.sectors.distances_cm
    # the warm-up camera sees -32 .. 32 deg; the wall covers -11.6 .. 11.6 deg at x_c = 30 m
    assert all(d[bin_of(c)] == 15001 for c in (-25, -20, -15, 15, 20, 25))
    assert 3000 <= d[bin_of(0)] <= 3010 and all(3000 <= d[bin_of(c)] <= 3070 for c in (-10, -5, 5, 10))
    assert d[bin_of(30)] == d[bin_of(-30)] == d[bin_of(90)] == ob.UINT16_MAX
    assert res.sectors_now is not None
    broken = SimpleNamespace(analyse=lambda *a, **k: 1 / 0)
    node.log.warning = lambda *a: None
    assert warm_up(node, ob.ObstacleConfig(), broken) is None and counted == {"warmup_errors": 1}


def _pool_reference(r, conf, k, q):
    """pool_confident by its definition, block by block: the floor(q/100 (n-1))-th confident pixel by range, ties to the
    first in row-major order (a stable sort)."""
    H, W = conf.shape
    idx, weight = [], []
    for by in range(0, H, k):
        for bx in range(0, W, k):
            pix = [(r[y, x], y * W + x) for y in range(by, min(by + k, H)) for x in range(bx, min(bx + k, W))
                   if conf[y, x]]
            if pix:
                pix.sort(key=lambda t: t[0])                        # stable
                idx.append(pix[int(math.floor(q / 100.0 * (len(pix) - 1)))][1])
                weight.append(len(pix))
    return np.array(idx), np.array(weight, float)


@pytest.mark.parametrize("k,q", [(2, 10.0), (3, 10.0), (2, 0.0), (3, 50.0), (4, 10.0)])
def test_pool_confident_matches_its_definition(k, q):
    """The element-wise path (every rank 0: k <= 3 at 10 %) and the argsort path pick the pixel the definition picks,
    on odd sizes, with holes; with ties (quantised ranges) the element-wise path takes the first pixel of the block
    (the argsort path's tie order is numpy's, so it is checked on distinct ranges only)."""
    rng = np.random.default_rng(k)
    H, W = 23, 31
    fast = math.floor(q / 100.0 * (k * k - 1)) == 0
    r = (np.round(rng.random((H, W)) * 4) + 1 if fast else rng.random((H, W)) * 100 + 1).astype(np.float32)
    conf = rng.random((H, W)) > 0.3
    idx, weight, cell, grid = ob.pool_confident(r, conf, k, q)
    want_idx, want_w = _pool_reference(r, conf, k, q)
    assert grid == (-(-H // k), -(-W // k)) and cell.size == want_idx.size
    np.testing.assert_array_equal(idx, want_idx)
    np.testing.assert_array_equal(weight, want_w)


def test_latest_nav_joins_attitude_and_position_messages():
    """The MAVLink ingest sends attitude and position as separate nav_state messages: the obstacle service joins the
    newest of each into one pose (stamped with the newer part) when they are within 200 ms of each other."""
    from eonav.services.obstacles import LatestNav
    nav = LatestNav()
    nan3, nan4 = [math.nan] * 3, [math.nan] * 4
    q_yaw90 = [math.cos(math.pi / 4), 0.0, 0.0, math.sin(math.pi / 4)]
    assert not nav.add(1_000_000, q_yaw90, nan3, nan3)                 # attitude alone: no pose
    assert nav.get() == (None, None)
    assert nav.add(1_150_000, nan4, [10.0, 20.0, -5.0], [3.0, 0.0, 0.0])  # position 150 ms later: joined
    state, stamp = nav.get()
    assert stamp == 1_150_000 and state.position_ned_m == pytest.approx([10.0, 20.0, -5.0])
    assert state.T_body_ned @ np.array([0.0, 1.0, 0.0]) == pytest.approx([1.0, 0.0, 0.0], abs=1e-9)   # east = nose
    assert nav.ownship(None, -1).velocity_ned_mps == pytest.approx([3.0, 0.0, 0.0])
    assert not nav.add(1_360_000, nan4, [11.0, 20.0, -5.0], nan3)      # 360 ms after the attitude: too far apart
    assert nav.get()[1] == 1_150_000
    assert nav.add(1_400_000, [1.0, 0.0, 0.0, 0.0], nan3, nan3)        # a new attitude 40 ms after it: joined again
    state, stamp = nav.get()
    assert stamp == 1_400_000 and state.position_ned_m[0] == pytest.approx(11.0)
    nav.add(1_500_000, [2.0, 0.0, 0.0, 0.0], nan3, nan3)                # not a unit quaternion: ignored
    assert nav.get()[1] == 1_400_000 and nav._q[0] == 1_400_000


def test_latest_nav_joins_parts_up_to_200_ms_apart_and_not_beyond():
    """The join limit of attitude and position holds at 200 ms exactly (MAX_PART_SKEW_US, inclusive) and not a
    microsecond beyond, either part being the newer one."""
    from eonav.services.obstacles import LatestNav
    nan3, nan4 = [math.nan] * 3, [math.nan] * 4
    for first_is_attitude in (True, False):
        for skew_us, joined in ((200_000, True), (200_001, False)):
            nav = LatestNav()
            parts = [(nan3, [1.0, 0.0, 0.0, 0.0]), ([5.0, 6.0, -7.0], nan4)]
            if not first_is_attitude:
                parts.reverse()
            (p0, q0), (p1, q1) = parts
            assert not nav.add(1_000_000, q0, p0, nan3)
            assert nav.add(1_000_000 + skew_us, q1, p1, nan3) is joined, (first_is_attitude, skew_us)
            assert nav.get()[1] == (1_000_000 + skew_us if joined else None)


def test_latest_nav_keeps_the_newest_parts_when_older_ones_arrive_late():
    """Nav parts can arrive out of order (two links, a replay's seam): an attitude or a position older than the one
    held does not replace it. After a pose heading east at (10, 20, -5), stamped 1.0 s, a late attitude heading north
    (0.9 s) and a late position (0.95 s) leave the pose as it was; a stale part would otherwise be joined into a pose
    that carries the newer stamp."""
    from eonav.services.obstacles import LatestNav
    nan3, nan4 = [math.nan] * 3, [math.nan] * 4
    nav = LatestNav()
    q_east = [math.cos(math.pi / 4), 0.0, 0.0, math.sin(math.pi / 4)]
    assert nav.add(1_000_000, q_east, [10.0, 20.0, -5.0], [0.0, 3.0, 0.0])
    nav.add(900_000, [1.0, 0.0, 0.0, 0.0], nan3, nan3)                  # late attitude, heading north
    nav.add(950_000, nan4, [0.0, 0.0, -5.0], [3.0, 0.0, 0.0])          # late position and velocity
    state, stamp = nav.get()
    assert stamp == 1_000_000 and state.position_ned_m == pytest.approx([10.0, 20.0, -5.0])
    assert state.T_body_ned @ np.array([0.0, 1.0, 0.0]) == pytest.approx([1.0, 0.0, 0.0], abs=1e-9)   # east = nose
    assert nav.ownship(None, -1).velocity_ned_mps == pytest.approx([0.0, 3.0, 0.0])


def test_mixture_sigma_against_a_sampled_mixture():
    # equal sigmas: that sigma
    assert ob.mixture_sigma(np.full(50, 2.0)) == pytest.approx(2.0, rel=1e-6)
    # 80 % of the points with sigma 1, 20 % with 10: the 95 % quantile of |a sample of that mixture| / 1.645
    # (an independent figure: 2e6 seeded draws), far above the median sigma (1)
    rng = np.random.default_rng(11)
    s = np.where(np.arange(100) < 80, 1.0, 10.0)
    draws = rng.standard_normal(2_000_000) * np.repeat(s, 20_000)
    q95 = np.quantile(draws, 0.95)
    assert ob.mixture_sigma(s) == pytest.approx(q95 / 1.6448536, rel=0.01)
    assert ob.mixture_sigma(s) > 4.0
    assert math.isnan(ob.mixture_sigma(np.array([])))


def test_obstacle_carries_its_pixels_range_noise():
    # a wall at 20 m whose pixels have sigma_rho 1e-4 (4 cm) except a band of 16 of its 64 columns at 2e-3 (0.8 m; on the analysis grid's cells):
    # the median sigma is the quiet pixels', the noise that spreads the face along the ray is the mixture's
    r = add_wall(ground_and_sky(), 20.0, 128, 192)
    std = np.full(r.shape, 1e-4, np.float32)
    std[:, 144:160] = 2e-3
    res = ob.analyse(r, CAM, LEVEL, inv_range_std_per_m=std, cfg=CFG)
    o, = res.obstacles
    assert o.range_std_m == pytest.approx(1e-4 * 400, rel=0.01)
    # a quarter of the wall's cells are noisy; at its foot the component takes a few more ground rows in the quiet
    # columns than in the noisy ones (the range jump test scales with the sigma): 22-25 % of its pixels
    lo, hi = (ob.mixture_sigma(np.array([0.04, 0.8]), np.array([1.0 - f, f])) for f in (0.22, 0.25))
    assert lo <= o.range_noise_std_m <= hi
    # weighted: a point standing for more pixels counts more
    assert ob.mixture_sigma(np.array([0.04, 0.8]), np.array([3.0, 1.0])) == pytest.approx(
        ob.mixture_sigma(np.repeat([0.04, 0.8], [48, 16])), rel=1e-9)
    assert o.range_noise_std_m > 5 * o.range_std_m
