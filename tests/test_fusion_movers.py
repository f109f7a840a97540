"""A moving object in the fused map: a motion pair cannot range it, a stereo rig can, and the rig's stereo
measurement leads where the motion pairs disagree with it (eonav.fusion.update, "Stereo leads")."""
from dataclasses import replace

import numpy as np
import pytest

from eonav import InputError
from eonav.app.bench_tracking import PARTNER_ID, Mover, Scenario, frames
from eonav.fusion.schedule import ScheduleConfig
from eonav.fusion.sequence import FusionConfig, FusionRunner, frame
from eonav.fusion.state import InverseRangeState
from eonav.fusion.update import UpdateConfig, gate_motion, stereo_restart, stereo_skipped_free
from eonav.geometry.camera import Camera, VehicleState
from eonav.ranging.rangemap import FILLED, ILL_CONDITIONED, LOW_TEXTURE, OCCLUDED, OUT_OF_VIEW, TRUNCATION, VALID
from eonav.sim.scene import Box, Scene

F32 = np.float32


def test_a_motion_pixel_beyond_k_sigma_of_the_same_frames_stereo_pixel_is_not_fused():
    # sigmas 0.003 and 0.004 per m: combined 0.005; k = 3 -> 0.015. Pixels 3.1 / 2.9 sigma off, one unmeasured in
    # the stereo measurement, one flagged OCCLUDED in the motion one
    rho_s = np.full((1, 5), 0.05, F32)
    std_s = np.full((1, 5), 0.004, F32)
    flags_s = np.full((1, 5), VALID, np.uint8)
    rho_m = np.array([[0.05 + 0.0155, 0.05 + 0.0145, 0.05 - 0.0155, 0.09, 0.09]], F32)
    std_m = np.full((1, 5), 0.003, F32)
    flags_m = np.array([[VALID, VALID, VALID, VALID, OUT_OF_VIEW | OCCLUDED]], np.uint8)
    rho_s[0, 3] = np.nan                                            # stereo did not measure pixel 3
    gated = gate_motion(rho_m, std_m, flags_m, rho_s, std_s, flags_s, UpdateConfig(stereo_lead_k=3.0))
    assert gated.tolist() == [[True, False, True, False, False]]
    assert np.isnan(rho_m[0, 0]) and np.isnan(rho_m[0, 2]) and rho_m[0, 1] == F32(0.05 + 0.0145)
    assert rho_m[0, 3] == F32(0.09)
    # k = 0: off
    rho_m2 = np.full((1, 5), 0.2, F32)
    assert not gate_motion(rho_m2, std_m, flags_m, rho_s, std_s, flags_s, UpdateConfig(stereo_lead_k=0.0)).any()
    assert (rho_m2 == F32(0.2)).all()
    with pytest.raises(InputError, match="stereo"):
        gate_motion(rho_m, std_m, flags_m, rho_s[:, :4], std_s[:, :4], flags_s[:, :4])
    with pytest.raises(InputError, match="stereo_lead_k"):
        UpdateConfig(stereo_lead_k=-1.0)


def test_a_motion_pixel_whose_stereo_pixel_failed_to_match_is_not_fused():
    # every motion pixel agrees with rho 0.05 +- 0.003; the stereo pixels: VALID (agrees), OCCLUDED (as the dense
    # method flags it, with OUT_OF_VIEW), TRUNCATION, OUT_OF_VIEW alone (the partner does not see the point),
    # LOW_TEXTURE, a weak ILL_CONDITIONED one (its sigma alone: measured), and OCCLUDED under a motion pixel without
    # a value
    flags_s = np.array([[VALID, OCCLUDED | OUT_OF_VIEW, TRUNCATION, OUT_OF_VIEW, LOW_TEXTURE, ILL_CONDITIONED,
                         OCCLUDED | OUT_OF_VIEW]], np.uint8)
    rho_s = np.full((1, 7), 0.05, F32)
    std_s = np.array([[0.004, 0.004, 0.004, 0.004, 0.004, 0.03, 0.004]], F32)      # pixel 5: sigma 0.6 x rho
    std_m = np.full((1, 7), 0.003, F32)
    flags_m = np.full((1, 7), VALID, np.uint8)

    def motion():
        r = np.full((1, 7), 0.05, F32)
        r[0, 6] = np.nan
        return r
    rho_m = motion()
    gated = gate_motion(rho_m, std_m, flags_m, rho_s, std_s, flags_s, UpdateConfig(stereo_lead_k=3.0))
    assert gated.tolist() == [[False, True, True, False, False, False, False]]
    assert np.isnan(rho_m[0, 1:3]).all() and (rho_m[0, [0, 3, 4, 5]] == F32(0.05)).all()
    # off: only the disagreement test (none here)
    rho_m = motion()
    cfg = UpdateConfig(stereo_lead_k=3.0, gate_unmatched=False)
    assert not gate_motion(rho_m, std_m, flags_m, rho_s, std_s, flags_s, cfg).any()
    assert (rho_m[0, :6] == F32(0.05)).all()
    # stereo leading off (k = 0): nothing, unmatched pixels either
    rho_m = motion()
    assert not gate_motion(rho_m, std_m, flags_m, rho_s, std_s, flags_s, UpdateConfig(stereo_lead_k=0.0)).any()


