"""Recorded autopilot logs through the MAVLink ingest service as a real process on a real zenoh session: an
ArduPilot dataflash log (tests/data/arducopter_sitl_short.bin, made by the real ArduCopter SITL, see
tests/data/make_dataflash_bin.py), the two real tlogs replayed in full (counts from pymavlink's own reader), a
.bin that is not a dataflash log refused, and corrupt MAVLink of many unknown ids kept to two counters."""
from __future__ import annotations

import math
import os
import struct
import subprocess
from collections import Counter
from pathlib import Path

import numpy as np
import pytest

from eonav.bus import keys as K
from eonav.bus import schema
from eonav.geometry.frames import T_body_ned_from_quat
from eonav.nav.dataflash import DataflashReader
from eonav.nav.mavlink_in import ClockMapper, NavDecoder, NavIngest, mavlink2_dialect, mavutil_v2

BIN = Path(__file__).resolve().parent / "data" / "arducopter_sitl_short.bin"
TLOGS = Path(__file__).resolve().parents[1].parent / "shared" / "data" / "tlogs"
REAL = {"copter": TLOGS / "arducopter_real_flight_dronekit.tlog",
        "sub": TLOGS / "ardusub_real_dive_qgc_mavlink2_small.tlog"}


def dfreader_messages(path):
    """Every message of a dataflash log, read with pymavlink's DFReader directly."""
    from pymavlink import DFReader
    r = DFReader.DFReader_binary(str(path), zero_time_base=False)
    out = []
    while (m := r.recv_msg()) is not None:
        out.append(m)
    return out


def _angle(q_a, q_b):
    R = T_body_ned_from_quat(q_a) @ T_body_ned_from_quat(q_b).T
    return float(np.arccos(np.clip((np.trace(R) - 1) / 2, -1, 1)))


def run_ingest(source, *extra, vehicle="lg", timeout=120):
    """The ingest service replaying ``source`` as fast as it can; returns (exit code, stderr, nav states, the last
    health counters)."""
    import zenoh

    from eonav.app.processes import drain, free_port, start_service
    from eonav.bus.session import endpoint, listener_session
    port = free_port()
    with listener_session(port) as s:
        nav_sub = s.declare_subscriber(K.nav_state(vehicle), zenoh.handlers.FifoChannel(100_000))
        h_sub = s.declare_subscriber(K.health(vehicle, "mavlink"), zenoh.handlers.FifoChannel(10_000))
        proc = start_service(["-m", "eonav.services.mavlink_ingest", "--source", str(source), "--rate", "0",
                              "--vehicle", vehicle, "--connect", endpoint(port), "--health-period", "0.2",
                              "--wait-subscribers", "10", *extra])
        nav, health = [], []
        try:
            _, err = proc.communicate(timeout=timeout)
        finally:
            if proc.poll() is None:
                proc.kill()
                proc.communicate()
        import time
        time.sleep(0.3)
        nav = [schema.decode(m.payload.to_bytes()) for m in drain(nav_sub)]
        health = [schema.decode(m.payload.to_bytes()) for m in drain(h_sub)]
    return proc.returncode, err, nav, (health[-1]["counters"] if health else {})


