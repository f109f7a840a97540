"""Autopilots in the loop for the tests: a real ArduCopter SITL and a real PX4 SITL (SIH quadrotor) as processes.

The tools are looked up in ``$EONAV_SITL_DIR`` (a folder holding ``ardupilot-sitl/`` and ``px4-sitl/``), else in
``shared/tools`` next to the repository's folder. Each autopilot runs in a fresh temporary folder (it writes its
parameters, eeprom and logs there) on a free instance number, so several can run at once.

    with ArduPilot() as ap:                       # waits for its HEARTBEAT on the ground-station link (SERIAL0)
        sender = ObstacleDistanceSender(ap.companion_url)      # our messages go in on SERIAL1
        ap.request_message_interval(DISTANCE_SENSOR_ID, 50_000)
        ap.wait_for(lambda: ap.distance_sensors(max_age_s=0.3), what="...")

    with PX4(params={"CP_DIST": 3}) as px4:       # waits for "Ready for takeoff!", sets parameters with px4-param
        px4.listener("obstacle_distance_fused")   # what its collision prevention made of our messages

A reader thread drains each ground-station link and keeps what the tests look at (the latest message of each type,
DISTANCE_SENSOR per orientation, every STATUSTEXT, every console line of PX4), each with its receive time
(``time.monotonic()``). Only helpers here; the tests are in test_sitl_*.py.
"""
from __future__ import annotations

import os
import re
import shutil
import signal
import socket
import subprocess
import tempfile
import threading
import time
from pathlib import Path

os.environ.setdefault("MAVLINK20", "1")

ENV_DIR = "EONAV_SITL_DIR"
MAV_SYS_STATUS_SENSOR_PROXIMITY = 1 << 26
DISTANCE_SENSOR_ID = 132
SYS_STATUS_ID = 1
OBSTACLE_DISTANCE_ID = 330
GCS_SYSID = 255
GCS_COMPID = 190               # MAV_COMP_ID_MISSIONPLANNER


def tools_dir() -> Path:
    env = os.environ.get(ENV_DIR)
    if env:
        return Path(env).expanduser().resolve()
    return Path(__file__).resolve().parents[1].parent / "shared" / "tools"


def ardupilot_dir() -> Path:
    return tools_dir() / "ardupilot-sitl"


def px4_dir() -> Path:
    return tools_dir() / "px4-sitl"


def missing(tool: Path, exe: str) -> str | None:
    """Why a tool cannot run (None when it can): the skip reason of the tests that need it."""
    if not (tool / exe).is_file():
        return f"{tool / exe} not found (set {ENV_DIR} to the folder holding ardupilot-sitl/ and px4-sitl/)"
    if not os.access(tool / exe, os.X_OK):
        return f"{tool / exe} is not executable"
    return None


def _free(port: int, kind=socket.SOCK_STREAM) -> bool:
    with socket.socket(socket.AF_INET, kind) as s:
        try:
            s.bind(("127.0.0.1", port))
        except OSError:
            return False
    return True


def _mavutil():
    from eonav.nav.mavlink_out import mavutil
    return mavutil()


class _Link:
    """A pymavlink ground-station connection drained by a thread: latest message per type, DISTANCE_SENSOR per
    orientation, every STATUSTEXT, each stamped with its receive time."""

    def __init__(self, conn, name: str):
        self.conn, self.name = conn, name
        self.lock = threading.Lock()
        self.latest: dict = {}                 # type -> (t, msg)
        self.distance: dict = {}               # orientation -> (t, msg)
        self.texts: list = []                  # (t, severity, text)
        self.history: dict = {}                # type -> [(t, msg)] for the types in ``keep``
        self.keep: set = set()
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, name=f"{name}-reader", daemon=True)
        self._thread.start()

    def _run(self):
        while not self._stop.is_set():
            try:
                m = self.conn.recv_match(blocking=True, timeout=0.1)
            except (OSError, ValueError):       # the link went away while we were shutting down
                if self._stop.wait(0.1):
                    return
                continue
            if m is None:
                continue
            t = time.monotonic()
            typ = m.get_type()
            if typ == "BAD_DATA":
                continue
            with self.lock:
                self.latest[typ] = (t, m)
                if typ == "DISTANCE_SENSOR":
                    self.distance[m.orientation] = (t, m)
                elif typ == "STATUSTEXT":
                    self.texts.append((t, m.severity, m.text))
                if typ in self.keep:
                    self.history.setdefault(typ, []).append((t, m))

    def get(self, typ: str):
        with self.lock:
            v = self.latest.get(typ)
        return None if v is None else v[1]

    def since(self, typ: str, t0: float) -> list:
        with self.lock:
            return [(t, m) for t, m in self.history.get(typ, []) if t >= t0]

    def texts_since(self, t0: float) -> list:
        with self.lock:
            return [(t, txt) for t, _, txt in self.texts if t >= t0]

    def close(self):
        self._stop.set()
        self._thread.join(timeout=2)
        try:
            self.conn.close()
        except Exception:  # noqa: BLE001  (closing a half-dead socket must not hide the test's result)
            pass


