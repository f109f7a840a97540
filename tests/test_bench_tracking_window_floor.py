"""The tracking benchmark's ``--window-floor KIND``: the dense method's window-residual floor reaches every fused
measurement (``dense_measurement(window_floor=KIND)``) and keys the map cache by the floor the maps were made with (a
cache of one floor must not be read back for a run with another; the fused measurement's default, "valid", is the
same key as naming it)."""
from __future__ import annotations

import eonav.fusion.sequence as S
from eonav.app import bench_tracking as B

TINY = ["--maps", "fused", "--scenarios", "approach-clear", "--duration-s", "0.5", "--size", "64x48",
        "--supersample", "1"]  # 8 point-sampled frames (cache names without _ss)


def _run(monkeypatch, tmp_path, *extra) -> list:
    """Run the benchmark's CLI on 8 small frames; return the ``window_floor`` of every fused measurement (None: the
    method's default)."""
    seen = []
    real = S.dense_measurement

    def spy(*args, **kw):
        seen.append(kw.get("window_floor"))
        return real(*args, **kw)

    monkeypatch.setattr(S, "dense_measurement", spy)
    assert B.main([*TINY, "--cache-dir", str(tmp_path), *extra]) == 0
    return seen


def test_window_floor_reaches_the_measurements_and_the_cache_key(monkeypatch, tmp_path):
    floors = _run(monkeypatch, tmp_path, "--window-floor", "global")
    assert floors and set(floors) == {"global"}
    assert [p.name for p in tmp_path.iterdir()] == ["approach-clear_0.5s_15hz_64x48_fused_seed0.pkl"]
    assert _run(monkeypatch, tmp_path, "--window-floor", "global") == []       # read back: nothing measured
    assert set(_run(monkeypatch, tmp_path, "--window-floor", "sensor")) == {"sensor"}   # another key, measured
    assert sorted(p.name for p in tmp_path.iterdir()) == ["approach-clear_0.5s_15hz_64x48_fused_seed0.pkl",
                                                           "approach-clear_0.5s_15hz_64x48_fused_seed0_floorsensor.pkl"]


def test_window_floor_default_is_the_measurements_own(monkeypatch, tmp_path):
    floors = _run(monkeypatch, tmp_path)
    assert floors and set(floors) == {None}                                     # no window_floor passed at all
    assert [p.name for p in tmp_path.iterdir()] == ["approach-clear_0.5s_15hz_64x48_fused_seed0_floorvalid.pkl"]
    assert _run(monkeypatch, tmp_path, "--window-floor", "valid") == []        # the same maps: read back


def test_the_fused_measurement_floors_at_the_valid_pixels_noise(monkeypatch):
    """``dense_measurement`` hands the dense method window_floor="valid" unless told otherwise."""
    import eonav.ranging.methods.dense as D
    seen = []
    monkeypatch.setattr(D, "locate_dense", lambda a, b, **kw: seen.append(kw.get("window_floor")))
    S.dense_measurement(None, None)
    S.dense_measurement(None, None, window_floor="global")
    assert seen == ["valid", "global"]


def test_match_blur_and_slant_px_reach_the_fused_maps_and_key_the_cache(monkeypatch, tmp_path):
    # --match-blur: every fused measurement with match_blur=True; --slant-px: the fused map's slant term; both key
    # the cache (_mb, _spx<PX>), so neither reads back maps made without them
    seen, cfgs = [], []
    real = S.dense_measurement

    def spy(*args, **kw):
        seen.append((kw.get("slant", False), kw.get("match_blur", False)))
        return real(*args, **kw)

    monkeypatch.setattr(S, "dense_measurement", spy)
    runner = S.FusionRunner.__init__

    def keep(self, config=None, *a, **kw):
        cfgs.append(config)
        return runner(self, config, *a, **kw)

    monkeypatch.setattr(S.FusionRunner, "__init__", keep)
    assert B.main([*TINY, "--cache-dir", str(tmp_path), "--slant", "--match-blur", "--slant-px", "0.9"]) == 0
    assert seen and set(seen) == {(True, True)}
    assert [c.output.slant_px for c in cfgs] == [0.9]
    assert [p.name for p in tmp_path.iterdir()] == [
        "approach-clear_0.5s_15hz_64x48_fused_seed0_slant_mb_spx0.9_floorvalid.pkl"]
    seen.clear()
    assert B.main([*TINY, "--cache-dir", str(tmp_path), "--slant"]) == 0
    assert seen and set(seen) == {(True, False)}
    assert len(list(tmp_path.iterdir())) == 2
