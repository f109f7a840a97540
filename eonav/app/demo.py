"""``eonav run`` with no source: the newcomer's end-to-end demo on one machine.

Records a simulated flight (``eonav.sim.record``: frames, MAVLink tlog, cameras, ground truth; cached per user under
``$XDG_CACHE_HOME/eonav/demo`` or ``~/.cache/eonav/demo``, keyed by its parameters), runs the whole pipeline on it
through ``eonav.app.launcher.run_pipeline``, scores what arrives on the bus against the truth (:class:`Monitor`,
:class:`Truth`, reused by ``tests/test_pipeline_e2e.py``), prints a summary (range error, coverage, obstacles against
the true nearest box, latency, drops, and the verdict: ``ok``, ``degraded`` when frames or maps were lost beyond
:data:`MIN_FRACTION`, ``failed``) and writes the picture of the last range map beside its truth. From the command
line every run gets its own folder, ``eonav-demo-<date>-<time>`` in the working directory (or ``--out DIR``), with
the picture (``range.png``), the summary (``summary.json``) and the services' logs (``logs/``).

The replays start once the sync, locator and obstacle services are alive, and both get the same
``--replay-shift-us`` (then + a start-up lead - the recording's first stamp), so no frame is lost to a service still
starting, camera and navigation stay aligned to the microsecond and the latency figures (now - stamp) are real.
"""
from __future__ import annotations

import json
import logging
import math
import os
import shutil
import sys
import tempfile
import threading
import time
from pathlib import Path

import numpy as np

from eonav.app.sources import DEFAULT_START_IN_S
from eonav.geometry.camera import on_grid

log = logging.getLogger("eonav.app.demo")

DEFAULT_FLIGHT = "approach"
DEFAULT_FRAMES = 16
DEFAULT_RATE_HZ = 5.0
DEFAULT_SIZE = 256
# Navigation runs before the camera, as on a vehicle: the MAVLink ingest needs 2 s of autopilot time to lock its
# clock-offset estimate before it publishes, so the recording starts the frames 3 s into the flight.
NAV_LEAD_S = 3.0
# The verdict: a run is "degraded" when fewer than this fraction of the recorded frames reached the bus, or of the
# frames that can have a range map (all but the first: it has no earlier frame to pair with) got one.
MIN_FRACTION = 0.8
PICTURE_BOXES = 6             # the picture boxes the nearest obstacles of the list (all of them clutter it)


def default_cache_dir() -> Path:
    """This user's cache of demo recordings: ``$XDG_CACHE_HOME/eonav/demo``, else ``~/.cache/eonav/demo``."""
    xdg = os.environ.get("XDG_CACHE_HOME")
    base = Path(xdg) if xdg and Path(xdg).is_absolute() else Path.home() / ".cache"
    return base / "eonav" / "demo"


def new_run_dir(out_dir=None) -> Path:
    """A fresh folder for one demo run, ``eonav-demo-<YYYYmmdd-HHMMSS>[-N]`` in ``out_dir`` (default: the working
    directory); never one another run uses."""
    base = Path(out_dir) if out_dir else Path.cwd()
    base.mkdir(parents=True, exist_ok=True)
    stem = "eonav-demo-" + time.strftime("%Y%m%d-%H%M%S")
    for n in range(1, 1000):
        d = base / (stem if n == 1 else f"{stem}-{n}")
        try:
            d.mkdir()
            return d
        except FileExistsError:
            continue
    raise RuntimeError(f"no free run folder {stem}-N in {base}")


# --------------------------------------------------------------------------------------------------
# recording + truth

def recording(flight: str = DEFAULT_FLIGHT, n_frames: int = DEFAULT_FRAMES, rate_hz: float = DEFAULT_RATE_HZ,
              size: int = DEFAULT_SIZE, seed: int = 0, cache_dir=None) -> Path:
    """A recorded simulated flight, rendered once and cached (keyed by its parameters) in ``cache_dir`` (default:
    :func:`default_cache_dir`, this user's)."""
    from eonav.sim.record import record_flight
    base = Path(cache_dir) if cache_dir else default_cache_dir()
    out = base / f"{flight}_n{n_frames}_r{rate_hz:g}_{size}px_s{seed}_lead{NAV_LEAD_S:g}"
    if (out / "manifest.json").is_file():
        return out
    base.mkdir(parents=True, exist_ok=True)
    tmp = Path(tempfile.mkdtemp(prefix=out.name + ".", dir=base))
    log.info("recording simulated flight %s (%d frames, %dx%d) into %s", flight, n_frames, size, size, out)
    record_flight(tmp, name=flight, n_frames=n_frames, rate_hz=rate_hz, size=(size, size), seed=seed,
                  frames_start_s=NAV_LEAD_S)
    try:
        tmp.rename(out)
    except OSError:                       # another run finished first: use theirs
        shutil.rmtree(tmp, ignore_errors=True)
    return out