# -- dataflash ----------------------------------------------------------------------------------------------------
def test_dataflash_reader_gives_what_dfreader_reads():
    msgs = dfreader_messages(BIN)
    types = Counter(m.get_type() for m in msgs)
    first_orgn = next(i for i, m in enumerate(msgs) if m.get_type() == "ORGN")
    n_xkf1_after = sum(1 for m in msgs[first_orgn:] if m.get_type() == "XKF1" and m.C == 0)
    r = DataflashReader(BIN)
    got = list(r)
    kinds = Counter(m.get_type() for _, m in got)
    assert kinds == {"ATTITUDE": types["ATT"], "ATTITUDE_QUATERNION": types["XKQ"],
                     "GLOBAL_POSITION_INT": types["POS"], "LOCAL_POSITION_NED": n_xkf1_after}
    assert r.stats.records == len(msgs) and r.stats.truncated_bytes == 0 and r.stats.resync_bytes == 0
    assert r.stats.no_origin == sum(1 for m in msgs[:first_orgn] if m.get_type() == "XKF1")
    # field by field against the DFReader messages (same order)
    src = [m for m in msgs if m.get_type() in ("ATT", "XKQ", "POS") or (m.get_type() == "XKF1" and
                                                                       msgs.index(m) > first_orgn)]
    assert len(src) == len(got)
    for m, (stamp, g) in zip(src, got):
        assert stamp == round(m._timestamp * 1e6) and g.time_boot_ms == m.TimeUS // 1000
        if m.get_type() == "ATT":
            yaw = math.degrees(g.yaw) % 360
            assert (math.degrees(g.roll), math.degrees(g.pitch)) == pytest.approx((m.Roll, m.Pitch), abs=1e-9)
            assert min(abs(yaw - m.Yaw), 360 - abs(yaw - m.Yaw)) < 1e-6 and -math.pi <= g.yaw < math.pi
        elif m.get_type() == "XKF1":
            assert (g.x, g.y, g.z, g.vx, g.vy, g.vz) == (m.PN, m.PE, m.PD, m.VN, m.VE, m.VD)
        elif m.get_type() == "POS":
            assert abs(g.lat - m.Lat * 1e7) <= 0.5 and abs(g.lon - m.Lng * 1e7) <= 0.5
            assert abs(g.alt - m.Alt * 1000) <= 0.5 and abs(g.relative_alt - m.RelHomeAlt * 1000) <= 0.5


def with_other_core(data: bytes):
    """``data`` (a dataflash log) with, after every XKF1 and XKQ of EKF core 0, the same message of core 1 (field C,
    the byte after TimeUS) whose quaternion is a half turn about the vertical (q = (0, 0, 0, 1)): what a log of a
    two-core EKF holds. Returns (the new log, the number of messages added)."""
    lengths, names = {128: 89}, {128: "FMT"}
    out, i, added = bytearray(), 0, 0
    while i + 3 <= len(data):
        assert data[i:i + 2] == b"\xa3\x95" and data[i + 2] in lengths, i      # the log is whole: no resync here
        t, n = data[i + 2], lengths[data[i + 2]]
        msg = bytearray(data[i:i + n])
        if t == 128:
            lengths[msg[3]], names[msg[3]] = msg[4], msg[5:9].rstrip(b"\0").decode()
        out += msg
        if names[t] in ("XKF1", "XKQ"):
            assert msg[11] == 0
            msg[11] = 1
            if names[t] == "XKQ":                                  # QBffff: TimeUS, C, Q1..Q4
                msg[12:28] = struct.pack("<4f", 0.0, 0.0, 0.0, 1.0)
            out += msg
            added += 1
        i += n
    return bytes(out), added


def test_dataflash_reader_keeps_ekf_core_0_only(tmp_path):
    """A log of a two-core EKF: XKF1 and XKQ of core 1 are interleaved with core 0's; the reader must give exactly
    what it gives for the core-0-only log (core 1 counted, never mixed in: a second attitude half a turn off
    would make the attitude jump at every message)."""
    data, added = with_other_core(BIN.read_bytes())
    p = tmp_path / "two_cores.bin"
    p.write_bytes(data)
    one, two = DataflashReader(BIN), DataflashReader(p)
    want, got = list(one), list(two)
    assert added > 100 and two.stats.other_core == added and one.stats.other_core == 0
    assert two.stats.records == one.stats.records + added and two.stats.nav == one.stats.nav
    assert [(t, repr(m)) for t, m in got] == [(t, repr(m)) for t, m in want]



def fmt_record_of(data, name: bytes) -> int:
    """The byte offset of the FMT record that defines message ``name`` in a dataflash log."""
    i = data.index(b"\xa3\x95\x80")
    while data[i + 5:i + 9].rstrip(b"\0") != name:
        i = data.index(b"\xa3\x95\x80", i + 89)
    return i


