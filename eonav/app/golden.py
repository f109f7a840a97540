"""The golden recording: the inputs of a short simulated run, and what the services make of them.

    python -m eonav.app.golden [--out tests/data]        # regenerate the three files below
    python -m eonav.app.golden --check [--out tests/data]  # replay and compare, print the differences

Files (tests/data):

- ``golden_inputs.mcap``: what the camera and MAVLink ingests put on the bus for 12 frames (256 x 256, 5 Hz) of the
  simulator's ``approach`` flight, its navigation starting 3 s before the first frame (``eonav.app.demo.recording``,
  seed 0), recorded by the recorder (``eonav.recording.recorder``: raw + Foxglove channels, health left out) with the
  cameras file stored as the MCAP attachment ``cameras.json``;
- ``golden_expected.npz``: the range maps the sync, locator and obstacle services made when that recording was
  replayed through them (``stamp_us``, ``other_stamp_us``, ``range_m`` float32, ``flags``);
- ``golden_expected.json``: their obstacle lists (per map stamp: distance, bearing, elevation, pixel count of each
  obstacle), with the service flags and tolerances used.

:func:`run_services` is the replay both the generator and tests/test_golden_recording.py run: an embedded router, the
sync, locator (``dense``, ``--scale 1``, no warm-up: fixed work, so every pair is the same one run after run) and
obstacle services as processes, then ``eonav.recording.replayer`` at real time, once every service's subscriber is
declared. :func:`compare` checks outputs against the expected ones with :data:`TOLERANCES`.
"""
from __future__ import annotations

import argparse
import json
import math
import sys
import tempfile
import threading
import time
from pathlib import Path

import numpy as np

from eonav import InputError

VEHICLE = "golden"
FLIGHT = {"flight": "approach", "n_frames": 12, "rate_hz": 5.0, "size": 256, "seed": 0}
INPUTS, EXPECTED_NPZ, EXPECTED_JSON = "golden_inputs.mcap", "golden_expected.npz", "golden_expected.json"
CAMERAS_ATTACHMENT = "cameras.json"
LOCATOR_ARGS = ["--method", "dense", "--cv-threads", "1", "--scale", "1", "--no-warmup"]
OBSTACLES_ARGS = ["--ground-down-m", "0", "--max-obstacle-distance-m", "150"]
# the recording's stamps are those of the day it was made: no age limit in the replay (the stamp-order rule holds)
NO_AGE_LIMIT = ["--max-input-age-ms", "1e12"]
# What "the same output" means. Range maps: every expected pair (reference stamp, partner stamp) and no other; per map,
# the VALID masks differ on at most `valid_mismatch` of the pixels, and on the pixels VALID in both the relative range
# difference has a median <= `median_rel` and a 99th percentile <= `p99_rel`. Obstacle lists: one per expected map
# stamp, the same number of obstacles, each (nearest first) within `distance_rel` of its distance, `bearing_deg` and
# `elevation_deg` of its direction, `pixels_rel` of its pixel count.
# Replays on the machine that made the files reproduced them bit for bit (every figure 0); the margins are for another
# CPU's floating point (vector widths, libm), far below what a change of the method moves (docs/recording.md).
TOLERANCES = {"valid_mismatch": 0.005, "median_rel": 2e-4, "p99_rel": 5e-3,
              "distance_rel": 0.005, "bearing_deg": 0.2, "elevation_deg": 0.2, "pixels_rel": 0.03}


def default_dir() -> Path:
    return Path(__file__).resolve().parents[2] / "tests" / "data"


# --------------------------------------------------------------------------------------------------
# making the inputs

def record_inputs(out_mcap, work_dir) -> Path:
    """Render the flight (cached in ``work_dir``), replay it through the camera and MAVLink ingests over an embedded
    router and record everything on the bus into ``out_mcap`` (replaced)."""
    from eonav.bus import keys as K
    from eonav.app.demo import pipeline_spec, recording, replay_shift_us
    from eonav.app.launcher import run_pipeline
    from eonav.recording.recorder import recorder_service
    work = Path(work_dir)
    rec = recording(FLIGHT["flight"], FLIGHT["n_frames"], FLIGHT["rate_hz"], FLIGHT["size"], FLIGHT["seed"],
                    cache_dir=work / "flight")
    man = json.loads((rec / "manifest.json").read_text())
    spec = pipeline_spec(rec, replay_shift_us(rec))
    services = [s for s in spec["services"] if s["name"] in ("camera", "mavlink")]
    recorder = recorder_service(out_mcap)
    # health left out: never replayed, and its details name this machine's paths
    recorder["args"] += ["--overwrite", "--compression", "zstd", "--attach", str(rec / man["cameras"]),
                         "--exclude", K.health_all(VEHICLE)]
    services.append(recorder)
    stop = threading.Event()

    def on_status(st):
        if all(st.get(n, {}).get("state") in ("done", "failed", "config_error") for n in ("camera", "mavlink")):
            time.sleep(1.0)                      # the last samples reach the recorder
            stop.set()

    code = run_pipeline({"services": services}, vehicle=VEHICLE, on_status=on_status, stop_event=stop, quiet=True,
                        log_dir=str(work / "logs"))
    if code != 0:
        raise RuntimeError(f"recording the golden inputs failed (pipeline exit {code}; logs in {work / 'logs'})")
    return Path(out_mcap)


