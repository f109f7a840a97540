"""Make tests/data/arducopter_sitl_short.bin: a real ArduCopter dataflash log of a short flight, cut to the
navigation messages (run by hand, not by the tests: ``python tests/data/make_dataflash_bin.py``).

The real ArduCopter SITL (tests/sitl.py finds it) flies: wait for a 3-D GPS fix and the EKF, GUIDED, arm, take off
to 10 m, fly 20 m north and 10 m east, LAND until disarmed. Its dataflash log (logs/00000001.BIN) is then cut to
the messages the MAVLink ingest reads and the ones that describe them (FMT, FMTU, UNIT, MULT, ATT, POS, GPS,
XKF1 and XKQ of EKF core 0, ORGN, MSG, MODE, EV), each message kept byte for byte, so that the file stays small (< 200 kB) and
every other dataflash reader reads it as the autopilot wrote it."""
from __future__ import annotations

import shutil
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[2]))
from tests.sitl import ArduPilot, wait_for  # noqa: E402

KEEP = {"FMT", "FMTU", "UNIT", "MULT", "ATT", "POS", "GPS", "XKF1", "XKQ", "ORGN", "MSG", "MODE", "EV"}
CORE0_ONLY = {"XKF1", "XKQ"}           # EKF messages: of the first core only (field C, the byte after TimeUS)
OUT = Path(__file__).with_name("arducopter_sitl_short.bin")


def cut(data: bytes, keep: set, core0_only: set = CORE0_ONLY) -> bytes:
    """The messages of a dataflash log whose type name is in ``keep`` (of ``core0_only`` those of EKF core 0), in
    order; FMT gives each type's length and format."""
    lengths, names, formats = {128: 89}, {128: "FMT"}, {128: "BB4s16s64s"}
    out, i = bytearray(), 0
    while i + 3 <= len(data):
        if data[i] != 0xA3 or data[i + 1] != 0x95:
            i += 1
            continue
        t = data[i + 2]
        if t not in lengths:
            i += 1
            continue
        n = lengths[t]
        msg = data[i:i + n]
        if len(msg) < n:
            break
        if t == 128:
            typ, length = msg[3], msg[4]
            lengths[typ], names[typ] = length, msg[5:9].rstrip(b"\0").decode("ascii", "replace")
            formats[typ] = msg[9:25].rstrip(b"\0").decode("ascii", "replace")
            if names[typ] in keep or typ == 128:
                out += msg
        elif names[t] in keep:
            if names[t] not in core0_only or (formats[t].startswith("QB") and msg[11] == 0):
                out += msg
        i += n
    return bytes(out)


def main():
    params = {"LOG_BITMASK": 6, "LOG_DISARMED": 0, "LOG_FILE_BUFSIZE": 16, "PRX1_TYPE": 0}   # ATTITUDE_MED + GPS; no proximity
    with ArduPilot(params=params) as ap:
        mu = ap.link.conn.mav
        ap.request_message_interval(24, 200_000)          # GPS_RAW_INT
        wait_for(lambda: (m := ap.link.get("GPS_RAW_INT")) is not None and m.fix_type >= 3, 60, "3-D GPS fix")
        deadline = time.monotonic() + 90
        while True:                                      # GUIDED and armed once the EKF is ready
            ap.link.conn.set_mode(4)
            ack = ap.command_long(400, 1)                # MAV_CMD_COMPONENT_ARM_DISARM
            if ack.result == 0:
                break
            if time.monotonic() > deadline:
                raise SystemExit(f"could not arm: {ack}\n" + "\n".join(t for _, _, t in ap.link.texts[-20:]))
            time.sleep(2)
        ap.command_long(22, 0, 0, 0, 0, 0, 0, 10)        # MAV_CMD_NAV_TAKEOFF to 10 m
        time.sleep(10)
        mu.set_position_target_local_ned_send(0, 1, 1, 1, 0b0000111111111000, 20, 10, -10, 0, 0, 0, 0, 0, 0, 0, 0)
        time.sleep(10)
        ap.link.conn.set_mode(9)                         # LAND
        wait_for(lambda: (h := ap.link.get("HEARTBEAT")) is not None and not (h.base_mode & 128), 40, "disarmed")
        time.sleep(1)
        logs = sorted((ap.workdir / "logs").glob("*.BIN"))
        data = logs[-1].read_bytes()
        shutil.copy(logs[-1], OUT.with_suffix(".full.BIN"))
    small = cut(data, KEEP)
    OUT.write_bytes(small)
    print(f"{logs[-1].name}: {len(data)} bytes -> {OUT} {len(small)} bytes")


if __name__ == "__main__":
    main()
