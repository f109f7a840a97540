"""Write a simulated flight as a recording the services replay: frames, timestamps, a MAVLink tlog, cameras, truth.

``record_flight(out_dir, name=, n_frames=, rate_hz=, size=, seed=)`` renders the flight (``eonav.sim.flight``) and
writes the image folder with its ``timestamps.txt`` (the camera ingest's source), ``flight.tlog`` (the MAVLink
ingest's source: the navigation messages from the flight's closed form, on a simulated autopilot boot clock with a
seeded link latency in the record headers), ``cameras.json``, ``truth.npz`` and ``manifest.json`` (the clocks and
rates). The layout and the clocks: docs/architecture.md, "Recordings".
"""
from __future__ import annotations

import json
import struct
from pathlib import Path

import cv2
import numpy as np

from eonav import InputError
from eonav.geometry.frames import quat_wxyz_from_rotation, ypr_from_T_body_ned
from eonav.nav.mavlink_in import lla_from_ned, mavlink2_dialect
from eonav.io.pairfile import camera_to_dict
from eonav.sim.flight import FLIGHTS, flight_states, render_flight

DEFAULT_START_UNIX_US = 1_760_000_000_000_000       # 2025-10-09, fixed so recordings are reproducible
DEFAULT_ORIGIN_LLA = (47.397742, 8.545594, 488.0)
ATT_HZ, POS_HZ = 50.0, 25.0
FRAME_T0_S = 0.2            # first frame 0.2 s into the flight: navigation brackets every frame


def _states_arrays(name, t):
    sts = flight_states(name, t)
    pos = np.array([s.position_ned_m for s in sts])
    T = np.array([s.T_body_ned for s in sts])
    return pos, T


def nav_truth(name: str, t_s) -> dict:
    """Position, attitude (q_wxyz, ypr), NED velocity and body rates of flight ``name`` at times t_s."""
    t = np.asarray(t_s, float)
    h = 1e-3
    pos, T = _states_arrays(name, t)
    tm = np.maximum(t - h, 0.0)
    tp = t + h
    pos_m, T_m = _states_arrays(name, tm)
    pos_p, T_p = _states_arrays(name, tp)
    dt = (tp - tm)[:, None]
    vel = (pos_p - pos_m) / dt
    # body rates: [w]x = R_nb^T dR_nb/dt with R_nb = T_body_ned^T
    rates = []
    for k in range(len(t)):
        dR = (T_p[k].T - T_m[k].T) / dt[k, 0]
        W = T[k] @ dR
        rates.append([0.5 * (W[2, 1] - W[1, 2]), 0.5 * (W[0, 2] - W[2, 0]), 0.5 * (W[1, 0] - W[0, 1])])
    q = np.array([quat_wxyz_from_rotation(Tk.T) for Tk in T])
    ypr = np.array([ypr_from_T_body_ned(Tk) for Tk in T])
    return {"position_ned_m": pos, "q_wxyz": q, "ypr_rad": ypr, "velocity_ned_mps": vel,
            "rates_frd_radps": np.array(rates), "T_body_ned": T}