def wait_for(cond, timeout: float, what: str, period: float = 0.02):
    """Poll ``cond()`` until truthy (returned) or raise AssertionError naming ``what``."""
    deadline = time.monotonic() + timeout
    while True:
        v = cond()
        if v is not None and v is not False and (not hasattr(v, "__len__") or len(v)):
            return v
        if time.monotonic() > deadline:
            raise AssertionError(f"timed out after {timeout:.1f} s waiting for {what}")
        time.sleep(period)


class ArduPilot:
    """ArduCopter SITL (``+`` frame, real time) with ``copter.parm`` + ``proximity-mavlink.parm`` (PRX1_TYPE 2) and
    ``params`` on top. Ground-station link: TCP SERIAL0 (this object's reader); companion link for our
    OBSTACLE_DISTANCE: ``companion_url`` (TCP SERIAL1)."""

    def __init__(self, params: dict | None = None, tool: Path | None = None, ready_timeout_s: float = 30.0):
        self.tool = tool or ardupilot_dir()
        why = missing(self.tool, "arducopter")
        if why:
            raise FileNotFoundError(why)
        self.params = {"PRX1_YAW_CORR": 0, "PRX1_ORIENT": 0, **(params or {})}
        self.ready_timeout_s = ready_timeout_s
        self.proc = None
        self.link = None
        self.workdir = None

    def _instance(self, first: int = 1) -> int:
        for i in range(first, 40):
            base = 5760 + 10 * i
            if all(_free(p) for p in (base, base + 2, base + 3)) and _free(5501 + 10 * i, socket.SOCK_DGRAM):
                return i
        raise RuntimeError("no free ArduPilot SITL instance (ports 5770..6153 busy)")

    def __enter__(self):
        self.workdir = Path(tempfile.mkdtemp(prefix="eonav-ardupilot-"))
        extra = self.workdir / "eonav-test.parm"
        extra.write_text("".join(f"{k} {v}\n" for k, v in self.params.items()))
        defaults = ",".join(str(p) for p in (self.tool / "copter.parm", self.tool / "proximity-mavlink.parm", extra))
        self.instance = 0
        for attempt in range(3):
            # a port seen free can be taken before arducopter binds it (seen in full parallel runs: "bind failed on
            # port 5770", and once an exit whose console was lost), and a start-up can reset our first connection and
            # send no HEARTBEAT on the reconnected one (seen in a fresh-clone CI run, twice in one module): after any
            # failed start-up the next free instance, at most three times; the last attempt's console goes into the
            # error
            self.instance = self._instance(self.instance + 1)
            self.proc = subprocess.Popen([str(self.tool / "arducopter"), "--model", "+", "--speedup", "1",
                                          f"-I{self.instance}", "--defaults", defaults],
                                         cwd=self.workdir, stdout=open(self.workdir / "console.txt", "wb"),
                                         stderr=subprocess.STDOUT, stdin=subprocess.DEVNULL, start_new_session=True)
            try:
                self._connect()
                return self
            except Exception:
                self._stop_process()
                if self.link is not None:
                    self.link.close()
                    self.link = None
                if attempt == 2:
                    self.__exit__(None, None, None)
                    raise
            except BaseException:           # KeyboardInterrupt and the like: no retry
                self._stop_process()
                self.__exit__(None, None, None)
                raise

    @property
    def gcs_port(self) -> int:
        return 5760 + 10 * self.instance

    @property
    def companion_url(self) -> str:
        return f"tcp:127.0.0.1:{5762 + 10 * self.instance}"

    def _connect(self):
        mu = _mavutil()
        deadline = time.monotonic() + self.ready_timeout_s
        conn = None
        while conn is None:
            if self.proc.poll() is not None:
                raise RuntimeError(f"arducopter exited with {self.proc.returncode}: {self.console()[-2000:]}")
            try:
                # autoreconnect: arducopter can accept the first connection and reset it while it starts up (seen
                # once in a full run: "Connection reset or closed by peer", then no HEARTBEAT on the dead socket)
                conn = mu.mavlink_connection(f"tcp:127.0.0.1:{self.gcs_port}", source_system=GCS_SYSID,
                                             source_component=GCS_COMPID, retries=0, autoreconnect=True)
            except OSError:
                if time.monotonic() > deadline:
                    raise
                time.sleep(0.1)
        self.link = _Link(conn, "ardupilot")
        wait_for(lambda: self.link.get("HEARTBEAT"), deadline - time.monotonic(), "ArduPilot HEARTBEAT")
        self.request_message_interval(SYS_STATUS_ID, 100_000)

    def console(self) -> str:
        try:
            return (self.workdir / "console.txt").read_text(errors="replace")
        except OSError:
            return ""

    def command_long(self, command: int, *params, timeout: float = 5.0):
        """Send COMMAND_LONG and return its COMMAND_ACK (AssertionError if none comes)."""
        p = list(params) + [0.0] * (7 - len(params))
        t0 = time.monotonic()
        self.link.keep.add("COMMAND_ACK")
        self.link.conn.mav.command_long_send(1, 1, command, 0, *p)
        return wait_for(lambda: next((m for _, m in self.link.since("COMMAND_ACK", t0) if m.command == command),
                                     None), timeout, f"COMMAND_ACK of command {command}")

    def request_message_interval(self, msg_id: int, interval_us: int):
        ack = self.command_long(511, msg_id, interval_us)          # MAV_CMD_SET_MESSAGE_INTERVAL
        if ack.result != 0:
            raise AssertionError(f"ArduPilot refused SET_MESSAGE_INTERVAL {msg_id}: result {ack.result}")

    def proximity_bits(self) -> tuple | None:
        """(present, enabled, healthy) of MAV_SYS_STATUS_SENSOR_PROXIMITY in the latest SYS_STATUS."""
        s = self.link.get("SYS_STATUS")
        if s is None:
            return None
        P = MAV_SYS_STATUS_SENSOR_PROXIMITY
        return (bool(s.onboard_control_sensors_present & P), bool(s.onboard_control_sensors_enabled & P),
                bool(s.onboard_control_sensors_health & P))

    def distance_sensors(self, max_age_s: float = 0.3) -> dict:
        """Orientation (0 = ahead .. 7 = ahead-left, 45-degree sectors) -> current_distance cm of the sectors holding
        an obstacle, from the DISTANCE_SENSOR messages received in the last ``max_age_s``. ArduPilot goes on sending
        a sector that once held an obstacle with current_distance = max_distance once it is empty: not counted."""
        now = time.monotonic()
        with self.link.lock:
            return {o: m.current_distance for o, (t, m) in self.link.distance.items()
                    if now - t <= max_age_s and m.current_distance < m.max_distance}

    def proximity_faces(self, max_distance_m: float, window_s: float = 0.3) -> dict:
        """(layer, sector) -> raw distance (m) of the faces of ArduPilot's 3D proximity boundary that hold an
        obstacle, from the newest ``PRXR`` records of its dataflash log (needs ``LOG_DISARMED 1`` and
        ``PRX_LOG_RAW 1``): per layer the latest record within ``window_s`` of the log's end (a layer with no
        obstacle is not logged). Layers 0..4 are elevations -75..-45, -45..-15, -15..15, 15..45, 45..75 deg;
        sectors 0..7 are 45-degree bearings centred on 45 k deg. Empty faces are logged at the sensor's max
        (``max_distance_m``)."""
        from pymavlink import DFReader
        logs = sorted((self.workdir / "logs").glob("*.BIN")) if self.workdir else []
        if not logs:
            return {}
        recs, t_end = [], None
        r = DFReader.DFReader_binary(str(logs[-1]))
        while True:                       # ATT (10 Hz, always logged) is the log's clock: PRXR stops when all is empty
            try:
                m = r.recv_match(type=["PRXR", "ATT"])
            except Exception:  # noqa: BLE001  (the log's last record may be half-written)
                break
            if m is None:
                break
            t_end = m.TimeUS
            if m.get_type() == "PRXR":
                recs.append(m)
        if not recs:
            return {}
        latest = {}
        for m in recs:
            if m.TimeUS >= t_end - window_s * 1e6:
                latest[m.Layer] = m
        names = ("D0", "D45", "D90", "D135", "D180", "D225", "D270", "D315")
        out = {}
        for layer, m in latest.items():
            for sector, n in enumerate(names):
                v = getattr(m, n)
                if v < max_distance_m - 1e-3:
                    out[(layer, sector)] = v
        return out

    def __exit__(self, *exc):
        if self.link is not None:
            self.link.close()
            self.link = None
        self._stop_process()
        if self.workdir is not None:
            shutil.rmtree(self.workdir, ignore_errors=True)
            self.workdir = None
        return False

    def _stop_process(self):
        if self.proc is not None:
            if self.proc.poll() is None:
                self.proc.terminate()
                try:
                    self.proc.wait(timeout=10)
                except subprocess.TimeoutExpired:
                    self.proc.kill()
                    self.proc.wait()
            self.proc = None


