"""OBSTACLE_DISTANCE_3D of the confirmed tracks (eonav.nav.mavlink_out): the body-frame point of each track against
hand-computed coordinates for yawed and pitched vehicles, the wire bytes through pymavlink's own parser, and the
sender's cycle (order, the end message, both sides of its thresholds, a stall) over a real UDP socket."""
import contextlib
import math
import os
import socket
import time

os.environ["MAVLINK20"] = "1"

import numpy as np
import pytest

from eonav import InputError
from eonav.geometry.camera import VehicleState
from eonav.nav import mavlink_out as mo
from eonav.obstacles.detect import N_SECTORS, Sectors

VEHICLE_NED = np.array([10.0, 20.0, -5.0])


def pose(yaw_deg=0.0, pitch_deg=0.0, roll_deg=0.0, position=VEHICLE_NED):
    return VehicleState.from_ypr(position, [math.radians(yaw_deg), math.radians(pitch_deg), math.radians(roll_deg)])


def track(id_, offset_ned, extent=(0.0, 0.0, 0.0), velocity=(0.0, 0.0, 0.0), moving=False):
    """An entry of the obstacle-track message's ``tracks`` at ``offset_ned`` from the vehicle."""
    return {"id": id_, "position_ned_m": VEHICLE_NED + np.asarray(offset_ned, float), "extent_ned_m": list(extent),
            "velocity_ned_mps": list(velocity), "moving": moving}


def frd(t, state, dt_s=0.0):
    return mo.nearest_point_frd(mo.TrackBox.from_track_msg(t), state.position_ned_m, state.T_body_ned, dt_s)


def test_nearest_point_in_body_frd_for_a_yawed_vehicle():
    # heading 30 deg: a point due east (bearing 90) is 60 deg right of the nose: (10 cos 60, 10 sin 60, 0)
    s = pose(yaw_deg=30.0)
    np.testing.assert_allclose(frd(track(1, (0, 10, 0)), s), [5.0, 10 * math.sin(math.radians(60)), 0.0], atol=1e-9)
    # a 2 m cube centred there: its nearest point is 9 m east (the vehicle is within its north and down spans)
    np.testing.assert_allclose(frd(track(1, (0, 10, 0), (2, 2, 2)), s), [4.5, 9 * math.sin(math.radians(60)), 0.0],
                               atol=1e-9)
    # 4 m above the vehicle, bottom face 1 m below the centre: down -3 (FRD z is down, unchanged by a yaw)
    np.testing.assert_allclose(frd(track(1, (0, 10, -4), (2, 2, 2)), s),
                               [4.5, 9 * math.sin(math.radians(60)), -3.0], atol=1e-9)
    # heading -90 (west): a point north is 90 deg right
    np.testing.assert_allclose(frd(track(1, (7, 0, 0)), pose(yaw_deg=-90.0)), [0.0, 7.0, 0.0], atol=1e-9)


def test_nearest_point_in_body_frd_for_a_pitched_and_rolled_vehicle():
    # nose up 20 deg: a level point 10 m ahead is below the nose (z down > 0)
    np.testing.assert_allclose(frd(track(1, (10, 0, 0)), pose(pitch_deg=20.0)),
                               [10 * math.cos(math.radians(20)), 0.0, 10 * math.sin(math.radians(20))], atol=1e-9)
    # rolled 90 deg right (right wing down): a point 5 m below the vehicle is on its right (y > 0)
    np.testing.assert_allclose(frd(track(1, (0, 0, 5)), pose(roll_deg=90.0)), [0.0, 5.0, 0.0], atol=1e-9)


def test_nearest_point_inside_the_box_is_its_centre_and_moving_tracks_are_carried():
    s = pose()
    np.testing.assert_allclose(frd(track(1, (0.5, 0, 0), (4, 4, 4)), s), [0.5, 0, 0], atol=1e-12)
    # moving at 2 m/s west, 0.5 s later: 1 m nearer on east
    t = track(1, (0, 10, 0), velocity=(0, -2, 0), moving=True)
    np.testing.assert_allclose(frd(t, s, dt_s=0.5), [0, 9, 0], atol=1e-12)
    t["moving"] = False                                  # a velocity the tracker does not call moving is not used
    np.testing.assert_allclose(frd(t, s, dt_s=0.5), [0, 10, 0], atol=1e-12)


