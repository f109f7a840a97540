"""Continuous simulated flights with known attitude, for streaming tests.

``flight_states(name, t_s)`` gives the exact VehicleState at any times (closed-form, smooth trajectories: a
consumer may interpolate between samples); ``render_flight(name, n_frames=, rate_hz=)`` renders the frames.

Flights:
- "approach": straight low flight north at 20 m/s, 6 m up, with small smooth attitude oscillations,
  towards parked vehicles, poles and a building.
- "turning":  coordinated right turn, 15 m/s, 15 deg bank, past obstacles placed along the arc.
- "climbing": 20 m/s, pitching up from 2 to 10 deg and climbing (climb rate rising to 4 m/s) towards a
  tall building and a mast.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from eonav import InputError
from eonav.geometry.camera import Camera, VehicleState, View
from eonav.sim.scene import Box, Runway, Scene

FLIGHTS = ("approach", "turning", "climbing")
G_MPS2 = 9.81


@dataclass(frozen=True)
class Flight:
    name: str
    scene: Scene
    camera: Camera
    description: str


def _camera(tilt_deg: float) -> Camera:
    from eonav.sim.presets import _nose_camera
    return _nose_camera(tilt_deg=tilt_deg)


def _approach_states(t):
    speed = 20.0
    north = -60.0 + speed * t
    east = 1.5 * np.sin(0.4 * t)
    down = -6.0 - 0.3 * np.sin(0.7 * t)
    yaw = np.deg2rad(0.6) * np.sin(0.5 * t)
    pitch = np.deg2rad(1.0 + 0.5 * np.sin(1.3 * t))
    roll = np.deg2rad(1.5) * np.sin(0.9 * t)
    return np.stack([north, east, down], -1), np.stack([yaw, pitch, roll], -1)


_TURN_SPEED, _TURN_BANK = 15.0, np.deg2rad(15.0)
_TURN_RATE = G_MPS2 * np.tan(_TURN_BANK) / _TURN_SPEED          # coordinated turn, rad/s
_TURN_RADIUS = _TURN_SPEED / _TURN_RATE


def _turning_states(t):
    psi = _TURN_RATE * t
    pos = np.stack([_TURN_RADIUS * np.sin(psi), _TURN_RADIUS * (1 - np.cos(psi)), np.full_like(t, -8.0)], -1)
    return pos, np.stack([psi, np.zeros_like(t), np.full_like(t, _TURN_BANK)], -1)


def _climbing_states(t):
    speed, tau = 20.0, 1.0
    climb_rate_final = 4.0
    down = -5.0 - climb_rate_final * (t - tau * (1 - np.exp(-t / tau)))   # climb rate 4 (1 - e^(-t/tau)) m/s
    pitch = np.deg2rad(2.0 + 8.0 * (1 - np.exp(-t / 0.7)))
    pos = np.stack([-40.0 + speed * t, np.full_like(t, -2.0), down], -1)
    return pos, np.stack([np.zeros_like(t), pitch, np.zeros_like(t)], -1)


_STATES = {"approach": _approach_states, "turning": _turning_states, "climbing": _climbing_states}


def _turn_point(arc_m: float, offset_m: float):
    """NED (north, east) on the turning flight's arc after arc_m metres, offset_m outward (left, + = outside)."""
    psi = arc_m / _TURN_RADIUS
    r = _TURN_RADIUS + offset_m
    return r * np.sin(psi), _TURN_RADIUS - r * np.cos(psi), np.rad2deg(psi)


