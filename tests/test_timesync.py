"""eonav.nav.timesync: stamp association and pose interpolation, edge cases against hand-derived values."""
import math

import numpy as np
import pytest

from eonav import InputError
from eonav.geometry.frames import T_body_ned_from_quat, quat_wxyz_from_ypr, ypr_from_T_body_ned
from eonav.nav.timesync import (QF_EXTRAPOLATED, QF_GAP, QF_JITTER, QF_NO_VELOCITY, QF_VELOCITY_AIDED,
                            NavBuffer, match_stamps)

D = math.radians


def yaw_of(q):
    return ypr_from_T_body_ned(T_body_ned_from_quat(q))[0]


# ----------------------------------------------------------------------------- match_stamps
def test_match_exact_and_nearest():
    a = [0, 100_000, 200_000]
    b = [1_000, 99_000, 260_000]
    assert match_stamps(a, b, max_diff_us=5_000) == [(0, 0), (1, 1)]       # 260 ms is 60 ms away


def test_match_no_match():
    assert match_stamps([0, 1_000_000], [500_000], max_diff_us=10_000) == []
    assert match_stamps([], [1, 2], max_diff_us=10) == []
    assert match_stamps([1, 2], [], max_diff_us=10) == []


def test_match_accepts_a_difference_of_exactly_max_diff_on_either_side():
    """``|a - b| <= max_diff_us``: a b exactly max_diff after or before a pairs, one microsecond more does not (also
    through the offset)."""
    assert match_stamps([1_000], [1_500], max_diff_us=500) == [(0, 0)]        # b later by max_diff
    assert match_stamps([1_000], [500], max_diff_us=500) == [(0, 0)]          # b earlier by max_diff
    assert match_stamps([1_000], [1_501], max_diff_us=500) == []
    assert match_stamps([1_000], [499], max_diff_us=500) == []
    assert match_stamps([1_000], [1_400], max_diff_us=500, offset_us=100) == [(0, 0)]
    assert match_stamps([1_000], [1_400], max_diff_us=500, offset_us=101) == []


def test_match_clock_offset():
    # b is on a clock 0.5 s behind a: b + 500 ms lands on a
    a = np.array([1_000_000, 1_100_000, 1_200_000])
    b = a - 500_000 + np.array([300, -200, 0])
    assert match_stamps(a, b, max_diff_us=1_000) == []
    assert match_stamps(a, b, max_diff_us=1_000, offset_us=500_000) == [(0, 0), (1, 1), (2, 2)]


def test_match_out_of_order_returns_original_indices():
    a = [300, 100, 200]
    b = [210, 290, 95]
    assert match_stamps(a, b, max_diff_us=20) == [(0, 1), (1, 2), (2, 0)]


def test_match_duplicate_stamps_one_to_one():
    # two frames with the same stamp and one nav sample: only one pair
    assert match_stamps([100, 100], [100], max_diff_us=5) == [(0, 0)]
    assert match_stamps([100], [100, 100], max_diff_us=5) == [(0, 0)]


def test_match_greedy_closest_first():
    # b=6 is 6 from a=0 and 4 from a=10: the closer pair wins, a=0 stays unmatched
    assert match_stamps([0, 10], [6], max_diff_us=10) == [(1, 0)]


def test_match_rejects_bad_input():
    with pytest.raises(InputError, match="finite"):
        match_stamps([0.0, float("nan")], [0], 10)
    with pytest.raises(InputError, match="non-negative"):
        match_stamps([0], [0], -1)
    with pytest.raises(InputError, match="1-D"):
        match_stamps([[0, 1]], [0], 10)


# ----------------------------------------------------------------------------- NavBuffer
def _buf(**kw):
    kw.setdefault("max_gap_us", 250_000)
    return NavBuffer(**kw)


def test_interpolation_hand_values():
    nb = _buf()
    nb.add(0, quat_wxyz_from_ypr(0, 0, 0), [0, 0, -10])
    nb.add(100_000, quat_wxyz_from_ypr(D(90), 0, 0), [4, -2, -11])
    r = nb.pose_at(25_000)
    assert r.ok and r.reason == ""
    # slerp at constant rate about a fixed axis: a quarter of 90 deg
    assert yaw_of(r.q_wxyz) == pytest.approx(D(22.5), abs=1e-12)
    np.testing.assert_allclose(r.position_ned_m, [1.0, -0.5, -10.25], atol=1e-12)
    np.testing.assert_allclose(r.velocity_ned_mps, [40.0, -20.0, -10.0], atol=1e-9)   # finite difference
    assert r.nav_gap_us == 100_000 and r.quality_flags & QF_GAP      # 100 ms > 60 ms warn


