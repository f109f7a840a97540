"""Stale outputs and silent inputs, in process: the age and stamp-order gate (eonav.bus.freshness), the node's
input watch (Node.expect_input / input_seen: both sides of each budget), the frame_age_ms field, and replays that
resume where the clock says they are (camera folder, tlog) instead of starting over. The same behaviour with real
processes and faults: tests/test_faults.py."""
from __future__ import annotations

import argparse
import logging
import math
import threading
import time

import cv2
import numpy as np
import pytest

from eonav import EonavError, InputError
from eonav.bus import schema
from eonav.bus.freshness import FreshnessGate, screen
from eonav.bus.node import Node
from eonav.services import camera_ingest as C
from eonav.services import mavlink_ingest as MI
from eonav.sim.record import DEFAULT_START_UNIX_US, write_tlog

NOW_US = 1_800_000_000_000_000


# ---- the gate ----------------------------------------------------------------------------------------------

def test_gate_age_limit_both_sides():
    g = FreshnessGate(0.5, max_ahead_s=1.0, clock_us=lambda: NOW_US)
    assert g.check("nose", NOW_US - 500_000) is None                 # exactly the limit: still current
    assert g.check("nose", NOW_US - 500_001) == "too_old"
    assert g.check("nose", NOW_US + 1_000_000) is None               # ahead by the tolerance
    assert g.check("nose", NOW_US + 1_000_001) == "future_stamp"
    assert g.max_age_s == 0.5
    for bad in (0, -1, math.nan, math.inf, "1"):
        with pytest.raises(InputError, match="max age"):
            FreshnessGate(bad)
    with pytest.raises(InputError, match="max ahead"):
        FreshnessGate(1.0, max_ahead_s=-0.1)


def test_gate_never_lets_a_camera_go_backwards():
    g = FreshnessGate(1.0, clock_us=lambda: NOW_US)
    g.commit("nose", NOW_US - 100_000)
    assert g.check("nose", NOW_US - 100_001) == "out_of_order"        # one microsecond older than the last put
    assert g.check("nose", NOW_US - 100_000) is None                  # the same stamp again: not older
    assert g.check("tail", NOW_US - 900_000) is None                  # each camera on its own
    g.commit("nose", NOW_US - 300_000)                                # an older commit does not lower the mark
    assert g.last_published_us("nose") == NOW_US - 100_000


def test_gate_starts_a_camera_afresh_after_the_clock_steps_back():
    now = {"us": NOW_US}
    g = FreshnessGate(1.0, max_ahead_s=1.0, clock_us=lambda: now["us"])
    g.commit("nose", NOW_US)
    now["us"] = NOW_US - 1_000_000                                    # stepped back by the tolerance: still held
    assert g.check("nose", now["us"]) == "out_of_order"
    now["us"] = NOW_US - 1_000_001                                    # beyond it: the old mark is dropped
    assert g.check("nose", now["us"]) is None
    assert g.last_published_us("nose") is None


def test_screen_counts_and_logs_the_reason():
    n = _node()
    g = FreshnessGate(0.2, clock_us=lambda: NOW_US)
    assert screen(n, g, "nose", NOW_US - 100_000, "arrival")
    assert not screen(n, g, "nose", NOW_US - 300_000, "arrival")
    assert not screen(n, g, "nose", NOW_US + 5_000_000, "publish")
    g.commit("nose", NOW_US - 50_000)
    assert not screen(n, g, "nose", NOW_US - 60_000, "publish")
    c = n.counters()
    assert (c["dropped.too_old"], c["dropped.future_stamp"], c["dropped.out_of_order"]) == (1, 1, 1)


# ---- frame_age_ms on the bus ----------------------------------------------------------------------------------

def _map_fields(**kw):
    from eonav.geometry.camera import Camera
    cam = Camera("c", 4, 3, 4.0, 4.0, 1.5, 1.0)
    return dict(camera_id="nose", seq=1, stamp_us=NOW_US, method="x", range_m=np.ones((3, 4), np.float32),
                confidence=np.ones((3, 4), np.float16), camera=schema.camera_to_msg(cam),
                position_ned_m=[0.0, 0.0, 0.0], q_wxyz=[1.0, 0.0, 0.0, 0.0], **kw)


