"""``eonav bench pipeline``: frame capture -> range map published -> obstacles published, over the real bus.

Starts the embedded router and the locator and obstacle services as processes, then plays posed frames of a
simulated flight at a fixed rate straight onto the posed-frame key (camera ingest and sync are not in the loop). A
frame's ``stamp_us`` is the moment it is put; the bench's subscriber stamps the arrival of the range map and of the
obstacle list carrying that stamp on the same host clock. Per case it prints latency p50/p99 (capture -> range map,
capture -> obstacles), throughput, drops, the locator's compute time and the scales the maps came at; then per stage
the services' own health latencies (ages at each point of a frame's way, each stage's wall and CPU time) and each
process's share of a core (/proc), with the load average (the machine may be shared: CPU times are the figures
other load moves least). ``--json`` adds every measured frame's timeline.
``--accuracy`` instead measures, in process, what a locate scale costs against the simulator's truth, and
``--fusion-time`` what fusion adds to the locator's time per frame.
``run_bench(cases, seconds=...)`` is the pipeline function under the command.
"""
from __future__ import annotations

import json
import logging
import math
import os
import signal
import sys
import threading
import time

import numpy as np

log = logging.getLogger("eonav.app.bench_pipeline")

DEFAULT_CASES = ((30.0, 640, 480), (30.0, 512, 512), (15.0, 640, 480), (15.0, 512, 512))
STARTUP_S = 600.0            # longest wait for the locator's subscription


def _frames(width: int, height: int, n: int = 4, rate_hz: float = 10.0):
    """n rendered frames of the approach flight at width x height (as posed_frame fields)."""
    from eonav.geometry.frames import quat_wxyz_from_rotation
    from eonav.bus.schema import camera_to_msg
    from eonav.sim.flight import render_flight
    out = []
    for _, view, _ in render_flight("approach", n_frames=n, rate_hz=rate_hz, size=(width, height), t0_s=2.5,
                                    supersample=1):
        out.append({"image": np.clip(np.round(view.image), 0, 255).astype(np.uint8),
                    "camera": camera_to_msg(view.camera), "position_ned_m": view.state.position_ned_m,
                    "q_wxyz": quat_wxyz_from_rotation(view.state.T_body_ned.T)})
    return out


def _pct(v, q):
    return float(np.percentile(v, q)) if len(v) else math.nan


# (label, service, health latency name): ages are capture -> that point, durations one stage of one frame
AGES = (("capture -> locator dequeues the frame", "locator", "age.dequeued"),
        ("capture -> locate starts", "locator", "age.locate_start"),
        ("capture -> fused map ready", "locator", "age.fused"),
        ("capture -> range map put", "locator", "capture_to_published"),
        ("capture -> obstacles dequeue the map", "obstacles", "age.dequeued"),
        ("capture -> obstacle list put", "obstacles", "capture_to_obstacles"))
DURATIONS = (("locator: frame taken -> map put (wall)", "locator", "frame_time"),
             ("locator: decode + grey image (CPU)", "locator", "cpu.ingest"),
             ("locator: locate (wall)", "locator", "locate"), ("locator: locate (CPU)", "locator", "cpu.locate"),
             ("locator: fusion (wall)", "locator", "fusion"), ("locator: fusion (CPU)", "locator", "cpu.fusion"),
             ("locator: map fields + encode + put (wall)", "locator", "publish"),
             ("locator: map fields + encode + put (CPU)", "locator", "cpu.publish"),
             ("obstacles: decode (CPU)", "obstacles", "cpu.decode"),
             ("obstacles: analyse (wall)", "obstacles", "analyse"),
             ("obstacles: analyse (CPU)", "obstacles", "cpu.analyse"),
             ("obstacles: track (wall)", "obstacles", "track"),
             ("obstacles: track (CPU)", "obstacles", "cpu.track"),
             ("obstacles: obstacle list encode + put (CPU)", "obstacles", "cpu.publish"),
             ("obstacles: then the track message (CPU)", "obstacles", "cpu.track_message"))


