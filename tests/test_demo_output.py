"""The demo's output: the picture (estimate and truth side by side, a colour bar in metres, obstacle boxes at their
bbox with their range; checked pixel by pixel against a synthetic map of known ranges), the ok / degraded / failed
verdict on both sides of its threshold, the monitor's figures against the truth (range error and coverage on VALID
pixels, the nearest box matched at its bearing from the nose; hand-made maps and lists), and where a run writes
(per-user cache, per-run folder where it is run)."""
from __future__ import annotations

import json
import math
import os
import subprocess
import sys

import numpy as np
import pytest

from eonav.app import demo as D
from eonav.io import viz as V

NEAR_M, FAR_M = 5.0, 150.0


def _colour(range_m):
    """The colour the scale gives ``range_m`` (one pixel through inverse_range_colours)."""
    return V.inverse_range_colours(np.array([[range_m]], np.float32), np.ones((1, 1), bool), NEAR_M, FAR_M)[0, 0]


def _scene():
    """A 64 x 64 map on the half-resolution grid of a 128 x 128 frame: 100 m background, a 10 m block at map pixels
    (20..35, 12..27), a hole (no estimate) at rows 50..55; the truth: the same, 120 m background."""
    r = np.full((64, 64), 100.0, np.float32)
    r[12:28, 20:36] = 10.0
    valid = np.ones((64, 64), bool)
    valid[50:56, :] = False
    truth = np.where(r == 10.0, 10.0, 120.0).astype(np.float32)
    # the obstacle list is in frame pixels (2x the map's): the block is frame pixels 40..71 x 24..55
    obstacle = {"id": 3, "distance_m": 10.4, "bbox_px": [40, 24, 71, 55]}
    return r, valid, truth, obstacle


