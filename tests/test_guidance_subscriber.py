"""examples/guidance_subscriber.py as a real process on a real zenoh bus (loopback, no multicast): it prints the
nearest threat of the obstacle_tracks messages the test publishes, and stops cleanly on SIGINT."""
import math
import re
import signal
import threading
from pathlib import Path

import numpy as np
import pytest

zenoh = pytest.importorskip("zenoh")

from eonav.bus import guidance_msg as G  # noqa: E402
from eonav.obstacles import guidance as GP  # noqa: E402
from eonav.bus import keys as K  # noqa: E402
from eonav.obstacles import tracking as T  # noqa: E402
from eonav.bus.session import endpoint, listener_session  # noqa: E402
from eonav.app.processes import free_port, start_service, stop_service  # noqa: E402
from eonav.geometry.camera import VehicleState  # noqa: E402

EXAMPLE = Path(__file__).resolve().parents[1] / "examples" / "guidance_subscriber.py"
VEHICLE = "guidtest"


def _message(seq):
    """Two confirmed tracks ahead of a vehicle flying north at 20 m/s: a pole straight ahead at 60 m (the threat,
    contact in (60 - 0.5 - 1 - 2 sigma) / 20 s) and a box 30 m to the side (not in the cone)."""
    tr = T.Tracker(T.TrackerConfig(confirm_hits=1))
    cov = np.diag([0.01, 0.01, 0.01])
    tr.update([T.Measurement([60.0, 0.0, -10.0], cov, [1.0, 1.0, 10.0], 150, 0.9, "nose"),
               T.Measurement([40.0, 30.0, -10.0], cov, [2.0, 2.0, 2.0], 300, 0.8, "nose")], 1_000_000)
    own = T.Ownship.from_state(VehicleState.from_ypr([0.0, 0.0, -10.0], [0.0, 0.0, 0.0]), [20.0, 0.0, 0.0],
                               1_000_000)
    return GP.build(tr, own, 1_000_000, seq=seq, trigger="map", stale_after_s=0.5)


def test_example_prints_the_nearest_threat_of_published_messages():
    msg = _message(0)
    th = msg["nearest_threat"]
    assert th["id"] == 1
    want_ttc = (60.0 - 0.5 - 1.0 - 2.0 * math.sqrt(msg["tracks"][0]["position_cov_ned_m2"][0][0])) / 20.0
    assert th["time_to_contact_s"] == pytest.approx(want_ttc)
    port = free_port()
    with listener_session(port) as s:
        pub = s.declare_publisher(K.obstacle_tracks(VEHICLE))
        proc = start_service([str(EXAMPLE), "--connect", endpoint(port), "--vehicle", VEHICLE])
        lines = []
        got = threading.Event()

        def read():
            for line in proc.stdout:
                lines.append(line.rstrip("\n"))
                if "threat id" in line:
                    got.set()
        reader = threading.Thread(target=read, daemon=True)
        reader.start()
        try:
            seq = 0
            while not got.wait(0.1):              # publish until the subscriber is connected and prints
                assert proc.poll() is None, proc.stderr.read()
                assert seq < 200, f"no threat line after {seq} messages; stdout {lines}"
                pub.put(G.encode(_message(seq)))
                seq += 1
            pub.put(b"not a message")               # a bad payload is reported, the example keeps running
            pub.put(G.encode(_message(seq)))
            deadline = 50
            while sum("threat id" in x for x in lines) < 2 and deadline:
                got.clear()
                got.wait(0.1)
                deadline -= 1
        finally:
            code, err = stop_service(proc, signal.SIGINT)
        reader.join(2.0)
    assert code == 0, err
    assert lines[0] == f"listening on {K.obstacle_tracks(VEHICLE)}"
    threat_lines = [x for x in lines if "threat id" in x]
    assert len(threat_lines) >= 2
    m = re.search(r"\| 2 tracks \| threat id (\d+) in ([\d.]+) s at ([\d.]+) m \(surface ([\d.]+) m\) "
                  r"az ([+-][\d.]+) el ([+-][\d.]+) deg closing ([\d.]+) m/s", threat_lines[0])
    assert m, threat_lines[0]
    assert int(m.group(1)) == 1
    assert float(m.group(2)) == pytest.approx(want_ttc, abs=0.005)
    assert float(m.group(3)) == pytest.approx(60.0, abs=0.05)
    assert float(m.group(4)) == pytest.approx(59.5, abs=0.05)           # to the 1 m deep extent box
    assert float(m.group(5)) == pytest.approx(0.0, abs=0.05) and float(m.group(6)) == pytest.approx(0.0, abs=0.05)
    assert float(m.group(7)) == pytest.approx(20.0, abs=0.05)
    assert "bad message" in err and "not msgpack" in err
