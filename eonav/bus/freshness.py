"""Stale and out-of-order outputs are never published: the age gate every pipeline stage puts its messages through.

A stage (sync, locator, obstacles) asks :meth:`FreshnessGate.check` twice per message: when an input arrives
(``arrival``) and just before its output would be published (``publish``). ``check`` gives the reason to drop it, or
None: ``too_old`` (the capture stamp is older than the stage's ``max_age_s`` on this host's clock), ``future_stamp``
(more than ``max_ahead_s`` ahead of the clock: a wrong clock or a forged stamp, never "fresh"), ``out_of_order``
(older than the last output published for the same camera, e.g. a replay that started over). :meth:`commit` records
a published output. A camera whose last published stamp is more than ``max_ahead_s`` ahead of the clock (the host
clock was stepped back) starts afresh, so one jump cannot blind a camera for longer than that. Pure: the clock is
injected. Defaults and the latency budget behind them: docs/bus.md, "Staleness".
"""
from __future__ import annotations

import logging
import math
import threading
import time
from typing import Callable

from eonav import InputError

__all__ = ["FreshnessGate", "screen", "age_ms", "REASONS", "DEFAULT_MAX_AHEAD_S"]

REASONS = ("too_old", "future_stamp", "out_of_order")
DEFAULT_MAX_AHEAD_S = 1.0


def _now_us() -> int:
    return time.time_ns() // 1000


def age_ms(stamp_us: int, now_us: int | None = None) -> float:
    """Age of a capture stamp in milliseconds on this host's realtime clock (negative: stamped in the future)."""
    return ((_now_us() if now_us is None else now_us) - int(stamp_us)) / 1e3


class FreshnessGate:
    """Per-stage age limit plus a per-camera watermark of the newest published capture stamp (thread-safe)."""

    def __init__(self, max_age_s: float, max_ahead_s: float = DEFAULT_MAX_AHEAD_S,
                 clock_us: Callable[[], int] = _now_us):
        if not (isinstance(max_age_s, (int, float)) and math.isfinite(max_age_s) and max_age_s > 0):
            raise InputError(f"max age must be a finite number of seconds > 0, got {max_age_s!r}")
        if not (isinstance(max_ahead_s, (int, float)) and math.isfinite(max_ahead_s) and max_ahead_s >= 0):
            raise InputError(f"max ahead must be a finite number of seconds >= 0, got {max_ahead_s!r}")
        self.max_age_us = int(round(max_age_s * 1e6))
        self.max_ahead_us = int(round(max_ahead_s * 1e6))
        self._clock = clock_us
        self._last: dict[str, int] = {}
        self._lock = threading.Lock()

    @property
    def max_age_s(self) -> float:
        return self.max_age_us / 1e6

    def now_us(self) -> int:
        return int(self._clock())

    def check(self, camera: str, stamp_us: int, now_us: int | None = None) -> str | None:
        """The reason to drop a message of ``camera`` stamped ``stamp_us`` now, or None to let it through."""
        now = self.now_us() if now_us is None else int(now_us)
        stamp = int(stamp_us)
        if stamp > now + self.max_ahead_us:
            return "future_stamp"
        if now - stamp > self.max_age_us:
            return "too_old"
        with self._lock:
            last = self._last.get(camera)
            if last is not None and last > now + self.max_ahead_us:
                del self._last[camera]          # the clock was stepped back: start this camera afresh
                last = None
        if last is not None and stamp < last:
            return "out_of_order"
        return None

    def commit(self, camera: str, stamp_us: int) -> None:
        """Record that an output of ``camera`` stamped ``stamp_us`` was published."""
        with self._lock:
            last = self._last.get(camera)
            if last is None or int(stamp_us) > last:
                self._last[camera] = int(stamp_us)

    def last_published_us(self, camera: str) -> int | None:
        with self._lock:
            return self._last.get(camera)


def screen(metrics, gate: FreshnessGate, camera: str, stamp_us: int, where: str) -> bool:
    """``gate.check`` for a service: True to go on; else the drop is counted as ``dropped.<reason>`` on ``metrics``
    (a ``Node``), logged at a limited rate naming ``where`` (``arrival`` or ``publish``), and False."""
    now = gate.now_us()
    reason = gate.check(camera, stamp_us, now)
    if reason is None:
        return True
    metrics.count(f"dropped.{reason}")
    metrics.log_limited(f"fresh:{where}:{reason}", logging.WARNING,
                        "camera %s frame stamped %d dropped at %s: %s (age %.0f ms, max %.0f ms)", camera,
                        int(stamp_us), where, reason, age_ms(stamp_us, now), gate.max_age_us / 1e3)
    return False
