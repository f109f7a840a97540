"""``eonav bench fuse``: fusion over the stream against single pairs, per sequence, printed as figures.

Per sequence the frames are pushed in time order through ``eonav.fusion.sequence.FusionRunner`` (the code of
``eonav fuse`` and the locator). At checkpoint frames k the fused map of frame k is scored against frame k's truth
beside single pairs of the same frame: the dense method and the OpenCV DIS flow baseline, each on the newest pair
(k, k-1) and on the widest pair (k, the earlier frame with the longest baseline within the pair policy's age and
rotation limits). Scored: median relative error and coverage of the pixels with truth (non-sky), the same for far
pixels (truth > 150 m), the fused sigma's calibration (robust z spread on VALID pixels and on FILLED ones; after 10 frames and on the last
frame also per true-range bin, fused and the dense newest pair, ``bench_locate.z_by_range``) and, per frame, the CPU time
of a push (measurement without its own fill + fusion) against a plain locate (dense with its fill) of the same pair:
what fusion adds to the locator's time (the median, and the sums: between full searches a measurement starts from
the prior and costs less, ``eonav.fusion.sequence.PriorConfig``). Targets of issue 11 are printed with "met" / "NOT met". Figures, not
assertions.

``--match-blur``: the dense method's resolution match (``locate_dense(match_blur=True)``, off by default) in the
fused measurements and the single pairs alike; ``--window-floor``: its window residual's floor likewise
(``locate_dense(window_floor=...)``; without it each takes its own default: "valid" for the fused measurements,
``eonav.fusion.sequence.dense_measurement``, "global" for the single pairs, the dense method's).
``--slant``: the dense method's slanted window (``locate_dense(slant=True)``, off by default) in the fused
measurements only: the single pairs, the ratio's denominator, stay the default dense method. ``--slant-px PX``: the
fused map's slant term (``MapConfig.slant_px``) for every sequence.
``--pair-checks``: the simulated sequences' measurements with the pair checks (``FusionConfig.pair_checks``, as the
real sequences have them); ``--attitude-noise-deg S``: each simulated frame's attitude as a navigation source with a
white error of S per body axis would give it (the images and the truth stay the true poses').

Sequences: the paper replica flown 1 s at 30 fps (31 frames, 512 x 512, last frame = the preset's reference with
the Table I vehicles), the "fast" preset and the approach flight at 30 fps; the real HoloLens indoor sequence (20
frames, depth-sensor reference); KITTI 00 frames 5 -> 0 pushed as a reversing camera so that the last frame is frame
0, where StereoSGBM gives the approximate reference (ratio only).
"""
from __future__ import annotations

import argparse
import json
import time
from dataclasses import dataclass, field, replace

import numpy as np

FAR_M = 150.0
FT = 0.3048


@dataclass
class SeqCase:
    name: str
    views: list
    truth: list                         # per frame: range_m on its grid (NaN unknown, inf sky) or None
    config: object
    objects: dict = field(default_factory=dict)
    object_ids: list | None = None
    table1: tuple = ()
    ratio_only: bool = False
    checkpoints: tuple = ()


def sim_case(name, n_frames, rate_hz, size, seed=0):
    from eonav.fusion.sequence import FusionConfig
    from eonav.sim.sequence import render_sequence
    seq = render_sequence(name, n_frames=n_frames, rate_hz=rate_hz, size=size, seed=seed)
    label = f"sim:{name} {n_frames} frames at {rate_hz:g} fps, seed {seed}"
    return SeqCase(label, seq.views, [r.range_m for r in seq.truth], FusionConfig(), dict(seq.objects),
                   [r.object_id for r in seq.truth], ("vehicle1", "vehicle2", "vehicle3") if name == "paper" else ())


def indoor_config(pair_checks: bool = True, max_pose_shift_px: float = 0.75):
    """The pair policy judged at an indoor reference range (3 m; the default 50 m sees no parallax indoors); the
    headset's tracked poses and auto-exposed images with the measurement's pair checks (``eonav.fusion.measure``)
    and no partner whose pose disagrees with its neighbours' images by more than ``max_pose_shift_px``."""
    from eonav.fusion.schedule import ScheduleConfig
    from eonav.fusion.sequence import FusionConfig
    from eonav.ranging.pair_policy import PairPolicyConfig
    return FusionConfig(schedule=ScheduleConfig(policy=PairPolicyConfig(ref_range_m=3.0),
                                                max_pose_shift_px=max_pose_shift_px), pair_checks=pair_checks)


