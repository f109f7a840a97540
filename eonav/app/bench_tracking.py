"""Tracker benchmark on simulated flights: rendered frames -> range maps -> ``eonav.obstacles.analyse`` ->
``eonav.obstacles.tracking.Tracker``, scored against the simulator's boxes.

Range maps: ``dense``, the dense locator on motion pairs chosen by ``eonav.ranging.pair_policy`` (what the pipeline does), or
``truth``, the renderer's true range with 1 % Gaussian noise per pixel (seeded) and that sigma as
``inv_range_std_per_m``: the tracker's own behaviour on clean obstacle lists.

Per box of the scene (ground truth: the renderer's object ids and the solid box):
- in view: at least ``min_obstacle_pixels`` of its pixels in the frame and its distance within the obstacle list's
  ``max_obstacle_distance_m``;
- represented by a confirmed track in a frame when the track's position lies within ``max(2 m, 5 % of the
  distance)`` of the solid box;
- confirmation delay: from the first frame in view to the first frame represented;
- id stability: of the frames in view after the first represented one, the fraction in which its most frequent
  track id is among the tracks representing it (``ids_used`` counts every id that ever did: duplicates and
  replacements);
- a confirmed track that never came near any box is false; false confirmed tracks per minute of flight.
The "clear" flight is the approach flight's trajectory and textured ground with every box removed.

    python -m eonav.app.bench_tracking [--approach-s 8] [--clear-s 30] [--rate-hz 15] [--size 320x240]
"""
from __future__ import annotations

import argparse
import time
from collections import Counter, defaultdict
from dataclasses import replace

import numpy as np

from eonav.geometry.camera import View
from eonav.obstacles.detect import ObstacleConfig, analyse, confident_mask, infinity_mask
from eonav.ranging.pair_policy import PairPolicy, PosedFrameInfo
from eonav.obstacles.tracking import FieldOfView, Tracker, TrackerConfig, measurements_from_obstacles

# the obstacle service's defaults (services/obstacles.py flags)
SERVICE_OBSTACLES = ObstacleConfig(max_rel_std=0.25)


def box_distance(box, p_ned) -> float:
    """Euclidean distance from p to the solid box (clamp in the box's local frame)."""
    local = box.R_ned_local.T @ (np.asarray(p_ned, float) - np.asarray(box.center_ned_m))
    return float(np.linalg.norm(local - np.clip(local, -box.half_m, box.half_m)))


def frames(flight_name: str, seconds: float, rate_hz: float, size, clear: bool = False, seed: int = 0):
    """Yield (stamp_us, View, Render) of a simulated flight (``clear``: its boxes removed)."""
    from eonav.sim.flight import flight, flight_states
    from eonav.sim.presets import scale_camera
    from eonav.sim.render import render
    fl = flight(flight_name)
    scene = replace(fl.scene, boxes=()) if clear else fl.scene
    cam = scale_camera(fl.camera, size)
    times = np.arange(int(round(seconds * rate_hz))) / rate_hz
    for i, st in enumerate(flight_states(flight_name, times)):
        r = render(scene, cam, st, supersample=1, noise_sigma=1.0,
                   seed=int(np.random.SeedSequence([seed, i]).generate_state(1)[0]))
        yield int(round(times[i] * 1e6)), View(cam, st, r.image), r, scene


def run_flight(flight_name: str, seconds: float, rate_hz: float, size, clear: bool = False,
               ocfg: ObstacleConfig = SERVICE_OBSTACLES, tcfg: TrackerConfig = TrackerConfig(), maps: str = "dense",
               seed: int = 0):
    """Feed a flight through locator (or noisy truth), analysis and tracker; returns the per-frame record and the
    tracker's time per map (measurements + visibility mask + update)."""
    from eonav.ranging.locate import locate
    from eonav.ranging.rangemap import AT_INFINITY, VALID
    policy = PairPolicy()
    tracker = Tracker(tcfg)
    rng = np.random.default_rng(seed)
    rec = []
    t_track = []
    for stamp, view, rnd, scene in frames(flight_name, seconds, rate_hz, size, clear):
        cam, st = view.camera, view.state
        if maps == "truth":
            with np.errstate(invalid="ignore"):
                r = (rnd.range_m * (1.0 + 0.01 * rng.standard_normal(rnd.range_m.shape))).astype(np.float32)
                r[~np.isfinite(rnd.range_m)] = np.inf
                std = np.where(np.isfinite(r), 0.01 / r, 0.0).astype(np.float32)
            flags = np.where(np.isfinite(r), VALID, AT_INFINITY).astype(np.uint8)
            conf = np.ones(r.shape, np.float32)
        else:
            d = policy.offer(PosedFrameInfo("nose", len(rec), stamp, cam, st, view))
            if not d.ok:
                continue
            res = locate(d.a.payload, d.b.payload, method="dense")
            r, conf, flags, std = res.range_m, res.confidence, res.flags, res.inv_range_std_per_m
        ob = analyse(r, cam, st, confidence=conf, flags=flags, inv_range_std_per_m=std, cfg=ocfg)
        t0 = time.perf_counter()
        meas = measurements_from_obstacles(ob.obstacles, cam, st, tcfg, camera_id="nose")
        mask = confident_mask(r, conf, flags, std, ocfg)
        fov = FieldOfView(cam, st, ocfg.max_obstacle_distance_m, ocfg.min_distance_m, r, mask | infinity_mask(r, flags))
        tracker.update(meas, stamp, fov)
        t_track.append(time.perf_counter() - t0)
        ids, counts = np.unique(rnd.object_id, return_counts=True)
        visible = {int(i) - 2: int(c) for i, c in zip(ids, counts) if i >= 2}
        rec.append({"stamp_us": stamp, "state": st, "scene": scene, "visible_px": visible,
                    "confirmed": [(t.id, t.x[:3].copy()) for t in tracker.confirmed()],
                    "n_measurements": len(meas)})
    return rec, t_track


