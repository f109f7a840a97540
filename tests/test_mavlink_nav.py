"""eonav.nav.mavlink_in: decoding, validation, reboots, clock offsets, tlogs (real bytes through pymavlink)."""
import math
import threading
import time
from collections import Counter
from pathlib import Path

import numpy as np
import pytest

from eonav import InputError
from eonav.geometry.frames import T_body_ned_from_quat, quat_wxyz_from_ypr, ypr_from_T_body_ned
from eonav.nav.mavlink_in import (WGS84_A_M, WGS84_E2, ClockMapper, MinWindowOffset, NavDecoder, NavIngest,
                               TimesyncEstimator, TlogReader, lla_from_ned, mavlink2_dialect, mavutil_v2,
                               ned_from_lla)

ML = mavlink2_dialect()
DATA = Path(__file__).resolve().parents[1].parent / "shared" / "data"
TLOGS = DATA / "tlogs"
COPTER = TLOGS / "arducopter_real_flight_dronekit.tlog"
SUB = TLOGS / "ardusub_real_dive_qgc_mavlink2_small.tlog"
needs_data = pytest.mark.skipif(not COPTER.is_file() or not SUB.is_file(),
                                reason=f"real tlogs not found in {TLOGS} (shared data absent)")


def wire(msg, sysid=1, compid=1):
    """Pack and parse a message as it would arrive on a link (header fields set)."""
    mav = ML.MAVLink(None, srcSystem=sysid, srcComponent=compid)
    return mav.decode(bytearray(msg.pack(mav)))


def att(t_ms, yaw=0.0, pitch=0.0, roll=0.0, **kw):
    return wire(ML.MAVLink_attitude_message(t_ms, roll, pitch, yaw, 0.0, 0.0, 0.0), **kw)


def attq(t_ms, q, **kw):
    return wire(ML.MAVLink_attitude_quaternion_message(t_ms, *q, 0.0, 0.0, 0.0, [0, 0, 0, 0]), **kw)


def lpos(t_ms, p, v=(0, 0, 0), **kw):
    return wire(ML.MAVLink_local_position_ned_message(t_ms, *p, *v), **kw)


def gpos(t_ms, lat, lon, alt_m, v_cms=(0, 0, 0), **kw):
    return wire(ML.MAVLink_global_position_int_message(t_ms, int(round(lat * 1e7)), int(round(lon * 1e7)),
                                                       int(round(alt_m * 1000)), 0, *v_cms, 0), **kw)


def yaw_of(q):
    return ypr_from_T_body_ned(T_body_ned_from_quat(q))[0]


# ----------------------------------------------------------------------------- decoding
def test_attitude_to_quaternion_hand_values():
    d = NavDecoder()
    s = d.decode(att(1000, yaw=math.pi / 2))
    np.testing.assert_allclose(s.q_wxyz, [math.cos(math.pi / 4), 0, 0, math.sin(math.pi / 4)], atol=1e-7)
    assert s.autopilot_time_us == 1_000_000 and s.msg_type == "ATTITUDE" and s.position_ned_m is None
    # pitch 10 deg: rotation about body Y: q = [cos 5, 0, sin 5, 0]
    s = d.decode(att(1020, pitch=math.radians(10)))
    np.testing.assert_allclose(s.q_wxyz, [math.cos(math.radians(5)), 0, math.sin(math.radians(5)), 0], atol=1e-7)


def test_attitude_quaternion_validation():
    d = NavDecoder()
    q = quat_wxyz_from_ypr(0.3, -0.1, 0.2)
    s = d.decode(attq(10, q))
    np.testing.assert_allclose(s.q_wxyz, q, atol=1e-6)
    assert d.decode(attq(20, [1.0, 0.1, 0, 0])) is None          # |q| = 1.005
    assert d.decode(attq(30, [math.nan, 0, 0, 1])) is None
    assert d.decode(attq(40, [math.inf, 0, 0, 1])) is None
    assert d.decode(att(50, roll=math.nan)) is None
    assert d.decode(att(60, pitch=2.0)) is None                   # |pitch| > 90 deg
    assert d.rejected == Counter({"quat_not_unit": 1, "attitude_nonfinite": 3, "attitude_out_of_range": 1})
    assert d.counts["ATTITUDE_QUATERNION"] == 1


def test_attitude_range_limits_roll_and_yaw_pi_pitch_half_pi():
    """ATTITUDE's range check: roll and yaw span [-pi, pi], pitch [-pi/2, pi/2]. A steep bank past 90 deg (roll
    115 deg: aerobatics, a fixed wing in a hard turn, a copter upset) is a valid attitude and must be kept; roll
    beyond pi is out of range. Hand values: a roll-only rotation r about body x is q = [cos r/2, sin r/2, 0, 0]."""
    d = NavDecoder()
    s = d.decode(att(100, roll=2.0))
    assert s is not None, d.rejected
    np.testing.assert_allclose(s.q_wxyz, [math.cos(1.0), math.sin(1.0), 0, 0], atol=1e-7)
    s = d.decode(att(120, yaw=-3.1))                              # heading just short of south, the other way
    np.testing.assert_allclose(s.q_wxyz, [math.cos(1.55), 0, 0, -math.sin(1.55)], atol=1e-7)
    assert d.decode(att(140, roll=3.2)) is None                  # |roll| > pi
    assert d.decode(att(160, yaw=-3.2)) is None                  # |yaw| > pi
    assert d.decode(att(180, pitch=1.6)) is None                 # |pitch| > pi/2
    assert d.rejected == Counter({"attitude_out_of_range": 3})


