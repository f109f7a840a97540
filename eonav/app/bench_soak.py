"""``eonav bench soak``: the whole pipeline at 30 fps for N minutes; memory and latency per minute, and their trend.

Every service runs as its own process under ``eonav.app.launcher.run_pipeline`` (embedded router, camera ingest,
MAVLink ingest, sync, locator, obstacles), fed by :func:`lap_recording`: one exact lap of the simulated turning
flight (a closed circle: the last frame joins the first), which the camera ingest replays in a loop, and a tlog of
the same flight as long as the soak, both on one ``--replay-shift-us`` so frames and navigation agree lap after
lap. :class:`BusWatch` (a client session) stamps the arrival of every frame, range map and obstacle list. Each
minute it prints the resident memory (VmRSS) of every service process and the p99 of capture -> obstacle list;
at the end the least-squares slope of each per minute. Goal: flat (no growth beyond noise). Not in the test run.
"""
from __future__ import annotations

import json
import logging
import math
import shutil
import sys
import tempfile
import threading
import time
from pathlib import Path

import numpy as np

log = logging.getLogger("eonav.app.bench_soak")

FLIGHT = "turning"
NAV_LEAD_S = 3.0                 # frames start 3 s into the flight: the tlog's clock estimate locks first
SERVICES = ("camera", "mavlink", "sync", "locator", "obstacles")


# --------------------------------------------------------------------------------------------------
# the recording

def lap_period_s() -> float:
    """One lap of the turning flight (positions and attitude repeat after it)."""
    from eonav.sim.flight import _TURN_RATE
    return 2.0 * math.pi / _TURN_RATE


def lap_recording(fps: float = 30.0, size=(320, 240), nav_s: float = 660.0, cache_dir=None) -> Path:
    """A recording (``eonav.sim.record`` layout) of one lap of the turning flight at about ``fps`` (exactly
    N / lap frames per second, N = round(fps x lap), so a looped replay joins without a jump), with a tlog of
    ``nav_s`` seconds of navigation. Rendered once and cached (this user's cache, beside the demo's, by default)."""
    from eonav.sim.record import record_flight, write_tlog
    period = lap_period_s()
    n = int(round(fps * period))
    from eonav.app.demo import default_cache_dir
    base = Path(cache_dir) if cache_dir else default_cache_dir().parent / "soak"
    out = base / f"{FLIGHT}_lap{n}_{size[0]}x{size[1]}_nav{nav_s:g}s"
    if (out / "manifest.json").is_file():
        return out
    base.mkdir(parents=True, exist_ok=True)
    tmp = Path(tempfile.mkdtemp(prefix=out.name + ".", dir=base))
    log.info("rendering one lap of the %s flight: %d frames %dx%d into %s", FLIGHT, n, size[0], size[1], out)
    record_flight(tmp, name=FLIGHT, n_frames=n, rate_hz=n / period, size=tuple(size), supersample=1,
                  frames_start_s=NAV_LEAD_S)
    man = json.loads((tmp / "manifest.json").read_text())
    man["tlog_counts"] = write_tlog(tmp / man["tlog"], FLIGHT, nav_s, start_unix_us=man["start_unix_us"],
                                    boot_offset_us=man["boot_offset_us"], origin_lla=man["origin_lla"],
                                    latency_us=tuple(man["latency_us"]), seed=man["seed"])
    man["lap_s"] = period
    (tmp / "manifest.json").write_text(json.dumps(man, indent=2))
    try:
        tmp.rename(out)
    except OSError:                       # another run finished first: use theirs
        shutil.rmtree(tmp, ignore_errors=True)
    return out


def looped_spec(rec_dir, shift_us: int, **kw) -> dict:
    """The demo's pipeline (``eonav.app.demo.pipeline_spec``) with the camera replay looping."""
    from eonav.app.demo import pipeline_spec
    spec = pipeline_spec(rec_dir, shift_us, **kw)
    for s in spec["services"]:
        if s["name"] == "camera":
            s["args"] = [*s["args"], "--loop"]
    return spec