def stage_table(health: dict) -> dict:
    """label -> {p50, p99, n} (ms) of each stage from the services' last health messages (their 10 s windows)."""
    out = {}
    gc = [(f"{svc}: garbage collector pause {name[3:]}", svc, name) for svc in ("locator", "obstacles")
          for name in sorted(health.get(svc, {}).get("latency_ms", {})) if name.startswith("gc.")]
    for label, svc, name in AGES + DURATIONS + tuple(gc):
        w = health.get(svc, {}).get("latency_ms", {}).get(name)
        if w and w.get("n"):
            out[label] = {"p50": w["p50"], "p99": w["p99"], "n": w["n"]}
    return out


def _frame_row(stamp_us: int, m, o) -> list:
    r = lambda x: None if x is None or not math.isfinite(x) else round(x, 1)    # noqa: E731
    return [r(m and m[4]), r(m and (m[0] - stamp_us) / 1e3), r(o and o[1]), r(o and (o[0] - stamp_us) / 1e3),
            r(m and 1e3 * m[1])]


def _cpu_seconds(procs) -> dict:
    """CPU seconds (user + system) so far of each service process (/proc/PID/stat) and of this process."""
    tick = os.sysconf("SC_CLK_TCK")
    out = {"bench": sum(os.times()[:2])}
    for name, p in zip(("locator", "obstacles"), procs):
        try:
            with open(f"/proc/{p.pid}/stat") as fh:
                f = fh.read().rsplit(")", 1)[1].split()
            out[name] = (int(f[11]) + int(f[12])) / tick
        except (OSError, IndexError, ValueError):
            pass
    return out


def _cpu_share(t0, t1) -> dict:
    """Each process's share of one core between two ``_cpu_seconds`` readings (with their monotonic times)."""
    if t0 is None or t1 is None or t1[1] <= t0[1]:
        return {}
    return {k: (t1[0][k] - v) / (t1[1] - t0[1]) for k, v in t0[0].items() if k in t1[0]}