def test_pos_without_a_relhomealt_column_still_gives_the_position(tmp_path):
    """A POS format without the RelHomeAlt column (its name changed, as another firmware would write it): the
    position (lat, lon, alt AMSL) is still every POS's, the relative altitude only is not known; no POS is lost."""
    b = bytearray(BIN.read_bytes())
    i = fmt_record_of(b, b"POS")
    cols = b"TimeUS,Lat,Lng,Alt,RelHomeAlt,RelOriginAlt"
    assert b[i + 25:i + 89].rstrip(b"\0") == cols
    b[i + 25:i + 89] = cols.replace(b"RelHomeAlt", b"RelAlt").ljust(64, b"\0")
    p = tmp_path / "pos_relalt.bin"
    p.write_bytes(bytes(b))
    pos = [m for m in dfreader_messages(BIN) if m.get_type() == "POS"]
    r = DataflashReader(p)
    got = [g for _, g in r if g.get_type() == "GLOBAL_POSITION_INT"]
    assert len(got) == len(pos) > 100 and r.stats.bad_fields == 0
    for m, g in zip(pos, got):
        assert abs(g.lat - m.Lat * 1e7) <= 0.5 and abs(g.lon - m.Lng * 1e7) <= 0.5 and abs(g.alt - m.Alt * 1000) <= 0.5
        assert g.relative_alt == 0


def test_fmt_record_longer_than_its_format_is_refused(tmp_path):
    """An FMT record whose length is one byte more than its format needs (ATT, QffffffB: 3 + 8 + 6*4 + 1 = 36): read
    with it, every ATT swallows a byte of the next message (all attitudes lost, the rest resynchronised); the log
    is refused at open, naming the record."""
    from eonav import InputError
    b = bytearray(BIN.read_bytes())
    i = fmt_record_of(b, b"ATT")
    assert b[i + 4] == 36 and b[i + 9:i + 25].rstrip(b"\0") == b"QffffffB"
    b[i + 4] = 37
    p = tmp_path / "att_37.bin"
    p.write_bytes(bytes(b))
    with pytest.raises(InputError, match=f"FMT record at byte {i} defines type {b[i + 3]} \\('ATT'\\) with length 37, "
                                         "but its format 'QffffffB' needs 36"):
        list(DataflashReader(p))

def test_service_replays_a_dataflash_log():
    msgs = dfreader_messages(BIN)
    first_orgn = next(i for i, m in enumerate(msgs) if m.get_type() == "ORGN")
    xkf1 = [m for m in msgs[first_orgn:] if m.get_type() == "XKF1"]
    n_att = sum(1 for m in msgs if m.get_type() == "ATT")
    n_xkq = sum(1 for m in msgs if m.get_type() == "XKQ")
    code, err, nav, c = run_ingest(BIN, "--position-source", "LOCAL_POSITION_NED")
    assert code == 0, err[-3000:]
    assert "end of dataflash log" in err and "Traceback" not in err
    by = Counter(m["source"] for m in nav)
    assert by == {"ATTITUDE": n_att, "ATTITUDE_QUATERNION": n_xkq, "LOCAL_POSITION_NED": len(xkf1)}
    assert c["dataflash_records"] == len(msgs) and c["nav_published"] == len(nav)
    pos = [m for m in nav if m["source"] == "LOCAL_POSITION_NED"]
    np.testing.assert_allclose([p["position_ned_m"] for p in pos], [[m.PN, m.PE, m.PD] for m in xkf1], atol=1e-5)
    assert np.linalg.norm(pos[-1]["position_ned_m"][:2] - [20, 10]) < 1.5     # the flight: 20 m N, 10 m E
    # the AHRS attitude (ATT, degrees) and the EKF quaternion (XKQ) of the same instant agree
    att = {m["autopilot_time_us"]: m["q_wxyz"] for m in nav if m["source"] == "ATTITUDE"}
    xkq = {m["autopilot_time_us"]: m["q_wxyz"] for m in nav if m["source"] == "ATTITUDE_QUATERNION"}
    common = sorted(set(att) & set(xkq))
    assert len(common) > 0.9 * n_att
    assert max(_angle(att[t], xkq[t]) for t in common) < math.radians(1.0)
    # stamps: the log's GPS-based times moved onto now by one shift (+- the 1 ms of time_boot_ms)
    for src in by:
        s = np.array([m["stamp_us"] - m["autopilot_time_us"] for m in nav if m["source"] == src])
        assert np.ptp(s) <= 1000, src


