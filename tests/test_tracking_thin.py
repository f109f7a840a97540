"""The tracker's options for thin objects (see-through measurements, duplicate tracks) and the benchmark's
id-stability breakdown, on hand-made measurements with known truth: a hovering camera, points on known rays."""
import math
from types import SimpleNamespace

import numpy as np
import pytest

from eonav import InputError
from eonav.app import bench_tracking as B
from eonav.geometry.camera import Camera, VehicleState
from eonav.obstacles import tracking as T
from eonav.obstacles.detect import Obstacle
from eonav.sim.scene import Box

RATE_HZ = 15.0
F_PX = 0.5 * 320 / math.tan(math.radians(20.0))
CAM = Camera("nose", 320, 240, F_PX, F_PX, 159.5, 119.5)
HOVER = VehicleState.from_ypr([0.0, 0.0, -10.0], [0.0, 0.0, 0.0])
LENS = T.lens_ned_m(CAM, HOVER)
POLE = np.array([60.0, 2.0, -8.0])
SEE = T.TrackerConfig(see_through_k=3.0)


def us(t_s):
    return int(round(t_s * 1e6))


def on_ray(p, range_m, range_sigma_m, px_sigma=1.0):
    """A measurement on the ray lens -> p at ``range_m`` (x_c) with the camera-geometry covariance, and the lens."""
    ray = (np.asarray(p, float) - LENS)
    x_c = ray[0]                                          # HOVER looks north, level: x_c = north offset
    q = LENS + ray * (range_m / x_c)
    return T.Measurement(q, T.camera_covariance(q, CAM, HOVER, range_sigma_m, px_sigma, px_sigma),
                         np.array([0.3, 0.3, 4.0]), lens_ned_m=LENS)


def confirmed_pole(cfg, n=10, rng=None):
    rng = rng or np.random.default_rng(21)
    tr = T.Tracker(cfg)
    for k in range(n):
        m = on_ray(POLE, POLE[0] - LENS[0], 0.6)
        m.position_ned_m = rng.multivariate_normal(m.position_ned_m, m.cov_ned_m2)
        tr.update([m], us(k / RATE_HZ))
    assert len(tr.confirmed()) == 1
    return tr, n


def test_see_through_threshold_both_sides_hand_derived():
    """A measurement farther than the track along the ray by e: below k sigma (of the predicted track, along the
    ray) a plain Kalman update; above, the same update with R + (k e)^2 l l^T; nearer: plain whatever e."""
    for factor, side in ((2.8, "far"), (3.2, "far"), (3.2, "near")):
        states = {}
        for name, cfg in (("plain", T.TrackerConfig()), ("see", SEE)):
            tr, n = confirmed_pole(cfg)
            t = tr.tracks[0]
            x, P = T.predict_state(t.x, t.P, (us(n / RATE_HZ) - t.stamp_us) * 1e-6, cfg)   # update()'s prediction
            los = (x[:3] - LENS) / np.linalg.norm(x[:3] - LENS)
            s = float(math.sqrt(los @ P[:3, :3] @ los))
            e = factor * s * (1 if side == "far" else -1)
            z = x[:3] + e * los
            m = T.Measurement(z, T.camera_covariance(z, CAM, HOVER, 1.0, 1.0, 1.0), lens_ned_m=LENS)
            tr.update([m], us(n / RATE_HZ))
            assert len(tr.tracks) == 1 and tr.tracks[0].misses == 0          # paired: a hit either way
            R = m.cov_ned_m2
            if name == "see" and side == "far" and factor > 3.0:
                R = R + (3.0 * e) ** 2 * np.outer(los, los)
            want = x + P[:, :3] @ np.linalg.solve(P[:3, :3] + R, z - x[:3])
            np.testing.assert_allclose(tr.tracks[0].x, want, rtol=0, atol=1e-9)
            states[name] = tr.tracks[0].x[:3] @ los - x[:3] @ los              # move along the ray
        if side == "far" and factor > 3.0:
            assert abs(states["see"]) < 0.25 * abs(states["plain"])         # the range hardly counts
        else:
            assert states["see"] == pytest.approx(states["plain"], abs=1e-12)


