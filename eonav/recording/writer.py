"""MCAP files written with the ``mcap`` library, rotated by size and by time.

One :class:`RecordingWriter` holds one open ``mcap.writer.Writer`` at a time. Channels and schemas are registered on
first use and again in every new file, so each file of a split recording is complete on its own (its own schemas,
channels, metadata, summary and index) and any one of them opens in a reader or in Foxglove.

File names: without rotation, exactly the path given. With ``split_bytes`` or ``split_s`` the parts are
``<stem>_000.mcap``, ``<stem>_001.mcap``, ... beside it. A part is closed once the bytes written reach ``split_bytes``
(checked before each message: a part can exceed it by the chunk being built, at most ``chunk_bytes`` before
compression, and by its summary) or once the log time of a message is ``split_s`` past the
first message of the part (that message then opens the next part).

Times are integer nanoseconds (MCAP's unit). Chunks are compressed with ``compression``: ``zstd`` (the library's
default: smaller files) or ``lz4`` (about 3 times less CPU; docs/recording.md has the figures), or not at all.
"""
from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path

from mcap.writer import CompressionType, Writer

from eonav import InputError

LIBRARY = "eonav"
DEFAULT_CHUNK_BYTES = 1024 * 1024
COMPRESSIONS = {"zstd": CompressionType.ZSTD, "lz4": CompressionType.LZ4, "none": CompressionType.NONE}


@dataclass(frozen=True)
class SchemaDef:
    """A schema as MCAP stores it: name, encoding (``protobuf``, ``jsonschema``, ...) and bytes."""
    name: str
    encoding: str
    data: bytes


def part_path(path: Path, index: int) -> Path:
    return path.with_name(f"{path.stem}_{index:03d}{path.suffix or '.mcap'}")


