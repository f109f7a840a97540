"""Tracker benchmark on simulated flights: rendered frames -> range maps -> ``eonav.obstacles.analyse`` ->
``eonav.obstacles.tracking.Tracker``, scored against the simulator's boxes.

Range maps (``--maps``):
- ``truth``: the renderer's true range with 1 % Gaussian noise per pixel (seeded) and that sigma: the tracker's own
  behaviour on clean obstacle lists;
- ``dense``: the dense locator on single motion pairs chosen by ``eonav.ranging.pair_policy``;
- ``fused``: what the locator publishes by default, the fused maps of ``eonav.fusion.sequence.FusionRunner`` (one
  push per frame, the dense method without its own fill as the measurement), with ``n_fused`` per pixel.

Scenarios (``--scenarios``): the simulator's flights (``approach``, ``turning``, ``climbing``) with their boxes, the
same flights with every box removed (``<flight>-clear``: textured ground and runway only), ``slope`` (the approach
flight, boxes removed, analysed in a frame pitched by ``--slope-deg``: the ground rises ahead, as over a slope the
vehicle follows), ``head-on`` (the approach flight's trajectory straight at a wall on its path: time to contact)
``moving`` (two vehicles driving at constant velocity, one across the path and one towards the aircraft: their
tracked velocity) and ``moving-stereo`` (the same, the nose camera with a stereo partner ``STEREO_BASELINE_M`` to
its right: fused maps take the rig's stereo pair of each instant besides the motion pair, the partner's frame handed
over first or, ``--rig-order arrival``, pushed after the reference's; dense maps are the stereo pair alone). The simulator's scene is static; a moving box is rendered at its place at each frame's time.

Renders (``--supersample N``): each pixel the mean of N x N samples over its area, as a camera pixel integrates the
light falling on it; N = 3 (the default, as the simulator's elsewhere); N = 1 is one point sample at the pixel centre,
which aliases edges and 1-2 px objects into steps that do not move with the scene (docs/guidance.md, "The long
box-free flights' false tracks": the approach's false track at 17 s; a mast ranged 60 % off). Ground truth (range,
object id) is the pixel-centre ray's either way. The render cache is keyed by N.

Per box (ground truth: the renderer's object ids and the solid box):
- in view: at least ``min_obstacle_pixels`` of its pixels in the frame and its distance within the obstacle list's
  ``max_obstacle_distance_m``;
- represented by a confirmed track in a frame when the track's position lies within ``max(2 m, 5 % of the
  distance)`` of the solid box;
- confirmation delay: from the first frame in view to the first frame represented;
- measured: a measurement of the map (``measurements_from_obstacles``) lies within that tolerance of the box;
- id stability: of the frames in view after the first represented one, the fraction in which its most frequent
  track id is among the tracks representing it (``ids_used`` counts every id that ever did: duplicates and
  replacements); the frames without the main id are split by cause: the main track is live but off by more than the
  tolerance (range error), it is not live and another track represents the box, or no track does;
- a confirmed track that never came near any box is false; false confirmed tracks per minute of flight; a false
  track that lies within 1 m of the ground (or below it) is a ground track; the tracks the tracker deleted because
  they followed the vehicle (its static-world test), and how many of them had been confirmed;
- time to contact (head-on): the guidance threat (``eonav.obstacles.tracking.assess``, ``nearest_threat``) against
  the true entry time of the vehicle's velocity ray into the wall grown by the vehicle radius, for every frame at most
  3 s from contact, both its ``time_to_contact_s`` (the earliest contact consistent with the cone's k sigma) and its
  ``expected_time_to_contact_s`` (without that margin); also the track's surface distance over the closing speed;
- velocity (moving): |v_track - v_true| / |v_true| of the mover's main track, scored in the frames from 1 s after
  that track's first confirmed frame (the filter's settling: its velocity starts at 0 +- 10 m/s) in which the mover
  is in view (the rule above) and the track was updated by a measurement of that map; the frames from then on in
  which the track is confirmed but not updated (coasting out of view, occluded or without data, or missed) are
  reported apart, as are updated frames with the mover out of view (a track not updated repeats its last velocity:
  scored, that one value would count once for every frame it coasts);
- a mover's pixels (moving): of its visible pixels while in view, the share the map ranges VALID within 10 % of the
  true range, VALID off by more, FILLED, flagged OCCLUDED (``mover_pixels``).

    python -m eonav.app.bench_tracking [--maps truth,dense,fused] [--scenarios approach,approach-clear,...]
        [--duration-s S] [--rate-hz 15] [--size 320x240] [--seed 0] [--see-through-k K] [--duplicate-chi2 D2]
        [--follow-k K] [--follow-fraction F] [--layer-gap-rel G] [--rig-baseline-m M] [--rig-order partner-first|arrival]
        [--stereo-lead-k K] [--skipped-free-k K] [--no-gate-unmatched] [--lr-check KINDS] [--slant] [--match-blur] [--slant-px PX] [--window-floor KIND]
        [--supersample N]
        [--cache-dir DIR]
"""
from __future__ import annotations

import argparse
import math
import time
from collections import Counter, defaultdict
from dataclasses import dataclass, replace

import numpy as np

from eonav.geometry.camera import VehicleState, View
from eonav.obstacles.detect import ObstacleConfig, analyse
from eonav.obstacles.tracking import (ConeConfig, FieldOfView, Ownship, Tracker, TrackerConfig, assess,
                                      box_entry_time, measurements_from_obstacles, nearest_threat)
from eonav.fusion.sequence import MEASUREMENT_WINDOW_FLOOR
from eonav.fusion.update import UpdateConfig
from eonav.ranging.pair_policy import PairPolicy, PosedFrameInfo
from eonav.ranging.rangemap import FILLED, OCCLUDED, VALID
from eonav.sim.scene import Box