def test_slerp_across_yaw_wrap():
    nb = _buf()
    nb.add(0, quat_wxyz_from_ypr(D(170), 0, 0), [0, 0, 0])
    nb.add(40_000, quat_wxyz_from_ypr(D(-170), 0, 0), [0, 0, 0])
    # midway through a 20 deg turn across the wrap: 180 deg, not 0 deg
    assert abs(yaw_of(nb.pose_at(20_000).q_wxyz)) == pytest.approx(math.pi, abs=1e-9)
    # a quarter: 175 deg
    assert yaw_of(nb.pose_at(10_000).q_wxyz) == pytest.approx(D(175), abs=1e-9)
    # three quarters: -175 deg
    assert yaw_of(nb.pose_at(30_000).q_wxyz) == pytest.approx(D(-175), abs=1e-9)


def test_hermite_velocity_aided_constant_acceleration():
    # p = 0.5 a t^2, v = a t, a = 4 m/s^2 north: samples at 0 and 0.1 s
    a = 4.0
    nb = _buf()
    for t_s in (0.0, 0.1):
        nb.add(int(t_s * 1e6), [1, 0, 0, 0], [0.5 * a * t_s**2, 0, 0], [a * t_s, 0, 0])
    r = nb.pose_at(50_000)
    assert r.quality_flags & QF_VELOCITY_AIDED
    assert r.position_ned_m[0] == pytest.approx(0.5 * a * 0.05**2, abs=1e-12)     # 5 mm; linear gives 10 mm
    assert r.velocity_ned_mps[0] == pytest.approx(a * 0.05, abs=1e-12)


def test_hermite_exact_for_cubic_motion_with_both_end_velocities_nonzero():
    """The velocity-aided interpolation is exact for motion up to cubic in time: position and velocity of
    p(t) = p0 + v0 t + a t^2 / 2 + j t^3 / 6 between 25 Hz samples at 1.00 and 1.04 s (both end velocities non-zero,
    each weighted by the bracket's 40 ms)."""
    p0, v0, a, j = (np.array([100.0, -20.0, -50.0]), np.array([20.0, -5.0, 1.0]), np.array([3.0, 2.0, -1.0]),
                    np.array([-6.0, 1.5, 0.5]))

    def truth(t_s):
        return p0 + v0 * t_s + a * t_s**2 / 2 + j * t_s**3 / 6, v0 + a * t_s + j * t_s**2 / 2

    nb = _buf()
    for t_us in (1_000_000, 1_040_000):
        p, v = truth(t_us * 1e-6)
        nb.add(t_us, [1, 0, 0, 0], p, v)
    for t_us in (1_010_000, 1_025_000):
        r = nb.pose_at(t_us)
        p, v = truth(t_us * 1e-6)
        assert r.ok and r.quality_flags & QF_VELOCITY_AIDED
        np.testing.assert_allclose(r.position_ned_m, p, atol=1e-9)
        np.testing.assert_allclose(r.velocity_ned_mps, v, atol=1e-7)


def test_no_velocity_flag_when_single_sample_without_velocity():
    nb = _buf()
    nb.add(0, [1, 0, 0, 0], [1, 2, 3])
    r = nb.pose_at(0)
    assert r.ok and r.quality_flags & QF_NO_VELOCITY
    np.testing.assert_allclose(r.position_ned_m, [1, 2, 3])


def test_gap_never():
    nb = _buf(max_gap_us=200_000)
    nb.add(0, [1, 0, 0, 0], [0, 0, 0])
    nb.add(500_000, [1, 0, 0, 0], [5, 0, 0])
    d = nb.decide(250_000)
    assert (d.state, d.reason) == ("never", "gap")
    r = nb.pose_at(250_000)
    assert not r.ok and r.reason == "gap"
    assert nb.pose_at(500_000).ok          # an exact hit needs no bracket


def test_jitter_flag():
    nb = _buf()
    for t in (0, 10_000, 20_000, 30_000, 40_000, 70_000, 80_000):
        nb.add(t, [1, 0, 0, 0], [t * 1e-6, 0, 0])
    assert not nb.pose_at(15_000).quality_flags & QF_JITTER
    assert nb.pose_at(55_000).quality_flags & QF_JITTER         # 30 ms bracket vs 10 ms spacing


