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