class Truth:
    """Ground truth of a recording: per-frame range (x_c) and pose, and the scene's boxes."""

    def __init__(self, rec_dir, shift_us: int = 0):
        """``shift_us``: the replay shift (bus stamp = recorded stamp + shift_us)."""
        from eonav.sim.flight import flight
        from eonav.sim.scene import FIRST_BOX_ID
        self.dir = Path(rec_dir)
        self.manifest = json.loads((self.dir / "manifest.json").read_text())
        z = np.load(self.dir / "truth.npz")
        self.recorded_stamp_us = z["stamp_us"].astype(np.int64)
        self.stamp_us = self.recorded_stamp_us + int(shift_us)
        self.range_m = z["range_m"]
        self.object_id = z["object_id"]
        self.position_ned_m = z["position_ned_m"]
        self.scene = flight(self.manifest["flight"]).scene
        self.box_ids = {FIRST_BOX_ID + i: b for i, b in enumerate(self.scene.boxes)}
        self.camera_id = self.manifest["camera_id"]

    def set_shift(self, shift_us: int) -> None:
        """The replay shift, once it is known (it is computed when the replays start)."""
        self.stamp_us = self.recorded_stamp_us + int(shift_us)

    def index(self, stamp_us: int) -> int | None:
        i = int(np.argmin(np.abs(self.stamp_us - int(stamp_us))))
        return i if abs(int(self.stamp_us[i]) - int(stamp_us)) <= 2 else None

    @staticmethod
    def box_distance(box, p_ned) -> float:
        """Distance from p to the solid box (clamped in the box frame)."""
        local = box.R_ned_local.T @ (np.asarray(p_ned, float) - np.asarray(box.center_ned_m))
        return float(np.linalg.norm(local - np.clip(local, -box.half_m, box.half_m)))

    def nearest_box(self, i: int, min_pixels: int = 50):
        """(name, distance_m, bearing_deg of its centre from the vehicle, relative to north) of the nearest box
        visible in frame i with at least ``min_pixels`` pixels; None if none."""
        ids, counts = np.unique(self.object_id[i], return_counts=True)
        best = None
        for oid, n in zip(ids, counts):
            box = self.box_ids.get(int(oid))
            if box is None or n < min_pixels:
                continue
            d = self.box_distance(box, self.position_ned_m[i])
            if best is None or d < best[1]:
                c = np.asarray(box.center_ned_m) - self.position_ned_m[i]
                best = (box.name, d, math.degrees(math.atan2(c[1], c[0])))
        return best


# --------------------------------------------------------------------------------------------------
# monitor

def _pct(v, q):
    return float(np.percentile(v, q)) if len(v) else math.nan


def _under(counters: dict, prefix: str) -> dict:
    """The health counters named ``prefix<rest>``, keyed by ``rest``."""
    return {k[len(prefix):]: v for k, v in counters.items() if k.startswith(prefix)}