def _state(mu, var, a=7.0, b=1.0, n=12):
    cam = Camera("c", len(mu), 1, 100.0, 100.0, 0.0, 0.0)
    st = InverseRangeState.empty(cam, VehicleState.from_ypr([0, 0, 0], [0, 0, 0], 0.0), 0.0)
    st.rho[0] = mu
    st.var[0] = var
    st.a[0], st.b[0], st.n[0] = a, b, n
    return st


def test_a_cell_the_stereo_measurement_disagrees_with_beyond_k_sigma_restarts_from_it():
    # cell sigma 0.0003 (converged background at 50 m), stereo sigma 0.004: sqrt(s^2 + tau^2) = 0.0040112;
    # k = 3 -> 0.0120337. Cells 0 and 1 just beyond / within; cell 2 empty (started by the usual update, not here)
    st = _state([0.02, 0.02, np.nan], [0.0003 ** 2] * 3)
    rho_s = np.array([[0.02 + 0.01210, 0.02 + 0.01196, 0.05]], F32)
    std_s = np.full((1, 3), 0.004, F32)
    flags_s = np.full((1, 3), VALID, np.uint8)
    cfg = UpdateConfig(stereo_lead_k=3.0)
    x0 = rho_s[0, 0]
    restarted = stereo_restart(st, rho_s, std_s, flags_s, cfg)
    assert restarted.tolist() == [[True, False, False]]
    assert st.rho[0, 0] == x0 and st.var[0, 0] == pytest.approx(0.004 ** 2, rel=1e-6)
    assert (st.a[0, 0], st.b[0, 0], st.n[0, 0]) == (cfg.a_init, cfg.b_init, 1)
    assert np.isnan(rho_s[0, 0])                                     # not fused a second time
    assert st.rho[0, 1] == F32(0.02) and st.n[0, 1] == 12 and rho_s[0, 1] == F32(0.02 + 0.01196)   # untouched
    assert np.isnan(st.rho[0, 2]) and rho_s[0, 2] == F32(0.05)
    # a loose cell (sigma 0.01: sqrt(s^2 + tau^2) = 0.010770, 3 sigma 0.03231): 0.03 off is within
    st1 = _state([0.02], [0.01 ** 2], n=3)
    assert not stereo_restart(st1, np.array([[0.05]], F32), np.array([[0.004]], F32), np.array([[VALID]], np.uint8),
                              cfg).any()
    st2 = _state([0.02], [0.0003 ** 2])
    assert not stereo_restart(st2, np.array([[0.5]], F32), np.array([[0.004]], F32), np.array([[VALID]], np.uint8),
                              UpdateConfig(stereo_lead_k=0.0)).any()
    assert st2.rho[0, 0] == F32(0.02)