def test_extrapolation_limit():
    nb = _buf(max_extrapolation_us=20_000)
    nb.add(0, quat_wxyz_from_ypr(0, 0, 0), [0, 0, 0], [10, 0, 0])
    nb.add(100_000, quat_wxyz_from_ypr(D(10), 0, 0), [1, 0, 0], [10, 0, 0])
    assert nb.decide(115_000).state == "wait"
    assert nb.pose_at(115_000).reason == "waiting_for_attitude"
    r = nb.pose_at(115_000, allow_extrapolation=True)
    assert r.ok and r.quality_flags & QF_EXTRAPOLATED
    assert yaw_of(r.q_wxyz) == pytest.approx(D(11.5), abs=1e-9)          # same rate continued
    assert r.position_ned_m[0] == pytest.approx(1.15, abs=1e-12)
    r = nb.pose_at(125_000, allow_extrapolation=True)
    assert not r.ok and r.reason == "extrapolation_limit"
    # before the first sample: within the limit ready (flagged), beyond it never
    assert nb.pose_at(-10_000).ok and nb.pose_at(-10_000).quality_flags & QF_EXTRAPOLATED
    assert nb.decide(-30_000).reason == "before_first_nav"


def test_watermark_wait_then_ready():
    nb = _buf()
    assert nb.watermark_us is None
    assert nb.decide(150_000).state == "wait"
    nb.add(0, [1, 0, 0, 0], None)
    nb.add(100_000, [1, 0, 0, 0], None)
    nb.add(0, None, [0, 0, 0])
    nb.add(200_000, None, [2, 0, 0])
    # attitude reached 100 ms, position 200 ms: the watermark is the older, 100 ms
    assert nb.watermark_us == 100_000
    d = nb.decide(150_000)
    assert (d.state, d.reason) == ("wait", "waiting_for_attitude")
    nb.add(200_000, [1, 0, 0, 0], None)
    assert nb.decide(150_000).state == "ready"
    np.testing.assert_allclose(nb.pose_at(150_000).position_ned_m, [1.5, 0, 0])


def test_watermark_late_frame_older_than_buffer():
    nb = _buf(max_samples=4)
    for k in range(10):
        nb.add(k * 10_000, [1, 0, 0, 0], [k, 0, 0])
    # samples 0..5 were evicted: a frame at 20 ms can never be posed
    d = nb.decide(20_000)
    assert (d.state, d.reason) == ("never", "older_than_buffer")
    assert nb.decide(75_000).state == "ready"
    # a nav sample older than the evicted horizon is refused
    nb.add(30_000, [1, 0, 0, 0], [3, 0, 0])
    assert nb.counts["too_old"] == 2        # counted for attitude and position


def test_out_of_order_nav_samples():
    rng = np.random.default_rng(3)
    ts = np.arange(0, 200_000, 10_000)
    ref, shuf = _buf(), _buf()
    for t in ts:
        ref.add(int(t), quat_wxyz_from_ypr(t * 1e-6, 0, 0), [t * 1e-5, 0, 0])
    for t in rng.permutation(ts):
        shuf.add(int(t), quat_wxyz_from_ypr(t * 1e-6, 0, 0), [t * 1e-5, 0, 0])
    assert shuf.counts["out_of_order"] > 0
    for t in (5_000, 77_000, 190_000):
        a, b = ref.pose_at(t), shuf.pose_at(t)
        np.testing.assert_array_equal(a.position_ned_m, b.position_ned_m)
        np.testing.assert_array_equal(a.q_wxyz, b.q_wxyz)


def test_duplicate_nav_stamps_keep_first():
    nb = _buf()
    nb.add(0, [1, 0, 0, 0], [0, 0, 0])
    nb.add(100_000, [1, 0, 0, 0], [1, 0, 0])
    nb.add(100_000, [1, 0, 0, 0], [9, 9, 9])
    assert nb.counts["duplicate_stamp"] == 2
    np.testing.assert_allclose(nb.pose_at(100_000).position_ned_m, [1, 0, 0])


def test_bad_nav_samples_ignored():
    nb = _buf()
    nb.add(0, [np.nan, 0, 0, 0], [np.inf, 0, 0])
    nb.add(0, [2, 0, 0, 0], None)            # not a unit quaternion
    assert len(nb.att) == 0 and len(nb.pos) == 0
    assert nb.counts["bad_attitude"] == 2 and nb.counts["bad_position"] == 1
    nb.add(0, [np.nan] * 4, [np.nan] * 3)    # an absent part (all NaN by schema convention) is not an error
    assert nb.counts["bad_attitude"] == 2 and nb.counts["bad_position"] == 1


