"""Measurement scheduling: which earlier frames the newest frame of a camera is measured against.

One dense measurement per frame and camera (the locator's budget), its partner taken in turn (``pattern``) as
- ``near``: the pair policy's choice (``eonav.ranging.pair_policy.PairPolicy``): the newest earlier frame of the camera with
  enough parallax, within its age and rotation limits -- a short baseline: near points, new regions, quick;
- ``wide``: the earlier frame within the same age and rotation limits with the most parallax (median translational
  disparity at the policy's reference range, ``pair_metrics``) up to ``wide_max_disparity_px``: the baseline
  far points need (a 185 m point a pixel of parallax in 0.17 s gets 5 px in 1 s);
falling back to the other when one has no partner. With ``max_pose_shift_px`` finite, each frame is checked
against the camera's previous frame by sparse tracks (``eonav.ranging.tracks.pose_shift_px``: the image shift the
pair's pose error puts on its matches, px) and a frame whose pose disagrees with its neighbours' images by more
than that (the smaller of the shifts to the frame before and after it, the one known while it is the newest or
the first) is no partner: one frame's pose error enters every pair it is in. With a stereo rig (``stereo_rig``: reference, partner camera
ids) the reference camera's newest frame is also measured against the partner camera's frame of the same instant
(``max_stereo_dt_s``), whichever of the two arrives second.
"""
from __future__ import annotations

import math
from collections import deque
from dataclasses import dataclass, field, replace

import numpy as np

from eonav import InputError
from eonav.geometry.camera import View
from eonav.ranging.pair_policy import (CAMERA_MISMATCH, HISTORY_RESET, OK_MOTION, OUT_OF_ORDER, PairMetrics,
                                      PairPolicy, PairPolicyConfig, PosedFrameInfo, _probe_pixels, pair_metrics)

NEAR, WIDE, STEREO = "near", "wide", "stereo"


@dataclass(frozen=True)
class ScheduleConfig:
    policy: PairPolicyConfig = field(default_factory=PairPolicyConfig)
    pattern: tuple = (NEAR, WIDE)
    wide_max_disparity_px: float = 15.0   # the wide partner: median disparity at the reference range at most this
    history: int = 48                     # frames kept per camera for the wide partner
    stereo_rig: tuple | None = None
    max_stereo_dt_s: float = 0.002
    max_pose_shift_px: float = math.inf   # a frame whose pose disagrees with its neighbours' by more is no partner

    def __post_init__(self):
        if not (self.max_pose_shift_px > 0):
            raise InputError(f"fusion schedule: max_pose_shift_px must be > 0, got {self.max_pose_shift_px!r}")
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


@dataclass
class _BatchedPolicy(PairPolicy):
    """The pair policy with its motion candidates' metrics from ``metrics(a, candidates, b)``: the scheduler's
    ``wide_metrics`` of all of frame a's candidates within the age limit at once, b's row, instead of one
    ``pair_metrics`` per candidate (equal to float rounding: the same decisions)."""
    metrics: object = None

    def _metrics(self, a, b) -> PairMetrics:
        cands = [x for x in self._hist[a.camera_id] if x is not a
                 and (a.stamp_us - x.stamp_us) * 1e-6 <= self.config.max_age_s]
        return self.metrics(a, cands if any(x is b for x in cands) else cands + [b], b)