# PX4 custom modes (px4_custom_mode.h): main mode in bits 16..23, sub mode in bits 24..31
PX4_MAIN_POSCTL = 3
PX4_MAIN_AUTO = 4
PX4_SUB_AUTO_TAKEOFF = 2
PX4_SUB_AUTO_LOITER = 3


class PX4:
    """PX4 SITL (SIH quadrotor, real time) started with ``run-px4-sitl.sh`` in a fresh folder. ``params`` are set
    with ``bin/px4-param`` once it is ready. The ground-station link is ours over UDP (we send to PX4's port
    18570 + instance, it answers to where we send from); ``companion_url`` is its onboard link (14580 + instance),
    where our OBSTACLE_DISTANCE goes. ``console`` holds PX4's console lines (e.g. "No obstacle data, not moving")."""

    def __init__(self, params: dict | None = None, tool: Path | None = None, ready_timeout_s: float = 40.0):
        self.tool = tool or px4_dir()
        why = missing(self.tool, "run-px4-sitl.sh") or missing(self.tool, "px4")
        if why:
            raise FileNotFoundError(why)
        self.params = dict(params or {})
        self.ready_timeout_s = ready_timeout_s
        self.proc = None
        self.link = None
        self.workdir = None
        self.console_lines: list = []          # (t, line)
        self._lock = threading.Lock()
        self._stop = threading.Event()
        self._threads: list = []
        self.manual = None                     # (x, y, z, r) MANUAL_CONTROL sent at 25 Hz while set

    def _instance(self, first: int = 1) -> int:
        for i in range(first, 10):
            ports = (18570 + i, 14580 + i, 14280 + i, 13030 + i, 19450 + i)
            if all(_free(p, socket.SOCK_DGRAM) for p in ports):
                return i
        raise RuntimeError("no free PX4 SITL instance 1..9 (its UDP ports are taken)")

    @property
    def sysid(self) -> int:
        return self.instance + 1                  # rcS: MAV_SYS_ID = instance + 1

    @property
    def companion_url(self) -> str:
        return f"udpout:127.0.0.1:{14580 + self.instance}"

    def __enter__(self):
        self.instance = 0
        for attempt in range(2):
            # PX4 does not always come up under a loaded machine (seen in a full parallel run: two starts in a row
            # silent for 40 s): once more on the next free instance, with the first console's tail in the error
            self._start(self._instance(self.instance + 1))
            try:
                wait_for(lambda: self.console_since(0, "Ready for takeoff"), self.ready_timeout_s,
                         "PX4 'Ready for takeoff!'")
                break
            except AssertionError as e:
                tail = [ln for _, ln in self.console_lines[-15:]]
                self.__exit__(None, None, None)
                if attempt == 1:
                    raise AssertionError(f"{e}; console: {tail}") from None
        try:
            for k, v in self.params.items():
                self.param_set(k, v)
            mu = _mavutil()
            conn = mu.mavlink_connection(f"udpout:127.0.0.1:{18570 + self.instance}", source_system=GCS_SYSID,
                                         source_component=GCS_COMPID)
            self.link = _Link(conn, "px4")
            self._spawn(self._gcs_loop)
            wait_for(lambda: self.link.get("HEARTBEAT"), 10, "PX4 HEARTBEAT on the ground-station link")
        except BaseException:
            self.__exit__(None, None, None)
            raise
        return self

    def _start(self, instance: int) -> None:
        """run-px4-sitl.sh as ``instance`` in a fresh folder, its console read into ``console_lines``."""
        self.workdir = Path(tempfile.mkdtemp(prefix="eonav-px4-")) / "w"
        self.instance = instance
        self.console_lines, self._stop, self._threads = [], threading.Event(), []
        self.proc = subprocess.Popen(["bash", str(self.tool / "run-px4-sitl.sh"), str(self.workdir),
                                      str(self.instance)], stdout=subprocess.PIPE, stderr=subprocess.STDOUT,
                                     stdin=subprocess.DEVNULL, start_new_session=True)
        self._spawn(self._read_console)

    def _spawn(self, fn):
        t = threading.Thread(target=fn, daemon=True)
        t.start()
        self._threads.append(t)

    def _read_console(self):
        ansi = re.compile(r"\x1b\[[0-9;]*m")
        for raw in iter(self.proc.stdout.readline, b""):
            line = ansi.sub("", raw.decode(errors="replace")).rstrip()
            with self._lock:
                self.console_lines.append((time.monotonic(), line))

    def _gcs_loop(self):
        """GCS HEARTBEAT at 1 Hz (PX4 answers to our address and counts the GCS as present) and MANUAL_CONTROL at
        25 Hz while ``self.manual`` is set."""
        mu = _mavutil()
        next_hb = 0.0
        while not self._stop.wait(0.04):
            conn = self.link.conn if self.link else None
            if conn is None:
                continue
            try:
                if time.monotonic() >= next_hb:
                    conn.mav.heartbeat_send(mu.mavlink.MAV_TYPE_GCS, mu.mavlink.MAV_AUTOPILOT_INVALID, 0, 0, 0)
                    next_hb = time.monotonic() + 1.0
                if self.manual is not None:
                    x, y, z, r = self.manual
                    conn.mav.manual_control_send(self.sysid, int(x), int(y), int(z), int(r), 0)
            except OSError:
                pass

    def console_since(self, t0: float, pattern: str) -> list:
        with self._lock:
            return [(t, ln) for t, ln in self.console_lines if t >= t0 and pattern in ln]

    def shell(self, *args: str, timeout: float = 10.0) -> str:
        """A PX4 shell command through its client (``bin/px4-<cmd> --instance N args``); returns its output."""
        cmd, *rest = args
        r = subprocess.run([str(self.workdir / "bin" / f"px4-{cmd}"), "--instance", str(self.instance), *rest],
                           cwd=self.workdir, capture_output=True, text=True, timeout=timeout)
        return r.stdout + r.stderr

    def param_set(self, name: str, value) -> None:
        out = self.shell("param", "set", name, str(value))
        got = self.shell("param", "show", name)
        m = re.search(rf"\b{re.escape(name)}\b.*:\s*(-?[0-9.]+)", got)
        if m is None or abs(float(m.group(1)) - float(value)) > 1e-6:
            raise AssertionError(f"PX4 param set {name} {value} did not take: {out.strip()} / {got.strip()}")

    def listener(self, topic: str) -> dict | None:
        """One message of a uORB topic (``px4-listener TOPIC -n 1``) as a dict of numbers / lists (None if the topic
        was never published)."""
        return parse_listener(self.shell("listener", topic, "-n", "1"))

    def command_long(self, command: int, *params, timeout: float = 5.0):
        p = list(params) + [0.0] * (7 - len(params))
        t0 = time.monotonic()
        self.link.keep.add("COMMAND_ACK")
        self.link.conn.mav.command_long_send(self.sysid, 1, command, 0, *p)
        return wait_for(lambda: next((m for _, m in self.link.since("COMMAND_ACK", t0) if m.command == command),
                                     None), timeout, f"PX4 COMMAND_ACK of command {command}")

    def set_mode(self, main: int, sub: int = 0):
        ack = self.command_long(176, 1, main, sub)                   # MAV_CMD_DO_SET_MODE, custom mode enabled
        if ack.result != 0:
            raise AssertionError(f"PX4 refused mode {main}/{sub}: result {ack.result}")

    def mode(self) -> tuple | None:
        hb = self.link.get("HEARTBEAT")
        if hb is None:
            return None
        return (hb.custom_mode >> 16) & 0xFF, (hb.custom_mode >> 24) & 0xFF

    def arm(self):
        ack = self.command_long(400, 1)                              # MAV_CMD_COMPONENT_ARM_DISARM
        if ack.result != 0:
            raise AssertionError(f"PX4 refused to arm: result {ack.result}; console: "
                                 f"{[ln for _, ln in self.console_lines[-10:]]}")

    def __exit__(self, *exc):
        self.manual = None
        if self.proc is not None and self.proc.poll() is None and self.workdir is not None:
            try:
                self.shell("shutdown", timeout=5)
                self.proc.wait(timeout=10)
            except (subprocess.TimeoutExpired, OSError):
                pass
        self._stop.set()
        if self.link is not None:
            self.link.close()
            self.link = None
        if self.proc is not None:
            if self.proc.poll() is None:
                os.killpg(self.proc.pid, signal.SIGTERM)
                try:
                    self.proc.wait(timeout=10)
                except subprocess.TimeoutExpired:
                    os.killpg(self.proc.pid, signal.SIGKILL)
                    self.proc.wait()
            self.proc = None
        for t in self._threads:
            t.join(timeout=2)
        if self.workdir is not None:
            shutil.rmtree(self.workdir.parent, ignore_errors=True)
            self.workdir = None
        return False