def test_attitude_only_mode():
    nb = _buf(require_position=False)
    nb.add(0, quat_wxyz_from_ypr(0, 0, 0))
    nb.add(20_000, quat_wxyz_from_ypr(0, D(2), 0))
    r = nb.pose_at(10_000)
    assert r.ok and np.all(np.isnan(r.position_ned_m))
    assert ypr_from_T_body_ned(T_body_ned_from_quat(r.q_wxyz))[1] == pytest.approx(D(1), abs=1e-12)
    assert not _buf().pose_at(10_000).ok


def test_nav_sample_and_frame_exactly_at_the_evicted_horizon_are_too_old():
    """The eviction horizon is inclusive: with samples every 10 ms in a 4-sample buffer, 0..50 ms were evicted. A nav
    sample stamped 50 ms again is refused as ``too_old`` (not taken as an out-of-order sample and evicted at once), and
    a frame at 50 ms is ``never`` / ``older_than_buffer`` like one at 49.999 ms, not extrapolated 10 ms back from the
    60 ms sample."""
    nb = _buf(max_samples=4)
    for k in range(10):
        nb.add(k * 10_000, [1, 0, 0, 0], [k, 0, 0])
    assert nb.att.t == [60_000, 70_000, 80_000, 90_000]
    nb.add(50_000, [1, 0, 0, 0], [5, 0, 0])
    assert nb.counts["too_old"] == 2 and nb.counts["out_of_order"] == 0      # attitude and position
    for t in (49_999, 50_000):
        d = nb.decide(t)
        assert (d.state, d.reason) == ("never", "older_than_buffer")
        r = nb.pose_at(t)
        assert not r.ok and r.reason == "older_than_buffer"
    assert nb.decide(50_001).state == "ready"         # 9.999 ms before the first kept sample: within 20 ms


def test_extrapolation_limit_is_inclusive_before_and_after_the_samples():
    """``max_extrapolation_us`` (20 ms) is the farthest a pose may be extrapolated, on both sides: positions 0 m at
    0.1 s and 1 m at 0.2 s (10 m/s), a frame exactly 20 ms before the first sample is posed at -0.2 m, exactly 20 ms
    after the newest at 1.2 m (both flagged); one microsecond further is refused."""
    nb = _buf(max_extrapolation_us=20_000)
    nb.add(100_000, [1, 0, 0, 0], [0, 0, 0])
    nb.add(200_000, [1, 0, 0, 0], [1, 0, 0])
    r = nb.pose_at(80_000)
    assert r.ok and r.quality_flags & QF_EXTRAPOLATED
    assert r.position_ned_m[0] == pytest.approx(-0.2, abs=1e-12)
    d = nb.decide(79_999)
    assert (d.state, d.reason) == ("never", "before_first_nav")
    r = nb.pose_at(220_000, allow_extrapolation=True)
    assert r.ok and r.quality_flags & QF_EXTRAPOLATED
    assert r.position_ned_m[0] == pytest.approx(1.2, abs=1e-12)
    r = nb.pose_at(220_001, allow_extrapolation=True)
    assert not r.ok and r.reason == "extrapolation_limit"


def test_max_gap_is_the_largest_bracket_accepted_and_gap_warn_flags_only_above():
    """``max_gap_us`` is the largest bracket accepted (a 250 ms bracket poses its midpoint, 250.001 ms is a ``gap``);
    ``gap_warn_us`` flags QF_GAP only for brackets above it (60 ms: not flagged, 60.001 ms: flagged)."""
    nb = _buf(max_gap_us=250_000)
    nb.add(0, [1, 0, 0, 0], [0, 0, 0])
    nb.add(250_000, [1, 0, 0, 0], [5, 0, 0])
    r = nb.pose_at(125_000)
    assert r.ok and r.nav_gap_us == 250_000
    assert r.position_ned_m[0] == pytest.approx(2.5, abs=1e-12)
    nb = _buf(max_gap_us=250_000)
    nb.add(0, [1, 0, 0, 0], [0, 0, 0])
    nb.add(250_001, [1, 0, 0, 0], [5, 0, 0])
    d = nb.decide(125_000)
    assert (d.state, d.reason) == ("never", "gap")
    for end, flagged in ((60_000, False), (60_001, True)):
        nb = _buf(gap_warn_us=60_000)
        nb.add(0, [1, 0, 0, 0], [0, 0, 0])
        nb.add(end, [1, 0, 0, 0], [1, 0, 0])
        r = nb.pose_at(30_000)
        assert r.ok and r.nav_gap_us == end
        assert bool(r.quality_flags & QF_GAP) == flagged