# the obstacle service's defaults (its flags default to the library's)
SERVICE_OBSTACLES = ObstacleConfig()
MAP_SOURCES = ("truth", "dense", "fused")
GROUND_TRACK_M = 1.0
STEREO_BASELINE_M = 0.8            # the simulator's stereo preset's rig
PARTNER_ID = "right"
SUPERSAMPLE = 3                    # renders' samples per pixel along each axis (1: one point sample), as every
                                   # other renderer default of the project (eonav sim, bench fuse, the demo)


@dataclass(frozen=True)
class Mover:
    box: Box                       # at t = 0
    velocity_ned_mps: tuple


@dataclass(frozen=True)
class Scenario:
    name: str
    flight: str
    seconds: float
    clear: bool = False            # the flight's boxes removed
    boxes: tuple = ()              # boxes added (static)
    movers: tuple = ()             # boxes moving at constant velocity
    slope_deg: float = 0.0         # analysis frame pitched by this (the ground rises ahead)
    ttc_box: str = ""              # the box whose time to contact is scored
    rig_baseline_m: float = 0.0    # > 0: a stereo partner of the nose camera this far to its right (``rig_camera``)


def scenario(name: str, seconds: float | None = None, slope_deg: float = 5.0,
             rig_baseline_m: float = 0.0) -> Scenario:
    """A named scenario (module docstring); ``seconds`` overrides its default length, ``rig_baseline_m`` (> 0) the
    stereo scenario's baseline."""
    base, _, clear = name.partition("-")
    if base in ("approach", "turning", "climbing") and clear in ("", "clear"):
        default = (30.0 if base == "approach" else 12.0) if clear else {"approach": 8.0, "turning": 10.0,
                                                                         "climbing": 6.0}[base]
        return Scenario(name, base, seconds or default, clear=bool(clear))
    if name == "slope":
        return Scenario(name, "approach", seconds or 12.0, clear=True, slope_deg=slope_deg)
    if name == "head-on":
        wall = Box.on_ground("wall", 150.0, 0.0, 3.0, 12.0, 8.0, albedo=120.0, contrast=30.0)
        return Scenario(name, "approach", seconds or 10.0, clear=True, boxes=(wall,), ttc_box="wall")
    if name in ("moving", "moving-stereo"):
        # the crosser drives across the oncoming vehicle's lane 12-15 m behind it (it crossed at north 110 m until
        # the two solid boxes passed through each other for 0.9 s: docs/guidance.md, "Moving obstacles")
        crosser = Mover(Box.on_ground("crosser", 125.0, -30.0, 4.5, 2.0, 1.8, yaw_deg=90.0, albedo=110.0), (0.0, 6.0, 0.0))
        oncoming = Mover(Box.on_ground("oncoming", 140.0, -7.0, 5.0, 2.0, 2.2, albedo=140.0), (-8.0, 0.0, 0.0))
        return Scenario(name, "approach", seconds or 7.0, clear=True, movers=(crosser, oncoming),
                        rig_baseline_m=(rig_baseline_m or STEREO_BASELINE_M) if name == "moving-stereo" else 0.0)
    raise SystemExit(f"unknown scenario {name!r}")


def box_distance(box, p_ned) -> float:
    """Euclidean distance from p to the solid box (clamp in the box's local frame)."""
    local = box.R_ned_local.T @ (np.asarray(p_ned, float) - np.asarray(box.center_ned_m))
    return float(np.linalg.norm(local - np.clip(local, -box.half_m, box.half_m)))


def scene_at(sc: Scenario, base_scene, t_s: float):
    """The scene at time ``t_s``: the flight's (or none) boxes, the scenario's, the movers where they are then."""
    boxes = (() if sc.clear else tuple(base_scene.boxes)) + tuple(sc.boxes)
    boxes += tuple(replace(m.box, center_ned_m=tuple(np.asarray(m.box.center_ned_m) + t_s * np.asarray(m.velocity_ned_mps)))
                   for m in sc.movers)
    return replace(base_scene, boxes=boxes)


def tilt(slope_deg: float) -> np.ndarray:
    """Rotation true NED -> analysis frame: pitched about east by ``slope_deg`` (the true ground, flat, then rises
    ahead in the analysis frame: down decreases northwards)."""
    a = math.radians(slope_deg)
    c, s = math.cos(a), math.sin(a)
    return np.array([[c, 0.0, s], [0.0, 1.0, 0.0], [-s, 0.0, c]])


def velocity_at(flight_name: str, t_s: float, dt: float = 1e-3) -> np.ndarray:
    from eonav.sim.flight import flight_states
    a, b = flight_states(flight_name, [max(t_s - dt, 0.0), t_s + dt])
    return (b.position_ned_m - a.position_ned_m) / (b.t_s - a.t_s)


def rig_camera(cam, baseline_m: float):
    """The stereo partner of ``cam``: the same intrinsics and mount, ``baseline_m`` to its right (body y)."""
    l = np.asarray(cam.l_body_m, float).reshape(3) + np.array([0.0, baseline_m, 0.0])
    return replace(cam, name=PARTNER_ID, l_body_m=l)


def frames(sc: Scenario, rate_hz: float, size, seed: int = 0, supersample: int = SUPERSAMPLE):
    """Yield (stamp_us, View, Render, scene, partner View or None) of a scenario's frames (true NED); with
    ``sc.rig_baseline_m`` the partner camera's frame of the same instant (its own sensor noise). ``supersample``:
    the renderer's samples per pixel along each axis (``render(supersample=)``, averaged: a pixel's area)."""
    from eonav.sim.flight import flight, flight_states
    from eonav.sim.presets import scale_camera
    from eonav.sim.render import render
    fl = flight(sc.flight)
    cam = scale_camera(fl.camera, size)
    partner = rig_camera(cam, sc.rig_baseline_m) if sc.rig_baseline_m > 0 else None
    times = np.arange(int(round(sc.seconds * rate_hz))) / rate_hz
    for i, st in enumerate(flight_states(sc.flight, times)):
        scene = scene_at(sc, fl.scene, float(times[i]))
        r = render(scene, cam, st, supersample=supersample, noise_sigma=1.0,
                   seed=int(np.random.SeedSequence([seed, i]).generate_state(1)[0]))
        pv = None
        if partner is not None:
            rp = render(scene, partner, st, supersample=supersample, noise_sigma=1.0,
                        seed=int(np.random.SeedSequence([seed, i, 1]).generate_state(1)[0]))
            pv = View(partner, st, rp.image)
        yield int(round(times[i] * 1e6)), View(cam, st, r.image), r, scene, pv