class Monitor:
    """Watches frames, range maps, obstacle lists and health on the bus and scores them against ``truth``.

    Use as a context manager around the pipeline run: ``with Monitor(endpoint, vehicle, truth) as m: ...``."""

    def __init__(self, endpoint: str, vehicle: str, truth: Truth, bearing_tol_deg: float = 3.0,
                 zenoh_config: str | None = None):
        self.endpoint, self.vehicle, self.truth, self.bearing_tol_deg = endpoint, vehicle, truth, bearing_tol_deg
        self.zenoh_config = zenoh_config              # a session config (the operator's credentials under ACL)
        self.lock = threading.Lock()
        self.frame_rx: dict[int, float] = {}          # stamp_us -> monotonic receive time
        self.range_rx: dict[int, float] = {}
        self.obst_rx: dict[int, float] = {}
        self.range_scores: list[dict] = []
        self.obst_scores: list[dict] = []
        self.health: dict[str, dict] = {}
        self.health_states: dict[str, set] = {}      # every state each service reported
        self.health_log: list[tuple] = []            # (monotonic receive time, service, state, detail)
        self.last_range = None
        self.obstacles_at: dict[int, list] = {}      # stamp_us -> obstacles of the latest lists
        self.bad_messages = 0
        self._session = None
        self._subs, self._threads = [], []

    def __enter__(self):
        from eonav.bus import keys as K
        from eonav.bus.session import client_session, consume_in_threads
        self._session = client_session(self.endpoint, self.zenoh_config)
        self._subs, self._threads = consume_in_threads(
            self._session, ((K.frames_all(self.vehicle), 256, self._on_frame),
                            (K.range_maps_all(self.vehicle), 64, self._on_range),
                            (K.obstacles(self.vehicle), 256, self._on_obstacles),
                            (K.health_all(self.vehicle), 1024, self._on_health)),
            name="monitor", on_error=self._bad)
        return self

    def __exit__(self, *exc):
        from eonav.bus.session import close_subscribers
        close_subscribers(self._subs, self._threads, self._session, 10.0)

    def _bad(self, sample, e):
        """A malformed message is counted; the monitor keeps going."""
        with self.lock:
            self.bad_messages += 1
        log.warning("monitor: %s on %s: %s", type(e).__name__, sample.key_expr, e)

    def _on_frame(self, sample, t):
        import msgpack
        # only the stamp is needed: read it without unpacking the image array
        doc = msgpack.unpackb(sample.payload.to_bytes(), raw=False)
        with self.lock:
            self.frame_rx.setdefault(int(doc["stamp_us"]), t)

    def _on_range(self, sample, t):
        from eonav.bus import schema
        from eonav.ranging.rangemap import VALID
        m = schema.decode(sample.payload.to_bytes(), expect="range_map")
        st = int(m["stamp_us"])
        i = self.truth.index(st)
        score = {"stamp_us": st, "seq": m["seq"], "frame": i, "compute_s": m["compute_s"],
                 "baseline_m": m["baseline_m"]}
        if i is not None:
            r = m["range_m"]
            # the map is on its camera's grid (the locate scale by default): the truth at its pixel centres
            gt = on_grid(self.truth.range_m[i], r.shape[1], r.shape[0]).astype(np.float32)
            valid = np.isfinite(r) & (r > 0)
            if m["flags"] is not None:
                valid &= (m["flags"] & VALID) != 0
            ok = valid & np.isfinite(gt)
            rel = np.abs(r[ok] - gt[ok]) / gt[ok]
            score.update(median_rel_error=float(np.median(rel)) if rel.size else math.nan,
                         p90_rel_error=_pct(rel, 90), coverage=float(valid.mean()), n_valid=int(valid.sum()))
        with self.lock:
            self.range_rx.setdefault(st, t)
            self.range_scores.append(score)
            self.last_range = (m, i)

    def _on_obstacles(self, sample, t):
        from eonav.bus import schema
        m = schema.decode(sample.payload.to_bytes(), expect="obstacle_list")
        st = int(m["stamp_us"])
        i = self.truth.index(st)
        score = {"stamp_us": st, "frame": i, "n_obstacles": len(m["obstacles"])}
        if i is not None:
            nb = self.truth.nearest_box(i)
            if nb is not None:
                name, dist, bearing_ned = nb
                yaw = _yaw_deg(m["q_wxyz"])
                bearing = (bearing_ned - yaw + 180.0) % 360.0 - 180.0
                match = [o for o in m["obstacles"] if abs(o["bearing_deg"] - bearing) <= self.bearing_tol_deg]
                score.update(truth_box=name, truth_distance_m=dist, truth_bearing_deg=bearing,
                             found=bool(match),
                             distance_m=match[0]["distance_m"] if match else math.nan,
                             rel_error=(abs(match[0]["distance_m"] - dist) / dist) if match else math.nan,
                             obstacle_id=match[0]["id"] if match else None)
        with self.lock:
            self.obst_rx.setdefault(st, t)
            self.obst_scores.append(score)
            self.obstacles_at[st] = m["obstacles"]
            while len(self.obstacles_at) > 8:
                self.obstacles_at.pop(next(iter(self.obstacles_at)))

    def _on_health(self, sample, t):
        from eonav.bus import schema
        m = schema.decode(sample.payload.to_bytes(), expect="health")
        with self.lock:
            self.health[m["service"]] = m
            self.health_states.setdefault(m["service"], set()).add(m["state"])
            self.health_log.append((t, m["service"], m["state"], m["detail"]))

    # ---- results ------------------------------------------------------------------------------
    def counts(self) -> dict:
        with self.lock:
            return {"frames": len(self.frame_rx), "range_maps": len(self.range_scores),
                    "obstacle_lists": len(self.obst_scores)}

    def summary(self) -> dict:
        with self.lock:
            rs, os_, h = list(self.range_scores), list(self.obst_scores), dict(self.health)
            lat_r = [self.range_rx[s] - self.frame_rx[s] for s in self.range_rx if s in self.frame_rx]
            lat_o = [self.obst_rx[s] - self.frame_rx[s] for s in self.obst_rx if s in self.frame_rx]
            n_frames = len(self.frame_rx)
            last_frame = max(self.frame_rx.values(), default=math.inf)
            # a service may report a silent input once the replay has ended, never while frames still come
            not_ok_fed = sorted({f"{svc} {state}: {detail}" for t, svc, state, detail in self.health_log
                                 if state != "ok" and t <= last_frame})
        errs = [s["median_rel_error"] for s in rs if np.isfinite(s.get("median_rel_error", math.nan))]
        cov = [s["coverage"] for s in rs if "coverage" in s]
        with_truth = [s for s in os_ if "truth_box" in s]
        found = [s for s in with_truth if s["found"]]
        n_expected = self.truth.manifest["n_frames"]
        loc = h.get("locator", {}).get("counters", {})
        sync = h.get("sync", {}).get("counters", {})
        return {
            "frames_recorded": n_expected, "frames_seen": n_frames, "range_maps": len(rs),
            "obstacle_lists": len(os_),
            "median_rel_error": float(np.median(errs)) if errs else math.nan,
            "worst_map_median_rel_error": float(np.max(errs)) if errs else math.nan,
            "coverage": float(np.mean(cov)) if cov else math.nan,
            "nearest_box_found": f"{len(found)}/{len(with_truth)}",
            "nearest_box_found_fraction": len(found) / len(with_truth) if with_truth else math.nan,
            "nearest_box_median_rel_error": float(np.median([s["rel_error"] for s in found])) if found else math.nan,
            "nearest_box": with_truth[-1]["truth_box"] if with_truth else None,
            "latency_capture_to_range_ms": {"p50": 1e3 * _pct(lat_r, 50), "p99": 1e3 * _pct(lat_r, 99),
                                            "n": len(lat_r)},
            "latency_capture_to_obstacles_ms": {"p50": 1e3 * _pct(lat_o, 50), "p99": 1e3 * _pct(lat_o, 99),
                                                "n": len(lat_o)},
            "compute_ms_p50": 1e3 * _pct([s["compute_s"] for s in rs], 50),
            "drops": {"frames_not_seen": max(0, n_expected - n_frames),
                      "frames_without_range_map": max(0, n_expected - 1 - len(rs)),
                      "locator_frames_skipped": loc.get("frames_skipped", 0),
                      "locator_frames_superseded": loc.get("frames_superseded", 0),
                      "locator_dropped": _under(loc, "dropped."),
                      "locator_skipped": _under(loc, "skipped."),
                      "locator_fusion_no_pair": {k: v for k, v in _under(loc, "fusion.policy.").items()
                                                 if k not in ("motion", "stereo", "ok")},
                      "sync_dropped": _under(sync, "dropped.")},
            "health": {k: v["state"] for k, v in h.items()},
            "health_states_seen": {k: sorted(v) for k, v in self.health_states.items()},
            "health_not_ok_while_fed": not_ok_fed,
            "bad_messages": self.bad_messages,
        }