def test_points_range_order_limit_ids_and_the_middle_layer():
    s = pose()
    ts = [track(7, (39.9, 0, 0)), track(8, (40.1, 0, 0)), track(9, (0.2, 0, 0)), track(65535 + 4, (5, 0, 0))]
    boxes = [mo.TrackBox.from_track_msg(t) for t in ts]
    pts = mo.obstacle_points_frd(boxes, s.position_ned_m, s.T_body_ned, 0.5, 40.0)
    assert [i for i, _ in pts] == [9, 4, 7]              # nearest first; 40.1 m dropped; id modulo 65535
    np.testing.assert_allclose(pts[0][1], [0.5, 0, 0])    # 0.2 m is reported at min_distance, same direction
    assert [i for i, _ in mo.obstacle_points_frd(boxes, s.position_ned_m, s.T_body_ned, 0.5, 40.0, limit=2)] == [9, 4]
    # off the middle layer: elevation 15.1 deg kept, 14.9 deg and level dropped, below kept
    e = [track(i, (10, 0, -10 * math.tan(math.radians(a)))) for i, a in ((1, 15.1), (2, 14.9), (3, 0.0), (4, -16.0))]
    boxes = [mo.TrackBox.from_track_msg(t) for t in e]
    kept = mo.obstacle_points_frd(boxes, s.position_ned_m, s.T_body_ned, 0.5, 40.0, off_middle_layer=True)
    assert sorted(i for i, _ in kept) == [1, 4]
    assert mo.elevation_deg(kept[[i for i, _ in kept].index(1)][1]) == pytest.approx(15.1)


def test_obstacle_distance_3d_bytes_through_pymavlink():
    mu = mo.mavutil()
    b = mo.encode_obstacle_distance_3d(321, (4.5, -7.25, -3.0), 123456, 0.5, 40.0, system_id=7, seq=9)
    parser = mu.mavlink.MAVLink(None)
    msgs = parser.parse_buffer(b)
    assert len(msgs) == 1
    m = msgs[0]
    assert m.get_type() == "OBSTACLE_DISTANCE_3D" and m.get_msgId() == 11037 and b[0] == 0xFD   # MAVLink 2
    assert (m.get_srcSystem(), m.get_srcComponent(), m.get_seq()) == (7, 191, 9)
    assert (m.time_boot_ms, m.obstacle_id, m.frame, m.sensor_type) == (123456, 321, 12, 4)
    assert (m.x, m.y, m.z, m.min_distance, m.max_distance) == (4.5, -7.25, -3.0, 0.5, 40.0)   # exact in float32


def test_bad_3d_input_is_refused():
    with pytest.raises(InputError, match="min_distance_m < max_distance_m"):
        mo.encode_obstacle_distance_3d(1, (1, 0, 0), 1, 5.0, 5.0)
    with pytest.raises(InputError, match="finite"):
        mo.encode_obstacle_distance_3d(1, (1, float("nan"), 0), 1, 0.5, 40.0)
    with pytest.raises(InputError, match="obstacle_id"):
        mo.encode_obstacle_distance_3d(65536, (1, 0, 0), 1, 0.5, 40.0)
    with pytest.raises(InputError, match="extent_ned_m"):
        mo.TrackBox.from_track_msg({"id": 1, "position_ned_m": [0, 0], "extent_ned_m": [0, 0, 0],
                                    "velocity_ned_mps": [0, 0, 0]})
    with pytest.raises(InputError, match="expected one of"):
        mo.ObstacleDistanceSender("udpout:127.0.0.1:9", messages="obstacle_distance_2d")


def _free_udp_port():
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def _sectors():
    d = np.full(N_SECTORS, 4001, np.uint16)
    d[4] = 1234
    return Sectors(d, 5.0, -20.0, 50, 4000)


