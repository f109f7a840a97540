"""``FusionRunner``: posed frames in, fused range maps out, one ``push`` per frame.

The code path of ``eonav fuse``, ``eonav bench fuse`` and (wired per posed frame) the locator service. For each
frame of camera c (``frame(camera_id, view, stamp_us, seq)``):

1. predict c's state into the frame (``predict``); a state older than ``max_gap_s`` (a navigation or camera gap) is
   dropped instead and the frame starts fresh;
2. the scheduler's measurements (``schedule``): c's newest frame against a near or a wide earlier frame of c, and,
   in a stereo rig, the reference camera's newest frame against the partner's frame of the same instant;
3. each measurement (``measure(view_a, view_b)``, default the dense method without its own fill) fused into the
   state of its reference camera (``update``); the push's measurements are all made before any is fused, so that
   a stereo measurement of a frame leads its motion measurement where they disagree (a moving object:
   ``eonav.fusion.update``, "Stereo leads"); a measurement of ``lr_check_kinds`` is made both ways, a -> b and
   b -> a, and the pixels of a the pair b -> a contradicts are flagged OCCLUDED, not fused
   (``eonav.ranging.consistency``: off by default, docs/methods.md), and a stereo pair made both ways empties the
   cells of the state its b -> a sees through (``stereo_free_space``);
4. the fused map (``fused_map``) of every state this frame updated, or predicted with anything in it; a state's
   last measurement and its map in one sweep (``update_and_map``), into the default measurement's arrays.

``push`` returns those maps (usually one: the frame's own camera; a stereo partner's frame returns the rig
reference's map, which it updated). In a rig whose reference's frame comes before its partner's, the reference's
measurements wait for the stereo one of their instant and are fused in the partner's push (``_hold_or_join``: the
gates of "Stereo leads" need the stereo measurement first). A frame not newer than its camera's state is dropped (``counts``
``out_of_order``). Timing per map (wall): ``locate_s`` (the measurements) and ``fusion_s`` (predict, update, map).

Predict needs only the state and the new frame's pose, so (``FusionConfig.overlap_predict``, with numba) its kernels
run on a worker thread while the measurements run (its Python part, ``predict_job``, on the caller's thread first:
the worker then hardly needs the GIL): its passes and the dense method's release the GIL, so on a machine with a
core to spare predict costs the push no wall time (``fusion_s`` then holds only the wait for it, if any). Only for
states of ``overlap_min_cells`` and more: a small state's predict is short, and handing it to another core cost
more CPU than it saved (docs/methods.md, "Fusion timing"). Not when a measurement may start from the predicted
state (``PriorConfig``). The results are the same either way.
``states[camera_id]`` is valid until the next push of that camera (the one before is reused for its arrays).
"""
from __future__ import annotations

import math
import time
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field, replace
from functools import lru_cache

import numpy as np

from eonav import InputError
from eonav.geometry.camera import View, pair_geometry
from eonav.ranging.consistency import LRCheckConfig, inconsistent, lr_checked
from eonav.ranging.methods._common import far_inverse_range
from eonav.ranging.pair_policy import PosedFrameInfo
from eonav.ranging.rangemap import FILLED, VALID, RangeResult
from eonav.ranging.tracks import recent_tracks
from eonav.fusion.fused_map import MapConfig, fused_map, update_and_map
from eonav.fusion.measure import add_pose_sigma, innovation_scale, state_shift_px
from eonav.fusion.predict import ProcessNoise, predict, predict_job
from eonav.fusion.schedule import NEAR, STEREO, WIDE, ScheduleConfig, Scheduler
from eonav.fusion.state import F32, InverseRangeState, optional_kernels
from eonav.fusion.update import (UpdateConfig, clear_cells, gate_motion, stereo_restart, stereo_skipped_free,
                                 update)


def frame(camera_id: str, view: View, stamp_us: int, seq: int = 0) -> PosedFrameInfo:
    """A posed frame for ``FusionRunner.push``: the view (camera, vehicle state, grey image) at ``stamp_us``."""
    return PosedFrameInfo(str(camera_id), int(seq), int(stamp_us), view.camera, view.state, payload=view)


MEASUREMENT_WINDOW_FLOOR = "valid"
# the state cells the pair checks judge a measurement's sigma against (``FusionRunner._against_state``)
AGAINST_MIN_FUSED = 3
AGAINST_MIN_INLIER = 0.8