def bench_case(ep: str, fps: float, width: int, height: int, seconds: float, frames: list, *, method: str = "dense",
               cv_threads: int = 1, vehicle: str = "bench", scale="auto", publish_grid: str = "locate") -> dict:
    import zenoh
    from eonav.bus import keys as K
    from eonav.bus import schema
    from eonav.bus.session import client_session
    from eonav.app.processes import start_service, stop_service, wait_until
    common = ["--vehicle", vehicle, "--connect", ep, "--health-period-s", "1", "--log-level", "warning"]
    procs = [start_service(["-m", "eonav.services.locator", *common, "--method", method, "--cv-threads", str(cv_threads),
                            "--scale", str(scale), "--publish-grid", publish_grid]),
             start_service(["-m", "eonav.services.obstacles", *common, "--ground-down-m", "0"])]
    res = {"fps": fps, "width": width, "height": height, "method": method, "scale": scale,
           "publish_grid": publish_grid}
    try:
        with client_session(ep) as s:
            rx_map, rx_obs, shm = {}, {}, {"maps": 0, "maps_shm": 0}
            health = {}
            lock = threading.Lock()
            subs = [s.declare_subscriber(K.range_maps_all(vehicle), zenoh.handlers.FifoChannel(256)),
                    s.declare_subscriber(K.obstacles(vehicle), zenoh.handlers.FifoChannel(256)),
                    s.declare_subscriber(K.health_all(vehicle), zenoh.handlers.FifoChannel(256))]

            def consume(sub, kind):
                try:
                    for smp in sub:
                        t = time.time_ns() // 1000
                        m = schema.decode(smp.payload.to_bytes(), expect=kind)
                        with lock:
                            if kind == "range_map":
                                rx_map[m["stamp_us"]] = (t, m["compute_s"], m["overhead_s"], m.get("scale", 1.0),
                                                         m["frame_age_ms"])
                                shm["maps"] += 1
                                shm["maps_shm"] += smp.payload.as_shm() is not None
                            elif kind == "obstacle_list":
                                rx_obs[m["stamp_us"]] = (t, m["frame_age_ms"])
                            else:
                                health[m["service"]] = m
                except Exception:
                    pass

            threads = [threading.Thread(target=consume, args=(sub, k))
                       for sub, k in zip(subs, ("range_map", "obstacle_list", "health"))]
            for t in threads:
                t.start()
            pub = s.declare_publisher(K.posed_frame(vehicle, "nose"))
            wait_until(lambda: {"locator", "obstacles"} <= set(health), timeout=60, what="services up")
            # the locator subscribes after loading its numba kernels: on a fresh install it compiles them first
            # (minutes on a loaded 2-core machine)
            wait_until(lambda: pub.matching_status.matching, timeout=STARTUP_S, what="locator subscribed")
            time.sleep(0.5)
            # warm-up: a few frames not counted
            sent = []
            period = 1.0 / fps
            t_next = time.monotonic()
            n_total = int(round((seconds + 2.0) * fps))
            cpu_t0 = None
            for i in range(n_total):
                if i == int(2.0 * fps):
                    cpu_t0 = _cpu_seconds(procs), time.monotonic()
                fr = frames[i % len(frames)]
                stamp = time.time_ns() // 1000
                pub.put(schema.encode("posed_frame", camera_id="nose", seq=i, stamp_us=stamp, encoding="mono8", **fr))
                if i >= int(2.0 * fps):
                    sent.append(stamp)
                t_next += period
                dt = t_next - time.monotonic()
                if dt > 0:
                    time.sleep(dt)
            cpu_t1 = _cpu_seconds(procs), time.monotonic()
            time.sleep(1.5)
            with lock:
                maps = {k: v for k, v in rx_map.items() if k in set(sent)}
                obs = {k: v for k, v in rx_obs.items() if k in set(sent)}
            lat_r = [(v[0] - k) / 1e3 for k, v in maps.items()]
            lat_o = [(v[0] - k) / 1e3 for k, v in obs.items()]
            comp = [v[1] * 1e3 for v in maps.values()]
            over = [v[2] * 1e3 for v in maps.values() if math.isfinite(v[2])]
            loc = health.get("locator", {}).get("counters", {})
            scales, runs = {}, []              # maps per scale; the scale's runs in capture order [scale, maps]
            for k in sorted(maps):
                sc = f"{maps[k][3]:g}"
                scales[sc] = scales.get(sc, 0) + 1
                if runs and runs[-1][0] == sc:
                    runs[-1][1] += 1
                else:
                    runs.append([sc, 1])
            obs_h = health.get("obstacles", {})
            res.update(frames_sent=len(sent), range_maps=len(maps), obstacle_lists=len(obs),
                       frames_dropped=len(sent) - len(maps), drop_fraction=(len(sent) - len(maps)) / max(1, len(sent)),
                       throughput_maps_hz=len(maps) / seconds,
                       capture_to_range_ms={"p50": _pct(lat_r, 50), "p99": _pct(lat_r, 99), "max": _pct(lat_r, 100)},
                       capture_to_obstacles_ms={"p50": _pct(lat_o, 50), "p99": _pct(lat_o, 99),
                                                "max": _pct(lat_o, 100)},
                       locate_compute_ms={"p50": _pct(comp, 50), "p99": _pct(comp, 99)},
                       locator_overhead_ms={"p50": _pct(over, 50), "p99": _pct(over, 99)},
                       obstacles_compute_ms=obs_h.get("latency_ms", {}).get("compute", {}),
                       locator_skipped=loc.get("frames_skipped", 0),
                       maps_per_scale=scales, scale_runs=runs, locator_scale_changes=loc.get("scale_changes", 0),
                       locator_scale_probes=loc.get("scale_changes.probe", 0),
                       locator_superseded=loc.get("frames_superseded", 0),
                       obstacles_superseded=obs_h.get("counters", {}).get("maps_superseded", 0),
                       range_map_payloads_via_shm=f"{shm['maps_shm']}/{shm['maps']}",
                       stages=stage_table(health),
                       # per measured frame: ms from capture to [map put, map received, obstacle list put, list
                                       # received], and the map's compute ms (None: no map / no list)
                                       by_frame_ms=[_frame_row(k, maps.get(k), obs.get(k)) for k in sent],
                       cpu_share=_cpu_share(cpu_t0, cpu_t1), load_average=os.getloadavg(),
                       payload_bytes_per_frame=len(schema.encode("posed_frame", camera_id="nose", seq=0, stamp_us=0,
                                                                 encoding="mono8", **frames[0])))
            for sub in subs:
                sub.undeclare()
            for t in threads:
                t.join(5)
    finally:
        codes = []
        for p in procs:
            try:
                codes.append(stop_service(p, signal.SIGINT, timeout=15)[0])
            except AssertionError:
                codes.append(None)
        res["service_exit_codes"] = codes
    return res


