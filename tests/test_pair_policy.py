"""Pair policy edge cases. Hand-derived geometry: a 256 x 256 camera with f = 256 px looking along the nose,
level flight north. Moving forward by d metres, a pixel at radial offset r from the principal point moves by
r * d*rho / (1 + d*rho) between infinity and range 1/rho. The 5 x 5 probe grid (10 %..90 %) has offsets
{0, +-51, +-102} px per axis, whose median radial offset is exactly 102 px: at 50 m, d = 1 m gives
102 * 0.02 / 1.02 = 2.0 px. A sideways baseline B gives f * B / Z everywhere."""
import math

import numpy as np
import pytest

from eonav import InputError
from eonav.geometry.camera import Camera, VehicleState
from eonav.geometry.frames import camera_from_ned
from eonav.ranging import pair_policy as pp

CAM = Camera("nose", 256, 256, 256.0, 256.0, 127.5, 127.5)


def frame(seq, t_s, north_m=0.0, yaw_deg=0.0, cam=CAM, east_m=0.0):
    st = VehicleState.from_ypr([north_m, east_m, -10.0], np.deg2rad([yaw_deg, 0.0, 0.0]), t_s)
    return pp.PosedFrameInfo(cam.name, seq, int(round(t_s * 1e6)) + 1_700_000_000_000_000, cam, st, payload=seq)


def policy(**kw):
    return pp.PairPolicy(pp.PairPolicyConfig(**kw))


def test_first_frame_has_no_pair():
    d = policy().offer(frame(0, 0.0))
    assert not d.ok and d.reason == pp.FIRST_FRAME and d.kind == "none"


def test_disparity_matches_hand_derived_value():
    m = pp.pair_metrics(frame(1, 0.1, north_m=1.0), frame(0, 0.0), ref_range_m=50.0)
    assert m.disparity_px == pytest.approx(102 * 0.02 / 1.02, rel=1e-9)
    assert m.baseline_m == pytest.approx(1.0) and m.rotation_deg == pytest.approx(0.0, abs=1e-6)
    assert m.dt_s == pytest.approx(0.1)


def test_disparity_matches_projection_of_real_points():
    # independent truth: put a world point at x_c = 50 m behind each probe pixel of frame a (eq. 33 by hand),
    # and a point at 1e9 m, project both into frame b (eqs. 12, 15, 8, 9) and take the median shift
    a, b = frame(1, 0.1, north_m=3.0, yaw_deg=2.0, east_m=0.4), frame(0, 0.0)
    T1 = CAM.T_cam_body
    shifts = []
    for v in np.linspace(0.1, 0.9, 5) * 255:
        for u in np.linspace(0.1, 0.9, 5) * 255:
            ray = np.array([1.0, (u - CAM.cx) / CAM.fx, (v - CAM.cy) / CAM.fy])
            uv = []
            for x_c in (50.0, 1e9):
                p_ned = a.state.position_ned_m + a.state.T_body_ned.T @ (T1.T @ (ray * x_c))
                xb = camera_from_ned(p_ned, T1, b.state.T_body_ned, b.state.position_ned_m, CAM.l_body_m)
                uv.append((CAM.fx * xb[1] / xb[0], CAM.fy * xb[2] / xb[0]))
            shifts.append(math.dist(*uv))
    m = pp.pair_metrics(a, b, 50.0)
    assert m.disparity_px == pytest.approx(float(np.median(shifts)), rel=1e-6)
    assert m.rotation_deg == pytest.approx(2.0, abs=1e-6)
    assert m.baseline_m == pytest.approx(math.hypot(3.0, 0.4), rel=1e-9)


def test_probe_grid_spans_each_axis_of_a_wide_image():
    """The probe grid spans 10..90 % of each axis: on a 321 x 161 camera (cx 160, cy 80) its offsets are {0, +-64,
    +-128} px across and {0, +-32, +-64} px down; the 25 radial offsets sorted are 0, 32 x2, 64 x4, 71.6 x4, 90.5 x4,
    ..., median (13th) 64 sqrt 2 px. 1 m forward at 50 m: 64 sqrt 2 * 0.02 / 1.02 px. Catches a planted swap of width
    and height in the probe grid (probes below the image, the median of other pixels)."""
    wide = Camera("wide", 321, 161, 160.0, 160.0, 160.0, 80.0)
    m = pp.pair_metrics(frame(1, 0.1, north_m=1.0, cam=wide), frame(0, 0.0, cam=wide), ref_range_m=50.0)
    assert m.disparity_px == pytest.approx(64 * math.sqrt(2) * 0.02 / 1.02, rel=1e-9)