def write_tlog(path, name: str, t_end_s: float, *, start_unix_us: int, boot_offset_us: int,
               origin_lla=DEFAULT_ORIGIN_LLA, latency_us=(1000, 3000), seed: int = 0) -> dict:
    """The MAVLink 2 tlog of flight ``name`` from t = 0 to t_end_s. Returns message counts."""
    mavlink = mavlink2_dialect()
    mav = mavlink.MAVLink(None, srcSystem=1, srcComponent=1)
    rng = np.random.default_rng(seed)
    events = []          # (t_s, order, kind)
    for k in range(int(np.floor(t_end_s * ATT_HZ)) + 1):
        events.append((k / ATT_HZ, 1, "att"))
    for k in range(int(np.floor(t_end_s * POS_HZ)) + 1):
        events.append((k / POS_HZ, 2, "pos"))
    for k in range(int(np.floor(t_end_s)) + 1):
        events.append((float(k), 0, "sec"))
    events.sort()
    ts = np.array(sorted({e[0] for e in events}))
    truth = nav_truth(name, ts)
    idx = {float(t): i for i, t in enumerate(ts)}
    recs = []
    counts = {}

    def emit(t_s, msg):
        unix_us = start_unix_us + int(round(t_s * 1e6))
        lat = int(rng.integers(latency_us[0], latency_us[1] + 1))
        buf = msg.pack(mav)
        mav.seq = (mav.seq + 1) % 256
        recs.append((unix_us + lat, len(recs), buf))
        counts[msg.get_type()] = counts.get(msg.get_type(), 0) + 1

    for t_s, _, kind in events:
        i = idx[float(t_s)]
        unix_us = start_unix_us + int(round(t_s * 1e6))
        boot_ms = (unix_us - boot_offset_us) // 1000
        if kind == "sec":
            emit(t_s, mavlink.MAVLink_heartbeat_message(mavlink.MAV_TYPE_FIXED_WING, mavlink.MAV_AUTOPILOT_ARDUPILOTMEGA,
                                                        mavlink.MAV_MODE_FLAG_SAFETY_ARMED, 0,
                                                        mavlink.MAV_STATE_ACTIVE, 3))
            emit(t_s, mavlink.MAVLink_system_time_message(unix_us, boot_ms))
            continue
        p, v = truth["position_ned_m"][i], truth["velocity_ned_mps"][i]
        y, pi, r = truth["ypr_rad"][i]
        w = truth["rates_frd_radps"][i]
        if kind == "att":
            emit(t_s, mavlink.MAVLink_attitude_message(boot_ms, r, pi, y, w[0], w[1], w[2]))
            continue
        q = truth["q_wxyz"][i]
        emit(t_s, mavlink.MAVLink_attitude_quaternion_message(boot_ms, q[0], q[1], q[2], q[3], w[0], w[1], w[2],
                                                              [0.0, 0.0, 0.0, 0.0]))
        emit(t_s, mavlink.MAVLink_local_position_ned_message(boot_ms, p[0], p[1], p[2], v[0], v[1], v[2]))
        lat, lon, alt = lla_from_ned(p, origin_lla)
        hdg = int(round(np.rad2deg(y) * 100)) % 36000
        emit(t_s, mavlink.MAVLink_global_position_int_message(
            boot_ms, int(round(lat * 1e7)), int(round(lon * 1e7)), int(round(alt * 1000)),
            int(round(-p[2] * 1000)), *(int(round(c * 100)) for c in v), hdg))
    recs.sort()
    with open(path, "wb") as f:
        for header_us, _, buf in recs:
            f.write(struct.pack(">Q", header_us) + buf)
    return counts