def run_bench(cases=DEFAULT_CASES, *, seconds: float = 8.0, method: str = "dense", cv_threads: int = 1,
              stream=None, scale="auto", publish_grid: str = "locate") -> list:
    """Run each (fps, width, height) case; print one line each and return the result dicts."""
    from eonav.app.processes import router_process
    stream = stream or sys.stdout
    print("services: eonav session defaults (zenoh shared memory off, see eonav.bus.session); the bench's own "
          "subscriber is a client of the embedded router", file=stream)
    out = []
    rendered = {}
    with router_process() as ep:
        for k, (fps, w, h) in enumerate(cases):
            if (w, h) not in rendered:
                rendered[(w, h)] = _frames(w, h)
            # a vehicle name per case: no health or subscriber of the previous case's services can be mistaken
            r = bench_case(ep, fps, w, h, seconds, rendered[(w, h)], method=method, cv_threads=cv_threads,
                           vehicle=f"bench{k}", scale=scale, publish_grid=publish_grid)
            out.append(r)
            scales = ", ".join(f"{k}: {n}" for k, n in sorted(r["maps_per_scale"].items(), reverse=True))
            runs = " -> ".join(f"{sc} x{n}" for sc, n in r["scale_runs"])
            print(f"{fps:4.0f} fps {w}x{h} {method} scale {scale} grid {publish_grid} (maps at {scales or '-'}; "
                  f"{r['locator_scale_changes']} changes, {r['locator_scale_probes']} of them probes"
                  f"{': ' + runs if len(r['scale_runs']) > 1 else ''}): capture->range p50 "
                  f"{r['capture_to_range_ms']['p50']:.0f} ms "
                  f"p99 {r['capture_to_range_ms']['p99']:.0f} ms | capture->obstacles p50 "
                  f"{r['capture_to_obstacles_ms']['p50']:.0f} ms p99 {r['capture_to_obstacles_ms']['p99']:.0f} ms | "
                  f"{r['throughput_maps_hz']:.1f} maps/s, dropped {r['frames_dropped']}/{r['frames_sent']} (latest "
                  f"frame wins: locator skipped {r['locator_skipped']}, superseded {r['locator_superseded']}; "
                  f"obstacles superseded {r['obstacles_superseded']}) | "
                  f"compute p50 {r['locate_compute_ms']['p50']:.0f} ms, locator overhead p50 "
                  f"{r['locator_overhead_ms']['p50']:.1f} ms, obstacles p50 "
                  f"{r['obstacles_compute_ms'].get('p50', math.nan):.1f} ms | shm {r['range_map_payloads_via_shm']}",
                  file=stream, flush=True)
            print_stages(r, stream)
    return out


def print_stages(r: dict, stream) -> None:
    """The per-stage lines of one case: ages, stage durations (wall and CPU), CPU share per process."""
    load = " / ".join(f"{x:.2f}" for x in r["load_average"])
    print(f"    per stage, p50 / p99 ms (services' health windows; load average {load} at the end):", file=stream)
    for label, v in r["stages"].items():
        print(f"      {label:44s} {v['p50']:7.1f} {v['p99']:7.1f}  (n {v['n']})", file=stream)
    share = ", ".join(f"{k} {100 * v:.0f} %" for k, v in r["cpu_share"].items())
    print(f"    CPU over the measured seconds (share of one core): {share}", file=stream, flush=True)


