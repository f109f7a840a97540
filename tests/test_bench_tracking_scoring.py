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
