"""Time to contact on a head-on approach when the range map is noisy per pixel: the range noise taken out of the
track's depth extent, merged fragments' extent, the expected time to contact beside the k-sigma earliest one, and
both on the obstacle_tracks message. Hand-made obstacle lists of a wall face at a known place."""
import math

import numpy as np
import pytest

from eonav.bus import guidance_msg as G
from eonav.geometry.camera import Camera, VehicleState
from eonav.geometry.frames import camera_from_ned
from eonav.obstacles import guidance as GP
from eonav.obstacles import tracking as T
from eonav.obstacles.detect import Obstacle

RATE_HZ = 15.0
F_PX = 0.5 * 320 / math.tan(math.radians(20.0))
CAM = Camera("nose", 320, 240, F_PX, F_PX, 159.5, 119.5)
SPEED = 20.0
WALL_N = 150.0                                         # the face seen, 12 m wide, 8 m tall, centred 5 m up


def us(t_s):
    return int(round(t_s * 1e6))


def _wall_obstacle(st, rng, rel_sigma_px=0.06):
    """The wall face as the obstacle list gives it from a noisy map: the median point on the face (its error that
    of a median over many pixels, 0.3 % of range), the per-pixel range sigma ``rel_sigma_px`` of x_c as its
    ``range_std_m``, and its points' 5..95 % extent along the ray = that noise's spread alone (3.29 sigma)."""
    x_c = WALL_N - st.position_ned_m[0]
    s_pix = rel_sigma_px * x_c
    p = [WALL_N + 0.003 * x_c * rng.standard_normal(), 0.0, -5.0]
    u0 = int(CAM.cx - F_PX * 6.0 / x_c)
    v0 = int(CAM.cy - F_PX * 4.0 / x_c)
    return Obstacle(id=1, distance_m=x_c, distance_median_m=x_c, horizontal_distance_m=x_c, bearing_deg=0.0,
                    elevation_deg=0.0, range_std_m=s_pix, position_ned_m=p,
                    extent_ned_m=[3.29 * s_pix, 12.0, 8.0], width_m=12.0, height_m=8.0, pixel_count=3000,
                    confidence=0.9, bbox_px=[u0, v0, 319 - u0, 239 - v0])


def _approach(keep_noise_in_extent=False, seed=3):
    """Fly north at 20 m/s, 5 m up, from north 60 m at the wall. Yields (true time to contact of the 1 m vehicle
    sphere with the face, nearest threat) for every frame from 3.5 s out."""
    rng = np.random.default_rng(seed)
    tr = T.Tracker()
    cone = T.ConeConfig(vehicle_radius_m=1.0)
    for k in range(200):
        t = k / RATE_HZ
        n = 60.0 + SPEED * t
        true_ttc = (WALL_N - 1.0 - n) / SPEED
        if true_ttc < 0.3:
            return
        st = VehicleState.from_ypr([n, 0.0, -5.0], [0.0, 0.0, 0.0])
        meas = T.measurements_from_obstacles([_wall_obstacle(st, rng)], CAM, st) if WALL_N - n <= 100 else []
        if keep_noise_in_extent:
            for m in meas:
                m.extent_noise_ned_m = np.zeros(3)
        tr.update(meas, us(t), T.FieldOfView(CAM, st, max_distance_m=100.0))
        own = T.Ownship.from_state(st, [SPEED, 0.0, 0.0], us(t))
        if true_ttc <= 3.5:
            yield true_ttc, T.nearest_threat(T.assess(tr.snapshot(us(t)), own, us(t), cone))


def test_static_wall_expected_time_to_contact_is_distance_over_speed():
    n = 0
    for true_ttc, th in _approach():
        if true_ttc > 3.0:
            continue
        assert th is not None
        # the track's depth extent is the face's (noise taken out), so the contact is with the face
        assert th.track.extent_ned_m[0] < 0.5
        assert th.expected_time_to_contact_s == pytest.approx(true_ttc, rel=0.03), true_ttc
        # the earliest contact consistent with k sigma comes first, and within 10 % from 3 s out
        assert th.time_to_contact_s <= th.expected_time_to_contact_s + 1e-12
        assert th.time_to_contact_s == pytest.approx(true_ttc, rel=0.10), true_ttc
        n += 1
    assert n >= 40