def hololens_case(data):
    from eonav.io.datasets import hololens_sequence
    views, truth = hololens_sequence(data)
    return SeqCase("real:hololens_dvmvs_20f (depth-sensor reference)", views, truth, indoor_config(),
                   checkpoints=tuple(range(1, len(views))))         # every frame: 20 frames are few


def kitti_case(data):
    from eonav.geometry.camera import VehicleState
    from eonav.fusion.sequence import FusionConfig
    from eonav.ranging.methods.flow_baseline import locate_sgbm
    from eonav.io.datasets import kitti_views
    views, right0 = kitti_views(data)
    ref = locate_sgbm(views[0], right0).range_m
    ref = np.where(np.isfinite(ref) & (ref < 40), ref, np.nan).astype(np.float32)
    rev = []
    for v in reversed(views):            # reversing camera: frame 5 first, frame 0 (the SGBM reference) last
        st = v.state
        rev.append(replace(v, state=VehicleState(st.position_ned_m, st.T_body_ned, views[-1].state.t_s - st.t_s)))
    truth = [None] * (len(rev) - 1) + [ref]
    return SeqCase("real:kitti00 frames 5 -> 0 (StereoSGBM reference, approximate: ratio only)", rev, truth,
                   FusionConfig(), ratio_only=True, checkpoints=(len(rev) - 1,))


def errors(range_m, truth, mask):
    est = mask & np.isfinite(range_m) & (range_m > 0)
    rel = np.abs(range_m[est] - truth[est]) / truth[est]
    n = int(mask.sum())
    return (float(np.median(rel)) if rel.size else float("nan")), float(est.sum() / max(n, 1))


def uncovered_reasons(res, state, mask, eta_inlier: float, border_px: int = 8, truth=None,
                      horizon_px: int = 16) -> dict:
    """Why the pixels of ``mask`` (truth, not sky) have no fused range: counts of those whose cell holds an estimate
    the map does not report (``loose``: the evidence agrees but the sigma fails the rule; ``disagree``: the evidence
    disagrees), of the empty cells by the last measurement's verdict (``empty_occluded``, ``empty_truncation``,
    ``empty_other``), and of all of them within ``border_px`` of the image border (``border``). With ``truth``
    (range_m, +inf sky) also where they are: beyond ``FAR_M`` (``far``) and within ``horizon_px`` of a sky pixel
    (``horizon``: the terrain under the skyline, where one window spans a factor of 2 in range; docs/methods.md,
    "Coverage after 10 frames")."""
    from eonav.ranging.rangemap import OCCLUDED, TRUNCATION
    unc = mask & ~(np.isfinite(res.range_m) & (res.range_m > 0))
    occ = state.occupied()
    with np.errstate(invalid="ignore", divide="ignore"):
        agree = occ & (state.a >= np.float32(eta_inlier) * (state.a + state.b))
    empty = unc & ~occ
    occl = empty & ((state.flags & OCCLUDED) != 0)
    trunc = empty & ~occl & ((state.flags & TRUNCATION) != 0)
    h, w = mask.shape
    yy, xx = np.mgrid[:h, :w]
    edge = np.minimum(np.minimum(xx, w - 1 - xx), np.minimum(yy, h - 1 - yy)) < border_px
    out = {"uncovered": int(unc.sum()), "loose": int((unc & agree).sum()), "disagree": int((unc & occ & ~agree).sum()),
           "empty_occluded": int(occl.sum()), "empty_truncation": int(trunc.sum()),
           "empty_other": int((empty & ~occl & ~trunc).sum()), "border": int((unc & edge).sum())}
    if truth is not None:
        from scipy import ndimage
        sky = np.isposinf(truth)
        near_sky = (ndimage.distance_transform_edt(~sky) <= horizon_px) if sky.any() else np.zeros_like(sky)
        with np.errstate(invalid="ignore"):
            out["far"] = int((unc & (truth >= FAR_M)).sum())
        out["horizon"] = int((unc & near_sky).sum())
    return out