_LIST = re.compile(r"^\s*(\w+):\s*\[(.*)\]\s*$")
_SCALAR = re.compile(r"^\s*(\w+):\s*(-?[0-9.eE+-]+|nan|inf|-inf|True|False)\b")


def parse_listener(text: str) -> dict | None:
    """``px4-listener`` output -> {field: number | bool | list}; None when it says the topic was never published."""
    if "never published" in text:
        return None
    out = {}
    for line in text.splitlines():
        m = _LIST.match(line)
        if m:
            out[m.group(1)] = [float(x) for x in m.group(2).replace(",", " ").split()]
            continue
        m = _SCALAR.match(line)
        if m:
            v = m.group(2)
            out[m.group(1)] = v == "True" if v in ("True", "False") else float(v)
    return out or None


# ---- synthetic range maps of known scenes (the renderer's ground-truth range: an exact, independent truth) -------

def make_camera(yaw_deg: float = 0.0, width: int = 320, height: int = 240, hfov_deg: float = 100.0):
    """A level pinhole camera at the body origin, yawed ``yaw_deg`` on the body (positive right)."""
    import math

    import numpy as np

    from eonav.geometry.camera import Camera
    f = (width / 2) / math.tan(math.radians(hfov_deg) / 2)
    return Camera(f"cam{yaw_deg:+.0f}".replace("+", "p").replace("-", "m"), width, height, f, f,
                  (width - 1) / 2, (height - 1) / 2, eps_rad=np.array([math.radians(yaw_deg), 0.0, 0.0]))


