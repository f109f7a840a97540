"""The tracker's static-world test (``drift_test``): a track whose detections drift along the vehicle's own velocity
at a good part of its speed is ground ranged at a near-constant range ahead (a phantom) and never confirmed; a
static obstacle and movers across or towards the path are. Hand-made measurements with known truth: a camera flying
north at 20 m/s, points seen through the camera-geometry covariance."""
import math

import numpy as np
import pytest

from eonav import InputError
from eonav.geometry.camera import Camera, VehicleState
from eonav.geometry.frames import camera_from_ned
from eonav.obstacles import tracking as T

RATE_HZ = 15.0
F_PX = 0.5 * 320 / math.tan(math.radians(20.0))
CAM = Camera("nose", 320, 240, F_PX, F_PX, 159.5, 119.5)
SPEED = 20.0
CFG = T.TrackerConfig()
HAND = T.TrackerConfig(follow_k=2.0, follow_fraction=0.5)        # round numbers for the hand-derived fits


def us(t_s):
    return int(round(t_s * 1e6))


def state(t_s, speed=SPEED):
    return VehicleState.from_ypr([speed * t_s, 0.0, -6.0], [0.0, 0.0, 0.0])


def observe(p, st, rng, rel_sigma=0.03):
    """A measurement of the point p: noise drawn from the camera-geometry covariance with a range 1-sigma of
    ``rel_sigma`` of x_c (the scatter of a fused map's obstacle ranges at 50-100 m)."""
    p = np.asarray(p, float)
    x_c = float(camera_from_ned(p, CAM.T_cam_body, st.T_body_ned, st.position_ned_m, CAM.l_body_m)[0])
    C = T.camera_covariance(p, CAM, st, rel_sigma * x_c, 1.0, 1.0)
    return T.Measurement(rng.multivariate_normal(p, C), C, np.array([1.0, 1.0, 2.0]))


def fly(truth, seconds=3.0, speed=SPEED, seed=5, cfg=CFG, velocity=None, rel_sigma=0.03):
    """Feed one measurement of ``truth(t, vehicle state)`` per map; returns (the first time a track is confirmed
    or None, the tracker)."""
    rng = np.random.default_rng(seed)
    tr = T.Tracker(cfg)
    first = None
    for k in range(int(seconds * RATE_HZ)):
        t = k / RATE_HZ
        st = state(t, speed)
        view = T.FieldOfView(CAM, st, 100.0, velocity_ned_mps=velocity)
        tr.update([observe(truth(t, st), st, rng, rel_sigma)], us(t), view)
        if first is None and tr.confirmed():
            first = t
    return first, tr


def line(slope_mps, n=8, scatter=None, dist_m=50.0):
    """Detections at 15 Hz on the north axis moving at ``slope_mps``, with residuals ``scatter`` (a per-point
    offset) or none; the vehicle flies north at SPEED."""
    t = np.arange(n) / RATE_HZ
    north = slope_mps * t + (0.0 if scatter is None else np.asarray(scatter, float))
    pos = np.stack([north + 100.0, np.zeros(n), np.full(n, -3.0)], axis=1)
    return np.round(t * 1e6).astype(np.int64), pos, np.full(n, dist_m), np.array([SPEED, 0.0, 0.0])


