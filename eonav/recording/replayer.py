"""Replay service: the raw channels of MCAP recordings back onto the bus, with their keys, encodings and attachments.

    eonav replay IN.mcap [IN_001.mcap ...] [--speed N | --as-fast-as-possible] [--connect tcp/127.0.0.1:7447]
    python -m eonav.recording.replayer IN.mcap ...          (the same, as a pipeline service)

What is put: every message of a channel with ``eonav.role=raw`` (``eonav.recording.recorder``), in file order (the
order the recorder received them), payload bytes unchanged, with ``zenoh.encoding`` from the channel metadata and the
attachment recorded with it. Keys matching ``--exclude`` (default ``eonav/*/health/*``: the health of processes that
are not running now) are skipped; ``--include`` narrows to some keys. ``--as-vehicle V`` rewrites the key prefix
``eonav/<recorded vehicle>/`` to ``eonav/V/``. Stamps inside the messages are not changed.

Pacing, by the recorded log times: real time (``--speed 1``, the default), ``--speed N`` times faster, or
``--as-fast-as-possible`` (no pacing). Every publisher uses CongestionControl.BLOCK: the bus never drops a replayed
sample, and a full transport queue (a slow link or peer) makes the replay wait; what a consumer's own queue keeps (a
ring channel keeps the newest samples only) is that consumer's choice.

First messages are never lost to a subscriber that is still connecting: all publishers are declared first, then the
replay waits until each key selected by ``--wait-for`` (default: every replayed key) has a matching subscriber
(``publisher.matching_status.matching``), at most ``--wait-timeout-s`` seconds; keys still without a subscriber then are
logged and replayed anyway (nobody listens to them). ``--wait-timeout-s 0`` starts at once.

All keys are put with one priority (DATA), so samples of different keys cannot overtake each other on the way.
End of the recordings: exit 0 (``eonav run --exit-when-done``). Health counters: ``messages``, ``bytes``.
"""
from __future__ import annotations

import logging
import time
from dataclasses import dataclass
from pathlib import Path

from eonav import InputError
from eonav.bus import keys as K
from eonav.bus.node import Node, add_flag, service_main
from eonav.recording.recorder import ATTACHMENT_SUFFIX, ROLE

log = logging.getLogger("eonav.recording.replayer")

DEFAULT_EXCLUDE = ("eonav/*/health/*",)


@dataclass
class Record:
    """One raw message to put."""
    key: str
    encoding: str
    payload: bytes
    attachment: bytes | None
    log_time_ns: int
    publish_time_ns: int


def _open_reader(path: Path):
    from mcap.reader import make_reader
    if not path.is_file():
        raise InputError(f"recording {path}: no such file")
    f = open(path, "rb")
    try:
        reader = make_reader(f)
        reader.get_header()
    except Exception as e:
        f.close()
        raise InputError(f"recording {path}: not an MCAP file ({type(e).__name__}: {e})") from None
    return f, reader


def _in_file_order(f, reader):
    """(schema, channel, message) of a file in file order. A file without a readable footer (a recorder killed
    mid-write) is read front to back: its index is what is missing, not its first chunks."""
    from mcap.reader import NonSeekingReader
    try:
        reader.get_summary()
    except Exception:
        f.seek(0)
        reader = NonSeekingReader(f)
    return reader.iter_messages(log_time_order=False)


def read_records(paths, include=None, exclude=DEFAULT_EXCLUDE, as_vehicle: str | None = None):
    """Yield the raw :class:`Record` s of ``paths`` in file order (files in the order given)."""
    import zenoh
    inc = [zenoh.KeyExpr(e) for e in (include or [])]
    exc = [zenoh.KeyExpr(e) for e in (exclude or [])]
    for path in map(Path, paths):
        f, reader = _open_reader(path)
        with f:
            pending: dict[tuple, bytes] = {}
            try:
                for _schema, channel, message in _in_file_order(f, reader):
                    role = channel.metadata.get(ROLE)
                    if role == "attachment":
                        pending[(channel.metadata.get("eonav.attachment_for"), message.sequence)] = message.data
                        continue
                    if role != "raw":
                        continue
                    key = channel.topic
                    att = pending.pop((key, message.sequence), None)
                    ke = zenoh.KeyExpr(key)
                    if (inc and not any(ke.intersects(e) for e in inc)) or any(ke.intersects(e) for e in exc):
                        continue
                    if as_vehicle:
                        key = rewrite_vehicle(key, as_vehicle)
                    yield Record(key, channel.metadata.get("zenoh.encoding", "application/msgpack"), message.data,
                                 att, message.log_time, message.publish_time)
            except InputError:
                raise
            except Exception as e:   # a truncated file (a recorder killed mid-write): what was read stays replayed
                log.warning("recording %s: stopped reading at a damaged record (%s: %s)", path, type(e).__name__, e)


def rewrite_vehicle(key: str, vehicle: str) -> str:
    parts = key.split("/", 2)
    if len(parts) < 3 or parts[0] != K.ROOT:
        return key
    return f"{K.ROOT}/{K.check_chunk(vehicle, '--as-vehicle')}/{parts[2]}"