def _yaw_deg(q_wxyz) -> float:
    from eonav.geometry.frames import T_body_ned_from_quat, ypr_from_T_body_ned
    return math.degrees(ypr_from_T_body_ned(T_body_ned_from_quat(q_wxyz))[0])


def range_picture(msg: dict, truth_range=None, obstacles=(), near_m: float = 5.0,
                  max_range_m: float = 150.0, max_boxes: int = PICTURE_BOXES) -> np.ndarray:
    """BGR picture of range map message ``msg``: the estimate (VALID pixels; black = no estimate) and the truth beside
    it on one colour scale from ``near_m`` (red) to ``max_range_m`` (blue), a colour bar in metres, and the
    ``max_boxes`` nearest ``obstacles`` (an obstacle list's, ``bbox_px`` in frame pixels) boxed with their distance
    (``eonav.io.viz.estimate_truth_picture``)."""
    from eonav.ranging.rangemap import VALID
    from eonav.io.viz import estimate_truth_picture

    r = np.asarray(msg["range_m"], np.float32)
    valid = np.isfinite(r) & (r > 0) & (r < max_range_m)
    if msg.get("flags") is not None:
        valid &= (msg["flags"] & VALID) != 0
    fw, fh = int(msg.get("frame_width") or 0), int(msg.get("frame_height") or 0)
    frame_size = (fw, fh) if fw > 0 and fh > 0 else None
    nearest = sorted(obstacles, key=lambda o: float(o["distance_m"]))[:max_boxes]
    pic, _ = estimate_truth_picture(r, valid, truth_range, obstacles=nearest, frame_size=frame_size,
                                    near_m=near_m, far_m=max_range_m)
    return pic


