"""Obstacle sectors and obstacle list against hand-made range maps (closed-form geometry) and simulator scenes
with known box positions (distance from the vehicle origin to the solid box, computed from the box itself)."""
import math
import sys

import numpy as np
import pytest

from eonav import InputError
from eonav import obstacles as ob
from eonav.camera import Camera, VehicleState
from eonav.rangemap import AT_INFINITY, VALID

# 256 x 256, f = 128 px: horizontal FOV exactly 90 deg (pixel edges at -0.5 and 255.5), 1.25 deg per bin
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


def test_sector_geometry_hand_derived():
    inc, off = ob.sector_geometry(CAM)
    assert inc == pytest.approx(90.0 / 72) and off == pytest.approx(-45.0)
    yawed = Camera("side", 256, 256, 128.0, 128.0, 127.5, 127.5, eps_rad=np.deg2rad([30.0, -5.0, 0.0]))
    inc, off = ob.sector_geometry(yawed)
    assert inc == pytest.approx(1.25) and off == pytest.approx(30.0 - 45.0)


def test_ground_only_is_clear_and_nothing_is_an_obstacle():
    res = ob.analyse(ground_and_sky(), CAM, LEVEL, cfg=CFG)
    assert res.obstacles == []
    assert np.all(res.sectors.distances_cm == res.sectors.max_distance_cm + 1)


def test_unmeasured_columns_are_unknown():
    r = ground_and_sky()
    r[:, :64] = np.nan                                     # left quarter: no estimate at all
    res = ob.analyse(r, CAM, LEVEL, cfg=CFG)
    d = res.sectors.distances_cm
    # columns 0..63 span bearings -45 .. atan(-63.5/128) = -26.4 deg: bins 0..14 fully inside
    assert np.all(d[:14] == ob.UINT16_MAX)
    assert np.all(d[16:] == res.sectors.max_distance_cm + 1)


def test_wall_distance_per_sector_hand_derived():
    # wall at x_c = 20 m over columns 128..191: bearings atan((u - 127.5)/128) = 0.22 .. 26.4 deg
    r = add_wall(ground_and_sky(), 20.0, 128, 192)
    res = ob.analyse(r, CAM, LEVEL, cfg=CFG)
    s = res.sectors
    lo = s.angle_offset_deg + np.arange(72) * s.increment_deg
    for j in range(37, 57):                               # bins fully inside the wall's bearings (0 .. 26.4)
        hi_d, lo_d = 20.0 / math.cos(math.radians(lo[j] + s.increment_deg)), 20.0 / math.cos(math.radians(lo[j]))
        # horizontal distance of a wall point at bearing b is 20 / cos b: the bin's value lies between its edges'
        assert lo_d * 100 - 1 <= s.distances_cm[j] <= hi_d * 100 + 1, j
    assert np.all(s.distances_cm[:36] == s.max_distance_cm + 1)
    assert np.all(s.distances_cm[58:] == s.max_distance_cm + 1)
    # one obstacle: nearest point of the wall at 20 m straight ahead, to the right, below the vehicle at the bottom
    assert len(res.obstacles) == 1
    o = res.obstacles[0]
    assert o.horizontal_distance_m == pytest.approx(20.0, rel=0.02)
    assert 0.0 < o.bearing_deg < 26.4
    assert o.position_ned_m[0] == pytest.approx(20.0, abs=1e-3)     # the wall plane is x = 20 m north
    assert o.bbox_px[0] == 128 and o.bbox_px[2] == 191
    assert o.id == 1 and o.confidence == 1.0


def test_wall_below_ground_clearance_is_ground():
    # a 0.4 m kerb is within the 0.6 m ground clearance: not an obstacle
    r = add_wall(ground_and_sky(), 20.0, 100, 160, top_down_m=-0.4)
    res = ob.analyse(r, CAM, LEVEL, cfg=CFG)
    assert res.obstacles == [] and np.all(res.sectors.distances_cm == res.sectors.max_distance_cm + 1)


def test_beyond_max_distance_is_clear():
    r = add_wall(ground_and_sky(), 120.0, 100, 160)
    res = ob.analyse(r, CAM, LEVEL, cfg=ob.ObstacleConfig(ground_down_m=0.0, max_distance_m=100.0))
    assert res.obstacles == [] and np.all(res.sectors.distances_cm == 10001)


def test_near_wall_is_clamped_to_min_distance():
    r = add_wall(ground_and_sky(), 0.3, 100, 160, top_down_m=-10.2)
    res = ob.analyse(r, CAM, LEVEL, cfg=ob.ObstacleConfig(ground_down_m=0.0, min_distance_m=1.0))
    centre_bins = res.sectors.distances_cm[36:40]
    assert np.all(centre_bins == 100)


def test_depth_discontinuity_splits_adjacent_objects():
    r = add_wall(ground_and_sky(), 40.0, 60, 200)
    r = add_wall(r, 20.0, 100, 140)                        # a near post in front of the far wall
    res = ob.analyse(r, CAM, LEVEL, cfg=CFG)
    d = sorted(round(o.horizontal_distance_m) for o in res.obstacles)
    assert len(res.obstacles) == 3 and d[0] == 20          # post, and the wall left and right of it
    assert all(abs(x - 40) <= 2 for x in d[1:])


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
    assert back.increment_deg == res.sectors.increment_deg and back.angle_offset_deg == -45.0


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
        got = min(res.obstacles, key=lambda o: abs(o.distance_m - want))
        assert got.distance_m == pytest.approx(want, rel=0.03), name
    # sectors: the van's bearing bins report its horizontal distance
    s = res.sectors
    b = math.degrees(math.atan2(c[1], c[0]))
    j = int((b - s.angle_offset_deg) // s.increment_deg)
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
    code = "import eonav.obstacles, eonav.pair_policy, sys; print('zenoh' in sys.modules, 'pymavlink' in sys.modules)"
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True).stdout
    assert out.split() == ["False", "False"]