def test_attitude_at_exactly_its_range_limits_is_kept_after_float32_rounding():
    """ATTITUDE's angles travel as float32, and float32(pi) = 3.14159274 > math.pi, float32(pi/2) > pi/2: a vehicle
    heading due south (yaw pi), flying inverted (roll -pi) or pointing straight up (pitch pi/2) arrives just beyond
    the range's own limits and must be kept (the check allows 1e-4 rad for that rounding). Hand values, q up to
    sign: yaw pi is q = [cos pi/2, 0, 0, sin pi/2] = [0, 0, 0, 1]; roll -pi is [0, -1, 0, 0]; pitch pi/2 is
    [cos pi/4, 0, sin pi/4, 0]."""
    assert float(np.float32(math.pi)) > math.pi and float(np.float32(math.pi / 2)) > math.pi / 2
    d = NavDecoder()
    for t_ms, kw, q in ((100, dict(yaw=math.pi), [0, 0, 0, 1]), (120, dict(roll=-math.pi), [0, -1, 0, 0]),
                        (140, dict(pitch=math.pi / 2), [math.cos(math.pi / 4), 0, math.sin(math.pi / 4), 0])):
        s = d.decode(att(t_ms, **kw))
        assert s is not None, (kw, d.rejected)
        q = np.array(q, float)
        assert min(np.abs(s.q_wxyz - q).max(), np.abs(s.q_wxyz + q).max()) < 1e-6, (kw, s.q_wxyz)
    assert d.rejected == Counter()


def test_body_rates_are_roll_pitch_yaw_in_that_order():
    """rates_frd_radps = (rollspeed, pitchspeed, yawspeed): the rates about body x (forward), y (right), z (down),
    from ATTITUDE and ATTITUDE_QUATERNION alike. The messages are built with each field set by its name, three
    different values exact in float32 (every other test sends zero rates)."""
    rates = dict(rollspeed=0.125, pitchspeed=-0.25, yawspeed=0.5)
    d = NavDecoder()
    s = d.decode(wire(ML.MAVLink_attitude_message(time_boot_ms=100, roll=0.0, pitch=0.0, yaw=0.0, **rates)))
    np.testing.assert_array_equal(s.rates_frd_radps, [0.125, -0.25, 0.5])
    s = d.decode(wire(ML.MAVLink_attitude_quaternion_message(time_boot_ms=100, q1=1.0, q2=0.0, q3=0.0, q4=0.0,
                                                             repr_offset_q=[0, 0, 0, 0], **rates)))
    np.testing.assert_array_equal(s.rates_frd_radps, [0.125, -0.25, 0.5])


def test_local_position_and_nonfinite():
    d = NavDecoder()
    s = d.decode(lpos(100, (1.5, -2.0, -30.0), (3.0, 0.5, -1.0)))
    np.testing.assert_allclose(s.position_ned_m, [1.5, -2.0, -30.0])
    np.testing.assert_allclose(s.velocity_ned_mps, [3.0, 0.5, -1.0])
    assert d.decode(lpos(200, (math.nan, 0, 0))) is None
    assert d.rejected["position_nonfinite"] == 1


def test_global_position_to_ned_hand_values():
    # meridian and prime-vertical radii of curvature at 45 deg (WGS-84), derived by hand:
    # M = a(1-e2)/(1-e2 sin^2)^1.5, N = a/sqrt(1-e2 sin^2)
    s2 = 0.5
    M = WGS84_A_M * (1 - WGS84_E2) / (1 - WGS84_E2 * s2) ** 1.5
    N = WGS84_A_M / math.sqrt(1 - WGS84_E2 * s2)
    dlat = math.radians(1e-3)
    ned = ned_from_lla(45.001, 0.0, 0.0, (45.0, 0.0, 0.0))
    assert ned[0] == pytest.approx(M * dlat, abs=2e-3)          # 111.13 m
    assert ned[0] == pytest.approx(111.13, abs=0.01)
    ned = ned_from_lla(45.0, 0.001, 10.0, (45.0, 0.0, 0.0))
    assert ned[1] == pytest.approx(N * math.cos(math.radians(45)) * dlat, abs=2e-3)   # 78.85 m
    assert ned[2] == pytest.approx(-10.0)
    # the decoder: first fix is the origin, alt mm -> down = -(alt - alt0)
    d = NavDecoder()
    assert d.decode(gpos(0, 0.0, 0.0, 0.0)) is None               # lat = lon = 0: no fix
    s0 = d.decode(gpos(100, 45.0, 0.0, 100.0, (150, -20, 30)))
    np.testing.assert_allclose(s0.position_ned_m, 0.0, atol=1e-9)
    np.testing.assert_allclose(s0.velocity_ned_mps, [1.5, -0.2, 0.3])
    s1 = d.decode(gpos(200, 45.001, 0.0, 103.0))
    assert s1.position_ned_m[0] == pytest.approx(M * dlat, abs=0.02)     # degE7 quantisation ~1 cm
    assert s1.position_ned_m[2] == pytest.approx(-3.0, abs=1e-6)
    assert d.rejected["global_no_fix"] == 1