class RecordingWriter:
    """``add(topic, message_encoding, data, log_time_ns, publish_time_ns, schema=None, metadata=None)`` writes one
    message; ``close()`` finishes the current file (summary and index). ``metadata`` of a channel is part of its
    identity: the same topic with other metadata (e.g. another zenoh encoding) is another channel.

    ``overwrite=False`` refuses to replace an existing file (InputError naming it): a recorder restarted by a
    supervisor must not destroy what it wrote before."""

    def __init__(self, path, *, split_bytes: int | None = None, split_s: float | None = None,
                 chunk_bytes: int = DEFAULT_CHUNK_BYTES, overwrite: bool = False, profile: str = "",
                 compression: str = "zstd"):
        self.path = Path(path)
        if self.path.suffix.lower() != ".mcap":
            raise InputError(f"recording {self.path}: expected a file name ending in .mcap")
        if split_bytes is not None and split_bytes < 64 * 1024:
            raise InputError(f"split size {split_bytes} bytes: expected at least 64 KiB")
        if split_s is not None and not split_s > 0:
            raise InputError(f"split duration {split_s} s: expected a positive number of seconds")
        if compression not in COMPRESSIONS:
            raise InputError(f"compression {compression!r}: expected one of {sorted(COMPRESSIONS)}")
        self.compression = COMPRESSIONS[compression]
        if not self.path.parent.is_dir():
            raise InputError(f"recording {self.path}: directory {self.path.parent} does not exist")
        self.split_bytes, self.split_s = split_bytes, split_s
        self.rotating = split_bytes is not None or split_s is not None
        self.chunk_bytes = chunk_bytes if split_bytes is None else min(chunk_bytes, max(16 * 1024, split_bytes // 4))
        self.overwrite, self.profile = overwrite, profile
        self.files: list[Path] = []
        self.metadata: dict[str, dict[str, str]] = {}
        self.attachments: list[tuple[str, str, bytes]] = []
        self.messages = 0
        self._f = None
        self._w: Writer | None = None
        self._schemas: dict[SchemaDef, int] = {}
        self._channels: dict[tuple, int] = {}
        self._seq: dict[int, int] = {}
        self._part_t0_ns: int | None = None
        if not self.rotating:
            self._check_free(self.path)
        else:
            self._check_free(part_path(self.path, 0))

    def _check_free(self, p: Path) -> None:
        if p.exists() and not self.overwrite:
            raise InputError(f"recording {p} already exists; choose another name or pass --overwrite")

    # ---- files ----------------------------------------------------------------------------------
    def _open(self, log_time_ns: int) -> None:
        p = part_path(self.path, len(self.files)) if self.rotating else self.path
        self._check_free(p)
        self._f = open(p, "wb")
        self._w = Writer(self._f, chunk_size=self.chunk_bytes, compression=self.compression)
        self._w.start(profile=self.profile, library=LIBRARY)
        for name, data in self.metadata.items():
            self._w.add_metadata(name, data)
        for att in self.attachments:
            self._write_attachment(*att)
        self._schemas, self._channels, self._seq = {}, {}, {}
        self._part_t0_ns = log_time_ns
        self.files.append(p)

    def _finish(self) -> None:
        if self._w is not None:
            self._w.finish()
            self._f.close()
            self._w = self._f = None

    def close(self) -> None:
        """Finish the current file. A writer that never got a message still leaves one valid, empty file."""
        if self._w is None and not self.files:
            self._open(0)
        self._finish()

    def add_metadata(self, name: str, data: dict) -> None:
        """A metadata record (string map) written into the current file and every later one."""
        d = {str(k): v if isinstance(v, str) else json.dumps(v) for k, v in data.items()}
        self.metadata[name] = d
        if self._w is not None:
            self._w.add_metadata(name, d)

    def add_attachment(self, name: str, media_type: str, data: bytes) -> None:
        """An MCAP attachment (a file the recording needs, e.g. the cameras file) in the current file and every
        later one."""
        self.attachments.append((name, media_type, bytes(data)))
        if self._w is not None:
            self._write_attachment(name, media_type, bytes(data))

    def _write_attachment(self, name: str, media_type: str, data: bytes) -> None:
        import time
        t = time.time_ns()
        self._w.add_attachment(create_time=t, log_time=self._part_t0_ns or t, name=name, media_type=media_type,
                               data=data)

    # ---- messages -------------------------------------------------------------------------------
    def _channel(self, topic: str, message_encoding: str, schema: SchemaDef | None, metadata: dict | None) -> int:
        md = tuple(sorted((metadata or {}).items()))
        key = (topic, message_encoding, schema, md)
        cid = self._channels.get(key)
        if cid is None:
            sid = 0
            if schema is not None:
                sid = self._schemas.get(schema)
                if sid is None:
                    sid = self._schemas[schema] = self._w.register_schema(schema.name, schema.encoding, schema.data)
            cid = self._channels[key] = self._w.register_channel(topic, message_encoding, sid, dict(md))
        return cid

    def bytes_written(self) -> int:
        return self._f.tell() if self._f is not None else 0

    def add(self, topic: str, message_encoding: str, data: bytes, log_time_ns: int, publish_time_ns: int | None = None,
            *, schema: SchemaDef | None = None, metadata: dict | None = None, sequence: int | None = None,
            may_rotate: bool = True) -> int:
        """Write one message; returns its sequence number (per channel and file, from 1, or ``sequence``).
        ``may_rotate=False`` keeps the message in the file of the one before (a payload and its attachment)."""
        if self._w is not None and may_rotate and self._part_full(log_time_ns):
            self._finish()
        if self._w is None:
            self._open(log_time_ns)
        cid = self._channel(topic, message_encoding, schema, metadata)
        if sequence is None:
            sequence = self._seq.get(cid, 0) + 1
        self._seq[cid] = sequence
        self._w.add_message(cid, log_time=int(log_time_ns), data=data,
                            publish_time=int(log_time_ns if publish_time_ns is None else publish_time_ns),
                            sequence=int(sequence) & 0xFFFFFFFF)
        self.messages += 1
        return sequence

    def _part_full(self, log_time_ns: int) -> bool:
        if self.split_bytes is not None and self.bytes_written() >= self.split_bytes:
            return True
        return self.split_s is not None and log_time_ns - self._part_t0_ns >= self.split_s * 1e9