def test_a_bin_that_is_not_a_dataflash_log_is_refused(tmp_path):
    bad = tmp_path / "flight.bin"
    bad.write_bytes(b"\x00" * 1000)
    code, err, nav, _ = run_ingest(bad, timeout=60)
    assert code == 2, err[-2000:]
    assert "flight.bin: a .bin that is not a dataflash log" in err and "Traceback" not in err and not nav


# -- unknown message ids: two counters, not one per id -------------------------------------------------------------
def test_unknown_message_ids_are_two_counters(tmp_path):
    ML = mavlink2_dialect()
    mav = ML.MAVLink(None, srcSystem=1, srcComponent=1)
    t0 = 1_700_000_000_000_000
    n_unknown, n_att = 1500, 60
    recs = []
    ids = [0x100000 + k for k in range(n_unknown)]                # not defined by the dialect
    assert not any(i in ML.mavlink_map for i in ids)
    for k in range(n_unknown):
        payload = bytes([k & 0xFF, 7, 7])
        pkt = struct.pack("<BBBBBBB", 0xFD, len(payload), 0, 0, k & 0xFF, 1, 1) + ids[k].to_bytes(3, "little")
        recs.append(struct.pack(">Q", t0 + k * 1000) + pkt + payload + b"\x00\x00")
    for k in range(n_att):
        recs.append(struct.pack(">Q", t0 + (n_unknown + k) * 1000)
                    + ML.MAVLink_attitude_message(1000 + k * 20, 0.1, 0, 0, 0, 0, 0).pack(mav))
    p = tmp_path / "unknown.tlog"
    p.write_bytes(b"".join(recs))
    code, err, nav, c = run_ingest(p)
    assert code == 0, err[-3000:]
    assert c["msg.unknown"] == n_unknown and c["unknown_msg_ids"] == 1024
    assert not [k for k in c if "UNKNOWN" in k] and len(c) < 30, sorted(c)
    assert c["msg.ATTITUDE"] == n_att and len(nav) == n_att


# -- the real tlogs, replayed in full ------------------------------------------------------------------------------
def pymavlink_reading(path):
    """Message counts by type, and the nav states NavIngest makes from the messages, both from pymavlink's own tlog
    reader (mavutil's mavlogfile: its own framing, BAD_DATA included)."""
    mavutil = mavutil_v2()
    conn = mavutil.mavlink_connection(str(path), dialect="ardupilotmega", robust_parsing=True)
    ing = NavIngest(NavDecoder(), ClockMapper(prefer=("receive",)))
    types, states = Counter(), []
    while (m := conn.recv_match()) is not None:
        types[m.get_type()] += 1
        if m.get_type() != "BAD_DATA":
            states += ing.feed(m, int(round(m._timestamp * 1e6)))
    states += ing.flush()
    return types, Counter(s["source"] for s in states)


@pytest.mark.realdata
@pytest.mark.parametrize("name", sorted(REAL))
def test_real_tlog_replays_in_full_through_the_service(name):
    path = REAL[name]
    if not path.is_file():
        pytest.skip(f"real tlog not found: {path} (shared data absent)")
    types, states = pymavlink_reading(path)
    code, err, nav, c = run_ingest(path)
    assert code == 0, err[-3000:]
    assert "end of tlog" in err and "Traceback" not in err
    for t, n in types.items():
        if t == "BAD_DATA":
            assert c["bad_data"] == n
        else:
            assert c.get(f"msg.{t}") == n, t
    assert c["tlog_records"] == sum(types.values()) - types["BAD_DATA"]
    assert Counter(m["source"] for m in nav) == states
    assert c["nav_published"] == sum(states.values()) == len(nav)
    if name == "copter":        # the data's README: these counts, 1314 corrupted radio packets
        assert (types["ATTITUDE"], types["GLOBAL_POSITION_INT"], types["LOCAL_POSITION_NED"],
                types["SYSTEM_TIME"], types["BAD_DATA"]) == (2829, 2833, 1161, 2812, 1314)
    else:
        assert (types["ATTITUDE"], types["GLOBAL_POSITION_INT"], types["LOCAL_POSITION_NED"]) == (5245, 792, 792)
