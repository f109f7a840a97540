"""The tracking benchmark's velocity score of a mover on hand-made track/truth records: scored only where the mover is
in view and its track was updated by a measurement, from 1 s after the track's first confirmed frame."""
from __future__ import annotations

from dataclasses import replace
from types import SimpleNamespace

import numpy as np
import pytest

from eonav.app import bench_tracking as B
from eonav.geometry.camera import VehicleState
from eonav.sim.scene import Box

RATE_HZ = 15.0
SPEED = 6.0                                    # the mover drives east at 6 m/s
MOVER = B.Mover(Box.on_ground("crosser", 0.0, 0.0, 4.0, 2.0, 2.0), (0.0, SPEED, 0.0))
WALL = Box.on_ground("wall", 50.0, 40.0, 4.0, 4.0, 4.0)     # a static box first: the mover is box 1


def frame(k: int, tracks, hit, visible_px: int, distance_m: float) -> dict:
    """Map k: the mover where it is at k / RATE_HZ, the vehicle ``distance_m`` south of its south face at the box's
    mid height (so the box distance is exactly ``distance_m``), ``visible_px`` of its pixels in the image."""
    t = k / RATE_HZ
    mover = replace(MOVER.box, center_ned_m=(0.0, SPEED * t, -1.0))
    st = VehicleState.from_ypr([-(distance_m + 2.0), SPEED * t, -1.0], [0.0, 0.0, 0.0])
    return {"stamp_us": int(round(t * 1e6)), "state": st, "scene": SimpleNamespace(boxes=(WALL, mover)),
            "visible_px": {0: 500, 1: visible_px}, "confirmed": [(i, np.zeros(3), np.asarray(v, float))
                                                                 for i, v in tracks], "hit": set(hit)}


def test_velocity_scored_only_in_view_and_measured_after_the_settling_second():
    ocfg = B.SERVICE_OBSTACLES
    assert (ocfg.min_obstacle_pixels, ocfg.max_obstacle_distance_m) == (12, 100.0)   # the boundaries used below
    v = lambda east: [(7, (0.0, east, 0.0))]                                          # track 7 at this east speed
    rec = [
        frame(0, v(1.0), {7}, 500, 60.0),        # first confirmed frame: settling, not scored
        frame(14, v(2.0), {7}, 500, 60.0),       # 0.933 s after it: still settling
        frame(15, v(6.0), {7}, 12, 100.0),       # 1.000 s, measured, on both in-view limits: scored, error 0
        frame(16, v(7.2), {7}, 11, 60.0),        # measured, one pixel too few: out of view
        frame(17, v(7.2), {7}, 500, 100.5),      # measured, 0.5 m beyond the listed distance: out of view
        frame(18, v(4.8), {7}, 500, 60.0),       # measured in view: scored, error 1.2 / 6 = 0.2
        frame(19, v(3.0), {8}, 500, 60.0),       # in view, another track updated, 7 not: coasting (0.5)
        frame(20, v(3.0), set(), 0, 60.0),       # the mover has left the image, 7 coasts on: not scored
        frame(21, v(3.0), set(), 0, 60.0),
        frame(22, [(8, (0.0, 6.0, 0.0))], {8}, 500, 60.0),   # track 7 gone, another one measured: not 7's
    ]
    s = B.score_velocity(rec, MOVER, {"main_id": 7}, ocfg)
    assert s["frames"] == 2
    np.testing.assert_allclose(s["rel_err"], [0.0, 0.2], atol=1e-12)
    assert s["coast_frames"] == 3
    np.testing.assert_allclose(s["coast_rel_err"], [0.5, 0.5, 0.5])
    assert s["measured_out_of_view"] == 2


def test_a_track_that_only_coasts_after_settling_scores_nothing():
    """The issue's case: confirmed, leaves the image within the settling second, then coasts on one velocity."""
    rec = [frame(k, [(3, (0.0, 5.46, 0.0))], {3} if k < 12 else set(), 500 if k < 12 else 0, 80.0)
           for k in range(30)]
    s = B.score_velocity(rec, MOVER, {"main_id": 3})
    assert s["frames"] == 0 and s["rel_err"] == [] and s["measured_out_of_view"] == 0
    assert s["coast_frames"] == 15                            # maps 15-29: 1 s and later
    assert s["coast_rel_err"] == pytest.approx([0.09] * 15)   # |5.46 - 6| / 6


def test_box_in_view_boundaries():
    r = frame(0, [], set(), 12, 100.0)
    assert B.box_in_view(r, 1)
    assert not B.box_in_view(frame(0, [], set(), 11, 100.0), 1)
    assert not B.box_in_view(frame(0, [], set(), 12, 100.5), 1)