def verdict(frames_recorded: int, frames_seen: int, range_maps: int) -> tuple[str, list[str]]:
    """``("ok", [])``, or ``("degraded", reasons)`` when fewer than :data:`MIN_FRACTION` of the recorded frames were
    seen on the bus or of the frames that can have a range map (all but the first) got one."""
    reasons = []
    if frames_seen < MIN_FRACTION * frames_recorded:
        reasons.append(f"{frames_seen}/{frames_recorded} frames seen (fewer than {MIN_FRACTION:.0%})")
    rangeable = max(frames_recorded - 1, 1)
    if range_maps < MIN_FRACTION * rangeable:
        reasons.append(f"{range_maps} range maps for {rangeable} frames that can have one "
                       f"(fewer than {MIN_FRACTION:.0%})")
    return ("degraded" if reasons else "ok"), reasons


def outcome(summary: dict, pipeline_exit: int | None, stop_reason: str) -> dict:
    """``verdict`` (``ok`` / ``degraded`` / ``failed``: the pipeline exited non-zero, ranged nothing, timed out or
    was interrupted), ``verdict_reasons`` and ``exit_code`` (0 only for ``ok``) of a run's summary."""
    state, reasons = verdict(summary["frames_recorded"], summary["frames_seen"], summary["range_maps"])
    if (pipeline_exit != 0 or summary["range_maps"] == 0 or stop_reason == "interrupted"
            or stop_reason.startswith("timeout")):
        state = "failed"
        reasons = [f"pipeline exit {pipeline_exit}, {summary['range_maps']} range maps, stopped: {stop_reason}"
                   ] + reasons
    return {"verdict": state, "verdict_reasons": reasons, "exit_code": 0 if state == "ok" else 1}


# --------------------------------------------------------------------------------------------------
# the pipeline

def recording_start_us(rec_dir) -> int:
    """The first stamp of a recording: the earlier of its first frame stamp and its first tlog record."""
    import struct
    rec = Path(rec_dir)
    man = json.loads((rec / "manifest.json").read_text())
    first_frame_us = round(float((rec / man["timestamps"]).read_text().split()[0]) * 1e6)
    with open(rec / man["tlog"], "rb") as f:
        first_tlog_us = struct.unpack(">Q", f.read(8))[0]
    return min(first_frame_us, first_tlog_us)


def replay_shift_us(rec_dir, start_in_s: float = 4.0) -> int:
    """The shift that replays the recording's first record ``start_in_s`` from now (process start-up time)."""
    return time.time_ns() // 1000 + int(start_in_s * 1e6) - recording_start_us(rec_dir)


