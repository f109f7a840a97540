"""The locator's adaptive scale controller (eonav.ranging.scale_control), edge case by edge case."""
import pytest

from eonav import InputError
from eonav.ranging.scale_control import ScaleController, ladder, parse_scale

FPS15_US = 66_667


def feed_frames(c, n, interval_us=FPS15_US, seq0=0, stamp0=1_000_000):
    for i in range(n):
        c.observe_frame(seq0 + i, stamp0 + i * interval_us)


def run(c, costs_by_scale, n):
    """n pairs, each ranged at the controller's current scale with cost ``costs_by_scale[scale]``; the changes."""
    out = []
    for _ in range(n):
        s = c.scale
        ch = c.observe_compute(s, costs_by_scale[s])
        if ch is not None:
            out.append(ch)
    return out


def test_parse_scale_and_ladder():
    assert parse_scale("auto") is None and parse_scale("AUTO") is None and parse_scale(None) is None
    assert parse_scale("0.5") == 0.5 and parse_scale(1) == 1.0
    for bad in ("0", "1.5", "x", "nan", "-1"):
        with pytest.raises(InputError):
            parse_scale(bad)
    assert ladder(0.5) == (1.0, 0.5)
    assert ladder(1.0) == (1.0,)
    assert ladder(0.25) == (1.0, 0.5, 0.25)
    assert ladder(0.3) == (1.0, 0.5, 0.3)
    with pytest.raises(InputError):
        ladder(0)


def test_budget_from_frame_interval():
    c = ScaleController()
    assert c.budget_s() == pytest.approx(0.2)                  # unknown interval: the upper bound
    feed_frames(c, 10)                                         # 15 fps
    assert c.budget_s() == pytest.approx(0.6 / 15, rel=1e-3)
    c2 = ScaleController()
    c2.observe_frame(0, 0)
    c2.observe_frame(2, 2 * FPS15_US)                          # a seq gap (ring skipped one): still 15 fps
    c2.observe_frame(3, 3 * FPS15_US + 20_000)                 # one late frame does not move the median much
    c2.observe_frame(4, 4 * FPS15_US)
    assert c2.budget_s() == pytest.approx(0.04, rel=1e-3)
    fast, slow = ScaleController(), ScaleController()
    feed_frames(fast, 10, interval_us=5_000)                   # 200 fps: clamped to 20 ms
    feed_frames(slow, 10, interval_us=2_000_000)               # 0.5 fps: clamped to 200 ms
    assert fast.budget_s() == pytest.approx(0.02) and slow.budget_s() == pytest.approx(0.2)
    assert ScaleController(budget_s=0.03).budget_s() == 0.03   # --budget-ms wins over the interval


def test_steps_down_when_over_budget():
    c = ScaleController()
    feed_frames(c, 10)                                         # budget 40 ms
    changes = run(c, {1.0: 0.044, 0.5: 0.012}, 2)
    assert not changes and c.scale == 1.0                      # fewer than min_samples pairs: no verdict yet
    changes = run(c, {1.0: 0.044, 0.5: 0.012}, 1)
    assert [(x.old, x.new, x.direction) for x in changes] == [(1.0, 0.5, "down")]
    assert "over the budget" in changes[0].reason
    # at 0.5: learnt ratio 44/12 ~ 3.7: predicted full 44 ms > 0.7 x 40 ms: it stays down
    assert not run(c, {1.0: 0.044, 0.5: 0.012}, 50) and c.scale == 0.5


def test_single_slow_pair_does_not_step_down():
    c = ScaleController()
    feed_frames(c, 10)
    costs = iter([0.030, 0.200, 0.030, 0.031, 0.029, 0.030])  # one outlier under the median
    for x in costs:
        assert c.observe_compute(c.scale, x) is None
    assert c.scale == 1.0


def test_steps_back_up_with_headroom_after_n_pairs():
    c = ScaleController(up_after=5)
    feed_frames(c, 10)
    run(c, {1.0: 0.060, 0.5: 0.015}, 3)                        # contention: down
    assert c.scale == 0.5
    run(c, {1.0: 0.060, 0.5: 0.015}, 10)
    assert c.scale == 0.5
    # the load goes away: 0.5 now costs 4 ms, full predicted 4 x 60/15 = 16 ms < 28 ms
    changes = run(c, {1.0: 0.016, 0.5: 0.004}, 4)
    assert not changes and c.scale == 0.5                      # the window median needs to fall, then N pairs
    changes = run(c, {1.0: 0.016, 0.5: 0.004}, 10)
    assert [(x.old, x.new, x.direction) for x in changes] == [(0.5, 1.0, "up")]
    assert "below" in changes[0].reason
    assert not run(c, {1.0: 0.016, 0.5: 0.004}, 50) and c.scale == 1.0


