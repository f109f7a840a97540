"""Which two posed frames the locator ranges: a pure, tested policy over a stream of frames.

``PairPolicy.offer(frame)`` returns a ``PairDecision``: a pair ``(a, b)`` or none, with a reason code (a plain string
the locator counts in its health message). ``remember(frame)`` keeps a frame as a partner only.

- Motion pairs: the new frame is the reference ``a`` (its ranges are the freshest, and an earlier frame sees what the
  newer one sees in forward flight). ``b`` is the newest earlier frame of the same camera that is not older than
  ``max_age_s``, not rotated by more than ``max_rotation_deg``, and gives enough parallax: the median over a 5 x 5
  probe grid of the translational disparity of a point at ``ref_range_m`` (exact, eqs. 25-26; the median because it
  is zero at the focus of expansion) is at least ``min_disparity_px``, or the baseline is at least
  ``min_baseline_m``. The newest sufficient frame wins: the shortest gap keeps appearance changes and pose errors small.
- Stereo pairs (``stereo_rig=(ref, partner)``, two cameras at one instant, the paper's multicamera case): a pair
  forms when the second frame within ``max_stereo_dt_s`` arrives; while the partner is alive an unmatched rig frame
  waits for it, and when it is silent the rig camera falls back to motion pairs.

No zenoh, no images touched: frames carry an opaque ``payload``.
"""
from __future__ import annotations

import math
from collections import deque
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from eonav import InputError
from eonav.geometry.camera import Camera, VehicleState
from eonav.geometry.frames import relative_pose

# Reason codes (stable strings: the locator's health counters are named after them).
OK_MOTION = "motion"
OK_STEREO = "stereo"
FIRST_FRAME = "first_frame"                  # no earlier frame of this camera yet
TOO_OLD = "too_old"                          # every earlier frame is older than max_age_s
TOO_LITTLE_PARALLAX = "too_little_parallax"  # within age and rotation, but baseline/disparity too small
TOO_MUCH_ROTATION = "too_much_rotation"      # within age, but rotated more than max_rotation_deg
OUT_OF_ORDER = "out_of_order"                # stamp not newer than the camera's last frame (dropped)
HISTORY_RESET = "history_reset"              # stamp jumped back by more than max_age_s (replay restart)
AWAITING_STEREO = "awaiting_stereo_partner"  # rig frame whose partner has not arrived yet
CAMERA_MISMATCH = "camera_mismatch"          # frame's camera model differs in size from the history
REASONS = (OK_MOTION, OK_STEREO, FIRST_FRAME, TOO_OLD, TOO_LITTLE_PARALLAX, TOO_MUCH_ROTATION,
           OUT_OF_ORDER, HISTORY_RESET, AWAITING_STEREO, CAMERA_MISMATCH)


@dataclass(frozen=True)
class PosedFrameInfo:
    """What the policy needs of a posed frame; ``payload`` is carried along untouched."""
    camera_id: str
    seq: int
    stamp_us: int
    camera: Camera
    state: VehicleState
    payload: Any = None


@dataclass(frozen=True)
class PairPolicyConfig:
    min_disparity_px: float = 2.0     # median translational disparity at ref_range_m (probe grid)
    ref_range_m: float = 50.0         # range at which parallax is judged
    min_baseline_m: float = 0.0       # > 0: a baseline of at least this also qualifies
    max_age_s: float = 1.0            # oldest partner frame accepted
    max_rotation_deg: float = 10.0    # largest rotation between the two camera frames (motion pairs)
    history: int = 8                  # frames kept per camera
    stereo_rig: tuple | None = None   # (reference camera id, partner camera id) or None
    max_stereo_dt_s: float = 0.002    # largest stamp difference of a stereo pair

    def __post_init__(self):
        for name in ("min_disparity_px", "min_baseline_m"):
            v = getattr(self, name)
            if not (math.isfinite(v) and v >= 0):
                raise InputError(f"pair policy: {name} must be a finite number >= 0, got {v!r}")
        for name in ("ref_range_m", "max_age_s", "max_rotation_deg", "max_stereo_dt_s"):
            v = getattr(self, name)
            if not (math.isfinite(v) and v > 0):
                raise InputError(f"pair policy: {name} must be a finite number > 0, got {v!r}")
        if not (isinstance(self.history, int) and self.history >= 1):
            raise InputError(f"pair policy: history must be an integer >= 1, got {self.history!r}")
        if self.stereo_rig is not None:
            rig = tuple(self.stereo_rig)
            if len(rig) != 2 or rig[0] == rig[1] or not all(isinstance(c, str) and c for c in rig):
                raise InputError(f"pair policy: stereo_rig must be two different camera ids, got {self.stereo_rig!r}")
            object.__setattr__(self, "stereo_rig", rig)

    def parallax_ok(self, m: "PairMetrics") -> bool:
        """Enough parallax: the disparity at ``ref_range_m`` at least ``min_disparity_px``, or (``min_baseline_m``
        > 0) the baseline at least that."""
        return (m.disparity_px >= self.min_disparity_px
                or (self.min_baseline_m > 0 and m.baseline_m >= self.min_baseline_m))