def range_maps(sc: Scenario, rate_hz: float, size, maps: str = "dense", seed: int = 0,
               stereo_lead_k: float = UpdateConfig().stereo_lead_k, rig_order: str = "partner-first",
               lr_check: tuple = (), slant: bool = False, skipped_free_k: float = UpdateConfig().skipped_free_k,
               supersample: int = SUPERSAMPLE, window_floor: str | None = None, match_blur: bool = False,
               slant_px: float | None = None, gate_unmatched: bool = UpdateConfig().gate_unmatched):
    """Yield one dict per range map of a scenario: stamp_us, camera, state (true NED), the map's arrays (range_m,
    confidence, flags, inv_range_std_per_m, n_fused or None), the render's visible box pixels, the scene.
    ``lr_check``: fused, the measurement kinds checked left-right (``FusionConfig.lr_check_kinds``); dense, any: every
    pair checked (method "dense_lr"). ``slant``: fused, measured by the dense method's slanted window
    (``locate_dense(slant=True)``); ``match_blur``: fused, the dense method's resolution match
    (``locate_dense(match_blur=True)``); ``slant_px``: fused, the fused map's slant term (``MapConfig.slant_px``; None:
    its default). ``window_floor``: fused and dense, the dense method's floor of the window residual
    (``locate_dense(window_floor=...)``; None: its default). ``supersample``: the renders' samples per pixel along each
    axis (``frames``)."""
    from eonav.ranging.locate import locate
    from eonav.ranging.rangemap import AT_INFINITY, VALID
    if maps not in MAP_SOURCES:
        raise SystemExit(f"unknown map source {maps!r}; expected one of {MAP_SOURCES}")
    policy = PairPolicy()
    runner = None
    if maps == "fused":
        from eonav.fusion.schedule import ScheduleConfig
        from eonav.fusion.sequence import FusionConfig, FusionRunner
        cfg = FusionConfig(update=UpdateConfig(stereo_lead_k=stereo_lead_k, skipped_free_k=skipped_free_k,
                                               gate_unmatched=gate_unmatched),
                           lr_check_kinds=tuple(lr_check))
        if sc.rig_baseline_m > 0:
            cfg = replace(cfg, schedule=ScheduleConfig(stereo_rig=("nose", PARTNER_ID)))
        if slant_px is not None:
            cfg = replace(cfg, output=replace(cfg.output, slant_px=float(slant_px)))
        dense_params = dict({"slant": True} if slant else {}, **({"match_blur": True} if match_blur else {}),
                            **({"window_floor": window_floor} if window_floor else {}))
        if dense_params:
            from functools import partial
            from eonav.fusion.sequence import dense_measurement
            runner = FusionRunner(cfg, partial(dense_measurement, **dense_params), fresh_measurements=True,
                                  takes_prior=True)
        else:
            runner = FusionRunner(cfg)
    floor = {"window_floor": window_floor} if window_floor else {}
    rng = np.random.default_rng(seed)
    for k, (stamp, view, rnd, scene, pview) in enumerate(frames(sc, rate_hz, size, seed, supersample)):
        cam, st = view.camera, view.state
        n_fused = None
        if maps == "truth":
            with np.errstate(invalid="ignore"):
                r = (rnd.range_m * (1.0 + 0.01 * rng.standard_normal(rnd.range_m.shape))).astype(np.float32)
                r[~np.isfinite(rnd.range_m)] = np.inf
                std = np.where(np.isfinite(r), 0.01 / r, 0.0).astype(np.float32)
            flags = np.where(np.isfinite(r), VALID, AT_INFINITY).astype(np.uint8)
            conf = np.ones(r.shape, np.float32)
        elif maps == "dense" and pview is not None:      # the rig's stereo pair of the instant
            res = locate(view, pview, method="dense_lr" if lr_check else "dense", **floor)
            r, conf, flags, std = res.range_m, res.confidence, res.flags, res.inv_range_std_per_m
        elif maps == "dense":
            d = policy.offer(PosedFrameInfo("nose", k, stamp, cam, st, view))
            if not d.ok:
                continue
            res = locate(d.a.payload, d.b.payload, method="dense_lr" if lr_check else "dense", **floor)
            r, conf, flags, std = res.range_m, res.confidence, res.flags, res.inv_range_std_per_m
        else:
            from eonav.fusion.sequence import frame
            if pview is not None and rig_order == "partner-first":  # the partner's frame first (a partner only: no
                runner.remember(frame(PARTNER_ID, pview, stamp, seq=k))  # state of its own), the reference's: both
            out = [m for m in runner.push(frame("nose", view, stamp, seq=k)) if m.frame.seq == k]
            if pview is not None and rig_order == "arrival":    # the reference's frame first, then the partner's
                out = out + [m for m in runner.push(frame(PARTNER_ID, pview, stamp, seq=k))    # (its own state too):
                             if m.frame.camera_id == "nose" and m.frame.seq == k]            # the reference's last map
                out = out[-1:]
            if not out:
                continue
            res = out[0].result
            r, conf, flags, std, n_fused = (res.range_m, res.confidence, res.flags, res.inv_range_std_per_m,
                                            np.asarray(out[0].n_fused))
        ids, counts = np.unique(rnd.object_id, return_counts=True)
        yield {"stamp_us": stamp, "camera": cam, "state": st, "range_m": r, "confidence": conf, "flags": flags,
               "inv_range_std_per_m": std, "n_fused": n_fused, "scene": scene,
               "visible_px": {int(i) - 2: int(c) for i, c in zip(ids, counts) if i >= 2},
               "truth_range_m": rnd.range_m, "object_id": rnd.object_id}


