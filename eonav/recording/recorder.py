"""Recorder service: every sample under ``eonav/<vehicle>/**`` into an MCAP file, plus Foxglove channels.

    eonav record OUT.mcap [--vehicle V] [--connect tcp/127.0.0.1:7447] [--split-size 512M] [--split-duration-s 600]
    python -m eonav.recording.recorder OUT.mcap ...          (the same, as ``eonav run --record`` starts it)

Raw channels (what ``eonav replay`` puts back): topic = the zenoh key, data = the payload bytes exactly as received,
``log_time`` = when the recorder received it (host realtime clock, ns), ``publish_time`` = the sample's zenoh
timestamp (the HLC time a router or a timestamping publisher stamped it with) or the log time when it carries none,
``sequence`` = per key, from 1 (across the files of a split recording). MCAP ``message_encoding`` is ``msgpack`` for the project's messages
(``json`` / ``cbor`` for those zenoh encodings, else the zenoh encoding string itself); the exact zenoh encoding is in
the channel metadata ``zenoh.encoding`` (one channel per key and encoding), with ``eonav.role=raw``, ``eonav.kind``
and ``eonav.schema_version`` of its first message. A sample's attachment (the project sends none today) is written just
before its payload on ``<key>/@attachment`` (``eonav.role=attachment``, same sequence number). Liveliness tokens
(``eonav/<vehicle>/alive/<service>``) are recorded as JSON ``{"alive": true|false}`` (``eonav.role=liveliness``),
never replayed. DELETE samples are counted (``deletes_ignored``), not recorded.

Foxglove channels (``eonav.recording.foxglove``; ``--no-foxglove`` to leave them out): protobuf messages of the
``foxglove.*`` schemas, their FileDescriptorSets taken from the foxglove-sdk, ``eonav.role=foxglove``, same log and
publish time as the sample they were made from.

``--attach FILE`` stores a file the recording needs (e.g. the cameras file of sync) as an MCAP attachment record.

Rotation: ``--split-size`` (bytes, with K/M/G suffixes) and ``--split-duration-s`` (seconds of log time) write
``OUT_000.mcap``, ``OUT_001.mcap``, ... each complete on its own (``eonav.recording.writer``). An existing file is
never replaced unless ``--overwrite``. On SIGINT/SIGTERM the subscriber is closed, what it had queued is written, and
the file is finished (summary and index): exit 0.

``--exclude KEYEXPR`` leaves keys out (e.g. ``eonav/*/posed/**``: the posed frames carry the frames' images again).
The recorder lowers its own CPU priority (``--nice``, default 10): the pipeline comes first, the recorder's queue
(``--queue``) absorbs the bursts. ``--compression lz4`` (the default) costs about a third of the CPU of ``zstd`` for
files about 1.5 times larger (docs/recording.md).

Health counters: ``messages``, ``bytes``, ``foxglove_messages``, ``convert_errors``, ``files``, ``liveliness_events``,
``deletes_ignored``, ``excluded``; latency ``write`` (one sample: raw + conversion).
"""
from __future__ import annotations

import json
import logging
import re
import threading
import time
from pathlib import Path

from eonav import InputError
from eonav.bus import schema
from eonav.bus import keys as K
from eonav.bus.node import Node, add_flag, service_main

# (the writer, the converter and their libraries are imported when a recording starts: ``eonav --help`` stays quick)
IMAGE_FORMATS = ("raw", "jpeg", "png")          # = eonav.recording.foxglove.IMAGE_FORMATS
DEFAULT_MAX_POINTS = 20000                      # = eonav.recording.foxglove.DEFAULT_MAX_POINTS

log = logging.getLogger("eonav.recording.recorder")

MCAP_ENCODINGS = {"application/msgpack": "msgpack", "application/json": "json", "text/json": "json",
                  "application/cbor": "cbor"}
ATTACHMENT_SUFFIX = "/@attachment"
ROLE = "eonav.role"
FOXGLOVE_METADATA = {ROLE: "foxglove"}     # one channel per topic (/tf is made from three kinds of message)


def parse_size(text) -> int | None:
    """``"512M"`` -> 536870912; ``None``/``""``/``0`` -> None (no size rotation)."""
    if text in (None, "", "0", 0):
        return None
    m = re.fullmatch(r"\s*(\d+(?:\.\d+)?)\s*([kKmMgG]?)i?[bB]?\s*", str(text))
    if not m:
        raise InputError(f"--split-size {text!r}: expected bytes, e.g. 500000, 64K, 512M or 2G")
    return int(float(m.group(1)) * 1024 ** " KMG".index(m.group(2).upper() or " "))


def mcap_encoding(zenoh_encoding: str) -> str:
    return MCAP_ENCODINGS.get(zenoh_encoding.split(";", 1)[0], zenoh_encoding)


_SCHEMAS: dict = {}


def foxglove_schema(msg):
    """The MCAP schema (SchemaDef) of a foxglove-sdk message: the FileDescriptorSet the sdk carries."""
    from eonav.recording.writer import SchemaDef
    t = type(msg)
    s = _SCHEMAS.get(t)
    if s is None:
        fs = t.get_schema()
        s = _SCHEMAS[t] = SchemaDef(fs.name, fs.encoding, bytes(fs.data))
    return s


