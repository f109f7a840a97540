"""``eonav bench locate``: accuracy and speed of every range method on the same pairs, printed as figures.

Cases: simulator presets (ground truth per pixel), Middlebury stereo pairs (ground-truth disparity),
KITTI motion and stereo pairs (no ground-truth depth: OpenCV StereoSGBM on the stereo pair stands in as
an approximate reference, and is labelled so). Every method runs on the same views in the same process;
the OpenCV DIS optical-flow baseline is one of them. Figures, not assertions.
"""
from __future__ import annotations

import argparse
import json
import statistics
import time
import tracemalloc
from dataclasses import dataclass, field

import numpy as np

FT = 0.3048


@dataclass
class Case:
    name: str
    view_a: object
    view_b: object
    truth_m: np.ndarray            # reference range on view a's grid (NaN unknown, inf sky)
    mask: np.ndarray               # pixels to score
    truth_label: str = "ground truth"
    object_id: np.ndarray | None = None
    objects: dict = field(default_factory=dict)
    stereo_rectified: bool = False
    scale_check: bool = False      # reference of another pair: also print the median range ratio to it
    measurable: np.ndarray | None = None   # scored pixels a two-view method can range at all (sim: in view of b)
    by_range: bool = False         # print the sigma's calibration per true-range bin (outdoor scenes)


def sim_cases(presets, size):
    from eonav.sim.presets import make_pair
    from eonav.sim.visibility import measurable_in_b
    out = []
    for name in presets:
        if name.startswith("flight:"):
            out.append(flight_case(name, size))
            continue
        sp = make_pair(name, seed=0, size=size if name != "paper" else None)
        t = sp.truth[0]
        out.append(Case(f"sim:{name}", sp.views[0], sp.views[1], t.range_m, np.isfinite(t.range_m),
                        object_id=t.object_id, objects=dict(sp.objects),
                        measurable=measurable_in_b(*sp.views, t.range_m, sp.truth[1].range_m), by_range=True))
    return out


def flight_case(name, size, k: int = 10, rate_hz: float = 30.0):
    """A pair of a simulated flight (``eonav.sim.sequence``, "flight:<name>"): frame k against frame k - 1 at
    rate_hz (seed 0), scored on frame k's truth."""
    from eonav.sim.sequence import render_sequence
    from eonav.sim.visibility import measurable_in_b
    seq = render_sequence(name, n_frames=k + 1, rate_hz=rate_hz, size=size, seed=0)
    t, tb = seq.truth[k], seq.truth[k - 1]
    return Case(f"sim:{name} frame {k} vs {k - 1} at {rate_hz:g} fps", seq.views[k], seq.views[k - 1], t.range_m,
                np.isfinite(t.range_m), object_id=t.object_id, objects=dict(seq.objects),
                measurable=measurable_in_b(seq.views[k], seq.views[k - 1], t.range_m, tb.range_m), by_range=True)


def middlebury_cases(data_dir):
    from eonav.io.datasets import MIDDLEBURY_SCENES, middlebury_pair
    out = []
    for scene in MIDDLEBURY_SCENES:
        a, b, truth, nonocc = middlebury_pair(data_dir, scene)
        out.append(Case(f"middlebury:{scene}", a, b, truth, nonocc, "GT disparity, non-occluded",
                        stereo_rectified=True, measurable=nonocc))
    return out


def kitti_cases(data_dir):
    from eonav.ranging.methods.flow_baseline import locate_sgbm
    from eonav.io.datasets import kitti_views
    views, right0 = kitti_views(data_dir)
    ref = locate_sgbm(views[0], right0).range_m
    mask = np.isfinite(ref) & (ref < 40)
    label = "StereoSGBM on the KITTI stereo pair (approximate, NOT ground truth)"
    return [Case("kitti:motion 0->1", views[0], views[1], ref, mask, label, scale_check=True),
            Case("kitti:motion 0->2", views[0], views[2], ref, mask, label, scale_check=True)]


def score(range_m, truth_m, mask, measurable=None):
    """Median relative error over the estimated scored pixels, share of the scored pixels within 5 %, coverage of
    the scored pixels and (given ``measurable``) of the measurable ones."""
    est = mask & np.isfinite(range_m) & (range_m > 0) & np.isfinite(truth_m)
    rel = np.abs(range_m[est] - truth_m[est]) / truth_m[est]
    n = int(mask.sum())
    out = {"median_rel_error": float(np.median(rel)) if rel.size else float("nan"),
           "within_5pct_of_scored": float((rel < 0.05).sum() / max(n, 1)),
           "coverage": float(est.sum() / max(n, 1))}
    if measurable is not None:
        out["coverage_of_measurable"] = float((est & measurable).sum() / max(int((mask & measurable).sum()), 1))
    return out


