"""``eonav fuse`` end to end on a written simulated sequence (real process, real files) and its error paths."""
import json
import subprocess
import sys

import numpy as np
import pytest

ARRAYS = ("range_m", "confidence", "inv_range_per_m", "inv_range_std_per_m", "flags", "n_fused")


def eonav(*args, check=True):
    out = subprocess.run([sys.executable, "-m", "eonav.app.cli", *map(str, args)], capture_output=True, text=True,
                         timeout=240)
    if check:
        assert out.returncode == 0, out.stderr
    return out


@pytest.fixture(scope="module")
def seq_dir(tmp_path_factory):
    from eonav.sim.sequence import render_sequence, write_sequence
    d = tmp_path_factory.mktemp("seq")
    write_sequence(render_sequence("fast", n_frames=6, rate_hz=10.0, size=128, supersample=2, seed=1), d)
    return d


def test_fuse_writes_the_last_map_and_one_per_frame(seq_dir, tmp_path):
    out, maps = tmp_path / "range.npz", tmp_path / "maps"
    r = eonav("fuse", seq_dir / "seq.json", "--out", out, "--out-dir", maps)
    assert "fused 6 frames (5 maps)" in r.stdout
    assert sorted(p.name for p in maps.iterdir()) == [f"range_{k:04d}.npz" for k in range(1, 6)]
    with np.load(out) as z, np.load(maps / "range_0005.npz") as z5:
        assert set(z.files) == set(ARRAYS)
        assert z["range_m"].dtype == np.float32 and z["flags"].dtype == np.uint8 and z["range_m"].shape == (128, 128)
        for k in ARRAYS:                                   # --out is the last frame's map
            assert np.array_equal(z[k], z5[k], equal_nan=True)
        truth = np.load(seq_dir / "truth.npz")["range_m"][-1]
        rng = z["range_m"]
        ok = np.isfinite(truth) & np.isfinite(rng) & (rng > 0)
        assert ok.sum() > 0.7 * np.isfinite(truth).sum()
        assert np.median(np.abs(rng[ok] / truth[ok] - 1)) < 0.05      # independent check against the truth
        assert (z["confidence"][~np.isfinite(rng)] == 0).all()
        assert int(np.median(z["n_fused"][ok])) >= 3


def write_doc(seq_dir, tmp_path, edit):
    doc = json.loads((seq_dir / "seq.json").read_text())
    for fr in doc["frames"]:                               # images stay where they are
        fr["image"] = str(seq_dir / fr["image"])
    edit(doc)
    p = tmp_path / "bad.json"
    p.write_text(json.dumps(doc))
    return p


@pytest.mark.parametrize("edit, needle", [
    (lambda d: d["frames"][2].update(t=-1.0), "frames[2].t: -1.0 is earlier than frames[1].t"),
    (lambda d: d["frames"][1].update(camera="tail"), "frames[1].camera: 'tail' is not one of the cameras ['nose']"),
    (lambda d: d.update(frames=d["frames"][:1]), "frames: eonav fuse needs a sequence of at least 2 frames, got 1"),
    (lambda d: d["frames"][3].pop("t"), "frames[3].t: missing"),
    (lambda d: d["frames"][2].update(t=d["frames"][1]["t"]), "frames[2].t: "),
])
def test_fuse_errors_name_the_field(seq_dir, tmp_path, edit, needle):
    r = eonav("fuse", write_doc(seq_dir, tmp_path, edit), "--out", tmp_path / "o.npz", check=False)
    assert r.returncode == 2 and needle in r.stderr, r.stderr
    assert not (tmp_path / "o.npz").exists()


def test_fuse_without_parallax_says_so(seq_dir, tmp_path):
    # every frame at one position (hover): no pair has parallax, so no map -- an error, not an empty file
    def hover(d):
        for fr in d["frames"]:
            fr["position_ned_m"] = d["frames"][0]["position_ned_m"]
            fr["ypr_deg"] = d["frames"][0]["ypr_deg"]
    r = eonav("fuse", write_doc(seq_dir, tmp_path, hover), "--out", tmp_path / "o.npz", check=False)
    assert r.returncode == 2 and "no fused map for camera 'nose'" in r.stderr, r.stderr


def test_out_is_the_first_frames_camera_even_when_another_camera_ends_the_file(seq_dir, tmp_path):
    """--out is the last map of the FIRST frame's camera (docs/pair-file.md), not the last map written: a second
    camera "tail" (same lens, not a stereo rig: 0.1 s after the nose's last frame) re-flies frames 0-3 after the
    nose's 6 frames, so the file's last map is tail's frame 9, on frame 3's grid. Catches --out taking any camera's
    map."""
    def add_tail(d):
        d["cameras"]["tail"] = dict(d["cameras"]["nose"])
        t_end = d["frames"][-1]["t"]
        d["frames"] += [dict(d["frames"][k], camera="tail", t=t_end + 0.1 * (k + 1)) for k in range(4)]
    out, maps = tmp_path / "range.npz", tmp_path / "maps"
    r = eonav("fuse", write_doc(seq_dir, tmp_path, add_tail), "--out", out, "--out-dir", maps)
    assert "frame 5 of camera 'nose'" in r.stdout, r.stdout
    assert {"range_0005.npz", "range_0009.npz"} <= {p.name for p in maps.iterdir()}
    truth = np.load(seq_dir / "truth.npz")["range_m"]
    with np.load(out) as z, np.load(maps / "range_0005.npz") as z5, np.load(maps / "range_0009.npz") as z9:
        assert np.array_equal(z["range_m"], z5["range_m"], equal_nan=True)
        assert not np.array_equal(z["range_m"], z9["range_m"], equal_nan=True)
        for rng, tr in ((z["range_m"], truth[5]), (z9["range_m"], truth[3])):    # each on its own frame's grid
            ok = np.isfinite(tr) & np.isfinite(rng) & (rng > 0)
            assert ok.sum() > 0.5 * np.isfinite(tr).sum() and np.median(np.abs(rng[ok] / tr[ok] - 1)) < 0.05