def test_up_count_restarts_on_a_pair_without_headroom():
    c = ScaleController(up_after=3, window=1, min_samples=1)
    feed_frames(c, 10)                                         # budget 40 ms, up below 28 ms predicted full
    run(c, {1.0: 0.050, 0.5: 0.0125}, 1)
    assert c.scale == 0.5
    assert c.observe_compute(0.5, 0.0125) is None              # learnt ratio 50 / 12.5 = 4 from the first pair at 0.5
    assert c.ratio(1.0, 0.5) == pytest.approx(4.0)
    for x in (0.005, 0.005, 0.009, 0.005, 0.005):              # 20, 20, 36 (no headroom), 20, 20 ms predicted
        assert c.observe_compute(0.5, x) is None
    assert c.observe_compute(0.5, 0.005) is not None and c.scale == 1.0


def test_each_step_up_waits_its_own_up_after_pairs():
    """Coming back up a three-rung ladder, the rung above is judged afresh: the N pairs in a row with headroom that
    took 0.25 up to 0.5 do not also take 0.5 up to 1.0 after a single pair there."""
    c = ScaleController(min_scale=0.25, up_after=5, window=1, min_samples=1)
    feed_frames(c, 10)                                         # budget 40 ms, up below 28 ms predicted
    load = {1.0: 0.080, 0.5: 0.050, 0.25: 0.0125}              # learnt ratios 80/50 = 1.6 and 50/12.5 = 4
    assert [(x.old, x.new) for x in run(c, load, 3)] == [(1.0, 0.5), (0.5, 0.25)] and c.scale == 0.25
    assert c.ratio(1.0, 0.5) == pytest.approx(1.6) and c.ratio(0.5, 0.25) == pytest.approx(4.0)
    light = {1.0: 0.0128, 0.5: 0.008, 0.25: 0.004}             # predicted 0.5: 4 x 4 = 16 ms; then 1.0: 8 x 1.6 = 12.8 ms
    pairs_at = {0.25: 0, 0.5: 0}
    changes = []
    while c.scale != 1.0 and len(changes) < 3:
        s = c.scale
        pairs_at[s] += 1
        ch = c.observe_compute(s, light[s])
        if ch is not None:
            changes.append((ch.old, ch.new))
    assert changes == [(0.25, 0.5), (0.5, 1.0)]
    assert pairs_at == {0.25: 5, 0.5: 5}


def test_no_oscillation_at_the_boundary():
    # full costs just under the budget, half just over a quarter of it: neither step qualifies
    c = ScaleController()
    feed_frames(c, 10)
    assert not run(c, {1.0: 0.039, 0.5: 0.0098}, 200) and c.scale == 1.0
    # full just over the budget: one step down and no way back (predicted 41 ms > 28 ms)
    c = ScaleController()
    feed_frames(c, 10)
    changes = run(c, {1.0: 0.041, 0.5: 0.0103}, 200)
    assert [x.new for x in changes] == [0.5]
    # the area prediction is optimistic (true ratio 3 but measured 0.5 cost when entering would say x4): the
    # learnt ratio keeps it from bouncing. Full 45 ms, half 15 ms under load; then half 8 ms: predicted 24 ms full,
    # true 24 ms: up once, stays up
    c = ScaleController()
    feed_frames(c, 10)
    changes = run(c, {1.0: 0.045, 0.5: 0.015}, 30) + run(c, {1.0: 0.024, 0.5: 0.008}, 100)
    assert [x.new for x in changes] == [0.5, 1.0]
    # a load that alternates pair by pair around the budget: the median and the N-pair rule keep it steady
    c = ScaleController()
    feed_frames(c, 10)
    n_changes = 0
    for i in range(300):
        s = c.scale
        cost = (0.036 if i % 2 else 0.046) * (s * s)
        n_changes += c.observe_compute(s, cost) is not None
    assert n_changes <= 1