def dense_measurement(view_a: View, view_b: View, pair_checks: bool = False,
                      window_floor: str = MEASUREMENT_WINDOW_FLOOR, **prior) -> RangeResult:
    """The default measurement: the dense method, measured pixels only (the fused map fills once, at the end);
    ``pair_checks``: after the pair's brightness match and with its pose error in the sigma
    (``eonav.fusion.measure``); ``prior``: ``prior=(rho, sigma)`` on view a's grid (the predicted state) and its
    options (``locate_dense``). ``window_floor``: the window residual's floor, by default the noise of the pixels the
    method ranges ("valid"), not of every pixel in view: the filter weighs each measurement by its sigma, and the
    in-view figure scales every sigma with the share of sky and occlusions in the frame (docs/methods.md, "The
    fused measurement's noise floor")."""
    if pair_checks:
        from eonav.fusion.measure import checked_dense
        return checked_dense(view_a, view_b, window_floor=window_floor, **prior)
    from eonav.ranging.methods.dense import locate_dense
    return locate_dense(view_a, view_b, fill=False, window_floor=window_floor, **prior)


@dataclass(frozen=True)
class PriorConfig:
    """The predicted state as the measurement's prior (``locate_dense(prior=...)``: where it is converged the
    refinement starts from it at a finer level, skipping the coarse search): cells of at least ``min_fused``
    measurements whose evidence agrees (the fused map's ``eta_inlier``), on the measurements of ``kinds`` only:
    a wide partner's baseline takes more pixels beyond the refinement's reach and leaves more of them occluded, so
    it searches in full. Every ``full_every``-th measurement of a camera at least searches in full, so that a new
    object, a region the prior does not hold and a cell whose prior is wrong are found by the search (1: always);
    so does one whose prior holds less than ``min_fraction`` x what the last full search measured."""
    full_every: int = 1            # off by default: see docs/methods.md, "Fusion" (a full search every 3rd: 3)
    kinds: tuple = ("near",)       # the measurements that may start from the prior (the wide ones search in full)
    level: int = 1                 # the pyramid level the refinement starts at from the prior
    min_fused: int = 2
    min_fraction: float = 0.8      # the prior seeds at least this x the last full search's measured pixels

    def __post_init__(self):
        if not (isinstance(self.full_every, int) and self.full_every >= 1):
            raise InputError(f"fusion prior: full_every must be an integer >= 1, got {self.full_every!r}")
        if not (isinstance(self.min_fused, int) and self.min_fused >= 1):
            raise InputError(f"fusion prior: min_fused must be an integer >= 1, got {self.min_fused!r}")
        kinds = tuple(self.kinds)
        if any(k not in (NEAR, WIDE, STEREO) for k in kinds):
            raise InputError(f"fusion prior: kinds must name {NEAR!r}, {WIDE!r} or {STEREO!r}, got {self.kinds!r}")
        object.__setattr__(self, "kinds", kinds)
        if not 0 <= self.min_fraction <= 1:
            raise InputError(f"fusion prior: min_fraction must be in [0, 1], got {self.min_fraction!r}")


@dataclass(frozen=True)
class FusionConfig:
    schedule: ScheduleConfig = field(default_factory=ScheduleConfig)
    noise: ProcessNoise = field(default_factory=ProcessNoise)
    update: UpdateConfig = field(default_factory=UpdateConfig)
    output: MapConfig = field(default_factory=MapConfig)
    prior: PriorConfig = field(default_factory=PriorConfig)
    max_gap_s: float = 1.0             # a state older than this is dropped (nav / camera gap)
    pair_checks: bool = False          # the default measurement's brightness match and pose term (fusion/measure.py)
    far_parallax_px: float = 0.5       # a pair's far limit, as the dense method's AT_INFINITY rule
    overlap_predict: bool = True       # predict on a worker thread beside the measurements (module docstring) ...
    overlap_min_cells: int = 150_000   # ... for states of at least this many cells (320 x 320 and smaller: in turn)
    lr_check_kinds: tuple = ()         # measurements also made b -> a, a's pixels b contradicts not fused (step 3)
    lr_check: LRCheckConfig = field(default_factory=LRCheckConfig)
    stereo_free_space: bool = True     # with the stereo pair checked both ways: cells its b -> a sees through emptied
    n_per_instant: bool = True         # a state's n counts instants: a rig frame's motion and stereo measurements of
                                       # one cell count once (``FusionRunner._count_instant``; docs/methods.md)

    def __post_init__(self):
        if not (math.isfinite(self.max_gap_s) and self.max_gap_s > 0):
            raise InputError(f"fusion: max_gap_s must be > 0, got {self.max_gap_s!r}")
        if not (isinstance(self.overlap_min_cells, int) and self.overlap_min_cells >= 0):
            raise InputError(f"fusion: overlap_min_cells must be an integer >= 0, got {self.overlap_min_cells!r}")
        kinds = tuple(self.lr_check_kinds)
        if any(k not in (NEAR, WIDE, STEREO) for k in kinds):
            raise InputError(f"fusion: lr_check_kinds must name {NEAR!r}, {WIDE!r} or {STEREO!r}, "
                             f"got {self.lr_check_kinds!r}")
        object.__setattr__(self, "lr_check_kinds", kinds)