def robust_spread(z) -> float:
    """1.4826 x the median absolute deviation of z: its standard deviation where z is Gaussian, not moved by a few
    outliers (the calibration figure of every bench: 1 when the reported sigma is right)."""
    z = np.asarray(z)
    return float(1.4826 * np.median(np.abs(z - np.median(z))))


def calibration(res, truth_m, mask) -> dict:
    """Honesty of the reported sigma on the pixels of ``mask`` with a finite range and sigma (VALID and FILLED alike;
    ``filled_line`` passes the FILLED ones): z = (rho - 1/truth) / sigma_rho; its robust spread (1.4826 MAD, 1 when
    sigma is right) and the share with |z| < 2 (0.95 for a Gaussian)."""
    ok = mask & np.isfinite(res.range_m) & (res.range_m > 0) & np.isfinite(truth_m) & (truth_m > 0)
    std = res.inv_range_std_per_m[ok]
    good = np.isfinite(std) & (std > 0)
    if not good.any():
        return {}
    z = (res.inv_range_per_m[ok][good] - 1.0 / truth_m[ok][good]) / std[good]
    return {"z_spread": robust_spread(z),
            "within_2_sigma": float(np.mean(np.abs(z) < 2.0))}


RANGE_BINS_M = (0.0, 30.0, 60.0, 100.0, 150.0, np.inf)


def z_by_range(res, truth_m, mask, flag=None, bins=RANGE_BINS_M, min_pixels: int = 20) -> list:
    """The sigma's calibration per true-range bin: for each bin [lo, hi) of ``bins`` (m), the pixels of ``mask``
    with a finite truth in it, ``flag`` set (default VALID), a finite range and a finite sigma > 0: (lo, hi, pixels,
    robust spread 1.4826 MAD of z = (rho - 1/truth) / sigma, median z, share with |z| > 3). A sigma right at every
    range gives spreads near 1 and medians near 0 in every bin; a global calibration can average an over-reported
    near sigma and an under-reported far one into a spread of 1. Bins of fewer than ``min_pixels``: NaN figures."""
    from eonav.ranging.rangemap import VALID
    flag = VALID if flag is None else flag
    ok = (mask & np.isfinite(truth_m) & (truth_m > 0) & ((res.flags & flag) != 0) & np.isfinite(res.range_m)
          & (res.range_m > 0) & np.isfinite(res.inv_range_std_per_m) & (res.inv_range_std_per_m > 0))
    t = np.where(ok, truth_m, np.nan)
    z = np.where(ok, (res.inv_range_per_m - 1.0 / np.where(ok, truth_m, 1.0)) / np.where(ok, res.inv_range_std_per_m,
                                                                                             1.0), np.nan)
    out = []
    for lo, hi in zip(bins[:-1], bins[1:]):
        zb = z[ok & (t >= lo) & (t < hi)]
        if zb.size < min_pixels:
            out.append((lo, hi, int(zb.size), float("nan"), float("nan"), float("nan")))
            continue
        out.append((lo, hi, int(zb.size), robust_spread(zb), float(np.median(zb)), float(np.mean(np.abs(zb) > 3.0))))
    return out


def z_range_line(rows, label: str = "z by true range") -> str:
    """One line of ``z_by_range``: per bin its spread, median z and |z| > 3 share."""
    def head(lo, hi):
        return f">{lo:g}" if not np.isfinite(hi) else f"{lo:g}-{hi:g}"
    parts = [f"{head(lo, hi)} m: -" if not np.isfinite(sp) else
             f"{head(lo, hi)} m: {sp:.2f} (med {med:+.2f}, |z|>3 {100 * f3:.1f}%, {n} px)"
             for lo, hi, n, sp, med, f3 in rows]
    return f"   {label}: " + "; ".join(parts)


def filled_line(name, res, case) -> str:
    """What the FILLED pixels (inferred, not measured) add: their share of the scored pixels, their median error and
    sigma calibration, and the coverage / median error of the measured (VALID) pixels alone."""
    from eonav.ranging.rangemap import FILLED, VALID
    if res.flags is None or not (res.flags & FILLED).any():
        return ""
    ok = case.mask & np.isfinite(case.truth_m)
    filled = ok & ((res.flags & FILLED) != 0)
    measured = (res.flags & VALID) != 0
    sm = score(np.where(measured, res.range_m, np.nan), case.truth_m, case.mask)
    rel = np.abs(res.range_m[filled] - case.truth_m[filled]) / case.truth_m[filled]
    cal = calibration(res, case.truth_m, filled)
    return (f"   {'':<14}measured only: {100 * sm['median_rel_error']:.2f}% over {100 * sm['coverage']:.1f}%; "
            f"FILLED: {100 * filled.sum() / max(int(case.mask.sum()), 1):.1f}% of the scored pixels at "
            f"{100 * float(np.median(rel)) if rel.size else float('nan'):.2f}%, z spread "
            f"{cal.get('z_spread', float('nan')):.2f}, |z|<2 {fmt_pct(cal.get('within_2_sigma'))}")