def test_disparity_in_pixels_does_not_depend_on_non_square_pixels():
    """Moving forward shifts a pixel radially by r d rho / (1 + d rho) in pixels whatever fx and fy (the probe ray's
    x_p / fx, y_p / fy and its projection's fx, fy cancel): a camera with fy = fx / 2 has the square camera's
    102 * 0.02 / 1.02 px at 1 m and 50 m. Catches a planted fx for fy in the probe rays (the v shifts halved)."""
    tall = Camera("nose", 256, 256, 256.0, 128.0, 127.5, 127.5)
    m = pp.pair_metrics(frame(1, 0.1, north_m=1.0, cam=tall), frame(0, 0.0, cam=tall), ref_range_m=50.0)
    assert m.disparity_px == pytest.approx(102 * 0.02 / 1.02, rel=1e-9)


def test_parallax_threshold_on_both_sides():
    p = policy(min_disparity_px=2.0, ref_range_m=50.0)
    p.offer(frame(0, 0.0, 0.0))
    d = p.offer(frame(1, 0.1, 0.95))                    # 1.94 px < 2
    assert d.reason == pp.TOO_LITTLE_PARALLAX and not d.ok
    assert d.disparity_px == pytest.approx(102 * 0.019 / 1.019)
    d = p.offer(frame(2, 0.2, 1.05))                    # 0.10 m from frame 1, 1.05 m from frame 0
    assert d.ok and d.reason == pp.OK_MOTION and d.kind == "motion"
    assert d.a.seq == 2 and d.b.seq == 0 and d.a.payload == 2 and d.b.payload == 0
    assert d.baseline_m == pytest.approx(1.05)


def test_parallax_exactly_at_the_thresholds_qualifies():
    """The thresholds are "at least": 0.5 m sideways judged at 64 m gives f B / Z = 256 * 0.5 / 64 = 2 px, exact in
    binary floating point (every factor a power of two), so min_disparity_px = 2 pairs, as does min_baseline_m = 0.5
    with the disparity far short. Catches a planted > for >= in the parallax test."""
    p = policy(min_disparity_px=2.0, ref_range_m=64.0)
    p.offer(frame(0, 0.0))
    d = p.offer(frame(1, 0.1, east_m=0.5))
    assert d.disparity_px == 2.0 and d.ok and d.b.seq == 0
    p = policy(min_disparity_px=50.0, min_baseline_m=0.5, ref_range_m=64.0)
    p.offer(frame(0, 0.0))
    d = p.offer(frame(1, 0.1, east_m=0.5))
    assert d.baseline_m == 0.5 and d.ok and d.b.seq == 0


def test_newest_sufficient_frame_wins():
    p = policy(min_disparity_px=2.0, ref_range_m=50.0)
    for i in range(5):
        p.offer(frame(i, 0.1 * i, 1.5 * i))             # every step alone is enough
    d = p.offer(frame(5, 0.5, 7.5))
    assert d.ok and d.b.seq == 4


def test_min_baseline_qualifies_when_disparity_small():
    p = policy(min_disparity_px=50.0, min_baseline_m=0.8)
    p.offer(frame(0, 0.0, 0.0))
    d = p.offer(frame(1, 0.1, 0.5))
    assert d.reason == pp.TOO_LITTLE_PARALLAX and "baseline 0.500 m < 0.8 m" in d.detail
    d = p.offer(frame(2, 0.2, 0.9))
    assert d.ok and d.b.seq == 0


def test_too_old():
    p = policy(max_age_s=0.5)
    p.offer(frame(0, 0.0, 0.0))
    d = p.offer(frame(1, 0.6, 20.0))
    assert d.reason == pp.TOO_OLD and d.dt_s == pytest.approx(0.6)



def test_a_partner_exactly_max_age_old_is_accepted_one_microsecond_more_is_not():
    """max_age_s is the oldest partner accepted: 500 000 us is 0.5 s exactly (500000 x 1e-6 rounds to 0.5), so a
    frame 0.5 s old pairs under max_age_s 0.5, one 1 us older is TOO_OLD. Catches a planted >= for > in the age
    test (a partner at exactly the limit refused)."""
    p = policy(max_age_s=0.5)
    p.offer(frame(0, 0.0))
    d = p.offer(frame(1, 0.5, 20.0))
    assert d.ok and d.b.seq == 0 and d.dt_s == 0.5
    p = policy(max_age_s=0.5)
    p.offer(frame(0, 0.0))
    assert p.offer(frame(1, 0.500001, 20.0)).reason == pp.TOO_OLD