class Rx:
    def __init__(self, port):
        self.conn = mo.mavutil().mavlink_connection(f"udpin:127.0.0.1:{port}")

    def drain(self):
        out = []
        deadline = time.time() + 1.0
        while time.time() < deadline:
            m = self.conn.recv_match(blocking=True, timeout=0.2)
            if m is None:
                break
            if m.get_type() != "HEARTBEAT":
                out.append(m)
        return out


@contextlib.contextmanager
def sender_to_rx(**kw):
    """An ``ObstacleDistanceSender`` to a loopback UDP port with an injected clock (``t[0]``, seconds) and its
    receiving end (``Rx``): yields (tx, t, rx); both closed after."""
    port = _free_udp_port()
    rx = Rx(port)
    t = [0.0]
    tx = mo.ObstacleDistanceSender(f"udpout:127.0.0.1:{port}", clock=lambda: t[0], **kw)
    try:
        yield tx, t, rx
    finally:
        tx.close()
        rx.conn.close()


@pytest.mark.parametrize("messages", ["obstacle_distance_3d", "both"])
def test_sender_cycle_end_message_and_stall(messages):
    s = pose(yaw_deg=30.0)
    tracks = [track(5, (0, 10, -4), (2, 2, 2)), track(6, (20, 0, 0)), track(7, (3, 0, 1.5))]
    with sender_to_rx(wall_us=lambda: 1_000_000, messages=messages) as (tx, t, rx):
        tx.tick()                                      # t = 0: heartbeat only, nothing known yet
        assert rx.drain() == []
        tx.update(_sectors(), 1_000_000)
        tx.update_tracks(tracks, 1_000_000, s.position_ned_m, s.T_body_ned, 0.5, 40.0)
        t[0] = 0.1
        tx.tick()
        got = rx.drain()
        types = [m.get_type() for m in got]
        both = messages == "both"
        d3 = [m for m in got if m.get_type() == "OBSTACLE_DISTANCE_3D"]
        if both:                                       # OBSTACLE_DISTANCE first (ArduPilot resets on it)
            assert types[0] == "OBSTACLE_DISTANCE" and types.count("OBSTACLE_DISTANCE") == 1
            assert [m.obstacle_id for m in d3] == [7, 5, 65535]    # level track 6 left to OBSTACLE_DISTANCE
        else:
            assert "OBSTACLE_DISTANCE" not in types
            assert [m.obstacle_id for m in d3] == [7, 5, 6, 65535]   # nearest first, then the end message
        by_id = {m.obstacle_id: m for m in d3}
        np.testing.assert_allclose([by_id[5].x, by_id[5].y, by_id[5].z], [4.5, 9 * math.sin(math.radians(60)), -3.0],
                                   atol=1e-5)
        # track 7: 3 m north, 1.5 m below; heading 30 deg: (3 cos 30, -3 sin 30, 1.5)
        np.testing.assert_allclose([by_id[7].x, by_id[7].y, by_id[7].z],
                                   [3 * math.cos(math.radians(30)), -1.5, 1.5], atol=1e-5)
        stamps = {m.time_boot_ms for m in d3 if m.obstacle_id != 65535}
        end = by_id[65535]
        assert len(stamps) == 1 and end.time_boot_ms == stamps.pop() + 1     # one stamp a cycle, the end's + 1
        assert (end.x, end.y, end.z, end.max_distance, end.min_distance) == (41.0, 0.0, 0.0, 40.0, 0.5)
        assert all(m.frame == 12 for m in d3)
        # next cycle: a new stamp
        t[0] = 0.2
        tx.tick()
        d3b = [m for m in rx.drain() if m.get_type() == "OBSTACLE_DISTANCE_3D"]
        assert min(m.time_boot_ms for m in d3b) >= end.time_boot_ms + 99
        # no confirmed track: the end message alone (ArduPilot stays healthy with nothing tracked)
        t[0] = 0.25
        tx.update(_sectors(), 1_100_000)
        tx.update_tracks([], 1_100_000, s.position_ned_m, s.T_body_ned, 0.5, 40.0)
        t[0] = 0.31
        tx.tick()
        d3c = [m for m in rx.drain() if m.get_type() == "OBSTACLE_DISTANCE_3D"]
        assert [m.obstacle_id for m in d3c] == [65535]
        # 0.29 s after the update (stale_s 0.3): still sent; 0.4 s: stale, the OBSTACLE_DISTANCE flush (both) only
        t[0] = 0.54
        tx.tick()
        assert [m.obstacle_id for m in rx.drain() if m.get_type() == "OBSTACLE_DISTANCE_3D"] == [65535]
        t[0] = 0.65
        tx.tick()
        got = rx.drain()
        assert [m.get_type() for m in got] == (["OBSTACLE_DISTANCE"] if both else [])
        if both:
            assert set(got[0].distances) == {65535}
        for now in (0.75, 0.85, 0.95):                 # then silence
            t[0] = now
            tx.tick()
        assert rx.drain() == []
        assert tx.counters["od3d_sent_end"] == 4 and tx.counters["od3d_sent"] == (4 if both else 6)