def test_a_motion_measurement_fused_earlier_restarts_cells_only_against_the_stereo_one_of_its_own_frame():
    """The partner's frame second: the reference's motion measurement was fused in its own push, kept, and the
    stereo measurement of the same frame restarts the cells where that motion measurement disagrees with it (rho
    0.05 +- 0.003 against 0.02 +- 0.004: 6 sigma). A kept motion measurement of an older frame (its stereo partner
    never came) says nothing of this frame's scene: the stereo measurement, agreeing with every cell, restarts none.
    Either way the kept one is used once."""
    from types import SimpleNamespace
    from eonav.fusion.schedule import NEAR, STEREO
    cfg = FusionConfig(schedule=ScheduleConfig(stereo_rig=("nose", PARTNER_ID)), update=UpdateConfig(stereo_lead_k=3.0))

    def meas(kind, seq, rho, std):
        m = SimpleNamespace(kind=kind, a=SimpleNamespace(camera_id="nose", seq=seq, stamp_us=1_000_000 + seq * 66_667))
        res = SimpleNamespace(inv_range_per_m=np.array([rho], F32), inv_range_std_per_m=np.full((1, 3), std, F32),
                              flags=np.full((1, 3), VALID, np.uint8))
        return m, res

    for stereo_seq, want in ((1, [True, False, False]), (2, [False, False, False])):
        runner = FusionRunner(cfg)
        runner.states["nose"] = st = _state([0.02, 0.02, 0.02], [0.0003 ** 2] * 3)
        assert runner._stereo_lead(*meas(NEAR, 1, [0.05, 0.021, 0.02], 0.003), None) == {}    # kept, not gated
        m, res = meas(STEREO, stereo_seq, [0.02, 0.02, 0.02], 0.004)
        out = runner._stereo_lead(m, res, None)
        assert out == {"stereo_restarted": sum(want)}, stereo_seq
        assert (st.n[0] == 1).tolist() == want and (np.isnan(res.inv_range_per_m[0])).tolist() == want
        assert (st.rho[0] == F32(0.02)).all()
        assert runner._stereo_lead(m, res, None) == {"stereo_restarted": 0}                    # used once


def test_a_skipped_stereo_pixel_seeing_beyond_k_sigma_past_a_cell_empties_it():
    # cells at 50 m, sigma 0.0003 (converged); skipped stereo pixels of sigma 0.002: sqrt(s^2 + tau^2) = 0.0020224,
    # k = 3 -> 0.0060673. ILL_CONDITIONED with a tight sigma (0.002 <= 0.34 x 0.0139, 0.0139 >= 2 x 0.002) is not
    # fused (``measured`` False): the pixel ranged 0.00610 farther empties its cell, 0.00600 farther keeps it.
    cfg = UpdateConfig(skipped_free_k=3.0)
    mu = 0.02
    rho_s = np.array([[mu - 0.00610, mu - 0.00600, mu - 0.01, mu + 0.02, mu - 0.01, mu - 0.01, mu - 0.01,
                       mu - 0.01, 0.005]], F32)
    std_s = np.full((1, 9), 0.002, F32)
    std_s[0, 6] = 0.004                                  # relative sigma 0.4 > 0.34: a weak pixel, fused
    flags_s = np.array([[ILL_CONDITIONED, ILL_CONDITIONED, TRUNCATION, ILL_CONDITIONED, ILL_CONDITIONED | OCCLUDED,
                         TRUNCATION | OUT_OF_VIEW, ILL_CONDITIONED, VALID, TRUNCATION]], np.uint8)
    st = _state([mu] * 8 + [np.nan], [0.0003 ** 2] * 9)
    rho_before = rho_s.copy()
    freed = stereo_skipped_free(st, rho_s, std_s, flags_s, cfg)
    # 0: 3.02 sigma farther, emptied; 1: 2.97 sigma, kept; 2: TRUNCATION 4.9 sigma farther, emptied; 3: nearer by
    # 10 sigma, kept (one-sided); 4, 5: OCCLUDED / OUT_OF_VIEW, the partner does not see the point; 6: weak (fused
    # by the update); 7: VALID (fused: the stereo restart's business); 8: an empty cell stays empty
    assert freed.tolist() == [[True, False, True, False, False, False, False, False, False]]
    assert np.isnan(st.rho[0, [0, 2]]).all() and (st.var[0, [0, 2]] == np.inf).all()
    assert (st.a[0, [0, 2]] == 0).all() and (st.n[0, [0, 2]] == 0).all()
    kept = [1, 3, 4, 5, 6, 7]
    assert (st.rho[0, kept] == F32(mu)).all() and (st.n[0, kept] == 12).all()
    assert np.isnan(st.rho[0, 8])
    np.testing.assert_array_equal(rho_s, rho_before)     # the measurement is not edited
    # k = 0 (the default): off
    st0 = _state([mu], [0.0003 ** 2])
    assert not stereo_skipped_free(st0, np.array([[0.005]], F32), np.array([[0.002]], F32),
                                   np.array([[TRUNCATION]], np.uint8), UpdateConfig()).any()
    assert st0.rho[0, 0] == F32(mu)
    with pytest.raises(InputError, match="skipped_free_k"):
        UpdateConfig(skipped_free_k=-1.0)
    with pytest.raises(InputError, match="shape"):
        stereo_skipped_free(st, rho_s[:, :4], std_s[:, :4], flags_s[:, :4], cfg)