def test_drift_test_hand_derived_on_both_sides_of_the_threshold():
    """No scatter: s is the floor 1 % of 50 m = 0.5 m, sigma_b = s / sqrt(sum (t - mean t)^2); 8 points at 15 Hz:
    sum = n (n^2 - 1) / 12 / 15^2. Threshold 0.5 x 20 m/s = 10 m/s; k = 2 sigma taken as the Student-t quantile
    (6 degrees of freedom) at the normal's level p = Phi(2) = 0.97725; checked against the closed form of 2 degrees
    of freedom, t = (2p - 1) / sqrt(2 p (1 - p)) = 4.5266, and the normal limit."""
    stt = 8 * 63 / 12 / RATE_HZ ** 2
    sb = 0.5 / math.sqrt(stt)
    thr = 10.0
    p = 0.977249868
    assert T.student_k(2.0, 2) == pytest.approx((2 * p - 1) / math.sqrt(2 * p * (1 - p)), rel=1e-6)
    assert T.student_k(2.0, 10 ** 6) == pytest.approx(2.0, abs=1e-4)
    k = T.student_k(2.0, 6)
    assert 2.0 < k < T.student_k(2.0, 2)
    for slope, want in ((thr + k * sb + 0.05, T.FOLLOWS), (thr + k * sb - 0.05, T.UNDECIDED),
                        (thr - k * sb + 0.05, T.UNDECIDED), (thr - k * sb - 0.05, T.STATIC), (0.0, T.STATIC)):
        verdict, b, s = T.drift_test(*line(slope), HAND)
        assert verdict == want, (slope, verdict)
        assert b == pytest.approx(slope, abs=1e-4) and s == pytest.approx(sb, rel=1e-5)   # stamps in whole us


def test_drift_test_uses_the_fits_own_scatter_above_its_floor():
    """Residuals +-e alternating about a line (orthogonal to t - mean t for an even count): s = sqrt(8 e^2 / 6)."""
    e = 0.8
    scatter = e * np.array([1, -1, -1, 1, 1, -1, -1, 1], float)      # sums to 0, orthogonal to t - mean t
    verdict, b, sb = T.drift_test(*line(0.0, scatter=scatter), HAND)
    stt = 8 * 63 / 12 / RATE_HZ ** 2
    assert b == pytest.approx(0.0, abs=1e-4)
    assert sb == pytest.approx(math.sqrt(8 * e * e / 6) / math.sqrt(stt), rel=1e-4)
    assert sb > 0.5 / math.sqrt(stt)                                  # above the floor
    assert verdict == T.STATIC                                        # 0 + 2.52 x 3.0 m/s < 10 m/s
    verdict, _, _ = T.drift_test(*line(0.0, scatter=2 * scatter), HAND)
    assert verdict == T.UNDECIDED                                     # 2.52 x 6.0 m/s > 10 m/s


def test_drift_test_needs_its_hits_a_moving_vehicle_and_can_be_off():
    st, pos, dist, v = line(30.0, n=HAND.follow_min_hits - 1)
    assert T.drift_test(st, pos, dist, v, HAND)[0] == T.UNDECIDED      # too few to fit
    st, pos, dist, v = line(30.0, n=HAND.follow_min_hits)
    assert T.drift_test(st, pos, dist, v, HAND)[0] == T.FOLLOWS
    slow = np.array([HAND.follow_min_speed_mps * 0.99, 0.0, 0.0])
    assert T.drift_test(st, pos, dist, slow, HAND)[0] == T.STATIC       # hovering: nothing drifts
    fast = np.array([HAND.follow_min_speed_mps * 1.01, 0.0, 0.0])
    assert T.drift_test(st, pos, dist, fast, HAND)[0] == T.FOLLOWS
    off = T.TrackerConfig(follow_k=0.0, follow_fraction=0.5)
    assert T.drift_test(st, pos, dist, v, off)[0] == T.STATIC
    # the drift across the vehicle's velocity does not count: the same line seen by a vehicle flying east
    assert T.drift_test(st, pos, dist, np.array([0.0, SPEED, 0.0]), HAND)[0] == T.STATIC