def test_range_noise_left_in_the_extent_makes_contact_early():
    # the same flight with the 5..95 % spread of the per-pixel noise kept as the wall's depth: its box stands
    # 1.65 sigma in front of the face and every contact at 3 s is more than 10 % early
    early = [(th.expected_time_to_contact_s - t) / t for t, th in _approach(keep_noise_in_extent=True)
             if 2.5 <= t <= 3.0]
    assert early and max(early) < -0.10


def test_the_noise_taken_out_is_the_pixels_mixture_not_their_median():
    # a face head-on at 80 m: 80 % of its pixels with a 0.8 m range sigma, 20 % with 8 m (near the focus of
    # expansion, little parallax); its points' 5..95 % spread along the ray is the mixture's, 3.29 x mixture_sigma
    st = VehicleState.from_ypr([70.0, 0.0, -5.0], [0.0, 0.0, 0.0])
    from eonav.obstacles.detect import mixture_sigma
    s_mix = mixture_sigma(np.where(np.arange(100) < 80, 0.8, 8.0))
    spread = 3.29 * s_mix

    def measured(noise_std):
        o = Obstacle(id=1, distance_m=80.0, distance_median_m=80.0, horizontal_distance_m=80.0, bearing_deg=0.0,
                     elevation_deg=0.0, range_std_m=0.8, position_ned_m=[WALL_N, 0.0, -5.0],
                     extent_ned_m=[spread, 12.0, 8.0], width_m=12.0, height_m=8.0, pixel_count=3000,
                     confidence=0.9, bbox_px=[100, 80, 219, 159], range_noise_std_m=noise_std)
        m, = T.measurements_from_obstacles([o], CAM, st)
        return m.object_extent_ned_m[0]

    assert measured(s_mix) == pytest.approx(0.0, abs=1e-6)        # the face: no depth of its own
    # with the median sigma alone (an obstacle without the field) most of the spread stays as depth, and the box
    # stands that much in front of the face
    assert measured(float("nan")) > 0.9 * spread


def test_range_noise_extent_per_axis():
    # on the axis the ray per metre of range is [1, 0, 0]; off the axis [1, a, b] spreads the noise sideways too
    np.testing.assert_allclose(T.range_noise_extent([1.0, 0.0, 0.0], 2.0), [6.58, 0.0, 0.0])
    np.testing.assert_allclose(T.range_noise_extent([1.0, -0.2, 0.1], 2.0), [6.58, 1.316, 0.658])
    m = T.Measurement([50.0, 0.0, 0.0], np.eye(3), [8.0, 5.0, 1.0], extent_noise_ned_m=[6.0, 6.0, 0.0])
    np.testing.assert_allclose(m.object_extent_ned_m, [math.sqrt(64 - 36), 0.0, 1.0])   # never below 0
    with pytest.raises(T.InputError, match="extent_noise_ned_m"):
        T.Measurement([50.0, 0.0, 0.0], np.eye(3), [8.0, 5.0, 1.0], extent_noise_ned_m=[-1.0, 0.0, 0.0])


def test_merged_fragments_keep_the_noise_out_of_the_extent():
    # a wall face in two side-by-side halves, both with a 5 m per-pixel range sigma (16.45 m of noise spread):
    # the merged measurement's object extent is the halves' own, not their noise
    cov = np.diag([25.0, 0.1, 0.1])
    a = T.Measurement([100.0, -3.0, -4.0], cov, [16.45, 6.0, 8.0], 1500, extent_noise_ned_m=[16.45, 0.0, 0.0])
    b = T.Measurement([100.0, 3.0, -4.0], cov, [16.45, 6.0, 8.0], 1500, extent_noise_ned_m=[16.45, 0.0, 0.0])
    m, = T.merge_fragments([a, b], gap_m=0.5)
    assert m.extent_ned_m[0] == pytest.approx(16.45)
    assert m.object_extent_ned_m[0] == pytest.approx(0.0, abs=1e-6)
    assert m.object_extent_ned_m[1] == pytest.approx(12.0 - 2 * 0.1 * (6.0 + 12.0 / 18.0) + 12.0 / 18.0, abs=1e-6)


