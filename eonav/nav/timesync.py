"""Time association and pose interpolation: frames (capture stamps) against navigation samples.

Pure numpy; stamps are integer microseconds on the companion clock (``stamp_us``).

- ``match_stamps(a_us, b_us, max_diff_us, offset_us=0)``: one-to-one nearest-neighbour association of two stamp
  lists, accepted greedily from the closest pair within ``max_diff_us``, each index used once.
- ``NavBuffer``: attitude and position as separate sorted, bounded streams (they arrive in separate messages with
  their own stamps). ``pose_at(t)`` interpolates each at the frame time: attitude by slerp (shortest path, so yaw
  wraps at +-180 deg), position linearly or by cubic Hermite when both samples carry a velocity. ``decide(t)`` is
  the watermark test for a pending frame: ``ready``, ``wait`` (the newest sample is still older than t) or
  ``never`` with a reason; bounded forward extrapolation is allowed only on request and flagged.
  ``PoseResult.quality_flags`` holds the ``QF_*`` bits (docs/bus.md, "Sync").
"""
from __future__ import annotations

import bisect
import math
from collections import Counter
from dataclasses import dataclass, field
from typing import Callable

import numpy as np

from eonav import InputError
from eonav.geometry.frames import slerp_quat_wxyz

QF_EXTRAPOLATED = 1
QF_GAP = 2
QF_JITTER = 4
QF_VELOCITY_AIDED = 8
QF_NO_VELOCITY = 16
QUALITY_FLAGS = {"extrapolated": QF_EXTRAPOLATED, "gap": QF_GAP, "jitter": QF_JITTER,
                 "velocity_aided": QF_VELOCITY_AIDED, "no_velocity": QF_NO_VELOCITY}


def _stamps(x, name: str) -> np.ndarray:
    a = np.asarray(x)
    if a.ndim != 1:
        raise InputError(f"{name}: expected a 1-D list of integer microsecond stamps, got shape {a.shape}")
    if a.size and not np.issubdtype(a.dtype, np.integer):
        if not np.all(np.isfinite(a.astype(float))):
            raise InputError(f"{name}: stamps must be finite")
        if np.any(a != np.round(a)):
            raise InputError(f"{name}: stamps must be whole microseconds")
    return a.astype(np.int64)


def match_stamps(a_us, b_us, max_diff_us: int, offset_us: int = 0) -> list:
    """One-to-one association of stamps ``a_us`` and ``b_us`` (any order, duplicates allowed).

    ``b + offset_us`` is compared with ``a`` (offset maps b's clock onto a's). Pairs with
    ``|a_i - (b_j + offset_us)| <= max_diff_us`` are taken greedily from the smallest difference
    (ties: smaller i, then smaller j), each index at most once. Returns ``[(i, j), ...]`` sorted by i.
    """
    if not (isinstance(max_diff_us, (int, np.integer, float)) and max_diff_us >= 0):
        raise InputError(f"max_diff_us must be a non-negative number of microseconds, got {max_diff_us!r}")
    a = _stamps(a_us, "a_us")
    b = _stamps(b_us, "b_us") + np.int64(offset_us)
    if a.size == 0 or b.size == 0:
        return []
    order = np.argsort(b, kind="stable")
    bs = b[order]
    cands = []
    for i, t in enumerate(a):
        lo = np.searchsorted(bs, t - max_diff_us, "left")
        hi = np.searchsorted(bs, t + max_diff_us, "right")
        for k in range(lo, hi):
            j = int(order[k])
            cands.append((abs(int(t) - int(bs[k])), i, j))
    cands.sort()
    used_a, used_b, out = set(), set(), []
    for _, i, j in cands:
        if i not in used_a and j not in used_b:
            used_a.add(i)
            used_b.add(j)
            out.append((i, j))
    return sorted(out)