def test_lla_round_trip():
    rng = np.random.default_rng(0)
    origin = (47.397742, 8.545594, 488.0)
    for _ in range(20):
        p = rng.uniform(-5000, 5000, 3)
        np.testing.assert_allclose(ned_from_lla(*lla_from_ned(p, origin), origin), p, atol=1e-6)


def test_given_origin_and_alt_datum_jump():
    d = NavDecoder(origin_lla=(45.0, 0.0, 50.0))
    assert d.decode(gpos(100, 45.0, 0.0, 51.0)).position_ned_m[2] == pytest.approx(-1.0)
    # ArduPilot switches alt from relative to AMSL when its EKF origin is set: +588 m in 0.1 s
    s = d.decode(gpos(200, 45.0, 0.0, 51.2 + 588.0))
    assert s.position_ned_m[2] == pytest.approx(-1.0, abs=1e-6)   # continuous (re-anchored to the previous sample)
    assert d.rejected["global_alt_datum_jump"] == 1
    assert d.decode(gpos(300, 45.0, 0.0, 641.2)).position_ned_m[2] == pytest.approx(-3.0, abs=1e-6)
    with pytest.raises(InputError, match="origin_lla"):
        NavDecoder(origin_lla=(95.0, 0.0, 0.0))


def test_alt_step_within_vertical_speed_is_motion_not_a_datum_change():
    """The datum-jump threshold grows with the time between fixes: alt_jump_m + max_vertical_speed_mps * dt
    (defaults 20 m + 100 m/s * dt). A real 60 m climb over 3 s between two fixes (a gap in GLOBAL_POSITION_INT) is
    below 20 + 300 m: it is motion and down must follow it (-(alt - alt0), hand value -60 m). A 75 m step in
    0.5 s is above 20 + 50 m: a datum change, absorbed (down stays where it was)."""
    d = NavDecoder(origin_lla=(45.0, 0.0, 100.0))
    assert d.decode(gpos(1_000, 45.0, 0.0, 100.0)).position_ned_m[2] == pytest.approx(0.0, abs=1e-6)
    s = d.decode(gpos(4_000, 45.0, 0.0, 160.0))                      # +60 m in 3 s
    assert s.position_ned_m[2] == pytest.approx(-60.0, abs=1e-6)
    assert d.rejected["global_alt_datum_jump"] == 0
    s = d.decode(gpos(4_500, 45.0, 0.0, 235.0))                      # +75 m in 0.5 s: > 20 + 100 * 0.5
    assert s.position_ned_m[2] == pytest.approx(-60.0, abs=1e-6)
    assert d.rejected["global_alt_datum_jump"] == 1


def test_global_position_east_of_90_degrees_longitude():
    """Longitude spans [-180, 180] deg (latitude [-90, 90]): a flight near Canberra (lon 149.165, the ArduPilot SITL
    home) or west of -90 is a valid fix; only beyond 180 is out of range. Hand value: 0.001 deg of longitude east
    at latitude phi is N cos(phi) dlon, N = a / sqrt(1 - e2 sin^2 phi). (Before this only the real ArduCopter tlog,
    shared data, saw a longitude beyond 90.)"""
    lat = -35.363262
    sl = math.sin(math.radians(lat))
    N = WGS84_A_M / math.sqrt(1 - WGS84_E2 * sl * sl)
    d = NavDecoder()
    assert d.decode(gpos(100, lat, 149.165237, 584.0)) is not None, d.rejected
    s = d.decode(gpos(200, lat, 149.166237, 584.0))
    assert s.position_ned_m[1] == pytest.approx(N * math.cos(math.radians(lat)) * math.radians(1e-3), abs=0.02)
    assert abs(s.position_ned_m[0]) < 0.02
    d = NavDecoder(origin_lla=(37.0, -122.4, 0.0))
    assert d.decode(gpos(100, 37.0, -122.4, 0.0)) is not None
    assert d.decode(gpos(200, 37.0, 180.5, 0.0)) is None
    assert d.rejected == Counter({"global_out_of_range": 1})


def test_position_source_auto_locks_first():
    d = NavDecoder()
    assert d.decode(lpos(100, (1, 2, 3))) is not None
    assert d.decode(gpos(100, 45.0, 0.0, 0.0)) is None
    assert d.rejected["position_source_not_selected"] == 1
    d = NavDecoder(position_source="GLOBAL_POSITION_INT")
    assert d.decode(lpos(100, (1, 2, 3))) is None
    assert d.decode(gpos(100, 45.0, 0.0, 0.0)) is not None


def test_odometry_body_velocity_rotated_to_ned():
    d = NavDecoder(position_source="ODOMETRY")
    q = quat_wxyz_from_ypr(math.pi / 2, 0, 0)          # heading east
    m = wire(ML.MAVLink_odometry_message(5_000_000, ML.MAV_FRAME_LOCAL_NED, ML.MAV_FRAME_BODY_FRD,
                                         1, 2, 3, list(q), 10.0, 0, 0, 0, 0, 0, [math.nan] * 21, [math.nan] * 21,
                                         0, 0, 100))
    s = d.decode(m)
    assert s.autopilot_time_us == 5_000_000 and s.time_base == "boot"
    np.testing.assert_allclose(s.position_ned_m, [1, 2, 3])
    np.testing.assert_allclose(s.velocity_ned_mps, [0, 10, 0], atol=1e-6)    # 10 m/s forward = east
    m = wire(ML.MAVLink_odometry_message(6_000_000, ML.MAV_FRAME_BODY_FRD, ML.MAV_FRAME_BODY_FRD,
                                         1, 2, 3, list(q), 0, 0, 0, 0, 0, 0, [math.nan] * 21, [math.nan] * 21,
                                         0, 0, 100))
    assert d.decode(m) is None and d.rejected["odometry_frame_unsupported"] == 1


