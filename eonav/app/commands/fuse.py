"""``eonav fuse SEQ.json --out RANGE.npz [--out-dir DIR]``: fuse a sequence of posed frames (docs/pair-file.md).

The frames are pushed in file order, as the locator service receives them, through ``eonav.fusion.sequence.
FusionRunner``. ``--out`` gets the fused map of the last frame of the first frame's camera; ``--out-dir`` also gets
``range_{k:04d}.npz`` for every frame index k that got a map.
"""
from __future__ import annotations

import argparse


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("seq", help="pair file with N >= 2 frames in time order (docs/pair-file.md)")
    p.add_argument("--out", required=True, help="output .npz: the fused map of the last frame of the first frame's camera")
    p.add_argument("--out-dir", help="also write range_{k:04d}.npz for every frame index k that got a map")
    p.add_argument("--max-stereo-dt-s", type=float, default=0.002, metavar="S",
                   help="frames of two cameras at most this many seconds apart are a stereo pair (the first frame's "
                        "camera is the reference; the locator's --max-stereo-dt-s)")
    p.add_argument("--stereo-dt", dest="max_stereo_dt_s", type=float, default=argparse.SUPPRESS, help=argparse.SUPPRESS)


def check_sequence(doc) -> None:
    """Errors naming the field: fewer than 2 frames, frames out of time order (``t``, per file order)."""
    from eonav import InputError
    frames = doc.get("frames") if isinstance(doc, dict) else None
    if not isinstance(frames, list) or len(frames) < 2:
        n = len(frames) if isinstance(frames, list) else 0
        raise InputError(f"frames: eonav fuse needs a sequence of at least 2 frames, got {n}")
    last_t = None
    for i, fr in enumerate(frames):
        if not isinstance(fr, dict) or "t" not in fr:
            raise InputError(f"frames[{i}].t: missing (eonav fuse needs the time of every frame, seconds)")
        t = fr["t"]
        if isinstance(t, bool) or not isinstance(t, (int, float)):
            raise InputError(f"frames[{i}].t: expected a number, got {t!r}")
        if last_t is not None and t < last_t:
            raise InputError(f"frames[{i}].t: {t!r} is earlier than frames[{i - 1}].t {last_t!r} "
                             "(frames must be in time order)")
        last_t = t


def stereo_rig(pf, max_dt_s: float):
    """(first frame's camera, another camera) when some frame of the other camera is within max_dt_s of a frame of
    the first camera (a stereo rig), else None. Judged on the whole-microsecond stamps the frames are pushed with, as
    the scheduler pairs them (``fused_maps``; ``schedule.Scheduler``): float seconds can differ at the limit."""
    ref = pf.frames[0]["camera"]
    ts = [_stamp_us(fr) for fr in pf.frames if fr["camera"] == ref]
    for fr in pf.frames:
        if fr["camera"] != ref and any(abs(_stamp_us(fr) - t) <= max_dt_s * 1e6 for t in ts):
            return ref, fr["camera"]
    return None


def _stamp_us(fr) -> int:
    """A frame's time as the stamp it is pushed with (us)."""
    return int(round(fr["t"] * 1e6))


def check_output_dir(path):
    """--out-dir: a folder that exists or can be made, in which a file can be created."""
    from pathlib import Path

    from eonav import InputError
    from eonav.io.files import check_output
    d = Path(path)
    if d.exists() and not d.is_dir():
        raise InputError(f"--out-dir {d}: exists and is not a directory")
    check_output(d / "range_0000.npz", "--out-dir")
    return d


def fused_maps(runner, pf, views):
    """The fused maps of the sequence's frames pushed in file order, then those of the measurements still waiting at
    the end (``FusionRunner.finish``: a rig reference's last frame with no partner's frame after it)."""
    from eonav.fusion.sequence import frame
    for k, (fr, view) in enumerate(zip(pf.frames, views)):
        yield from runner.push(frame(fr["camera"], view, _stamp_us(fr), seq=k))
    yield from runner.finish()


def run(args) -> int:
    from pathlib import Path

    import numpy as np

    from eonav import InputError
    from eonav.fusion.schedule import ScheduleConfig
    from eonav.fusion.sequence import FusionConfig, FusionRunner
    from eonav.io.files import check_output, write_npz
    from eonav.io.pairfile import parse_pair, read_json

    check_output(args.out, "--out")                     # before any work: a path that cannot be written fails now
    doc = read_json(args.seq, "sequence file")
    check_sequence(doc)
    pf = parse_pair(doc, Path(args.seq).parent)
    for i in range(1, len(pf.frames)):
        cam = pf.frames[i]["camera"]
        prev = [j for j in range(i) if pf.frames[j]["camera"] == cam]
        if prev and pf.frames[i]["t"] <= pf.frames[prev[-1]]["t"]:
            raise InputError(f"frames[{i}].t: {pf.frames[i]['t']!r} is not after frames[{prev[-1]}].t "
                             f"{pf.frames[prev[-1]]['t']!r} of the same camera {cam!r}")
    rig = stereo_rig(pf, args.max_stereo_dt_s)
    runner = FusionRunner(FusionConfig(schedule=ScheduleConfig(stereo_rig=rig, max_stereo_dt_s=args.max_stereo_dt_s)))
    views = pf.views()
    out_dir = check_output_dir(args.out_dir) if args.out_dir else None
    ref = pf.frames[0]["camera"]
    last = None
    n_maps = 0
    for m in fused_maps(runner, pf, views):
        arrays = dict(m.result.arrays(), n_fused=m.n_fused.astype(np.uint16))
        n_maps += 1
        if out_dir:
            write_npz(out_dir / f"range_{m.frame.seq:04d}.npz", arrays, "--out-dir")
        if m.frame.camera_id == ref:
            last = (m.frame.seq, arrays)
    if last is None:
        raise InputError(f"no fused map for camera {ref!r}: no frame pair of the sequence had enough parallax")
    out = write_npz(args.out, last[1], "--out")
    r = last[1]["range_m"]
    print(f"fused {len(pf.frames)} frames ({n_maps} maps): frame {last[0]} of camera {ref!r}: "
          f"{int(np.isfinite(r).sum())}/{r.size} pixels with a finite range ({100.0 * np.isfinite(r).mean():.1f} %), "
          f"median {int(np.median(last[1]['n_fused']))} measurements fused -> {out}")
    return 0