def pipeline_spec(rec_dir, shift_us: int, *, method: str = "dense", cv_threads: int = 1,
                  mavlink_out: str | None = None) -> dict:
    """The demo pipeline: replays of the recording (both shifted by ``shift_us``) + sync, locator, obstacles.
    ``shift_us`` = ``"{replay_shift_us}"`` (a substitution of ``run_pipeline``): the replays start once the other
    services are alive, with the shift computed then."""
    rec = Path(rec_dir).resolve()
    man = json.loads((rec / "manifest.json").read_text())
    staged = isinstance(shift_us, str) and shift_us.startswith("{")
    shift_us = shift_us if staged else str(int(shift_us))
    after = {"after": ["sync", "locator", "obstacles"]} if staged else {}
    obst = ["--ground-down-m", "0",                     # local NED origin at the take-off (ground) level
            "--max-obstacle-distance-m", "150"]
    if mavlink_out:
        obst += ["--mavlink-out", mavlink_out]
    # the replays are restarted like any service: with the shared shift a restarted replay resumes at the record
    # the clock says is due, so nothing older than that reaches the pipeline (docs/bus.md, Staleness)
    return {"services": [
        {"name": "camera", "module": "camera_ingest", **after,
         "args": ["--source", str(rec / man["frames"]), "--camera-id", man["camera_id"],
                  "--replay-shift-us", shift_us]},
        {"name": "mavlink", "module": "mavlink_ingest", **after,
         # --origin: the recording's local NED origin (take-off point on the ground), not the first GPS fix, so that
         # positions match the truth and the ground is at down = 0
         "args": ["--source", str(rec / man["tlog"]), "--replay-shift-us", shift_us,
                  "--origin", ",".join(str(x) for x in man["origin_lla"])]},
        {"name": "sync", "module": "sync", "args": ["--cameras", str(rec / man["cameras"])]},
        {"name": "locator", "module": "locator", "args": ["--method", method, "--cv-threads", str(cv_threads)]},
        {"name": "obstacles", "module": "obstacles", "args": obst},
    ]}