def test_time_backwards_and_duplicates_per_stream():
    d = NavDecoder()
    assert d.decode(att(1000)) and d.decode(lpos(900, (0, 0, 0)))   # other stream, own clock check
    assert d.decode(att(1000)) is None                                # duplicate
    assert d.decode(att(990)) is None                                 # 10 ms back
    assert d.decode(att(1010)) is not None
    assert d.rejected == Counter({"duplicate_time": 1, "time_backwards": 1})


def test_reboot_detected_after_confirmation():
    d = NavDecoder()
    for t in (100_000, 100_020, 100_040):
        assert d.decode(att(t)) is not None
    assert d.decode(att(5_000)) is None            # first message of the new boot: a candidate only
    assert d.reboots == 0
    s = d.decode(att(5_020))                       # confirmed
    assert d.reboots == 1 and s is not None and s.boot_epoch == 1 and s.autopilot_time_us == 5_020_000
    assert d.decode(att(5_040)) is not None
    # a lone glitch back is not a reboot
    d2 = NavDecoder()
    d2.decode(att(100_000))
    assert d2.decode(att(3_000)) is None
    assert d2.decode(att(100_020)) is not None and d2.reboots == 0


def test_two_jumps_back_that_disagree_are_not_a_reboot():
    """A reboot is time_boot jumping back by more than 2 s on two consecutive messages that agree with each other
    (within 2 s: one new boot clock running). Two corrupt times far apart (3 s, then 50 s, after 100 s) are two
    glitches: both rejected as time_backwards, no reboot, the stream goes on at 100.04 s in boot epoch 0. A real
    reboot afterwards (5 s, then 5.02 s) is still confirmed."""
    d = NavDecoder()
    assert d.decode(att(100_000)) is not None
    assert d.decode(att(3_000)) is None
    assert d.decode(att(50_000)) is None
    assert d.reboots == 0 and d.rejected == Counter({"time_backwards": 2})
    s = d.decode(att(100_040))
    assert s is not None and s.boot_epoch == 0
    assert d.decode(att(5_000)) is None
    s = d.decode(att(5_020))
    assert d.reboots == 1 and s.boot_epoch == 1 and s.autopilot_time_us == 5_020_000


def test_system_filter():
    d = NavDecoder()
    assert d.decode(att(10, sysid=255, compid=190)) is None       # a GCS: never the autopilot
    assert d.decode(att(10, sysid=1, compid=100)) is None         # a camera component
    assert d.decode(att(10, sysid=7)) is not None and d.system_id == 7
    assert d.decode(att(20, sysid=1)) is None
    assert d.rejected["wrong_system"] == 3


# ----------------------------------------------------------------------------- clock offset
def test_min_window_offset():
    est = MinWindowOffset("receive", window_us=10_000_000)
    # true offset 5 s; latencies 3, 1, 7 ms; then later samples only see >= 2 ms
    for t_s, lat_ms in ((0, 3), (1, 1), (2, 7)):
        est.add(5_000_000 + t_s * 1_000_000 + lat_ms * 1000, t_s * 1_000_000)
    assert est.offset_us == 5_001_000
    for t_s in range(3, 13):
        est.add(5_000_000 + t_s * 1_000_000 + 2000, t_s * 1_000_000)
    assert est.offset_us == 5_002_000                  # the 1 ms sample left the 10 s window
    assert est.span_us == 12_000_000


def test_timesync_estimator_hand_values():
    ts = TimesyncEstimator(max_rtt_us=10_000)
    # companion sends at 1000.000 s; autopilot clock = companion - 900 s; reply 2 ms later, symmetric
    t_send = 1_000_000_000_000
    ts1 = ts.request(t_send)
    assert ts.on_reply(tc1_ns=t_send + 1_000_000 - 900_000_000_000, ts1_ns=ts1, t_rx_ns=t_send + 2_000_000)
    assert ts.offset_us == 900_000_000 and ts.rtt_us == 2000
    assert not ts.on_reply(5, 12345, t_send)                       # not our request
    ts1 = ts.request(t_send + 10**9)
    assert not ts.on_reply(0, ts1, t_send + 10**9 + 50_000_000)    # 50 ms RTT: rejected
    assert ts.rejected == Counter({"timesync_not_ours": 1, "timesync_rtt_too_long": 1})