def cached_maps(sc: Scenario, rate_hz: float, size, maps: str, seed: int, cache_dir: str | None,
                stereo_lead_k: float = UpdateConfig().stereo_lead_k, rig_order: str = "partner-first",
                lr_check: tuple = (), slant: bool = False, skipped_free_k: float = UpdateConfig().skipped_free_k,
                supersample: int = SUPERSAMPLE, window_floor: str | None = None, match_blur: bool = False,
                slant_px: float | None = None, gate_unmatched: bool = UpdateConfig().gate_unmatched):
    """``range_maps`` of a scenario, stored in ``cache_dir`` (one pickle per scenario, length, rate, size, source,
    seed, the renders' supersampling (``_ss<N>`` when not 1: the point-sampled renders' files keep their names), rig baseline, the left-right check, the slanted window, the resolution match and the fused map's ``slant_px`` when given (``_mb``, ``_spx<PX>``), the window floor the maps were made with (``_floor<KIND>`` unless "global"; fused maps' default is "valid") and, fused with a rig, ``stereo_lead_k`` and a
    non-zero ``skipped_free_k``, and ``_gu`` with the stereo pair's unmatched pixels gating the motion pairs, the
    default) the first time and read back afterwards: the maps are the slow part, the tracker alone is deterministic on
    them. No cache_dir: computed as they are used (a stream, nothing kept)."""
    lead = ({"stereo_lead_k": stereo_lead_k, "rig_order": rig_order} if maps == "fused" and sc.rig_baseline_m > 0
            else {})
    if lr_check:
        lead["lr_check"] = tuple(lr_check)
    if slant and maps == "fused":
        lead["slant"] = True
    if match_blur and maps == "fused":
        lead["match_blur"] = True
    if slant_px is not None and maps == "fused":
        lead["slant_px"] = float(slant_px)
    if window_floor and maps in ("dense", "fused"):
        lead["window_floor"] = window_floor
    # the floor the maps were made with keys the cache (named unless "global"): the fused measurement's own default
    # is "valid" (``dense_measurement``), the dense method's "global"
    floor = window_floor or (MEASUREMENT_WINDOW_FLOOR if maps == "fused" else "global")
    if skipped_free_k and "stereo_lead_k" in lead:
        lead["skipped_free_k"] = skipped_free_k
    if "stereo_lead_k" in lead:
        lead["gate_unmatched"] = bool(gate_unmatched)
    lead["supersample"] = supersample
    if not cache_dir:
        return range_maps(sc, rate_hz, size, maps, seed, **lead)
    import pickle
    from pathlib import Path
    path = Path(cache_dir) / (f"{sc.name}_{sc.seconds:g}s_{rate_hz:g}hz_{size[0]}x{size[1]}_{maps}_seed{seed}"
                              f"{f'_ss{supersample}' if supersample != 1 else ''}"
                              f"{f'_slope{sc.slope_deg:g}' if sc.slope_deg else ''}"
                              f"{f'_rig{sc.rig_baseline_m:g}' if sc.rig_baseline_m > 0 else ''}"
                              f"{f'_lead{stereo_lead_k:g}' if 'stereo_lead_k' in lead else ''}"
                              f"{'_arrival' if rig_order == 'arrival' and 'rig_order' in lead else ''}"
                              f"{'_lr-' + '-'.join(lr_check) if lr_check else ''}"
                              f"{'_slant' if lead.get('slant') else ''}"
                              f"{'_mb' if lead.get('match_blur') else ''}"
                              f"{f'_spx{slant_px:g}' if 'slant_px' in lead else ''}"
                              f"{'_floor' + floor if floor != 'global' and maps != 'truth' else ''}"
                              f"{f'_free{skipped_free_k:g}' if 'skipped_free_k' in lead else ''}"
                              f"{'_gu' if lead.get('gate_unmatched') and stereo_lead_k > 0 else ''}.pkl")
    if path.exists():
        with open(path, "rb") as f:
            return pickle.load(f)
    out = list(range_maps(sc, rate_hz, size, maps, seed, **lead))
    path.parent.mkdir(parents=True, exist_ok=True)
    with open(path.with_suffix(".tmp"), "wb") as f:
        pickle.dump(out, f, protocol=pickle.HIGHEST_PROTOCOL)
    path.with_suffix(".tmp").replace(path)
    return out


def to_analysis(st: VehicleState, R: np.ndarray) -> VehicleState:
    """The vehicle state in the analysis frame x' = R x."""
    return VehicleState(R @ st.position_ned_m, st.T_body_ned @ R.T, st.t_s)


