"""The obstacle service's handling of one range map (services/obstacles.py, ``process_map``) in process: a Node whose
session records every put, a range map of a wall 20 m ahead of a level camera 10 m up (closed-form geometry, the
helpers of tests/test_obstacles.py), and a MAVLink sender that records what it is given. Checked: which pose the
autopilot's sectors are measured from (the latest nav pose only when it is newer than the map and on its timeline),
the freshness rules at arrival and at publishing (docs/bus.md, Staleness), the order of the two messages a map
makes, what the tracker is told each map could see, and the vehicle pose the track message gives. The same service as
a real process: tests/test_locator_service.py."""
from __future__ import annotations

import argparse
import logging
import time
from types import SimpleNamespace

import numpy as np
import pytest

from eonav.bus import keys as K
from eonav.bus import schema
from eonav.bus.freshness import FreshnessGate
from eonav.bus.node import Node
from eonav.geometry.camera import VehicleState
from eonav.obstacles import detect as ob
from eonav.ranging.rangemap import AT_INFINITY, VALID
from eonav.services import obstacles as O
from eonav.services.locator import CameraCache
from test_locator_service import RecordingSession
from test_obstacles import ALT_M, CAM, CFG, add_wall, ground_and_sky

AHEAD = 4            # the sector whose centre is straight ahead: angle_offset -20 deg, increment 5 deg


class RecordingSender:
    """Stands in for ObstacleDistanceSender: the sectors handed over, as (sectors, stamp_us, source)."""
    send_3d = False

    def __init__(self):
        self.updates = []

    def update(self, sectors, stamp_us, source=""):
        self.updates.append((sectors, stamp_us, source))


def wall_map(stamp_us: int, camera_id: str = "nose", seq: int = 1, wall: bool = True) -> SimpleNamespace:
    """A received sample: the range map of flat ground 10 m below a level camera at NED (0, 0, -10) and a wall 20 m
    ahead over the middle quarter of the columns (straight ahead included); ``wall`` False: ground and sky only."""
    r = add_wall(ground_and_sky(), 20.0, 96, 160) if wall else ground_and_sky()
    payload = schema.encode(
        "range_map", camera_id=camera_id, seq=seq, stamp_us=stamp_us, method="synthetic", range_m=r,
        confidence=np.ones(r.shape, np.float16), flags=np.where(np.isfinite(r), VALID, AT_INFINITY).astype(np.uint8),
        inv_range_std_per_m=np.full(r.shape, 1e-4, np.float16), camera=schema.camera_to_msg(CAM),
        position_ned_m=[0.0, 0.0, -ALT_M], q_wxyz=[1.0, 0.0, 0.0, 0.0])
    return SimpleNamespace(key_expr=K.range_map("v", camera_id), payload=SimpleNamespace(to_bytes=lambda: payload))


class Service:
    """``process_map`` with its collaborators: gate clock ``now["us"]`` (max age 1 s), nav, guidance, sender."""

    def __init__(self, no_nav: bool = False, analyse_s: float = 0.0):
        self.t0 = time.time_ns() // 1000
        self.now = {"us": self.t0}
        self.session = RecordingSession()
        self.node = Node("obstacles", argparse.Namespace(vehicle="v", input_grace_s=10.0, health_period_s=1.0),
                         self.session, log=logging.getLogger("test.obstacles_service"))
        self.pub = self.node.publisher(K.obstacles("v"))
        self.nav = O.LatestNav()
        self.guidance = O.Guidance(self.node, self.nav, 10.0, 0.3)
        self.sender = RecordingSender()
        self.args = SimpleNamespace(no_nav=no_nav,
                                    _freshness=FreshnessGate(1.0, clock_us=lambda: self.now["us"]))
        self.cameras = CameraCache()

        def analyse(*a, **kw):               # the analysis taking ``analyse_s`` on the gate's clock
            self.now["us"] += int(analyse_s * 1e6)
            return ob.analyse(*a, **kw)
        self.ob = SimpleNamespace(analyse=analyse)

    def nav_at(self, stamp_us: int, north_m: float) -> None:
        """A whole nav pose: level, at NED (north_m, 0, -10)."""
        assert self.nav.add(stamp_us, [1.0, 0.0, 0.0, 0.0], [north_m, 0.0, -ALT_M], [20.0, 0.0, 0.0])

    def map(self, sample) -> None:
        O.process_map(self.node, sample, self.pub, CFG, self.guidance, self.nav, self.sender, self.args,
                      self.cameras, self.ob, VehicleState)

    def lists(self) -> list:
        return [schema.decode(p, expect="obstacle_list") for k, p in self.session.puts if k == K.obstacles("v")]