def test_timesync_estimate_is_the_lowest_rtt_quarter():
    """A reply delayed on its way back biases the offset by (down - up) / 2; the estimate is the median offset of
    the lowest-RTT quarter of the exchanges (docs/mavlink.md), so two clean exchanges among eight outvote six
    asymmetric ones. Autopilot clock = companion - 900 s. Clean: 0.5 ms each way -> offset exactly 900 s.
    Asymmetric: 0.5 ms up, 8.5 ms down (RTT 9 ms, under the 10 ms limit) -> 900 s + 4 ms, by hand."""
    ts = TimesyncEstimator(max_rtt_us=10_000)
    t = 1_000_000_000_000
    for k, down_ms in enumerate((8.5, 0.5, 8.5, 8.5, 0.5, 8.5, 8.5, 8.5)):
        ts1 = ts.request(t + k * 100_000_000)
        up, down = 500_000, int(down_ms * 1e6)
        assert ts.on_reply(tc1_ns=ts1 + up - 900_000_000_000, ts1_ns=ts1, t_rx_ns=ts1 + up + down)
    assert ts.samples == 8 and ts.rtt_us == 1000
    assert ts.offset_us == 900_000_000                  # the median of all eight would be 900_004_000


def test_timesync_round_trip_limit_is_inclusive():
    """Replies with a round trip ABOVE max_rtt_us are rejected (docs/mavlink.md: 'above 10 ms'): exactly 10 ms is an
    exchange, 10.001 ms is not. Symmetric 5 ms each way; autopilot clock = companion - 900 s, so the offset is
    exactly 900 s."""
    ts = TimesyncEstimator(max_rtt_us=10_000)
    t = 1_000_000_000_000
    ts1 = ts.request(t)
    assert ts.on_reply(tc1_ns=ts1 + 5_000_000 - 900_000_000_000, ts1_ns=ts1, t_rx_ns=ts1 + 10_000_000)
    assert ts.rtt_us == 10_000 and ts.offset_us == 900_000_000
    ts1 = ts.request(t + 100_000_000)
    assert not ts.on_reply(tc1_ns=ts1 + 5_000_500 - 900_000_000_000, ts1_ns=ts1, t_rx_ns=ts1 + 10_001_000)
    assert ts.samples == 1 and ts.rejected == Counter({"timesync_rtt_too_long": 1})


def test_timesync_reply_received_twice_is_one_exchange():
    """A reply that arrives twice (a router or a second link forwarding the same packet) answers its request once:
    the copy is 'not ours'. Counted twice, copies would make the 3 exchanges of the lock out of fewer real ones,
    and a copy arriving 5 ms late would join the estimate with a 2.5 ms bias. Offset 900 s by hand, as above."""
    cm = ClockMapper(prefer=("timesync",))
    ts = cm.timesync
    t = 1_000_000_000_000
    for k in range(2):
        ts1 = ts.request(t + k * 100_000_000)
        tc1 = ts1 + 500_000 - 900_000_000_000
        assert ts.on_reply(tc1_ns=tc1, ts1_ns=ts1, t_rx_ns=ts1 + 1_000_000)
        assert not ts.on_reply(tc1_ns=tc1, ts1_ns=ts1, t_rx_ns=ts1 + 6_000_000)     # the copy
    assert ts.samples == 2 and ts.rejected == Counter({"timesync_not_ours": 2})
    assert ts.offset_us == 900_000_000 and not cm.locked                            # 2 exchanges: not locked


def test_timesync_outranks_a_locked_receive_clock_only_after_three_exchanges():
    """The mapper's TIMESYNC estimate is locked after 3 exchanges (docs/mavlink.md); before that a locked estimate
    further down the preference (receive time, 2 s seen) is used, and one or two replies do not take over. Hand
    values: receive latency floor 700 us over an offset of exactly 5000 s; TIMESYNC 0.5 ms each way -> 5000 s."""
    cm = ClockMapper()                                    # timesync, system_time, receive; lock 2 s
    off_us = 5_000_000_000
    for k in range(3):
        cm.receive.add(k * 1_000_000 + off_us + 700, k * 1_000_000)
    assert cm.locked and (cm.best().method, cm.best().offset_us) == ("receive", off_us + 700)
    t = 1_000_000_000_000_000
    for k in range(3):
        assert cm.best().method == "receive", k
        ts1 = cm.timesync.request(t + k * 100_000_000)
        assert cm.timesync.on_reply(tc1_ns=ts1 + 500_000 - off_us * 1000, ts1_ns=ts1, t_rx_ns=ts1 + 1_000_000)
    est = cm.best()
    assert (est.method, est.offset_us, est.samples, est.rtt_us) == ("timesync", off_us, 3, 1000)


def test_clock_mapper_slews_down_and_steps_up():
    cm = ClockMapper(prefer=("receive",), lock_span_us=0, slew=0.1)
    cm.receive.add(1_000_300_000, 0)               # first sample 300 ms late
    assert cm.map(0) == 1_000_300_000
    cm.receive.add(1_000_100_000 + 100_000, 100_000)   # floor now 100 ms lower
    # 100 ms of autopilot time may remove at most 10 ms of offset
    assert cm.map(100_000) == 100_000 + 1_000_290_000
    stamps = [cm.map(t) for t in range(100_000, 3_000_000, 20_000)]
    assert np.all(np.diff(stamps) > 0)
    assert cm.applied_offset_us == 1_000_100_000   # converged
    cm.receive.reset()
    cm.receive.add(1_000_500_000 + 3_000_000, 3_000_000)
    assert cm.map(3_000_000) == 3_000_000 + 1_000_500_000    # increases step at once