def test_drift_test_counts_the_vehicles_vertical_speed():
    """A vehicle descending straight down at 5 m/s (no horizontal speed: a landing): ground ranged at a constant
    range below-ahead drifts down with it at 5 m/s, a phantom; a static obstacle does not drift. 8 points at 15 Hz,
    20 m away: the scatter floor 0.2 m, sigma_b = 0.2 / sqrt(8 x 63 / 12 / 15^2) = 0.463 m/s, k = 2.52 (Student-t, 6
    degrees of freedom): FOLLOWS above 0.5 x 5 + 1.17 = 3.67 m/s, STATIC below 2.5 - 1.17 = 1.33 m/s. Climbing: the
    same upwards."""
    t = np.arange(8) / RATE_HZ
    stamps = np.round(t * 1e6).astype(np.int64)

    def verdict(drift_down_mps, velocity):
        pos = np.stack([np.full(8, 20.0), np.zeros(8), -3.0 + drift_down_mps * t], axis=1)
        return T.drift_test(stamps, pos, np.full(8, 20.0), np.array(velocity, float), HAND)[0]
    assert verdict(5.0, [0.0, 0.0, 5.0]) == T.FOLLOWS
    assert verdict(0.0, [0.0, 0.0, 5.0]) == T.STATIC
    assert verdict(-5.0, [0.0, 0.0, -5.0]) == T.FOLLOWS


def fly_dropping(drop, seed, seconds=2.0, p=(100.0, 3.0, -2.0), rel_sigma=0.04):
    """The static obstacle ``p`` observed every map except the map indices in ``drop`` (in view: a miss); the noise is
    drawn for every map, so flights that drop different maps see the same detections. Returns (first confirmation
    time or None, the ids confirmed then, the tracker's tracks after the first dropped map)."""
    rng = np.random.default_rng(seed)
    tr = T.Tracker(CFG)
    first, ids, after_miss = None, None, None
    for k in range(int(seconds * RATE_HZ)):
        t = k / RATE_HZ
        st = state(t)
        z = observe(np.asarray(p, float), st, rng, rel_sigma)
        tr.update([] if k in drop else [z], us(t), T.FieldOfView(CAM, st, 100.0))
        if after_miss is None and k in drop:
            after_miss = [(trk.id, trk.misses, trk.verdict, trk.drift_mps) for trk in tr.tracks]
        if first is None and tr.confirmed():
            first, ids = t, [trk.id for trk in tr.confirmed()]
    return first, ids, after_miss


def _outlives_one_miss_not_two(monkeypatch, drop: int, rule: str, drift_ok):
    """Six seeded flights of the static obstacle, not detected in map ``drop``: its first track outlives that miss
    (one miss, UNDECIDED, ``drift_ok(drift)``) and is confirmed (id 1); not detected in ``drop`` and ``drop + 1``: it
    dies at its second consecutive miss and a second track is confirmed. With the tracker's ``rule`` off the single
    miss kills it too."""
    for seed in range(6):
        first, ids, after = fly_dropping({drop}, seed)
        (tid, misses, verdict, drift), = after
        assert (tid, misses, verdict) == (1, 1, T.UNDECIDED) and drift_ok(drift)
        assert first is not None and ids == [1]
        first, ids, _ = fly_dropping({drop, drop + 1}, seed)
        assert first is not None and ids == [2]
    monkeypatch.setattr(T, rule, lambda *args: False)
    for seed in range(6):
        first, ids, after = fly_dropping({drop}, seed)
        assert after == [] and ids != [1]


def test_a_track_the_test_is_still_deciding_outlives_one_miss_not_two(monkeypatch):
    """The static obstacle at 100 m with a 4 % range scatter, not detected in its 10th map (0.6 s), where every
    flight's drift fit is still undecided inside the static band (``still_deciding``)."""
    _outlives_one_miss_not_two(monkeypatch, 9, "still_deciding", lambda d: abs(d) < CFG.follow_fraction * SPEED)


def test_a_phantom_at_a_constant_range_ahead_never_confirms():
    """Ground ranged at 70 m ahead of the vehicle whatever its true range: it moves with the vehicle in NED."""
    first, tr = fly(lambda t, st: st.position_ned_m + np.array([70.0, 6.0, 3.0]))
    assert first is None
    off_first, _ = fly(lambda t, st: st.position_ned_m + np.array([70.0, 6.0, 3.0]), cfg=T.TrackerConfig(follow_k=0))
    assert off_first is not None and off_first < 0.2                 # without the test: confirmed at its 3rd map