def fmt_pct(x) -> str:
    return "-" if x is None else f"{100 * x:.1f}%"


def common_pixel_line(case, per, names=("dense", "dis")):
    """Median error of each of ``names`` on the pixels ALL of them estimate: a method that drops hard pixels
    gains nothing here."""
    if not all(n in per for n in names):
        return None
    common = case.mask & np.isfinite(case.truth_m)
    for n in names:
        r = per[n].range_m
        common &= np.isfinite(r) & (r > 0)
    if not common.any():
        return None
    t = case.truth_m[common]
    errs = [f"{n} {100 * np.median(np.abs(per[n].range_m[common] - t) / t):.2f} %" for n in names]
    return f"   same {int(common.sum())} pixels for {' and '.join(names)}: " + ", ".join(errs)


def scale_line(case, per):
    """Median ratio of each method's range to the reference (a scale disagreement between pose and images
    shows as a ratio far from 1 for every method alike)."""
    parts = []
    for n, res in per.items():
        ok = case.mask & np.isfinite(res.range_m) & (res.range_m > 0)
        if ok.any():
            parts.append(f"{n} x{np.median(res.range_m[ok] / case.truth_m[ok]):.3f}")
    return "   median range / reference: " + ", ".join(parts)


def time_methods(fns: dict, a, b, repeat):
    """Each method's result (its warm-up run), median CPU seconds per pair, median wall seconds and peak traced
    memory. Every method runs on one core (one OpenCV thread, numba not parallel), so the process's CPU time is
    its time on that core (wall time would also count what a virtual machine's host takes away; here the two
    agree). The timed runs are interleaved round-robin (dense, dis, dense, dis, ...): the machine's speed drifts
    by up to 1.5x over minutes, and one method's runs after the other's put that drift into their ratio. Even so
    the ratio of one build spread 0.40-0.59 over runs of this 2-core machine."""
    res = {name: fn(a, b) for name, fn in fns.items()}          # warm-up, and the result we score
    times = {name: [] for name in fns}
    walls = {name: [] for name in fns}
    for _ in range(repeat):
        for name, fn in fns.items():
            c0, t0 = time.process_time(), time.perf_counter()
            fn(a, b)
            times[name].append(time.process_time() - c0)
            walls[name].append(time.perf_counter() - t0)
    peak = {}
    for name, fn in fns.items():
        tracemalloc.start()
        fn(a, b)
        peak[name] = tracemalloc.get_traced_memory()[1]
        tracemalloc.stop()
    return {name: (res[name], statistics.median(times[name]), peak[name], statistics.median(walls[name]))
            for name in fns}


def object_rows(case, range_m):
    rows = []
    for oid, name in sorted(case.objects.items()):
        on = case.object_id == oid
        if not on.any() or oid < 2:
            continue
        actual = float(np.median(case.truth_m[on]))
        est = range_m[on & np.isfinite(range_m) & (range_m > 0)]
        e = float(np.median(est)) if est.size else float("nan")
        rows.append((name, actual, e, abs(e - actual) / actual, int(est.size)))
    return rows