def test_respects_min_scale():
    c = ScaleController(min_scale=0.5)
    feed_frames(c, 10)
    run(c, {1.0: 0.5, 0.5: 0.2}, 100)                          # hopeless even at 0.5: stays at the lowest rung
    assert c.scale == 0.5
    c = ScaleController(min_scale=0.25)
    feed_frames(c, 10)
    changes = run(c, {1.0: 0.5, 0.5: 0.2, 0.25: 0.05}, 100)
    assert [x.new for x in changes] == [0.5, 0.25] and c.scale == 0.25
    c = ScaleController(min_scale=1.0)
    feed_frames(c, 10)
    assert not run(c, {1.0: 0.5}, 50) and c.scale == 1.0


def test_fixed_scale_never_changes():
    for fixed in (1.0, 0.5):
        c = ScaleController(fixed=fixed)
        feed_frames(c, 10)
        assert c.ladder == (fixed,)
        assert not run(c, {fixed: 0.5}, 50) and c.scale == fixed
        assert not run(c, {fixed: 0.0001}, 50) and c.scale == fixed


def test_pairs_at_another_scale_do_not_decide():
    c = ScaleController()
    feed_frames(c, 10)
    for _ in range(10):                                        # e.g. a pair computed before a change was applied
        assert c.observe_compute(0.5, 1.0) is None
    assert c.scale == 1.0


def test_bad_configuration():
    with pytest.raises(InputError):
        ScaleController(budget_s=0.0)
    with pytest.raises(InputError):
        ScaleController(min_scale=2.0)
    with pytest.raises(InputError):
        ScaleController(fixed="x")


@pytest.mark.parametrize("full_ms, half_ms, max_changes", [(44, 15, 1), (40, 14, 1), (35, 13, 4), (30, 11, 0)])
def test_noisy_costs_near_the_budget_change_rarely(full_ms, half_ms, max_changes):
    """Compute times with noise and 2 % stalls (seeded) around the 40 ms budget of 15 fps: 2000 pairs (over two
    minutes) change the scale at most a few times."""
    import numpy as np
    rng = np.random.default_rng(1)
    c = ScaleController()
    feed_frames(c, 10)
    n = 0
    for _ in range(2000):
        s = c.scale
        base, sd = (full_ms, 5.0) if s == 1.0 else (half_ms, 2.0)
        cost = max(1.0, rng.normal(base, sd) + (30.0 if rng.random() < 0.02 else 0.0)) * 1e-3
        n += c.observe_compute(s, cost) is not None
    assert n <= max_changes


# -- calibrated start: one locate call per rung timed before any pair (the locator's warm-up) --------------------

def test_calibrated_start_takes_the_largest_rung_that_fits_before_any_pair():
    c = ScaleController()
    feed_frames(c, 3)                                          # 15 fps: budget 40 ms
    assert c.calibrate({1.0: 0.045, 0.5: 0.015}) == 0.5 and c.scale == 0.5
    assert c.ratio(1.0, 0.5) == pytest.approx(3.0)             # the calibrated ratio, not the area's 4
    c = ScaleController()
    feed_frames(c, 3)
    assert c.calibrate({1.0: 0.030, 0.5: 0.010}) == 1.0        # fits: full scale, as without calibration


def test_calibrated_start_follows_the_budget_until_the_first_pair():
    c = ScaleController()
    assert c.calibrate({1.0: 0.045, 0.5: 0.015}) == 1.0        # no frame yet: budget 200 ms, full fits
    feed_frames(c, 3)                                          # the interval is known: 40 ms, full does not fit
    assert c.scale == 0.5
    c.observe_compute(0.5, 0.015)                              # the first pair: from now on only the controller moves
    feed_frames(c, 10, interval_us=1_000_000, seq0=3, stamp0=1_000_000 + 3 * FPS15_US)   # budget back at 200 ms
    assert c.scale == 0.5


def test_calibrated_start_when_no_rung_fits_takes_the_lowest_calibrated_rung():
    c = ScaleController(min_scale=0.25)
    feed_frames(c, 3)
    assert c.calibrate({1.0: 0.5, 0.5: 0.2}) == 0.5            # 0.25 not calibrated: the lowest that was