def test_too_old_reports_the_age_of_the_newest_earlier_frame():
    """Every earlier frame too old: the decision gives how old the newest of them is (what a healthy stream would
    have paired with), 1.0 - 0.2 = 0.8 s here, not the oldest's 1.0 s."""
    p = policy(max_age_s=0.5)
    p.offer(frame(0, 0.0))
    p.offer(frame(1, 0.2, 0.5))
    d = p.offer(frame(2, 1.0, 20.0))
    assert d.reason == pp.TOO_OLD and d.dt_s == pytest.approx(0.8) and "0.800 s old" in d.detail


def test_too_little_parallax_reports_the_best_candidate():
    """No earlier frame gives enough parallax: the decision carries the candidate with the most (the one to wait
    for), here frame 0, 0.75 m behind the new frame (102 x 0.015 / 1.015 px at 50 m), not the newest, 0.05 m
    behind (0.1 px), nor the middle one, 0.15 m."""
    p = policy(min_disparity_px=2.0, ref_range_m=50.0)
    for i, north in enumerate((0.0, 0.6, 0.7)):
        p.offer(frame(i, 0.1 * i, north))
    d = p.offer(frame(3, 0.3, 0.75))
    assert d.reason == pp.TOO_LITTLE_PARALLAX
    assert d.disparity_px == pytest.approx(102 * 0.015 / 1.015) and d.baseline_m == pytest.approx(0.75)

def test_too_much_rotation():
    p = policy(max_rotation_deg=10.0)
    p.offer(frame(0, 0.0, 0.0, yaw_deg=0.0))
    d = p.offer(frame(1, 0.1, 5.0, yaw_deg=15.0))
    assert d.reason == pp.TOO_MUCH_ROTATION and d.rotation_deg == pytest.approx(15.0)
    d = p.offer(frame(2, 0.2, 10.0, yaw_deg=18.0))     # 3 deg from frame 1: fine
    assert d.ok and d.b.seq == 1


def test_a_turned_newest_frame_is_passed_over_for_an_older_one_within_the_limit():
    """A yaw wobble: the newest earlier frame is turned 15 deg (> max_rotation_deg), the one before it is level like
    the new frame: the policy looks past the turned frame to the level one (rotation, unlike age, does not grow
    further back), 2 m forward: 102 * 0.04 / 1.04 px. Catches a planted ``break`` for ``continue`` after a frame
    rotated too much (no pair until the wobble leaves the history)."""
    p = policy(max_rotation_deg=10.0)
    p.offer(frame(0, 0.0, 0.0))
    assert p.offer(frame(1, 0.1, 1.0, yaw_deg=15.0)).reason == pp.TOO_MUCH_ROTATION
    d = p.offer(frame(2, 0.2, 2.0))
    assert d.ok and d.reason == pp.OK_MOTION and d.b.seq == 0
    assert d.rotation_deg == pytest.approx(0.0, abs=1e-6) and d.disparity_px == pytest.approx(102 * 0.04 / 1.04)


def test_parallax_reason_wins_over_rotation_reason():
    p = policy(max_rotation_deg=10.0)
    p.offer(frame(0, 0.0, 0.0, yaw_deg=30.0))           # rotated too much
    p.offer(frame(1, 0.05, 0.0))                        # no motion at all
    d = p.offer(frame(2, 0.1, 0.1))
    assert d.reason == pp.TOO_LITTLE_PARALLAX


def test_out_of_order_frame_is_dropped_and_not_kept():
    p = policy()
    p.offer(frame(0, 0.0, 0.0))
    p.offer(frame(1, 0.2, 2.0))
    d = p.offer(frame(9, 0.1, 1.0))
    assert d.reason == pp.OUT_OF_ORDER
    assert [f.seq for f in p.history("nose")] == [0, 1]
    d = p.offer(frame(2, 0.2, 2.5))                     # same stamp as last: also out of order
    assert d.reason == pp.OUT_OF_ORDER