def held_single_line(state, truth, mask, mcfg):
    """The map without the held-single rule (``MapConfig.held_single`` off; the state is the same, only the map
    differs): its (error, coverage, z), and what the held cells with truth were (how many, how many it reported
    VALID, their median error there, the last measurement's flags). None when the rule is off or holds nothing."""
    from eonav.fusion.fused_map import fused_map, held_single
    from eonav.ranging.rangemap import FLAG_NAMES, VALID
    if not mcfg.held_single:
        return None
    off = fused_map(state, replace(mcfg, held_single=False))
    held = held_single(state) & mask
    was = held & ((off.flags & VALID) != 0) & np.isfinite(off.range_m)
    e_was, _ = errors(off.range_m, truth, was)
    names = {}
    for bit, name in FLAG_NAMES.items():
        c = int(np.count_nonzero(held & ((state.flags & bit) != 0)))
        if c:
            names[name] = c
    fig = {"fused": errors(off.range_m, truth, mask), "z": z_spread(off, truth, mask), "held": int(held.sum()),
           "held_valid": int(was.sum()), "held_valid_error": e_was, "held_last_flags": names}
    line = (f"         without held_single: {fmt(*fig['fused']).strip()}, z {fig['z']:.2f}; held cells with truth "
            f"{fig['held']} ({100 * fig['held'] / max(int(mask.sum()), 1):.2f} %), VALID without the rule "
            f"{fig['held_valid']} at {100 * e_was:.1f} % median error; last flags {names}")
    return fig, line


def by_range(res, truth, mask, bins=(0.0, 30.0, 60.0, 100.0, 150.0, 300.0, np.inf)) -> list:
    """Per true-range bin [lo, hi) (m): (lo, hi, pixels of ``mask``, median relative error, coverage) of ``res``."""
    out = []
    for lo, hi in zip(bins[:-1], bins[1:]):
        sel = mask & (truth >= lo) & (truth < hi)
        e, c = errors(res.range_m, truth, sel)
        out.append((lo, hi, int(sel.sum()), e, c))
    return out


def z_spread(res, truth, mask, flag=None) -> float:
    """Robust spread (1.4826 MAD) of the z-scores (rho - 1/truth) / sigma of the pixels with truth, a finite range
    and ``flag`` (default VALID); NaN under 10 such pixels."""
    from eonav.ranging.rangemap import VALID
    flag = VALID if flag is None else flag
    ok = mask & ((res.flags & flag) != 0) & np.isfinite(res.range_m) & (res.range_m > 0)
    std = res.inv_range_std_per_m[ok]
    good = np.isfinite(std) & (std > 0)
    if good.sum() < 10:
        return float("nan")
    from eonav.app.bench_locate import robust_spread
    return robust_spread((res.inv_range_per_m[ok][good] - 1.0 / truth[ok][good]) / std[good])


def widest_partner(views, k, cfg):
    """Index of the earlier frame with the longest baseline to frame k within the policy's age and rotation."""
    from eonav.geometry.camera import pair_geometry
    pc = cfg.schedule.policy
    best, best_b = None, -1.0
    for j in range(k):
        if views[k].state.t_s - views[j].state.t_s > pc.max_age_s:
            continue
        g = pair_geometry(views[k], views[j])
        rot = np.degrees(np.arccos(np.clip((np.trace(g.R_ba) - 1) / 2, -1, 1)))
        if rot <= pc.max_rotation_deg and g.baseline_m > best_b:
            best, best_b = j, g.baseline_m
    return best