def run_demo(*, flight: str = DEFAULT_FLIGHT, n_frames: int = DEFAULT_FRAMES, rate_hz: float = DEFAULT_RATE_HZ,
             size: int = DEFAULT_SIZE, seed: int = 0, cache_dir=None, png=None, vehicle: str = "demo",
             method: str = "dense", mavlink_out: str | None = None, timeout_s: float = 180.0,
             drain_s: float = 3.0, quiet: bool = False, log_dir=None, stream=None, record=None,
             acl_dir=None) -> dict:
    """Record (cached), run the pipeline, score it; returns the summary dict (``summary["exit_code"]``).
    ``acl_dir``: under access control (``run_pipeline``); the monitor connects as the operator."""
    from eonav.app.processes import free_port
    from eonav.app.launcher import run_pipeline
    stream = stream or sys.stdout
    rec = recording(flight, n_frames, rate_hz, size, seed, cache_dir)
    if method == "dense":
        # the locator compiles its numba kernels (or loads them from numba's cache, ~2 s) before it subscribes, and
        # the replays wait for it: on a fresh install ~15-25 s. Compiled here first (the cache is shared) with a word
        # to the newcomer, the locator only loads them.
        from eonav.fusion.sequence import prepare_kernels
        t = time.monotonic()
        if not quiet:
            print("eonav demo: preparing the dense locator's kernels (compiled once per install)", file=stream,
                  flush=True)
        prepare_kernels()
        if not quiet:
            print(f"eonav demo: kernels ready in {time.monotonic() - t:.1f} s", file=stream, flush=True)
    truth = Truth(rec)
    shift = {}

    def shift_now() -> int:            # called when the replays start (the other services alive)
        shift["us"] = replay_shift_us(rec, start_in_s=DEFAULT_START_IN_S)
        truth.set_shift(shift["us"])
        return shift["us"]
    port = free_port()
    endpoint = f"tcp/127.0.0.1:{port}"
    stop = threading.Event()
    status: dict = {}
    result = {"code": None}

    def on_status(st):
        status.update(st)

    def pipeline():
        spec = pipeline_spec(rec, "{replay_shift_us}", method=method, mavlink_out=mavlink_out)
        result["code"] = run_pipeline(spec, vehicle=vehicle, port=port, on_status=on_status, stop_event=stop,
                                      quiet=quiet, log_dir=log_dir, record=record, acl_dir=acl_dir,
                                      substitutions={"replay_shift_us": shift_now})

    th = threading.Thread(target=pipeline, name="pipeline")
    th.start()
    t0 = time.monotonic()
    reason = ""
    try:
        _wait_port(port, th, timeout_s=30.0)
        monitor_config = None
        if acl_dir:
            from eonav.bus.acl import OPERATOR_USER, session_file
            monitor_config = str(session_file(acl_dir, OPERATOR_USER))
        with Monitor(endpoint, vehicle, truth, zenoh_config=monitor_config) as mon:
            last_n, last_change = -1, time.monotonic()
            while th.is_alive():
                time.sleep(0.2)
                c = mon.counts()
                n = c["range_maps"] + c["obstacle_lists"]
                if n != last_n:
                    last_n, last_change = n, time.monotonic()
                replay_done = all(status.get(s, {}).get("state") in ("done", "failed", "config_error", "missing")
                                  for s in ("camera", "mavlink"))
                if c["range_maps"] >= n_frames - 1 and c["obstacle_lists"] >= c["range_maps"] and replay_done:
                    reason = "replay ended, every frame ranged"
                    break
                if replay_done and time.monotonic() - last_change > drain_s:
                    reason = "replay ended, pipeline drained"
                    break
                if time.monotonic() - t0 > timeout_s:
                    reason = f"timeout {timeout_s:g} s"
                    break
            time.sleep(1.2)                                 # one more round of health messages
            stop.set()
            th.join(60.0)
            summary = mon.summary()
            last = mon.last_range
            with mon.lock:
                boxes = mon.obstacles_at.get(int(last[0]["stamp_us"]), []) if last is not None else []
    except KeyboardInterrupt:
        reason = "interrupted"
        stop.set()
        th.join(60.0)
        raise
    finally:
        stop.set()
        th.join(60.0)
    summary.update(recording=str(rec), stop_reason=reason, pipeline_exit=result["code"],
                   replay_shift_us=shift.get("us"),
                   exit_codes={k: v.get("exit_code") for k, v in status.items() if k != "router"},
                   service_states={k: v.get("state") for k, v in status.items() if k != "router"})
    if last is not None and png is not None:
        import cv2
        m, i = last
        pic = range_picture(m, on_grid(truth.range_m[i], m["range_m"].shape[1], m["range_m"].shape[0])
                            .astype(np.float32) if i is not None else None, obstacles=boxes)
        cv2.imwrite(str(png), pic)
        summary.update(png=str(png), png_obstacles=min(len(boxes), PICTURE_BOXES), obstacles_in_list=len(boxes))
    summary.update(outcome(summary, result["code"], reason))
    return summary


def _wait_port(port: int, th: threading.Thread, timeout_s: float) -> None:
    import socket
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        if not th.is_alive():
            raise RuntimeError("the pipeline stopped before its router came up")
        with socket.socket() as s:
            s.settimeout(0.2)
            if s.connect_ex(("127.0.0.1", port)) == 0:
                return
        time.sleep(0.1)
    raise RuntimeError(f"embedded router on port {port} not reachable after {timeout_s:g} s")