def track_maps(stream, sc: Scenario, ocfg: ObstacleConfig = SERVICE_OBSTACLES, tcfg: TrackerConfig = TrackerConfig(),
               cone: ConeConfig = ConeConfig()):
    """Analyse and track a stream of ``range_maps``; returns the per-map record (tracks and threat in true NED) and
    the tracker's time per map (measurements + update; the visibility mask is the analysis' ``data_mask``)."""
    R = tilt(sc.slope_deg)
    tracker = Tracker(tcfg)
    rec, t_track = [], []
    for m in stream:
        cam, st_true = m["camera"], m["state"]
        st = to_analysis(st_true, R)
        r, conf, flags, std = m["range_m"], m["confidence"], m["flags"], m["inv_range_std_per_m"]
        ob = analyse(r, cam, st, confidence=conf, flags=flags, inv_range_std_per_m=std, cfg=ocfg,
                     **({"n_fused": m["n_fused"]} if m.get("n_fused") is not None else {}))
        t0 = time.perf_counter()
        meas = measurements_from_obstacles(ob.obstacles, cam, st, tcfg, camera_id="nose")
        fov = FieldOfView(cam, st, ocfg.max_obstacle_distance_m, ocfg.min_distance_m, r, ob.data_mask)
        tracker.update(meas, m["stamp_us"], fov)
        t_track.append(time.perf_counter() - t0)
        v_true = velocity_at(sc.flight, st_true.t_s)
        own = Ownship.from_state(st, R @ v_true, m["stamp_us"])
        views = assess(tracker.snapshot(m["stamp_us"]), own, m["stamp_us"], cone, tcfg)
        threat = nearest_threat(views)
        rec.append({"stamp_us": m["stamp_us"], "state": st_true, "scene": m["scene"], "visible_px": m["visible_px"],
                    "velocity_ned_mps": v_true,
                    "confirmed": [(t.id, R.T @ t.x[:3], R.T @ t.x[3:]) for t in tracker.confirmed()],
                    "hit": {t.id for t in tracker.confirmed() if t.last_hit_us == m["stamp_us"]},
                    "surface": {tv.track.id: (tv.surface_distance_m, tv.closing_speed_mps) for tv in views},
                    "threat": None if threat is None else (threat.track.id, threat.time_to_contact_s,
                                                           threat.expected_time_to_contact_s),
                    "n_measurements": len(meas), "n_obstacles": len(ob.obstacles),
                    "mover_px": mover_pixels(m, sc, ocfg),
                    "measured": [R.T @ mm.position_ned_m for mm in meas],
                    "followers": (tracker.n_followers, tracker.n_followers_confirmed)})
    return rec, t_track


def mover_pixels(m: dict, sc: Scenario, ocfg: ObstacleConfig = SERVICE_OBSTACLES) -> dict:
    """Per mover in view (``box_in_view``), its visible pixels by what the map says of them: VALID (not FILLED)
    within 10 % of the true range (right), VALID off by more (wrong), FILLED, OCCLUDED, other (no range)."""
    out = {}
    if "object_id" not in m:
        return out
    boxes = m["scene"].boxes
    for j in range(len(sc.movers)):
        i = len(boxes) - len(sc.movers) + j
        if not box_in_view(m, i, ocfg):
            continue
        px = m["object_id"] == i + 2
        fl = m["flags"][px]
        valid = (fl & (VALID | FILLED)) == VALID
        with np.errstate(invalid="ignore"):
            ok = np.abs(m["range_m"][px] / m["truth_range_m"][px] - 1.0) <= 0.10
        out[boxes[i].name] = {"pixels": int(px.sum()), "right": int((valid & ok).sum()),
                              "wrong": int((valid & ~ok).sum()), "filled": int(((fl & FILLED) != 0).sum()),
                              "occluded": int(((fl & OCCLUDED) != 0).sum())}
    return out


def true_ttc(box: Box, pos_ned, vel_ned, radius_m: float) -> float | None:
    """Entry time of the ray pos + vel t into the (axis-aligned, yaw 0) box grown by ``radius_m``."""
    c = np.asarray(box.center_ned_m) - np.asarray(pos_ned)
    return box_entry_time(c, box.half_m + radius_m, np.asarray(vel_ned))


def box_in_view(r: dict, i: int, ocfg: ObstacleConfig = SERVICE_OBSTACLES) -> bool:
    """Box ``i`` of the record's scene in view (module docstring): at least ``min_obstacle_pixels`` visible and
    within ``max_obstacle_distance_m`` of the vehicle."""
    return (r["visible_px"].get(i, 0) >= ocfg.min_obstacle_pixels
            and box_distance(r["scene"].boxes[i], r["state"].position_ned_m) <= ocfg.max_obstacle_distance_m)


def score(rec, rate_hz: float, ocfg: ObstacleConfig = SERVICE_OBSTACLES, sc: Scenario | None = None,
          cone: ConeConfig = ConeConfig()) -> dict:
    """Confirmation delay and id stability per box, false confirmed tracks, time to contact, velocity (module
    docstring)."""
    if not rec:
        return {}
    per_box = defaultdict(lambda: {"first_in_view_us": None, "first_confirmed_us": None, "ids": [], "tracked": [],
                                   "measured": []})
    near_box_ids, all_ids, ground_ids = set(), set(), set()
    for r in rec:
        pos = r["state"].position_ned_m
        boxes = r["scene"].boxes
        for tid, p, _ in r["confirmed"]:
            all_ids.add(tid)
            if p[2] > -GROUND_TRACK_M:
                ground_ids.add(tid)
            for b in boxes:
                if box_distance(b, p) <= max(2.0, 0.05 * np.linalg.norm(p - pos)):
                    near_box_ids.add(tid)
        for i, b in enumerate(boxes):
            if not box_in_view(r, i, ocfg):
                continue
            dist = box_distance(b, pos)
            s = per_box[b.name]
            if s["first_in_view_us"] is None:
                s["first_in_view_us"] = r["stamp_us"]
            tol = max(2.0, 0.05 * dist)
            reps = {tid for tid, p, _ in r["confirmed"] if box_distance(b, p) <= tol}
            if reps and s["first_confirmed_us"] is None:
                s["first_confirmed_us"] = r["stamp_us"]
            if s["first_confirmed_us"] is not None:
                s["ids"].append(reps)
                s["tracked"].append({tid for tid, _, _ in r["confirmed"]})
                s["measured"].append(any(box_distance(b, z) <= tol for z in r.get("measured", ())))
    boxes = {}
    for name, s in per_box.items():
        counts = Counter(i for reps in s["ids"] for i in reps)
        main = counts.most_common(1)[0] if counts else (None, 0)
        lost = [(main[0] in live, bool(reps)) for reps, live in zip(s["ids"], s["tracked"]) if main[0] not in reps]
        boxes[name] = {
            "frames_in_view": len(s["ids"]),
            "confirm_delay_s": (None if s["first_confirmed_us"] is None
                                else (s["first_confirmed_us"] - s["first_in_view_us"]) * 1e-6),
            "id_stability": main[1] / len(s["ids"]) if s["ids"] else 0.0,
            "ids_used": len(counts),
            "main_id": main[0],
            # the frames of id_stability without the main id, by cause: the main track is live but farther than the
            # tolerance (range error), it is not live (not yet born or deleted) and another track represents the
            # box, or no track does; and the frames with a measurement of the box within the tolerance
            "main_off": sum(1 for live, _ in lost if live),
            "main_gone_other": sum(1 for live, other in lost if not live and other),
            "main_gone_none": sum(1 for live, other in lost if not live and not other),
            "measured": sum(s["measured"]),
        }
    minutes = (rec[-1]["stamp_us"] - rec[0]["stamp_us"]) * 1e-6 / 60.0 + 1.0 / rate_hz / 60.0
    false_ids = all_ids - near_box_ids
    out = {"boxes": boxes, "false_confirmed": len(false_ids), "false_per_min": len(false_ids) / minutes,
           "followers": rec[-1].get("followers", (0, 0)),
           "false_ground": len(false_ids & ground_ids), "minutes": minutes, "maps": len(rec),
           "mean_measurements": float(np.mean([r["n_measurements"] for r in rec])),
           "mean_obstacles": float(np.mean([r["n_obstacles"] for r in rec]))}
    if sc is not None and sc.ttc_box:
        out["ttc"] = score_ttc(rec, sc.ttc_box, boxes.get(sc.ttc_box, {}).get("main_id"), cone)
    if sc is not None and sc.movers:
        out["velocity"] = {m.box.name: score_velocity(rec, m, boxes.get(m.box.name, {}), ocfg) for m in sc.movers}
    return out