def test_expected_contact_time_hand_derived():
    # the ray meets the radius box: its entry time
    assert T.expected_contact_time([50.0, 0.0, 0.0], [1.0, 1.0, 1.0], [10.0, 0.0, 0.0], 4.0) == pytest.approx(4.9)
    # it passes beside it (1.5 m off, 1 m half width), meets only the sigma-grown box: closest approach to the
    # centre, w.c / w.w = 5 s
    assert T.expected_contact_time([50.0, 1.5, 0.0], [1.0, 1.0, 1.0], [10.0, 0.0, 0.0], 4.0) == pytest.approx(5.0)
    # never before the entry into the grown box
    assert T.expected_contact_time([50.0, 1.5, 0.0], [1.0, 1.0, 1.0], [10.0, 0.0, 0.0], 6.0) == pytest.approx(6.0)
    # no relative motion: the earliest (0 inside the grown box)
    assert T.expected_contact_time([0.5, 1.5, 0.0], [1.0, 1.0, 1.0], [0.0, 0.0, 0.0], 0.0) == 0.0


def test_assess_reports_both_times_and_the_margin_between_them():
    tr = T.Tracker(T.TrackerConfig(confirm_hits=1))
    cov = np.diag([4.0, 0.04, 0.04])                      # 2 m 1-sigma along the ray
    st = VehicleState.from_ypr([0.0, 0.0, -10.0], [0.0, 0.0, 0.0])
    tr.update([T.Measurement([60.0, 0.0, -10.0], cov, [0.0, 4.0, 4.0])], us(0.0))
    own = T.Ownship.from_state(st, [20.0, 0.0, 0.0], us(0.0))
    v, = T.assess(tr.snapshot(us(0.0)), own, us(0.0), T.ConeConfig(vehicle_radius_m=1.0, k_sigma=2.0))
    assert v.in_cone
    assert v.expected_time_to_contact_s == pytest.approx((60.0 - 1.0) / 20.0)
    assert v.time_to_contact_s == pytest.approx((60.0 - 1.0 - 2.0 * 2.0) / 20.0)
    # out of the cone: both NaN
    own_away = T.Ownship.from_state(st, [-20.0, 0.0, 0.0], us(0.0))
    v, = T.assess(tr.snapshot(us(0.0)), own_away, us(0.0))
    assert not v.in_cone and math.isnan(v.expected_time_to_contact_s) and math.isnan(v.time_to_contact_s)


def test_message_carries_the_expected_time_and_reads_old_messages():
    tr = T.Tracker(T.TrackerConfig(confirm_hits=1))
    tr.update([T.Measurement([60.0, 0.0, -10.0], np.diag([4.0, 0.04, 0.04]), [0.0, 4.0, 4.0])], us(0.0))
    st = VehicleState.from_ypr([0.0, 0.0, -10.0], [0.0, 0.0, 0.0])
    msg = GP.build(tr, T.Ownship.from_state(st, [20.0, 0.0, 0.0], us(0.0)), us(0.0), seq=1, trigger="map",
                   stale_after_s=0.5)
    back = G.decode(G.encode(msg))
    assert back["tracks"][0]["expected_time_to_contact_s"] == pytest.approx(59.0 / 20.0)
    assert back["nearest_threat"]["expected_time_to_contact_s"] == pytest.approx(59.0 / 20.0)
    assert back["nearest_threat"]["time_to_contact_s"] == pytest.approx(55.0 / 20.0)
    # a message of a publisher without the field decodes with NaN there
    del msg["tracks"][0]["expected_time_to_contact_s"], msg["nearest_threat"]["expected_time_to_contact_s"]
    old = G.decode(G.encode(msg))
    assert math.isnan(old["tracks"][0]["expected_time_to_contact_s"])
    assert math.isnan(old["nearest_threat"]["expected_time_to_contact_s"])
    # a mistyped one is refused, naming it
    msg["tracks"][0]["expected_time_to_contact_s"] = "soon"
    with pytest.raises(G.SchemaError, match="expected_time_to_contact_s"):
        G.decode(G.encode(msg))