def test_two_cameras_at_one_instant_are_in_time_order():
    """Only a decrease of t is out of order (docs/pair-file.md: t "may not decrease"): the frames of a rig triggered
    together share a t and must pass check_sequence (two frames of ONE camera at one t are refused later, by run).
    Catches `t <= last_t` refusing a simultaneous stereo pair."""
    from eonav import InputError
    from eonav.app.commands.fuse import check_sequence
    check_sequence({"frames": [{"camera": "left", "t": 0.0}, {"camera": "right", "t": 0.0},
                               {"camera": "left", "t": 0.1}, {"camera": "right", "t": 0.1}]})
    with pytest.raises(InputError, match=r"frames\[1\]\.t: -0.001 is earlier than frames\[0\]\.t 0.0"):
        check_sequence({"frames": [{"camera": "left", "t": 0.0}, {"camera": "right", "t": -0.001}]})


def test_stereo_rig_is_frames_at_most_max_dt_apart():
    """--max-stereo-dt-s S: frames of two cameras AT MOST S apart are a rig (the scheduler pairs |dt| <= S too), the
    first frame's camera the reference, whichever of the two comes first in the file. S = 0.25 s and stamps exactly
    representable in binary, so the boundary is exact. Catches `<` for `<=` at the threshold."""
    from types import SimpleNamespace

    from eonav.app.commands.fuse import stereo_rig

    def seq(*frames):
        return SimpleNamespace(frames=[{"camera": c, "t": t} for c, t in frames])
    assert stereo_rig(seq(("nose", 0.5), ("right", 0.75)), 0.25) == ("nose", "right")
    assert stereo_rig(seq(("right", 0.25), ("nose", 0.5)), 0.25) == ("right", "nose")
    assert stereo_rig(seq(("nose", 0.5), ("right", 0.75 + 2 ** -20)), 0.25) is None
    assert stereo_rig(seq(("nose", 0.0), ("nose", 0.0625)), 0.25) is None              # one camera: no rig
    # judged on the microsecond stamps the frames are pushed with, as the scheduler does: 1.002 - 1.0 is
    # 0.0020000000000000018 s in floats, but 2000 us apart, which the scheduler pairs at 0.002 s
    assert 1.002 - 1.0 > 0.002 and stereo_rig(seq(("nose", 1.0), ("right", 1.002)), 0.002) == ("nose", "right")


def test_frames_reach_the_fusion_with_microsecond_stamps_in_file_order():
    """fused_maps pushes frame k with stamp round(t * 1e6) us and seq k (the locator's stamps are microseconds: the
    pair policy's max_age_s and the rig's max_stereo_dt_s are judged on them), then drains finish(). Catches a unit
    slip (ms for us) and a lost finish()."""
    from types import SimpleNamespace

    from eonav.app.commands.fuse import fused_maps

    class Runner:
        def __init__(self):
            self.pushed = []

        def push(self, f):
            self.pushed.append((f.camera_id, f.stamp_us, f.seq))
            return [f.seq]

        def finish(self):
            return ["end"]
    frames = [{"camera": "nose", "t": 0.0}, {"camera": "right", "t": 0.0015}, {"camera": "nose", "t": 2.1234566}]
    views = [SimpleNamespace(camera=None, state=None, image=None)] * 3
    runner = Runner()
    assert list(fused_maps(runner, SimpleNamespace(frames=frames), views)) == [0, 1, 2, "end"]
    assert runner.pushed == [("nose", 0, 0), ("right", 1500, 1), ("nose", 2123457, 2)]


def test_max_stereo_dt_reaches_the_scheduler_that_pairs_the_rig(seq_dir, tmp_path, monkeypatch):
    """--max-stereo-dt-s S is one limit for both halves of the rig decision: stereo_rig finds the rig with it AND the
    fusion's scheduler pairs the two cameras' frames with it. A "right" camera 5 ms after each nose frame is a rig
    at S = 0.01 but not at the 0.002 default; the runner eonav fuse builds must get (nose, right) and 0.01. The
    runner is stopped at construction (the wiring is the point, not the fusion). Catches the limit left out of
    ScheduleConfig (the rig found, then never paired: a silent mono run)."""
    from eonav.app.cli import build_parser
    from eonav.app.commands import fuse
    from eonav.fusion import sequence

    def add_right(d):
        d["cameras"]["right"] = dict(d["cameras"]["nose"])
        d["frames"] = [g for fr in d["frames"] for g in (fr, dict(fr, camera="right", t=fr["t"] + 0.005))]
    seen = []

    class Built(Exception):
        pass

    def capture(config, *a, **kw):
        seen.append(config.schedule)
        raise Built
    monkeypatch.setattr(sequence, "FusionRunner", capture)
    p = write_doc(seq_dir, tmp_path, add_right)
    for flags, rig, dt in (([], None, 0.002), (["--max-stereo-dt-s", "0.01"], ("nose", "right"), 0.01)):
        seen.clear()
        with pytest.raises(Built):
            fuse.run(build_parser().parse_args(["fuse", str(p), "--out", str(tmp_path / "o.npz"), *flags]))
        assert [(s.stereo_rig, s.max_stereo_dt_s) for s in seen] == [(rig, dt)], flags
