"""The predicted state as the dense measurement's prior in ``FusionRunner`` (``PriorConfig``): between full searches
the refinement starts from the prior; a wrong prior is found by the full searches no later than ``full_every`` times
what the search alone needs. Scene: a textured wall 20 m ahead, the camera flying at it (every frame the wall's
homography of the first frame: exact truth)."""
from __future__ import annotations

from functools import lru_cache

import cv2
import numpy as np

from eonav.fusion.schedule import ScheduleConfig
from eonav.fusion.sequence import FusionConfig, FusionRunner, PriorConfig, dense_measurement, frame
from eonav.geometry.camera import Camera, VehicleState, View, pair_geometry
from eonav.ranging.pair_policy import PairPolicyConfig
from eonav.ranging.rangemap import VALID

WALL_M = 20.0
SIZE = 192
FULL_EVERY = 2
WRONG_RHO = 0.5       # a block moved to 2 m: several pixels of disparity off, beyond the refinement's reach


@lru_cache(maxsize=1)
def wall_flight(n=12, step_m=0.25):
    """n frames at 10 Hz, the camera 0.25 m nearer the wall (and 0.05 m to the right) each frame; unit sensor noise."""
    f = 0.8 * SIZE
    c = (SIZE - 1) / 2.0
    cam = Camera("nose", SIZE, SIZE, f, f, c, c)
    rng = np.random.default_rng(3)
    texture = cv2.GaussianBlur(rng.standard_normal((SIZE, SIZE)).astype(np.float32), (0, 0), 1.5) * 150 + 128
    st0 = VehicleState.from_ypr([0.0, 0.0, 0.0], [0.0, 0.0, 0.0], 0.0)
    v0 = View(cam, st0, texture)
    to_m = np.array([[0.0, 0.0, 1.0], [1.0 / f, 0.0, -c / f], [0.0, 1.0 / f, -c / f]])
    to_px = np.array([[c, f, 0.0], [c, 0.0, f], [1.0, 0.0, 0.0]])
    views, truth = [], []
    for k in range(n):
        st = VehicleState.from_ypr([step_m * k, 0.05 * k, 0.0], [0.0, 0.0, 0.0], 0.1 * k)
        geo = pair_geometry(v0, View(cam, st, texture))
        H = to_px @ (geo.R_ba + np.outer(geo.t_ba_m, [1.0 / WALL_M, 0.0, 0.0])) @ to_m
        img = cv2.warpPerspective(texture, H, (SIZE, SIZE), flags=cv2.INTER_LINEAR, borderMode=cv2.BORDER_REFLECT)
        views.append(View(cam, st, (img + rng.standard_normal(img.shape)).astype(np.float32)))
        truth.append(WALL_M - step_m * k)
    return views, truth


def config(full_every):
    return FusionConfig(schedule=ScheduleConfig(policy=PairPolicyConfig(ref_range_m=WALL_M)),
                        prior=PriorConfig(full_every=full_every, kinds=("near", "wide")))


class Recorder:
    """The default measurement, recording per measurement (frame of view a, prior offered, started from it)."""

    def __init__(self, views):
        self.index = {id(v): k for k, v in enumerate(views)}
        self.log = []

    def __call__(self, va, vb, **prior):
        res = dense_measurement(va, vb, **prior)
        self.log.append((self.index[id(va)], "prior" in prior,
                         not res.info.get("prior", {"full_search": True})["full_search"]))
        return res

    @property
    def seeded(self):
        return [s for _, _, s in self.log]


def run(full_every, views, hook=None):
    rec = Recorder(views)
    runner = FusionRunner(config(full_every), measure=rec, fresh_measurements=True, takes_prior=True)
    maps = []
    for k, v in enumerate(views):
        if hook is not None:
            hook(runner, k)
        maps += runner.push(frame("nose", v, int(round(v.state.t_s * 1e6)), k))
    return runner, maps, rec


def test_the_prior_seeds_the_measurements_between_full_searches_as_accurately():
    views, truth = wall_flight()
    _, maps_full, rec_full = run(1, views)
    _, maps, rec = run(3, views)
    seeded_full, seeded = rec_full.seeded, rec.seeded
    assert not any(seeded_full)
    assert sum(seeded) >= len(seeded) // 2
    assert "True, True, True" not in str(seeded)            # a full search at least every third measurement
    for m0, m1 in zip(maps_full[-3:], maps[-3:]):
        t = truth[m1.frame.seq]
        for m in (m0, m1):
            ok = (m.result.flags & VALID) != 0
            assert ok.mean() > 0.85
            assert abs(np.median(m.result.range_m[ok]) / t - 1) < 0.003