@dataclass
class FusedMap:
    """The fused range map of ``frame`` (its camera's newest frame): ``result`` has the arrays of ``eonav locate``
    (method "fused") and ``n_fused`` the measurements fused per pixel; ``measurements``: what this push measured
    into it (kind, other camera and seq, baseline, update counts). With ``FusionConfig.n_per_instant`` (default)
    ``n_fused`` counts instants: the measurements of one frame of the reference camera (a rig's motion and stereo
    pairs) count once."""
    frame: PosedFrameInfo
    result: RangeResult
    n_fused: object
    measurements: list
    locate_s: float
    fusion_s: float


class FusionRunner:
    """Per-camera inverse-range states fed by a stream of posed frames (module docstring). One thread."""

    def __init__(self, config: FusionConfig = FusionConfig(), measure=None, fresh_measurements: bool | None = None,
                 takes_prior: bool | None = None):
        """fresh_measurements: ``measure`` returns results nobody else holds, so their arrays may become the fused
        map's (no fresh memory per frame); takes_prior: ``measure`` takes ``prior=(rho, sigma)`` (as
        ``dense_measurement``); None: True for the default measurement only."""
        self.config = config
        self.measure = measure or dense_measurement
        self.fresh = (self.measure is dense_measurement) if fresh_measurements is None else bool(fresh_measurements)
        self.takes_prior = (self.measure is dense_measurement) if takes_prior is None else bool(takes_prior)
        self._since_full: dict[str, int] = {}                # measurements since the last full search, per camera
        self._prior_bufs: dict[str, tuple] = {}
        self._full_measured: dict[str, int] = {}             # pixels the last full search measured, per camera
        self.scheduler = Scheduler(config.schedule)
        self.states: dict[str, InverseRangeState] = {}
        self.frames: dict[str, PosedFrameInfo] = {}          # the frame each state is on
        self.counts: dict[str, int] = {}
        self._spare: dict[str, InverseRangeState] = {}       # the state before the last predict: arrays to reuse
        self._rig_motion: dict[str, tuple] = {}              # a rig reference's last motion measurement (stereo leads)
        self._held: dict[str, tuple] = {}                    # a rig reference's measurements waiting for the stereo
                                                             # one of their instant: (frame, [(m, result)], seconds)
        self._seen_us: dict[str, int] = {}                   # the newest stamp pushed or remembered, per camera
        self._instants: dict[str, dict] = {}                 # per reference camera: its frame being measured, the n
                                                             # before its first measurement (n_per_instant)
        self.worker_cpu_s = 0.0      # CPU seconds the predicts on the worker thread took so far (overlap_predict)

    def count(self, name: str, k: int = 1) -> None:
        self.counts[name] = self.counts.get(name, 0) + k

    def reset(self, camera_id: str | None = None) -> None:
        """Forget the state of one camera (or of all): its next frame starts fresh."""
        for cid in ([camera_id] if camera_id is not None else list(self.states)):
            self.states.pop(cid, None)
            self.frames.pop(cid, None)
            self._spare.pop(cid, None)
            self._since_full.pop(cid, None)
            self._full_measured.pop(cid, None)
            self._rig_motion.pop(cid, None)
            self._held.pop(cid, None)

    def remember(self, f: PosedFrameInfo) -> None:
        """A frame that will not be pushed (the caller skipped it: a newer one was waiting): a partner only."""
        self._saw(f)
        self.scheduler.remember(f)

    def _saw(self, f: PosedFrameInfo) -> None:
        """The newest stamp of ``f``'s camera pushed or remembered (``_hold_or_join``: is a rig's partner alive)."""
        self._seen_us[f.camera_id] = max(self._seen_us.get(f.camera_id, f.stamp_us), f.stamp_us)

    def push(self, f: PosedFrameInfo) -> list:
        """Predict, measure, update; the fused maps of the states touched (see the module docstring)."""
        if not isinstance(f.payload, View):
            raise InputError("FusionRunner.push: the frame's payload must be its View (use eonav.fusion.sequence.frame)")
        cid = f.camera_id
        t_s = f.stamp_us * 1e-6
        old = self.states.get(cid)
        if old is not None and f.stamp_us <= self.frames[cid].stamp_us:
            self.count("out_of_order")
            return []
        t0 = time.perf_counter()
        prev = self.frames.get(cid)
        self._saw(f)
        if cid in self._held:        # its stereo partner never came: fused as they are, on their own frame's grid
            self._fuse_held(cid, want_map=False)
        touched = {}
        pending = None               # the predict running on the worker thread beside this push's measurements
        if old is not None:
            if t_s - old.stamp_s > self.config.max_gap_s:
                self.count("gap_resets")
                old = None
            else:
                args = (old, f.camera, f.state, t_s, self.config.noise)
                kw = {"out": self._spare.get(cid)}
                if self._overlap_predict(old):    # its Python here, its kernels on the worker
                    pending = _worker().submit(_cpu_timed, predict_job(*args, **kw))
                else:
                    self.states[cid] = predict(*args, **kw)
                self._spare[cid] = old
                self.frames[cid] = f
        if old is None:
            self.states[cid] = InverseRangeState.empty(f.camera, f.state, t_s)
            self.frames[cid] = f
        fusion_s = time.perf_counter() - t0
        try:
            measurements, reason = self.scheduler.offer(f)
            self.count(f"policy.{reason}")
            locate_s = 0.0
            live = [m for m in measurements if self.frames.get(m.a.camera_id) is m.a]
            if len(live) < len(measurements):                  # the reference's state moved on (or never started)
                self.count("stale_measurements", len(measurements) - len(live))
            results = self._measure_all(live)
            locate_s = sum(r[2] for r in results)
            live, results, held_here, joined_s = self._hold_or_join(f, prev, live, results)
            locate_s += joined_s
        finally:
            if pending is not None:                            # (also when a measurement raised: the state is whole)
                t_wait = time.perf_counter()
                self.states[cid], cpu_s = pending.result()
                self.worker_cpu_s += cpu_s
                fusion_s += time.perf_counter() - t_wait
        # nothing measured yet: no map to give (a state this push measures gives one: its cells not read for that);
        # none either while its measurements wait for their stereo partner (``_hold_or_join``)
        if (old is not None and not held_here
                and (any(m.a.camera_id == cid for m in live) or self.states[cid].occupied().any())):
            touched[cid] = []
        maps, fused_s = self._fuse(live, results, touched)
        fusion_s += fused_s
        return [self._fused_map(ref, maps, ms, locate_s, fusion_s) for ref, ms in touched.items()]

    def _fused_map(self, ref: str, maps: dict, measurements: list, locate_s: float, fusion_s: float) -> FusedMap:
        """The ``FusedMap`` of ``ref``'s state: the map its last measurement made (``maps``), else one made now."""
        t0 = time.perf_counter()
        res = maps[ref] if ref in maps else fused_map(self.states[ref], self.config.output)
        n_fused = res.info.pop("n_fused")
        return FusedMap(self.frames[ref], res, n_fused, measurements, locate_s,
                        fusion_s + time.perf_counter() - t0)

    def _fuse(self, live, results, touched: dict) -> tuple:
        """Fuse the measurements ``live`` (with their ``results``) into their reference cameras' states, in order;
        the record of each goes to ``touched[ref]``. Returns ({ref: the map made with its last measurement}, the
        seconds it took)."""
        fusion_s = 0.0
        last = {m.a.camera_id: i for i, m in enumerate(live)}
        maps = {}
        stereo = {m.a.camera_id: r[1] for m, r in zip(live, results) if m.kind == STEREO}
        backs = {i: r[3] for i, r in enumerate(results) if r[3] is not None}   # the left-right check's b -> a
        for i, (m, (prior, res, _, _)) in enumerate(zip(live, results)):
            ref = m.a.camera_id
            t2 = time.perf_counter()
            geo = pair_geometry(m.a.payload, m.b.payload)
            if "pair_check" in res.info:
                self._pose_along(m, geo, res, self.states[ref])
                self._against_state(res, self.states[ref])
            used = self._after_measure(ref, prior, res)
            rho_far = far_inverse_range(geo, self.config.far_parallax_px)
            # (only a rig measures one frame twice: one camera's runs skip the copies)
            inst = (self._instant(ref, m.a) if self.config.n_per_instant and self.config.schedule.stereo_rig is not None
                    else None)
            lead = self._stereo_lead(m, res, stereo.get(ref), backs.get(i))
            args = (self.states[ref], res.inv_range_per_m, res.inv_range_std_per_m, res.flags, self.config.update)
            if last[ref] == i:        # the state's last measurement of this push: update and map in one sweep;
                # a fresh measurement's arrays (nobody else holds them) become the map's
                counts, maps[ref] = update_and_map(*args, self.config.output, rho_far=rho_far,
                                                   reuse=res if self.fresh else None)
            else:
                counts = update(*args, rho_far=rho_far)
            if inst is not None:
                self._count_instant(ref, inst, maps[ref] if last[ref] == i else None)
            if not used:
                self._full_measured[ref] = counts["measured"]
            fusion_s += time.perf_counter() - t2
            self.count(f"measurements.{m.kind}")
            touched.setdefault(ref, []).append(dict(counts, **lead, kind=m.kind, other_camera_id=m.b.camera_id,
                                                    other_seq=m.b.seq, baseline_m=m.baseline_m,
                                                    disparity_px=m.disparity_px))
        return maps, fusion_s

    def _hold_or_join(self, f: PosedFrameInfo, prev: PosedFrameInfo | None, live: list, results: list) -> tuple:
        """A rig's stereo measurement must come before its motion measurements of the same instant for the gates of
        ``eonav.fusion.update`` ("Stereo leads") to act. When the reference's frame comes first (no stereo
        measurement of it in this push) and the partner camera delivered the reference's previous instant (a frame
        stamped no more than ``max_stereo_dt_s`` before it: the scheduler's stereo pairing), its
        measurements are measured now and held, not fused, and no map of it is given; the partner's push, which
        makes the stereo measurement of that frame, fuses them just before it, as if the partner's frame had come
        first, and gives the map. Held measurements whose partner never comes are fused, ungated, when the
        reference's next frame arrives (``_fuse_held``): a lost partner frame costs that instant's map.
        Returns (live, results, whether this push's reference measurements were held, the held ones' seconds)."""
        rig = self.config.schedule.stereo_rig
        if rig is None or self.config.update.stereo_lead_k == 0:
            return live, results, False, 0.0
        ref = rig[0]
        if f.camera_id == rig[1] and ref in self._held:  # the partner's push: the stereo measurement they wait for
            frame_held, items, seconds = self._held.pop(ref)
            at = next((i for i, m in enumerate(live) if m.kind == STEREO and _same(m.a, frame_held)), len(live))
            self.count("held_joined" if at < len(live) else "held_fused_without_stereo")
            live = live[:at] + [m for m, _ in items] + live[at:]
            results = results[:at] + [r for _, r in items] + results[at:]
            return live, results, False, seconds
        seen = self._seen_us.get(rig[1])             # the partner's newest frame: of the previous instant or later?
        if (f.camera_id != ref or prev is None or any(m.kind == STEREO and _same(m.a, f) for m in live)
                or seen is None or seen < prev.stamp_us - self.config.schedule.max_stereo_dt_s * 1e6):
            return live, results, False, 0.0
        mine = [_same(m.a, f) for m in live]       # (none: its map still waits for the stereo measurement)
        held = [(m, r) for m, r, x in zip(live, results, mine) if x]
        self._held[ref] = (f, held, sum(r[2] for _, r in held))
        self.count("held_for_stereo")
        return ([m for m, x in zip(live, mine) if not x], [r for r, x in zip(results, mine) if not x], True, 0.0)

    def finish(self) -> list:
        """The end of a stream: the measurements still waiting for their stereo partner (``_hold_or_join``: the last
        frame of a rig's reference with no partner's frame after it) fused as they are, and their maps."""
        return [m for m in (self._fuse_held(cid, want_map=True) for cid in list(self._held)) if m is not None]

    def _fuse_held(self, cid: str, want_map: bool):
        """Camera ``cid``'s held measurements (``_hold_or_join``) fused into its state as they are: their stereo
        partner never came. With ``want_map`` (the end of the stream) their ``FusedMap``, else None (a newer frame
        of the camera is being pushed)."""
        frame_held, items, seconds = self._held.pop(cid)
        if self.frames.get(cid) is not frame_held:
            return None
        touched = {cid: []}
        maps, fusion_s = self._fuse([m for m, _ in items], [r for _, r in items], touched)
        if items:
            self.count("held_fused_without_stereo")
        return self._fused_map(cid, maps, touched[cid], seconds, fusion_s) if want_map else None

    def _instant(self, ref: str, a: PosedFrameInfo) -> dict:
        """Before a measurement of ``ref``'s frame ``a`` touches the state (stereo lead included): the instant's
        record, started at its first measurement (n then, the cells (re)started since), and the cells' n, rho and
        variance now, to tell the cells this measurement (re)starts."""
        st = self.states[ref]
        key = (a.seq, a.stamp_us)
        inst = self._instants.get(ref)
        if inst is None or inst["key"] != key or inst["state"] is not st:
            inst = self._instants[ref] = {"key": key, "state": st, "base": st.n.copy(),
                                          "fresh": np.zeros(st.shape, bool)}
        inst["n"], inst["rho"], inst["var"] = st.n.copy(), st.rho.copy(), st.var.copy()
        return inst

    def _count_instant(self, ref: str, inst: dict, res: RangeResult | None) -> int:
        """After a measurement of the instant ``inst`` of ``ref``: a cell's n rises by at most one over the
        instant's measurements (a cell (re)started in it: n 1), in the state and in ``res``'s ``n_fused`` (the map
        this measurement made, if any). The held-single rule (``MapConfig.held_single``: n 1, the last measurement
        looked and did not range it) then withdraws a cell both pairs of one rig frame ranged and no later frame
        repeated, as it does one pair's guess: two pairs sharing a reference frame (its noise, its faint sky) are
        one look, not two (docs/methods.md, "Fusion over the stream"). One measurement a frame (one camera): nothing
        changes. Returns the cells capped."""
        st = self.states[ref]
        with np.errstate(invalid="ignore"):
            started = (st.n == 1) & ((inst["n"] != 1) | ~(st.rho == inst["rho"]) | ~(st.var == inst["var"]))
        inst["fresh"] |= started
        cap = np.where(inst["fresh"], 1, inst["base"].astype(np.int64) + 1)
        over = st.n > cap
        k = int(np.count_nonzero(over))
        if k:
            st.n[over] = cap[over]
            if res is not None and res.info.get("n_fused") is not None:
                res.info["n_fused"][over] = cap[over]
            self.count("n_instant_capped", k)
        return k

    def _pose_along(self, m, geo, res, state: InverseRangeState) -> None:
        """The pair checks' pose term along the epipolar lines too (``measure.state_shift_px``: the tracks' offsets
        from where the predicted state puts their points): what it finds beyond the across-line shift already in
        the sigma is added the same way (``add_pose_sigma``); ``res.info["pair_check"]["state_shift_px"]``."""
        check = res.info["pair_check"]
        if "tracks" not in check:
            return
        tracks = recent_tracks(m.a.payload.image, m.b.payload.image)
        s = state_shift_px(state.rho, state.var, state.n, geo, tracks)
        check["state_shift_px"] = s
        across = check.get("pose_shift_px", float("nan"))
        across = across if math.isfinite(across) else 0.0
        if math.isfinite(s) and s > across:
            add_pose_sigma(res, geo, math.sqrt(s * s - across * across))
            self.count("pose_along_added")

    def _against_state(self, res, state: InverseRangeState) -> None:
        """The pair checks' last one: the measurement's sigma scaled by ``measure.innovation_scale``, judged on its
        VALID pixels (the weak ones' sigma is wide by construction) against the predicted state's confident cells
        (at least ``AGAINST_MIN_FUSED`` measurements, E[inlier ratio] at least ``AGAINST_MIN_INLIER``);
        ``res.info["pair_check"]["innovation_scale"]``."""
        rho, std = res.inv_range_per_m, res.inv_range_std_per_m
        with np.errstate(invalid="ignore"):
            confident = ((state.n >= AGAINST_MIN_FUSED) & np.isfinite(state.rho)
                         & (state.a >= np.float32(AGAINST_MIN_INLIER) * (state.a + state.b)))
        valid = (res.flags & np.uint8(VALID | FILLED)) == np.uint8(VALID)
        c = innovation_scale(rho, std, valid & np.isfinite(rho) & (std > 0), state.rho, state.var, confident)
        res.info["pair_check"]["innovation_scale"] = c
        if c > 1.0:
            std *= np.float32(c)
            self.count("innovation_scaled")

    def _overlap_predict(self, state: InverseRangeState) -> bool:
        """Whether predict of ``state`` runs beside the measurements (``FusionConfig.overlap_predict``): with numba,
        for a state of at least ``overlap_min_cells`` cells and only when no measurement can start from the predicted
        state (``PriorConfig``: a prior needs predict done first)."""
        return (self.config.overlap_predict and state.rho.size >= self.config.overlap_min_cells
                and optional_kernels() is not None and (not self.takes_prior or self.config.prior.full_every == 1))

    def _measure_all(self, live) -> list:
        """(prior, result, seconds, its pair b -> a or None) of each measurement, in order; a measurement of
        ``lr_check_kinds`` is also made b -> a, and its result is the left-right checked one."""
        out = []
        for m in live:
            ref = m.a.camera_id
            t1 = time.perf_counter()
            prior = self.prior(ref) if m.kind in self.config.prior.kinds else None
            kw = {"pair_checks": True} if self.config.pair_checks and self.measure is dense_measurement else {}
            res = (self.measure(m.a.payload, m.b.payload, prior=prior[:2], prior_level=self.config.prior.level,
                                prior_min_fraction=prior[2], **kw)
                   if prior is not None else self.measure(m.a.payload, m.b.payload, **kw))
            back = None
            if m.kind in self.config.lr_check_kinds:       # left-right check: the pair b -> a too
                back = self.measure(m.b.payload, m.a.payload, **kw)
                res = lr_checked(res, back, pair_geometry(m.a.payload, m.b.payload), self.config.lr_check)
            dt = time.perf_counter() - t1
            if not self.fresh and self.config.schedule.stereo_rig is not None:     # stereo leads edits rho:
                res = replace(res, inv_range_per_m=np.array(res.inv_range_per_m, F32))  # not the caller's arrays
            out.append((prior, res, dt, back))
        return out

    def _stereo_lead(self, m, res, stereo_res, back=None) -> dict:
        """Stereo leads (``eonav.fusion.update``): a motion measurement's pixels that disagree with this push's
        stereo measurement of the same frame are not fused; a stereo measurement restarts the cells it disagrees
        with, and, when the frame's motion measurement was fused in an earlier push (the partner's frame came
        second), the cells where that motion measurement disagrees with it. With the stereo pair's b -> a (``back``,
        the left-right check's) and ``stereo_free_space``, first the cells of the state the partner camera sees
        through (``_free_space``) are emptied; with ``UpdateConfig.skipped_free_k`` the cells the stereo pixels the
        update skips see past (``stereo_skipped_free``). Edits ``res``'s inverse range in place; returns the counts
        (gated, stereo_restarted, seen_through, skipped_free)."""
        ucfg = self.config.update
        rig = self.config.schedule.stereo_rig
        if ucfg.stereo_lead_k == 0 or rig is None:
            return {}
        ref = m.a.camera_id
        if m.kind == STEREO:
            seen = self._free_space(m, back) if back is not None and self.config.stereo_free_space else None
            kept = self._rig_motion.pop(ref, None)
            extra = None
            if kept is not None and kept[0] == (m.a.seq, m.a.stamp_us):
                extra = gate_motion(kept[1], kept[2], kept[3], res.inv_range_per_m, res.inv_range_std_per_m,
                                    res.flags, ucfg)
            out = {}
            if ucfg.skipped_free_k > 0:
                out["skipped_free"] = int(stereo_skipped_free(self.states[ref], res.inv_range_per_m,
                                                              res.inv_range_std_per_m, res.flags, ucfg).sum())
            out["stereo_restarted"] = int(stereo_restart(self.states[ref], res.inv_range_per_m,
                                                         res.inv_range_std_per_m, res.flags, ucfg,
                                                         also=extra).sum())
            return out if seen is None else dict(out, seen_through=seen)
        if stereo_res is None:
            if ref == rig[0]:       # its frame's stereo measurement may come with the partner's frame
                self._rig_motion[ref] = ((m.a.seq, m.a.stamp_us), res.inv_range_per_m.copy(),
                                         res.inv_range_std_per_m.copy(), res.flags.copy())
            return {}
        return {"gated": int(gate_motion(res.inv_range_per_m, res.inv_range_std_per_m, res.flags,
                                         stereo_res.inv_range_per_m, stereo_res.inv_range_std_per_m,
                                         stereo_res.flags, ucfg).sum())}

    def _free_space(self, m, back) -> int:
        """Empty the cells of the reference's state (before the stereo measurement is fused) that the partner
        camera sees through: its pair b -> a ranges the pixel the cell's point lands on farther than the cell holds,
        beyond both sigmas and ``lr_check.floor_px`` (``eonav.ranging.consistency``, one-sided). A moving object
        leaves its range in the cells it uncovers; where no pair of the frame ranges them again (hidden in b, as the
        background an object uncovers on the partner's side is, or ranged only with a sigma wide enough for the old
        range) they keep it, and the partner's own view of them contradicts it. Returns the cells emptied."""
        st = self.states[m.a.camera_id]
        held = st.occupied()
        if not held.any():
            return 0
        with np.errstate(invalid="ignore"):
            std = np.sqrt(st.var)
        cells = RangeResult(range_m=st.rho, confidence=st.rho, method="state", inv_range_per_m=st.rho,
                            inv_range_std_per_m=std, flags=np.where(held, VALID, 0).astype(np.uint8))
        seen, _ = inconsistent(cells, back, pair_geometry(m.a.payload, m.b.payload),
                               replace(self.config.lr_check, farther=True))
        return clear_cells(st, seen)

    def prior(self, camera_id: str):
        """The prior of the next measurement of ``camera_id``'s state (``PriorConfig``) as (rho, sigma, the least
        share of the pixels it must seed), or None: a full search."""
        cfg = self.config.prior
        st = self.states.get(camera_id)
        n_full = self._full_measured.get(camera_id, 0)
        if (not self.takes_prior or st is None or n_full == 0
                or self._since_full.get(camera_id, 0) + 1 >= cfg.full_every):
            return None
        K = optional_kernels()
        bufs = self._prior_bufs.get(camera_id)
        if bufs is None or bufs[0].shape != st.shape:
            bufs = self._prior_bufs[camera_id] = (np.empty(st.shape, F32), np.empty(st.shape, F32))
        if K is not None:
            n = K.prior_arrays(st.rho, st.var, st.a, st.b, st.n, F32(self.config.output.eta_inlier),
                               int(cfg.min_fused), *bufs)
        else:
            with np.errstate(invalid="ignore", divide="ignore"):
                ok = (st.occupied() & (st.n >= cfg.min_fused)
                      & (st.a >= F32(self.config.output.eta_inlier) * (st.a + st.b)))
            bufs[0][...] = np.where(ok, st.rho, np.nan)
            bufs[1][...] = np.where(ok, np.sqrt(st.var), np.inf)
            n = int(ok.sum())
        need = cfg.min_fraction * n_full          # the prior must hold most of what a full search measures
        if n < need:
            return None
        return bufs + (need / st.rho.size,)

    def _after_measure(self, camera_id: str, prior, res) -> bool:
        used = prior is not None and not (res.info.get("prior") or {}).get("full_search", True)
        self._since_full[camera_id] = self._since_full.get(camera_id, 0) + 1 if used else 0
        self.count("prior_seeded" if used else "full_search")
        return used