class Scheduler:
    """Keeps a history of frames per camera and picks the measurements of each new frame. One thread."""

    def __init__(self, config: ScheduleConfig = ScheduleConfig()):
        self.config = config
        self.policy = _BatchedPolicy(config.policy, metrics=self._policy_metrics)
        self._batch: tuple = (None, {})     # (frame a, {id(b): (b, rotation deg, disparity px, baseline m)})
        self._hist: dict[str, deque] = {}
        self._count: dict[str, int] = {}
        self._stereo_done: deque = deque(maxlen=64)
        self._poses: dict = {}        # id(frame) -> _cam_pose(frame), for the frames in a history (alive)
        self._shift: dict = {}        # id(frame) -> (frame, pose shift to the frame before, to the frame after)

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

    def _pose(self, f: PosedFrameInfo):
        """_cam_pose of a frame in a history, computed once (a frame in a history is alive, so its id is its own;
        an entry of a dead frame is overwritten when its id comes back with a new frame)."""
        p = self._poses.get(id(f))
        if p is None or p[0] is not f:
            if len(self._poses) > 4 * self.config.history * max(len(self._hist), 1):
                live = {id(x) for h in self._hist.values() for x in h}
                self._poses = {k: v for k, v in self._poses.items() if k in live}
            p = self._poses[id(f)] = (f, *_cam_pose(f))
        return p[1:]

    def _known_metrics(self, a, bs) -> dict:
        """{id(b): (b, rotation deg, disparity px, baseline m)} of ``a`` against (at least) each of ``bs``
        (``wide_metrics``), those not yet known for ``a`` computed together."""
        if self._batch[0] is not a:
            self._batch = (a, {})
        known = self._batch[1]
        miss = [b for b in bs if id(b) not in known or known[id(b)][0] is not b]
        if miss:
            rot, disp, base = wide_metrics(a, miss, self.config.policy.ref_range_m, [self._pose(b) for b in miss],
                                           pose_a=self._pose(a))
            for i, b in enumerate(miss):
                known[id(b)] = (b, float(rot[i]), float(disp[i]), float(base[i]))
        return known

    def _metrics_of(self, a, bs):
        """(rotation deg, disparity px, baseline m) arrays of ``a`` against each of ``bs`` (``_known_metrics``)."""
        known = self._known_metrics(a, bs)
        rows = [known[id(b)] for b in bs]
        return (np.array([r[1] for r in rows]), np.array([r[2] for r in rows]), np.array([r[3] for r in rows]))

    def _policy_metrics(self, a, cands, b) -> PairMetrics:
        _, rot, disp, base = self._known_metrics(a, cands)[id(b)]
        return PairMetrics(base, rot, disp, (a.stamp_us - b.stamp_us) * 1e-6)

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
        if math.isfinite(cfg.max_pose_shift_px):
            self._check_pose(f, earlier[-1] if earlier else None)
            earlier = [b for b in earlier if self.pose_ok(b)]
            if d.reason == OK_MOTION and not self.pose_ok(d.b):
                d = replace(d, reason="pose_shift")
        motion = self._motion(f, earlier, d if d.reason == OK_MOTION else None)
        if motion is not None:
            out.append(motion)
        if cfg.stereo_rig is not None and f.camera_id in cfg.stereo_rig:
            st = self._stereo(f)
            if st is not None:
                out.append(st)
        return out, d.reason

    def _check_pose(self, f, prev) -> None:
        """The pose shift between ``f`` and the camera's previous frame, kept as f's "before" and prev's "after"."""
        from eonav.ranging.tracks import recent_pose_shift, recent_tracks
        from eonav.geometry.camera import pair_geometry
        s = math.nan
        if prev is not None and isinstance(f.payload, View) and isinstance(prev.payload, View):
            s = recent_pose_shift(pair_geometry(f.payload, prev.payload),
                                  recent_tracks(f.payload.image, prev.payload.image))
        if len(self._shift) > 4 * self.config.history * max(len(self._hist), 1):
            live = {id(x) for h in self._hist.values() for x in h}
            self._shift = {k: v for k, v in self._shift.items() if k in live}
        self._shift[id(f)] = (f, s, math.nan)
        if prev is not None:
            e = self._shift.get(id(prev))
            self._shift[id(prev)] = (prev, e[1] if e is not None and e[0] is prev else math.nan, s)

    def pose_ok(self, b) -> bool:
        """Whether frame ``b``'s pose agrees with its neighbours' images (``max_pose_shift_px``; unknown: yes)."""
        e = self._shift.get(id(b))
        if e is None or e[0] is not b:
            return True
        known = [x for x in e[1:] if math.isfinite(x)]
        return not known or min(known) <= self.config.max_pose_shift_px

    def _motion(self, f, earlier, near) -> Measurement | None:
        """near: the pair policy's decision (OK_MOTION) or None."""
        cfg = self.config
        k = self._count.get(f.camera_id, 0)
        role = cfg.pattern[k % len(cfg.pattern)]
        wide = self._wide(f, earlier) if role == WIDE or near is None else None
        if role == WIDE and wide is not None:
            b, disp, base = wide
        elif near is not None:
            b, disp, base = near.b, near.disparity_px, near.baseline_m
            role = NEAR
        elif wide is not None:
            (b, disp, base), role = wide, WIDE
        else:
            return None
        self._count[f.camera_id] = k + 1
        return Measurement(role, f, b, disp, base)

    def _wide(self, f, earlier):
        """(frame, disparity px, baseline m) of the earlier frame with the most parallax up to
        wide_max_disparity_px, or None: ``pair_metrics`` of every candidate at once (``wide_metrics``)."""
        pc = self.config.policy
        cands = [b for b in reversed(earlier) if (f.stamp_us - b.stamp_us) * 1e-6 <= pc.max_age_s]
        if not cands:
            return None
        rot_deg, disp, base = self._metrics_of(f, cands)
        ok = (rot_deg <= pc.max_rotation_deg) & (disp >= pc.min_disparity_px) & (disp <= self.config.wide_max_disparity_px)
        if not ok.any():
            return None
        i = int(np.argmax(np.where(ok, disp, -np.inf)))     # the newest of equal ones
        return cands[i], float(disp[i]), float(base[i])

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
        if not cfg.policy.parallax_ok(m):
            return None
        self._stereo_done.append((a.camera_id, a.seq, a.stamp_us))
        return Measurement(STEREO, a, b, m.disparity_px, m.baseline_m)