def test_frame_age_field_on_range_maps_and_obstacle_lists():
    m = schema.decode(schema.encode("range_map", **_map_fields(frame_age_ms=42.5)))
    assert m["frame_age_ms"] == 42.5
    assert math.isnan(schema.decode(schema.encode("range_map", **_map_fields()))["frame_age_ms"])   # unknown
    o = schema.decode(schema.encode("obstacle_list", stamp_us=NOW_US, obstacles=[], frame_age_ms=7.0))
    assert o["frame_age_ms"] == 7.0
    assert schema.decode(schema.encode("obstacle_list", stamp_us=1, obstacles=[],
                                       frame_age_ms=-schema.MAX_AGE_MS))["frame_age_ms"] == -schema.MAX_AGE_MS
    # a replay of a week-old recording with the age gates lifted (the golden recording's replay): a real age
    week_ms = 7 * 86_400_000.0
    assert schema.decode(schema.encode("range_map", **_map_fields(frame_age_ms=week_ms)))["frame_age_ms"] == week_ms
    for bad in (math.inf, schema.MAX_AGE_MS * 1.001):
        with pytest.raises(schema.SchemaError, match="frame_age_ms") as e:
            schema.decode(schema.encode("obstacle_list", stamp_us=NOW_US, obstacles=[], frame_age_ms=bad))
        assert e.value.reason == "range"


def test_frame_age_negative_side_of_the_limit():
    """The age limit holds on magnitude: -MAX_AGE_MS (a publisher's clock behind) passes, -inf or beyond it is
    refused, as +inf is (an age of -inf would pass every freshness gate)."""
    def obstacle_list(age):
        return schema.decode(schema.encode("obstacle_list", stamp_us=NOW_US, obstacles=[], frame_age_ms=age))
    assert obstacle_list(-schema.MAX_AGE_MS)["frame_age_ms"] == -schema.MAX_AGE_MS
    for bad in (-math.inf, -schema.MAX_AGE_MS * 1.001):
        with pytest.raises(schema.SchemaError, match="frame_age_ms") as e:
            obstacle_list(bad)
        assert e.value.reason == "range"
        with pytest.raises(schema.SchemaError, match="frame_age_ms"):
            schema.decode(schema.encode("range_map", **_map_fields(frame_age_ms=bad)))


# ---- the node's input watch ------------------------------------------------------------------------------------

def _node(grace_s=10.0):
    args = argparse.Namespace(vehicle="v", input_grace_s=grace_s, health_period_s=1.0)
    n = Node("svc", args, session=None, log=logging.getLogger("test.staleness"))
    return n


def test_input_silent_after_its_budget_and_ok_when_it_flows_again():
    n = _node()
    n.expect_input("frames", 1.0, now=100.0)
    n.input_seen("frames", now=100.5)
    assert not n.check_inputs(now=101.5) and n.state == "ok"           # silent exactly the budget: ok
    assert n.check_inputs(now=101.501) and n.state == "degraded"       # just past it: degraded, a change
    st = n.health_fields()
    assert st["state"] == "degraded" and "no frames for" in st["detail"] and "budget 1.00 s" in st["detail"]
    assert not n.check_inputs(now=103.0)                                # still silent: no change
    n.input_seen("frames", now=103.1)
    assert n.check_inputs(now=103.2) and n.state == "ok"                # flowing again
    assert n.silent_inputs() == []


def test_input_grace_before_the_first_sample():
    n = _node(grace_s=5.0)
    n.expect_input("range maps", 0.5, now=10.0)
    assert not n.check_inputs(now=15.0) and n.state == "ok"            # the grace, not the 0.5 s budget
    assert n.check_inputs(now=15.001) and n.state == "degraded"
    assert "no range maps yet after 5.0 s" in n.silent_inputs()[0]
    n.expect_input("nav", 2.0, grace_s=1.0, now=20.0)                   # a grace shorter than the budget: the budget
    n.input_seen("range maps", now=21.9)
    n.check_inputs(now=22.0)
    assert n.state == "ok"
    n.check_inputs(now=22.001)
    assert n.state == "degraded" and n.silent_inputs() == ["no nav yet after 2.0 s"]
    with pytest.raises(EonavError, match="timeout must be > 0"):
        n.expect_input("x", 0)


def test_silent_input_named_and_combined_with_the_services_own_state():
    n = _node()
    n.expect_input("frames", 1.0, now=0.0)
    n.expect_input("nav", 0.5, now=0.0)
    n.input_seen("frames", now=1.0)
    n.input_seen("nav", now=1.0)
    n.check_inputs(now=1.6)                                             # nav silent 0.6 s, frames 0.6 s
    assert n.state == "degraded" and n.silent_inputs() == ["no nav for 0.6 s (budget 0.50 s)"]
    n.set_state("degraded", "locate failing")                           # the service's own reason is kept
    assert n._reported_state() == ("degraded", "no nav for 0.6 s (budget 0.50 s); locate failing")
    n.set_state("ok")
    n.fail("worker died")                                               # an error is never masked
    assert n.state == "error" and n.health_fields()["detail"] == "worker died"


class _HealthPub:
    """A health publisher that keeps what it was given, decoded."""
    def __init__(self):
        self.got = []

    def put(self, payload):
        self.got.append(schema.decode(payload, expect="health"))