def recorded_keys(paths, **kw) -> list[tuple[str, str]]:
    """(key, encoding) of every raw channel that would be replayed, from the files' summaries (no message read;
    a file without one, cut short, is read)."""
    import zenoh
    inc = [zenoh.KeyExpr(e) for e in (kw.get("include") or [])]
    exc = [zenoh.KeyExpr(e) for e in (kw.get("exclude", DEFAULT_EXCLUDE) or [])]
    out = []
    for path in map(Path, paths):
        f, reader = _open_reader(path)
        with f:
            try:
                summary = reader.get_summary()
            except Exception:
                summary = None
            if summary is None:     # no summary (a file cut short): the keys of the messages that can be read
                for rec in read_records([path], include=kw.get("include"), exclude=kw.get("exclude", DEFAULT_EXCLUDE),
                                        as_vehicle=kw.get("as_vehicle")):
                    if (rec.key, rec.encoding) not in out:
                        out.append((rec.key, rec.encoding))
                continue
            for ch in summary.channels.values():
                if ch.metadata.get(ROLE) != "raw" or ch.topic.endswith(ATTACHMENT_SUFFIX):
                    continue
                ke = zenoh.KeyExpr(ch.topic)
                if (inc and not any(ke.intersects(e) for e in inc)) or any(ke.intersects(e) for e in exc):
                    continue
                key = rewrite_vehicle(ch.topic, kw["as_vehicle"]) if kw.get("as_vehicle") else ch.topic
                item = (key, ch.metadata.get("zenoh.encoding", "application/msgpack"))
                if item not in out:
                    out.append(item)
    return out


def wait_for_subscribers(publishers: dict, wait_for, timeout_s: float, stop_event, poll_s: float = 0.02) -> list:
    """Wait until every publisher whose key matches ``wait_for`` (all when empty) has a matching subscriber, or
    ``timeout_s``; returns the keys still without one. 50 ms more after the last match, so routes are up on every hop
    (as ``Node.wait_matching``)."""
    import zenoh
    exprs = [zenoh.KeyExpr(e) for e in (wait_for or [])]
    todo = {k: p for k, p in publishers.items() if not exprs or any(zenoh.KeyExpr(k).intersects(e) for e in exprs)}
    deadline = time.monotonic() + timeout_s
    while todo and not stop_event.is_set():
        todo = {k: p for k, p in todo.items() if not p.matching_status.matching}
        if not todo:
            stop_event.wait(0.05)
            break
        if time.monotonic() >= deadline:
            break
        stop_event.wait(poll_s)
    return sorted(todo)


def add_arguments(p) -> None:
    p.add_argument("inputs", nargs="+", metavar="IN.mcap", help="recordings, replayed one after the other")
    g = p.add_argument_group("replay")
    pace = g.add_mutually_exclusive_group()
    add_flag(pace, "--speed", env="EONAV_REPLAY_SPEED", default=1.0, type=float, metavar="FACTOR",
             help="FACTOR times real time")
    pace.add_argument("--as-fast-as-possible", action="store_true", help="no pacing (the bus still never drops)")
    g.add_argument("--include", action="append", default=None, metavar="KEYEXPR",
                   help="replay only keys matching this (repeatable)")
    g.add_argument("--exclude", action="append", default=None, metavar="KEYEXPR",
                   help=f"skip keys matching this (repeatable; default {' '.join(DEFAULT_EXCLUDE)})")
    g.add_argument("--as-vehicle", default=None, metavar="V", help="replay under eonav/V/ instead of the recorded vehicle")
    g.add_argument("--wait-for", action="append", default=None, metavar="KEYEXPR",
                   help="keys that must have a subscriber before the first message (repeatable; default: all)")
    add_flag(g, "--wait-timeout-s", env="EONAV_REPLAY_WAIT_TIMEOUT_S", default=10.0, type=float, metavar="S",
             help="longest wait for subscribers before the first message", aliases="--wait-timeout",
             old_env="EONAV_REPLAY_WAIT_TIMEOUT")


def body(node: Node, args) -> None:
    import zenoh
    if not args.as_fast_as_possible and not args.speed > 0:
        raise InputError(f"--speed {args.speed}: expected a positive factor (or --as-fast-as-possible)")
    exclude = DEFAULT_EXCLUDE if args.exclude is None else args.exclude
    sel = dict(include=args.include, exclude=exclude, as_vehicle=args.as_vehicle)
    keys = recorded_keys(args.inputs, **sel)
    if not keys:
        raise InputError(f"{', '.join(args.inputs)}: no raw channel to replay (not an eonav recording, or all "
                         "keys excluded)")
    # one priority for every key: samples of different priorities travel in different queues and could overtake
    # each other; with one, the bus keeps the recorded order
    pubs = {}
    for key, _enc in keys:
        if key not in pubs:
            pubs[key] = node.publisher(key, priority=zenoh.Priority.DATA, express=False)
    speed = None if args.as_fast_as_possible else float(args.speed)

    def replay():
        missing = wait_for_subscribers(pubs, args.wait_for, args.wait_timeout_s, node.stop_event)
        if node.stop_event.is_set():
            return
        if missing:
            node.log.warning("no subscriber after %.1f s for %s; replaying anyway", args.wait_timeout_s,
                             ", ".join(missing))
        n, t0_wall, t0_log = 0, None, None
        encodings: dict[str, zenoh.Encoding] = {}
        for rec in read_records(args.inputs, **sel):
            if node.stop_event.is_set():
                return
            if speed is not None:
                if t0_wall is None:
                    t0_wall, t0_log = time.monotonic(), rec.log_time_ns
                due = t0_wall + (rec.log_time_ns - t0_log) / 1e9 / speed
                if node.stop_event.wait(max(0.0, due - time.monotonic())):
                    return
            enc = encodings.get(rec.encoding)
            if enc is None:
                enc = encodings[rec.encoding] = zenoh.Encoding(rec.encoding)
            pubs[rec.key].put(rec.payload, encoding=enc, attachment=rec.attachment)
            n += 1
            node.count("messages")
            node.count("bytes", len(rec.payload))
            node.tick("messages")
        node.set_state("ok", f"replayed {n} messages")
        node.stop(f"end of the recording ({n} messages)")

    node.worker(replay, name="replay")


if __name__ == "__main__":
    service_main("replay", add_arguments, body)