def accuracy(size=(640, 480), scales=(1.0, 0.5), n_frames: int = 5, rate_hz: float = 10.0, method: str = "dense",
             stream=None, publish_grid: str = "locate") -> list:
    """What the locator's ``--scale`` costs, in process, against the simulator's truth: consecutive frames of the
    approach flight (the bench's frames) ranged through the locator's own code path (``frame_info`` at the scale,
    locate, ``map_fields`` for ``publish_grid``), scored on the grid of the map that would be published (its own
    camera's: the truth sampled at its pixel centres, ``eonav.camera.on_grid``): median |relative range error| and
    coverage of confident pixels, and the obstacle list's nearest distance (the obstacle service's ``analyse_msg``)
    against the one from the true full-resolution range map."""
    import cv2
    from eonav.services.locator import CameraCache, frame_info, map_fields
    from eonav.services.obstacles import analyse_msg
    from eonav.obstacles import detect as ob
    from eonav.geometry.camera import on_grid
    from eonav.bus import schema
    from eonav.geometry.camera import View
    from eonav.geometry.frames import quat_wxyz_from_rotation
    from eonav.ranging.locate import locate
    from eonav.ranging.rangemap import VALID
    from eonav.sim.flight import render_flight
    cv2.setNumThreads(1)
    stream = stream or sys.stdout
    w, h = size
    rendered = list(render_flight("approach", n_frames=n_frames, rate_hz=rate_hz, size=(w, h), t0_s=2.5,
                                  supersample=1))
    msgs = [schema.decode(schema.encode("posed_frame", camera_id="nose", seq=i, stamp_us=int(t * 1e6) + 1,
                                        encoding="mono8",
                                        image=np.clip(np.round(v.image), 0, 255).astype(np.uint8),
                                        camera=schema.camera_to_msg(v.camera), position_ned_m=v.state.position_ned_m,
                                        q_wxyz=quat_wxyz_from_rotation(v.state.T_body_ned.T)))
            for i, (t, v, _) in enumerate(rendered)]
    cfg = ob.ObstacleConfig(ground_down_m=0.0)
    out = []
    for scale in scales:
        cams = CameraCache(scale)
        infos = [frame_info(m, cams) for m in msgs]
        errs, cover, near_err, t_loc = [], [], [], []
        for i in range(1, len(infos)):
            a, b = infos[i], infos[i - 1]
            t0 = time.perf_counter()
            res = locate(View(a.payload["camera"], a.state, a.payload["image"]),
                         View(b.payload["camera"], b.state, b.payload["image"]), method=method)
            t_loc.append(time.perf_counter() - t0)
            m = map_fields(res, a, a.payload["camera"], "f16", publish_grid)
            r, fl = m["range_m"], m["flags"]
            truth = on_grid(rendered[i][2].range_m, r.shape[1], r.shape[0])
            ok = ((fl & VALID) != 0) & np.isfinite(r) & np.isfinite(truth)
            errs.append(float(np.median(np.abs(r[ok] - truth[ok]) / truth[ok])))
            cover.append(float(ok.mean()))
            est = analyse_msg(ob, m, schema.camera_from_msg(m["camera"]), a.state, cfg)
            tru = ob.analyse(rendered[i][2].range_m.astype(np.float32), a.camera, a.state, cfg=cfg)
            if est.obstacles and tru.obstacles:
                near_err.append(est.obstacles[0].distance_m / tru.obstacles[0].distance_m - 1.0)
        row = {"width": w, "height": h, "scale": scale, "median_rel_error": float(np.median(errs)),
               "worst_map_median_rel_error": float(np.max(errs)), "coverage": float(np.mean(cover)),
               "nearest_obstacle_rel_error": [round(x, 4) for x in near_err],
               "locate_ms_p50": 1e3 * float(np.median(t_loc))}
        out.append(row)
        print(f"{w}x{h} scale {scale:g}: median |rel range error| {100 * row['median_rel_error']:.2f} % (worst map "
              f"{100 * row['worst_map_median_rel_error']:.2f} %), coverage {100 * row['coverage']:.1f} %, nearest "
              f"obstacle vs truth {[f'{100 * x:+.1f} %' for x in near_err]}, locate p50 {row['locate_ms_p50']:.0f} ms",
              file=stream, flush=True)
    return out