def score_ttc(rec, box_name: str, main_id, cone: ConeConfig, horizon_s: float = 3.0) -> dict:
    """Relative time-to-contact errors over the frames at most ``horizon_s`` from contact (module docstring)."""
    threat_err, expected_err, plain_err, missing = [], [], [], 0
    for r in rec:
        box = next(b for b in r["scene"].boxes if b.name == box_name)
        t_true = true_ttc(box, r["state"].position_ned_m, r["velocity_ned_mps"], cone.vehicle_radius_m)
        if t_true is None or not 0 < t_true <= horizon_s:
            continue
        thr = r["threat"]
        if thr is None or thr[0] != main_id:
            missing += 1
            threat_err.append(math.inf)
            expected_err.append(math.inf)
        else:
            threat_err.append((thr[1] - t_true) / t_true)
            expected_err.append((thr[2] - t_true) / t_true if len(thr) > 2 else math.nan)
        surf = r["surface"].get(main_id)
        if surf is not None and surf[1] > 0:
            plain_err.append((surf[0] - cone.vehicle_radius_m) / surf[1] / t_true - 1.0)
        else:
            plain_err.append(math.inf)
    return {"frames": len(threat_err), "missing": missing, "threat_rel_err": threat_err,
            "expected_rel_err": expected_err, "plain_rel_err": plain_err}


def score_velocity(rec, mover: Mover, box_score: dict, ocfg: ObstacleConfig = SERVICE_OBSTACLES,
                   settle_s: float = 1.0) -> dict:
    """|v_track - v_true| / |v_true| of the mover's main track from ``settle_s`` after its first confirmed frame
    (module docstring): ``rel_err`` over the frames with the mover in view (``box_in_view``) and the track updated by
    a measurement of that map (the record's ``hit`` ids); ``coast_rel_err`` over the frames the track was not updated;
    ``measured_out_of_view``: frames it was updated with the mover out of view (not scored)."""
    tid = box_score.get("main_id")
    v_true = np.asarray(mover.velocity_ned_mps)
    first = None
    errs, coast, out_of_view = [], [], 0
    for r in rec:
        v = next((v for i, _, v in r["confirmed"] if i == tid), None)
        if v is None:
            continue
        first = r["stamp_us"] if first is None else first
        if r["stamp_us"] - first < settle_s * 1e6:
            continue
        err = float(np.linalg.norm(v - v_true) / np.linalg.norm(v_true))
        if tid not in r.get("hit", ()):
            coast.append(err)
            continue
        i = next(k for k, b in enumerate(r["scene"].boxes) if b.name == mover.box.name)
        if box_in_view(r, i, ocfg):
            errs.append(err)
        else:
            out_of_view += 1
    return {"frames": len(errs), "rel_err": errs, "coast_frames": len(coast), "coast_rel_err": coast,
            "measured_out_of_view": out_of_view}


def _size(s: str):
    w, h = (int(x) for x in s.lower().split("x"))
    return w, h


DEFAULT_SCENARIOS = ("approach,approach-clear,turning,turning-clear,climbing,climbing-clear,slope,head-on,moving,"
                     "moving-stereo")


