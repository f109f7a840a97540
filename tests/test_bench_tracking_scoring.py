"""The tracking benchmark's per-flight figures on a hand-made record whose answers are derived by hand: the
confirmation delay in seconds, false confirmed tracks per minute of flight (n maps at the rate span n / rate s) and
which false tracks are ground tracks (within 1 m of the ground or below it: NED down > -1 m)."""
from __future__ import annotations

from types import SimpleNamespace

import numpy as np
import pytest

from eonav.app import bench_tracking as B
from eonav.geometry.camera import VehicleState
from eonav.sim.scene import Box

RATE_HZ = 15.0
POLE = Box.on_ground("pole", 60.0, 0.0, 0.3, 0.3, 10.0)      # north 59.85-60.15, east +-0.15, down -10..0
HOVER = VehicleState.from_ypr([0.0, 0.0, -6.0], [0.0, 0.0, 0.0])
ON_POLE = np.array([59.9, 0.0, -5.0])                       # inside the pole: distance 0
FALSE = {21: np.array([30.0, 20.0, -0.5]),                  # 0.5 m above the ground: a ground track
         22: np.array([30.0, -20.0, 0.3]),                  # below the ground: a ground track too
         23: np.array([40.0, 25.0, -20.0])}                 # 20 m up: false, not on the ground


def _record(n_maps: int) -> list:
    """``n_maps`` maps at RATE_HZ: the pole is in view from map 2 (100 px, 60 m), track 1 on it confirmed from map 5;
    the three false tracks confirmed in maps 8 and 9."""
    rec = []
    for k in range(n_maps):
        confirmed = ([(1, ON_POLE, np.zeros(3))] if k >= 5 else []) + (
            [(i, p, np.zeros(3)) for i, p in FALSE.items()] if k in (8, 9) else [])
        rec.append({"stamp_us": int(round(k / RATE_HZ * 1e6)), "state": HOVER,
                    "scene": SimpleNamespace(boxes=(POLE,)), "visible_px": {0: 100} if k >= 2 else {},
                    "confirmed": confirmed, "n_measurements": 1, "n_obstacles": 1})
    return rec


def test_confirmation_delay_is_in_seconds_from_the_first_frame_in_view():
    b = B.score(_record(15), RATE_HZ)["boxes"]["pole"]
    assert b["confirm_delay_s"] == pytest.approx(3 / RATE_HZ)           # maps 2 -> 5 at 15 Hz: 0.2 s
    assert (b["main_id"], b["frames_in_view"], b["id_stability"]) == (1, 10, 1.0)


def test_false_tracks_per_minute_and_on_the_ground():
    # 15 maps at 15 Hz: 1 s of flight (14 intervals and the last map's own 1/15 s), 3 false tracks: 180 a minute;
    # 30 maps: 2 s, 90 a minute. Tracks 21 (0.5 m up) and 22 (below) are ground tracks, 23 (20 m up) is not
    for n, per_min in ((15, 180.0), (30, 90.0)):
        s = B.score(_record(n), RATE_HZ)
        assert s["minutes"] == pytest.approx(n / RATE_HZ / 60.0) and s["maps"] == n
        assert (s["false_confirmed"], s["false_ground"]) == (3, 2)
        assert s["false_per_min"] == pytest.approx(per_min)


def test_box_distance_turns_the_point_into_a_yawed_boxs_own_frame():
    # a 10 x 2 m box yawed 30 deg (the flights' trucks and vans are yawed -30 to 5 deg): 4.5 m out along its long
    # axis, (3.897, 2.25) m north-east of its centre, lies inside it (0); 4 m out along its short axis, (-2, 3.464) m,
    # is 3 m off its long face. Turning the point by the yaw instead of back (R for R^T) puts the first 2.9 m out
    box = Box("truck", (50.0, 10.0, -1.0), (10.0, 2.0, 2.0), np.radians(30.0))
    c = np.array(box.center_ned_m)
    assert B.box_distance(box, c + [4.5 * np.cos(np.radians(30)), 4.5 * np.sin(np.radians(30)), 0.0]) == pytest.approx(
        0.0, abs=1e-9)
    assert B.box_distance(box, c + [-2.0, 2.0 * np.sqrt(3.0), 0.0]) == pytest.approx(3.0)
    assert B.box_distance(box, c + [0.0, 0.0, -4.0]) == pytest.approx(3.0)          # 3 m above its top


def test_a_track_is_near_a_box_within_5_percent_of_its_distance_from_the_vehicle():
    # the vehicle at north 1000 m (the NED origin is the flight's start, 1 km behind): a track 3 m off a pole 40 m
    # ahead is false (tolerance max(2 m, 5 % of 43 m) = 2.15 m), one 3 m off a pole 80 m ahead is near it (4.15 m).
    # Measuring the 5 % from the NED origin (~1 km) would take both as near
    near_pole = Box.on_ground("p40", 1040.0, 0.0, 0.3, 0.3, 10.0)        # north faces at 1040.15 and 1080.15
    far_pole = Box.on_ground("p80", 1080.0, 0.0, 0.3, 0.3, 10.0)
    st = VehicleState.from_ypr([1000.0, 0.0, -6.0], [0.0, 0.0, 0.0])
    tracks = [(31, np.array([1043.15, 0.0, -5.0]), np.zeros(3)), (32, np.array([1083.15, 0.0, -5.0]), np.zeros(3))]
    rec = [{"stamp_us": int(round(k / RATE_HZ * 1e6)), "state": st, "visible_px": {},
            "scene": SimpleNamespace(boxes=(near_pole, far_pole)), "confirmed": tracks, "n_measurements": 2,
            "n_obstacles": 2} for k in range(3)]
    s = B.score(rec, RATE_HZ)
    assert s["false_confirmed"] == 1 and s["false_ground"] == 0


def test_the_frames_without_the_main_id_are_split_by_cause():
    # the pole in view in 11 maps (tolerance max(2 m, 5 % of 60 m) = 3 m): track 1 on it in maps 0-4 and 10 (the
    # main id, 6 of 11); map 5: 1 live 10 m off the pole (off); 6: 1 gone, 2 on the pole (another id); 7, 8: no track
    # (none); 9: 1 live off and 2 on it (off: the main track is live). Measured within the tolerance in maps 0-4
    off = np.array([70.0, 0.0, -5.0])
    maps = [[(1, ON_POLE)]] * 5 + [[(1, off)], [(2, ON_POLE)], [], [], [(1, off), (2, ON_POLE)], [(1, ON_POLE)]]
    rec = [{"stamp_us": int(round(k / RATE_HZ * 1e6)), "state": HOVER, "scene": SimpleNamespace(boxes=(POLE,)),
            "visible_px": {0: 100}, "confirmed": [(i, p, np.zeros(3)) for i, p in tr], "n_measurements": 1,
            "n_obstacles": 1, "measured": [ON_POLE] if k < 5 else [off]} for k, tr in enumerate(maps)]
    b = B.score(rec, RATE_HZ)["boxes"]["pole"]
    assert (b["main_id"], b["frames_in_view"], b["ids_used"]) == (1, 11, 2)
    assert b["id_stability"] == pytest.approx(6 / 11)
    assert (b["main_off"], b["main_gone_other"], b["main_gone_none"]) == (2, 1, 2)
    assert b["measured"] == 5