def test_sectors_for_the_autopilot_come_from_a_newer_nav_pose_never_an_older_one():
    """The autopilot applies OBSTACLE_DISTANCE where the vehicle is on arrival: a nav pose 0.3 s newer than the map
    and 10 m nearer the wall gives 10 m straight ahead (``mavlink.nav_compensated``); a nav pose older than the map,
    or more than NAV_MAX_AHEAD_S newer (another timeline), is not used: the capture pose's 20 m
    (``mavlink.capture_pose``). The obstacle list is the capture pose's in every case."""
    cases = ((+300_000, 1000, "mavlink.nav_compensated"), (-300_000, 2000, "mavlink.capture_pose"),
             (+1_200_000, 2000, "mavlink.capture_pose"), (+1_000_000, 1000, "mavlink.nav_compensated"))
    for dt_us, want_cm, counter in cases:
        svc = Service()
        svc.nav_at(svc.t0 + dt_us, 10.0)
        svc.map(wall_map(svc.t0))
        (sectors, stamp, source), = svc.sender.updates
        assert (stamp, source) == (svc.t0, "nose")
        assert sectors.distances_cm[AHEAD] == pytest.approx(want_cm, abs=5), dt_us
        assert svc.node.counters()[counter] == 1, dt_us
        o, = svc.lists()[0]["obstacles"]
        assert o["horizontal_distance_m"] == pytest.approx(20.0, abs=0.05)


def test_a_map_gone_stale_during_its_analysis_is_not_published():
    """Fresh on arrival (age 0) but 1.2 s old once analysed (max age 1 s): no obstacle list, no track message, no
    sectors for the autopilot, counted ``dropped.too_old``; a map analysed within the limit goes out."""
    svc = Service(analyse_s=1.2)
    svc.map(wall_map(svc.t0))
    c = svc.node.counters()
    assert svc.session.puts == [] and svc.sender.updates == []
    assert c["dropped.too_old"] == 1 and "maps_processed" not in c
    ok = Service(analyse_s=0.9)
    ok.map(wall_map(ok.t0))
    assert len(ok.lists()) == 1 and len(ok.sender.updates) == 1 and "dropped.too_old" not in ok.node.counters()


def test_an_older_map_of_a_camera_after_a_newer_one_is_dropped():
    """A camera's obstacle lists never go back in time: after the map of t0 is published, that camera's map of
    t0 - 100 ms (late, e.g. a replay that started over) is dropped (``dropped.out_of_order``); another camera's map
    of the same older stamp, and the first camera's next map, go out."""
    svc = Service()
    svc.map(wall_map(svc.t0, seq=2))
    svc.map(wall_map(svc.t0 - 100_000, seq=1))
    svc.map(wall_map(svc.t0 - 100_000, "left", seq=1))
    svc.map(wall_map(svc.t0 + 100_000, seq=3))
    assert [(m["camera_id"], m["stamp_us"]) for m in svc.lists()] == [
        ("nose", svc.t0), ("left", svc.t0 - 100_000), ("nose", svc.t0 + 100_000)]
    assert svc.node.counters()["dropped.out_of_order"] == 1 and len(svc.sender.updates) == 3