def test_a_phantom_ranged_at_a_fraction_of_its_true_range_never_confirms():
    """A ground point 150 m ahead ranged at 0.4 of its range (the fused maps' far ground: 0.16-0.7): in NED it
    moves at (1 - 0.4) x the vehicle's velocity, 12 m/s, at the threshold (0.6 x 20 m/s): never below it by k
    sigma."""
    g = np.array([150.0, -10.0, 0.0])
    first, _ = fly(lambda t, st: st.position_ned_m + 0.4 * (g - st.position_ned_m))
    assert first is None
    # the test's limit: ranged at 0.9 of its range it drifts at 0.1 of the speed, well below follow_fraction: it
    # passes as a static obstacle would (at 0.7, 0.3 of the speed, the fit on 3 % scatter stays undecided for the
    # second a tentative track has)
    first, _ = fly(lambda t, st: st.position_ned_m + 0.9 * (g - st.position_ned_m))
    assert first is not None


def test_a_static_obstacle_confirms_within_a_second_and_stays():
    first, tr = fly(lambda t, st: np.array([95.0, 3.0, -2.0]), seconds=3.0)
    assert first is not None and first <= 1.0
    trk, = tr.confirmed()
    assert trk.verdict == T.STATIC and abs(trk.drift_mps) < 3.0


def test_the_scatter_floor_is_relative_to_the_distance_from_the_vehicle_not_from_the_ned_origin():
    """The drift fit's scatter floor is ``follow_rel_scatter`` of the detections' distance from the vehicle. The
    static-obstacle flight moved 5 km north, vehicle and obstacle both (NED set up where the flight began): each
    detection's distance is the one to the vehicle (under 100 m: 95 m less 20 m/s x t, plus the noise), and the
    track confirms in the same map as near the origin (same seed, same detections but for the offset). A floor of
    1 % of the 5 km from the origin (51 m) would hold every obstacle UNDECIDED, never confirmed."""
    def run(north_m):
        off = np.array([north_m, 0.0, 0.0])
        rng = np.random.default_rng(5)
        tr = T.Tracker(CFG)
        first, dists = None, []
        for k in range(int(2.0 * RATE_HZ)):
            t = k / RATE_HZ
            st = VehicleState.from_ypr(state(t).position_ned_m + off, [0.0, 0.0, 0.0])
            z = observe(np.array([95.0, 3.0, -2.0]) + off, st, rng)
            tr.update([z], us(t), T.FieldOfView(CAM, st, 100.0))
            dists.append(float(np.linalg.norm(z.position_ned_m - st.position_ned_m)))
            if first is None and tr.confirmed():
                first = t
        trk, = tr.tracks
        return first, trk, dists

    first, _, _ = run(0.0)
    assert first is not None and first <= 1.0
    far_first, trk, dists = run(5000.0)
    assert far_first == first
    # the last follow_window_s of detections carry their distances from the vehicle
    got = [d[2] for d in trk.detections]
    np.testing.assert_allclose(got, dists[-len(got):], rtol=1e-9)
    assert max(got) < 100.0


@pytest.mark.parametrize("name, p0, v", [("crossing", [90.0, -20.0, -1.0], [0.0, 6.0, 0.0]),
                                         ("oncoming", [110.0, 4.0, -1.0], [-8.0, 0.0, 0.0])])
def test_movers_across_and_towards_the_path_confirm_within_a_second(name, p0, v):
    first, tr = fly(lambda t, st: np.asarray(p0) + t * np.asarray(v), seconds=2.0)
    assert first is not None and first <= 1.0, (name, first)


def test_still_deciding_on_both_sides_of_each_threshold():
    """Past confirm_window_s and a single miss a tentative track lives on while the test is UNDECIDED with |drift|
    below follow_fraction x speed (0.6 x 20 = 12 m/s), up to follow_window_s (1.5 s); not with another verdict, an
    unknown drift (fewer than follow_min_hits detections) or an unknown vehicle speed."""
    ok = lambda drift, age=1.2, verdict=T.UNDECIDED, speed=SPEED: T.still_deciding(verdict, drift, age, speed, CFG)
    assert ok(11.9) and ok(-11.9) and ok(0.0)
    assert not ok(12.1) and not ok(-12.1)
    assert ok(5.0, age=1.5) and not ok(5.0, age=1.51)
    assert not ok(5.0, verdict=T.STATIC) and not ok(5.0, verdict=T.FOLLOWS)
    assert not ok(math.nan) and not ok(5.0, speed=math.nan)
    assert ok(5.0, speed=9.0) and not ok(5.0, speed=8.0)              # the band scales with the speed: 5.4 / 4.8


