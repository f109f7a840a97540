"""``eonav sim PRESET --out DIR [--size N] [--seed S] [--noise SIGMA]``: render a preset pair and write it
(frame PNGs, pair.json per docs/pair-file.md, truth.npz, objects.json)."""
from __future__ import annotations

PRESET_NAMES = ("paper", "fast", "turning", "climbing", "stereo", "hover")


def add_arguments(p) -> None:
    p.add_argument("preset", choices=PRESET_NAMES, help="scene and motion to render")
    p.add_argument("--out", required=True, help="output directory (created if missing)")
    p.add_argument("--size", type=int, default=None, help="square image size in pixels (intrinsics scaled)")
    p.add_argument("--seed", type=int, default=0, help="sensor-noise seed")
    p.add_argument("--noise", type=float, default=1.0, help="Gaussian sensor noise sigma, grey levels")
    p.add_argument("--supersample", type=int, default=3, help="rays per pixel along each axis")


def run(args) -> int:
    import json

    from eonav.sim.presets import make_pair, write_pair
    pair = make_pair(args.preset, seed=args.seed, size=args.size, noise_sigma=args.noise,
                     supersample=args.supersample)
    path = write_pair(pair, args.out)
    out = path.parent
    cam = pair.views[0].camera
    print(f"wrote {path} ({args.preset}: {cam.width}x{cam.height}, {len(pair.views)} frames)")
    for name in sorted(p.name for p in out.iterdir() if p.name != path.name):
        print(f"wrote {out / name}")
    print(json.dumps({"object_range_m": pair.meta["object_range_m"], "motion": pair.meta["motion"]}))
    return 0
