"""Every zenoh key expression eonav uses, built in one place: ``eonav/<vehicle>/<subject>...``.

One function per key (``frame(vehicle, camera_id)``, ``nav_state(vehicle)``, ``range_map(vehicle, camera_id)``,
``obstacles(vehicle)``, ``health``, ``alive``, ``config``, ...) and a wildcard form for subscribers
(``frames_all``, ``range_maps_all``, ...); the table of keys, producers and messages is in docs/bus.md. Names must be
one plain key chunk (``check_chunk``). Plain strings, no zenoh import: the math and the schema never load the
transport.
"""
from __future__ import annotations

import re

from eonav import InputError

ROOT = "eonav"
_CHUNK = re.compile(r"^[A-Za-z0-9_\-.]+$")


def check_chunk(name: str, what: str = "key chunk") -> str:
    """A vehicle, camera or service name must be one plain key chunk (no '/', '*', '$', '#', '?', '@')."""
    if not isinstance(name, str) or not _CHUNK.match(name):
        raise InputError(f"{what} {name!r}: expected letters, digits, '_', '-' or '.' only")
    return name


def _v(vehicle: str) -> str:
    return f"{ROOT}/{check_chunk(vehicle, 'vehicle')}"


def frame(vehicle: str, camera_id: str) -> str:
    return f"{_v(vehicle)}/camera/{check_chunk(camera_id, 'camera id')}/frame"


def frames_all(vehicle: str) -> str:
    return f"{_v(vehicle)}/camera/*/frame"


def nav_state(vehicle: str) -> str:
    return f"{_v(vehicle)}/nav/state"


def nav_clock(vehicle: str) -> str:
    return f"{_v(vehicle)}/nav/clock"


def posed_frame(vehicle: str, camera_id: str) -> str:
    return f"{_v(vehicle)}/posed/{check_chunk(camera_id, 'camera id')}/frame"


def posed_frames_all(vehicle: str) -> str:
    return f"{_v(vehicle)}/posed/*/frame"


def range_map(vehicle: str, camera_id: str) -> str:
    return f"{_v(vehicle)}/range/{check_chunk(camera_id, 'camera id')}"


def range_maps_all(vehicle: str) -> str:
    return f"{_v(vehicle)}/range/*"


def obstacles(vehicle: str) -> str:
    return f"{_v(vehicle)}/obstacles"


def obstacle_tracks(vehicle: str) -> str:
    return f"{_v(vehicle)}/obstacles/tracks"


def health(vehicle: str, service: str) -> str:
    return f"{_v(vehicle)}/health/{check_chunk(service, 'service')}"


def health_all(vehicle: str) -> str:
    return f"{_v(vehicle)}/health/*"


def alive(vehicle: str, service: str) -> str:
    return f"{_v(vehicle)}/alive/{check_chunk(service, 'service')}"


def alive_all(vehicle: str) -> str:
    return f"{_v(vehicle)}/alive/*"


def config(vehicle: str, service: str) -> str:
    return f"{_v(vehicle)}/config/{check_chunk(service, 'service')}"


def vehicle_all(vehicle: str) -> str:
    return f"{_v(vehicle)}/**"
