"""eonav.sim.record: a simulated flight written as frames + tlog + truth decodes back to the flight."""
import json

import cv2
import numpy as np
import pytest

from eonav.geometry.frames import T_body_ned_from_quat
from eonav.nav.mavlink_in import ClockMapper, NavDecoder, NavIngest, TlogReader, mavutil_v2
from eonav.io.pairfile import parse_camera
from eonav.sim.flight import flight_states
from eonav.sim.record import nav_truth, record_flight


@pytest.fixture(scope="module")
def rec(tmp_path_factory):
    out = tmp_path_factory.mktemp("rec") / "approach"
    return record_flight(out, "approach", n_frames=4, rate_hz=10.0, size=(64, 48), seed=1, supersample=1)


def _angle(q_a, q_b):
    R = T_body_ned_from_quat(q_a) @ T_body_ned_from_quat(q_b).T
    return float(np.arccos(np.clip((np.trace(R) - 1) / 2, -1, 1)))


def test_files_and_timestamps_align(rec):
    man = json.loads((rec / "manifest.json").read_text())
    pngs = sorted((rec / "frames").glob("*.png"))
    assert len(pngs) == 4 and cv2.imread(str(pngs[0]), cv2.IMREAD_UNCHANGED).shape == (48, 64)
    lines = (rec / "frames" / "timestamps.txt").read_text().split()
    stamps = [int(round(float(x) * 1e6)) for x in lines]
    truth = np.load(rec / "truth.npz")
    assert stamps == truth["stamp_us"].tolist()
    # frame i at flight time 0.2 + i/10 s on the UNIX clock of the manifest
    assert stamps == [man["start_unix_us"] + 200_000 + 100_000 * i for i in range(4)]
    assert lines[1] == f"{(man['start_unix_us'] + 300_000) / 1e6:.6f}"          # microsecond decimals
    assert truth["range_m"].shape == (4, 48, 64) and truth["range_m"].dtype == np.float16
    assert truth["object_id"].dtype == np.int16 and (truth["object_id"] >= 2).any()   # boxes in view
    cams = json.loads((rec / "cameras.json").read_text())
    cam = parse_camera("nose", cams["nose"])
    assert (cam.width, cam.height) == (64, 48)
    st = flight_states("approach", truth["t_s"])
    np.testing.assert_allclose(truth["position_ned_m"], [s.position_ned_m for s in st])


def test_tlog_decodes_with_pymavlink(rec):
    man = json.loads((rec / "manifest.json").read_text())
    conn = mavutil_v2().mavlink_connection(str(rec / "flight.tlog"), dialect="ardupilotmega")
    counts, prev_ts, boot_minus = {}, 0.0, []
    while True:
        m = conn.recv_match(blocking=False)
        if m is None:
            break
        assert m.get_type() != "BAD_DATA"
        counts[m.get_type()] = counts.get(m.get_type(), 0) + 1
        assert m._timestamp >= prev_ts
        prev_ts = m._timestamp
        if m.get_type() == "SYSTEM_TIME":
            boot_minus.append(m.time_unix_usec - m.time_boot_ms * 1000)
    conn.close()
    assert counts == man["tlog_counts"]
    # 0.2 + 0.3 + 0.5 s of flight: ATTITUDE at 50 Hz (t = 0..1.0 s), position messages at 25 Hz
    assert counts["ATTITUDE"] == 51 and counts["ATTITUDE_QUATERNION"] == 26 and counts["SYSTEM_TIME"] == 2
    assert set(boot_minus) == {man["boot_offset_us"]}                     # the known boot clock