def test_attitude_norm_tolerance_is_two_sided():
    """An attitude is taken only when its norm is within 1 % of 1, on both sides: norms 0.5 and 0.98 are refused
    (``bad_attitude``) like 2; a norm of 1.005 is taken and stored normalised."""
    nb = _buf()
    nb.add(0, [0.5, 0, 0, 0], None)
    nb.add(10_000, [0.98, 0, 0, 0], None)
    assert len(nb.att) == 0 and nb.counts["bad_attitude"] == 2
    nb.add(20_000, [1.005, 0, 0, 0], None)
    assert nb.att.t == [20_000]
    np.testing.assert_allclose(nb.att.v[0], [1, 0, 0, 0], atol=1e-15)


def test_interpolated_quaternion_has_non_negative_w_across_the_yaw_wrap():
    """The library's quaternions have w >= 0 (eonav.geometry.frames). Slerp from yaw 170 deg to -170 deg takes the
    short way, through 180 deg, where the arc leaves that hemisphere: three quarters along (yaw -175 deg) the pose's
    quaternion is quat_wxyz_from_ypr(-175 deg) itself, not its negative."""
    nb = _buf()
    nb.add(0, quat_wxyz_from_ypr(D(170), 0, 0), [0, 0, 0])
    nb.add(40_000, quat_wxyz_from_ypr(D(-170), 0, 0), [0, 0, 0])
    q = nb.pose_at(30_000).q_wxyz
    assert q[0] >= 0
    np.testing.assert_allclose(q, quat_wxyz_from_ypr(D(-175), 0, 0), atol=1e-12)


def test_single_position_sample_extrapolates_along_its_velocity_both_ways():
    """One position sample (5, -2, -10) m at 0.1 s with velocity (10, -5, 1) m/s, attitude bracketing: a frame 10 ms
    after it (extrapolation allowed) is at p + 0.01 v, one 10 ms before it at p - 0.01 v; both flagged, velocity the
    sample's."""
    nb = _buf()
    nb.add(0, [1, 0, 0, 0], None)
    nb.add(200_000, [1, 0, 0, 0], None)
    p, v = np.array([5.0, -2.0, -10.0]), np.array([10.0, -5.0, 1.0])
    nb.add(100_000, None, p, v)
    assert nb.pose_at(110_000).reason == "waiting_for_position"
    for t_us, dt_s, allow in ((110_000, 0.01, True), (90_000, -0.01, False)):
        r = nb.pose_at(t_us, allow_extrapolation=allow)
        assert r.ok and r.quality_flags & QF_EXTRAPOLATED
        np.testing.assert_allclose(r.position_ned_m, p + dt_s * v, atol=1e-12)
        np.testing.assert_allclose(r.velocity_ned_mps, v, atol=0)


def test_extrapolation_continues_the_last_bracket_linearly_not_the_cubic():
    """Beyond the samples position continues the last bracket's straight line and velocity the line through its end
    velocities (the cubic Hermite is for interpolation only). Constant 10 m/s north with noisy velocity reports (10.5,
    9.5 m/s): 15 ms past the 0.1 s sample the position is the truth 1.15 m (the cubic, weighting the noisy velocities,
    gives 1.1414 m). Constant 4 m/s^2 with exact velocities: the extrapolated velocity is the truth a t = 0.46 m/s, the
    position the line's 23 mm, short of the truth by 0.5 a t_ex (t_ex + dt) = 3.45 mm (the bound the sync service's position lead cites)."""
    nb = _buf()
    nb.add(0, [1, 0, 0, 0], [0, 0, 0], [10.5, 0, 0])
    nb.add(100_000, [1, 0, 0, 0], [1, 0, 0], [9.5, 0, 0])
    r = nb.pose_at(115_000, allow_extrapolation=True)
    assert r.ok and r.quality_flags & QF_EXTRAPOLATED and not r.quality_flags & QF_VELOCITY_AIDED
    assert r.position_ned_m[0] == pytest.approx(1.15, abs=1e-12)
    assert nb.pose_at(-10_000).position_ned_m[0] == pytest.approx(-0.1, abs=1e-12)
    a = 4.0
    nb = _buf()
    for t_s in (0.0, 0.1):
        nb.add(int(t_s * 1e6), [1, 0, 0, 0], [0.5 * a * t_s**2, 0, 0], [a * t_s, 0, 0])
    r = nb.pose_at(115_000, allow_extrapolation=True)
    assert r.velocity_ned_mps[0] == pytest.approx(a * 0.115, abs=1e-12)
    assert r.position_ned_m[0] == pytest.approx(0.023, abs=1e-12)
    assert 0.5 * a * 0.115**2 - r.position_ned_m[0] == pytest.approx(0.5 * a * 0.015 * (0.015 + 0.1), abs=1e-12)