def test_picture_has_estimate_truth_colour_bar_and_obstacle_boxes():
    r, valid, truth, ob = _scene()
    pic, lay = V.estimate_truth_picture(r, valid, truth, obstacles=[ob], frame_size=(128, 128), near_m=NEAR_M,
                                        far_m=FAR_M)
    k, top, (x_est, x_truth), bar_x = lay["scale"], lay["title_px"], lay["tiles"], lay["bar_x"]
    assert k == 6 and pic.shape[0] == top + 64 * k                     # 64 rows enlarged to >= 384
    px = lambda x0, u, v: pic[top + v * k + k // 2, x0 + u * k + k // 2]   # centre of map pixel (u, v)
    # the tiles: estimate and truth on one scale, black where there is no estimate
    assert np.array_equal(px(x_est, 5, 5), _colour(100.0)) and np.array_equal(px(x_truth, 5, 5), _colour(120.0))
    assert np.array_equal(px(x_est, 28, 20), _colour(10.0)) and np.array_equal(px(x_truth, 28, 20), _colour(10.0))
    assert not px(x_est, 5, 52).any() and px(x_truth, 5, 52).any()
    # the colour bar: each row the colour of the range it stands for, near (top) to far (bottom), labelled in metres
    bar_h = 64 * k
    for r_m in (NEAR_M, 10.0, 20.0, 50.0, 100.0, FAR_M):
        y = top + int(round(V.bar_row(r_m, bar_h, NEAR_M, FAR_M)))
        np.testing.assert_allclose(pic[y, bar_x + 4].astype(int), _colour(r_m).astype(int), atol=3)
    labels = pic[top:, bar_x + V.BAR_WIDTH_PX + 6:]
    ticks = V.bar_ticks(bar_h, NEAR_M, FAR_M)
    for r_m, y in ticks:
        assert (labels[max(0, y - 6):y + 6] > 200).all(axis=2).any(), f"no label at {r_m} m"
    # 1-2-5 steps; 100 m is 7 px from 150 m on this bar: left out, so no two labels overlap
    assert V.nice_ticks_m(NEAR_M, FAR_M) == [5.0, 10.0, 20.0, 50.0, 100.0, 150.0]
    assert [r_m for r_m, _ in ticks] == [5.0, 10.0, 20.0, 50.0, 150.0]
    assert not (labels[ticks[-2][1] + 8:ticks[-1][1] - 10] > 200).all(axis=2).any()   # nothing between 50 and 150
    # the obstacle box: frame bbox [40, 24, 71, 55] -> map pixels 20..35 x 12..27 -> picture pixels x k, both tiles
    u0, v0, u1, v1 = 20 * k, 12 * k, 36 * k - 1, 28 * k - 1
    for x0 in (x_est, x_truth):
        t = pic[top:, x0:x0 + 64 * k]
        for edge in (t[v0, u0:u1 + 1], t[v1, u0:u1 + 1], t[v0:v1 + 1, u0], t[v0:v1 + 1, u1]):
            assert (edge == V.BOX_BGR).all()
        assert np.array_equal(t[v0 + 1, u0 + 1], _colour(10.0))          # just inside: the map, not the box
        outside = _colour(100.0 if x0 == x_est else 120.0)
        assert np.array_equal(t[(v0 + v1) // 2, u0 - 1], outside)        # just outside: the map
        assert np.array_equal(t[(v0 + v1) // 2, u1 + 1], outside)
        label = t[v0 - 14:v0 - 1, u0:u0 + 60]
        assert (label > 200).all(axis=2).sum() > 20                      # "10.4 m" above the box
    # without the obstacle list the same pixels are the map's
    bare, _ = V.estimate_truth_picture(r, valid, truth, frame_size=(128, 128), near_m=NEAR_M, far_m=FAR_M)
    assert np.array_equal(bare[top + v0, x_est + u0 + 5], _colour(10.0))
    assert not (bare[top + v0 - 14:top + v0 - 1, x_est + u0:x_est + u0 + 60] > 200).all(axis=2).any()


def test_demo_range_picture_boxes_the_obstacles_on_the_messages_grid():
    # a range map message at the locate scale (its arrays 64 x 64, frame 128 x 128): the box lands as above
    from eonav.ranging.rangemap import VALID
    r, valid, truth, ob = _scene()
    msg = {"range_m": r, "flags": np.where(valid, VALID, 0).astype(np.uint8), "frame_width": 128,
           "frame_height": 128}
    far = [dict(ob, id=10 + i, distance_m=60.0 + i, bbox_px=[2 * i, 100, 2 * i + 1, 101]) for i in range(8)]
    pic = D.range_picture(msg, truth, obstacles=far + [ob], max_boxes=3)
    k, top = 6, 20
    assert (pic[top + 12 * k, 20 * k:36 * k] == V.BOX_BGR).all()        # the nearest obstacle is boxed
    boxed = [(pic[top + 50 * k, i * k] == V.BOX_BGR).all() for i in range(8)]
    assert boxed == [True, True] + [False] * 6                           # and the next two nearest only
    assert not pic[top + 52 * k, 10 * k + 3].any()                       # flags: no estimate in the hole


def test_boxes_follow_each_axis_of_a_map_on_an_anisotropic_grid():
    """A 48 x 32 map of a 96 x 128 frame (x halved, y quartered): k = ceil(384 / 32) = 12, so a frame pixel is 6
    picture pixels wide and 3 high. The 10 m block at map pixels u 10..19, v 8..15 is frame bbox [20, 32, 39, 63]:
    its box must run over picture columns 120..239 and rows 96..191, the block's own pixels (hand-derived). Catches
    the x and y scales swapped (invisible on a square frame)."""
    r = np.full((32, 48), 100.0, np.float32)
    r[8:16, 10:20] = 10.0
    ob = {"id": 1, "distance_m": 10.0, "bbox_px": [20, 32, 39, 63]}
    pic, lay = V.estimate_truth_picture(r, np.ones(r.shape, bool), obstacles=[ob], frame_size=(96, 128),
                                        near_m=NEAR_M, far_m=FAR_M)
    assert lay["scale"] == 12 and lay["tiles"] == [0]
    t = pic[lay["title_px"]:, :48 * 12]
    u0, v0, u1, v1 = 120, 96, 239, 191
    for edge in (t[v0, u0:u1 + 1], t[v1, u0:u1 + 1], t[v0:v1 + 1, u0], t[v0:v1 + 1, u1]):
        assert (edge == V.BOX_BGR).all()
    assert np.array_equal(t[v0 + 1, u0 + 1], _colour(10.0)) and np.array_equal(t[v1 - 1, u1 - 1], _colour(10.0))
    assert np.array_equal(t[(v0 + v1) // 2, u1 + 1], _colour(100.0))
    assert np.array_equal(t[v1 + 1, (u0 + u1) // 2], _colour(100.0))


@pytest.mark.parametrize("rows,k", [(64, 6), (100, 4), (383, 2), (384, 1), (385, 1)])
def test_maps_are_enlarged_by_the_smallest_whole_factor_reaching_the_minimum_height(rows, k):
    """min_height_px = 384: a map of ``rows`` rows is enlarged k = ceil(384 / rows) times (hand: 100 rows -> 4, i.e.
    400 >= 384 rows; 383 -> 2), never below the minimum. Catches the factor rounded down (100 rows -> 3 = 300)."""
    pic, lay = V.estimate_truth_picture(np.full((rows, 4), 10.0, np.float32), np.ones((rows, 4), bool),
                                        near_m=NEAR_M, far_m=FAR_M)
    assert lay["scale"] == k and pic.shape[0] == lay["title_px"] + rows * k and rows * k >= 384


def test_truth_beyond_the_far_end_of_the_scale_is_black():
    """The truth tile is black where the truth is beyond ``far_m`` (150 m), infinite or not positive; the estimate
    tile shows every VALID pixel, one beyond the scale in its far colour. Catches the truth's far cut dropped (a
    truth of 151 m drawn as if it were 150 m, beside an estimate that is)."""
    truth = np.array([[149.0, 151.0, 400.0, np.inf, 0.0]], np.float32)
    est = np.full(truth.shape, 200.0, np.float32)
    pic, lay = V.estimate_truth_picture(est, np.ones(est.shape, bool), truth, near_m=NEAR_M, far_m=FAR_M,
                                        min_height_px=1)
    top, (x_est, x_truth) = lay["title_px"], lay["tiles"]
    assert lay["scale"] == 1
    assert np.array_equal(pic[top, x_truth], _colour(149.0)) and _colour(149.0).any()
    assert not pic[top, x_truth + 1:x_truth + 5].any()                  # 151 m, 400 m, inf, 0: black
    assert (pic[top, x_est:x_est + 5] == _colour(FAR_M)).all() and _colour(FAR_M).any()


def test_range_picture_dims_the_least_confident_tenth():
    """``range_picture`` (eonav locate --png): confidences 1..100 on a 10 x 10 map at 20 m (scale 20..100 m, so
    every pixel the near end's colour C): the 10th percentile of the positive confidences is 10.9, so exactly the
    ten pixels of confidence 1..10 are drawn at C / 2 (floored) and the other ninety at C. Catches the dimming
    applied to the most confident instead, or not at all."""
    import cv2
    c = np.arange(1, 101, dtype=np.float32).reshape(10, 10)
    out = V.range_picture(np.full((10, 10), 20.0, np.float32), max_range_m=100.0, confidence=c)
    C = cv2.applyColorMap(np.full((1, 1), 255, np.uint8), cv2.COLORMAP_TURBO)[0, 0]
    dim = c <= 10
    assert (out[~dim] == C).all()
    assert (out[dim] == C // 2).all() and not np.array_equal(C // 2, C)


# ---- verdict ----------------------------------------------------------------------------------------------

def test_verdict_on_both_sides_of_the_threshold():
    # 16 frames recorded, 15 can have a range map (the first has no earlier frame to pair with); threshold 80 %
    assert D.MIN_FRACTION == 0.8
    assert D.verdict(16, 16, 15) == ("ok", [])
    assert D.verdict(16, 13, 12) == ("ok", [])            # 13 >= 12.8 frames, 12 >= 12.0 maps
    state, why = D.verdict(16, 12, 12)                    # 12 < 12.8 frames
    assert state == "degraded" and len(why) == 1 and "12/16 frames seen" in why[0]
    state, why = D.verdict(16, 16, 11)                    # 11 < 12.0 maps
    assert state == "degraded" and len(why) == 1 and "11 range maps for 15" in why[0]
    state, why = D.verdict(16, 12, 7)                     # the run of the issue: both
    assert state == "degraded" and len(why) == 2


def _summary(seen, maps, recorded=16):
    return {"frames_recorded": recorded, "frames_seen": seen, "range_maps": maps}


def test_outcome_exit_codes_and_the_summary_line():
    ok = D.outcome(_summary(16, 15), 0, "replay ended, every frame ranged")
    assert ok == {"verdict": "ok", "verdict_reasons": [], "exit_code": 0}
    bad = D.outcome(_summary(12, 7), 0, "replay ended, pipeline drained")
    assert bad["verdict"] == "degraded" and bad["exit_code"] == 1
    assert D.outcome(_summary(16, 15), 1, "replay ended")["verdict"] == "failed"
    assert D.outcome(_summary(16, 15), 0, "timeout 180 s")["exit_code"] == 1
    assert D.outcome(_summary(16, 0), 0, "replay ended")["verdict"] == "failed"
    s = {"recording": "r", "frames_seen": 12, "frames_recorded": 16, "range_maps": 7, "median_rel_error": 0.01,
         "worst_map_median_rel_error": 0.02, "coverage": 0.5, "obstacle_lists": 7, "nearest_box": "pole",
         "nearest_box_found": "6/7", "nearest_box_median_rel_error": 0.02, "compute_ms_p50": 30.0,
         "latency_capture_to_range_ms": {"p50": 40.0, "p99": 50.0, "n": 7},
         "latency_capture_to_obstacles_ms": {"p50": 45.0, "p99": 55.0, "n": 7},
         "drops": {}, "service_states": {}, "exit_codes": {}, "stop_reason": "replay ended", **bad}
    line = D.format_summary(s).splitlines()[-1]
    assert line.split()[:2] == ["verdict", "degraded:"] and "12/16 frames seen" in line
    s.update(D.outcome(_summary(16, 15), 0, "replay ended"))
    assert D.format_summary(s).splitlines()[-1].split()[:2] == ["verdict", "ok"]


def test_verdict_exactly_at_the_threshold_is_ok():
    # "fewer than 80 %" degrades, exactly 80 % does not: 8 of 10 frames seen is ok, 7 is not (the maps' side at
    # exactly 80 %, 12 of 15, is above)
    assert D.verdict(10, 8, 9) == ("ok", [])
    state, why = D.verdict(10, 7, 9)
    assert state == "degraded" and len(why) == 1 and "7/10 frames seen" in why[0]


def test_an_interrupted_run_fails_whatever_it_ranged():
    # Ctrl-C after every frame was ranged is still no finished run: failed, exit code 1, the reason given
    out = D.outcome(_summary(16, 15), 0, "interrupted")
    assert out["verdict"] == "failed" and out["exit_code"] == 1 and "stopped: interrupted" in out["verdict_reasons"][0]


# ---- the monitor's figures against the truth --------------------------------------------------------------------

STAMP_US = 1_800_000_000_000_000


class _Truth:
    """Stands in for ``Truth``: one frame (stamped STAMP_US) whose true range is 20 m in the left half of an 8 x 8 grid
    and 50 m in the right half, and whose nearest box, the pole, is 40 m away at bearing 50 deg from north."""
    manifest = {"n_frames": 2}
    range_m = np.hstack([np.full((8, 4), 20.0), np.full((8, 4), 50.0)])[None]

    def index(self, stamp_us):
        return 0 if stamp_us == STAMP_US else None

    def nearest_box(self, i, min_pixels=50):
        return ("pole", 40.0, 50.0)


def _sample(kind, **fields):
    """A bus sample carrying ``kind`` (what the monitor's callbacks take)."""
    from types import SimpleNamespace

    from eonav.bus import schema
    data = schema.encode(kind, stamp_us=STAMP_US, **fields)
    return SimpleNamespace(key_expr="test", payload=SimpleNamespace(to_bytes=lambda: data))


def test_monitor_scores_only_the_valid_pixels_of_a_range_map():
    """The demo's range error and coverage count the pixels the map says are VALID: on those the map is 10 % long
    (error 0.1), on the other two rows it says 5 m (wrong, but flagged: not counted); coverage 48 / 64."""
    from eonav.bus import schema
    from eonav.geometry.camera import Camera
    from eonav.ranging.rangemap import VALID
    r = (_Truth.range_m[0] * 1.1).astype(np.float32)
    flags = np.full((8, 8), VALID, np.uint8)
    r[6:], flags[6:] = 5.0, 0
    mon = D.Monitor("tcp/127.0.0.1:1", "v", _Truth())
    mon._on_range(_sample("range_map", camera_id="nose", seq=1, method="test", range_m=r,
                          confidence=np.ones((8, 8), np.float32), flags=flags,
                          camera=schema.camera_to_msg(Camera("nose", 8, 8, 8.0, 8.0, 3.5, 3.5)),
                          position_ned_m=[0, 0, 0], q_wxyz=[1, 0, 0, 0]), 0.0)
    (score,) = mon.range_scores
    assert score["frame"] == 0 and score["n_valid"] == 48 and score["coverage"] == 0.75
    assert score["median_rel_error"] == pytest.approx(0.1, rel=1e-5)
    assert score["p90_rel_error"] == pytest.approx(0.1, rel=1e-5)
    s = mon.summary()
    assert s["coverage"] == 0.75 and s["median_rel_error"] == pytest.approx(0.1, rel=1e-5)


def test_monitor_finds_the_nearest_box_at_its_bearing_from_the_nose():
    """Obstacle bearings are from the nose (body frame, clockwise): with the vehicle yawed 30 deg (q_wxyz rotates body
    into NED: cos 15 deg, 0, 0, sin 15 deg) the pole at 50 deg from north is 20 deg right of the nose. The obstacle
    there (41 m: 2.5 % long) is the match, not the ones at 50 deg (north-referenced) or 80 deg (yaw added)."""
    mon = D.Monitor("tcp/127.0.0.1:1", "v", _Truth())
    h = math.radians(15.0)
    obstacles = [{"id": 7, "distance_m": 30.0, "bearing_deg": 80.0}, {"id": 8, "distance_m": 35.0, "bearing_deg": 50.0},
                 {"id": 9, "distance_m": 41.0, "bearing_deg": 20.0}]
    mon._on_obstacles(_sample("obstacle_list", camera_id="nose", obstacles=obstacles,
                              q_wxyz=[math.cos(h), 0.0, 0.0, math.sin(h)]), 0.0)
    (score,) = mon.obst_scores
    assert score["truth_box"] == "pole" and score["truth_bearing_deg"] == pytest.approx(20.0)
    assert score["found"] and score["obstacle_id"] == 9 and score["rel_error"] == pytest.approx(0.025)
    s = mon.summary()
    assert s["nearest_box_found"] == "1/1" and s["nearest_box_median_rel_error"] == pytest.approx(0.025)


# ---- where a run writes ---------------------------------------------------------------------------------------

def test_cache_is_per_user_and_run_folders_are_per_run(tmp_path, monkeypatch):
    monkeypatch.delenv("XDG_CACHE_HOME", raising=False)
    recs = {}
    for user in ("alice", "bob"):
        home = tmp_path / user
        home.mkdir()
        monkeypatch.setenv("HOME", str(home))
        assert D.default_cache_dir() == home / ".cache" / "eonav" / "demo"
        recs[user] = D.recording(n_frames=2, rate_hz=5.0, size=48)
        files = {p for p in recs[user].rglob("*") if p.is_file()}
        assert files and all(p.is_relative_to(home) for p in files)
    assert recs["alice"] != recs["bob"] and recs["alice"].name == recs["bob"].name   # same key, own copies
    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path / "xdg"))
    assert D.default_cache_dir() == tmp_path / "xdg" / "eonav" / "demo"
    monkeypatch.setenv("XDG_CACHE_HOME", "relative/cache")                # not absolute: ignored, as the spec says
    assert D.default_cache_dir() == tmp_path / "bob" / ".cache" / "eonav" / "demo"
    # two runs in one place never share a folder
    a, b = D.new_run_dir(tmp_path / "out"), D.new_run_dir(tmp_path / "out")
    assert a != b and a.parent == b.parent == tmp_path / "out" and a.name.startswith("eonav-demo-")
    monkeypatch.chdir(tmp_path / "alice")
    assert D.new_run_dir().parent == tmp_path / "alice"


@pytest.mark.pipeline
def test_demo_command_writes_its_run_folder_where_it_is_run(tmp_path):
    pytest.importorskip("zenoh")
    home, work = tmp_path / "home", tmp_path / "work"
    home.mkdir()
    work.mkdir()
    env = {k: v for k, v in os.environ.items() if k != "XDG_CACHE_HOME"}
    env.update(HOME=str(home), PYTHONUNBUFFERED="1")
    out = subprocess.run([sys.executable, "-m", "eonav.app.demo", "--frames", "8", "--size", "128", "--json"],
                         cwd=work, env=env, capture_output=True, text=True, timeout=150)
    assert out.returncode == 0, out.stdout + out.stderr
    (run,) = list(work.iterdir())
    assert run.name.startswith("eonav-demo-")
    assert {p.name for p in run.iterdir()} == {"range.png", "summary.json", "logs"}
    assert {"camera.log", "mavlink.log", "sync.log", "locator.log", "obstacles.log"} <= {
        p.name for p in (run / "logs").iterdir()}
    s = json.loads((run / "summary.json").read_text())
    assert s["verdict"] == "ok" and s["png"] == str(run / "range.png") and s["range_maps"] >= 6
    assert s["recording"].startswith(str(home / ".cache" / "eonav" / "demo"))       # the cache: this user's
    assert "verdict              ok" in out.stdout