def test_clock_mapper_slew_ignores_an_older_sample_mapped_later():
    """Streams are mapped in arrival order, so a sample can carry an earlier autopilot time than the last one mapped
    (a GLOBAL_POSITION_INT stamped 20 ms before the ATTITUDE received just before it). While the offset slews down,
    such a sample neither slews it (no autopilot time passed) nor pushes it back up. Hand values as in the test
    above: first offset 300 ms late, floor then 100 ms lower, 0.1 s/s: 100 ms -> 10 ms less, 20 ms -> 2 ms less."""
    cm = ClockMapper(prefer=("receive",), lock_span_us=0, slew=0.1)
    cm.receive.add(1_000_300_000, 0)
    assert cm.map(0) == 1_000_300_000
    cm.receive.add(1_000_100_000 + 100_000, 100_000)
    assert cm.map(100_000) == 100_000 + 1_000_290_000
    assert cm.map(80_000) == 80_000 + 1_000_290_000          # older: the offset held
    assert cm.map(120_000) == 120_000 + 1_000_288_000        # 20 ms on from 100 ms: 2 ms less


def test_ingest_waits_for_clock_lock_then_maps_all():
    ing = NavIngest(mapper=ClockMapper(prefer=("receive",), lock_span_us=1_000_000))
    boot_offset = 1_700_000_000_000_000
    out = []
    for k in range(0, 100):
        t_ms = 10_000 + 20 * k
        rx = boot_offset + t_ms * 1000 + 500 + (k * 37 % 5) * 100
        out += ing.feed(att(t_ms), rx)
        if k < 49:
            assert out == []                          # < 1 s of samples: not locked yet, held
    assert len(out) == 100
    st = np.array([o["stamp_us"] for o in out])
    # the earliest samples are mapped with the locked estimate (min latency 500 us)
    np.testing.assert_array_equal(st[:50] - (10_000_000 + 20_000 * np.arange(50)), boot_offset + 500)
    assert out[0]["clock_offset_us"] == boot_offset + 500 and out[0]["source"] == "ATTITUDE"
    assert np.all(np.isnan(out[0]["position_ned_m"]))


def test_ingest_locks_when_the_clock_has_seen_exactly_the_lock_span():
    """The mapper locks once its estimator has seen lock_span_us of autopilot time, that span included
    (docs/mavlink.md: 2 s): ATTITUDE at 10.00 s .. 10.04 s with a 40 ms lock span are held until the third, which
    releases all three. Stamps: autopilot time + 5000 s + the 700 us latency floor."""
    ing = NavIngest(mapper=ClockMapper(prefer=("receive",), lock_span_us=40_000))
    off_us = 5_000_000_000 + 700
    assert ing.feed(att(10_000), 10_000_000 + off_us) == []
    assert ing.feed(att(10_020), 10_020_000 + off_us) == []
    out = ing.feed(att(10_040), 10_040_000 + off_us)
    assert [o["stamp_us"] for o in out] == [t + off_us for t in (10_000_000, 10_020_000, 10_040_000)]
    cm = ClockMapper(prefer=("receive",))                  # the default lock span, 2 s
    cm.receive.add(off_us, 0)
    cm.receive.add(1_999_999 + off_us, 1_999_999)
    assert not cm.locked
    cm.receive.add(2_000_000 + off_us, 2_000_000)
    assert cm.locked


def test_ingest_holds_at_most_max_pending_samples_before_the_lock():
    """Before the clock locks, samples wait in a queue of max_pending; beyond that the oldest are dropped and
    counted (clock_unlocked). max_pending 3, five ATTITUDE 20 ms apart and a lock at 80 ms of autopilot time (the
    fifth): the two oldest are dropped, the three newest come out with the lock."""
    ing = NavIngest(mapper=ClockMapper(prefer=("receive",), lock_span_us=80_000), max_pending=3)
    off_us = 5_000_000_000 + 700
    out = []
    for t_ms in (1_000, 1_020, 1_040, 1_060, 1_080):
        out += ing.feed(att(t_ms), t_ms * 1000 + off_us)
    assert [o["autopilot_time_us"] for o in out] == [1_040_000, 1_060_000, 1_080_000]
    assert [o["stamp_us"] for o in out] == [t + off_us for t in (1_040_000, 1_060_000, 1_080_000)]
    assert ing.rejected["clock_unlocked"] == 2


def test_system_time_zero_ignored_and_used_after_fix():
    ing = NavIngest(mapper=ClockMapper(prefer=("system_time", "receive"), lock_span_us=0))
    ing.feed(wire(ML.MAVLink_system_time_message(0, 5000)), 77)
    assert ing.rejected["system_time_no_gps"] == 1 and ing.mapper.system_time.offset_us is None
    ing.feed(wire(ML.MAVLink_system_time_message(1_700_000_006_000_300, 6000)), None)
    ing.feed(wire(ML.MAVLink_system_time_message(1_700_000_007_000_900, 7000)), None)
    assert ing.clock().method == "system_time" and ing.clock().offset_us == 1_700_000_000_000_300


