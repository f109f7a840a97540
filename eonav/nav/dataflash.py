"""ArduPilot dataflash logs (``.BIN``, read with pymavlink's DFReader) as the MAVLink messages the ingest decodes.

A dataflash log is what the autopilot writes to its own SD card: messages defined by FMT records, stamped with
``TimeUS`` (autopilot boot time, us). ``DataflashReader`` yields ``(stamp_us, message)`` as ``TlogReader`` does, each
message shaped as the MAVLink message that carries the same quantity, so ``NavDecoder`` validates it the same way:

- ``ATT`` (AHRS attitude, deg)          -> ATTITUDE (rad, yaw wrapped to +-pi; no rates);
- ``XKQ`` of EKF core 0 (quaternion)    -> ATTITUDE_QUATERNION;
- ``XKF1`` of EKF core 0 (PN/PE/PD, VN/VE/VD about the EKF origin) -> LOCAL_POSITION_NED, once the log has an
  ``ORGN`` (before it the EKF has no origin and ArduPilot sends no LOCAL_POSITION_NED either);
- ``POS`` (AHRS position, deg, m AMSL)  -> GLOBAL_POSITION_INT (no velocity).

``stamp_us`` is the UNIX time DFReader gives the message (its boot time plus the offset of the first GPS message
with a week number; boot time if the log has no GPS time): an exact "receive" time, so the ingest's receive-time
clock estimate is the log's own GPS clock. Message units and field names: docs/mavlink.md.
"""
from __future__ import annotations

import contextlib
import math
import mmap
import struct
from dataclasses import dataclass

from eonav import InputError

DATAFLASH_MAGIC = b"\xa3\x95"
NAV_SOURCES = ("ATT", "XKQ", "XKF1", "POS")


def is_dataflash(path) -> bool:
    """True when the file starts as a dataflash log (the two header bytes of every message, A3 95)."""
    try:
        with open(path, "rb") as f:
            return f.read(2) == DATAFLASH_MAGIC
    except OSError:
        return False


class DFNav:
    """A MAVLink-shaped message made from a dataflash message (system 1, component 1: the autopilot itself)."""

    def __init__(self, mav_type: str, stamp_s: float, **fields):
        self._type = mav_type
        self._timestamp = stamp_s
        self.__dict__.update(fields)

    def get_type(self) -> str:
        return self._type

    def get_srcSystem(self) -> int:
        return 1

    def get_srcComponent(self) -> int:
        return 1

    def __repr__(self):
        return f"{self._type} {{{', '.join(f'{k}: {v}' for k, v in vars(self).items() if not k.startswith('_'))}}}"


@dataclass
class DataflashStats:
    records: int = 0          # dataflash messages read
    nav: int = 0              # of them, turned into navigation messages
    no_origin: int = 0        # XKF1 before the log's ORGN: no local position yet
    other_core: int = 0       # XKF1 / XKQ of another EKF core
    bad_fields: int = 0       # navigation messages with a field missing or not a number (e.g. POS.Lat NaN)
    resync_bytes: int = 0     # bytes between messages that are not a message (DFReader skips them)
    truncated_bytes: int = 0  # bytes at the end that do not form a whole message
    reader_warnings: int = 0  # lines DFReader printed about the damage it met (kept off the console)


class _Quiet(contextlib.ExitStack):
    def __init__(self, sink):
        super().__init__()
        self.enter_context(contextlib.redirect_stdout(sink))
        self.enter_context(contextlib.redirect_stderr(sink))


def _wrap_pi(a: float) -> float:
    return (a + math.pi) % (2.0 * math.pi) - math.pi


def convert(m, have_origin: bool):
    """The MAVLink-shaped message of one dataflash message, or None (the reason is the caller's to count)."""
    t = m.get_type()
    stamp = float(m._timestamp)
    boot_ms = int(m.TimeUS) // 1000
    nan = math.nan
    if t == "ATT":
        return DFNav("ATTITUDE", stamp, time_boot_ms=boot_ms, roll=math.radians(m.Roll),
                     pitch=math.radians(m.Pitch), yaw=_wrap_pi(math.radians(m.Yaw)),
                     rollspeed=nan, pitchspeed=nan, yawspeed=nan)
    if t == "XKQ":
        return DFNav("ATTITUDE_QUATERNION", stamp, time_boot_ms=boot_ms, q1=m.Q1, q2=m.Q2, q3=m.Q3, q4=m.Q4,
                     rollspeed=nan, pitchspeed=nan, yawspeed=nan)
    if t == "XKF1":
        if not have_origin:
            return None
        return DFNav("LOCAL_POSITION_NED", stamp, time_boot_ms=boot_ms, x=m.PN, y=m.PE, z=m.PD,
                     vx=m.VN, vy=m.VE, vz=m.VD)
    if t == "POS":
        rel = getattr(m, "RelHomeAlt", 0.0)
        return DFNav("GLOBAL_POSITION_INT", stamp, time_boot_ms=boot_ms, lat=int(round(m.Lat * 1e7)),
                     lon=int(round(m.Lng * 1e7)), alt=int(round(m.Alt * 1000)), relative_alt=int(round(rel * 1000)),
                     vx=nan, vy=nan, vz=nan, hdg=65535)
    return None