def format_summary(s: dict) -> str:
    lr, lo = s["latency_capture_to_range_ms"], s["latency_capture_to_obstacles_ms"]
    lines = [
        "eonav demo summary",
        f"  recording            {s['recording']}",
        f"  frames               {s['frames_seen']}/{s['frames_recorded']} seen on the bus",
        f"  range maps           {s['range_maps']} (median relative range error {100 * s['median_rel_error']:.1f} % "
        f"on confident pixels, worst map {100 * s['worst_map_median_rel_error']:.1f} %; coverage "
        f"{100 * s['coverage']:.0f} % of pixels)",
        f"  obstacle lists       {s['obstacle_lists']}; nearest box ({s['nearest_box']}) found in "
        f"{s['nearest_box_found']} at median distance error {100 * s['nearest_box_median_rel_error']:.1f} %",
        f"  latency capture->range      p50 {lr['p50']:.0f} ms  p99 {lr['p99']:.0f} ms  (n={lr['n']})",
        f"  latency capture->obstacles  p50 {lo['p50']:.0f} ms  p99 {lo['p99']:.0f} ms  (n={lo['n']})",
        f"  locate compute p50   {s['compute_ms_p50']:.0f} ms",
        f"  drops                {json.dumps(s['drops'])}",
        f"  services             {json.dumps(s['service_states'])} exit codes {json.dumps(s['exit_codes'])}",
        f"  stopped              {s['stop_reason']}",
    ]
    if "png" in s:
        lines.append(f"  range picture        {s['png']} (left: estimate, right: truth, colour bar in metres; "
                     f"the {s.get('png_obstacles', 0)} nearest of the map's {s.get('obstacles_in_list', 0)} obstacles "
                     f"boxed with their distance from the vehicle origin, the colours range from the camera; "
                     f"black = no estimate)")
    if "verdict" in s:
        why = f": {'; '.join(s['verdict_reasons'])}" if s["verdict_reasons"] else (
            f" (at least {MIN_FRACTION:.0%} of the frames seen and ranged)")
        lines.append(f"  verdict              {s['verdict']}{why}")
    return "\n".join(lines)


# --------------------------------------------------------------------------------------------------
# CLI (``eonav run`` with no pipeline or source delegates here; also ``python -m eonav.app.demo``)

def add_arguments(p) -> None:
    p.add_argument("--flight", default=DEFAULT_FLIGHT, help="simulated flight (approach, turning, climbing)")
    p.add_argument("--frames", type=int, default=DEFAULT_FRAMES, help="frames to record")
    p.add_argument("--fps", type=float, default=DEFAULT_RATE_HZ, help="frame rate of the recording")
    p.add_argument("--size", type=int, default=DEFAULT_SIZE, help="square image size in pixels")
    p.add_argument("--method", default="dense", help="locator method")
    p.add_argument("--out", default=None, metavar="DIR",
                   help="where this run's folder eonav-demo-<date>-<time> goes (default: the working directory)")
    p.add_argument("--png", default=None, help="where to write the range picture (default: range.png in the run folder)")
    p.add_argument("--cache-dir", default=None,
                   help="recording cache (default: $XDG_CACHE_HOME/eonav/demo or ~/.cache/eonav/demo)")
    p.add_argument("--json", action="store_true", help="print the summary as JSON too")


def run(args) -> int:
    run_dir = new_run_dir(getattr(args, "out", None))
    log_dir = getattr(args, "log_dir", None)
    if log_dir is None and not getattr(args, "verbose", 0):
        # A newcomer sees the status line and the summary; each service's log goes to a file.
        log_dir = str(run_dir / "logs")
    print(f"eonav demo: simulated flight -> camera, MAVLink, sync, locator, obstacle services over an embedded "
          f"zenoh router; this run's picture, summary{' and service logs' if log_dir else ''} in {run_dir}"
          f"{' (-v to see the logs here)' if log_dir else ''}", flush=True)
    s = run_demo(flight=getattr(args, "flight", DEFAULT_FLIGHT), n_frames=getattr(args, "frames", DEFAULT_FRAMES),
                 rate_hz=getattr(args, "fps", DEFAULT_RATE_HZ), size=getattr(args, "size", DEFAULT_SIZE),
                 method=getattr(args, "method", "dense"), png=getattr(args, "png", None) or run_dir / "range.png",
                 cache_dir=getattr(args, "cache_dir", None), vehicle=getattr(args, "vehicle", "demo") or "demo",
                 quiet=getattr(args, "quiet", False), log_dir=log_dir, record=getattr(args, "record", None),
                 acl_dir=getattr(args, "acl_dir", None))
    s["run_dir"] = str(run_dir)
    (run_dir / "summary.json").write_text(json.dumps(s, indent=2, default=str))
    print(format_summary(s))
    print(f"  summary              {run_dir / 'summary.json'}")
    if getattr(args, "json", False):
        print(json.dumps(s, default=str))
    return s["exit_code"]


if __name__ == "__main__":
    import argparse
    ap = argparse.ArgumentParser(prog="python -m eonav.app.demo", description=__doc__.split("\n")[0])
    add_arguments(ap)
    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(levelname)s %(name)s: %(message)s")
    sys.exit(run(ap.parse_args()))