def add_arguments(p) -> None:
    p.add_argument("--maps", default="truth,dense,fused", help=f"comma list of {', '.join(MAP_SOURCES)}")
    p.add_argument("--scenarios", default=DEFAULT_SCENARIOS, help="comma list (module docstring)")
    p.add_argument("--duration-s", type=float, default=None, metavar="S",
                   help="length of every scenario (default: its own)")
    p.add_argument("--rate-hz", type=float, default=15.0, metavar="HZ", help="frame rate")
    p.add_argument("--size", type=_size, default=(320, 240), help="image size in pixels, WxH")
    p.add_argument("--seed", type=int, default=0, help="sensor-noise seed")
    p.add_argument("--slope-deg", type=float, default=5.0, metavar="DEG", help="the slope scenario's ground slope")
    p.add_argument("--min-fused", type=int, default=SERVICE_OBSTACLES.min_fused,
                   help="ObstacleConfig.min_fused: fused-map pixels need this many measurements")
    p.add_argument("--horizon-min-fused", type=int, default=SERVICE_OBSTACLES.horizon_min_fused,
                   help="ObstacleConfig.horizon_min_fused: fused-map pixels at or above the ground plane's horizon "
                        "need this many measurements")
    p.add_argument("--jump-sigma-k", type=float, default=SERVICE_OBSTACLES.jump_sigma_k, metavar="K",
                   help="ObstacleConfig.jump_sigma_k: a range jump between neighbours cuts two objects beyond K x "
                        "the hypot of their relative sigmas (and max_rel_jump)")
    p.add_argument("--layer-gap-rel", type=float, default=SERVICE_OBSTACLES.layer_gap_rel, metavar="G",
                   help="ObstacleConfig.layer_gap_rel: a component whose ranges fall into two layers this far apart "
                        "(relative) is two objects (0: off)")
    p.add_argument("--see-through-k", type=float, default=TrackerConfig().see_through_k, metavar="K",
                   help="TrackerConfig.see_through_k: farther measurements bearing-only beyond K track sigma (0: off)")
    p.add_argument("--duplicate-chi2", type=float, default=TrackerConfig().duplicate_chi2, metavar="D2",
                   help="TrackerConfig.duplicate_chi2: merge confirmed tracks within this 6-dof d^2 (0: off)")
    p.add_argument("--follow-k", type=float, default=TrackerConfig().follow_k, metavar="K",
                   help="TrackerConfig.follow_k: sigma of the static-world test (0: off)")
    p.add_argument("--follow-fraction", type=float, default=TrackerConfig().follow_fraction, metavar="F",
                   help="TrackerConfig.follow_fraction: drift along the vehicle's velocity, as a fraction of its "
                        "speed, above which a track follows the vehicle")
    p.add_argument("--rig-baseline-m", type=float, default=0.0, metavar="M",
                   help=f"moving-stereo: the rig's baseline (default {STEREO_BASELINE_M:g} m)")
    p.add_argument("--rig-order", choices=("partner-first", "arrival"), default="partner-first",
                   help="moving-stereo, fused: the partner's frame handed over first (a partner only) or pushed after "
                        "the reference's, as the locator does when the reference's frame arrives first")
    p.add_argument("--stereo-lead-k", type=float, default=UpdateConfig().stereo_lead_k, metavar="K",
                   help="UpdateConfig.stereo_lead_k: a rig's stereo measurement leads where it disagrees by K sigma "
                        "(0: off)")
    p.add_argument("--skipped-free-k", type=float, default=UpdateConfig().skipped_free_k, metavar="K",
                   help="UpdateConfig.skipped_free_k: with a rig, the stereo pixels the update skips empty the cells "
                        "they see farther by K sigma (0: off)")
    p.add_argument("--no-gate-unmatched", dest="gate_unmatched", action="store_false",
                   help="with a rig: fuse the motion pairs also where the same frame's stereo pixel failed to match "
                        "(UpdateConfig.gate_unmatched off)")
    p.add_argument("--lr-check", default="", metavar="KINDS",
                   help="comma list of the measurement kinds (stereo, near, wide) the fused maps check left-right "
                        "(FusionConfig.lr_check_kinds; default none); dense maps: any checks every pair")
    p.add_argument("--slant", action="store_true",
                   help="fused maps: the dense method's slanted window (slant=True)")
    p.add_argument("--match-blur", action="store_true",
                   help="fused maps: the dense method's resolution match (match_blur=True)")
    p.add_argument("--slant-px", type=float, default=None, metavar="PX",
                   help="fused maps: the fused map's slant term (MapConfig.slant_px; default its own)")
    p.add_argument("--supersample", type=int, default=SUPERSAMPLE, metavar="N",
                   help="render each pixel as the mean of N x N samples over its area (1: point sampling)")
    p.add_argument("--window-floor", default=None, choices=("global", "valid", "sensor", "mid"),
                   help="dense and fused maps: the dense method's floor of the window residual "
                        "(locate_dense(window_floor=...); default: the measurement's own, 'valid' for fused maps "
                             "(eonav.fusion.sequence.dense_measurement), 'global' for dense ones)")
    p.add_argument("--cache-dir", default=None, metavar="DIR",
                   help="store the range maps here and reuse them on the next run with the same settings")
    p.add_argument("--rate", dest="rate_hz", type=float, default=argparse.SUPPRESS, help=argparse.SUPPRESS)


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    add_arguments(p)
    args = p.parse_args(argv)
    ocfg = replace(SERVICE_OBSTACLES, min_fused=args.min_fused, horizon_min_fused=args.horizon_min_fused,
                   jump_sigma_k=args.jump_sigma_k, layer_gap_rel=args.layer_gap_rel)
    tcfg = replace(TrackerConfig(), see_through_k=args.see_through_k, duplicate_chi2=args.duplicate_chi2,
                   follow_k=args.follow_k, follow_fraction=args.follow_fraction)
    print(f"obstacle config: {ocfg}")
    print(f"tracker: see_through_k {tcfg.see_through_k:g}, duplicate_chi2 {tcfg.duplicate_chi2:g}, follow_k "
          f"{tcfg.follow_k:g}, follow_fraction {tcfg.follow_fraction:g}")
    for maps in [s for s in args.maps.split(",") if s]:
        for name in [s for s in args.scenarios.split(",") if s]:
            report(scenario(name, args.duration_s, args.slope_deg, args.rig_baseline_m), args.rate_hz, args.size, maps, args.seed, ocfg,
                   tcfg, args.cache_dir, args.stereo_lead_k, args.rig_order,
                   tuple(k for k in args.lr_check.split(",") if k), args.slant, args.skipped_free_k, args.supersample,
                   args.window_floor, args.match_blur, args.slant_px, args.gate_unmatched)
    return 0


def _pct(errs, q):
    a = np.abs(np.asarray(errs, float))
    return float(np.percentile(a, q, method="nearest")) if a.size else math.nan


def _within(errs, tol) -> str:
    """Percentage of ``errs`` within ``tol`` (0 decimals), "-" for none."""
    return f"{100 * np.mean(np.abs(np.asarray(errs, float)) <= tol):.0f}" if len(errs) else "-"