class Recorder:
    """Samples -> a RecordingWriter (raw channel, attachment, Foxglove channels). Thread-safe; no zenoh in here,
    so tests can drive it with plain bytes."""

    def __init__(self, writer, converter=None, node: Node | None = None):
        """``writer``: a ``RecordingWriter``; ``converter``: a ``FoxgloveConverter`` or None (raw only)."""
        self.writer, self.converter, self.node = writer, converter, node
        self.lock = threading.Lock()
        self._raw_md: dict[tuple, dict] = {}
        self._seq: dict[str, int] = {}

    def _count(self, name: str, n: int = 1) -> None:
        if self.node is not None:
            self.node.count(name, n)

    def _raw_metadata(self, key: str, encoding: str, payload: bytes) -> dict:
        md = self._raw_md.get((key, encoding))
        if md is None:
            md = {ROLE: "raw", "zenoh.encoding": encoding}
            if mcap_encoding(encoding) == "msgpack":
                try:
                    import msgpack
                    doc = msgpack.unpackb(payload, raw=False)
                    md.update({"eonav.kind": str(doc.get("kind", "")), "eonav.schema_version": str(doc.get("v", ""))})
                except Exception:
                    pass
            self._raw_md[(key, encoding)] = md
        return md

    def record(self, key: str, encoding: str, payload: bytes, log_time_ns: int, publish_time_ns: int | None = None,
               attachment: bytes | None = None) -> None:
        t0 = time.perf_counter()
        md = self._raw_metadata(key, encoding, payload)
        with self.lock:
            seq = self._seq[key] = self._seq.get(key, 0) + 1
            if attachment is not None:
                self.writer.add(key + ATTACHMENT_SUFFIX, "application/octet-stream", attachment, log_time_ns,
                                publish_time_ns, metadata={ROLE: "attachment", "eonav.attachment_for": key},
                                sequence=seq)
            n_files = len(self.writer.files)
            self.writer.add(key, mcap_encoding(encoding), payload, log_time_ns, publish_time_ns, metadata=md,
                            sequence=seq, may_rotate=attachment is None)
            if len(self.writer.files) != n_files:
                self._count("files")
        self._count("messages")
        self._count("bytes", len(payload))
        if self.converter is not None and md.get("eonav.kind"):
            self._convert(key, payload, log_time_ns, publish_time_ns)
        if self.node is not None:
            self.node.latency("write", time.perf_counter() - t0)

    def _convert(self, key: str, payload: bytes, log_time_ns: int, publish_time_ns: int | None) -> None:
        try:
            out = self.converter.convert(schema.decode(payload))
            encoded = [(topic, foxglove_schema(m), m.encode()) for topic, m in out]
        except Exception as e:     # a malformed message is still recorded raw; its picture is skipped
            self._count("convert_errors")
            if self.node is not None:
                self.node.log_limited(f"convert:{key}", logging.WARNING, "no Foxglove message for %s: %s", key, e)
            else:
                log.warning("no Foxglove message for %s: %s", key, e)
            return
        with self.lock:
            for topic, sch, data in encoded:
                self.writer.add(topic, "protobuf", data, log_time_ns, publish_time_ns, schema=sch,
                                metadata=FOXGLOVE_METADATA)
        self._count("foxglove_messages", len(encoded))

    def liveliness(self, key: str, alive: bool, log_time_ns: int) -> None:
        with self.lock:
            self.writer.add(key, "json", json.dumps({"alive": bool(alive)}).encode(), log_time_ns,
                            metadata={ROLE: "liveliness"})
        self._count("liveliness_events")

    def close(self) -> None:
        with self.lock:
            self.writer.close()