def test_a_far_static_obstacle_the_test_is_still_deciding_keeps_its_first_track(monkeypatch):
    """A static obstacle at 100 m seen with a 4 % range scatter (the fused maps' 3-4 m there), six seeded flights:
    at 1 s (confirm_window_s) the drift fit of some is still undecided; their track lives to the test's own window
    and every flight confirms its first track (id 1) within follow_window_s. Without the rule those tracks die at 1 s
    and a new one restarts its fit: a second id, or nothing confirmed within 2 s."""
    truth = lambda t, st: np.array([100.0, 3.0, -2.0])
    runs = [fly(truth, seconds=2.0, seed=seed, rel_sigma=0.04) for seed in range(6)]
    for first, tr in runs:
        assert first is not None and first <= CFG.follow_window_s
        assert [t.id for t in tr.confirmed()] == [1]
    # confirmed after the first map past the window (that map's detection confirms before the window is checked)
    late = [seed for seed, (first, _) in enumerate(runs) if first > CFG.confirm_window_s + 1.0 / RATE_HZ]
    assert late                                                       # the rule is exercised
    monkeypatch.setattr(T, "still_deciding", lambda *args: False)
    for seed in late:
        first, tr = fly(truth, seconds=2.0, seed=seed, rel_sigma=0.04)
        assert first is None or [t.id for t in tr.confirmed()] != [1]


def test_a_mover_receding_along_the_path_faster_than_the_fraction_is_held():
    """What a phantom does: 0.8 of the vehicle's speed away along its path (a limitation of the test, see
    docs/guidance.md): held; with the test off it confirms. At 0.3 of the speed it confirms, later than a static
    obstacle (its drift is nearer the threshold: the fit needs a smaller sigma)."""
    truth = lambda t, st: np.array([60.0, 4.0, -1.0]) + t * np.array([16.0, 0.0, 0.0])
    assert fly(truth)[0] is None
    assert fly(truth, cfg=T.TrackerConfig(follow_k=0))[0] is not None
    slow, _ = fly(lambda t, st: np.array([70.0, 4.0, -1.0]) + t * np.array([6.0, 0.0, 0.0]))
    assert slow is not None and slow <= 1.5


def test_a_confirmed_track_that_follows_is_deleted():
    """A phantom at a constant range ahead confirmed with the test off (as a tracker configured without it would),
    then judged with it: deleted at its next detection, counted as a confirmed follower."""
    rng = np.random.default_rng(9)
    ahead = np.array([70.0, 6.0, 3.0])
    tr = T.Tracker(T.TrackerConfig(follow_k=0.0))
    n = int(CFG.follow_window_s * RATE_HZ)                            # a full window of detections
    for k in range(n):
        st = state(k / RATE_HZ)
        tr.update([observe(st.position_ned_m + ahead, st, rng)], us(k / RATE_HZ), T.FieldOfView(CAM, st, 100.0))
    trk, = tr.confirmed()
    tr.cfg = CFG
    st = state(n / RATE_HZ)
    tr.update([observe(st.position_ned_m + ahead, st, rng)], us(n / RATE_HZ), T.FieldOfView(CAM, st, 100.0))
    assert all(t.id != trk.id for t in tr.tracks)
    assert (tr.n_followers, tr.n_followers_confirmed) == (1, 1)