def _run_health_loop(node, until, timeout_s: float = 20.0):
    """Run the node's own health loop (the worker body of _declare_infrastructure) until ``until()`` holds (checked
    every 10 ms) or ``timeout_s`` has passed: the loop's own timing decides what it publishes, and a loaded machine
    only makes it take longer."""
    t = threading.Thread(target=_health_loop(node))
    t.start()
    try:
        deadline = time.monotonic() + timeout_s
        while not until() and time.monotonic() < deadline:
            threading.Event().wait(0.01)
    finally:
        node.stop_event.set()
        t.join(5)


def test_health_timer_publishes_at_once_when_an_input_falls_silent():
    n = _node()
    n.args.health_period_s = 30.0                                         # the periodic message would be far away
    n._health_pub = pub = _HealthPub()
    n.expect_input("frames", 0.2)
    n.input_seen("frames")
    _run_health_loop(n, lambda: any(h["state"] == "degraded" for h in pub.got))
    states = [h["state"] for h in pub.got]
    assert states[0] == "ok" and "degraded" in states, states          # first message, then the change at once
    assert len(pub.got) == 2, states


def test_health_timer_reports_a_silence_that_ends_before_its_message():
    # the input resumes between the timer's check and the message it sends (seen on a loaded machine: the
    # silence was found and then re-checked away inside the message, so no degraded health was ever published)
    n = _node()
    n.args.health_period_s = 30.0
    n.expect_input("frames", 0.2)
    n.input_seen("frames")
    real_check = n.check_inputs

    def check_then_sample(now=None):                   # a sample lands right after each check that finds a silence
        changed = real_check(now)
        if n.silent_inputs():
            n.input_seen("frames")
        return changed
    n.check_inputs = check_then_sample
    n._health_pub = pub = _HealthPub()
    _run_health_loop(n, lambda: "degraded" in [h["state"] for h in pub.got] and pub.got[-1]["state"] == "ok")
    states = [h["state"] for h in pub.got]
    assert "degraded" in states, states                             # the silence was published ...
    assert states[-1] == "ok", states                               # ... and the recovery after it


def _health_loop(node):
    """The health worker's body as ``Node._declare_infrastructure`` defines it (declared without a session)."""
    captured = {}

    class FakeSession:
        def liveliness(self):
            return self

        def declare_token(self, key):
            return None

        def declare_publisher(self, key, **kw):
            return node._health_pub

        def declare_queryable(self, key, handler):
            class Q:
                def __iter__(self):
                    return iter(())

                def undeclare(self):
                    pass
            return Q()

    pub = node._health_pub
    node.session = FakeSession()
    node.worker = lambda fn, *a, name=None: captured.setdefault(name, fn)
    node._declare_infrastructure()
    node._health_pub = pub
    return captured["health"]


# ---- replays resume where the clock says --------------------------------------------------------------------

class FakeClock(C.Clock):
    def __init__(self, now_us):
        self.us = now_us

    def now_us(self):
        return self.us

    def monotonic(self):
        return self.us / 1e6

    def sleep(self, s, stop=None):
        self.us += max(0, int(round(s * 1e6)))


def _folder(tmp_path, n=10, dt_s=0.1):
    d = tmp_path / "rec"
    d.mkdir()
    for i in range(n):
        cv2.imwrite(str(d / f"f{i:03d}.png"), np.full((8, 8), i, np.uint8))
    (d / "timestamps.txt").write_text("".join(f"{100 + i * dt_s:.6f}\n" for i in range(n)))
    return d


def test_camera_replay_restarted_midway_resumes_at_the_due_frame(tmp_path):
    d = _folder(tmp_path)
    first_us = 100_000_000
    # frame i is due at shift + 100 s + i * 0.1 s; the replay (re)starts when frame 4 was due 0.1 s ago exactly
    # (RESUME_LATE_US): frames 0-3 are passed over, frame 4 is the first published, seq continues from the file
    clock = FakeClock(NOW_US)
    shift = NOW_US - C.RESUME_LATE_US - (first_us + 400_000)
    out = []
    st = C.capture_loop(C.folder_frames(d, clock=clock, replay_shift_us=shift), out.append, camera_id="nose")
    assert [f["seq"] for f in out] == list(range(4, 10)) and st.skipped == 4
    assert [int(f["image"][0, 0]) for f in out] == list(range(4, 10))
    assert out[0]["stamp_us"] == first_us + 400_000 + shift            # due 0.1 s ago: published at once
    assert all(f["stamp_us"] >= NOW_US - C.RESUME_LATE_US for f in out)
    # one microsecond later, frame 4 is past the limit too
    clock = FakeClock(NOW_US + 1)
    out = []
    C.capture_loop(C.folder_frames(d, clock=clock, replay_shift_us=shift), out.append, camera_id="nose")
    assert out[0]["seq"] == 5