def _same(a: PosedFrameInfo, b: PosedFrameInfo) -> bool:
    """One frame: the same camera, seq and stamp."""
    return a.camera_id == b.camera_id and a.seq == b.seq and a.stamp_us == b.stamp_us


def _cpu_timed(fn, *args, **kw):
    """(fn(*args, **kw), the CPU seconds of the call on this thread)."""
    c0 = time.thread_time()
    out = fn(*args, **kw)
    return out, time.thread_time() - c0


@lru_cache(maxsize=1)
def _worker() -> ThreadPoolExecutor:
    """The one worker thread the runners' predicts run on (``FusionConfig.overlap_predict``); a push waits for its
    own predict, so one thread serves every runner."""
    return ThreadPoolExecutor(max_workers=1, thread_name_prefix="eonav-fusion-predict")


def run_frames(frames, config: FusionConfig = FusionConfig(), measure=None) -> list:
    """All fused maps of a list of posed frames pushed in order (a convenience of ``FusionRunner``)."""
    runner = FusionRunner(config, measure)
    out = []
    for f in frames:
        out.extend(runner.push(f))
    return out


def prepare_kernels() -> None:
    """Compile (or load from numba's cache) the dense method's kernels and the fusion's passes now: a pipeline that
    fuses spends this before its first frame, not in it (a fresh install compiles for tens of seconds). One small
    plane pair through a runner reaches predict, update and the fused map; the prior's arrays and the map of a
    frame that got no measurement are called directly."""
    from eonav.ranging import consistency
    from eonav.ranging.methods import dense
    from eonav.fusion.schedule import ScheduleConfig
    from eonav.ranging.pair_policy import PairPolicyConfig
    dense.prepare_kernels()
    consistency.prepare_kernels()       # the left-right check (``lr_check_kinds``), off by default
    va, vb = dense._plane_pair(96)
    probe = FusionRunner(FusionConfig(schedule=ScheduleConfig(policy=PairPolicyConfig(min_disparity_px=0.01))))
    for k, v in enumerate((va, vb, va)):
        probe.push(frame("warmup", v, 1_000_000 + k * 100_000, k))
    st = probe.states["warmup"]
    K = optional_kernels()
    if K is not None:       # the prior of a measurement (``FusionRunner.prior``), whether the probe reached it or not
        K.prior_arrays(st.rho, st.var, st.a, st.b, st.n, F32(0.65), 2, np.empty(st.shape, F32),
                       np.empty(st.shape, F32))
        one = np.ones((3, 2), F32)     # the pair checks' pose term (``measure.add_pose_sigma``), off by default
        K.pose_sigma(one[:2], one[:2].copy(), one, one, one[:, 0].copy(), F32(1.0), F32(1.0), F32(1.0))
    fused_map(st, probe.config.output)     # the map of a frame without a measurement (its own classification pass)


__all__ = ["FusionRunner", "prepare_kernels", "FusionConfig", "PriorConfig", "FusedMap", "frame", "dense_measurement", "run_frames"]