def test_a_static_obstacle_replaced_by_a_phantom_loses_its_track_and_the_phantom_never_confirms():
    """A static obstacle's track confirmed; then its detections hold a constant range ahead (a phantom in its
    place): they leave the static track's gate (it dies of misses), and the track they start never confirms and is
    deleted as a follower."""
    p = np.array([80.0, 3.0, -2.0])
    truth = lambda t, st: p if t < 1.5 else st.position_ned_m + (p - state(1.5).position_ned_m)
    rng = np.random.default_rng(9)
    tr = T.Tracker(CFG)
    confirmed_ids = []
    for k in range(int(3.5 * RATE_HZ)):
        t = k / RATE_HZ
        st = state(t)
        tr.update([observe(truth(t, st), st, rng)], us(t), T.FieldOfView(CAM, st, 100.0))
        confirmed_ids.append({trk.id for trk in tr.confirmed()})
    assert confirmed_ids[int(1.4 * RATE_HZ)] == {1}                   # confirmed while static
    assert set().union(*confirmed_ids) == {1} and not confirmed_ids[-1]
    assert tr.n_followers >= 1 and tr.n_followers_confirmed == 0


def test_bench_reports_the_followers_of_the_last_map():
    from types import SimpleNamespace

    from eonav.app import bench_tracking as B
    st = state(0.0)
    rec = [{"stamp_us": us(k / RATE_HZ), "state": st, "scene": SimpleNamespace(boxes=()), "visible_px": {},
            "confirmed": [], "n_measurements": 0, "n_obstacles": 0, "followers": (k, k // 2)} for k in range(4)]
    assert B.score(rec, RATE_HZ)["followers"] == (3, 1)
    del rec[-1]["followers"]                                          # a record without them (older callers)
    assert B.score(rec, RATE_HZ)["followers"] == (0, 0)


def test_hovering_confirms_after_the_hits_and_the_views_velocity_is_used():
    """Below follow_min_speed_mps the test passes: confirmed at the 3rd map as without it. A view that gives the
    vehicle's velocity is used instead of the poses' difference: a zero velocity turns the test off."""
    first, _ = fly(lambda t, st: np.array([40.0, 3.0, -2.0]), speed=0.5)
    assert first == pytest.approx(2 / RATE_HZ)
    first, _ = fly(lambda t, st: st.position_ned_m + np.array([70.0, 6.0, 3.0]), velocity=[0.0, 0.0, 0.0])
    assert first == pytest.approx(2 / RATE_HZ)
    # two maps of one stamp (two cameras): the second keeps the velocity the poses gave before; the phantom seen by
    # both never confirms
    rng = np.random.default_rng(4)
    tr = T.Tracker(CFG)
    for k in range(int(2 * RATE_HZ)):
        st = state(k / RATE_HZ)
        for _ in range(2):
            tr.update([observe(st.position_ned_m + np.array([70.0, 6.0, 3.0]), st, rng)], us(k / RATE_HZ),
                      T.FieldOfView(CAM, st, 100.0))
        assert not tr.confirmed()
    # without a view the tracker knows no vehicle motion: the test is off
    rng = np.random.default_rng(3)
    tr = T.Tracker(CFG)
    for k in range(3):
        st = state(k / RATE_HZ)
        tr.update([observe(st.position_ned_m + np.array([70.0, 6.0, 3.0]), st, rng)], us(k / RATE_HZ))
    assert len(tr.confirmed()) == 1


def test_follow_options_are_checked():
    with pytest.raises(InputError, match="follow_min_hits"):
        T.TrackerConfig(follow_min_hits=2)
    with pytest.raises(InputError, match="follow_k"):
        T.TrackerConfig(follow_k=-1.0)
    with pytest.raises(InputError, match="follow_window_s"):
        T.TrackerConfig(follow_window_s=0.0)
    with pytest.raises(InputError, match="velocity_ned_mps"):
        T.FieldOfView(CAM, state(0.0), velocity_ned_mps=[1.0, math.nan, 0.0])


def test_awaiting_fit_on_both_sides_of_the_detections_the_fit_needs():
    """Fewer than follow_min_hits (5) detections with the verdict UNDECIDED: the test has not had its chance yet. A
    STATIC verdict without a fit (the test off, the vehicle at rest) or a FOLLOWS one is not waiting."""
    assert T.awaiting_fit(T.UNDECIDED, 4, CFG) and T.awaiting_fit(T.UNDECIDED, 1, CFG)
    assert not T.awaiting_fit(T.UNDECIDED, 5, CFG)
    assert not T.awaiting_fit(T.STATIC, 4, CFG) and not T.awaiting_fit(T.FOLLOWS, 4, CFG)
    assert T.awaiting_fit(T.UNDECIDED, 6, T.TrackerConfig(follow_min_hits=7))


def test_a_track_without_its_fit_yet_outlives_one_miss_not_two(monkeypatch):
    """The static obstacle at 100 m (4 % range scatter), not detected in its 4th map (0.2 s), when its track has 3
    detections and no drift fit (``awaiting_fit``; the approach's van on seed 1, docs/guidance.md)."""
    _outlives_one_miss_not_two(monkeypatch, 3, "awaiting_fit", math.isnan)


def test_a_track_without_its_fit_still_dies_at_the_confirmation_window():
    """A track with 3 detections that then coasts out of view (no data at its pixel: no miss counted) is still
    awaiting its fit at 1 s, and dies there (not at follow_window_s, as a track whose fit is inside the band would)."""
    rng = np.random.default_rng(1)
    tr = T.Tracker(CFG)
    p = np.array([100.0, 3.0, -2.0])
    alive = {}
    for k in range(int(1.4 * RATE_HZ)):
        t = k / RATE_HZ
        st = state(t)
        z = observe(p, st, rng, 0.04)
        # maps 3 on: nothing listed, and the map has no range anywhere: the track coasts (NO_DATA), no miss
        rng_map = np.full((CAM.height, CAM.width), np.nan)
        view = T.FieldOfView(CAM, st, 100.0, range_m=rng_map) if k >= 3 else T.FieldOfView(CAM, st, 100.0)
        tr.update([z] if k < 3 else [], us(t), view)
        alive[k] = [(trk.id, trk.misses, T.awaiting_fit(trk.verdict, len(trk.detections), CFG)) for trk in tr.tracks]
    assert alive[14] == [(1, 0, True)]                                # 0.93 s: coasting, awaiting its fit
    assert alive[16] == []                                            # 1.07 s: past confirm_window_s, gone


def test_a_track_without_its_fit_dies_when_its_miss_went_to_another_track():
    """A confirmed track on a static obstacle 60 m ahead and a tentative one born beside it from a second measurement
    3 m farther along the ray (inside both gates). In the next map one measurement at the obstacle: it goes to the
    confirmed track, and the tentative one, without a fit yet but with that measurement inside its gate, dies at
    this miss (a duplicate). In a map with nothing listed it outlives the miss (the list lost the object)."""
    p = np.array([60.0, 2.0, -2.0])

    def meas(q, st):
        x_c = float(camera_from_ned(q, CAM.T_cam_body, st.T_body_ned, st.position_ned_m, CAM.l_body_m)[0])
        return T.Measurement(q, T.camera_covariance(q, CAM, st, 0.04 * x_c, 1.0, 1.0), np.array([1.0, 1.0, 2.0]))

    def run(last):
        tr = T.Tracker(CFG)
        for k in range(13):
            t = k / RATE_HZ
            st = state(t)
            ray = (p - st.position_ned_m) / np.linalg.norm(p - st.position_ned_m)
            z = [meas(p, st)] + ([meas(p + 3.0 * ray, st)] if k == 11 else [])
            if k == 12:
                z = z if last == "taken" else []
            tr.update(z, us(t), T.FieldOfView(CAM, st, 100.0))
            if k == 11:
                assert [(trk.id, trk.confirmed) for trk in tr.tracks] == [(1, True), (2, False)]
        return [(trk.id, trk.misses, trk.miss_taken) for trk in tr.tracks]

    assert run("taken") == [(1, 0, False)]
    assert run("nothing") == [(1, 1, False), (2, 1, False)]