@dataclass
class PoseResult:
    """Pose at ``stamp_us``; ``ok`` False with ``reason`` when there is none."""
    stamp_us: int
    ok: bool
    reason: str = ""
    position_ned_m: np.ndarray = field(default_factory=lambda: np.full(3, np.nan))
    q_wxyz: np.ndarray = field(default_factory=lambda: np.full(4, np.nan))
    velocity_ned_mps: np.ndarray = field(default_factory=lambda: np.full(3, np.nan))
    nav_gap_us: int = 0
    quality_flags: int = 0


@dataclass
class Decision:
    state: str          # "ready" | "wait" | "never"
    reason: str = ""


class _Stream:
    """One sorted, bounded stream of (stamp, value[, velocity])."""

    def __init__(self, name: str, max_samples: int):
        self.name, self.max_samples = name, max_samples
        self.t: list = []
        self.v: list = []
        self.vel: list = []
        self.evicted_until_us: int | None = None      # newest stamp ever evicted

    def __len__(self):
        return len(self.t)

    def add(self, t_us: int, value, vel=None) -> str:
        if self.evicted_until_us is not None and t_us <= self.evicted_until_us:
            return "too_old"
        k = bisect.bisect_left(self.t, t_us)
        if k < len(self.t) and self.t[k] == t_us:
            return "duplicate_stamp"
        out_of_order = k < len(self.t)
        self.t.insert(k, t_us)
        self.v.insert(k, value)
        self.vel.insert(k, vel)
        if len(self.t) > self.max_samples:
            self.evicted_until_us = self.t.pop(0)
            self.v.pop(0)
            self.vel.pop(0)
        return "out_of_order" if out_of_order else ""

    @property
    def newest_us(self) -> int | None:
        return self.t[-1] if self.t else None

    def median_spacing_us(self, k: int) -> float:
        """Median spacing of the up-to-16 intervals around index k."""
        lo, hi = max(0, k - 8), min(len(self.t), k + 9)
        d = np.diff(self.t[lo:hi])
        return float(np.median(d)) if d.size else math.nan

    def decide(self, t_us: int, max_extrap_us: int, max_gap_us: int) -> Decision:
        if not self.t:
            return Decision("wait", f"no_{self.name}_yet")
        if self.evicted_until_us is not None and t_us <= self.evicted_until_us:
            return Decision("never", "older_than_buffer")
        if t_us < self.t[0]:
            if self.t[0] - t_us <= max_extrap_us:
                return Decision("ready")
            return Decision("never", "before_first_nav")
        if t_us > self.t[-1]:
            return Decision("wait", f"waiting_for_{self.name}")
        k = bisect.bisect_left(self.t, t_us)
        if self.t[k] == t_us:
            return Decision("ready")
        if self.t[k] - self.t[k - 1] > max_gap_us:
            return Decision("never", "gap")
        return Decision("ready")

    def bracket(self, t_us: int):
        """(i0, i1, s, gap_us, extrapolation_us): interpolation weights for t; i0 == i1 for exact hits
        and single-sample streams. s may lie outside [0, 1] when extrapolating."""
        n = len(self.t)
        if n == 1:
            return 0, 0, 0.0, 0, abs(t_us - self.t[0])
        if t_us <= self.t[0]:
            i0, i1 = 0, 1
        elif t_us >= self.t[-1]:
            i0, i1 = n - 2, n - 1
        else:
            k = bisect.bisect_left(self.t, t_us)
            if self.t[k] == t_us:
                return k, k, 0.0, 0, 0
            i0, i1 = k - 1, k
        t0, t1 = self.t[i0], self.t[i1]
        ex = max(0, self.t[0] - t_us, t_us - self.t[-1])
        return i0, i1, (t_us - t0) / (t1 - t0), t1 - t0, ex


