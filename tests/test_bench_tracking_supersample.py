"""The tracking benchmark's ``--supersample N``: every frame is rendered with N x N samples a pixel (a camera pixel
integrates light over its area; one point sample aliases edges into steps that do not move with the scene), and the
render cache is keyed by N (a point-sampled cache must not be read back for a supersampled run, nor the reverse)."""
from __future__ import annotations

import eonav.sim.render as R
from eonav.app import bench_tracking as B

TINY = ["--maps", "truth", "--scenarios", "approach-clear", "--duration-s", "0.14", "--size", "32x24"]  # 2 frames


def _run(monkeypatch, tmp_path, *extra) -> list:
    """Run the benchmark's CLI on 2 tiny frames; return the ``supersample`` of every render call."""
    seen = []
    real = R.render

    def spy(*args, **kw):
        seen.append(kw["supersample"])
        return real(*args, **kw)

    monkeypatch.setattr(R, "render", spy)
    assert B.main([*TINY, "--cache-dir", str(tmp_path), *extra]) == 0
    return seen


def test_supersample_reaches_the_renderer_and_the_cache_key(monkeypatch, tmp_path):
    assert _run(monkeypatch, tmp_path, "--supersample", "2") == [2, 2]
    assert [p.name for p in tmp_path.iterdir()] == ["approach-clear_0.14s_15hz_32x24_truth_seed0_ss2.pkl"]
    assert _run(monkeypatch, tmp_path, "--supersample", "2") == []          # read back: no render
    assert _run(monkeypatch, tmp_path, "--supersample", "1") == [1, 1]      # another key: rendered again
    assert sorted(p.name for p in tmp_path.iterdir()) == ["approach-clear_0.14s_15hz_32x24_truth_seed0.pkl",
                                                           "approach-clear_0.14s_15hz_32x24_truth_seed0_ss2.pkl"]


def test_supersample_default_is_the_benchmarks(monkeypatch, tmp_path):
    assert _run(monkeypatch, tmp_path) == [B.SUPERSAMPLE] * 2
