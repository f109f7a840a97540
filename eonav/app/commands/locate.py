"""``eonav locate PAIR.json --out RANGE.npz``: a range map from a pair file (the contract: docs/pair-file.md)."""
from __future__ import annotations

import argparse


def add_arguments(p: argparse.ArgumentParser) -> None:
    from eonav.ranging.locate import DEFAULT_METHOD, METHODS
    p.add_argument("pair", help="pair file (JSON, docs/pair-file.md); frame 0 is the reference")
    p.add_argument("--out", required=True, help="output .npz: range_m (H x W float32, NaN = no estimate), confidence, ...")
    p.add_argument("--method", default=DEFAULT_METHOD, choices=sorted(METHODS),
                   help="; ".join(f"{k}: {v[2]}" for k, v in METHODS.items()))
    p.add_argument("--other", type=int, default=1, help="index of the second frame in the pair file (default 1)")
    p.add_argument("--png", help="also write a colour-mapped range picture beside frame 1")
    p.add_argument("--truth", help="ground-truth .npz with range_m (e.g. from 'eonav sim'): print an accuracy summary")
    p.add_argument("--timing", action="store_true", help="time the estimator; last stdout line is JSON")
    p.add_argument("--repeat", type=int, default=5, help="runs for --timing (median after one warm-up)")
    p.add_argument("--cv-threads", type=int, default=-1, metavar="N",
                   help="cv2.setNumThreads(N); -1 (default) keeps OpenCV's default, 0 disables its threading")
    p.add_argument("--threads", dest="cv_threads", type=int, action=_OldThreads, default=argparse.SUPPRESS,
                   help=argparse.SUPPRESS)
    p.add_argument("--measured-only", action="store_true",
                   help="dense: no FILLED pixels (ranges the pair could not measure, inferred from their neighbours); "
                        "range_m is then finite on VALID pixels only")


class _OldThreads(argparse.Action):
    """``--threads N``, the old spelling of ``--cv-threads``, where 0 meant OpenCV's default (now -1)."""

    def __call__(self, parser, namespace, values, option_string=None):
        setattr(namespace, self.dest, -1 if values == 0 else values)


def accuracy_summary(range_m, truth_m, confidence=None) -> dict:
    """Median relative error and coverage against a ground-truth range map (finite, non-sky truth only); sky is
    +inf truth, NaN truth is unknown (neither scene nor sky)."""
    import numpy as np
    t = np.asarray(truth_m, np.float64)
    r = np.asarray(range_m, np.float64)
    scene = np.isfinite(t) & (t > 0)
    est = scene & np.isfinite(r) & (r > 0)
    rel = np.abs(r[est] - t[est]) / t[est]
    sky = np.isposinf(t)
    out = {"scene_pixels": int(scene.sum()), "coverage": float(est.sum() / max(scene.sum(), 1)),
           "median_rel_error": float(np.median(rel)) if rel.size else float("nan"),
           "within_5pct": float((rel < 0.05).mean()) if rel.size else float("nan"),
           "p90_rel_error": float(np.percentile(rel, 90)) if rel.size else float("nan")}
    if sky.any():
        out["sky_reported_finite"] = float((np.isfinite(r[sky])).mean())
    return out


def check_png_output(path) -> None:
    """--png: a writable path whose extension OpenCV can write (.png, .jpg, ...)."""
    import cv2

    from eonav import InputError
    from eonav.io.files import check_output
    check_output(path, "--png")
    if not cv2.haveImageWriter(str(path)):
        raise InputError(f"--png {path}: no image writer for this file name (expected e.g. range.png)")


def load_npz_array(path, name: str, what: str):
    """Array ``name`` of an .npz file (a regular file, no pickles), with errors that name the file."""
    import io
    import zipfile

    import numpy as np

    from eonav import InputError
    from eonav.io.files import read_regular_file
    data = read_regular_file(path, what, 1 << 30)
    if data[:4] != b"PK\x03\x04":
        raise InputError(f"{what} {path}: not an .npz file (expected the .npz of 'eonav sim' holding {name!r})")
    try:
        t = np.load(io.BytesIO(data), allow_pickle=False)
    except (ValueError, OSError, EOFError, zipfile.BadZipFile) as e:
        raise InputError(f"{what} {path}: not a readable .npz ({e})") from None
    if not isinstance(t, np.lib.npyio.NpzFile):
        raise InputError(f"{what} {path}: a single array, expected an .npz holding {name!r}")
    with t:
        if name not in t.files:
            raise InputError(f"{what} {path}: no {name!r} array (it has {t.files})")
        try:
            return t[name]
        except (ValueError, OSError, EOFError, zipfile.BadZipFile) as e:
            raise InputError(f"{what} {path}: cannot read {name!r} ({e})") from None


def run(args) -> int:
    import json
    import statistics
    import time

    import numpy as np

    from eonav import InputError
    from eonav.io.files import check_output, write_npz
    from eonav.io.pairfile import load_pair_file
    from eonav.ranging.locate import get_method

    if args.cv_threads >= 0:
        import cv2
        cv2.setNumThreads(args.cv_threads)
    check_output(args.out, "--out")                     # before any work: a path that cannot be written fails now
    if args.png:
        check_png_output(args.png)
    truth = load_npz_array(args.truth, "range_m", "--truth") if args.truth else None
    pf = load_pair_file(args.pair)
    if not 1 <= args.other < len(pf.frames):
        raise InputError(f"--other {args.other}: the pair file has frames 0..{len(pf.frames) - 1}")
    a, b = pf.views(indices=(0, args.other))
    if truth is not None and truth.shape != a.image.shape[:2]:       # before any work: no --out left by an error
        raise InputError(f"--truth {args.truth}: shape {truth.shape} differs from the range map {a.image.shape[:2]}")
    fn = get_method(args.method)
    if args.measured_only:
        if args.method != "dense":
            raise InputError(f"--measured-only: method {args.method!r} fills nothing (only dense does)")
        import functools
        fn = functools.partial(fn, fill=False)
    res = fn(a, b)
    out = write_npz(args.out, res.arrays(), "--out")
    r = res.range_m
    n = r.size
    print(f"{args.method}: {int(np.isfinite(r).sum())}/{n} pixels with a finite range "
          f"({100.0 * np.isfinite(r).sum() / n:.1f} %), {int(np.isposinf(r).sum())} at infinity -> {out}")
    if truth is not None:
        s = accuracy_summary(r, truth, res.confidence)
        print(f"accuracy vs truth: median relative error {100 * s['median_rel_error']:.2f} %, "
              f"{100 * s['within_5pct']:.1f} % of estimates within 5 %, coverage {100 * s['coverage']:.1f} % "
              f"of {s['scene_pixels']} non-sky pixels")
    if args.png:
        from eonav.io.viz import write_range_png
        write_range_png(args.png, r, a.image, confidence=res.confidence)
        print(f"picture -> {args.png}")
    if args.timing:
        fn(a, b)  # warm-up
        times = []
        for _ in range(max(1, args.repeat)):
            t0 = time.perf_counter()
            fn(a, b)
            times.append(time.perf_counter() - t0)
        print(json.dumps({"seconds_per_pair": statistics.median(times), "method": args.method,
                          "repeat": len(times), "width": a.camera.width, "height": a.camera.height}))
    return 0