def test_big_backward_jump_resets_history():
    p = policy(max_age_s=1.0)
    p.offer(frame(0, 10.0, 0.0))
    p.offer(frame(1, 10.1, 2.0))
    d = p.offer(frame(0, 0.0, 0.0))                     # replay restarted
    assert d.reason == pp.HISTORY_RESET
    assert [f.seq for f in p.history("nose")] == [0]
    d = p.offer(frame(1, 0.1, 2.0))
    assert d.ok and d.b.stamp_us == frame(0, 0.0).stamp_us


def test_history_is_bounded():
    p = policy(history=3)
    for i in range(10):
        p.offer(frame(i, 0.01 * i, 0.0))
    assert [f.seq for f in p.history("nose")] == [7, 8, 9]


def test_camera_size_change_clears_history():
    p = policy()
    p.offer(frame(0, 0.0, 0.0))
    small = Camera("nose", 128, 128, 128.0, 128.0, 63.5, 63.5)
    d = p.offer(frame(1, 0.1, 5.0, cam=small))
    assert d.reason == pp.CAMERA_MISMATCH and len(p.history("nose")) == 1


def test_cameras_keep_separate_histories():
    p = policy()
    tail = Camera("tail", 256, 256, 256.0, 256.0, 127.5, 127.5)
    p.offer(frame(0, 0.0, 0.0))
    d = p.offer(frame(0, 0.05, 3.0, cam=tail))
    assert d.reason == pp.FIRST_FRAME


# -- stereo ------------------------------------------------------------------------------------
LEFT = Camera("left", 256, 256, 256.0, 256.0, 127.5, 127.5, l_body_m=[1.0, -0.25, 0.0])
RIGHT = Camera("right", 256, 256, 256.0, 256.0, 127.5, 127.5, l_body_m=[1.0, 0.25, 0.0])


def test_stereo_pair_either_arrival_order():
    for first, second in ((LEFT, RIGHT), (RIGHT, LEFT)):
        p = policy(stereo_rig=("left", "right"), max_stereo_dt_s=0.002, min_disparity_px=2.0)
        d1 = p.offer(frame(0, 0.0, 0.0, cam=first))
        assert not d1.ok
        d2 = p.offer(frame(0, 0.001, 0.0, cam=second))
        assert d2.ok and d2.reason == pp.OK_STEREO and d2.kind == "stereo"
        assert d2.a.camera_id == "left" and d2.b.camera_id == "right"   # reference is the rig's first camera
        assert d2.disparity_px == pytest.approx(256 * 0.5 / 50.0, rel=1e-6)   # f B / Z
        assert d2.baseline_m == pytest.approx(0.5)


def test_stereo_awaits_live_partner_and_uses_each_reference_once():
    p = policy(stereo_rig=("left", "right"), min_disparity_px=100.0, min_baseline_m=0.4)
    p.offer(frame(0, 0.0, 0.0, cam=LEFT))
    assert p.offer(frame(0, 0.0005, 0.0, cam=RIGHT)).reason == pp.OK_STEREO
    d = p.offer(frame(1, 0.1, 2.0, cam=LEFT))           # right's frame for t=0.1 not here yet
    assert d.reason == pp.AWAITING_STEREO
    d = p.offer(frame(1, 0.1, 2.0, cam=RIGHT))
    assert d.reason == pp.OK_STEREO and d.a.seq == 1


def test_stereo_too_little_parallax():
    p = policy(stereo_rig=("left", "right"), min_disparity_px=5.0)     # 2.56 px available
    p.offer(frame(0, 0.0, 0.0, cam=LEFT))
    d = p.offer(frame(0, 0.0, 0.0, cam=RIGHT))
    assert d.reason == pp.TOO_LITTLE_PARALLAX and "stereo" in d.detail


def test_stereo_falls_back_to_motion_when_partner_silent():
    p = policy(stereo_rig=("left", "right"), max_age_s=0.5)
    p.offer(frame(0, 0.0, 0.0, cam=RIGHT))
    p.offer(frame(0, 1.0, 0.0, cam=LEFT))               # right last seen 1 s ago: silent
    d = p.offer(frame(1, 1.1, 2.0, cam=LEFT))
    assert d.reason == pp.OK_MOTION and d.b.seq == 0 and d.b.camera_id == "left"