def no_output_reason(view_a, view_b, truth, res) -> str:
    """Why a single pair gave no range on the pixels with truth: the pair's true motion (from the reference) against
    what the method's matches say (DIS: the robust spread of its matches' distance from the epipolar lines)."""
    from eonav.geometry.camera import pair_geometry
    geo = pair_geometry(view_a, view_b)
    rot = np.degrees(np.arccos(np.clip((np.trace(geo.R_ba) - 1) / 2, -1, 1)))
    ok = np.isfinite(truth) & (truth > 0)
    ub, vb, den = geo.map_to_b(np.where(ok, 1.0 / np.where(ok, truth, 1.0), 0.0))
    u, v = view_a.camera.pixel_grid()
    disp = np.hypot(ub - u, vb - v)[ok & (den > 0)]
    inside = ok & (den > 0) & (ub >= 0) & (ub <= view_b.camera.width - 1) & (vb >= 0) & (vb <= view_b.camera.height - 1)
    parts = [f"baseline {geo.baseline_m:.3f} m, rotation {rot:.1f} deg; true motion median {np.median(disp):.0f} px "
             f"(90 % {np.percentile(disp, 90):.0f} px), {100 * inside.sum() / max(ok.sum(), 1):.0f} % of the pixels "
             f"with truth still in view b"]
    if "flow_sigma_px" in res.info:
        parts.append(f"the flow's matches lie a robust {res.info['flow_sigma_px']:.0f} px off their epipolar lines "
                     f"(a tracked flow: under 3 px), so no pixel's sigma passes: the flow lost the motion")
    return "; ".join(parts)


def fmt(e, c):
    return f"{100 * e:6.2f}% {100 * c:5.1f}%" if np.isfinite(e) else "     -       -  "