def check_formats(data, where: str) -> int:
    """Walk the log as DFReader does (a message = A3 95, a type byte defined by an FMT record, then its body; any
    other byte is skipped) and refuse an FMT record whose length is not its format's size: DFReader trusts it, and a
    length below 3 makes it read the same bytes forever. Returns the number of FMT records."""
    from pymavlink.DFReader import FORMAT_TO_STRUCT
    lengths = {0x80: 89}
    ofs, n, count = 0, len(data), 0
    while ofs + 3 <= n:
        if data[ofs] != 0xA3 or data[ofs + 1] != 0x95 or data[ofs + 2] not in lengths:
            ofs += 1
            continue
        t, length = data[ofs + 2], lengths[data[ofs + 2]]
        if ofs + length > n:
            break
        if t == 0x80:
            typ, declared = data[ofs + 3], data[ofs + 4]
            name = data[ofs + 5:ofs + 9].split(b"\0")[0].decode("ascii", "replace")
            fmt = data[ofs + 9:ofs + 25].split(b"\0")[0].decode("ascii", "replace")
            bad = sorted(set(c for c in fmt if c not in FORMAT_TO_STRUCT))
            need = 3 + sum(struct.calcsize(FORMAT_TO_STRUCT[c][0]) for c in fmt if c in FORMAT_TO_STRUCT)
            if bad or declared != need or (typ == 0x80 and declared != 89):
                raise InputError(f"dataflash log {where}: the FMT record at byte {ofs} defines type {typ} "
                                 f"({name!r}) with length {declared}, but its format {fmt!r} "
                                 + (f"has unknown letters {bad}" if bad else f"needs {need}")
                                 + " (a corrupt log)")
            lengths[typ] = declared
            count += 1
        ofs += length
    return count


class _Sink:
    """Where DFReader's prints go (it reports every skipped byte of a damaged log on stdout or stderr)."""

    def __init__(self):
        self.lines = 0

    def write(self, s):
        self.lines += s.count("\n")
        return len(s)

    def flush(self):
        pass


class DataflashReader:
    """Stream a dataflash log as ``(stamp_us, MAVLink-shaped message)`` (see the module docstring).

    pymavlink's DFReader reads the whole file at open (it indexes every message); a file it cannot read is an
    ``InputError`` naming the file and the offset, never another exception."""

    def __init__(self, path):
        self.path = str(path)
        self.stats = DataflashStats()
        self._sink = _Sink()
        try:
            with open(self.path, "rb") as f, mmap.mmap(f.fileno(), 0, access=mmap.ACCESS_READ) as data:
                n_fmt = check_formats(data, self.path)
        except (OSError, ValueError) as e:        # (ValueError: an empty file cannot be mapped)
            raise InputError(f"dataflash log {self.path}: cannot read it ({e})") from None
        if n_fmt == 0:
            raise InputError(f"dataflash log {self.path}: no FMT record (expected a log starting with A3 95 80)")
        try:
            from pymavlink import DFReader
            with self._quiet():
                self._r = DFReader.DFReader_binary(self.path, zero_time_base=False)
        except Exception as e:  # noqa: BLE001  (DFReader raises anything on a malformed file: ValueError, struct..)
            raise InputError(f"dataflash log {self.path}: cannot read it ({type(e).__name__}: {e})") from None

    def _quiet(self):
        return _Quiet(self._sink)

    def close(self):
        try:
            self._r.close()
        except Exception:  # noqa: BLE001
            pass

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()

    def __iter__(self):
        st, r = self.stats, self._r
        have_origin = False
        while True:
            before = r.offset
            try:
                with self._quiet():
                    m = r.recv_msg()
            except Exception as e:  # noqa: BLE001
                raise InputError(f"dataflash log {self.path}: unreadable at byte {before} "
                                 f"({type(e).__name__}: {e})") from None
            if m is None:
                break
            if r.offset <= before:
                raise InputError(f"dataflash log {self.path}: no progress at byte {before} (a corrupt log)")
            st.records += 1
            st.resync_bytes += max(0, r.offset - before - m.fmt.len)
            t = m.get_type()
            if t == "ORGN":
                have_origin = True
                continue
            if t not in NAV_SOURCES:
                continue
            if t in ("XKF1", "XKQ") and getattr(m, "C", 0) != 0:
                st.other_core += 1
                continue
            try:
                out = convert(m, have_origin)
            except (AttributeError, TypeError, ValueError, OverflowError):   # a field missing, NaN or not a number
                st.bad_fields += 1
                continue
            if out is None:
                st.no_origin += t == "XKF1"
                continue
            st.nav += 1
            yield int(round(out._timestamp * 1e6)), out
        st.truncated_bytes = max(0, r.data_len - r.offset)
        st.reader_warnings = self._sink.lines