def test_calibration_after_the_first_pair_only_seeds_the_ratios():
    c = ScaleController()
    feed_frames(c, 3)
    c.observe_compute(1.0, 0.030)
    assert c.calibrate({1.0: 0.045, 0.5: 0.015}) == 1.0 and c.scale == 1.0
    assert c.ratio(1.0, 0.5) == pytest.approx(3.0)


def test_calibration_ignores_bad_values_unknown_rungs_and_a_fixed_scale():
    c = ScaleController()
    feed_frames(c, 3)
    assert c.calibrate({1.0: float("nan"), 0.5: -1.0, 0.3: 0.001, 2.0: 0.001}) == 1.0
    assert c.ratio(1.0, 0.5) == pytest.approx(4.0)             # nothing learnt from bad values
    f = ScaleController(fixed=0.5)
    feed_frames(f, 3)
    assert f.calibrate({0.5: 1.0}) == 0.5 and f.scale == 0.5


def test_single_slow_pair_does_not_step_down_after_a_calibrated_start():
    """The calibrated start does not weaken the steady-state hysteresis: one outlier still changes nothing."""
    c = ScaleController()
    feed_frames(c, 10)
    assert c.calibrate({1.0: 0.030, 0.5: 0.010}) == 1.0
    for x in (0.030, 0.200, 0.030, 0.031, 0.029, 0.030):
        assert c.observe_compute(c.scale, x) is None
    assert c.scale == 1.0


def test_calibrated_start_below_full_steps_up_when_the_pairs_show_headroom():
    """A calibration made under a passing load (start at 0.5) is corrected by the ordinary step-up rule."""
    c = ScaleController(up_after=5)
    feed_frames(c, 10)
    assert c.calibrate({1.0: 0.045, 0.5: 0.015}) == 0.5
    changes = run(c, {1.0: 0.021, 0.5: 0.007}, 20)             # predicted full 7 x 3 = 21 ms < 28 ms
    assert [x.new for x in changes] == [1.0] and c.scale == 1.0


# -- the latency target: published maps' ages (capture -> put) -----------------------------------------------------
FPS30_US = 33_333


def ages(c, age_s, n):
    """n maps published at the current scale, each ``age_s`` old; the changes."""
    out = []
    for _ in range(n):
        ch = c.observe_latency(c.scale, age_s)
        if ch is not None:
            out.append(ch)
    return out


def test_latency_over_the_target_steps_down_after_enough_maps():
    c = ScaleController(min_scale=0.3, latency_target_s=0.05)
    feed_frames(c, 10, interval_us=FPS30_US)
    assert not ages(c, 0.051, 9) and c.scale == 1.0            # 9 maps (fewer than latency_min_samples): no verdict
    ch = ages(c, 0.051, 1)
    assert [(x.old, x.new) for x in ch] == [(1.0, 0.5)] and "latency target 50.0 ms" in ch[0].reason
    assert not ages(c, 0.051, 9) and c.scale == 0.5            # the new rung is judged on its own maps
    assert [(x.old, x.new) for x in ages(c, 0.051, 1)] == [(0.5, 0.3)]
    assert not ages(c, 0.2, 100) and c.scale == 0.3            # the floor


def test_latency_just_under_the_target_and_rare_late_maps_keep_the_scale():
    c = ScaleController(latency_target_s=0.05)
    assert not ages(c, 0.049, 100) and c.scale == 1.0          # under the target: no change
    c = ScaleController(latency_target_s=0.05)
    for i in range(300):                                       # 1 map in 15 late (under 10 %): the p90 is not
        assert c.observe_latency(1.0, 0.12 if i % 15 == 14 else 0.02) is None
    assert c.scale == 1.0
    c = ScaleController(latency_target_s=0.05)
    for i in range(30):                                        # 1 map in 5 late: the p90 is, and it steps down
        ch = c.observe_latency(1.0, 0.12 if i % 5 == 0 else 0.02)
    assert c.scale == 0.5


def test_no_latency_target_or_a_fixed_scale_ignores_ages():
    c = ScaleController()
    assert not ages(c, 10.0, 100) and c.scale == 1.0
    c = ScaleController(fixed=0.5, latency_target_s=0.05)
    assert not ages(c, 10.0, 100) and c.scale == 0.5
    c = ScaleController(latency_target_s=0.05)
    assert c.observe_latency(0.5, 10.0) is None                # a map of another rung does not decide
    assert not ages(c, float("nan"), 50) and c.latency_s() is None