def run_case(case: SeqCase, out: list, dense_params: dict | None = None, fused_params: dict | None = None) -> dict:
    """One sequence (module docstring); ``dense_params``: options of the dense method (``locate_dense``) for the
    fused measurements and the single pairs alike (e.g. match_blur=True); ``fused_params``: more options for the
    fused measurements only (e.g. slant=True)."""
    from functools import partial

    from eonav.app.bench_locate import z_by_range, z_range_line
    from eonav.fusion.sequence import FusionRunner, dense_measurement, frame
    from eonav.ranging.locate import get_method
    from eonav.ranging.rangemap import FILLED, VALID
    dense, dis = get_method("dense"), get_method("dis")
    if dense_params:
        dense = partial(dense, **dense_params)
    if dense_params or fused_params:
        mparams = dict(dense_params or {}, **(fused_params or {}))

        def measure(a, b, **kw):          # the runner's default measurement with the options (and the pair checks)
            return dense_measurement(a, b, pair_checks=case.config.pair_checks, **mparams, **kw)
        runner = FusionRunner(case.config, measure=measure, fresh_measurements=True, takes_prior=True)
    else:
        runner = FusionRunner(case.config)
    n = len(case.views)
    checks = set(case.checkpoints or (k for k in (1, 2, 3, 5, 10, 15, 20, 30) if k < n)) | {n - 1}
    w, h = case.views[0].camera.width, case.views[0].camera.height
    print(f"\n== {case.name}  ({w}x{h}, {n} frames)")
    print(f"   {'k':>3} {'fused':>15} {'fused VALID':>15} {'dense newest':>15} {'dense widest':>15} "
          f"{'DIS newest':>15} {'DIS widest':>15} {'z fused':>8} {'z filled':>8}   (median error, coverage of the pixels "
          f"with truth; z spread of the VALID and of the FILLED pixels)")
    t_push, t_plain, summary, far_rows, last = [], [], {}, [], None
    for k, v in enumerate(case.views):
        f = frame(v.camera.name, v, int(round(v.state.t_s * 1e6)), seq=k)
        c0 = time.process_time()
        maps = [m for m in runner.push(f) if m.frame.seq == k]
        c1 = time.process_time()
        if not maps:
            continue
        m = maps[0]
        last = m
        if m.measurements:
            other = m.measurements[0]["other_seq"]
            t_push.append(c1 - c0)
            c2 = time.process_time()
            plain = dense(v, case.views[other])
            t_plain.append(time.process_time() - c2)
            del plain
        truth = case.truth[k]
        if k not in checks or truth is None:
            continue
        mask = np.isfinite(truth) & (truth > 0)
        res = m.result
        jw = widest_partner(case.views, k, case.config)
        singles = {"dense newest": dense(v, case.views[k - 1]), "dense widest": dense(v, case.views[jw]),
                   "DIS newest": dis(v, case.views[k - 1]), "DIS widest": dis(v, case.views[jw])}
        if case.ratio_only:
            parts = []
            for name, r in [("fused", res)] + list(singles.items()):
                ok = mask & np.isfinite(r.range_m) & (r.range_m > 0)
                parts.append(f"{name} x{np.median(r.range_m[ok] / truth[ok]):.3f} ({100 * ok.sum() / mask.sum():.0f} %)"
                             if ok.any() else f"{name} -")
            print(f"   {k:>3} median range / reference (coverage): " + ", ".join(parts))
            continue
        row = {"frame": k, "fused": errors(res.range_m, truth, mask),
               "fused_valid": errors(np.where((res.flags & VALID) != 0, res.range_m, np.nan), truth, mask),
               "z": z_spread(res, truth, mask), "z_filled": z_spread(res, truth, mask, FILLED)}
        row.update({name: errors(r.range_m, truth, mask) for name, r in singles.items()})
        far = mask & (truth > FAR_M)
        if far.sum() >= 20:
            far_rows.append((k, errors(res.range_m, truth, far), errors(singles["dense newest"].range_m, truth, far),
                             errors(singles["dense widest"].range_m, truth, far), int(far.sum())))
        summary[k] = row
        print(f"   {k:>3} {fmt(*row['fused'])} {fmt(*row['fused_valid'])} {fmt(*row['dense newest'])} "
              f"{fmt(*row['dense widest'])} {fmt(*row['DIS newest'])} {fmt(*row['DIS widest'])} {row['z']:>8.2f} {row['z_filled']:>8.2f}")
        held = held_single_line(runner.states[v.camera.name], truth, mask, case.config.output)
        if held is not None:
            row["held_single_off"], line = held
            print(line)
        if k == 10 or k == n - 1:
            zf, zd = z_by_range(res, truth, mask), z_by_range(singles["dense newest"], truth, mask)
            row["z_by_range"], row["z_by_range_dense_newest"] = [list(r) for r in zf], [list(r) for r in zd]
            print(z_range_line(zf, "      fused z by true range (VALID)"))
            print(z_range_line(zd, "      dense newest z by true range (VALID)"))
            rf, rd = by_range(res, truth, mask), by_range(singles["dense newest"], truth, mask)
            print("      error, coverage by true range: fused | dense newest: " + "; ".join(
                f"{lo:g}-{hi:g} m ({npx} px) {fmt(e, c).strip()} | {fmt(*d[3:]).strip()}"
                for (lo, hi, npx, e, c), d in zip(rf, rd)))
            why = uncovered_reasons(res, runner.states[v.camera.name], mask, case.config.output.eta_inlier,
                                     truth=truth)
            row["uncovered"] = why
            print("      pixels with truth and no fused range: " + ", ".join(f"{k2} {v2}" for k2, v2 in why.items()))
        for name, r in singles.items():
            if not np.isfinite(row[name][0]):
                j = k - 1 if "newest" in name else jw
                row[name + " reason"] = why = no_output_reason(v, case.views[j], truth, r)
                print(f"         {name} ({k} vs {j}) gives no output: {why}")
        out.append({"case": case.name, **{kk: (list(vv) if isinstance(vv, tuple) else vv) for kk, vv in row.items()}})
    if far_rows:
        print(f"   far pixels (truth > {FAR_M:g} m): k, fused, dense newest, dense widest, pixels")
        for k, fu, dn, dw, npx in far_rows:
            print(f"   {k:>3} {fmt(*fu)} {fmt(*dn)} {fmt(*dw)} {npx:>8d}")
    if t_push:
        tp, tl = float(np.median(t_push)), float(np.median(t_plain))
        print(f"   time per frame (CPU, median of {len(t_push)}): push {1e3 * tp:.1f} ms (measurement without its fill "
              f"+ fusion) vs plain dense locate of the same pair {1e3 * tl:.1f} ms: fusion adds {100 * (tp / tl - 1):+.0f} % "
              f"(sum over the frames {100 * (sum(t_push) / sum(t_plain) - 1):+.0f} %); measurements started from the "
              f"prior {runner.counts.get('prior_seeded', 0)}, full searches {runner.counts.get('full_search', 0)}")
        summary["time_added"] = tp / tl - 1
    if case.table1 and last is not None:
        truth, oid = case.truth[last.frame.seq], case.object_ids[last.frame.seq]
        print(f"   Table I vehicles on the last frame ({last.frame.seq}): object, actual m / ft, fused m / ft, error")
        errs = []
        for name in case.table1:
            ids = [i for i, nm in case.objects.items() if nm == name]
            on = oid == ids[0]
            act = float(np.median(truth[on]))
            est = last.result.range_m[on & np.isfinite(last.result.range_m)]
            e = float(np.median(est)) if est.size else float("nan")
            errs.append(abs(e - act) / act)
            print(f"   {name:<10} {act:7.1f} / {act / FT:6.1f} {e:7.1f} / {e / FT:6.1f} {100 * (e - act) / act:+6.1f}% "
                  f"({est.size}/{int(on.sum())} px)")
        summary["table1_max_error"] = float(np.max(errs))      # NaN (NOT met) if one has no range
    return summary