# --------------------------------------------------------------------------------------------------
# what arrives on the bus

class BusWatch:
    """Every frame, range map, obstacle list and health message on the bus, with its arrival time.

    ``frames``, ``maps``, ``lists``: lists of dicts (``t`` monotonic arrival, ``rx_us`` arrival on the realtime
    clock, ``stamp_us``, ``seq``, ``camera_id``, and for maps and lists ``frame_age_ms``); ``health``: (t, message).
    A context manager (a client session on ``endpoint``; ``zenoh_config``: a session config applied first, e.g. the
    operator's credentials under access control)."""

    def __init__(self, endpoint: str, vehicle: str, zenoh_config: str | None = None):
        self.endpoint, self.vehicle, self.zenoh_config = endpoint, vehicle, zenoh_config
        self.lock = threading.Lock()
        self.frames, self.maps, self.lists, self.health = [], [], [], []
        self.bad = 0
        self._session, self._subs, self._threads = None, [], []

    def __enter__(self):
        from eonav.bus import keys as K
        from eonav.bus.session import client_session, consume_in_threads
        self._session = client_session(self.endpoint, self.zenoh_config)

        def stamped(fn):              # the handlers take the payload and both arrival times
            return lambda sample, t: fn(sample.payload.to_bytes(), t, time.time_ns() // 1000)
        self._subs, self._threads = consume_in_threads(
            self._session, ((K.frames_all(self.vehicle), 256, stamped(self._frame)),
                            (K.range_maps_all(self.vehicle), 256, stamped(self._map)),
                            (K.obstacles(self.vehicle), 256, stamped(self._list)),
                            (K.health_all(self.vehicle), 1024, stamped(self._health))),
            name="watch", on_error=self._bad)
        return self

    def __exit__(self, *exc):
        from eonav.bus.session import close_subscribers
        close_subscribers(self._subs, self._threads, self._session, 10.0)

    def _bad(self, sample, e):
        """A malformed message is counted; the watch keeps going."""
        with self.lock:
            self.bad += 1
        log.warning("bus watch: %s on %s: %s", type(e).__name__, sample.key_expr, e)

    def _frame(self, payload, t, rx):
        import msgpack
        doc = msgpack.unpackb(payload, raw=False)  # the stamp only: no image decode
        with self.lock:
            self.frames.append({"t": t, "rx_us": rx, "stamp_us": int(doc["stamp_us"]), "seq": int(doc["seq"]),
                                "camera_id": doc["camera_id"]})

    def _out(self, payload, t, rx, kind, into):
        from eonav.bus import schema
        m = schema.decode(payload, expect=kind)
        with self.lock:
            into.append({"t": t, "rx_us": rx, "stamp_us": int(m["stamp_us"]), "seq": int(m.get("seq", -1)),
                         "camera_id": m["camera_id"], "frame_age_ms": float(m["frame_age_ms"])})

    def _map(self, payload, t, rx):
        self._out(payload, t, rx, "range_map", self.maps)

    def _list(self, payload, t, rx):
        self._out(payload, t, rx, "obstacle_list", self.lists)

    def _health(self, payload, t, rx):
        from eonav.bus import schema
        m = schema.decode(payload, expect="health")
        with self.lock:
            self.health.append((t, m))

    def snapshot(self) -> dict:
        with self.lock:
            return {"frames": list(self.frames), "maps": list(self.maps), "lists": list(self.lists),
                    "health": list(self.health)}

    def latest_health(self) -> dict:
        with self.lock:
            out = {}
            for t, m in self.health:
                out[m["service"]] = (t, m)
            return out


# --------------------------------------------------------------------------------------------------
# the soak

def rss_mb(pid: int | None) -> float:
    """Resident memory of process ``pid`` in MB (VmRSS), NaN if it is gone."""
    if not pid:
        return math.nan
    try:
        for line in Path(f"/proc/{pid}/status").read_text().splitlines():
            if line.startswith("VmRSS:"):
                return int(line.split()[1]) / 1024.0
    except (OSError, ValueError):
        pass
    return math.nan


def slope_per_minute(values) -> float:
    """Least-squares slope of ``values`` (one per minute) in units per minute; NaN with fewer than 2 finite."""
    y = np.asarray(values, float)
    x = np.arange(len(y), dtype=float)
    ok = np.isfinite(y)
    if ok.sum() < 2:
        return math.nan
    return float(np.polyfit(x[ok], y[ok], 1)[0])


def _p99(v):
    return float(np.percentile(v, 99)) if len(v) else math.nan


def run_soak(*, minutes: float = 10.0, fps: float = 30.0, size=(320, 240), method: str = "dense",
             vehicle: str = "soak", stream=None, log_dir=None, cache_dir=None) -> dict:
    """Run the soak; print one line per minute and the slopes; return the figures."""
    from eonav.app.demo import replay_shift_us
    from eonav.app.launcher import run_pipeline
    from eonav.app.processes import free_port
    stream = stream or sys.stdout
    # navigation for whole 10-minute blocks (one cached recording serves every shorter soak), a minute to spare
    rec = lap_recording(fps, size, nav_s=NAV_LEAD_S + 600.0 * math.ceil((minutes + 1.0) / 10.0), cache_dir=cache_dir)
    man = json.loads((rec / "manifest.json").read_text())
    if method == "dense":                          # compiled / loaded once here, not in the locator's first pair
        from eonav.fusion.sequence import prepare_kernels
        prepare_kernels()
    shift = replay_shift_us(rec, start_in_s=6.0)
    port = free_port()
    stop = threading.Event()
    status: dict = {}
    result = {}

    def pipeline():
        result["code"] = run_pipeline(looped_spec(rec, shift, method=method), vehicle=vehicle, port=port,
                                      on_status=status.update, stop_event=stop, quiet=True, log_dir=log_dir)

    th = threading.Thread(target=pipeline, name="pipeline")
    th.start()
    rows = []
    print(f"soak: {minutes:g} min at {man['rate_hz']:.2f} fps, {size[0]}x{size[1]}, method {method}, every service "
          f"a process (recording {rec}; a looped lap of {man['n_frames']} frames)", file=stream, flush=True)
    try:
        from eonav.app.demo import _wait_port
        _wait_port(port, th, 30.0)
        with BusWatch(f"tcp/127.0.0.1:{port}", vehicle) as w:
            deadline = time.monotonic() + 120.0       # processes up, the replay's lead, warm-ups: not measured
            while not w.snapshot()["lists"] and th.is_alive() and time.monotonic() < deadline:
                time.sleep(0.2)
            time.sleep(5.0)
            for k in range(int(math.ceil(minutes))):
                t0 = time.monotonic()
                while time.monotonic() - t0 < 60.0 and th.is_alive():
                    time.sleep(0.5)
                snap = w.snapshot()
                win = [x for x in snap["lists"] if t0 <= x["t"] < t0 + 60.0]
                frames = [x for x in snap["frames"] if t0 <= x["t"] < t0 + 60.0]
                lat = [(x["rx_us"] - x["stamp_us"]) / 1e3 for x in win]
                row = {"minute": k + 1, "frames": len(frames), "obstacle_lists": len(win),
                       "capture_to_obstacles_p50_ms": float(np.median(lat)) if lat else math.nan,
                       "capture_to_obstacles_p99_ms": _p99(lat),
                       "rss_mb": {n: rss_mb(status.get(n, {}).get("pid")) for n in SERVICES},
                       "restarts": {n: status.get(n, {}).get("restarts", 0) for n in SERVICES}}
                rows.append(row)
                print(f"minute {k + 1:2d}: frames {row['frames']:5d}, obstacle lists {row['obstacle_lists']:5d}, "
                      f"capture->obstacles p50 {row['capture_to_obstacles_p50_ms']:6.1f} ms p99 "
                      f"{row['capture_to_obstacles_p99_ms']:6.1f} ms | RSS MB "
                      + " ".join(f"{n} {v:6.1f}" for n, v in row["rss_mb"].items()), file=stream, flush=True)
                if not th.is_alive():
                    break
            health = {n: m for n, (t, m) in w.latest_health().items()}
    finally:
        stop.set()
        th.join(60.0)
    slopes = {"capture_to_obstacles_p99_ms_per_min": slope_per_minute([r["capture_to_obstacles_p99_ms"] for r in rows]),
              "rss_mb_per_min": {n: slope_per_minute([r["rss_mb"][n] for r in rows]) for n in SERVICES}}
    later = rows[1:]                      # the first minute still grows caches and pools
    slopes_after_first = {
        "capture_to_obstacles_p99_ms_per_min": slope_per_minute([r["capture_to_obstacles_p99_ms"] for r in later]),
        "rss_mb_per_min": {n: slope_per_minute([r["rss_mb"][n] for r in later]) for n in SERVICES}}
    drops = {n: {k: v for k, v in (health.get(n, {}).get("counters") or {}).items()
                 if k.startswith(("dropped.", "frames_skipped", "skipped", "maps_superseded", "message_errors"))}
             for n in SERVICES}
    print("slope per minute (least squares over all minutes): p99 "
          f"{slopes['capture_to_obstacles_p99_ms_per_min']:+.2f} ms/min; RSS "
          + " ".join(f"{n} {v:+.2f}" for n, v in slopes["rss_mb_per_min"].items()) + " MB/min", file=stream)
    print("slope per minute from minute 2: p99 "
          f"{slopes_after_first['capture_to_obstacles_p99_ms_per_min']:+.2f} ms/min; RSS "
          + " ".join(f"{n} {v:+.2f}" for n, v in slopes_after_first["rss_mb_per_min"].items()) + " MB/min",
          file=stream)
    print(f"drops and skips (final health counters): {json.dumps(drops)}", file=stream, flush=True)
    return {"minutes": rows, "slopes": slopes, "slopes_from_minute_2": slopes_after_first, "drops": drops,
            "pipeline_exit": result.get("code"), "fps": man["rate_hz"], "size": list(size), "method": method}


# --------------------------------------------------------------------------------------------------
# CLI

def add_arguments(p) -> None:
    p.add_argument("--minutes", type=float, default=10.0, help="how long (default 10)")
    p.add_argument("--fps", type=float, default=30.0, help="camera frame rate (default 30)")
    p.add_argument("--size", default="320x240", metavar="WxH", help="frame size (default 320x240)")
    p.add_argument("--method", default="dense", help="locator method")
    p.add_argument("--log-dir", default=None, help="one log file per service here (default: a temp folder)")
    p.add_argument("--json", action="store_true", help="print the figures as JSON at the end")


def run(args) -> int:
    from eonav import InputError
    try:
        w, h = (int(x) for x in args.size.lower().split("x"))
    except ValueError:
        raise InputError(f"--size {args.size!r}: expected WIDTHxHEIGHT, e.g. 320x240") from None
    if not args.minutes > 0 or not args.fps > 0:
        raise InputError("--minutes and --fps must be > 0")
    log_dir = args.log_dir or tempfile.mkdtemp(prefix="eonav-soak-logs.")
    res = run_soak(minutes=args.minutes, fps=args.fps, size=(w, h), method=args.method, log_dir=log_dir)
    print(f"service logs in {log_dir}")
    if args.json:
        print(json.dumps(res, default=str))
    return 0 if res["pipeline_exit"] == 0 else 1


if __name__ == "__main__":
    import argparse
    ap = argparse.ArgumentParser(prog="python -m eonav.app.bench_soak", description=__doc__.split("\n")[0])
    add_arguments(ap)
    logging.basicConfig(level=logging.INFO)
    sys.exit(run(ap.parse_args()))