def test_steps_up_only_when_the_latency_above_is_predicted_to_fit():
    # compute has headroom at 0.5 (cost 5 ms, full predicted 20 ms < 0.7 x 40 ms budget); the latency decides
    def down_at_half(age_s):
        c = ScaleController(budget_s=0.04, latency_target_s=0.05)
        assert [(x.old, x.new) for x in ages(c, 0.06, 10)] == [(1.0, 0.5)]
        for _ in range(60):                                    # 60 pairs at 0.5, each with a map of age_s
            ch = c.observe_compute(0.5, 0.005) or c.observe_latency(0.5, age_s)
            if ch is not None:
                return c, ch
        return c, None
    # ages 8 ms: predicted at full 8 x 4 (area ratio) = 32 ms < 0.7 x 50 ms: up, once a whole window is seen
    c, ch = down_at_half(0.008)
    assert ch is not None and (ch.old, ch.new) == (0.5, 1.0)
    # ages 9 ms: 36 ms predicted, over 35 ms: it stays at 0.5
    c, ch = down_at_half(0.009)
    assert ch is None and c.scale == 0.5


def test_bad_latency_target():
    for bad in (0.0, -0.01, float("nan"), float("inf")):
        with pytest.raises(InputError):
            ScaleController(latency_target_s=bad)