# a van 90 m ahead of the approach flight (20 m/s) driving towards it at 8 m/s, 4 m left of its path, for 2 s (to
# 34 m): a motion pair sees it close at 28 m/s and ranges it too near (about 20 / 28 of its range where the motion
# is along the ray)
ONCOMING = Mover(Box.on_ground("van", 30.0, -4.0, 4.0, 2.0, 2.2, albedo=140.0, contrast=30.0), (-8.0, 0.0, 0.0))


@pytest.fixture(scope="module")
def oncoming_frames():
    sc = Scenario("oncoming", "approach", 2.0, clear=True, movers=(ONCOMING,), rig_baseline_m=0.8)
    return list(frames(sc, 15.0, (160, 120), seed=0, supersample=1))     # (the renders the figures below were measured on)


def van_pixels(fr, rig: bool, k: float = 3.0, partner_first: bool = True, gate_unmatched: bool = True):
    """Per fused map from 1.2 s on (the motion pairs' wrong ranges converged): the shares of the van's pixels ranged VALID within 10 % of the truth and
    VALID off by more."""
    cfg = FusionConfig(update=UpdateConfig(stereo_lead_k=k, gate_unmatched=gate_unmatched))
    if rig:
        cfg = replace(cfg, schedule=ScheduleConfig(stereo_rig=("nose", PARTNER_ID)))
    runner = FusionRunner(cfg)
    right, wrong = [], []
    for i, (stamp, view, truth, _, partner) in enumerate(fr):
        if rig and partner_first:                   # the partner's frame first: the reference's push has both
            runner.remember(frame(PARTNER_ID, partner, stamp, i))
        out = [m for m in runner.push(frame("nose", view, stamp, i)) if m.frame.seq == i]
        if rig and not partner_first:               # the partner's frame second: its push brings the stereo one
            out += [m for m in runner.push(frame(PARTNER_ID, partner, stamp, i)) if m.frame.camera_id == "nose"]
        if i < 18:
            continue
        res = out[-1].result
        px = truth.object_id == 2
        valid = (res.flags[px] & (VALID | FILLED)) == VALID
        ok = np.abs(res.range_m[px] / truth.range_m[px] - 1.0) <= 0.10
        right.append(float(np.mean(valid & ok)))
        wrong.append(float(np.mean(valid & ~ok)))
    return np.mean(right), np.mean(wrong)


def test_a_monocular_camera_ranges_an_oncoming_vehicle_wrong_and_a_stereo_rig_ranges_it(oncoming_frames, monkeypatch):
    right_mono, wrong_mono = van_pixels(oncoming_frames, rig=False)
    right_rig, wrong_rig = van_pixels(oncoming_frames, rig=True)
    right_avg, _ = van_pixels(oncoming_frames, rig=True, k=0.0)
    right_arrival, wrong_arrival = van_pixels(oncoming_frames, rig=True, partner_first=False)
    right_ungated, _ = van_pixels(oncoming_frames, rig=True, gate_unmatched=False)
    # measured (160 x 120, seed 0): mono 0.28 right / 0.69 wrong, the rig with stereo leading 0.96 / 0.04 (0.93 /
    # 0.05 with the motion pairs fused where the stereo pixel failed to match: gate_unmatched off), the rig's stereo
    # fused as one more measurement (k = 0) 0.92 right. The partner's frame second: the reference's measurements
    # wait for the stereo one of their instant and are fused with it in the partner's push, as if the partner's
    # frame had come first (before they waited: 0.91 / 0.06, the gates could not act). The mover's motion pairs
    # misfit, and with each window's own residual in the dense sigma they weigh little: averaging loses little to
    # stereo leading. With the image-wide sigma alone (window_noise=False) their sigma is over-confident and stereo
    # leading is what keeps the van: rig 0.89 right, k = 0 0.75.
    assert right_mono < 0.3 and wrong_mono > 0.4
    assert right_rig > 0.75 and wrong_rig < 0.15
    assert right_rig > right_ungated + 0.02
    assert abs(right_avg - right_rig) < 0.05
    assert (right_arrival, wrong_arrival) == (right_rig, wrong_rig)
    from eonav.ranging.methods.dense import locate_dense
    monkeypatch.setitem(locate_dense.__kwdefaults__, "window_noise", False)
    right_rig0, wrong_rig0 = van_pixels(oncoming_frames, rig=True)
    right_avg0, _ = van_pixels(oncoming_frames, rig=True, k=0.0)
    assert right_rig0 > 0.75 and wrong_rig0 < 0.15
    assert right_avg0 < right_rig0 - 0.1