def test_see_through_does_not_apply_to_tentative_tracks_or_without_a_lens():
    for lens in (LENS, None):
        out = {}
        for name, cfg in (("plain", T.TrackerConfig()), ("see", SEE)):
            tr = T.Tracker(cfg)
            m0 = on_ray(POLE, 58.0, 0.6)
            tr.update([m0], us(0.0))                                         # tentative (1 hit of 3)
            m = on_ray(POLE, 62.0, 0.6)
            m.lens_ned_m = lens
            tr.update([m], us(1 / RATE_HZ))
            if lens is None:                                                 # a confirmed track, no lens: plain
                for k in range(2, 8):
                    tr.update([on_ray(POLE, 58.0, 0.6)], us(k / RATE_HZ))
                far = on_ray(POLE, 70.0, 5.0)
                far.lens_ned_m = None
                tr.update([far], us(8 / RATE_HZ))
            out[name] = [t.x.copy() for t in tr.tracks]
        for a, b in zip(out["plain"], out["see"], strict=True):
            np.testing.assert_array_equal(a, b)


def test_thin_pole_keeps_its_id_and_place_through_a_second_of_background_ranges():
    """The pole at 60 m, then 1 s (15 maps) in which the map ranges it at its background (120 m, a 5 m sigma that
    does not cover the error), then the pole again. With see-through: one id, within 1 m of the pole throughout.
    Without: the background measurements fall outside the gate, the track misses M = 6 times and dies, and the
    pole comes back under a new id."""
    for cfg, keeps in ((SEE, True), (T.TrackerConfig(), False)):
        rng = np.random.default_rng(22)
        tr, n = confirmed_pole(cfg, rng=rng)
        first = tr.confirmed()[0].id
        ids, errs = set(), []
        for k in range(n, n + 40):
            behind = n + 5 <= k < n + 20
            m = on_ray(POLE, 120.0, 5.0) if behind else on_ray(POLE, POLE[0] - LENS[0], 0.6)
            m.position_ned_m = rng.multivariate_normal(m.position_ned_m, m.cov_ned_m2)
            tr.update([m], us(k / RATE_HZ))
            near = [t for t in tr.confirmed() if np.linalg.norm(t.x[:3] - POLE) < 3.0]
            ids |= {t.id for t in near}
            errs.append(min((np.linalg.norm(t.x[:3] - POLE) for t in near), default=math.inf))
        if keeps:
            assert ids == {first} and max(errs) < 1.0
            assert [t.id for t in tr.confirmed()] == [first]
        else:
            assert first not in {t.id for t in tr.tracks} and len(ids) == 2


def test_duplicate_tracks_merge_into_the_older_id_and_neighbours_do_not():
    cov = np.diag([0.36, 0.01, 0.01])
    dup = T.TrackerConfig(duplicate_chi2=T.CHI2_6_99)
    for cfg, merged in ((dup, True), (T.TrackerConfig(), False)):
        rng = np.random.default_rng(23)
        tr = T.Tracker(cfg)
        for k in range(6):
            tr.update([T.Measurement(rng.multivariate_normal(POLE, cov), cov)], us(k / RATE_HZ))
        older = tr.confirmed()[0]
        trace_before = np.trace(older.P[:3, :3])
        # the list now gives the pole twice a map (a fragment the list did not merge): a second track is born
        for k in range(6, 12):
            tr.update([T.Measurement(rng.multivariate_normal(POLE, cov), cov) for _ in range(2)], us(k / RATE_HZ))
        ids = [t.id for t in tr.confirmed()]
        if merged:
            assert ids == [older.id]
            assert np.trace(tr.tracks[0].P[:3, :3]) < trace_before          # the better state kept, still updated
        else:
            assert len(ids) == 2 and older.id in ids
    # two poles 2 m apart (20 sigma across the ray) stay two tracks with the merge on
    tr = T.Tracker(dup)
    rng = np.random.default_rng(24)
    other = POLE + [0.0, 2.0, 0.0]
    for k in range(30):
        tr.update([T.Measurement(rng.multivariate_normal(p, cov), cov) for p in (POLE, other)], us(k / RATE_HZ))
    assert len(tr.confirmed()) == 2