def test_recorded_hits_on_a_rendered_flight_leave_the_coast_unscored():
    """Truth maps (1 % noise, seed 0) of the ``moving`` scenario at 160 x 120, 8 s: the oncoming vehicle passes below
    the image at about 6.3 s and its track coasts on. The record's ``hit`` ids are confirmed tracks; the main track is
    never recorded as updated in a frame without any of the mover's pixels; its frames not updated after the
    settling second repeat one velocity (a constant-velocity prediction leaves the velocity as it is), and they are
    the ones left out of the score."""
    sc = B.scenario("moving", 8.0)
    rec, _ = B.track_maps(B.range_maps(sc, RATE_HZ, (160, 120), "truth", seed=0), sc)
    s = B.score(rec, RATE_HZ, sc=sc)
    tid = s["boxes"]["oncoming"]["main_id"]
    i = next(k for k, b in enumerate(rec[0]["scene"].boxes) if b.name == "oncoming")
    for r in rec:
        assert r["hit"] <= {j for j, _, _ in r["confirmed"]}
        if r["visible_px"].get(i, 0) == 0:
            assert tid not in r["hit"]
    v = s["velocity"]["oncoming"]
    assert v["frames"] >= 5 and v["coast_frames"] >= 20
    assert len(set(v["coast_rel_err"])) == 1                       # one coasting value, counted once a frame
    assert min(v["rel_err"]) < 0.05 < v["coast_rel_err"][0]       # while measured it is near the truth


def _footprints_overlap(a: Box, b: Box) -> bool:
    """Whether two boxes standing on the ground (yaw a multiple of 90 deg) overlap in north-east: their footprints'
    half extents along N and E are |R| half."""
    ha, hb = (np.abs(x.R_ned_local[:2, :2]) @ x.half_m[:2] for x in (a, b))
    return bool(np.all(np.abs(np.asarray(a.center_ned_m[:2]) - np.asarray(b.center_ned_m[:2])) < ha + hb))


@pytest.mark.parametrize("name", ["moving", "moving-stereo"])
def test_the_moving_scenarios_vehicles_never_pass_through_each_other(name):
    sc = B.scenario(name, 8.0)
    crosser, oncoming = sc.movers

    def overlaps(c, t):
        at = [replace(m.box, center_ned_m=tuple(np.asarray(m.box.center_ned_m) + t * np.asarray(m.velocity_ned_mps)))
              for m in (c, oncoming)]
        return _footprints_overlap(*at)

    times = np.arange(0.0, sc.seconds + 1e-9, 0.01)
    assert not any(overlaps(crosser, t) for t in times)
    # the check sees an intersection: the crosser on its former lane (north 110 m) met the oncoming vehicle from
    # 3.31 to 4.19 s (crosser east -30 + 6 t +- 2.25 m, north 110 +- 1; oncoming north 140 - 8 t +- 2.5, east -7 +- 1)
    old = replace(crosser, box=replace(crosser.box, center_ned_m=(110.0, *crosser.box.center_ned_m[1:])))
    hit = [t for t in times if overlaps(old, t)]
    assert hit and hit[0] == pytest.approx(3.32, abs=0.011) and hit[-1] == pytest.approx(4.18, abs=0.011)


def test_mover_pixels_are_the_movers_own_when_a_static_box_comes_first():
    # the scene's boxes are the scenario's static ones, then the movers (``scene_at``): the wall is box 0 (object id 2),
    # the crosser box 1 (id 3). A 4 x 5 image: the crosser's 8 pixels in rows 0-1 (6 within 10 %, 2 off by 20 %), the
    # wall's 12 in rows 2-3 (all right); the crosser has 12 visible pixels in view (at least min_obstacle_pixels)
    sc = B.Scenario("m", "approach", 1.0, clear=True, boxes=(WALL,), movers=(MOVER,))
    m = frame(0, [], set(), 12, 60.0)
    oid = np.full((4, 5), 2, np.int32)
    oid[:2, :4] = 3
    truth = np.full((4, 5), 60.0, np.float32)
    rng = truth.copy()
    rng[0, :2] = 72.0
    m.update(object_id=oid, truth_range_m=truth, range_m=rng, flags=np.full((4, 5), B.VALID, np.uint8))
    assert B.mover_pixels(m, sc) == {"crosser": {"pixels": 8, "right": 6, "wrong": 2, "filled": 0, "occluded": 0}}
    m["visible_px"] = {0: 500, 1: 11}                     # the crosser too small; the wall's pixels do not count
    assert B.mover_pixels(m, sc) == {}