def record_flight(out_dir, name: str = "approach", n_frames: int = 20, rate_hz: float = 10.0, size=(160, 120),
                  seed: int = 0, *, camera_id: str = "nose", start_unix_us: int = DEFAULT_START_UNIX_US,
                  boot_at_start_s: float = 123.456, origin_lla=DEFAULT_ORIGIN_LLA, latency_us=(1000, 3000),
                  supersample: int = 3, noise_sigma: float = 1.0, frames_start_s: float = FRAME_T0_S) -> Path:
    """Render flight ``name`` and write the recording (see module docstring). Returns ``out_dir``.
    Navigation starts at flight time 0, the first frame at ``frames_start_s`` (navigation lead)."""
    if not (np.isfinite(frames_start_s) and frames_start_s >= 0):
        raise InputError(f"frames_start_s must be >= 0, got {frames_start_s!r}")
    if name not in FLIGHTS:
        raise InputError(f"unknown flight {name!r}; expected one of {', '.join(FLIGHTS)}")
    if not (int(n_frames) == n_frames and n_frames >= 1):
        raise InputError(f"n_frames must be a whole number >= 1, got {n_frames!r}")
    if not (np.isfinite(rate_hz) and rate_hz > 0):
        raise InputError(f"rate_hz must be > 0, got {rate_hz!r}")
    if not (0 <= latency_us[0] <= latency_us[1]):
        raise InputError(f"latency_us {latency_us!r}: expected (min, max) with 0 <= min <= max")
    out = Path(out_dir)
    frames_dir = out / "frames"
    frames_dir.mkdir(parents=True, exist_ok=True)
    boot_offset_us = start_unix_us - int(round(boot_at_start_s * 1e6))

    stamps, t_list, ranges, oids, cam = [], [], [], [], None
    for i, (t_s, view, rend) in enumerate(render_flight(name, n_frames=int(n_frames), rate_hz=float(rate_hz),
                                                        size=size, seed=seed, supersample=supersample,
                                                        noise_sigma=noise_sigma, t0_s=frames_start_s)):
        cam = view.camera
        img = np.clip(np.round(view.image), 0, 255).astype(np.uint8)
        if not cv2.imwrite(str(frames_dir / f"{i:06d}.png"), img):
            raise InputError(f"cannot write {frames_dir / f'{i:06d}.png'}")
        stamps.append(start_unix_us + int(round(t_s * 1e6)))
        t_list.append(t_s)
        rng_m = np.where(rend.range_m < 60000.0, rend.range_m, np.inf)      # float16 max 65504
        ranges.append(rng_m.astype(np.float16))
        oids.append(rend.object_id.astype(np.int16))
    (frames_dir / "timestamps.txt").write_text("".join(f"{s // 1_000_000}.{s % 1_000_000:06d}\n" for s in stamps))

    t_end_s = t_list[-1] + 0.5
    counts = write_tlog(out / "flight.tlog", name, t_end_s, start_unix_us=start_unix_us,
                        boot_offset_us=boot_offset_us, origin_lla=origin_lla, latency_us=latency_us, seed=seed)
    (out / "cameras.json").write_text(json.dumps({camera_id: camera_to_dict(cam)}, indent=2))
    tr = nav_truth(name, np.array(t_list))
    np.savez_compressed(out / "truth.npz", stamp_us=np.array(stamps, np.int64), t_s=np.array(t_list),
                        range_m=np.stack(ranges), object_id=np.stack(oids),
                        position_ned_m=tr["position_ned_m"], q_wxyz=tr["q_wxyz"])
    manifest = {
        "flight": name, "n_frames": int(n_frames), "rate_hz": float(rate_hz), "seed": int(seed),
        "size": [cam.width, cam.height], "camera_id": camera_id,
        "frames": "frames", "timestamps": "frames/timestamps.txt", "tlog": "flight.tlog",
        "cameras": "cameras.json", "truth": "truth.npz",
        "start_unix_us": int(start_unix_us), "frame_t0_s": float(frames_start_s),
        "boot_offset_us": int(boot_offset_us), "boot_at_start_s": float(boot_at_start_s),
        "clock_note": "unix_us = t_s*1e6 + start_unix_us; time_boot_ms = (unix_us - boot_offset_us) // 1000; "
                      "tlog header = unix send time + latency in latency_us",
        "latency_us": [int(latency_us[0]), int(latency_us[1])],
        "origin_lla": [float(x) for x in origin_lla], "tlog_counts": counts,
        "nav_rates_hz": {"ATTITUDE": ATT_HZ, "ATTITUDE_QUATERNION": POS_HZ, "LOCAL_POSITION_NED": POS_HZ,
                         "GLOBAL_POSITION_INT": POS_HZ, "SYSTEM_TIME": 1.0, "HEARTBEAT": 1.0},
    }
    (out / "manifest.json").write_text(json.dumps(manifest, indent=2))
    return out