def run_bench(methods, cases, repeat, json_out=None):
    from eonav.ranging.locate import get_method
    results = []
    for case in cases:
        w, h = case.view_a.camera.width, case.view_a.camera.height
        meas = "" if case.measurable is None else (
            f"; {100 * (case.mask & case.measurable).sum() / max(int(case.mask.sum()), 1):.1f} % of them measurable"
            " (in view of b, not occluded there)")
        print(f"\n== {case.name}  ({w}x{h}, reference: {case.truth_label}, {int(case.mask.sum())} scored pixels{meas})")
        print(f"   {'method':<14}{'median err':>11}{'within 5%':>11}{'coverage':>10}"
              f"{'of meas.':>10}{'CPU ms':>10}{'peak MB':>9}{'z spread':>10}{'|z|<2':>7}  (coverage: finite ranges, "
              "FILLED included)")
        per = {}
        names = list(methods) + (["sgbm"] if case.stereo_rectified and "sgbm" not in methods else [])
        timed = time_methods({name: get_method(name) for name in names}, case.view_a, case.view_b, repeat)
        for name in names:
            res, secs, peak, wall = timed[name]
            s = score(res.range_m, case.truth_m, case.mask, case.measurable)
            if not case.scale_check:          # a reference of another pair says nothing of this pair's sigma
                s.update(calibration(res, case.truth_m, case.mask))
            per[name] = res
            print(f"   {name:<14}{100 * s['median_rel_error']:>10.2f}%{100 * s['within_5pct_of_scored']:>10.1f}%"
                  f"{100 * s['coverage']:>9.1f}%{fmt_pct(s.get('coverage_of_measurable')):>10}"
                  f"{1000 * secs:>10.1f}{peak / 2**20:>9.1f}"
                  f"{s['z_spread'] if 'z_spread' in s else float('nan'):>10.2f}{fmt_pct(s.get('within_2_sigma')):>7}")
            results.append({"case": case.name, "method": name, "seconds_per_pair": secs, "wall_seconds_per_pair": wall,
                            "peak_bytes": peak, **s})
            filled = filled_line(name, res, case)
            if filled:
                print(filled)
            if not case.scale_check and case.by_range and res.flags is not None:
                zr = z_by_range(res, case.truth_m, case.mask)
                results[-1]["z_by_range"] = [list(r) for r in zr]
                print(z_range_line(zr, f"{'':<11}z by true range (VALID)"))
        line = common_pixel_line(case, per)
        if line:
            print(line)
        secs = {r["method"]: (r["seconds_per_pair"], r["wall_seconds_per_pair"]) for r in results
                if r["case"] == case.name}
        if "dense" in secs and "dis" in secs and secs["dis"][0] > 0:
            print(f"   time dense / dis: {secs['dense'][0] / secs['dis'][0]:.2f} (CPU on one core; wall clock "
                  f"{secs['dense'][1] / secs['dis'][1]:.2f})")
        if case.scale_check and per:
            print(scale_line(case, per))
        if case.objects and per:
            print("   Table I style (range in m / ft):")
            print(f"   {'object':<12}{'method':<8}{'actual':>16}{'estimated':>18}{'error':>8}{'points':>8}")
            for name, res in per.items():
                for obj, actual, est, err, pts in object_rows(case, res.range_m):
                    print(f"   {obj:<12}{name:<8}{actual:>7.1f} /{actual / FT:>7.1f}{est:>8.1f} /{est / FT:>8.1f}"
                          f"{100 * err:>7.1f}%{pts:>8d}")
    if json_out:
        with open(json_out, "w") as f:
            json.dump(results, f, indent=1)
    return results


def add_arguments(p):
    p.add_argument("--methods", default="dense,paper,dis", help="comma-separated methods (default dense,paper,dis)")
    p.add_argument("--presets", default="paper,fast,turning,climbing,stereo,flight:approach",
                   help="simulator presets (and flights as flight:<name>: frame 10 vs 9 at 30 fps)")
    p.add_argument("--size", type=int, default=512, help="image size for the simulator presets other than 'paper'")
    p.add_argument("--data", default=None, help="real data folder (default: shared/data beside the checkout)")
    p.add_argument("--no-real", action="store_true", help="skip Middlebury and KITTI")
    p.add_argument("--repeat", type=int, default=3, help="timed runs per method and pair (median)")
    p.add_argument("--cv-threads", type=int, default=1, metavar="N",
                   help="OpenCV threads, cv2.setNumThreads(N) (default 1: one core)")
    p.add_argument("--threads", dest="cv_threads", type=int, default=argparse.SUPPRESS, help=argparse.SUPPRESS)
    p.add_argument("--json", default=None, help="also write the figures as JSON")


def run(args) -> int:
    import cv2
    from pathlib import Path

    from eonav.io.datasets import default_data_dir
    cv2.setNumThreads(args.cv_threads)
    methods = [m for m in args.methods.split(",") if m]
    cases = sim_cases([p for p in args.presets.split(",") if p], args.size)
    data = Path(args.data) if args.data else default_data_dir()
    if not args.no_real:
        if data.is_dir():
            cases += middlebury_cases(data)
            cases += kitti_cases(data)
        else:
            print(f"(real data folder {data} not found: Middlebury and KITTI skipped)")
    print(f"eonav bench locate: methods {methods}, OpenCV threads {args.cv_threads}, median of {args.repeat} runs")
    run_bench(methods, cases, args.repeat, args.json)
    return 0