def test_sender_carries_a_moving_track_by_the_age_of_the_tracks():
    """The tracks were stamped 0.25 s before the send (wall clock in µs): a track moving 2 m/s west is sent 0.5 m
    nearer on east, a static one where it was; both against hand-computed points of a vehicle heading north."""
    s = pose()
    tracks = [track(5, (0, 10, 0), velocity=(0, -2, 0), moving=True), track(6, (12, 0, 0), velocity=(3, 0, 0))]
    with sender_to_rx(wall_us=lambda: 1_250_000, messages="obstacle_distance_3d") as (tx, t, rx):
        tx.update_tracks(tracks, 1_000_000, s.position_ned_m, s.T_body_ned, 0.5, 40.0)
        t[0] = 0.1
        tx.tick()
        by_id = {m.obstacle_id: m for m in rx.drain()}
        assert sorted(by_id) == [5, 6, 65535]
        np.testing.assert_allclose([by_id[5].x, by_id[5].y, by_id[5].z], [0.0, 9.5, 0.0], atol=1e-5)
        np.testing.assert_allclose([by_id[6].x, by_id[6].y, by_id[6].z], [12.0, 0.0, 0.0], atol=1e-5)


def test_sender_does_not_carry_a_track_back_when_the_wall_clock_is_behind_its_stamp():
    """The wall clock reads 0.25 s BEFORE the tracks' stamp (stepped back by a time sync, or the tracks stamped on a
    clock ahead): a track moving 2 m/s west is sent where it was measured (10 m east), not 0.5 m back along its
    velocity (catches the clamp of the tracks' age at 0 dropped)."""
    s = pose()
    with sender_to_rx(wall_us=lambda: 750_000, messages="obstacle_distance_3d") as (tx, t, rx):
        tx.update_tracks([track(5, (0, 10, 0), velocity=(0, -2, 0), moving=True)], 1_000_000, s.position_ned_m,
                         s.T_body_ned, 0.5, 40.0)
        t[0] = 0.1
        tx.tick()
        by_id = {m.obstacle_id: m for m in rx.drain()}
        assert sorted(by_id) == [5, 65535]
        np.testing.assert_allclose([by_id[5].x, by_id[5].y, by_id[5].z], [0.0, 10.0, 0.0], atol=1e-5)


def test_a_moving_track_without_a_finite_velocity_is_sent_where_it_is():
    """A track entry marked moving whose velocity is not finite (NaN: unknown) is carried by no velocity: its point
    is the measured one, finite, and encodes; a NaN point would raise InputError inside the sender's tick, which
    only survives OSError (catches the finite-velocity fallback of TrackBox.from_track_msg dropped)."""
    s = pose()
    box = mo.TrackBox.from_track_msg(track(3, (0, 10, 0), (2, 2, 2), velocity=(math.nan, -2.0, 0.0), moving=True))
    np.testing.assert_array_equal(box.velocity_ned_mps, [0.0, 0.0, 0.0])
    (oid, p), = mo.obstacle_points_frd([box], s.position_ned_m, s.T_body_ned, 0.5, 40.0, dt_s=0.5)
    assert oid == 3
    np.testing.assert_allclose(p, [0.0, 9.0, 0.0], atol=1e-12)      # the box's west face, 9 m east
    mo.encode_obstacle_distance_3d(oid, p, 1, 0.5, 40.0)