class NavBuffer:
    """Attitude and position streams for interpolating a pose at a frame's capture time.

    ``max_extrapolation_us``: the farthest a pose may be extrapolated beyond the samples (20 ms).
    ``max_gap_us``: the largest bracket gap accepted (250 ms); ``gap_warn_us`` flags QF_GAP (60 ms).
    ``require_position``: a pose needs a position stream (True) or attitude alone is enough.
    ``clock_us`` (host UNIX us now) with ``max_future_us``: a sample stamped further ahead than that is refused
    (``future_stamp``): one bogus far-future sample would otherwise sit in the stream for good and turn every
    later frame's bracket into a gap.
    """

    def __init__(self, max_samples: int = 4096, max_extrapolation_us: int = 20_000, max_gap_us: int = 250_000,
                 gap_warn_us: int = 60_000, require_position: bool = True,
                 clock_us: Callable[[], int] | None = None, max_future_us: int = 5_000_000):
        if max_samples < 2:
            raise InputError(f"max_samples {max_samples}: expected at least 2")
        if max_extrapolation_us < 0 or max_gap_us <= 0:
            raise InputError("max_extrapolation_us must be >= 0 and max_gap_us > 0 (microseconds)")
        self.att = _Stream("attitude", max_samples)
        self.pos = _Stream("position", max_samples)
        self.max_extrapolation_us = int(max_extrapolation_us)
        self.max_gap_us = int(max_gap_us)
        self.gap_warn_us = int(gap_warn_us)
        self.require_position = require_position
        self.clock_us, self.max_future_us = clock_us, int(max_future_us)
        self.counts: Counter = Counter()      # add outcomes: attitude, position, duplicate_stamp, ...

    # ------------------------------------------------------------------ input
    def add(self, stamp_us: int, q_wxyz=None, position_ned_m=None, velocity_ned_mps=None) -> None:
        """Add one navigation sample; absent or non-finite parts are ignored (counted)."""
        t = int(stamp_us)
        if self.clock_us is not None and t > self.clock_us() + self.max_future_us:
            self.counts["future_stamp"] += 1
            return
        if q_wxyz is not None:
            q = np.asarray(q_wxyz, float).reshape(4)
            n = float(np.linalg.norm(q)) if np.all(np.isfinite(q)) else math.nan
            if math.isfinite(n) and abs(n - 1.0) < 1e-2:
                r = self.att.add(t, q / n)
                self.counts[r or "attitude"] += 1
                if r == "out_of_order":
                    self.counts["attitude"] += 1
            elif not np.all(np.isnan(q)):
                self.counts["bad_attitude"] += 1
        if position_ned_m is not None:
            p = np.asarray(position_ned_m, float).reshape(3)
            if np.all(np.isfinite(p)):
                v = None if velocity_ned_mps is None else np.asarray(velocity_ned_mps, float).reshape(3)
                r = self.pos.add(t, p, v if v is not None and np.all(np.isfinite(v)) else None)
                self.counts[r or "position"] += 1
                if r == "out_of_order":
                    self.counts["position"] += 1
            elif not np.all(np.isnan(p)):
                self.counts["bad_position"] += 1

    def add_state(self, msg: dict) -> None:
        """Add a decoded nav_state message (schema.decode output)."""
        self.add(msg["stamp_us"], msg.get("q_wxyz"), msg.get("position_ned_m"), msg.get("velocity_ned_mps"))

    # ------------------------------------------------------------------ watermark
    def _streams(self):
        return (self.att, self.pos) if self.require_position else (self.att,)

    @property
    def watermark_us(self) -> int | None:
        """The newest time every needed stream has reached (None before all have a sample)."""
        newest = [s.newest_us for s in self._streams()]
        return None if any(x is None for x in newest) else min(newest)

    def decide(self, t_us: int) -> Decision:
        """ready / wait / never for a frame at t_us (see module docstring)."""
        ds = [s.decide(int(t_us), self.max_extrapolation_us, self.max_gap_us) for s in self._streams()]
        for d in ds:
            if d.state == "never":
                return d
        for d in ds:
            if d.state == "wait":
                return d
        return Decision("ready")

    # ------------------------------------------------------------------ interpolation
    def jitter_us(self, stream: str = "attitude") -> float:
        """Standard deviation of the sample spacing of a stream (us)."""
        s = self.att if stream == "attitude" else self.pos
        return float(np.std(np.diff(s.t))) if len(s) > 2 else math.nan

    def pose_at(self, t_us: int, allow_extrapolation: bool = False) -> PoseResult:
        """Interpolated pose at t_us, or ok=False with a reason.

        Without ``allow_extrapolation`` the frame must be ``ready`` (see ``decide``); with it, a
        frame past the newest sample may be extrapolated by up to ``max_extrapolation_us``."""
        t = int(t_us)
        d = self.decide(t)
        if d.state == "never":
            return PoseResult(t, False, d.reason)
        if d.state == "wait":
            if not allow_extrapolation:
                return PoseResult(t, False, d.reason)
            for s in self._streams():
                if not len(s):
                    return PoseResult(t, False, f"no_{s.name}_yet")
                if t - s.newest_us > self.max_extrapolation_us:
                    return PoseResult(t, False, "extrapolation_limit")
        flags, gap = 0, 0
        # attitude: slerp (shortest arc; extrapolation continues the same great circle)
        i0, i1, s, g, ex = self.att.bracket(t)
        q = self.att.v[i0] if i0 == i1 else slerp_quat_wxyz(self.att.v[i0], self.att.v[i1], s)
        q = q if q[0] >= 0 else -q
        gap = max(gap, g)
        flags |= self._flags(self.att, i1, g, ex)
        pos, vel = np.full(3, np.nan), np.full(3, np.nan)
        if len(self.pos):
            j0, j1, s, g, ex = self.pos.bracket(t)
            p0, p1 = self.pos.v[j0], self.pos.v[j1]
            v0, v1 = self.pos.vel[j0], self.pos.vel[j1]
            dt_s = (self.pos.t[j1] - self.pos.t[j0]) * 1e-6
            if j0 == j1:
                pos = p0 + (v0 * (t - self.pos.t[j0]) * 1e-6 if v0 is not None else 0.0)
                vel = v0 if v0 is not None else vel
            elif v0 is not None and v1 is not None and 0.0 <= s <= 1.0:
                # cubic Hermite with end velocities (exact for motion up to cubic in time)
                h00, h10 = 2 * s**3 - 3 * s**2 + 1, s**3 - 2 * s**2 + s
                h01, h11 = -2 * s**3 + 3 * s**2, s**3 - s**2
                pos = h00 * p0 + h10 * dt_s * v0 + h01 * p1 + h11 * dt_s * v1
                dh00, dh10 = (6 * s**2 - 6 * s) / dt_s, 3 * s**2 - 4 * s + 1
                dh01, dh11 = (-6 * s**2 + 6 * s) / dt_s, 3 * s**2 - 2 * s
                vel = dh00 * p0 + dh10 * v0 + dh01 * p1 + dh11 * v1
                flags |= QF_VELOCITY_AIDED
            else:
                pos = p0 + s * (p1 - p0)
                if v0 is not None and v1 is not None:
                    vel = v0 + s * (v1 - v0)
                else:
                    vel = (p1 - p0) / dt_s
            gap = max(gap, g)
            flags |= self._flags(self.pos, j1, g, ex)
        if not np.all(np.isfinite(vel)):
            flags |= QF_NO_VELOCITY
        return PoseResult(t, True, "", np.asarray(pos, float), np.asarray(q, float), np.asarray(vel, float),
                          int(gap), flags)

    def _flags(self, stream: _Stream, k: int, gap_us: int, extrap_us: int) -> int:
        f = 0
        if extrap_us > 0:
            f |= QF_EXTRAPOLATED
        if gap_us > self.gap_warn_us:
            f |= QF_GAP
        med = stream.median_spacing_us(k)
        if gap_us > 0 and math.isfinite(med) and gap_us > 1.5 * med:
            f |= QF_JITTER
        return f