def test_the_obstacle_list_goes_out_before_the_track_message_that_labels_it():
    """Each map makes an obstacle list and then a track message built on it (its ``map_stamp_us``): guidance reads
    the track ids the list's obstacles carry, so the list must be out first. Five maps of the wall, 100 ms apart:
    the wall is labelled with one track id throughout, the track confirmed in the later messages."""
    from eonav.bus import guidance_msg
    svc = Service()
    for k in range(5):
        svc.now["us"] = svc.t0 + k * 100_000
        svc.map(wall_map(svc.now["us"], seq=k + 1))
    keys = [k for k, _ in svc.session.puts]
    assert keys == [K.obstacles("v"), K.obstacle_tracks("v")] * 5
    lists = [schema.decode(p, expect="obstacle_list") for _, p in svc.session.puts[0::2]]
    tracks = [guidance_msg.decode(p) for _, p in svc.session.puts[1::2]]
    assert [m["map_stamp_us"] for m in tracks] == [m["stamp_us"] for m in lists]
    ids = {o["id"] for m in lists for o in m["obstacles"]}
    assert len(ids) == 1 and 0 not in ids
    assert [t["id"] for t in tracks[-1]["tracks"]] == list(ids)


def test_a_tracked_wall_that_gives_way_to_open_sky_is_missed_and_dropped():
    """Each map tells the tracker what it could see (its camera and pose, the distances from ``min_distance_m`` to
    ``max_obstacle_distance_m``): the wall 20 m ahead, tracked over five maps, then gone from maps that see open sky
    and ground where it stood, is missed once per map while still listed ("confirmed", not "coasting" as a track out
    of view would be) and is no longer published after TrackerConfig.max_misses (6) such maps."""
    from eonav.bus import guidance_msg
    from eonav.obstacles.tracking import TrackerConfig
    svc = Service()
    gone = TrackerConfig().max_misses
    assert gone == 6
    for k in range(5 + gone):
        svc.now["us"] = svc.t0 + k * 100_000
        svc.map(wall_map(svc.now["us"], seq=k + 1, wall=k < 5))
    tracks = [guidance_msg.decode(p)["tracks"] for key, p in svc.session.puts if key == K.obstacle_tracks("v")]
    assert [(t["state"], t["hits"], t["misses"]) for t, in tracks[4:5 + gone - 1]] == [
        ("confirmed", 5, m) for m in range(gone)]
    assert tracks[-1] == []


def test_the_track_message_describes_the_vehicle_by_the_latest_nav_pose_and_its_stamp(monkeypatch):
    """Guidance's track message gives the vehicle of the latest nav pose (0.3 s newer than the map, 10 m north,
    20 m/s north) with that pose's stamp (``nav_stamp_us``), carried on by its velocity to the message's time: the
    message of t0 + 0.5 s puts the vehicle at 10 + 20 x 0.2 = 14 m north, not 10 + 20 x 0.5 as if the pose were the
    map's capture time."""
    from eonav.bus import guidance_msg
    svc = Service()
    svc.nav_at(svc.t0 + 300_000, 10.0)
    monkeypatch.setattr(O, "now_us", lambda: svc.t0 + 500_000)       # the service's clock when the message is made
    svc.map(wall_map(svc.t0))
    m, = [guidance_msg.decode(p) for key, p in svc.session.puts if key == K.obstacle_tracks("v")]
    assert (m["stamp_us"], m["map_stamp_us"], m["nav_stamp_us"]) == (svc.t0 + 500_000, svc.t0, svc.t0 + 300_000)
    np.testing.assert_allclose(m["position_ned_m"], [14.0, 0.0, -ALT_M], atol=1e-9)
    np.testing.assert_allclose(m["velocity_ned_mps"], [20.0, 0.0, 0.0])