def flight(name: str) -> Flight:
    """Scene, camera and description of a named flight."""
    if name == "approach":
        boxes = (Box.on_ground("truck", 60.0, -9.0, 7.0, 2.5, 3.0, yaw_deg=5.0, albedo=100.0),
                 Box.on_ground("van", 95.0, 8.0, 5.0, 2.0, 2.2, yaw_deg=-25.0, albedo=150.0),
                 Box.on_ground("pole", 75.0, 3.0, 0.3, 0.3, 10.0, albedo=70.0, contrast=15.0),
                 Box.on_ground("mast", 140.0, -3.0, 0.5, 0.5, 18.0, albedo=60.0, contrast=15.0),
                 Box.on_ground("building", 230.0, 0.0, 20.0, 40.0, 15.0, yaw_deg=3.0, albedo=150.0))
        return Flight(name, Scene(boxes, Runway(15.0, -300.0, 2500.0), seed=10), _camera(-4.0),
                      "straight low flight north at 20 m/s, 6 m up, towards vehicles, poles and a building")
    if name == "turning":
        specs = [("truck", 50.0, 9.0, (7.0, 2.5, 3.0), 100.0), ("pole", 70.0, -2.0, (0.3, 0.3, 12.0), 70.0),
                 ("building", 110.0, 20.0, (15.0, 12.0, 10.0), 150.0), ("van", 90.0, -12.0, (5.0, 2.0, 2.2), 130.0),
                 ("mast", 150.0, 3.0, (0.5, 0.5, 20.0), 60.0)]
        boxes = []
        for bname, arc, off, (ln, wd, ht), alb in specs:
            n, e, yaw_deg = _turn_point(arc, off)
            boxes.append(Box.on_ground(bname, n, e, ln, wd, ht, yaw_deg=yaw_deg, albedo=alb))
        return Flight(name, Scene(tuple(boxes), Runway(15.0, -300.0, 2500.0), seed=11), _camera(-5.0),
                      "coordinated right turn, 15 m/s, 15 deg bank, yaw rate %.1f deg/s" % np.rad2deg(_TURN_RATE))
    if name == "climbing":
        boxes = (Box.on_ground("building", 110.0, 6.0, 20.0, 25.0, 30.0, yaw_deg=5.0, albedo=150.0),
                 Box.on_ground("mast", 70.0, -8.0, 0.5, 0.5, 25.0, albedo=70.0, contrast=15.0),
                 Box.on_ground("truck", 40.0, -14.0, 7.0, 2.5, 3.0, yaw_deg=-30.0, albedo=100.0))
        return Flight(name, Scene(boxes, Runway(15.0, -300.0, 2500.0), seed=12), _camera(-6.0),
                      "climb at 20 m/s: pitch 2 -> 10 deg, climb rate rising to 4 m/s")
    raise InputError(f"unknown flight {name!r}; expected one of {', '.join(FLIGHTS)}")


def flight_states(name: str, t_s) -> list:
    """Exact VehicleState of flight ``name`` at each time in ``t_s`` (seconds from the flight start, >= 0)."""
    if name not in _STATES:
        raise InputError(f"unknown flight {name!r}; expected one of {', '.join(FLIGHTS)}")
    t = np.atleast_1d(np.asarray(t_s, float))
    if t.ndim != 1 or not np.all(np.isfinite(t)) or np.any(t < 0):
        raise InputError("flight_states: t_s must be finite times >= 0 s (scalar or 1-D)")
    pos, ypr = _STATES[name](t)
    return [VehicleState.from_ypr(p, a, float(ti)) for p, a, ti in zip(pos, ypr, t)]


def render_flight(name: str, *, n_frames: int, rate_hz: float, size=None, seed: int = 0,
                  supersample: int = 3, noise_sigma: float = 1.0, t0_s: float = 0.0):
    """Yield (t_s, View, Render) for frames at t0_s + i / rate_hz, i < n_frames. Sensor noise of frame i uses
    seed (seed, i)."""
    from eonav.sim.presets import scale_camera
    from eonav.sim.render import render
    if int(n_frames) != n_frames or n_frames < 1:
        raise InputError(f"render_flight: n_frames must be a whole number >= 1, got {n_frames!r}")
    if not (np.isfinite(rate_hz) and rate_hz > 0):
        raise InputError(f"render_flight: rate_hz must be > 0, got {rate_hz!r}")
    fl = flight(name)
    cam = scale_camera(fl.camera, size)
    times = t0_s + np.arange(int(n_frames)) / float(rate_hz)
    for i, state in enumerate(flight_states(name, times)):
        noise_seed = int(np.random.SeedSequence([int(seed), i]).generate_state(1)[0])
        r = render(fl.scene, cam, state, supersample=supersample, noise_sigma=noise_sigma, seed=noise_seed)
        yield float(times[i]), View(cam, state, r.image), r