def _cam_pose(f: PosedFrameInfo):
    """(R_cam_ned, camera centre in NED, m) of a frame: X_cam = R (X_ned - c)."""
    T2 = np.asarray(f.state.T_body_ned, float)
    R = np.asarray(f.camera.T_cam_body, float) @ T2
    c = np.asarray(f.state.position_ned_m, float).reshape(3) + T2.T @ np.asarray(f.camera.l_body_m, float).reshape(3)
    return R, c


def _probe_rays(cam):
    """[1, x_p/fx, y_p/fy] of ``pair_metrics``' probe pixels of ``cam`` (3 x p), computed once per camera."""
    key = (cam.width, cam.height, cam.fx, cam.fy, cam.cx, cam.cy)
    m = _RAYS.get(key)
    if m is None:
        u, v = _probe_pixels(cam)
        m = _RAYS[key] = np.stack([np.ones_like(u), (u - cam.cx) / cam.fx, (v - cam.cy) / cam.fy])
        m.setflags(write=False)
    return m


_RAYS: dict = {}


def wide_metrics(a: PosedFrameInfo, bs: list, ref_range_m: float, poses=None, pose_a=None):
    """``pair_metrics(a, b, ref_range_m)``'s rotation (deg), median translational disparity (px) and baseline (m) of
    a against every frame of ``bs`` in one pass (arrays): the same pose algebra as ``relative_pose`` (R_ba = R_b
    R_a^T, t_ba = R_b (c_a - c_b) with the camera centres c in NED) and the same probe grid. ``poses``, ``pose_a``:
    the ``_cam_pose`` of each of ``bs`` and of ``a`` if known."""
    Ra, ca = pose_a if pose_a is not None else _cam_pose(a)
    poses = poses if poses is not None else [_cam_pose(b) for b in bs]
    Rb = np.array([p[0] for p in poses])
    cb = np.array([p[1] for p in poses])
    R = Rb @ Ra.T                                                       # (n, 3, 3)
    t = np.einsum("nij,nj->ni", Rb, ca[None, :] - cb)                  # (n, 3)
    rot_deg = np.degrees(np.arccos(np.clip((np.trace(R, axis1=1, axis2=2) - 1.0) / 2.0, -1.0, 1.0)))
    m = _probe_rays(a.camera)                                           # (3, p)
    A = R @ m                                                           # (n, 3, p): X_b / x_c at rho = 0
    rho = 1.0 / ref_range_m
    den_inf = A[:, 0]
    den_ref = den_inf + t[:, 0:1] * rho
    ok = (den_inf > 1e-6) & (den_ref > 1e-6)
    fx = np.array([b.camera.fx for b in bs])[:, None]
    fy = np.array([b.camera.fy for b in bs])[:, None]
    with np.errstate(divide="ignore", invalid="ignore"):
        du = fx * ((A[:, 1] + t[:, 1:2] * rho) / den_ref - A[:, 1] / den_inf)
        dv = fy * ((A[:, 2] + t[:, 2:3] * rho) / den_ref - A[:, 2] / den_inf)
    d = np.hypot(du, dv)
    if ok.all() and np.isfinite(d).all():
        d.sort(axis=1)                  # the median (np.median's value, without its overhead on small rows)
        p = d.shape[1]
        disp = d[:, p // 2] if p % 2 else (d[:, p // 2 - 1] + d[:, p // 2]) / 2
    elif ok.all():
        disp = np.median(d, axis=1)
    else:
        disp = np.array([float(np.median(x[k])) if k.any() else 0.0 for x, k in zip(d, ok)])
    return rot_deg, disp, np.linalg.norm(t, axis=1)


def _size(f: PosedFrameInfo):
    return f.camera.width, f.camera.height