def test_the_benchmark_sorts_a_movers_pixels_by_what_the_map_says_of_them():
    from eonav.app.bench_tracking import mover_pixels
    sc = Scenario("m", "approach", 1.0, clear=True, movers=(ONCOMING,))
    box = ONCOMING.box
    state = VehicleState.from_ypr([box.center_ned_m[0] - 50.0, 0.0, -6.0], [0, 0, 0], 0.0)
    oid = np.full((4, 5), 0, np.int32)
    oid[:, :4] = 2                                       # 16 pixels of the van, a column of ground
    truth = np.full((4, 5), 50.0, np.float32)
    rng = truth * np.tile(np.array([1.09, 0.91, 1.0, 1.11, 1.0], np.float32), (4, 1))     # column 3 11 % off
    flags = np.full((4, 5), VALID, np.uint8)
    flags[3, :2] = FILLED
    flags[2, 2:4] = OUT_OF_VIEW | OCCLUDED
    m = {"scene": Scene(boxes=(box,)),
         "state": state, "visible_px": {0: 16}, "object_id": oid, "flags": flags, "range_m": rng,
         "truth_range_m": truth}
    # VALID pixels of the van: rows 0-1 all, row 2 columns 0-1, row 3 columns 2-3; off by 11 %: column 3 of those
    assert mover_pixels(m, sc) == {"van": {"pixels": 16, "right": 9, "wrong": 3, "filled": 2, "occluded": 2}}
    assert mover_pixels(dict(m, visible_px={0: 11}), sc) == {}             # fewer than min_obstacle_pixels
    far = VehicleState.from_ypr([box.center_ned_m[0] - 130.0, 0.0, -6.0], [0, 0, 0], 0.0)
    assert mover_pixels(dict(m, state=far), sc) == {}                     # beyond max_obstacle_distance_m


def test_stereo_leads_does_not_edit_the_arrays_of_a_measurement_the_caller_holds(oncoming_frames):
    # a measurement that is not fresh (the caller keeps its results): the lead works on copies
    from eonav.fusion.sequence import dense_measurement
    held = []

    def measure(a, b, **kw):
        res = dense_measurement(a, b, **kw)
        held.append((res, res.inv_range_per_m.copy()))
        return res

    runner = FusionRunner(FusionConfig(schedule=ScheduleConfig(stereo_rig=("nose", PARTNER_ID))), measure=measure)
    restarted = 0
    for i, (stamp, view, _, _, partner) in enumerate(oncoming_frames[:20]):
        runner.remember(frame(PARTNER_ID, partner, stamp, i))
        for m in runner.push(frame("nose", view, stamp, i)):
            restarted += sum(x.get("stereo_restarted", 0) + x.get("gated", 0) for x in m.measurements)
    assert restarted > 0
    for res, rho in held:
        np.testing.assert_array_equal(res.inv_range_per_m, rho)


