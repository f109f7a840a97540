"""Adaptive locate scale: a pure controller choosing, per camera and per pair, the scale the locator ranges at.

``ScaleController`` picks the largest rung of a ladder (1.0, 0.5, ... ``min_scale``) whose measured compute time fits a
latency budget: ``budget_s``, else ``budget_fraction`` (0.6) of the camera's measured frame interval, clamped to
``budget_bounds_s``. Guidance needs bounded latency more than pixel detail, but a fixed half scale throws accuracy
away when the machine has headroom. After each pair (``observe_compute``) it steps down one rung when the current
rung's recent median exceeds the budget, and up one rung only when the predicted cost there (the current median times
the learnt cost ratio of the two rungs, area-proportional until measured) stays below ``up_margin`` (0.7) of the
budget for ``up_after`` pairs in a row: between the two nothing changes, so a cost at the boundary does not
oscillate. ``calibrate`` takes one timed locate per rung, made before the camera's first pair, to choose the starting
rung and seed the cost ratios. No zenoh, no images: the locator owns one controller per camera.

A median compute budget does not bound the tail guidance sees: the locator's time per frame also holds the decode,
the encode and put, and the time it lost to other processes. With ``latency_target_s`` the controller also gets that
time for each published map (``observe_latency``: frame taken off the ring -> map put) and steps down one rung when
the recent ``latency_q`` quantile (0.9) of ``latency_window`` maps (30) exceeds the target; it steps up only when both the compute and the
latency predicted at the rung above (the current quantile, over a whole window, times the rungs' cost ratio) stay
below ``up_margin`` of their limits.

The margin that keeps a rung at the boundary from oscillating also keeps the controller from coming back to a rung
it held until a transient (a burst of load from another process, a pause) pushed it off: at 30 fps 640 x 480 the
half-scale locator runs at ~80 % of its latency target, above the margin, and one two-second burst left it at the
lowest rung for the rest of the run. So the controller remembers the highest rung it has held for ``hold_s`` of
frame time (the camera's stamps, ``observe_frame``) and, while below it, probes the rung above after ``probe_s`` at
the lower one: it steps up and lets the usual rules judge it. A step up (a probe or the rule above) pushed off again
within ``hold_s`` doubles the wait before the next step up, up to ``probe_max_s``, and the rule above waits it too
(under a load that stays, its cost ratios, learnt at the changes, can predict a fit that is not there); a rung that
holds resets the wait. A rung never held (too costly from the start) is never probed, and a load that stays costs
at most one verdict's worth of late maps per ``probe_max_s``. Without frame stamps nothing is probed.
"""
from __future__ import annotations

import math
from collections import deque
from dataclasses import dataclass

from eonav import InputError

AUTO = "auto"


def parse_scale(value) -> float | None:
    """``--scale`` value -> None for ``auto`` or a float in (0, 1]. Raises InputError."""
    if value is None or (isinstance(value, str) and value.strip().lower() == AUTO):
        return None
    try:
        s = float(value)
    except (TypeError, ValueError):
        raise InputError(f"--scale must be 'auto' or a number in (0, 1], got {value!r}") from None
    if not (math.isfinite(s) and 0 < s <= 1):
        raise InputError(f"--scale must be 'auto' or a number in (0, 1], got {value!r}")
    return s


def ladder(min_scale: float = 0.5) -> tuple:
    """1.0, 0.5, 0.25, ... while >= ``min_scale``, with ``min_scale`` itself as the lowest rung."""
    if not (math.isfinite(min_scale) and 0 < min_scale <= 1):
        raise InputError(f"--min-scale must be in (0, 1], got {min_scale!r}")
    out, s = [], 1.0
    while s >= min_scale - 1e-12:
        out.append(s)
        s /= 2
    if out[-1] > min_scale + 1e-12:
        out.append(float(min_scale))
    return tuple(out)


@dataclass(frozen=True)
class ScaleChange:
    old: float
    new: float
    reason: str
    probe: bool = False            # a step up that probes a rung held before (module docstring)

    @property
    def direction(self) -> str:
        return "down" if self.new < self.old else "up"