def cameras_file(inputs_mcap, out_path) -> Path:
    """The cameras file stored in the recording (MCAP attachment ``cameras.json``), written to ``out_path``."""
    from mcap.reader import make_reader
    with open(inputs_mcap, "rb") as f:
        for att in make_reader(f).iter_attachments():
            if att.name == CAMERAS_ATTACHMENT:
                Path(out_path).write_bytes(att.data)
                return Path(out_path)
    raise InputError(f"{inputs_mcap}: no attachment {CAMERAS_ATTACHMENT!r} (expected a golden recording)")


# --------------------------------------------------------------------------------------------------
# replaying through the services

def run_services(inputs_mcap, work_dir, *, speed: float = 1.0, timeout_s: float = 90.0) -> dict:
    """Replay ``inputs_mcap`` through sync, locator and obstacles; returns {"range_maps": [...], "obstacle_lists":
    [...], "exit_codes": {...}} with the decoded messages in arrival order."""
    import zenoh
    from eonav.bus import keys as K
    from eonav.bus import schema
    from eonav.bus.session import client_session
    from eonav.app.processes import router_process, start_service, stop_service, wait_until
    from eonav.fusion.sequence import prepare_kernels
    work = Path(work_dir)
    work.mkdir(parents=True, exist_ok=True)
    cams = cameras_file(inputs_mcap, work / CAMERAS_ATTACHMENT)
    camera_ids = list(json.loads(cams.read_text()))
    prepare_kernels()                    # compiled here once (numba's cache is shared), only loaded by the locator
    out = {"range_maps": [], "obstacle_lists": [], "health": {}}
    lock = threading.Lock()
    with router_process() as ep, client_session(ep) as s:
        # clients of the router: every sample goes through it, no peer-to-peer links forming while the replay runs
        common = ["--vehicle", VEHICLE, "--connect", ep, "--mode", "client", "--log-level", "warning",
                  "--health-period-s", "0.5"]
        subs = [s.declare_subscriber(K.range_maps_all(VEHICLE), zenoh.handlers.FifoChannel(256)),
                s.declare_subscriber(K.obstacles(VEHICLE), zenoh.handlers.FifoChannel(256)),
                s.declare_subscriber(K.health_all(VEHICLE), zenoh.handlers.FifoChannel(1024))]

        def consume(sub):
            try:
                for smp in sub:
                    m = schema.decode(smp.payload.to_bytes())
                    with lock:
                        if m["kind"] == "range_map":
                            out["range_maps"].append(m)
                        elif m["kind"] == "obstacle_list":
                            out["obstacle_lists"].append(m)
                        elif m["kind"] == "health":
                            out["health"][m["service"]] = m
            except Exception:
                pass                            # channel closed

        threads = [threading.Thread(target=consume, args=(sub,), name="golden-consume") for sub in subs]
        for t in threads:
            t.start()
        procs = {"sync": start_service(["-m", "eonav.services.sync", *common, *NO_AGE_LIMIT, "--cameras", str(cams)]),
                 "locator": start_service(["-m", "eonav.services.locator", *common, *NO_AGE_LIMIT, *LOCATOR_ARGS]),
                 "obstacles": start_service(["-m", "eonav.services.obstacles", *common, *NO_AGE_LIMIT,
                                             *OBSTACLES_ARGS])}
        codes = {}
        try:
            # every consumer's subscriber is declared: the locator's (posed frames) and the obstacle service's (range
            # maps) seen through probe publishers; sync's by the replay itself (--wait-for frames and nav)
            probes = [s.declare_publisher(K.posed_frame(VEHICLE, camera_ids[0])),
                      s.declare_publisher(K.range_map(VEHICLE, camera_ids[0]))]
            deadline = time.monotonic() + timeout_s
            for name, p in procs.items():
                wait_until(lambda: p.poll() is None and name in out["health"] or p.poll() is not None,
                           timeout=max(1.0, deadline - time.monotonic()), what=f"{name} up")
                if p.poll() is not None:
                    raise RuntimeError(f"{name} exited {p.returncode}: {p.stderr.read()[-2000:]}")
            for pr in probes:
                wait_until(lambda: pr.matching_status.matching, timeout=max(1.0, deadline - time.monotonic()),
                           what="locator and obstacle subscribers")
                pr.undeclare()
            replay = start_service(["-m", "eonav.recording.replayer", str(inputs_mcap), *common, "--name", "replay",
                                    "--speed", str(speed), "--wait-for", K.frames_all(VEHICLE),
                                    "--wait-for", K.nav_state(VEHICLE), "--wait-timeout-s", "20"])
            try:
                rc = replay.wait(max(1.0, deadline - time.monotonic()))
            except Exception:
                rc = None
            codes["replay"] = rc if rc is not None else stop_service(replay)[0]
            # drained: nothing new for 5 s (the locator ranges the last frame within ~0.1 s on a quiet machine, but a
            # loaded 2-core machine has been seen to take over 2 s)
            last, t_last = -1, time.monotonic()
            while time.monotonic() - t_last < 5.0 and time.monotonic() < deadline:
                with lock:
                    n = len(out["range_maps"]) + len(out["obstacle_lists"])
                if n != last:
                    last, t_last = n, time.monotonic()
                time.sleep(0.1)
        finally:
            for name, p in procs.items():
                codes[name] = stop_service(p)[0]
            for sub in subs:
                sub.undeclare()
            for t in threads:
                t.join(5)
    out["exit_codes"] = codes
    return out