def test_a_wrong_converged_block_is_found_by_the_full_searches():
    # a converged block of the state moved to 2 m with full evidence before frame 6: the frames after it
    # report the block VALID at the wrong range no longer than full_every x as long as with the search alone
    views, truth = wall_flight(n=14)
    blk = np.s_[70:120, 70:120]

    def corrupt(runner, k):
        if k == 6:
            st = runner.states["nose"]
            st.rho[blk] = WRONG_RHO
            st.var[blk] = 1e-8
            st.a[blk], st.b[blk], st.n[blk] = 7.0, 1.0, 20       # E[inlier ratio] 0.875 at the evidence cap

    def wrong_frames(full_every):
        _, maps, rec = run(full_every, views, corrupt)
        out = []
        for m in maps:
            if m.frame.seq < 6:
                continue
            r = m.result
            wrong = ((r.flags[blk] & VALID) != 0) & (np.abs(r.inv_range_per_m[blk] / WRONG_RHO - 1) < 0.2)
            out.append(wrong.mean())
        return out, rec.log

    plain, _ = wrong_frames(1)
    prior, log = wrong_frames(FULL_EVERY)
    assert plain[0] > 0.9 and prior[0] > 0.9                 # the corruption took
    assert any(s for k, _, s in log if k < 6)                # the prior seeded measurements before it
    n_plain = next(i for i, w in enumerate(plain) if w < 0.05)
    n_prior = next(i for i, w in enumerate(prior) if w < 0.05)
    assert n_prior <= FULL_EVERY * n_plain
    assert max(prior[n_prior:]) < 0.05                       # and it does not come back
    # with no full search scheduled at all the block is found as soon: it fits badly at its prior (beyond the
    # refinement's reach), so it is not measured at the wrong range, and the prior is not offered while the
    # state's evidence disagrees
    never, log = wrong_frames(1000)
    assert [o for k, o, _ in log if k == 6] == [True]
    assert next(i for i, w in enumerate(never) if w < 0.05) <= n_plain


def test_prior_config_errors_name_the_field():
    import pytest

    from eonav import InputError
    for kw, field in (({"full_every": 0}, "full_every"), ({"kinds": ("sideways",)}, "kinds"),
                      ({"min_fused": 0}, "min_fused"), ({"min_fraction": 1.5}, "min_fraction")):
        with pytest.raises(InputError, match=field):
            PriorConfig(**kw)
    assert PriorConfig(full_every=1, kinds=["near", "wide"]).kinds == ("near", "wide")
    assert FusionConfig().prior.full_every == 1          # off by default (docs/methods.md, "Fusion")


def test_the_prior_holds_the_cells_of_enough_agreeing_measurements_on_both_paths(monkeypatch):
    """``FusionRunner.prior`` by hand on a 4 x 2 state, numba's pass and the numpy path alike: a cell is in the prior
    (its rho, its sigma = sqrt(var)) when it holds an estimate of at least ``min_fused`` (2) measurements whose
    evidence agrees (a >= eta_inlier (0.65) x (a + b)), else NaN / inf; the prior is offered while it holds at least
    ``min_fraction`` (0.8) x the pixels the last full search measured (4 cells: offered after a search of 5, as the
    least share 4 / 8 of the pixels; not after one of 6). Catches a planted ``n > min_fused`` in the numpy path
    (the cells of exactly 2 measurements left out: only the numba pass was reached by the other tests)."""
    import pytest

    import eonav.fusion.sequence as seq_mod
    from eonav.fusion.state import InverseRangeState, optional_kernels
    cam = Camera("nose", 4, 2, 4.0, 4.0, 1.5, 0.5)
    nan = np.nan
    rho = np.array([[0.05, 0.05, 0.05, 0.05], [nan, 0.1, 0.02, 0.02]], np.float32)
    var = np.array([[1e-6, 1e-6, 1e-6, 1e-6], [np.inf, 4e-6, 1e-8, 1e-8]], np.float32)
    n = np.array([[2, 1, 3, 3], [0, 5, 2, 2]], np.uint16)
    a = np.array([[5, 5, 1, 7], [0, 9, 2, 6]], np.float32)      # E[inlier ratio]: 0.83 0.83 0.5 0.7 / - 0.9 0.67 0.6
    b = np.array([[1, 1, 1, 3], [0, 1, 1, 4]], np.float32)
    want_rho = np.array([[0.05, nan, nan, 0.05], [nan, 0.1, 0.02, nan]], np.float32)
    want_std = np.array([[1e-3, np.inf, np.inf, 1e-3], [np.inf, 2e-3, 1e-4, np.inf]], np.float32)
    for kernels in ([True] if optional_kernels() is not None else []) + [False]:      # (numba's first)
        if not kernels:
            monkeypatch.setattr(seq_mod, "optional_kernels", lambda: None)
        assert (seq_mod.optional_kernels() is not None) == kernels
        runner = FusionRunner(FusionConfig(prior=PriorConfig(full_every=3)))
        level = VehicleState.from_ypr([0.0, 0.0, 0.0], [0.0, 0.0, 0.0], 0.0)
        st = runner.states["nose"] = InverseRangeState.empty(cam, level, 0.0)
        st.rho[...], st.var[...], st.n[...], st.a[...], st.b[...] = rho, var, n.astype(st.n.dtype), a, b
        assert runner.prior("nose") is None                   # no full search yet
        runner._full_measured["nose"] = 5
        p_rho, p_std, least = runner.prior("nose")
        np.testing.assert_array_equal(p_rho, want_rho)
        np.testing.assert_allclose(p_std, want_std, rtol=1e-6)
        assert least == pytest.approx(0.5)
        runner._full_measured["nose"] = 6
        assert runner.prior("nose") is None, kernels