def print_targets(summaries: dict) -> None:
    def verdict(ok):
        return "met" if ok else "NOT met"
    print("\n== targets (issue 11)")
    for name, s in summaries.items():
        if "table1_max_error" in s:
            v = s["table1_max_error"]
            print(f"   {name}: every Table I vehicle within 3 % on the last frame: worst {100 * v:.1f} % -> {verdict(v <= 0.03)}")
        if 10 in s:
            r = s[10]
            ratio = r["fused"][0] / r["dense newest"][0]
            print(f"   {name}: after 10 frames median error {100 * r['fused'][0]:.2f} % = {ratio:.2f} x single-pair dense "
                  f"{100 * r['dense newest'][0]:.2f} % (<= 0.5) -> {verdict(ratio <= 0.5)}; coverage "
                  f"{100 * r['fused'][1]:.1f} % (>= 95 %) -> {verdict(r['fused'][1] >= 0.95)}; z spread {r['z']:.2f} "
                  f"(0.8-1.2) -> {verdict(0.8 <= r['z'] <= 1.2)}; FILLED z spread {r['z_filled']:.2f} -> "
                  f"{verdict(0.8 <= r['z_filled'] <= 1.2)}")
        if name.startswith("real:") and s:
            ks = [k for k in s if isinstance(k, int)]
            if ks:
                r = s[max(ks)]
                dw = r["DIS widest"]
                vs_dw = (f"{100 * dw[0]:.2f} % -> {verdict(r['fused'][0] < dw[0])}" if np.isfinite(dw[0]) else
                         f"no output (above) -> {verdict(r['fused'][1] > 0)}")
                print(f"   {name}: last frame fused {100 * r['fused'][0]:.2f} % over {100 * r['fused'][1]:.1f} % vs DIS "
                      f"widest {vs_dw}; vs DIS newest {100 * r['DIS newest'][0]:.2f} % over {100 * r['DIS newest'][1]:.1f} % "
                      f"-> {verdict(r['fused'][0] < r['DIS newest'][0])}; vs dense newest {100 * r['dense newest'][0]:.2f} % / "
                      f"widest {100 * r['dense widest'][0]:.2f} % -> "
                      f"{verdict(r['fused'][0] < min(r['dense newest'][0], r['dense widest'][0]))}")
        if "time_added" in s:
            print(f"   {name}: fusion adds {100 * s['time_added']:+.0f} % to the locator's time per frame (<= 30 %) -> "
                  f"{verdict(s['time_added'] <= 0.30)}")


def with_attitude_noise(views, sigma_deg: float, seed: int) -> list:
    """The views with each frame's attitude turned by a rotation of ``sigma_deg`` 1-sigma per body axis (white,
    ``numpy.random.default_rng((seed, 7))``): what a navigation source's attitude error does to the poses the
    ranging is given; the images and the truth stay those of the true poses."""
    import cv2

    from eonav.geometry.camera import VehicleState
    rng = np.random.default_rng((seed, 7))
    out = []
    for v in views:
        turn = cv2.Rodrigues(np.radians(sigma_deg) * rng.standard_normal((3, 1)))[0]
        st = v.state
        out.append(replace(v, state=VehicleState(st.position_ned_m, turn @ st.T_body_ned, st.t_s)))
    return out