def test_stereo_pair_at_exactly_max_stereo_dt():
    """max_stereo_dt_s is the largest stamp difference of a pair, inclusive: 2000 us apart pairs at 2 ms (integer
    stamps; 0.002 * 1e6 is 2000.0 exactly), 2001 us does not (the right frame waits for a left one). Catches a planted
    < for <= in the stereo match."""
    p = policy(stereo_rig=("left", "right"), max_stereo_dt_s=0.002)
    p.offer(frame(0, 0.0, cam=LEFT))
    d = p.offer(frame(0, 0.002, cam=RIGHT))
    assert d.reason == pp.OK_STEREO and d.dt_s == pytest.approx(-0.002)
    p = policy(stereo_rig=("left", "right"), max_stereo_dt_s=0.002)
    p.offer(frame(0, 0.0, cam=LEFT))
    assert p.offer(frame(0, 0.002001, cam=RIGHT)).reason == pp.AWAITING_STEREO


def test_stereo_reference_is_not_paired_twice_by_a_faster_partner():
    """A partner frame arriving 1 ms after one already paired with the left reference (a faster partner camera, or a
    repeat) is within 2 ms of that reference, but the reference has been measured: pairing it again would fuse the
    same ranges twice. The right frame falls back to motion (none: it has not moved). Catches a planted removal of the
    used-reference check."""
    p = policy(stereo_rig=("left", "right"), max_stereo_dt_s=0.002)
    p.offer(frame(0, 0.0, cam=LEFT))
    assert p.offer(frame(0, 0.0005, cam=RIGHT)).reason == pp.OK_STEREO
    d = p.offer(frame(1, 0.0015, cam=RIGHT))
    assert not d.ok and d.reason == pp.TOO_LITTLE_PARALLAX


def test_stereo_frame_whose_partner_already_passed_its_instant_falls_back_to_motion():
    """The right camera dropped its 0.1 s frame and delivered its 0.2 s one before the left 0.1 s frame arrived: no
    right frame for 0.1 s can come any more, so the left frame does not wait but pairs with the left frame 2 m back
    (102 * 0.04 / 1.04 px); at 0.2 s the rig pairs again. Catches a planted removal of "partner behind us" from the
    wait (the frame would wait for a partner that never comes, and be lost)."""
    p = policy(stereo_rig=("left", "right"), max_stereo_dt_s=0.002)
    p.offer(frame(0, 0.0, cam=LEFT))
    assert p.offer(frame(0, 0.0, cam=RIGHT)).reason == pp.OK_STEREO
    assert p.offer(frame(2, 0.2, 4.0, cam=RIGHT)).reason == pp.AWAITING_STEREO     # left behind: its frame will come
    d = p.offer(frame(1, 0.1, 2.0, cam=LEFT))
    assert d.reason == pp.OK_MOTION and d.b.seq == 0 and d.b.camera_id == "left"
    assert d.disparity_px == pytest.approx(102 * 0.04 / 1.04)
    d = p.offer(frame(2, 0.2, 4.0, cam=LEFT))
    assert d.reason == pp.OK_STEREO and d.a.seq == 2 and d.b.seq == 2


@pytest.mark.parametrize("kw, match", [
    ({"min_disparity_px": -1.0}, "min_disparity_px"),
    ({"ref_range_m": 0.0}, "ref_range_m"),
    ({"max_age_s": math.nan}, "max_age_s"),
    ({"history": 0}, "history"),
    ({"stereo_rig": ("left", "left")}, "stereo_rig"),
    ({"stereo_rig": ("left",)}, "stereo_rig"),
])
def test_bad_config_is_rejected(kw, match):
    with pytest.raises(InputError, match=match):
        pp.PairPolicyConfig(**kw)


def test_remember_adds_a_partner_without_a_decision():
    """A frame the locator skipped (a newer one was waiting) still serves as the partner of the next frame."""
    cam = Camera("nose", 256, 256, 128.0, 128.0, 127.5, 127.5)
    fr = [pp.PosedFrameInfo("nose", i, 1_000_000 + i * 100_000, cam,
                         VehicleState.from_ypr([2.0 * i, 0.0, -10.0], [0.0, 0.0, 0.0])) for i in range(3)]
    p = pp.PairPolicy(pp.PairPolicyConfig(min_disparity_px=0.5))
    assert p.offer(fr[0]).reason == pp.FIRST_FRAME
    assert p.remember(fr[1]) is True
    d = p.offer(fr[2])
    assert d.ok and d.b.seq == 1                                    # the remembered frame, the newest partner
    assert p.remember(fr[1]) is False                              # out of order: not added
    assert [f.seq for f in p.history("nose")] == [0, 1, 2]
