"""Recorded sources of ``eonav run`` and the one replay shift they share.

A recording is an image folder or a video file with its recorded stamps (the folder's ``timestamps.txt``, the
video's ``<name>.timestamps.txt``; the camera ingest's formats) plus a MAVLink tlog. Replayed together they must
get the same ``--replay-shift-us`` (bus stamp = recorded stamp + shift, each record released when the host clock
reaches it): each replay mapped onto "now at its own start" puts the streams apart by the difference of the start
times, and frames then fall outside the navigation they need (docs/bus.md, "Camera ingest"). The shift puts the
recording's first record a start-up lead from now; ``eonav run`` computes it when the replays start, once the services
that consume them are alive.
"""
from __future__ import annotations

import time
from dataclasses import dataclass
from pathlib import Path

from eonav import InputError

DEFAULT_START_IN_S = 2.0      # a replay's own start-up (imports, zenoh session, waiting for its subscribers)


@dataclass
class SourceStart:
    """One source of a run: ``kind`` (folder / file / v4l2 / stream / tlog / link) and, for a recording with
    stamps, its first stamp (``first_us``; None otherwise)."""
    what: str
    kind: str
    first_us: int | None

    @property
    def recorded(self) -> bool:
        return self.kind in ("folder", "file", "tlog")


def camera_stamps_file(source) -> Path | None:
    """The recorded-stamps file of an image folder or a video file (None when it has none)."""
    from eonav.services.camera_ingest import TIMESTAMPS_FILE, video_timestamps_file
    p = Path(source)
    t = p / TIMESTAMPS_FILE if p.is_dir() else video_timestamps_file(p)
    return t if t.is_file() else None


def camera_start(what: str, source: str) -> SourceStart:
    from eonav.services.camera_ingest import classify_source, parse_timestamps
    kind = classify_source(source)
    first = None
    if kind in ("folder", "file"):
        t = camera_stamps_file(source)
        stamps = parse_timestamps(t) if t is not None else []
        first = stamps[0] if stamps else None
    return SourceStart(what, kind, first)


def mavlink_start(what: str, source: str) -> SourceStart:
    from eonav.services.mavlink_ingest import is_tlog
    if not is_tlog(source):
        return SourceStart(what, "link", None)
    from eonav.nav.mavlink_in import TlogReader
    if not Path(source).is_file():
        raise InputError(f"{what} {source}: no such tlog file")
    with TlogReader(source) as reader:
        first = next(iter(reader), None)
    if first is None:
        raise InputError(f"{what} {source}: no MAVLink record in the tlog")
    return SourceStart(what, "tlog", int(first[0]))


def joint_replay_shift_us(starts: list[SourceStart], start_in_s: float = DEFAULT_START_IN_S,
                          now_us: int | None = None) -> int | None:
    """The shift every replay of ``starts`` gets: the earliest first stamp lands ``start_in_s`` from now. None when
    fewer than two sources are recorded (nothing to keep in step) or when recordings are mixed with live sources
    (a live stream cannot be shifted; each replay then maps onto the current clock by itself). A recording without
    stamps beside another recording is an error: it could not be replayed in step."""
    rec = [s for s in starts if s.recorded]
    if len(rec) < 2 or len(rec) < len(starts):
        return None
    unstamped = [s for s in rec if s.first_us is None]
    if unstamped:
        s = unstamped[0]
        where = ("timestamps.txt in the folder" if s.kind == "folder"
                 else "<video name>.timestamps.txt beside the video")
        raise InputError(f"{s.what}: a recording without recorded stamps cannot be replayed in step with the other "
                         f"recordings; expected {where} (one stamp per frame, docs/bus.md)")
    now = time.time_ns() // 1000 if now_us is None else int(now_us)
    return now + int(round(start_in_s * 1e6)) - min(s.first_us for s in rec)
