"""End to end over a real zenoh bus on loopback: the launcher's embedded router and five real service processes
(camera ingest replaying the recorded frames, MAVLink ingest replaying the recorded tlog, sync, locator,
obstacles) fed by ``eonav.sim.record.record_flight``; the demo's monitor scores what comes out against the
recording's ground truth (range per pixel, true box positions)."""
import math

import pytest

from eonav.app.demo import format_summary, run_demo

pytestmark = pytest.mark.pipeline   # real services against real-time budgets: one such test at a time

SERVICES = ("camera", "mavlink", "sync", "locator", "obstacles")


def test_pipeline_end_to_end(tmp_path):
    # 12 frames at 5 Hz, 256 x 256, starting 3 s into the approach flight (navigation lead): the nearest box
    # in view is the pole beside the flight path
    s = run_demo(n_frames=12, rate_hz=5.0, size=256, seed=0, cache_dir=tmp_path / "rec", png=tmp_path / "r.png",
                 vehicle="e2e", quiet=True, log_dir=str(tmp_path / "logs"), timeout_s=120.0)
    print(format_summary(s))
    assert s["exit_code"] == 0 and s["pipeline_exit"] == 0, s
    assert s["verdict"] == "ok", s["verdict_reasons"]
    # every process ran and exited cleanly: the replays at their end (0), the others on the launcher's SIGINT (0)
    assert s["exit_codes"] == {name: 0 for name in SERVICES}, s["exit_codes"]
    assert s["service_states"]["camera"] == "done" and s["service_states"]["mavlink"] == "done"
    assert all(s["service_states"][n] == "stopped" for n in ("sync", "locator", "obstacles"))
    # every service published health: "ok" while the replay ran; once it ended, the services fed by it may report
    # their silent input ("degraded"), never an error
    assert set(s["health_states_seen"]) >= set(SERVICES), s["health_states_seen"]
    assert s["health_not_ok_while_fed"] == [], s["health_not_ok_while_fed"]
    assert all(set(v) <= {"ok", "degraded"} and "ok" in v for k, v in s["health_states_seen"].items()
               if k in SERVICES), s["health_states_seen"]
    # range maps arrive and match the ground truth
    assert s["frames_seen"] == 12
    assert s["range_maps"] >= 8, s["drops"]
    assert s["median_rel_error"] < 0.05 and s["worst_map_median_rel_error"] < 0.10
    assert s["coverage"] > 0.15
    # the nearest box is in the obstacle list at its true distance (within 8 %)
    assert s["obstacle_lists"] >= 3
    assert s["nearest_box"] == "pole"
    assert s["nearest_box_found_fraction"] >= 0.6, s["nearest_box_found"]
    assert s["nearest_box_median_rel_error"] < 0.08
    lr = s["latency_capture_to_range_ms"]
    assert lr["n"] >= 8 and math.isfinite(lr["p50"])
    assert s["bad_messages"] == 0
    assert (tmp_path / "r.png").is_file()