def pole(name: str, bearing_deg: float, distance_m: float, width_m: float = 0.1, height_m: float = 20.0,
         origin_ne=(0.0, 0.0), yaw0_deg: float = 0.0):
    """A square pole standing on the ground whose near face is ``distance_m`` (horizontal) from ``origin_ne`` at
    ``bearing_deg`` relative to the heading ``yaw0_deg``, turned to face it: the nearest point is the face's centre."""
    import math

    from eonav.sim.scene import Box
    a = math.radians(yaw0_deg + bearing_deg)
    c = distance_m + width_m / 2
    return Box.on_ground(name, origin_ne[0] + c * math.cos(a), origin_ne[1] + c * math.sin(a), width_m, width_m,
                         height_m, yaw_deg=yaw0_deg + bearing_deg)


def range_map_of(scene, camera, state):
    """(range_m, flags, confidence, inv_range_std_per_m) of ``camera`` at ``state``: exact ranges, VALID where
    finite, AT_INFINITY on the sky, confidence 1, a 0.01 %/m inverse-range sigma."""
    import numpy as np

    from eonav.ranging.rangemap import AT_INFINITY, VALID
    from eonav.sim.render import render
    r = render(scene, camera, state, supersample=1, noise_sigma=0.0, quantize=False).range_m
    flags = np.where(np.isfinite(r), VALID, AT_INFINITY).astype(np.uint8)
    return r, flags, np.ones(r.shape, np.float16), np.full(r.shape, 1e-4, np.float16)