def add_arguments(p) -> None:
    p.add_argument("output", metavar="OUT.mcap", help="the recording (with rotation: OUT_000.mcap, OUT_001.mcap, ...)")
    g = p.add_argument_group("recording")
    add_flag(g, "--split-size", env="EONAV_RECORD_SPLIT_SIZE", default=None, metavar="BYTES",
             help="start a new file after this many bytes (suffix K, M, G)")
    add_flag(g, "--split-duration-s", env="EONAV_RECORD_SPLIT_DURATION_S", default=None, type=float, metavar="S",
             help="start a new file after this many seconds", aliases="--split-duration",
             old_env="EONAV_RECORD_SPLIT_DURATION")
    add_flag(g, "--compression", env="EONAV_RECORD_COMPRESSION", default="lz4", choices=("lz4", "zstd", "none"),
             help="chunk compression: lz4 (least CPU), zstd (smallest files)")
    add_flag(g, "--overwrite", env="EONAV_RECORD_OVERWRITE", default=False, action="store_true",
             help="replace existing files")
    add_flag(g, "--no-foxglove", env="EONAV_RECORD_NO_FOXGLOVE", default=False, action="store_true",
             help="raw channels only (no Foxglove channels)")
    add_flag(g, "--images", env="EONAV_RECORD_IMAGES", default="jpeg", choices=IMAGE_FORMATS,
             help="Foxglove images: RawImage (raw) or CompressedImage (jpeg, png)")
    add_flag(g, "--max-points", env="EONAV_RECORD_MAX_POINTS", default=DEFAULT_MAX_POINTS, type=int,
             help="largest point cloud per range map (the map is subsampled to fit)")
    add_flag(g, "--range-near-m", env="EONAV_RECORD_RANGE_NEAR_M", default=5.0, type=float, metavar="M",
             help="range colour scale: this range and nearer are red", aliases="--range-near",
             old_env="EONAV_RECORD_RANGE_NEAR")
    add_flag(g, "--range-far-m", env="EONAV_RECORD_RANGE_FAR_M", default=150.0, type=float, metavar="M",
             help="range colour scale: this range and farther are blue", aliases="--range-far",
             old_env="EONAV_RECORD_RANGE_FAR")
    add_flag(g, "--queue", env="EONAV_RECORD_QUEUE", default=256, type=int,
             help="samples the subscriber queues while the writer is busy")
    add_flag(g, "--nice", env="EONAV_RECORD_NICE", default=10, type=int, metavar="N",
             help="lower the recorder's CPU priority by N (os.nice): the pipeline first, the recorder in its gaps")
    g.add_argument("--exclude", action="append", default=[], metavar="KEYEXPR",
                   help="do not record keys matching this (repeatable), e.g. 'eonav/*/posed/**' (the frames again)")
    g.add_argument("--attach", action="append", default=[], metavar="FILE",
                   help="store FILE in the recording as an MCAP attachment (e.g. the cameras file; repeatable)")


def make_recorder(args, node: Node | None, vehicle: str) -> Recorder:
    from eonav.recording.foxglove import FoxgloveConverter
    from eonav.recording.writer import RecordingWriter
    out = Path(args.output).expanduser().resolve()
    writer = RecordingWriter(out, split_bytes=parse_size(args.split_size), split_s=args.split_duration_s,
                             overwrite=args.overwrite, compression=args.compression)
    writer.add_metadata("eonav.recording", {"vehicle": vehicle, "key_expr": K.vehicle_all(vehicle),
                                            "schema_version": str(schema.SCHEMA_VERSION),
                                            "started_unix_ns": str(time.time_ns())})
    for a in args.attach:
        p = Path(a)
        if not p.is_file():
            raise InputError(f"--attach {a}: no such file")
        writer.add_attachment(p.name, "application/json" if p.suffix == ".json" else "application/octet-stream",
                              p.read_bytes())
    conv = None if args.no_foxglove else FoxgloveConverter(args.images, near_m=args.range_near_m, far_m=args.range_far_m,
                                                           max_points=args.max_points)
    return Recorder(writer, conv, node)


def body(node: Node, args) -> None:
    import zenoh
    if args.nice > 0:
        import os
        os.nice(args.nice)
    rec = make_recorder(args, node, node.vehicle)
    key = K.vehicle_all(node.vehicle)
    sub = node.subscribe(key, fifo=args.queue)
    alive = node.session.liveliness().declare_subscriber(K.alive_all(node.vehicle), zenoh.handlers.FifoChannel(256),
                                                         history=True)
    node.set_state("ok", f"recording {key} to {rec.writer.path}")
    node.log.info("recording %s to %s", key, rec.writer.path)

    def watch_liveliness():
        try:
            while not node.stop_event.is_set():
                s = alive.try_recv()
                if s is None:
                    node.stop_event.wait(0.05)
                    continue
                rec.liveliness(str(s.key_expr), s.kind == zenoh.SampleKind.PUT, time.time_ns())
        finally:
            alive.undeclare()

    live = threading.Thread(target=watch_liveliness, name="recorder.liveliness")

    excluded = [zenoh.KeyExpr(e) for e in args.exclude]

    def record_loop():
        live.start()
        try:
            for s in sub:
                log_ns = time.time_ns()
                if s.kind != zenoh.SampleKind.PUT:
                    node.count("deletes_ignored")
                    continue
                if excluded and any(s.key_expr.intersects(e) for e in excluded):
                    node.count("excluded")
                    continue
                ts = s.timestamp
                pub_ns = ts.get_time_as_ntp64().as_nanos() if ts is not None else None
                att = s.attachment.to_bytes() if s.attachment is not None else None
                rec.record(str(s.key_expr), str(s.encoding), s.payload.to_bytes(), log_ns, pub_ns, att)
        finally:
            live.join()
            rec.close()
            node.log.info("recording finished: %d messages in %s", rec.writer.messages,
                          ", ".join(str(p) for p in rec.writer.files))

    node.worker(record_loop, name="record")


def recorder_service(path, name: str = "recorder") -> dict:
    """The pipeline-spec entry of a recorder writing ``path`` (``eonav run --record``). Not restarted: a restart
    would stop at the existing file (and must not replace it)."""
    return {"name": name, "module": "eonav.recording.recorder", "restart": False,
            "args": [str(Path(path).expanduser().resolve()), "--mode", "client"]}


if __name__ == "__main__":
    service_main("recorder", add_arguments, body)