@pytest.mark.parametrize("position_source", ["LOCAL_POSITION_NED", "GLOBAL_POSITION_INT"])
def test_tlog_decodes_back_to_flight_states(rec, position_source):
    man = json.loads((rec / "manifest.json").read_text())
    dec = NavDecoder(position_source=position_source, origin_lla=man["origin_lla"])
    ing = NavIngest(dec, ClockMapper(prefer=("receive",), lock_span_us=500_000))
    out = []
    for h, m in TlogReader(rec / "flight.tlog"):
        out += ing.feed(m, h)
    out += ing.flush()
    assert ing.rejected.get("position_source_not_selected") == 26
    # receive-time offset: boot offset + the smallest simulated link latency (1..3 ms)
    off = ing.clock().offset_us - man["boot_offset_us"]
    assert man["latency_us"][0] <= off <= man["latency_us"][0] + 300
    t_s = np.array([(o["autopilot_time_us"] + man["boot_offset_us"] - man["start_unix_us"]) / 1e6 for o in out])
    tr = nav_truth("approach", t_s)
    pos_err, att_err = [], []
    for k, o in enumerate(out):
        if o["source"] == position_source:
            pos_err.append(np.abs(o["position_ned_m"] - tr["position_ned_m"][k]).max())
            assert np.allclose(o["velocity_ned_mps"], tr["velocity_ned_mps"][k], atol=0.006)
        else:
            att_err.append(_angle(o["q_wxyz"], tr["q_wxyz"][k]))
        # stamps: the UNIX send time shifted by the estimated latency floor, within the latency spread
        unix_us = t_s[k] * 1e6 + man["start_unix_us"]
        assert 0 <= o["stamp_us"] - unix_us - man["latency_us"][0] <= 300
    assert len(pos_err) == 26 and len(att_err) == 51 + 26
    assert max(att_err) < 1e-6                                     # float32 on the wire
    assert max(pos_err) < (1e-5 if position_source == "LOCAL_POSITION_NED" else 0.012)   # degE7 ~ 1 cm


def _tlog_messages(rec, typ: str):
    """The recording's tlog messages of type ``typ`` (pymavlink) and their times from the flight's start (s, from
    time_boot_ms and the manifest's clocks)."""
    man = json.loads((rec / "manifest.json").read_text())
    conn = mavutil_v2().mavlink_connection(str(rec / "flight.tlog"), dialect="ardupilotmega")
    msgs = []
    while (m := conn.recv_match(type=typ, blocking=False)) is not None:
        msgs.append(m)
    conn.close()
    return msgs, np.array([(m.time_boot_ms * 1000 + man["boot_offset_us"] - man["start_unix_us"]) / 1e6
                           for m in msgs])


def test_global_position_int_fields_follow_the_mavlink_units_and_signs(rec):
    """GLOBAL_POSITION_INT of the approach flight against its closed form (6 + 0.3 sin 0.7t m up, 20 m/s north,
    east 1.5 sin 0.4t, yaw 0.6 deg sin 0.5t), in MAVLink's units: relative_alt mm ABOVE home (positive up), alt
    mm above the origin's 488 m, vx vy vz cm/s NED, hdg centidegrees in 0..35999. Another tool reads the tlog
    (pymavlink here): catches relative_alt written as NED down."""
    msgs, times = _tlog_messages(rec, "GLOBAL_POSITION_INT")
    assert len(msgs) == 26
    for m, t in zip(msgs, times):
        height_m = 6.0 + 0.3 * np.sin(0.7 * t)
        assert abs(m.relative_alt - 1000 * height_m) <= 1.0
        assert abs(m.alt - 1000 * (488.0 + height_m)) <= 1.0
        assert (m.vx, m.vz) == (2000, round(-21.0 * np.cos(0.7 * t)))          # d(down)/dt = -0.21 cos 0.7t m/s
        assert abs(m.vy - 60.0 * np.cos(0.4 * t)) <= 1.0
        assert m.hdg == round(60.0 * np.sin(0.5 * t)) % 36000


def test_body_rates_are_in_the_body_frame(rec):
    """nav_truth's body rates (FRD, the ATTITUDE rollspeed/pitchspeed/yawspeed of the tlog), hand-derived: the
    turning flight yaws at w = g tan 15 / 15 = 0.17524 rad/s about NED down while banked 15 deg right, so in the
    body frame p = 0, q = w sin 15, r = w cos 15; the climbing flight pitches up at 8/0.7 e^(-t/0.7) deg/s
    (2.7389 deg/s at 1 s) with no roll or yaw. The tlog's ATTITUDE carries them as written (float32). Catches the
    rates taken in NED (q = 0, r = w while banked) and a rate's sign flipped on the wire."""
    att, t = _tlog_messages(rec, "ATTITUDE")
    np.testing.assert_allclose([[m.rollspeed, m.pitchspeed, m.yawspeed] for m in att],
                               nav_truth("approach", t)["rates_frd_radps"], atol=1e-7)
    w = 0.17523877184995426
    s15, c15 = np.sin(np.deg2rad(15.0)), np.cos(np.deg2rad(15.0))
    tr = nav_truth("turning", np.array([0.5, 1.0, 3.0]))
    np.testing.assert_allclose(tr["rates_frd_radps"], np.tile([0.0, w * s15, w * c15], (3, 1)), atol=1e-6)
    tr = nav_truth("climbing", np.array([1.0]))
    np.testing.assert_allclose(tr["rates_frd_radps"][0], [0.0, np.deg2rad(2.738868987906009), 0.0], atol=1e-6)