def fusion_time(size=(640, 480), scales=(1.0, 0.5, 0.3), n_frames: int = 12, repeats: int = 4, stream=None) -> list:
    """What fusion adds to the locator's time per frame, in process: the approach flight's frames at each locate
    scale pushed through two ``FusionRunner``s in turn, predict before the measurements and beside them
    (``FusionConfig.overlap_predict`` off / on), and the plain dense locate (with its fill) of each frame's pair.
    Per frame the least of ``repeats`` runs (wall and CPU time of this process), mean over frames 2 on: the ratios
    to the plain locate. The maps of the two runners are checked to be the same. Wall time shows what the second
    core does only where the machine has one to spare."""
    import cv2
    from eonav.fusion.sequence import FusionConfig, FusionRunner, frame, prepare_kernels
    from eonav.geometry.camera import View, scaled_camera
    from eonav.ranging.methods.dense import locate_dense
    from eonav.sim.flight import render_flight
    cv2.setNumThreads(1)
    prepare_kernels()
    stream = stream or sys.stdout
    w, h = size
    rendered = [(np.clip(np.round(v.image), 0, 255).astype(np.float32), v) for _, v, _ in
                render_flight("approach", n_frames=n_frames, rate_hz=30.0, size=(w, h), t0_s=2.5, supersample=1)]
    out = []
    for scale in scales:
        views = []
        for img, v in rendered:
            cam = v.camera if scale == 1.0 else scaled_camera(v.camera, scale)
            views.append(View(cam, v.state, img if scale == 1.0 else
                              cv2.resize(img, (cam.width, cam.height), interpolation=cv2.INTER_AREA)))
        best: dict = {}
        for r in range(repeats):
            runners = {"serial": FusionRunner(FusionConfig(overlap_predict=False)),
                       "beside": FusionRunner(FusionConfig(overlap_predict=True))}
            for k, v in enumerate(views):
                f = frame("nose", v, int(round(v.state.t_s * 1e6)), seq=k)
                maps = {}
                for name in (("serial", "beside") if (k + r) % 2 else ("beside", "serial")):
                    w0, c0 = time.perf_counter(), time.process_time()
                    maps[name] = runners[name].push(f)
                    _least(best.setdefault(k, {}), name, time.perf_counter() - w0, time.process_time() - c0)
                for a, b in zip(maps["serial"], maps["beside"]):
                    if not all(np.array_equal(getattr(a.result, x), getattr(b.result, x), equal_nan=True)
                               for x in ("range_m", "inv_range_std_per_m", "flags")):
                        raise AssertionError(f"scale {scale:g} frame {k}: predict beside changed the fused map")
                if maps["beside"] and maps["beside"][0].measurements:
                    other = maps["beside"][0].measurements[0]["other_seq"]
                    w0, c0 = time.perf_counter(), time.process_time()
                    locate_dense(v, views[other])
                    _least(best[k], "plain", time.perf_counter() - w0, time.process_time() - c0)
        rows = [b for k, b in best.items() if k >= 2 and "plain" in b]
        if not rows:
            print(f"{views[0].camera.width}x{views[0].camera.height} (scale {scale:g}): no frame from the third on had "
                  "a pair (too little parallax)", file=stream, flush=True)
            continue
        row = {"width": views[0].camera.width, "height": views[0].camera.height, "scale": scale, "frames": len(rows),
               **{f"{name}_{kind}_ms": 1e3 * float(np.mean([b[name][j] for b in rows]))
                  for name in ("plain", "serial", "beside") for j, kind in enumerate(("wall", "cpu"))}}
        out.append(row)
        pl_w, pl_c = row["plain_wall_ms"], row["plain_cpu_ms"]
        small = row["width"] * row["height"] < FusionConfig().overlap_min_cells
        note = " (in turn too: a state under overlap_min_cells)" if small else ""
        print(f"{row['width']}x{row['height']} (scale {scale:g}, {len(rows)} frames, least of {repeats}): plain locate "
              f"{pl_w:.1f} ms wall / {pl_c:.1f} ms CPU; push, predict in turn: {row['serial_wall_ms'] / pl_w:.3f} / "
              f"{row['serial_cpu_ms'] / pl_c:.3f} x plain (wall / CPU); predict beside{note}: "
              f"{row['beside_wall_ms'] / pl_w:.3f} / {row['beside_cpu_ms'] / pl_c:.3f} x plain; the same maps",
              file=stream, flush=True)
    return out