def test_replay_restarted_without_a_time_reference_ends(tmp_path, monkeypatch):
    d = _folder(tmp_path)
    from eonav.services.camera_ingest import add_arguments, body
    from eonav.bus.node import build_parser
    args = build_parser("camera", add_arguments).parse_args(["--source", str(d)])
    n = _node()
    monkeypatch.setenv("EONAV_RESTART_COUNT", "1")
    body(n, args)
    assert n.stop_event.is_set() and "cannot resume" in n.stop_reason
    monkeypatch.setenv("EONAV_RESTART_COUNT", "0")                      # the first start replays
    n2 = _node()
    n2.publisher = lambda key, image=False: None
    n2.worker = lambda fn, *a, name=None: None
    body(n2, args)
    assert not n2.stop_event.is_set()


def test_tlog_replay_restarted_midway_fast_forwards_and_resumes(tmp_path):
    p = tmp_path / "f.tlog"
    write_tlog(p, "turning", 3.0, start_unix_us=DEFAULT_START_UNIX_US, boot_offset_us=DEFAULT_START_UNIX_US - 10**8,
               latency_us=(1000, 3000), seed=3)
    with open(p, "rb") as f:
        first_hdr = int.from_bytes(f.read(8), "big")
    now = {"us": NOW_US}

    def sleep(s):
        now["us"] += int(round(s * 1e6))

    shift = NOW_US - C.RESUME_LATE_US - first_hdr - 1_500_000          # restarted 1.6 s into the recording
    fed, skipped = [], []
    MI.replay_tlog(p, lambda m, rx: fed.append(rx), speed=1.0, stop=threading.Event(), clock=lambda: now["us"],
                   sleep=sleep, shift_us=shift, skip=lambda m, rx: skipped.append(rx))
    assert skipped and fed
    assert max(skipped) < NOW_US - C.RESUME_LATE_US <= min(fed)        # nothing older than the limit is fed
    assert np.all(np.diff(fed) >= 0) and np.all(np.diff(skipped) >= 0)
    with MI.TlogReader(p) as reader:
        headers = [h for h, _ in reader]
    assert len(skipped) == sum(h < first_hdr + 1_500_000 for h in headers) > 100    # the first 1.5 s of records
    assert len(skipped) + len(fed) == len(headers)


def test_tlog_replay_resumes_at_a_record_due_exactly_the_limit_ago(tmp_path):
    """As the camera replay's: a record due exactly RESUME_LATE_US (0.1 s) ago when the replay (re)starts is fed,
    one due a microsecond longer ago is passed over, so the frames and the tlog of one joint replay resume at the
    same line."""
    p = tmp_path / "f.tlog"
    write_tlog(p, "turning", 1.0, start_unix_us=DEFAULT_START_UNIX_US, boot_offset_us=DEFAULT_START_UNIX_US - 10**8,
               latency_us=(1000, 3000), seed=4)
    with MI.TlogReader(p) as reader:
        headers = [h for h, _ in reader]
    k = 40
    assert headers[k - 1] < headers[k] < headers[k + 1]
    assert MI.RESUME_LATE_US == C.RESUME_LATE_US == 100_000
    for late_us, first_fed in ((100_000, k), (100_001, k + 1)):
        now = {"us": NOW_US}

        def sleep(s):
            now["us"] += int(round(s * 1e6))

        shift = NOW_US - late_us - headers[k]                              # record k due late_us ago
        fed, skipped = [], []
        MI.replay_tlog(p, lambda m, rx: fed.append(rx), speed=1.0, stop=threading.Event(), clock=lambda: now["us"],
                       sleep=sleep, shift_us=shift, skip=lambda m, rx: skipped.append(rx))
        assert len(skipped) == first_fed and fed[0] == headers[first_fed] + shift, late_us
        assert len(fed) == len(headers) - first_fed


def test_status_line_shows_the_silent_input():
    import time as _t
    from eonav.app import launcher as L
    p = L.Proc(L.ServiceSpec(name="sync", module="m"), state="running")
    p.health = {"state": "degraded", "detail": "no frames for 1.3 s (budget 1.00 s); no nav for 0.6 s",
                "rates_hz": {}, "latency_ms": {}, "counters": {"dropped.too_old": 4}}
    p.health_mono = _t.monotonic()
    line = L._fmt_service(p, _t.monotonic())
    assert line.startswith("sync degraded(no frames for 1.3 s (budget 1.00 s))") and "drops 4" in line, line
    p.health = dict(p.health, state="ok", detail="clock receive")
    assert L._fmt_service(p, _t.monotonic()).startswith("sync ok"), "an ok detail is not shown"