# --------------------------------------------------------------------------------------------------
# expected outputs

def obstacle_summary(ol: dict) -> dict:
    return {"stamp_us": int(ol["stamp_us"]),
            "obstacles": [{k: o[k] for k in ("distance_m", "bearing_deg", "elevation_deg", "pixel_count")}
                          for o in sorted(ol["obstacles"], key=lambda o: o["distance_m"])]}


def save_expected(outputs: dict, out_dir) -> None:
    maps = sorted(outputs["range_maps"], key=lambda m: m["stamp_us"])
    out_dir = Path(out_dir)
    np.savez_compressed(out_dir / EXPECTED_NPZ,
                        stamp_us=np.array([m["stamp_us"] for m in maps], np.int64),
                        other_stamp_us=np.array([m["other_stamp_us"] for m in maps], np.int64),
                        range_m=np.stack([np.asarray(m["range_m"], np.float32) for m in maps]),
                        flags=np.stack([np.asarray(m["flags"], np.uint8) for m in maps]))
    doc = {"made_by": "python -m eonav.app.golden", "flight": FLIGHT, "vehicle": VEHICLE,
           "locator_args": LOCATOR_ARGS, "obstacles_args": OBSTACLES_ARGS, "tolerances": TOLERANCES,
           "obstacle_lists": [obstacle_summary(o) for o in sorted(outputs["obstacle_lists"],
                                                                  key=lambda o: o["stamp_us"])]}
    (out_dir / EXPECTED_JSON).write_text(json.dumps(doc, indent=1) + "\n")


def load_expected(data_dir) -> dict:
    d = Path(data_dir)
    z = np.load(d / EXPECTED_NPZ)
    doc = json.loads((d / EXPECTED_JSON).read_text())
    return {"stamp_us": z["stamp_us"], "other_stamp_us": z["other_stamp_us"], "range_m": z["range_m"],
            "flags": z["flags"], "obstacle_lists": doc["obstacle_lists"]}