def _least(d: dict, name: str, wall_s: float, cpu_s: float) -> None:
    """Keep the least wall and the least CPU time seen of ``name`` in ``d``."""
    old = d.get(name, (math.inf, math.inf))
    d[name] = (min(old[0], wall_s), min(old[1], cpu_s))


def add_arguments(p) -> None:
    p.add_argument("--case", action="append", default=[], metavar="FPS@WxH",
                   help="a case, e.g. 30@640x480 (repeatable; default: 30@640x480 30@512x512 15@640x480 15@512x512)")
    p.add_argument("--seconds", type=float, default=8.0, help="measured seconds per case (after 2 s warm-up)")
    p.add_argument("--methods", default="dense,dis",
                   help="locator methods, each over every case in the same run (default dense,dis: DIS is the "
                        "OpenCV optical-flow baseline)")
    p.add_argument("--cv-threads", type=int, default=1, metavar="N",
                   help="the locator's OpenCV threads (its --cv-threads; default 1: one core)")
    p.add_argument("--scale", default="auto",
                   help="locator --scale: auto (default, adaptive) or a number (1: full, 0.5: half-resolution locate)")
    p.add_argument("--publish-grid", default="locate", choices=("locate", "frame"),
                   help="locator --publish-grid: range maps on the locate grid (default) or upsampled to the frame's")
    p.add_argument("--accuracy", action="store_true",
                   help="instead of the pipeline: range error, coverage and nearest obstacle vs simulator truth at "
                        "scales 1 and 0.5 (in process, the locator's code path) for each case's image size")
    p.add_argument("--fusion-time", action="store_true",
                   help="instead of the pipeline: what fusion adds to the locator's time per frame, in process, at "
                        "locate scales 1, 0.5 and 0.3 of each case's image size, predict before and beside the "
                        "measurements (wall and CPU time against a plain dense locate)")
    p.add_argument("--json", action="store_true", help="print the results as JSON at the end")


def parse_case(s: str):
    from eonav import InputError
    try:
        fps, size = s.split("@")
        w, h = size.lower().split("x")
        return float(fps), int(w), int(h)
    except ValueError:
        raise InputError(f"--case {s!r}: expected FPS@WIDTHxHEIGHT, e.g. 30@640x480") from None


def run(args) -> int:
    cases = [parse_case(c) for c in args.case] or list(DEFAULT_CASES)
    methods = [m for m in args.methods.split(",") if m]
    from eonav.ranging.scale_control import parse_scale
    fixed = parse_scale(args.scale)              # None: auto; InputError on anything else
    scale = "auto" if fixed is None else fixed
    if args.fusion_time:
        sizes = list(dict.fromkeys((w, h) for _, w, h in cases))
        res = [r for size in sizes for r in fusion_time(size)]
    elif args.accuracy:
        sizes = list(dict.fromkeys((w, h) for _, w, h in cases))
        res = [r for m in methods for size in sizes
               for r in accuracy(size, scales=sorted({1.0, fixed or 1.0, 0.5}, reverse=True), method=m,
                                 publish_grid=args.publish_grid)]
    else:
        # every method in the same run: the OpenCV DIS baseline ("dis") beside the default ("dense")
        res = [r for m in methods for r in run_bench(cases, seconds=args.seconds, method=m,
                                                      cv_threads=args.cv_threads, scale=scale,
                                                      publish_grid=args.publish_grid)]
    if args.json:
        print(json.dumps(res))
    return 0


if __name__ == "__main__":
    import argparse
    ap = argparse.ArgumentParser(prog="python -m eonav.app.bench_pipeline")
    add_arguments(ap)
    logging.basicConfig(level=logging.WARNING)
    sys.exit(run(ap.parse_args()))