def test_duplicate_merge_spares_tracks_of_different_velocity():
    """Two objects passing each other at 6 m/s both ways: at the crossing their positions agree, their
    velocities do not (6 dof), so both ids live on."""
    cov = 0.04 * np.eye(3)
    tr = T.Tracker(T.TrackerConfig(duplicate_chi2=T.CHI2_6_99))
    rng = np.random.default_rng(25)
    ids = []
    for k in range(int(4 * RATE_HZ)):
        t = k / RATE_HZ
        a = np.array([50.0, -12.0 + 6.0 * t, -8.0])
        b = np.array([50.0, 12.0 - 6.0 * t, -6.0])
        tr.update([T.Measurement(rng.multivariate_normal(p, cov), cov) for p in (a, b)], us(t))
        if k >= 3:
            ids.append(tuple(sorted(t.id for t in tr.confirmed())))
    assert set(ids) == {ids[0]} and len(ids[0]) == 2


def test_lens_and_options_are_checked_and_measurements_carry_the_lens():
    cov = np.eye(3)
    with pytest.raises(InputError, match="lens_ned_m"):
        T.Measurement([1.0, 2.0, 3.0], cov, lens_ned_m=[1.0, 2.0, 3.0])
    with pytest.raises(InputError, match="lens_ned_m"):
        T.Measurement([1.0, 2.0, 3.0], cov, lens_ned_m=[1.0, np.nan, 3.0])
    for name in ("see_through_k", "duplicate_chi2"):
        with pytest.raises(InputError, match=name):
            T.TrackerConfig(**{name: -1.0})
    o = Obstacle(id=1, distance_m=40.0, distance_median_m=40.0, horizontal_distance_m=40.0, bearing_deg=0.0,
                 elevation_deg=0.0, range_std_m=0.4, position_ned_m=[40.0, 0.0, -10.0], extent_ned_m=[0.5, 0.5, 4.0],
                 width_m=0.5, height_m=4.0, pixel_count=80, confidence=0.9, bbox_px=[155, 90, 164, 149])
    m, = T.measurements_from_obstacles([o], CAM, HOVER)
    np.testing.assert_array_equal(m.lens_ned_m, LENS)
    # merged fragments keep it
    a, b = T.Measurement([60.0, 0.0, -1.0], cov, [0.3, 0.3, 2.0], lens_ned_m=LENS), \
        T.Measurement([60.0, 0.0, -3.0], cov, [0.3, 0.3, 2.0], lens_ned_m=LENS)
    merged, = T.merge_fragments([a, b], 0.5)
    np.testing.assert_array_equal(merged.lens_ned_m, LENS)


def test_bench_id_stability_breakdown_counts_each_cause():
    """One box at 60 m, eight frames from its first represented one: main id near (x3), main id 10 m off (range
    error, x3), main id gone and another id near, nothing near; a measurement within tolerance in four frames."""
    box = Box.on_ground("pole", 60.0, 0.0, 0.3, 0.3, 10.0)
    scene = SimpleNamespace(boxes=(box,))
    st = VehicleState.from_ypr([0.0, 0.0, -6.0], [0.0, 0.0, 0.0])
    near, off = np.array([59.9, 0.0, -5.0]), np.array([70.0, 0.0, -5.0])
    z = np.zeros(3)
    frames = [([(1, near, z)], [near]), ([(1, near, z)], [near]), ([(1, off, z)], [off]), ([(1, near, z)], [near]),
              ([(2, near, z)], [near]), ([], [off]), ([(1, off, z)], []), ([(1, off, z)], [off])]
    rec = [{"stamp_us": us(k / RATE_HZ), "state": st, "scene": scene, "visible_px": {0: 100}, "confirmed": c,
            "measured": meas, "n_measurements": len(meas), "n_obstacles": len(meas)}
           for k, (c, meas) in enumerate(frames)]
    b = B.score(rec, RATE_HZ)["boxes"]["pole"]
    assert (b["frames_in_view"], b["main_id"], b["id_stability"]) == (8, 1, pytest.approx(3 / 8))
    assert (b["main_off"], b["main_gone_other"], b["main_gone_none"], b["measured"]) == (3, 1, 1, 4)
    assert b["ids_used"] == 2 and b["confirm_delay_s"] == 0.0