def range_map_payload(scene, camera, state, seq: int, stamp_us: int) -> bytes:
    """A ``range_map`` message (schema encoded) of the scene, as the locator publishes it."""
    from eonav.bus import schema
    from eonav.geometry.frames import quat_wxyz_from_rotation
    r, flags, conf, sig = range_map_of(scene, camera, state)
    return schema.encode("range_map", camera_id=camera.name, seq=seq, stamp_us=stamp_us, method="truth",
                         range_m=r, confidence=conf, flags=flags, inv_range_std_per_m=sig,
                         camera=schema.camera_to_msg(camera), position_ned_m=state.position_ned_m,
                         q_wxyz=quat_wxyz_from_rotation(state.T_body_ned.T))


def ardupilot_sector(bearing_deg: float) -> int:
    """ArduPilot's 45-degree proximity sector of a body bearing (0 = ahead, centred on 45 k)."""
    import math
    return int(math.floor(((bearing_deg + 22.5) % 360.0) / 45.0))


class MapFeeder:
    """Publishes range maps of ``scene`` seen by ``camera`` from ``state`` at ``rate_hz`` on a zenoh publisher, each
    stamped with the time it is put (UNIX µs), from a thread. ``set(scene, camera, state)`` switches the scene (the
    map is rendered once per scene); ``paused`` stalls the pipeline; ``last_put`` is the monotonic time of the last
    map put."""

    def __init__(self, session, key: str, rate_hz: float = 10.0):
        self.pub = session.declare_publisher(key)
        self.rate_hz = rate_hz
        self.paused = True
        self.last_put = None
        self.count = 0
        self._what = None
        self._live = None
        self._lock = threading.Lock()
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, daemon=True, name="map-feeder")
        self._thread.start()

    def set(self, scene, camera, state):
        maps = range_map_of(scene, camera, state)
        with self._lock:
            self._what = (camera, state, maps)
            self._live = None

    def set_live(self, source):
        """Render a fresh map at every tick from ``source()`` -> (scene, camera, state) (None: skip the tick)."""
        with self._lock:
            self._live = source

    def _run(self):
        from eonav.bus import schema
        from eonav.geometry.frames import quat_wxyz_from_rotation
        while not self._stop.wait(1.0 / self.rate_hz):
            with self._lock:                      # held while putting: pause() returns after the last put
                if self._live is not None and not self.paused:
                    what = self._live()
                    if what is not None:
                        scene, camera, state = what
                        self._what = (camera, state, range_map_of(scene, camera, state))
                if self._what is None or self.paused:
                    continue
                camera, state, (r, flags, conf, sig) = self._what
                self.count += 1
                self.pub.put(schema.encode(
                    "range_map", camera_id=camera.name, seq=self.count, stamp_us=time.time_ns() // 1000,
                    method="truth", range_m=r, confidence=conf, flags=flags, inv_range_std_per_m=sig,
                    camera=schema.camera_to_msg(camera), position_ned_m=state.position_ned_m,
                    q_wxyz=quat_wxyz_from_rotation(state.T_body_ned.T)))
                self.last_put = time.monotonic()

    def pause(self) -> float | None:
        """Stop publishing; returns the monotonic time of the last map put."""
        with self._lock:
            self.paused = True
            return self.last_put

    def resume(self):
        with self._lock:
            self.paused = False

    def close(self):
        self._stop.set()
        self._thread.join(timeout=2)
        self.pub.undeclare()