def test_autopilot_timesync_request_is_a_receive_time_sample_in_us():
    """The autopilot's own TIMESYNC requests (tc1 = 0) carry its boot clock in ts1, in nanoseconds: each is a
    receive-time sample, offset = rx_us - ts1 / 1000. Hand values: boot 5 s received 700 us late, boot 6 s 300 us
    late -> the minimum, 1_700_000_000_000_300 us. (Before this, only a real-tlog test caught a ns/us slip.)"""
    ing = NavIngest(mapper=ClockMapper(prefer=("receive",), lock_span_us=0))
    ing.feed(wire(ML.MAVLink_timesync_message(0, 5_000_000_000)), 1_700_000_005_000_700)
    assert ing.clock().offset_us == 1_700_000_000_000_700
    ing.feed(wire(ML.MAVLink_timesync_message(0, 6_000_000_000)), 1_700_000_006_000_300)
    assert ing.clock().method == "receive" and ing.clock().offset_us == 1_700_000_000_000_300
    ing.feed(wire(ML.MAVLink_timesync_message(0, 7_000_000_000), sysid=255, compid=190), 1_700_000_006_500_000)
    assert ing.mapper.receive.samples == 2                # a GCS's request is not the autopilot's clock


def test_autopilot_reboot_restarts_the_receive_clock():
    """After a reboot the autopilot's boot clock restarts, so companion - autopilot grows by the old boot time: the
    estimators restart and the new boot's stamps are its receive times again (latency 500 us), not 105 s in the
    past as the old estimate would put them. Boot A at 100.00 .. 100.04 s received at U + t + 500 us; boot B
    at 5.00, 5.02 s received 10 s later. (Before this only the real ArduCopter tlog, shared data, saw a reboot.)"""
    ing = NavIngest(mapper=ClockMapper(prefer=("receive",), lock_span_us=0))
    U = 1_700_000_000_000_000
    for t_ms in (100_000, 100_020, 100_040):
        (o,) = ing.feed(att(t_ms), U + t_ms * 1000 + 500)
        assert o["stamp_us"] == U + t_ms * 1000 + 500
    assert ing.feed(att(5_000), U + 110_000_500) == []             # a reboot candidate
    (o,) = ing.feed(att(5_020), U + 110_020_500)                   # confirmed
    assert ing.decoder.reboots == 1
    assert o["stamp_us"] == U + 110_020_500 and o["clock_offset_us"] == U + 105_000_500