def test_sender_obstacle_distance_only_sends_no_3d():
    s = pose()
    with sender_to_rx() as (tx, t, rx):
        tx.update(_sectors(), 1_000_000)
        tx.update_tracks([track(5, (0, 10, -4))], 1_000_000, s.position_ned_m, s.T_body_ned, 0.5, 40.0)
        t[0] = 0.1
        tx.tick()
        assert [m.get_type() for m in rx.drain()] == ["OBSTACLE_DISTANCE"]
        assert "od3d_sent" not in tx.counters


def test_obstacles_service_sends_the_tracks_as_obstacle_distance_3d():
    """The real obstacles service (a process, range maps over a real zenoh session) with ``--mavlink-messages both``
    to a UDP socket: OBSTACLE_DISTANCE, then per cycle OBSTACLE_DISTANCE_3D of the confirmed track above the vehicle
    (the level pole is left to OBSTACLE_DISTANCE) at the nearest point of its published box, and the end message."""
    import sitl
    from eonav.app.processes import free_port, start_service, stop_service
    from eonav.bus import guidance_msg, keys as K
    from eonav.bus.session import endpoint, listener_session
    from eonav.sim.scene import Box, Scene

    port, udp = free_port(), _free_udp_port()
    rx = Rx(udp)
    latest = {}
    state = VehicleState.from_ypr([0.0, 0.0, -5.0], [0.0, 0.0, 0.0])
    scene = Scene(boxes=(sitl.pole("p", 0.0, 9.0, 0.1), Box("above", (6.5, -3.0, -9.5), (1.0, 1.0, 2.0))), runway=None)
    with listener_session(port) as session:
        sub = session.declare_subscriber(K.obstacle_tracks("od3d"), lambda s: latest.__setitem__(
            "m", guidance_msg.decode(s.payload.to_bytes())))
        proc = start_service(["-m", "eonav.services.obstacles", "--vehicle", "od3d", "--connect", endpoint(port),
                              "--ground-down-m", "0", "--no-nav", "--max-distance-m", "40",
                              "--mavlink-out", f"udpout:127.0.0.1:{udp}", "--mavlink-messages", "both"])
        feeder = sitl.MapFeeder(session, K.range_map("od3d", "nose"))
        try:
            feeder.set(scene, sitl.make_camera(0.0), state)
            feeder.resume()
            got, deadline = [], time.monotonic() + 15.0
            while time.monotonic() < deadline:
                got += rx.drain()
                if sum(m.get_type() == "OBSTACLE_DISTANCE_3D" and m.obstacle_id != 65535 for m in got) >= 10:
                    break
        finally:
            feeder.close()
            code, err = stop_service(proc)
            sub.undeclare()
            rx.conn.close()
    assert code == 0, err[-2000:]
    tracks = latest["m"]["tracks"]
    assert len(tracks) == 2
    above = next(t for t in tracks if t["position_ned_m"][2] < -7.0)
    d3 = [m for m in got if m.get_type() == "OBSTACLE_DISTANCE_3D" and m.obstacle_id != 65535]
    assert len(d3) >= 10 and {m.obstacle_id for m in d3} == {above["id"]}     # the level pole is not sent in 3D
    c, half = np.asarray(above["position_ned_m"]), 0.5 * np.asarray(above["extent_ned_m"])
    want = c + np.clip(state.position_ned_m - c, -half, half) - state.position_ned_m     # heading north, level
    np.testing.assert_allclose([d3[-1].x, d3[-1].y, d3[-1].z], want, atol=0.02)
    assert want[2] < -3.0 and want[1] < -2.0                                  # above and to the left
    # each 3D message follows an OBSTACLE_DISTANCE of its cycle and is followed by the end message (stamp + 1)
    for i, m in enumerate(got):
        if m.get_type() == "OBSTACLE_DISTANCE_3D" and m.obstacle_id != 65535 and i + 1 < len(got):
            assert got[i - 1].get_type() == "OBSTACLE_DISTANCE"
            assert got[i + 1].obstacle_id == 65535 and got[i + 1].time_boot_ms == m.time_boot_ms + 1