class ScaleController:
    """Per-camera scale choice (see the module docstring). Not thread-safe (one locator thread)."""

    def __init__(self, *, fixed: float | None = None, min_scale: float = 0.5, budget_s: float | None = None,
                 budget_fraction: float = 0.6, budget_bounds_s: tuple = (0.02, 0.2), window: int = 5,
                 min_samples: int = 3, up_after: int = 5, up_margin: float = 0.7, interval_window: int = 15,
                 latency_target_s: float | None = None, latency_window: int = 30, latency_min_samples: int = 10,
                 latency_q: float = 0.9, probe_s: float = 5.0, probe_max_s: float = 60.0, hold_s: float = 2.0):
        if fixed is not None:
            fixed = parse_scale(fixed)
        if budget_s is not None and not (math.isfinite(budget_s) and budget_s > 0):
            raise InputError(f"--budget-ms must be > 0, got {budget_s * 1e3!r}")
        lo, hi = budget_bounds_s
        if not (0 < lo <= hi):
            raise InputError(f"budget bounds must be 0 < low <= high, got {budget_bounds_s!r}")
        if not (0 < up_margin < 1 and 0 < budget_fraction and window >= 1 and 1 <= min_samples <= window
                and up_after >= 1 and 1 <= latency_min_samples <= latency_window and 0 < latency_q <= 1):
            raise InputError("scale controller: bad tuning parameters")
        if not (0 < probe_s <= probe_max_s and math.isfinite(probe_max_s) and 0 < hold_s < math.inf):
            raise InputError("scale controller: probe_s, probe_max_s and hold_s must be 0 < probe_s <= probe_max_s "
                             "(finite) and hold_s > 0 (finite)")
        if latency_target_s is not None and not (math.isfinite(latency_target_s) and latency_target_s > 0):
            raise InputError(f"--latency-target-ms must be > 0, got {latency_target_s * 1e3!r}")
        self.latency_target_s = latency_target_s
        self.latency_min_samples, self.latency_q = latency_min_samples, latency_q
        self._times = deque(maxlen=latency_window)  # per-frame times of the maps at the current rung
        self.fixed = fixed
        self.ladder = (fixed,) if fixed is not None else ladder(min_scale)
        self._i = 0                                  # index into the ladder: start at full scale
        self.budget_fixed_s = budget_s
        self.budget_fraction, self.budget_bounds_s = budget_fraction, (lo, hi)
        self.min_samples, self.up_after, self.up_margin = min_samples, up_after, up_margin
        self._cost = {s: deque(maxlen=window) for s in self.ladder}
        self._intervals = deque(maxlen=interval_window)
        self._last_frame = None                      # (seq, stamp_us)
        self._up_streak = 0
        self._ratio: dict = {}                       # rung -> cost ratio to the next rung down, learnt at changes
        self._pending = None                         # (rung left, its median) until the new rung has min_samples
        self._calibrated: dict = {}                  # rung -> seconds of one locate call timed before any pair
        self._computed = 0                           # pairs observed (at any rung)
        # probing a rung the controller was pushed off (module docstring); times are frame stamps (us)
        self.probe_s, self.probe_max_s, self.hold_s = float(probe_s), float(probe_max_s), float(hold_s)
        self._backoff_s = self.probe_s
        self._home = None                            # index of the highest rung held for hold_s, if any
        self._entered_us = None                      # frame stamp when the current rung was entered
        self._trying = False                         # the current rung was entered by a step up, not yet held
        self._blocked = False                        # the last step up was pushed off: the next waits _backoff_s
        self.probes = 0                              # probes made
        self.ups_failed = 0                          # steps up (probes or not) pushed off before they held

    # -- inputs -------------------------------------------------------------------------------
    @property
    def scale(self) -> float:
        return self.ladder[self._i]

    def observe_frame(self, seq: int, stamp_us: int) -> None:
        """Every frame of the camera (ranged or not): feeds the frame-interval estimate."""
        if self._last_frame is not None:
            pseq, pstamp = self._last_frame
            if seq > pseq and stamp_us > pstamp:
                self._intervals.append((stamp_us - pstamp) * 1e-6 / (seq - pseq))
            elif stamp_us <= pstamp:                 # replay restart or out of order: keep the estimate, re-anchor
                pass
        self._last_frame = (seq, stamp_us)
        if self._calibrated and not self._computed:
            self._i = self._calibrated_start()
        if self._entered_us is None or self._entered_us > stamp_us:   # the first frame, or a replay restarted
            self._entered_us = stamp_us
        elif stamp_us - self._entered_us >= self.hold_s * 1e6 and self._computed:
            if self._home is None or self._i < self._home:
                self._home = self._i
            if self._trying:                         # the rung stepped up to held: the next wait is the least again
                self._trying = False
                self._backoff_s = self.probe_s

    def calibrate(self, costs: dict) -> float:
        """Seconds of one locate call per rung ({scale: seconds}, timed before any pair: see the module docstring).
        Rungs not on the ladder and bad values are ignored. Returns the scale the controller now starts at (the
        largest calibrated rung that fits the budget; the lowest calibrated rung when none does). After the first
        computed pair it only seeds the cost ratios and leaves the rung alone."""
        good = {s: float(t) for s, t in costs.items()
                if s in self._cost and isinstance(t, (int, float)) and math.isfinite(t) and t > 0}
        if self.fixed is not None or not good:
            return self.scale
        self._calibrated = good
        for hi, lo in zip(self.ladder, self.ladder[1:]):
            if hi in good and lo in good and hi not in self._ratio:
                self._ratio[hi] = max(1.0, good[hi] / good[lo])
        if not self._computed:
            self._i = self._calibrated_start()
        return self.scale

    def _calibrated_start(self) -> int:
        budget = self.budget_s()
        rungs = [i for i, s in enumerate(self.ladder) if s in self._calibrated]
        for i in rungs:
            if self._calibrated[self.ladder[i]] <= budget:
                return i
        return rungs[-1]

    def frame_interval_s(self) -> float | None:
        if not self._intervals:
            return None
        v = sorted(self._intervals)
        n = len(v)
        return v[n // 2] if n % 2 else 0.5 * (v[n // 2 - 1] + v[n // 2])

    def budget_s(self) -> float:
        if self.budget_fixed_s is not None:
            return self.budget_fixed_s
        lo, hi = self.budget_bounds_s
        iv = self.frame_interval_s()
        if iv is None:
            return hi
        return min(hi, max(lo, self.budget_fraction * iv))

    # -- costs --------------------------------------------------------------------------------
    @staticmethod
    def _median(d) -> float:
        v = sorted(d)
        n = len(v)
        return v[n // 2] if n % 2 else 0.5 * (v[n // 2 - 1] + v[n // 2])

    def measured_s(self, scale: float) -> float | None:
        d = self._cost.get(scale)
        return self._median(d) if d else None

    def ratio(self, hi: float, lo: float) -> float:
        """Cost at rung ``hi`` over cost at the next rung down ``lo``: learnt at the last change between them, else
        area-proportional."""
        return self._ratio.get(hi, (hi / lo) ** 2)

    def predicted_s(self, scale: float) -> float | None:
        """Expected compute time at the next rung up, down, or the current one, from the current rung's recent
        median; None before the current rung has a sample."""
        cur = self.scale
        c = self.measured_s(cur)
        if c is None or scale == cur:
            return c
        if scale > cur:
            return c * self.ratio(scale, cur)
        return c / self.ratio(cur, scale)

    def latency_s(self, full: bool = False) -> float | None:
        """The ``latency_q`` quantile of the current rung's recent per-frame times; None before ``latency_min_samples``
        (``full``: before a whole ``latency_window``)."""
        if len(self._times) < (self._times.maxlen if full else self.latency_min_samples):
            return None
        v = sorted(self._times)
        return v[min(len(v) - 1, int(math.ceil(self.latency_q * len(v))) - 1)]

    # -- decision -----------------------------------------------------------------------------
    def observe_latency(self, scale: float, frame_s: float) -> ScaleChange | None:
        """Record the time (frame taken -> map put) of a map published at ``scale``; returns the change it causes, if any:
        one rung down when the recent quantile exceeds ``latency_target_s`` (nothing without a target)."""
        if self.latency_target_s is None or self.fixed is not None or scale != self.scale:
            return None
        if not (math.isfinite(frame_s) and frame_s >= 0):
            return None
        self._times.append(frame_s)
        lat = self.latency_s()
        if lat is not None and lat > self.latency_target_s and self._i + 1 < len(self.ladder):
            return self._change(self._i + 1, f"time per frame p{round(100 * self.latency_q)} {lat * 1e3:.1f} ms over the "
                                f"latency target {self.latency_target_s * 1e3:.1f} ms")
        return None

    def _latency_headroom(self, up: float) -> bool:
        """Whether the latency predicted at rung ``up`` (above the current one) stays below ``up_margin`` of the
        target (True without a target; False before a whole window of maps at the current rung)."""
        if self.latency_target_s is None:
            return True
        lat = self.latency_s(full=True)
        return lat is not None and lat * self.ratio(up, self.scale) < self.up_margin * self.latency_target_s

    def observe_compute(self, scale: float, seconds: float) -> ScaleChange | None:
        """Record the compute time of a pair ranged at ``scale``; returns the change of scale it causes, if any."""
        if scale in self._cost and math.isfinite(seconds) and seconds >= 0:
            self._cost[scale].append(seconds)
            self._computed += 1
        if self.fixed is not None or scale != self.scale:
            return None
        budget = self.budget_s()
        cur = self._cost[scale]
        if self._pending is not None and len(cur) >= self.min_samples:
            other, other_cost = self._pending            # the rung we left and its median just before the change
            c = self._median(cur)
            hi, lo, r = (other, scale, other_cost / c) if other > scale else (scale, other, c / other_cost)
            self._ratio[hi] = max(1.0, r)
            self._pending = None
        if len(cur) >= self.min_samples and self._median(cur) > budget and self._i + 1 < len(self.ladder):
            return self._change(self._i + 1, f"compute p50 {self._median(cur) * 1e3:.1f} ms over the budget "
                                f"{budget * 1e3:.1f} ms")
        if self._i == 0:
            return None
        if self._probe_due():
            self.probes += 1
            return self._change(self._i - 1, f"probe: scale {self.ladder[self._i - 1]:g} was held before; "
                                f"{self._backoff_s:g} s at {self.scale:g}", probe=True)
        up = self.ladder[self._i - 1]
        pred = self.predicted_s(up)
        if (pred is not None and pred < self.up_margin * budget and self._latency_headroom(up)
                and (not self._blocked or self._waited())):
            self._up_streak += 1
            if self._up_streak >= self.up_after:
                return self._change(self._i - 1, f"predicted compute at scale {up:g} {pred * 1e3:.1f} ms below "
                                    f"{self.up_margin:g} x budget {budget * 1e3:.1f} ms for {self._up_streak} pairs")
        else:
            self._up_streak = 0
        return None

    def _waited(self) -> bool:
        """``_backoff_s`` of frame time at the current rung."""
        if self._entered_us is None or self._last_frame is None:
            return False
        return self._last_frame[1] - self._entered_us >= self._backoff_s * 1e6

    def _probe_due(self) -> bool:
        """Below the highest rung held, and waited long enough at the current one (module docstring)."""
        return self._home is not None and self._i > self._home and self._waited()

    def _change(self, i: int, reason: str, probe: bool = False) -> ScaleChange:
        if i > self._i and self._trying:             # a step up pushed off before it held: the next one waits longer
            self.ups_failed += 1
            self._backoff_s = min(2.0 * self._backoff_s, self.probe_max_s)
            self._blocked = True
        elif i < self._i:
            self._blocked = False
        self._trying = i < self._i
        if self._last_frame is not None:
            self._entered_us = self._last_frame[1]
        old = self.scale
        m = self.measured_s(old)
        self._pending = None if m is None else (old, m)
        self._i = i
        self._up_streak = 0
        self._cost[self.scale].clear()               # the new rung is judged on fresh samples only
        self._times.clear()
        return ScaleChange(old, self.scale, reason, probe)