def test_timesync_over_udp_loopback_against_simulated_autopilot():
    """pymavlink on both ends: an autopilot thread answers TIMESYNC with its boot clock (ns)."""
    mavutil = mavutil_v2()
    import socket
    s = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    s.bind(("127.0.0.1", 0))
    port = s.getsockname()[1]
    s.close()
    boot_offset_ns = time.time_ns() - 4_321_987_654_321        # autopilot booted 4322 s ago
    ap = mavutil.mavlink_connection(f"udpin:127.0.0.1:{port}", source_system=1, source_component=1,
                                    dialect="ardupilotmega")
    gcs = mavutil.mavlink_connection(f"udpout:127.0.0.1:{port}", source_system=1, source_component=191,
                                     dialect="ardupilotmega")
    stop = threading.Event()

    def autopilot():
        while not stop.is_set():
            m = ap.recv_match(type="TIMESYNC", blocking=True, timeout=0.1)
            if m is not None and m.tc1 == 0:
                ap.mav.timesync_send(time.time_ns() - boot_offset_ns, m.ts1)

    th = threading.Thread(target=autopilot)
    th.start()
    try:
        ing = NavIngest()
        got = 0
        for _ in range(20):
            gcs.mav.timesync_send(0, ing.mapper.timesync.request(time.time_ns()))
            m = gcs.recv_match(type="TIMESYNC", blocking=True, timeout=0.5)
            if m is not None:
                ing.feed(m, time.time_ns() // 1000)
                got += 1
            time.sleep(0.01)
    finally:
        stop.set()
        th.join()
        ap.close()
        gcs.close()
    est = ing.clock()
    assert got >= 10 and est.method == "timesync"
    assert abs(est.offset_us - boot_offset_ns / 1000) < 1000, (est, boot_offset_ns)
    assert 0 <= est.rtt_us < 10_000


# ----------------------------------------------------------------------------- tlogs
def _decode_tlog(path, **kw):
    ing = NavIngest(NavDecoder(**kw), ClockMapper(prefer=("receive",)))
    reader = TlogReader(path)
    types, out = Counter(), []
    for h, m in reader:
        types[m.get_type()] += 1
        out += ing.feed(m, h)
    out += ing.flush()
    return reader.stats, types, ing, out


@pytest.mark.realdata
@needs_data
def test_real_arducopter_tlog():
    st, types, ing, out = _decode_tlog(COPTER)
    # counts as the data README states (and pymavlink's own reader gives)
    assert (types["ATTITUDE"], types["GLOBAL_POSITION_INT"], types["LOCAL_POSITION_NED"], types["SYSTEM_TIME"]) \
        == (2829, 2833, 1161, 2812)
    assert st.bad_data == 1314                         # the corrupted radio packets
    assert ing.decoder.reboots == 1                    # time_boot_ms 279 s -> 19 s mid-log
    assert ing.decoder.position_source == "GLOBAL_POSITION_INT"
    assert ing.rejected["global_no_fix"] > 100 and ing.rejected["global_alt_datum_jump"] >= 1
    for src in ("ATTITUDE", "GLOBAL_POSITION_INT"):
        stamps = np.array([o["stamp_us"] for o in out if o["source"] == src])
        assert np.all(np.diff(stamps) > 0), src
    pos = np.array([o["position_ned_m"] for o in out if o["source"] == "GLOBAL_POSITION_INT"])
    assert np.all(np.abs(pos[:, :2]) < 100)            # a small field flight
    assert -30 < pos[:, 2].min() and pos[:, 2].max() < 5
    # stamps are receive-time bounded: never later than the header (latency only adds)
    assert ing.clock().method == "receive"


@pytest.mark.realdata
@needs_data
def test_real_ardusub_tlog_mavlink2_components():
    st, types, ing, out = _decode_tlog(SUB)
    assert (types["ATTITUDE"], types["GLOBAL_POSITION_INT"], types["LOCAL_POSITION_NED"]) == (5245, 792, 792)
    assert st.bad_data == 4 and st.truncated_bytes == 0
    assert ing.decoder.system_id == 1 and ing.decoder.reboots == 0
    assert ing.published["ATTITUDE"] == 5245
    # the GCS's SYSTEM_TIME (255/190, time_boot_ms 0) is not the autopilot's clock
    assert ing.mapper.system_time.samples == 0
    att_stamps = np.array([o["stamp_us"] for o in out if o["source"] == "ATTITUDE"])
    assert np.all(np.diff(att_stamps) > 0)
    ap = np.array([o["autopilot_time_us"] for o in out if o["source"] == "ATTITUDE"])
    # after mapping, stamp - autopilot time is the applied clock offset: over the 263 s dive it moves by
    # 16 ms (the receive-latency floor of a QGC log), never by the 650 ms of the start-up burst
    assert np.ptp(att_stamps - ap) < 25_000


@pytest.mark.realdata
@needs_data
def test_truncated_real_tlog(tmp_path):
    data = SUB.read_bytes()
    cut = tmp_path / "cut.tlog"
    cut.write_bytes(data[:len(data) - 1010])           # ends inside a record
    st, types, ing, out = _decode_tlog(cut)
    assert st.truncated_bytes > 0
    full = _decode_tlog(SUB)
    assert 0 < full[0].records - st.records < 40
    assert types["ATTITUDE"] <= 5245 and len(out) > 5000


def test_truncated_generated_tlog_every_cut(tmp_path):
    mav = ML.MAVLink(None, srcSystem=1, srcComponent=1)
    import struct
    recs = b"".join(struct.pack(">Q", 1_700_000_000_000_000 + k * 20_000)
                    + ML.MAVLink_attitude_message(k * 20, 0, 0, 0, 0, 0, 0).pack(mav) for k in range(5))
    rec_len = len(recs) // 5
    for cut in range(1, rec_len):
        p = tmp_path / f"c{cut}.tlog"
        p.write_bytes(recs[:len(recs) - cut])
        r = TlogReader(p)
        n = sum(1 for _ in r)
        assert n == 4 and r.stats.truncated_bytes == rec_len - cut and r.stats.bad_data == 0, cut


def test_corrupt_packet_in_generated_tlog(tmp_path):
    import struct
    mav = ML.MAVLink(None, srcSystem=1, srcComponent=1)
    recs = [bytearray(struct.pack(">Q", 1_700_000_000_000_000 + k * 20_000)
                      + ML.MAVLink_attitude_message(k * 20, 0, 0, 0, 0, 0, 0).pack(mav)) for k in range(5)]
    recs[2][20] ^= 0xFF                                 # flip payload bits: CRC fails
    p = tmp_path / "bad.tlog"
    p.write_bytes(b"".join(recs))
    r = TlogReader(p)
    got = [m.time_boot_ms for _, m in r]
    assert got == [0, 20, 60, 80] and r.stats.bad_data == 1


def test_corrupt_header_times_do_not_move_the_clock(tmp_path):
    import struct
    mav = ML.MAVLink(None, srcSystem=1, srcComponent=1)
    t0 = 1_700_000_000_000_000
    hdrs = [t0 + k * 20_000 for k in range(8)]
    hdrs[3] -= 5_000_000                                # a header 5 s in the past
    hdrs[5] += 3600 * 10**6                             # and one an hour ahead, unconfirmed
    p = tmp_path / "h.tlog"
    p.write_bytes(b"".join(struct.pack(">Q", h) + ML.MAVLink_attitude_message(k * 20, 0, 0, 0, 0, 0, 0).pack(mav)
                           for k, h in enumerate(hdrs)))
    r = TlogReader(p)
    got = [h for h, _ in r]
    assert got == [t0, t0 + 20_000, t0 + 40_000, t0 + 40_000, t0 + 80_000, t0 + 80_000, t0 + 120_000, t0 + 140_000]
    assert r.stats.backwards_headers == 1 and r.stats.header_jumps == 1
    # a real gap (two records agree on the new time base) is kept
    hdrs = [t0, t0 + 20_000, t0 + 600 * 10**6, t0 + 600 * 10**6 + 20_000]
    p.write_bytes(b"".join(struct.pack(">Q", h) + ML.MAVLink_attitude_message(k * 20, 0, 0, 0, 0, 0, 0).pack(mav)
                           for k, h in enumerate(hdrs)))
    r = TlogReader(p)
    assert [h for h, _ in r] == [t0, t0 + 20_000, t0 + 20_000, t0 + 600 * 10**6 + 20_000]