def score(rec, rate_hz: float, ocfg: ObstacleConfig = SERVICE_OBSTACLES) -> dict:
    """Confirmation delay and id stability per box, false confirmed tracks (see the module docstring)."""
    if not rec:
        return {}
    scene = rec[0]["scene"]
    per_box = defaultdict(lambda: {"first_in_view_us": None, "first_confirmed_us": None, "ids": []})
    near_box_ids = set()
    all_ids = set()
    for r in rec:
        pos = r["state"].position_ned_m
        for tid, p in r["confirmed"]:
            all_ids.add(tid)
            for b in scene.boxes:
                if box_distance(b, p) <= max(2.0, 0.05 * np.linalg.norm(p - pos)):
                    near_box_ids.add(tid)
        for i, b in enumerate(scene.boxes):
            dist = box_distance(b, pos)
            if r["visible_px"].get(i, 0) < ocfg.min_obstacle_pixels or dist > ocfg.max_obstacle_distance_m:
                continue
            s = per_box[b.name]
            if s["first_in_view_us"] is None:
                s["first_in_view_us"] = r["stamp_us"]
            tol = max(2.0, 0.05 * dist)
            reps = {tid for tid, p in r["confirmed"] if box_distance(b, p) <= tol}
            if reps and s["first_confirmed_us"] is None:
                s["first_confirmed_us"] = r["stamp_us"]
            if s["first_confirmed_us"] is not None:
                s["ids"].append(reps)
    boxes = {}
    for name, s in per_box.items():
        counts = Counter(i for reps in s["ids"] for i in reps)
        main = counts.most_common(1)[0] if counts else (None, 0)
        boxes[name] = {
            "frames_in_view": len(s["ids"]),
            "confirm_delay_s": (None if s["first_confirmed_us"] is None
                                else (s["first_confirmed_us"] - s["first_in_view_us"]) * 1e-6),
            "id_stability": main[1] / len(s["ids"]) if s["ids"] else 0.0,
            "ids_used": len(counts),
        }
    minutes = (rec[-1]["stamp_us"] - rec[0]["stamp_us"]) * 1e-6 / 60.0 + 1.0 / rate_hz / 60.0
    false_ids = all_ids - near_box_ids
    return {"boxes": boxes, "false_confirmed": len(false_ids), "false_per_min": len(false_ids) / minutes,
            "minutes": minutes, "maps": len(rec), "mean_measurements": float(np.mean([r["n_measurements"]
                                                                                     for r in rec]))}


def _size(s: str):
    w, h = (int(x) for x in s.lower().split("x"))
    return w, h


def add_arguments(p) -> None:
    p.add_argument("--approach-s", type=float, default=8.0, metavar="S",
                   help="seconds of the approach flight towards the boxes (0: skip it)")
    p.add_argument("--clear-s", type=float, default=30.0, metavar="S",
                   help="seconds of the same flight with every box removed, for false tracks (0: skip it)")
    p.add_argument("--rate-hz", type=float, default=15.0, metavar="HZ", help="frame rate")
    p.add_argument("--size", type=_size, default=(320, 240), help="image size in pixels, WxH")
    p.add_argument("--maps", choices=("dense", "truth", "both"), default="both",
                   help="range maps from the dense locator, from the truth with 1 %% noise, or both")
    for old, new in (("--seconds-approach", "approach_s"), ("--seconds-clear", "clear_s"), ("--rate", "rate_hz")):
        p.add_argument(old, dest=new, type=float, default=argparse.SUPPRESS, help=argparse.SUPPRESS)


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    add_arguments(p)
    args = p.parse_args(argv)
    sources = ("truth", "dense") if args.maps == "both" else (args.maps,)
    for maps in sources:
        for name, secs, clear in (("approach", args.approach_s, False), ("approach", args.clear_s, True)):
            if secs > 0:
                report(name, secs, args.rate_hz, args.size, clear, maps)
    return 0


def report(name, secs, rate, size, clear, maps) -> None:
    """Run one flight and print its figures."""
    t0 = time.perf_counter()
    rec, tt = run_flight(name, secs, rate, size, clear=clear, maps=maps)
    sc = score(rec, rate)
    label = f"{name}{' (boxes removed)' if clear else ''}, {maps} maps"
    print(f"{label}: {sc['maps']} maps over {sc['minutes'] * 60:.1f} s at {rate:g} Hz, {size[0]}x{size[1]}, "
          f"{sc['mean_measurements']:.1f} measurements a map; tracker p50 {np.median(tt) * 1e3:.2f} ms, "
          f"max {max(tt) * 1e3:.2f} ms a map ({time.perf_counter() - t0:.0f} s run)")
    for bname, b in sorted(sc["boxes"].items()):
        delay = "never" if b["confirm_delay_s"] is None else f"{b['confirm_delay_s']:.2f} s"
        print(f"  {bname:9s} confirmed after {delay:>7s}; id stable in {100 * b['id_stability']:5.1f} % of "
              f"{b['frames_in_view']} frames ({b['ids_used']} id(s))")
    print(f"  false confirmed tracks: {sc['false_confirmed']} ({sc['false_per_min']:.1f} per minute)", flush=True)


if __name__ == "__main__":
    raise SystemExit(main())