def add_arguments(p):
    p.add_argument("--sequences", default="paper,fast,flight:approach",
                   help="simulated sequences (eonav.sim.sequence: presets or flight:<name>)")
    p.add_argument("--size", type=int, default=320, help="image size of the simulated sequences other than 'paper'")
    p.add_argument("--frames", type=int, default=16, help="frames of the simulated sequences other than 'paper' (31)")
    p.add_argument("--seed", type=int, default=0, help="sensor-noise seed of the simulated sequences")
    p.add_argument("--data", default=None, help="real data folder (default: shared/data beside the checkout)")
    p.add_argument("--no-real", action="store_true", help="skip the HoloLens and KITTI sequences")
    p.add_argument("--match-blur", action="store_true",
                   help="the dense method's resolution match (locate_dense(match_blur=True); off by default)")
    p.add_argument("--window-floor", default=None, choices=("global", "valid", "sensor", "mid"),
                   help="the dense method's floor of the window residual (locate_dense(window_floor=...)) in the fused "
                        "measurements and the single pairs alike (default: their own, 'valid' and 'global')")
    p.add_argument("--slant", action="store_true",
                   help="the dense method's slanted window (locate_dense(slant=True)) in the fused measurements only "
                        "(the single pairs stay the default dense method)")
    p.add_argument("--slant-px", type=float, default=None, metavar="PX",
                   help="the fused map's slant term (MapConfig.slant_px; default its own)")
    p.add_argument("--pair-checks", action="store_true",
                   help="simulated sequences: the measurement's pair checks (brightness match and pose term, "
                        "FusionConfig.pair_checks; the real sequences have them on)")
    p.add_argument("--attitude-noise-deg", type=float, default=0.0,
                   help="simulated sequences: each frame's navigation attitude off by a rotation of this 1-sigma "
                        "per body axis (white, seeded by --seed), as an attitude source's error")
    p.add_argument("--cv-threads", type=int, default=1, metavar="N",
                   help="OpenCV threads, cv2.setNumThreads(N) (default 1: one core)")
    p.add_argument("--threads", dest="cv_threads", type=int, default=argparse.SUPPRESS, help=argparse.SUPPRESS)
    p.add_argument("--json", default=None, help="also write the figures as JSON")


def run(args) -> int:
    from pathlib import Path

    import cv2

    from eonav.fusion.sequence import prepare_kernels      # the dense method's kernels and the fusion's passes
    from eonav.io.datasets import default_data_dir
    cv2.setNumThreads(args.cv_threads)
    prepare_kernels()
    cases = []
    for name in [s for s in args.sequences.split(",") if s]:
        if name == "paper":
            cases.append(lambda: sim_case("paper", 31, 30.0, None, args.seed))
        else:
            cases.append(lambda name=name: sim_case(name, args.frames, 30.0, args.size, args.seed))
    data = Path(args.data) if args.data else default_data_dir()
    if not args.no_real:
        if (data / "hololens_dvmvs_20f").is_dir():
            cases.append(lambda: hololens_case(data))
        else:
            print(f"(real data {data / 'hololens_dvmvs_20f'} not found: skipped)")
        if (data / "kitti00_frames0-5").is_dir():
            cases.append(lambda: kitti_case(data))
    print(f"eonav bench fuse: OpenCV threads {args.cv_threads}; times are CPU time of this process")
    rows, summaries = [], {}
    for make in cases:
        case = make()
        if args.attitude_noise_deg > 0 and case.name.startswith("sim:"):
            case.views = with_attitude_noise(case.views, args.attitude_noise_deg, args.seed)
            case.name += f", attitude noise {args.attitude_noise_deg:g} deg"
        if args.pair_checks and case.name.startswith("sim:"):
            case.config = replace(case.config, pair_checks=True)
            case.name += ", pair checks"
        params = dict({"match_blur": True} if args.match_blur else {},
                      **({"window_floor": args.window_floor} if args.window_floor else {}))
        if args.slant_px is not None:
            case.config = replace(case.config, output=replace(case.config.output, slant_px=args.slant_px))
            case.name += f", slant_px {args.slant_px:g}"
        if args.slant:
            case.name += ", fused slanted window"
        summaries[case.name] = run_case(case, rows, params or None, {"slant": True} if args.slant else None)
    print_targets(summaries)
    if args.json:
        with open(args.json, "w") as f:
            json.dump(rows, f, indent=1)
    return 0