def test_bench_scores_both_contact_times_against_the_true_entry():
    from types import SimpleNamespace
    from eonav.app import bench_tracking as B
    from eonav.sim.scene import Box
    wall = Box.on_ground("wall", 150.0, 0.0, 3.0, 12.0, 8.0)             # face at north 148.5
    scene = SimpleNamespace(boxes=(wall,))
    rec = []
    for n, thr in ((100.0, (7, 2.0, 2.375)), (110.0, (7, 1.5, 1.5)), (120.0, (8, 1.0, 1.0))):
        st = VehicleState.from_ypr([n, 0.0, -5.0], [0.0, 0.0, 0.0])
        rec.append({"state": st, "scene": scene, "velocity_ned_mps": np.array([SPEED, 0.0, 0.0]), "threat": thr,
                    "surface": {7: (148.5 - n, SPEED)}})
    t = B.score_ttc(rec, "wall", 7, T.ConeConfig(vehicle_radius_m=1.0))
    # true entry (148.5 - 1 - n) / 20: 2.375, 1.875, 1.375 s; the third frame's threat is another track
    assert t["frames"] == 3 and t["missing"] == 1
    np.testing.assert_allclose(t["threat_rel_err"][:2], [2.0 / 2.375 - 1, 1.5 / 1.875 - 1])
    np.testing.assert_allclose(t["expected_rel_err"][:2], [0.0, 1.5 / 1.875 - 1], atol=1e-12)
    assert math.isinf(t["expected_rel_err"][2]) and math.isinf(t["threat_rel_err"][2])



def test_bench_scores_the_surface_time_less_the_vehicle_radius_within_the_horizon():
    """The plain figure: (surface distance - vehicle radius) / closing speed against the true entry. Radius 1 m,
    20 m/s at the wall's face (north 148.5): entry (147.5 - n) / 20 s. North 80 m: 3.375 s, beyond the 3 s horizon,
    not scored; 87.5 m: exactly 3 s, scored, the face 61 m off -> 60 / 20 = 3 s: error 0; 110 m: 1.875 s, the face
    reported 42.25 m off -> 41.25 / 20 = 2.0625 s: +10 %; 120 m: the main track closes at 0 m/s, and 125 m: it is
    not assessed at all: both inf."""
    from types import SimpleNamespace
    from eonav.app import bench_tracking as B
    from eonav.sim.scene import Box
    wall = Box.on_ground("wall", 150.0, 0.0, 3.0, 12.0, 8.0)
    rec = []
    for n, surf in ((80.0, (68.5, SPEED)), (87.5, (61.0, SPEED)), (110.0, (42.25, SPEED)), (120.0, (28.5, 0.0)),
                    (125.0, None)):
        rec.append({"state": VehicleState.from_ypr([n, 0.0, -5.0], [0.0, 0.0, 0.0]),
                    "scene": SimpleNamespace(boxes=(wall,)), "velocity_ned_mps": np.array([SPEED, 0.0, 0.0]),
                    "threat": (7, 1.0, 1.0),
                    "surface": {} if surf is None else {7: surf}})
    t = B.score_ttc(rec, "wall", 7, T.ConeConfig(vehicle_radius_m=1.0))
    assert t["frames"] == 4 and t["missing"] == 0
    np.testing.assert_allclose(t["plain_rel_err"][:2], [0.0, 0.10], atol=1e-12)
    assert math.isinf(t["plain_rel_err"][2]) and math.isinf(t["plain_rel_err"][3])
    np.testing.assert_allclose(t["expected_rel_err"], [1.0 / 3.0 - 1, 1.0 / 1.875 - 1, 1.0 / 1.375 - 1,
                                                       1.0 / 1.125 - 1])

def test_bench_map_cache_computes_once(tmp_path, monkeypatch):
    from eonav.app import bench_tracking as B
    calls = []

    def fake(sc, rate, size, maps, seed, **kw):
        calls.append(seed)
        yield {"stamp_us": 0, "seed": seed}

    monkeypatch.setattr(B, "range_maps", fake)
    sc = B.scenario("head-on", 1.0)
    first = B.cached_maps(sc, 15.0, (320, 240), "truth", 4, str(tmp_path))
    again = B.cached_maps(sc, 15.0, (320, 240), "truth", 4, str(tmp_path))
    assert first == again == [{"stamp_us": 0, "seed": 4}] and calls == [4]
    B.cached_maps(sc, 15.0, (320, 240), "truth", 5, str(tmp_path))          # another seed: computed
    assert calls == [4, 5] and len(list(tmp_path.glob("*.pkl"))) == 2