def stream(c, seconds, cost_s, age_s, stamp0_us, fps=30):
    """``seconds`` of frames at ``fps``, each ranged at the current scale: compute ``cost_s(scale)`` and time per frame
    ``age_s(scale)``; returns (the changes as (old, new, probe, stamp in s), the next stamp)."""
    out, dt = [], int(round(1e6 / fps))
    stamp = stamp0_us
    for i in range(int(round(seconds * fps))):
        c.observe_frame(stamp // dt, stamp)
        s = c.scale
        for ch in (c.observe_compute(s, cost_s(s)), c.observe_latency(s, age_s(s))):
            if ch is not None:
                out.append((ch.old, ch.new, ch.probe, round(stamp * 1e-6, 2)))
        stamp += dt
    return out, stamp


# The 30 fps 640 x 480 locator at half scale: compute ~13 ms of a 20 ms budget, time per frame p90 ~20 ms of a 25 ms
# target (above the 0.7 margin of the ordinary step up), at 0.3 ~6 / ~12 ms; full scale far over both.
def cost_half(s):
    return {1.0: 0.050, 0.5: 0.013, 0.3: 0.006}[s]


def age_half(s):
    return {1.0: 0.060, 0.5: 0.020, 0.3: 0.012}[s]


def half_controller():
    c = ScaleController(min_scale=0.3, latency_target_s=0.025)
    c.calibrate({1.0: 0.05, 0.5: 0.013, 0.3: 0.006})
    feed_frames(c, 2, interval_us=FPS30_US, seq0=-2, stamp0=1_000_000 - 2 * FPS30_US)   # the first pair's frames
    assert c.scale == 0.5                                      # the calibrated start at a 20 ms budget
    return c


def test_a_transient_load_does_not_keep_the_scale_down():
    c = half_controller()
    ch, t = stream(c, 10.0, cost_half, age_half, 1_000_000)
    assert c.scale == 0.5 and not ch                           # held 10 s: no change
    # a 2 s burst of load: the maps take 40 ms: one step down
    ch, t = stream(c, 2.0, cost_half, lambda s: 0.040, t)
    assert [x[:3] for x in ch] == [(0.5, 0.3, False)]
    down_at = ch[0][3]
    # the load is gone; the ordinary rule would never step up (20 ms predicted x area ratio over 0.7 x 25 ms):
    # the probe does, probe_s (5 s) after the step down, and the half scale holds from then on
    ch, t = stream(c, 30.0, cost_half, age_half, t)
    assert [x[:3] for x in ch] == [(0.3, 0.5, True)]
    assert ch[0][3] - down_at == pytest.approx(5.0, abs=0.1)
    assert c.scale == 0.5 and c.probes == 1 and c.ups_failed == 0


def test_a_load_that_stays_is_probed_ever_less_often():
    c = half_controller()
    _, t = stream(c, 10.0, cost_half, age_half, 1_000_000)
    # from now on the half scale's maps take 40 ms: down, then each probe fails and the next waits twice as long,
    # up to probe_max_s
    ch, t = stream(c, 200.0, cost_half, lambda s: {1.0: 0.08, 0.5: 0.040, 0.3: 0.012}[s], t)
    ups = [x[3] for x in ch if x[2]]
    downs = [x[3] for x in ch if not x[2]]
    assert len(downs) == len(ups) + 1                          # every probe pushed off again
    waits = [u - d for d, u in zip(downs, ups)]
    assert waits == pytest.approx([5.0, 10.0, 20.0, 40.0, 60.0, 60.0], abs=0.1)   # each probe's verdict: 10 maps
    assert c.probes == 6 and c.ups_failed == 6 and c.scale == 0.3
    # a probe that holds resets the wait: the load goes, the next probe is back at probe_s
    ch, t = stream(c, 120.0, cost_half, age_half, t)
    assert [x[:3] for x in ch] == [(0.3, 0.5, True)] and c.scale == 0.5
    _, t = stream(c, 3.0, cost_half, age_half, t)
    ch, t = stream(c, 2.0, cost_half, lambda s: 0.040, t)
    assert [x[:3] for x in ch] == [(0.5, 0.3, False)]
    ch2, t = stream(c, 10.0, cost_half, age_half, t)
    assert [x[:3] for x in ch2] == [(0.3, 0.5, True)] and ch2[0][3] - ch[0][3] == pytest.approx(5.0, abs=0.1)


def test_a_rung_never_held_is_never_probed():
    # the half scale never fits (its maps take 30 ms from the start): down to 0.3 within the first second, and no
    # probe in the two minutes after: 0.5 was never held for hold_s
    c = half_controller()
    ch, _ = stream(c, 120.0, cost_half, lambda s: {1.0: 0.08, 0.5: 0.030, 0.3: 0.012}[s], 1_000_000)
    assert [x[:3] for x in ch] == [(0.5, 0.3, False)] and ch[0][3] < 1.0 + 1.0
    assert c.probes == 0 and c.scale == 0.3
    # the rung held until the step down, 10 maps (0.33 s) into the load: 1.5 + 0.33 s, under hold_s (2 s): never
    # probed; 2.0 + 0.33 s: probed
    for held_s, probes in ((1.5, 0), (2.0, 1)):
        c = half_controller()
        _, t = stream(c, held_s, cost_half, age_half, 1_000_000)
        ch, t = stream(c, 1.0, cost_half, lambda s: 0.040, t)
        assert [x[:2] for x in ch] == [(0.5, 0.3)]
        stream(c, 20.0, cost_half, age_half, t)
        assert c.probes == probes, held_s


def test_probe_settings_are_checked():
    for kw in ({"probe_s": 0.0}, {"probe_s": 10.0, "probe_max_s": 5.0}, {"probe_max_s": float("inf")},
               {"hold_s": 0.0}, {"hold_s": float("nan")}):
        with pytest.raises(InputError):
            ScaleController(**kw)


def test_a_step_up_by_the_rule_pushed_off_makes_the_next_one_wait_too():
    # the ordinary rule predicts that full scale fits (0.5 costs 5 ms, its maps 8 ms: 20 / 32 ms predicted, under 0.7
    # x 40 / 50 ms), but full scale's maps take 60 ms: each step up is pushed off after one verdict (10 maps). The
    # first step down (from the start, not a step up) lets the rule step up after a window of maps (30) and 5 pairs;
    # without the wait it did so after every step down; with it the next steps up wait 10, 20, 40 s
    c = ScaleController(budget_s=0.04, latency_target_s=0.05)
    cost = lambda s: {1.0: 0.020, 0.5: 0.005}[s]
    age = lambda s: {1.0: 0.060, 0.5: 0.008}[s]
    ch, _ = stream(c, 90.0, cost, age, 1_000_000)
    downs = [x[3] for x in ch if x[1] < x[0]]
    ups = [x[3] for x in ch if x[1] > x[0]]
    assert not any(x[2] for x in ch)                           # full scale never held: no probe, the rule alone
    waits = [u - d for d, u in zip(downs, ups)]
    assert waits == pytest.approx([1.17, 10.0, 20.0, 40.0], abs=0.2)
    assert c.ups_failed == 4 and len(downs) == 5 and c.scale == 0.5


def test_a_step_up_learns_the_ratio_of_the_upper_rungs_cost_to_the_lower_ones():
    """The cost ratio of two rungs is learnt at every change between them, up as well as down: 1.0 at 50 ms steps
    down (budget 40 ms) and learns 50 / 12.5 = 4 from the first pair at 0.5; 0.5 at 5 ms then predicts 20 ms < 28 ms
    at full scale and steps up; the first pair there costs 15 ms: the ratio is now 15 / 5 = 3 (the upper rung's cost
    over the lower one's), and the prediction at 0.5 from full scale 15 / 3 = 5 ms."""
    c = ScaleController(window=1, min_samples=1, up_after=1)
    feed_frames(c, 10)                                         # 15 fps: budget 40 ms
    assert [(x.old, x.new) for x in run(c, {1.0: 0.050, 0.5: 0.0125}, 2)] == [(1.0, 0.5)]
    assert c.ratio(1.0, 0.5) == pytest.approx(4.0)
    assert [(x.old, x.new) for x in run(c, {1.0: 0.015, 0.5: 0.005}, 2)] == [(0.5, 1.0)]
    assert c.ratio(1.0, 0.5) == pytest.approx(3.0)
    assert c.predicted_s(0.5) == pytest.approx(0.005)


def test_a_replay_restart_restarts_the_wait_before_a_probe():
    """A replay restarted (frame stamps back at the start) while the controller waits at 0.3 below a rung it held:
    the wait restarts with the stamps, and the probe comes probe_s (5 s) of frame time after the restart, not 5 s
    after the step down measured on the stamps of before the restart (here 16.1 s: 15.1 s into the restarted replay)."""
    c = half_controller()
    _, t = stream(c, 10.0, cost_half, age_half, 1_000_000)     # 0.5 held
    ch, t = stream(c, 2.0, cost_half, lambda s: 0.040, t)       # a burst: down to 0.3 at 11.1 s (4 late of 30)
    assert [x[:3] for x in ch] == [(0.5, 0.3, False)] and ch[0][3] == pytest.approx(11.1, abs=0.05)
    ch, _ = stream(c, 30.0, cost_half, age_half, 1_000_000)     # the replay restarts at 1 s, without the load
    assert [x[:3] for x in ch] == [(0.3, 0.5, True)]
    assert ch[0][3] == pytest.approx(1.0 + 5.0, abs=0.1)


def test_a_step_up_that_holds_lets_the_next_step_up_by_the_rule_come_without_a_wait():
    """Only a step up pushed off before it held makes the next one wait: here full scale's maps first take 60 ms
    (the rule's step up after the first step down, 1.17 s, is pushed off; the next waits 10 s), then, from 5 s on,
    20 ms: that step up holds. A later burst steps down again; once it is over the rule steps up after a window of maps and
    up_after pairs (~1.17 s) as at the start, not after the 5 s wait of a blocked one."""
    c = ScaleController(budget_s=0.04, latency_target_s=0.05)
    cost = lambda s: {1.0: 0.020, 0.5: 0.005}[s]
    ch, t = stream(c, 5.0, cost, lambda s: {1.0: 0.060, 0.5: 0.008}[s], 1_000_000)
    ch2, t = stream(c, 17.0, cost, lambda s: {1.0: 0.020, 0.5: 0.008}[s], t)
    ch += ch2
    assert [x[:2] for x in ch] == [(1.0, 0.5), (0.5, 1.0), (1.0, 0.5), (0.5, 1.0)] and c.ups_failed == 1
    assert ch[3][3] - ch[2][3] == pytest.approx(10.0, abs=0.2) and c.scale == 1.0
    ch, t = stream(c, 1.0, cost, lambda s: {1.0: 0.060, 0.5: 0.008}[s], t)     # a burst: down
    assert [x[:2] for x in ch] == [(1.0, 0.5)]
    down = ch[0][3]
    ch, t = stream(c, 10.0, cost, lambda s: {1.0: 0.020, 0.5: 0.008}[s], t)
    assert [x[:3] for x in ch] == [(0.5, 1.0, False)]
    assert ch[0][3] - down == pytest.approx(1.17, abs=0.2) and c.ups_failed == 1