def test_skipped_free_space_needs_a_rig_and_empties_cells_with_one(oncoming_frames):
    # one camera: the maps with skipped_free_k = 3 are those without it, bit for bit; with the rig it empties cells
    def run(k, rig):
        cfg = FusionConfig(update=UpdateConfig(skipped_free_k=k))
        if rig:
            cfg = replace(cfg, schedule=ScheduleConfig(stereo_rig=("nose", PARTNER_ID)))
        runner = FusionRunner(cfg)
        maps, freed = [], 0
        for i, (stamp, view, _, _, partner) in enumerate(oncoming_frames[:12]):
            if rig:
                runner.remember(frame(PARTNER_ID, partner, stamp, i))
            for m in runner.push(frame("nose", view, stamp, i)):
                maps.append(m.result)
                freed += sum(x.get("skipped_free", 0) for x in m.measurements)
        return maps, freed

    mono_off, _ = run(0.0, False)
    mono_on, freed_mono = run(3.0, False)
    assert freed_mono == 0 and len(mono_on) == len(mono_off) > 0
    for a, b in zip(mono_off, mono_on):
        np.testing.assert_array_equal(a.inv_range_per_m, b.inv_range_per_m)
        np.testing.assert_array_equal(a.inv_range_std_per_m, b.inv_range_std_per_m)
        np.testing.assert_array_equal(a.flags, b.flags)
    _, freed_rig = run(3.0, True)
    assert freed_rig > 0


@pytest.mark.parametrize("partner_first", [True, False])
def test_a_rigs_frames_count_once_in_the_pushed_stream(oncoming_frames, partner_first):
    # through FusionRunner.push (FusionConfig.n_per_instant, default): with the rig every frame is measured twice
    # (motion and stereo) and no cell's n_fused passes the number of the reference camera's frames measured so far;
    # one camera is measured once a frame and never capped
    for rig in (True, False):
        cfg = FusionConfig(schedule=ScheduleConfig(stereo_rig=("nose", PARTNER_ID))) if rig else FusionConfig()
        runner = FusionRunner(cfg)
        most = []
        for i, (stamp, view, truth, _, partner) in enumerate(oncoming_frames[:12]):
            if rig and partner_first:
                runner.remember(frame(PARTNER_ID, partner, stamp, i))
            out = [m for m in runner.push(frame("nose", view, stamp, i)) if m.frame.camera_id == "nose"]
            if rig and not partner_first:
                out += [m for m in runner.push(frame(PARTNER_ID, partner, stamp, i)) if m.frame.camera_id == "nose"]
            most += [(i, int(m.n_fused.max())) for m in out]
        assert most and all(n <= i + 1 for i, n in most), most
        if rig:
            assert runner.counts.get("n_instant_capped", 0) > 0
            assert runner.counts.get("measurements.stereo", 0) >= 10
        else:
            assert "n_instant_capped" not in runner.counts


def _rig_pushes(fr, order, drop_partner=(), partner_seen=True, third=False, partner_dt_us=0, superseded=()):
    """Push a rig's frames (``order``: "partner-first" or "arrival"); the partner's frames of ``drop_partner`` never
    come, and with ``partner_seen`` False none does; ``third``: a camera outside the rig pushes a frame between the
    reference's and the partner's; ``partner_dt_us``: the partner's stamps that much after the reference's (its
    pose that of the reference's instant); ``superseded``: the partner's frames of these instants remembered, not
    pushed (the locator's "a newer frame of this camera is already waiting"). Returns (the runner, the reference's
    frame index of each map of the reference camera given, in order)."""
    runner = FusionRunner(FusionConfig(schedule=ScheduleConfig(stereo_rig=("nose", PARTNER_ID))))
    got = []
    for i, (stamp, view, _, _, partner) in enumerate(fr):
        pf = frame(PARTNER_ID, partner, stamp + partner_dt_us, i)
        send = partner_seen and i not in drop_partner
        if send and order == "partner-first":
            runner.remember(pf)
        got += [m.frame.seq for m in runner.push(frame("nose", view, stamp, i)) if m.frame.camera_id == "nose"]
        if third:
            got += [m.frame.seq for m in runner.push(frame("tail", view, stamp + 1, i)) if m.frame.camera_id == "nose"]
        if send and order == "arrival" and i in superseded:
            runner.remember(pf)
        elif send and order == "arrival":
            got += [m.frame.seq for m in runner.push(pf) if m.frame.camera_id == "nose"]
    return runner, got