def report(sc: Scenario, rate, size, maps, seed=0, ocfg: ObstacleConfig = SERVICE_OBSTACLES,
           tcfg: TrackerConfig = TrackerConfig(), cache_dir: str | None = None,
           stereo_lead_k: float = UpdateConfig().stereo_lead_k, rig_order: str = "partner-first",
           lr_check: tuple = (), slant: bool = False, skipped_free_k: float = UpdateConfig().skipped_free_k,
           supersample: int = SUPERSAMPLE, window_floor: str | None = None, match_blur: bool = False,
           slant_px: float | None = None, gate_unmatched: bool = UpdateConfig().gate_unmatched) -> dict:
    """Run one scenario and print its figures."""
    t0 = time.perf_counter()
    rec, tt = track_maps(cached_maps(sc, rate, size, maps, seed, cache_dir, stereo_lead_k, rig_order, lr_check, slant,
                                     skipped_free_k, supersample, window_floor, match_blur, slant_px,
                                     gate_unmatched), sc, ocfg, tcfg)
    s = score(rec, rate, ocfg, sc=sc)
    label = (f"{sc.name}{f' ({sc.slope_deg:g} deg)' if sc.slope_deg else ''}, {maps} maps, seed {seed}"
             f"{', left-right check ' + ','.join(lr_check) if lr_check else ''}"
             f"{', slanted window' if slant and maps == 'fused' else ''}"
             f"{', resolution match' if match_blur and maps == 'fused' else ''}"
             f"{f', slant_px {slant_px:g}' if slant_px is not None and maps == 'fused' else ''}"
             f"{f', window floor {window_floor}' if window_floor and maps in ('dense', 'fused') else ''}"
             f"{f', skipped_free_k {skipped_free_k:g}' if skipped_free_k and maps == 'fused' else ''}"
             f"{', motion pairs not gated by unmatched stereo pixels' if not gate_unmatched and sc.rig_baseline_m > 0 and maps == 'fused' else ''}")
    print(f"{label}: {s['maps']} maps over {s['minutes'] * 60:.1f} s at {rate:g} Hz, {size[0]}x{size[1]} "
          f"({supersample} x {supersample} samples a pixel), "
          f"{s['mean_obstacles']:.1f} obstacles / {s['mean_measurements']:.1f} measurements a map; tracker p50 "
          f"{np.median(tt) * 1e3:.2f} ms, max {max(tt) * 1e3:.2f} ms a map ({time.perf_counter() - t0:.0f} s run)")
    for bname, b in sorted(s["boxes"].items()):
        delay = "never" if b["confirm_delay_s"] is None else f"{b['confirm_delay_s']:.2f} s"
        print(f"  {bname:9s} confirmed after {delay:>7s}; id stable in {100 * b['id_stability']:5.1f} % of "
              f"{b['frames_in_view']} frames ({b['ids_used']} id(s)); without it: {b['main_off']} off by more than "
              f"the tolerance, {b['main_gone_other']} another id, {b['main_gone_none']} none; measured within the "
              f"tolerance in {b['measured']}")
    print(f"  false confirmed tracks: {s['false_confirmed']} ({s['false_per_min']:.1f} per minute), "
          f"{s['false_ground']} of them on the ground; tracks deleted as following the vehicle: "
          f"{s['followers'][0]} ({s['followers'][1]} of them confirmed before)")
    if "ttc" in s:
        t = s["ttc"]
        within = np.mean(np.abs(t["threat_rel_err"]) <= 0.10) if t["frames"] else math.nan
        within_p = np.mean(np.abs(t["plain_rel_err"]) <= 0.10) if t["frames"] else math.nan
        within_e = np.mean(np.abs(t["expected_rel_err"]) <= 0.10) if t["frames"] else math.nan
        print(f"  time to contact, {t['frames']} frames <= 3 s out: guidance threat's expected time within 10 % in "
              f"{100 * within_e:.0f} % (|error| median {100 * _pct(t['expected_rel_err'], 50):.1f} %, max "
              f"{100 * _pct(t['expected_rel_err'], 100):.1f} %, {t['missing']} frames without the wall as the "
              f"threat); its earliest (k-sigma) time within 10 % in {100 * within:.0f} % (median "
              f"{100 * _pct(t['threat_rel_err'], 50):.1f} %, max {100 * _pct(t['threat_rel_err'], 100):.1f} %); "
              f"surface distance / closing speed within 10 % in {100 * within_p:.0f} % (median "
              f"{100 * _pct(t['plain_rel_err'], 50):.1f} %, max {100 * _pct(t['plain_rel_err'], 100):.1f} %)")
    px = defaultdict(Counter)
    for r in rec:
        for name, c in r.get("mover_px", {}).items():
            px[name].update(c)
            px[name]["frames"] += 1
    for name, c in sorted(px.items()):
        n = max(c["pixels"], 1)
        print(f"  pixels of {name} over {c['frames']} frames in view: VALID within 10 % {100 * c['right'] / n:.0f} %, "
              f"VALID off by more {100 * c['wrong'] / n:.0f} %, FILLED {100 * c['filled'] / n:.0f} %, OCCLUDED "
              f"{100 * c['occluded'] / n:.0f} %")
    for name, v in s.get("velocity", {}).items():
        print(f"  velocity of {name}: {v['frames']} frames in view and measured from 1 s after confirmation, "
              f"|error| / speed median {100 * _pct(v['rel_err'], 50):.1f} %, p90 {100 * _pct(v['rel_err'], 90):.1f} "
              f"%, within 20 % in {_within(v['rel_err'], 0.2)} %; not scored: {v['coast_frames']} not updated (median "
              f"{100 * _pct(v['coast_rel_err'], 50):.1f} %, within 20 % in {_within(v['coast_rel_err'], 0.2)} %), "
              f"{v['measured_out_of_view']} measured out of view")
    print("", flush=True)
    return s


if __name__ == "__main__":
    raise SystemExit(main())