def compare(outputs: dict, expected: dict, tol: dict = TOLERANCES) -> dict:
    """Differences between ``outputs`` (run_services) and ``expected`` (load_expected): {"ok": bool, "problems":
    [...], "maps": [per-map figures], "obstacles": [per-list figures]}."""
    from eonav.ranging.rangemap import VALID
    problems, maps, obst = [], [], []
    got = {(int(m["stamp_us"]), int(m["other_stamp_us"])): m for m in outputs["range_maps"]}
    want = {(int(s), int(o)): i for i, (s, o) in enumerate(zip(expected["stamp_us"], expected["other_stamp_us"]))}
    if set(got) != set(want):
        problems.append(f"range map pairs differ: missing {sorted(set(want) - set(got))}, "
                        f"unexpected {sorted(set(got) - set(want))}")
    for pair in sorted(set(got) & set(want)):
        i = want[pair]
        r, f = np.asarray(got[pair]["range_m"], np.float32), np.asarray(got[pair]["flags"])
        er, ef = expected["range_m"][i], expected["flags"][i]
        if r.shape != er.shape:
            problems.append(f"map {pair}: shape {r.shape} != {er.shape}")
            continue
        va, vb = (f & VALID) != 0, (ef & VALID) != 0
        both = va & vb & np.isfinite(r) & np.isfinite(er)
        rel = np.abs(r[both] / er[both] - 1.0) if both.any() else np.array([math.inf])
        row = {"pair": pair, "valid_mismatch": float((va != vb).mean()), "median_rel": float(np.median(rel)),
               "p99_rel": float(np.percentile(rel, 99)), "n_valid": int(both.sum())}
        maps.append(row)
        for k in ("valid_mismatch", "median_rel", "p99_rel"):
            if not row[k] <= tol[k]:
                problems.append(f"map {pair}: {k} {row[k]:.3g} > {tol[k]:g}")
    got_o = {int(o["stamp_us"]): obstacle_summary(o) for o in outputs["obstacle_lists"]}
    for e in expected["obstacle_lists"]:
        g = got_o.get(e["stamp_us"])
        if g is None:
            problems.append(f"obstacle list {e['stamp_us']}: missing")
            continue
        if len(g["obstacles"]) != len(e["obstacles"]):
            problems.append(f"obstacle list {e['stamp_us']}: {len(g['obstacles'])} obstacles, expected "
                            f"{len(e['obstacles'])}")
            continue
        for j, (a, b) in enumerate(zip(g["obstacles"], e["obstacles"])):
            d = {"distance_rel": abs(a["distance_m"] / b["distance_m"] - 1.0),
                 "bearing_deg": abs(a["bearing_deg"] - b["bearing_deg"]),
                 "elevation_deg": abs(a["elevation_deg"] - b["elevation_deg"]),
                 "pixels_rel": abs(a["pixel_count"] / max(1, b["pixel_count"]) - 1.0)}
            obst.append({"stamp_us": e["stamp_us"], "obstacle": j, **d})
            for k, v in d.items():
                if not v <= tol[k]:
                    problems.append(f"obstacle list {e['stamp_us']} obstacle {j}: {k} {v:.3g} > {tol[k]:g}")
    extra = set(got_o) - {e["stamp_us"] for e in expected["obstacle_lists"]}
    if extra:
        problems.append(f"unexpected obstacle lists at {sorted(extra)}")
    return {"ok": not problems, "problems": problems, "maps": maps, "obstacles": obst}


def worst(report: dict) -> dict:
    """The largest figure of each kind in a comparison report."""
    out = {}
    for rows in (report["maps"], report["obstacles"]):
        for row in rows:
            for k, v in row.items():
                if isinstance(v, float):
                    out[k] = max(out.get(k, 0.0), v)
    return out


def main(argv=None) -> int:
    p = argparse.ArgumentParser(prog="python -m eonav.app.golden", description=__doc__.splitlines()[0])
    p.add_argument("--out", default=str(default_dir()), help="directory of the golden files (default tests/data)")
    p.add_argument("--check", action="store_true", help="replay the committed files and compare; write nothing")
    p.add_argument("--keep-inputs", action="store_true", help="regenerate the expected outputs only")
    a = p.parse_args(argv)
    out = Path(a.out)
    with tempfile.TemporaryDirectory(prefix="eonav-golden-") as tmp:
        if a.check:
            rep = compare(run_services(out / INPUTS, Path(tmp) / "run"), load_expected(out))
            print(json.dumps({"ok": rep["ok"], "problems": rep["problems"], "worst": worst(rep)}, indent=1))
            return 0 if rep["ok"] else 1
        out.mkdir(parents=True, exist_ok=True)
        if not a.keep_inputs:
            record_inputs(out / INPUTS, Path(tmp) / "record")
        outputs = run_services(out / INPUTS, Path(tmp) / "run")
        if any(c != 0 for c in outputs["exit_codes"].values()):
            print(f"a service did not exit cleanly: {outputs['exit_codes']}", file=sys.stderr)
            return 1
        save_expected(outputs, out)
        print(f"{out / INPUTS}: {(out / INPUTS).stat().st_size} bytes; {len(outputs['range_maps'])} range maps, "
              f"{len(outputs['obstacle_lists'])} obstacle lists -> {out / EXPECTED_NPZ} "
              f"({(out / EXPECTED_NPZ).stat().st_size} bytes), {out / EXPECTED_JSON}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