@dataclass(frozen=True)
class PairDecision:
    """``a`` is the reference frame (ranges on its grid), ``b`` the other one; both None when no pair."""
    reason: str
    a: PosedFrameInfo | None = None
    b: PosedFrameInfo | None = None
    detail: str = ""
    disparity_px: float = math.nan
    baseline_m: float = math.nan
    rotation_deg: float = math.nan
    dt_s: float = math.nan

    @property
    def ok(self) -> bool:
        return self.a is not None

    @property
    def kind(self) -> str:
        return self.reason if self.ok else "none"


@dataclass
class PairMetrics:
    baseline_m: float
    rotation_deg: float
    disparity_px: float
    dt_s: float


def _probe_pixels(cam: Camera, n: int = 5):
    """n x n probe pixels spread over the image (10 % margins)."""
    us = np.linspace(0.1, 0.9, n) * (cam.width - 1)
    vs = np.linspace(0.1, 0.9, n) * (cam.height - 1)
    u, v = np.meshgrid(us, vs)
    return u.ravel(), v.ravel()


def pair_metrics(a: PosedFrameInfo, b: PosedFrameInfo, ref_range_m: float) -> PairMetrics:
    """Baseline, rotation and median translational disparity (px) at ``ref_range_m`` of the pair (a, b)."""
    ca, cb = a.camera, b.camera
    R, t = relative_pose(ca.T_cam_body, a.state.T_body_ned, a.state.position_ned_m, ca.l_body_m,
                         cb.T_cam_body, b.state.T_body_ned, b.state.position_ned_m, cb.l_body_m)
    rot = math.degrees(math.acos(max(-1.0, min(1.0, (np.trace(R) - 1.0) / 2.0))))
    u, v = _probe_pixels(ca)
    m = np.stack([np.ones_like(u), (u - ca.cx) / ca.fx, (v - ca.cy) / ca.fy])   # [1, x_p/f, y_p/f] per probe
    A = R @ m                                                                   # X_b / x_c at rho = 0
    rho = 1.0 / ref_range_m
    den_inf, den_ref = A[0], A[0] + t[0] * rho
    ok = (den_inf > 1e-6) & (den_ref > 1e-6)     # in front of camera b both at infinity and at ref range
    if not ok.any():
        disp = 0.0
    else:
        ub_inf = cb.fx * A[1][ok] / den_inf[ok]
        vb_inf = cb.fy * A[2][ok] / den_inf[ok]
        ub_ref = cb.fx * (A[1][ok] + t[1] * rho) / den_ref[ok]
        vb_ref = cb.fy * (A[2][ok] + t[2] * rho) / den_ref[ok]
        disp = float(np.median(np.hypot(ub_ref - ub_inf, vb_ref - vb_inf)))
    return PairMetrics(float(np.linalg.norm(t)), rot, disp, (a.stamp_us - b.stamp_us) * 1e-6)