def test_a_reference_frame_first_waits_for_its_stereo_partner_and_a_lost_partner_costs_one_map(oncoming_frames):
    fr = oncoming_frames[:12]
    # the reference's frame first: its first frame (no partner seen before it) gives its map at once; every later
    # one waits for the partner's frame of its instant, whose push gives it: one map a frame, in order (before the
    # waiting: two for each frame after the first, the motion one and the stereo one)
    runner, got = _rig_pushes(fr, "arrival")
    assert got == list(range(12)), got
    assert runner.counts.get("held_for_stereo") == runner.counts.get("held_joined") == 11
    # a camera outside the rig pushing in between does not take them: they wait for the partner's push
    runner, got = _rig_pushes(fr, "arrival", third=True)
    assert got == list(range(12)), got
    assert runner.counts.get("held_joined") == 11 and "held_fused_without_stereo" not in runner.counts
    # the partner's frame 6 is lost: frame 6's measurements are fused without it when frame 7 arrives, and frame 6
    # has no map; frame 7 does not wait (the partner's newest frame, 5, is older than the reference's previous one,
    # 6): its own push gives a map, and its partner's push another one with the stereo measurement, as before the
    # waiting; frame 8 waits again
    runner, got = _rig_pushes(fr, "arrival", drop_partner={6})
    assert got == [0, 1, 2, 3, 4, 5, 7, 7, 8, 9, 10, 11], got
    assert runner.counts.get("held_fused_without_stereo") == 1 and runner.counts.get("held_joined") == 9
    # a stream that ends on a reference frame whose partner's frame never comes (a pair file's last instant):
    # finish() fuses what waits and gives that frame's map; then nothing waits
    runner, got = _rig_pushes(fr, "arrival", drop_partner={11})
    assert got == list(range(11)), got
    last = runner.finish()
    assert [m.frame.seq for m in last] == [11] and last[0].measurements and runner.finish() == []
    # the partner's frames first: nothing waits
    runner, got = _rig_pushes(fr, "partner-first")
    assert got == list(range(12)) and "held_for_stereo" not in runner.counts
    # a partner camera never seen: nothing waits, every frame's map at its own push from the first motion pair on
    # (frame 0 has no partner, frame 1 too little parallax against it), as with one camera
    runner, got = _rig_pushes(fr, "arrival", partner_seen=False)
    assert got == list(range(2, 12)) and "held_for_stereo" not in runner.counts


def test_a_partner_stamped_just_before_the_reference_is_waited_for(oncoming_frames):
    """The partner's frame of an instant may be stamped up to ``max_stereo_dt_s`` (2 ms) before the reference's (the
    scheduler pairs them either way): it still delivered the reference's previous instant, so each reference frame
    after the first waits for it and its map comes once, with the stereo measurement leading; stamped 1 ms after,
    the same. Catches the partner's liveness taken against the reference's previous stamp exactly (a partner
    stamped 1 ms early was never waited for: two maps a frame, the motion one ungated)."""
    fr = oncoming_frames[:6]
    for dt_us in (-1000, 1000):
        runner, got = _rig_pushes(fr, "arrival", partner_dt_us=dt_us)
        assert got == list(range(6)), (dt_us, got)
        assert runner.counts.get("held_for_stereo") == runner.counts.get("held_joined") == 5, dt_us
        assert runner.counts.get("measurements.stereo") == 6, dt_us


def test_a_superseded_partner_frame_still_tells_that_the_partner_is_alive(oncoming_frames):
    """``remember`` (the locator's answer to a partner frame a newer one supersedes) records the partner as alive:
    with the partner's frame 3 remembered, not pushed, frame 3's measurements wait in vain and are fused without it
    when frame 4 arrives (frame 3: no map), and frame 4 still waits for the partner's frame 4, whose push gives its
    one map. Catches a planted ``remember`` that does not note the frame's stamp (frame 4 then not waited for: a map
    at its own push, its motion measurement ungated, and a second one with the stereo measurement)."""
    runner, got = _rig_pushes(oncoming_frames[:6], "arrival", superseded={3})
    assert got == [0, 1, 2, 4, 5], got
    assert runner.counts.get("held_for_stereo") == 5 and runner.counts.get("held_joined") == 4
    assert runner.counts.get("held_fused_without_stereo") == 1
