"""Measurement scheduling: which earlier frames the newest frame of a camera is measured against.

One dense measurement per frame and camera (the locator's budget), its partner taken in turn (``pattern``) as
- ``near``: the pair policy's choice (``eonav.ranging.pair_policy.PairPolicy``): the newest earlier frame of the camera with
  enough parallax, within its age and rotation limits -- a short baseline: near points, new regions, quick;
- ``wide``: the earlier frame within the same age and rotation limits with the most parallax (median translational
  disparity at the policy's reference range, ``pair_metrics``) up to ``wide_max_disparity_px``: the baseline
  far points need (a 185 m point a pixel of parallax in 0.17 s gets 5 px in 1 s);
falling back to the other when one has no partner. With a stereo rig (``stereo_rig``: reference, partner camera
ids) the reference camera's newest frame is also measured against the partner camera's frame of the same instant
(``max_stereo_dt_s``), whichever of the two arrives second.
"""
from __future__ import annotations

import math
from collections import deque
from dataclasses import dataclass, field

from eonav import InputError
from eonav.ranging.pair_policy import (CAMERA_MISMATCH, HISTORY_RESET, OK_MOTION, OUT_OF_ORDER, PairPolicy, PairPolicyConfig,
                           PosedFrameInfo, pair_metrics)

NEAR, WIDE, STEREO = "near", "wide", "stereo"


@dataclass(frozen=True)
class ScheduleConfig:
    policy: PairPolicyConfig = field(default_factory=PairPolicyConfig)
    pattern: tuple = (NEAR, WIDE)
    wide_max_disparity_px: float = 15.0   # the wide partner: median disparity at the reference range at most this
    history: int = 48                     # frames kept per camera for the wide partner
    stereo_rig: tuple | None = None
    max_stereo_dt_s: float = 0.002

    def __post_init__(self):
        pat = tuple(self.pattern)
        if not pat or any(p not in (NEAR, WIDE) for p in pat):
            raise InputError(f"fusion schedule: pattern must be a non-empty sequence of {NEAR!r} / {WIDE!r}, got {self.pattern!r}")
        object.__setattr__(self, "pattern", pat)
        if not (math.isfinite(self.wide_max_disparity_px) and self.wide_max_disparity_px > 0):
            raise InputError(f"fusion schedule: wide_max_disparity_px must be > 0, got {self.wide_max_disparity_px!r}")
        if not (isinstance(self.history, int) and self.history >= 2):
            raise InputError(f"fusion schedule: history must be an integer >= 2, got {self.history!r}")
        if self.policy.stereo_rig is not None:
            raise InputError("fusion schedule: give the stereo rig as ScheduleConfig.stereo_rig, not in the pair policy")
        if self.stereo_rig is not None:
            rig = tuple(self.stereo_rig)
            if len(rig) != 2 or rig[0] == rig[1]:
                raise InputError(f"fusion schedule: stereo_rig must be two different camera ids, got {self.stereo_rig!r}")
            object.__setattr__(self, "stereo_rig", rig)


@dataclass(frozen=True)
class Measurement:
    """A pair to measure: ranges on ``a``'s grid (``a`` is its camera's newest frame) against ``b``."""
    kind: str
    a: PosedFrameInfo
    b: PosedFrameInfo
    disparity_px: float = math.nan
    baseline_m: float = math.nan


class Scheduler:
    """Keeps a history of frames per camera and picks the measurements of each new frame. One thread."""

    def __init__(self, config: ScheduleConfig = ScheduleConfig()):
        self.config = config
        self.policy = PairPolicy(config.policy)
        self._hist: dict[str, deque] = {}
        self._count: dict[str, int] = {}
        self._stereo_done: deque = deque(maxlen=64)

    def newest(self, camera_id: str) -> PosedFrameInfo | None:
        h = self._hist.get(camera_id)
        return h[-1] if h else None

    def remember(self, f: PosedFrameInfo) -> None:
        """History only (a frame the caller did not measure): a later frame's partner."""
        if self.policy.remember(f):
            h = self._history(f.camera_id)
            if h and (f.stamp_us <= h[-1].stamp_us or _size(h[-1]) != _size(f)):
                h.clear()                         # the pair policy restarted this camera's history: so do we
            h.append(f)

    def _history(self, camera_id: str) -> deque:
        return self._hist.setdefault(camera_id, deque(maxlen=self.config.history))

    def offer(self, f: PosedFrameInfo) -> tuple[list, str]:
        """The measurements of the new frame ``f`` (possibly none) and the pair policy's reason code."""
        cfg = self.config
        d = self.policy.offer(f)
        if d.reason == OUT_OF_ORDER:
            return [], d.reason
        h = self._history(f.camera_id)
        if d.reason in (HISTORY_RESET, CAMERA_MISMATCH):
            h.clear()
        earlier = list(h)
        h.append(f)
        out = []
        motion = self._motion(f, earlier, d.b if d.reason == OK_MOTION else None)
        if motion is not None:
            out.append(motion)
        if cfg.stereo_rig is not None and f.camera_id in cfg.stereo_rig:
            st = self._stereo(f)
            if st is not None:
                out.append(st)
        return out, d.reason

    def _motion(self, f, earlier, near_b) -> Measurement | None:
        cfg = self.config
        k = self._count.get(f.camera_id, 0)
        role = cfg.pattern[k % len(cfg.pattern)]
        wide = self._wide(f, earlier) if role == WIDE or near_b is None else None
        if role == WIDE and wide is not None:
            b, m = wide
        elif near_b is not None:
            b, m = near_b, pair_metrics(f, near_b, cfg.policy.ref_range_m)
            role = NEAR
        elif wide is not None:
            (b, m), role = wide, WIDE
        else:
            return None
        self._count[f.camera_id] = k + 1
        return Measurement(role, f, b, m.disparity_px, m.baseline_m)

    def _wide(self, f, earlier):
        """(frame, metrics) of the earlier frame with the most parallax up to wide_max_disparity_px, or None."""
        pc = self.config.policy
        best = None
        for b in reversed(earlier):
            if (f.stamp_us - b.stamp_us) * 1e-6 > pc.max_age_s:
                break
            m = pair_metrics(f, b, pc.ref_range_m)
            if (m.rotation_deg > pc.max_rotation_deg or m.disparity_px < pc.min_disparity_px
                    or m.disparity_px > self.config.wide_max_disparity_px):
                continue
            if best is None or m.disparity_px > best[1].disparity_px:
                best = (b, m)
        return best

    def _stereo(self, f) -> Measurement | None:
        cfg = self.config
        ref_id, partner_id = cfg.stereo_rig
        a = f if f.camera_id == ref_id else self.newest(ref_id)
        b = f if f.camera_id == partner_id else self.newest(partner_id)
        if a is None or b is None or abs(a.stamp_us - b.stamp_us) > cfg.max_stereo_dt_s * 1e6:
            return None
        if (a.camera_id, a.seq, a.stamp_us) in self._stereo_done:
            return None
        m = pair_metrics(a, b, cfg.policy.ref_range_m)
        if m.disparity_px < cfg.policy.min_disparity_px and not (
                cfg.policy.min_baseline_m > 0 and m.baseline_m >= cfg.policy.min_baseline_m):
            return None
        self._stereo_done.append((a.camera_id, a.seq, a.stamp_us))
        return Measurement(STEREO, a, b, m.disparity_px, m.baseline_m)


def _size(f: PosedFrameInfo):
    return f.camera.width, f.camera.height