@dataclass
class PairPolicy:
    """Stateful pair chooser: keeps a short history per camera. Not thread-safe (one locator thread)."""
    config: PairPolicyConfig = field(default_factory=PairPolicyConfig)

    def __post_init__(self):
        self._hist: dict[str, deque] = {}
        self._stereo_done: deque = deque(maxlen=64)     # (camera_id, seq) of stereo references used

    def history(self, camera_id: str) -> list:
        return list(self._hist.get(camera_id, ()))

    def remember(self, f: PosedFrameInfo) -> bool:
        """Add ``f`` to the history without a decision: a frame the locator skipped because a newer one of the same
        camera was already waiting (latest frame wins) may still be the partner of a later frame. Same ordering rules
        as ``offer``; returns False when ``f`` was dropped as out of order."""
        d = self._admit(f)
        if d is None:
            self._hist[f.camera_id].append(f)
            return True
        return d.reason != OUT_OF_ORDER

    def offer(self, f: PosedFrameInfo) -> PairDecision:
        """Decide on the new frame ``f`` and add it to the history (unless dropped as out of order)."""
        cfg = self.config
        d = self._admit(f)
        if d is not None:
            return d
        hist = self._hist[f.camera_id]
        earlier = list(hist)
        hist.append(f)
        if cfg.stereo_rig is not None and f.camera_id in cfg.stereo_rig:
            d = self._stereo(f)
            if d is not None:
                return d
        return self._motion(f, earlier)

    def _admit(self, f: PosedFrameInfo) -> PairDecision | None:
        """None when ``f`` may join its camera's history; else the decision (out of order, history reset or camera
        mismatch; the latter two have already restarted the history with ``f``)."""
        cfg = self.config
        hist = self._hist.setdefault(f.camera_id, deque(maxlen=cfg.history))
        if hist:
            last = hist[-1]
            if f.stamp_us <= last.stamp_us:
                if last.stamp_us - f.stamp_us > cfg.max_age_s * 1e6:
                    hist.clear()
                    hist.append(f)
                    return PairDecision(HISTORY_RESET, detail=f"stamp went back {(last.stamp_us - f.stamp_us) / 1e6:.3f} s; "
                                        f"history of {f.camera_id!r} cleared")
                return PairDecision(OUT_OF_ORDER, detail=f"stamp {f.stamp_us} not newer than last {last.stamp_us} "
                                    f"of camera {f.camera_id!r}")
            if (last.camera.width, last.camera.height) != (f.camera.width, f.camera.height):
                hist.clear()
                hist.append(f)
                return PairDecision(CAMERA_MISMATCH, detail=f"camera {f.camera_id!r} changed size to "
                                    f"{f.camera.width}x{f.camera.height}; history cleared")
        return None

    # -- stereo -------------------------------------------------------------------------------
    def _stereo(self, f: PosedFrameInfo) -> PairDecision | None:
        cfg = self.config
        ref_id, partner_id = cfg.stereo_rig
        other_id = partner_id if f.camera_id == ref_id else ref_id
        others = self._hist.get(other_id)
        if not others:
            return None
        best = min(others, key=lambda o: abs(o.stamp_us - f.stamp_us))
        if abs(best.stamp_us - f.stamp_us) <= cfg.max_stereo_dt_s * 1e6:
            a, b = (f, best) if f.camera_id == ref_id else (best, f)
            if (a.camera_id, a.seq) in self._stereo_done:
                return None
            m = pair_metrics(a, b, cfg.ref_range_m)
            if not self.config.parallax_ok(m):
                return PairDecision(TOO_LITTLE_PARALLAX, detail=f"stereo: {self._parallax_text(m)}", **_mfields(m))
            self._stereo_done.append((a.camera_id, a.seq))
            return PairDecision(OK_STEREO, a, b, detail=f"stereo {a.camera_id}/{b.camera_id}", **_mfields(m))
        newest_other = others[-1]
        if abs(f.stamp_us - newest_other.stamp_us) <= cfg.max_age_s * 1e6 and f.stamp_us > newest_other.stamp_us:
            # the partner camera is alive and behind us: its frame for this instant should come
            return PairDecision(AWAITING_STEREO, detail=f"no {other_id!r} frame within {cfg.max_stereo_dt_s * 1e3:.1f} ms yet")
        return None                                       # partner silent (or ahead without a match): motion

    # -- motion -------------------------------------------------------------------------------
    def _metrics(self, a: PosedFrameInfo, b: PosedFrameInfo) -> PairMetrics:
        """``pair_metrics`` of a motion candidate (a subclass may compute a frame's candidates together)."""
        return pair_metrics(a, b, self.config.ref_range_m)

    def _parallax_text(self, m: PairMetrics) -> str:
        cfg = self.config
        s = f"disparity {m.disparity_px:.2f} px at {cfg.ref_range_m:g} m < {cfg.min_disparity_px:g} px"
        if cfg.min_baseline_m > 0:
            s += f" and baseline {m.baseline_m:.3f} m < {cfg.min_baseline_m:g} m"
        return s

    def _motion(self, f: PosedFrameInfo, earlier: list) -> PairDecision:
        cfg = self.config
        if not earlier:
            return PairDecision(FIRST_FRAME, detail=f"first frame of camera {f.camera_id!r}")
        seen_rot = seen_parallax = None
        for b in reversed(earlier):                      # newest first
            age_s = (f.stamp_us - b.stamp_us) * 1e-6
            if age_s > cfg.max_age_s:
                break                                    # the rest are older still
            m = self._metrics(f, b)
            if m.rotation_deg > cfg.max_rotation_deg:
                seen_rot = seen_rot or m
                continue
            if not self.config.parallax_ok(m):
                if seen_parallax is None or m.disparity_px > seen_parallax.disparity_px:
                    seen_parallax = m
                continue
            return PairDecision(OK_MOTION, f, b, detail=f"seq {f.seq} with seq {b.seq}", **_mfields(m))
        if seen_parallax is not None:
            return PairDecision(TOO_LITTLE_PARALLAX, detail=f"best {self._parallax_text(seen_parallax)}",
                                **_mfields(seen_parallax))
        if seen_rot is not None:
            return PairDecision(TOO_MUCH_ROTATION, detail=f"rotation {seen_rot.rotation_deg:.2f} deg > "
                                f"{cfg.max_rotation_deg:g} deg", **_mfields(seen_rot))
        newest_age = (f.stamp_us - earlier[-1].stamp_us) * 1e-6
        return PairDecision(TOO_OLD, detail=f"newest earlier frame is {newest_age:.3f} s old > {cfg.max_age_s:g} s",
                            dt_s=newest_age)


def _mfields(m: PairMetrics) -> dict:
    return {"disparity_px": m.disparity_px, "baseline_m": m.baseline_m, "rotation_deg": m.rotation_deg, "dt_s": m.dt_s}
