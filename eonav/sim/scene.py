"""Scene description for the simulator: a ground plane (NED z = 0) with an optional runway, boxes standing
on it (vehicles, buildings, poles), sky at infinity, a sun and haze.

Object ids (``Render.object_id``): 0 sky, 1 ground (runway included), 2 + i the i-th box.
All coordinates NED metres; a box is centred at ``center_ned_m`` with half extents along its own axes
(x forward = north when yaw is 0, y right, z down) and yawed by ``yaw_rad`` about the down axis.
"""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from eonav import InputError

SKY_ID = 0
GROUND_ID = 1
FIRST_BOX_ID = 2


@dataclass(frozen=True)
class Box:
    """A textured box. ``size_m`` = (length along its x, width along its y, height) in metres."""
    name: str
    center_ned_m: tuple
    size_m: tuple
    yaw_rad: float = 0.0
    albedo: float = 120.0          # mean grey level in full sun
    contrast: float = 30.0         # texture std in grey levels

    def __post_init__(self):
        c = np.asarray(self.center_ned_m, float).reshape(3)
        s = np.asarray(self.size_m, float).reshape(3)
        if not (np.all(np.isfinite(c)) and np.all(s > 0) and np.isfinite(self.yaw_rad)):
            raise InputError(f"box {self.name!r}: center must be finite and size_m positive, "
                             f"got center={c.tolist()} size={s.tolist()}")
        object.__setattr__(self, "center_ned_m", tuple(c.tolist()))
        object.__setattr__(self, "size_m", tuple(s.tolist()))

    @classmethod
    def on_ground(cls, name, north_m, east_m, length_m, width_m, height_m, yaw_deg=0.0, **kw) -> "Box":
        """A box standing on the ground (bottom face at z = 0), centred at (north_m, east_m)."""
        return cls(name, (north_m, east_m, -0.5 * height_m), (length_m, width_m, height_m),
                   float(np.deg2rad(yaw_deg)), **kw)

    @property
    def R_ned_local(self) -> np.ndarray:
        """Rotation box-local -> NED (yaw about down)."""
        c, s = np.cos(self.yaw_rad), np.sin(self.yaw_rad)
        return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])

    @property
    def half_m(self) -> np.ndarray:
        return 0.5 * np.asarray(self.size_m)


@dataclass(frozen=True)
class Runway:
    """A paved runway along north, centred on east = 0, from north0_m to north1_m, with painted markings."""
    half_width_m: float = 15.0
    north0_m: float = -300.0
    north1_m: float = 2500.0


@dataclass(frozen=True)
class Scene:
    boxes: tuple = ()
    runway: Runway | None = field(default_factory=Runway)
    seed: int = 0                                        # texture seed (same scene -> same texture)
    sun_ned: tuple = (-0.45, 0.35, -0.82)                # direction towards the sun (unit after normalising)
    visibility_m: float = 4000.0                         # haze: contrast falls as exp(-distance / visibility)
    sky_horizon_grey: float = 205.0
    sky_zenith_grey: float = 150.0

    def __post_init__(self):
        object.__setattr__(self, "boxes", tuple(self.boxes))
        names = [b.name for b in self.boxes]
        if len(set(names)) != len(names):
            raise InputError(f"scene: box names must be unique, got {names}")
        s = np.asarray(self.sun_ned, float)
        object.__setattr__(self, "sun_ned", tuple((s / np.linalg.norm(s)).tolist()))

    @property
    def objects(self) -> dict:
        """Object id -> name, for every id a render can produce."""
        out = {SKY_ID: "sky", GROUND_ID: "ground"}
        out.update({FIRST_BOX_ID + i: b.name for i, b in enumerate(self.boxes)})
        return out