def test_a_map_too_old_on_arrival_is_neither_analysed_nor_counted_as_input():
    """A range map already 1.5 s old on arrival (max age 1 s) is dropped before the analysis (``dropped.too_old``,
    no analysis time spent on it, nothing published) and does not count as the "range maps" input flowing: a stream of
    nothing but stale maps leaves the input silent, so the service reports degraded (Node.input_seen). A fresh map
    then does both."""
    svc = Service()
    calls = []
    analyse = svc.ob.analyse
    svc.ob.analyse = lambda *a, **kw: calls.append(1) or analyse(*a, **kw)
    t = time.monotonic()
    svc.node.expect_input("range maps", 1.0, grace_s=1.0, now=t - 10.0)       # watched for 10 s, nothing yet
    svc.map(wall_map(svc.t0 - 1_500_000))
    assert svc.node.counters()["dropped.too_old"] == 1 and svc.session.puts == [] and svc.sender.updates == []
    assert calls == []
    svc.node.check_inputs()
    assert svc.node.silent_inputs() != []
    svc.map(wall_map(svc.t0))
    assert calls == [1] and len(svc.lists()) == 1
    svc.node.check_inputs()
    assert svc.node.silent_inputs() == []


def test_the_track_topic_ticks_on_its_timer_and_tells_how_old_its_newest_map_is():
    """Guidance's fixed-rate messages (``Guidance.timer_loop``, 10 Hz here): with no vehicle state to describe (no
    navigation, no map) nothing is sent; with a nav pose and no map yet, "timer" messages with status "no_map", no map
    stamp (-1), an infinite map age, the nav pose's stamp and its position carried at its velocity (20 m/s north) to
    the message's time, seq rising by one, never more of them than
    the rate allows; after a map, every timer message refers to it, its age the message stamp minus the map's capture
    stamp, its status "ok" up to stale_after_s (0.3 s) and "stale" beyond (a stall guidance can see), until it is
    stopped. Waits on what arrives (20 s at most), not on fixed sleeps."""
    import threading

    from eonav.bus import guidance_msg
    from eonav.bus.node import now_us
    svc = Service()

    def timer_msgs():                                                  # (of the first 200 puts: a runaway loop
        puts = svc.session.puts[:200]                                  # fails the waits below, not the machine)
        return [m for m in (guidance_msg.decode(p) for k, p in puts if k == K.obstacle_tracks("v"))
                if m["trigger"] == "timer"]

    def wait_for(cond):
        deadline = time.monotonic() + 20.0
        while not cond() and time.monotonic() < deadline:
            threading.Event().wait(0.01)
        assert cond()

    loop = threading.Thread(target=svc.guidance.timer_loop)
    t_start = now_us()
    loop.start()
    try:
        threading.Event().wait(0.25)
        assert svc.session.puts == []                                  # nothing to describe yet
        nav_us = now_us()
        svc.nav_at(nav_us, 5.0)
        wait_for(lambda: len(timer_msgs()) >= 3)
        first = timer_msgs()
        for m in first:
            assert (m["status"], m["map_stamp_us"], m["map_age_s"]) == ("no_map", -1, float("inf"))
            dt_s = (m["stamp_us"] - nav_us) * 1e-6                   # the vehicle carried to the message's time
            assert m["nav_stamp_us"] == nav_us and m["position_ned_m"] == pytest.approx([5.0 + 20.0 * dt_s, 0.0, -ALT_M])
        assert [m["seq"] for m in first] == list(range(first[0]["seq"], first[0]["seq"] + len(first)))
        map_us = svc.now["us"] = now_us()
        svc.map(wall_map(map_us))
        wait_for(lambda: any(m["status"] == "stale" for m in timer_msgs()))
    finally:
        svc.node.stop_event.set()
        loop.join(5)
    assert not loop.is_alive()
    msgs = timer_msgs()
    map_msg, = [guidance_msg.decode(p) for k, p in svc.session.puts[:200]
                if k == K.obstacle_tracks("v") and guidance_msg.decode(p)["trigger"] == "map"]
    after = [m for m in msgs if m["seq"] > map_msg["seq"]]           # built after the tracker took the map
    assert after and all(m["map_stamp_us"] == map_us for m in after)
    for m in after:
        assert m["map_age_s"] == pytest.approx((m["stamp_us"] - map_us) * 1e-6, abs=1e-9)
        assert m["status"] == ("ok" if m["map_age_s"] <= 0.3 else "stale"), m["map_age_s"]
    elapsed_s = (msgs[-1]["stamp_us"] - t_start) * 1e-6
    assert len(msgs) <= elapsed_s / 0.1 + 1                            # never faster than the rate
