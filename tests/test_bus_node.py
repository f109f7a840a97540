"""The node skeleton (eonav.bus.node) in real processes over a real zenoh bus on loopback:
liveliness token, health messages, config queryable, SIGINT/SIGTERM, worker failure, bad payloads."""
from __future__ import annotations

import argparse
import json
import signal
import textwrap
import time

import pytest

zenoh = pytest.importorskip("zenoh")

from eonav.bus import keys as K  # noqa: E402
from eonav.bus import schema  # noqa: E402
from eonav.bus import session as S  # noqa: E402
from eonav.bus.node import LatencyWindow, Node, RateMeter  # noqa: E402
from eonav.bus.session import endpoint, listener_session  # noqa: E402
from eonav.app.processes import drain, free_port, start_service, stop_service, wait_until  # noqa: E402

VEHICLE = "testv"

# A tiny service: counts bad payloads on nav/state (fifo), ticks a loop; --crash makes its worker raise,
# --config-error makes body raise an InputError.
TINY = textwrap.dedent('''
    import time
    from eonav import InputError
    from eonav.bus import keys
    from eonav.bus.node import service_main, add_flag

    def add_arguments(p):
        add_flag(p, "--crash-after", env="TINY_CRASH_AFTER", type=float, default=-1.0)
        add_flag(p, "--config-error", env="TINY_CONFIG_ERROR", action="store_true")

    def body(node, args):
        if args.config_error:
            raise InputError("--config-error given")
        sub = node.subscribe(keys.nav_state(node.vehicle), fifo=16)
        def consume():
            for sample in sub:
                node.decode(sample, expect="nav_state")
        def loop():
            t0 = time.monotonic()
            while not node.stop_event.wait(0.05):
                node.tick("loop")
                node.latency("loop", 0.001)
                if 0 <= args.crash_after < time.monotonic() - t0:
                    raise RuntimeError("tiny crashed on purpose")
        node.worker(consume, name="consume")
        node.worker(loop, name="loop")

    if __name__ == "__main__":
        service_main("tiny", add_arguments, body)
''')


@pytest.fixture
def tiny(tmp_path):
    p = tmp_path / "tiny.py"
    p.write_text(TINY)
    return p


class Bus:
    """The test's side of the bus: a listening peer with health + liveliness subscribers."""

    def __init__(self, port):
        self.port = port
        self.session = listener_session(port)
        self.health_sub = self.session.declare_subscriber(K.health_all(VEHICLE), zenoh.handlers.FifoChannel(1000))
        self.alive_sub = self.session.liveliness().declare_subscriber(
            K.alive_all(VEHICLE), zenoh.handlers.FifoChannel(100), history=True)
        self.health, self.alive_events = [], []

    def poll(self):
        for s in drain(self.health_sub):
            self.health.append(schema.decode(s.payload.to_bytes(), expect="health"))
        for s in drain(self.alive_sub):
            self.alive_events.append((str(s.key_expr), s.kind))
        return self

    def alive(self, name):
        state = None
        for key, kind in self.alive_events:
            if key == K.alive(VEHICLE, name):
                state = kind == zenoh.SampleKind.PUT
        return state

    def close(self):
        self.health_sub.undeclare()
        self.alive_sub.undeclare()
        self.session.close()


@pytest.fixture
def bus():
    b = Bus(free_port())
    yield b
    b.close()


def _start(script, bus, *extra, name="tiny"):
    return start_service([str(script), "--vehicle", VEHICLE, "--name", name, "--connect", endpoint(bus.port),
                          "--health-period-s", "0.2", *extra])


@pytest.mark.parametrize("sig", [signal.SIGINT, signal.SIGTERM], ids=["SIGINT", "SIGTERM"])
def test_token_health_config_and_clean_stop(tiny, bus, sig):
    proc = _start(tiny, bus)
    try:
        wait_until(lambda: bus.poll().alive("tiny"), 20, what="liveliness token PUT")
        wait_until(lambda: len(bus.poll().health) >= 3, 10, what="3 health messages")
        h = bus.health[-1]
        assert h["service"] == "tiny" and h["state"] == "ok" and h["pid"] == proc.pid
        assert h["rates_hz"]["loop"] > 5
        assert h["latency_ms"]["loop"]["p50"] == pytest.approx(1.0)
        # config queryable returns the effective flags as JSON
        replies = list(bus.session.get(K.config(VEHICLE, "tiny"), timeout=5.0))
        cfg = json.loads(next(r.ok for r in replies if r.ok is not None).payload.to_string())
        assert cfg["service"] == "tiny" and cfg["vehicle"] == VEHICLE
        assert cfg["args"]["connect"] == endpoint(bus.port) and cfg["args"]["health_period_s"] == 0.2
    finally:
        code, err = stop_service(proc, sig)
    assert code == 0, err
    assert f"stopped ({sig.name}), exit 0" in err
    wait_until(lambda: bus.poll().alive("tiny") is False, 10, what="liveliness token DELETE")


def test_malformed_payloads_are_counted_not_fatal(tiny, bus):
    proc = _start(tiny, bus)
    try:
        wait_until(lambda: bus.poll().alive("tiny"), 20, what="liveliness token")
        pub = bus.session.declare_publisher(K.nav_state(VEHICLE), congestion_control=zenoh.CongestionControl.BLOCK)
        wait_until(lambda: pub.matching_status.matching, 10, what="subscriber match")
        time.sleep(0.2)
        good = schema.encode("nav_state", stamp_us=1, position_ned_m=[0, 0, 0])
        import msgpack
        doc = msgpack.unpackb(good)
        doc["v"] = 99
        pub.put(b"\xc1 not msgpack")                      # garbage
        pub.put(msgpack.packb(doc, use_bin_type=True))     # unknown schema version
        pub.put(schema.encode("health", service="x", stamp_us=1, state="ok"))  # wrong kind
        pub.put(good)

        def counters():
            bus.poll()
            c = bus.health[-1]["counters"] if bus.health else {}
            return c if c.get("in.nav_state") == 1 and c.get("decode_errors") == 3 else None
        c = wait_until(counters, 10, what="decode counters in health")
        assert c["unknown_version"] == 1
        assert proc.poll() is None and bus.health[-1]["state"] == "ok"
        pub.undeclare()
    finally:
        code, err = stop_service(proc)
    assert code == 0, err
    assert "dropped payload" in err


def test_worker_exception_sets_error_and_exits_nonzero(tiny, bus):
    proc = _start(tiny, bus, "--crash-after", "0.5")
    code = proc.wait(20)
    err = proc.stderr.read()
    assert code == 1, err
    assert "tiny crashed on purpose" in err
    bus.poll()
    assert bus.health and bus.health[-1]["state"] == "error"
    assert "RuntimeError" in bus.health[-1]["detail"]


def test_configuration_error_exits_2(tiny, bus):
    proc = _start(tiny, bus, "--config-error")
    assert proc.wait(20) == 2
    assert "--config-error given" in proc.stderr.read()


def test_bad_flags_exit_2(tiny):
    proc = start_service([str(tiny), "--vehicle", "has/slash"])
    assert proc.wait(20) == 2
    assert "vehicle" in proc.stderr.read()


# ---- pure parts --------------------------------------------------------------------------------------

class FakeClock:
    def __init__(self):
        self.t = 100.0

    def __call__(self):
        return self.t


def test_rate_meter_sliding_window():
    clk = FakeClock()
    m = RateMeter(window_s=5.0, clock=clk)
    assert m.rate_hz() == 0.0
    for _ in range(50):  # 10 Hz for 5 s
        m.tick()
        clk.t += 0.1
    assert m.rate_hz() == pytest.approx(10.0, rel=0.05)
    clk.t += 10.0
    assert m.rate_hz() == 0.0


def test_latency_window_percentiles():
    clk = FakeClock()
    w = LatencyWindow(window_s=10.0, clock=clk)
    assert w.summary_ms() == {"n": 0}
    for i in range(1, 101):
        w.add(i / 1000.0)
    s = w.summary_ms()
    assert s["n"] == 100 and s["p50"] == pytest.approx(50.0, abs=1.0) and s["p99"] == pytest.approx(99.0, abs=1.0)
    assert s["max"] == 100.0
    clk.t += 11
    assert w.summary_ms() == {"n": 0}


def test_rate_meter_after_its_window_and_before_it_fills():
    """The rate is the ticks of the last 5 s over 5 s once the meter is older than its window (a service up for a
    minute at 10 Hz reads 10 Hz, not its last 50 ticks over 60 s), and over the time since the first tick before
    that (10 Hz for 2 s reads 10 Hz, not 20 ticks over 5 s)."""
    clk = FakeClock()
    m = RateMeter(window_s=5.0, clock=clk)
    for _ in range(20):                                 # 10 Hz for 2 s
        m.tick()
        clk.t += 0.1
    assert m.rate_hz() == pytest.approx(10.0, rel=1e-9)
    for _ in range(580):                                # and on, 60 s in all
        m.tick()
        clk.t += 0.1
    assert m.rate_hz() == pytest.approx(10.0, rel=0.03)   # 50 or 51 ticks in the window (its edge, float times)


def test_latency_window_p99_of_a_few_samples_is_the_slowest():
    """Percentiles are the sample at rank round(p (n - 1)): with fewer than 51 samples the p99 is the slowest one, so
    ten 1 ms loop iterations and one 80 ms pause (a gc collection) read p50 1 ms, p99 80 ms; three read the middle
    one as p50 and the slowest as p99. Rounded, not truncated: truncation would hide the pause."""
    clk = FakeClock()
    w = LatencyWindow(window_s=10.0, clock=clk)
    for s in [0.001] * 5 + [0.080] + [0.001] * 5:
        w.add(s)
    assert w.summary_ms() == {"p50": 1.0, "p99": 80.0, "max": 80.0, "n": 11}
    w = LatencyWindow(window_s=10.0, clock=clk)
    for s in (0.100, 0.001, 0.002):
        w.add(s)
    assert w.summary_ms() == {"p50": 2.0, "p99": 100.0, "max": 100.0, "n": 3}


class _Sample:
    def __init__(self, payload, key="eonav/x/nav/state"):
        self.key_expr = key
        self.payload = self
        self._p = payload

    def to_bytes(self):
        return self._p


def test_node_decode_never_raises():
    args = argparse.Namespace(vehicle="v", health_period_s=1.0)
    node = Node("unit", args, session=None)
    assert node.decode(_Sample(b"\x00garbage"), expect="nav_state") is None
    assert node.decode(_Sample(schema.encode("nav_state", stamp_us=5)), expect="obstacle_list") is None
    msg = node.decode(_Sample(schema.encode("nav_state", stamp_us=5)), expect="nav_state")
    assert msg["stamp_us"] == 5
    c = node.counters()
    assert c["decode_errors"] == 2 and c["in.nav_state"] == 1
    f = node.health_fields()
    schema.decode(schema.encode("health", **f), expect="health")  # health is always encodable
    with pytest.raises(Exception, match="state"):
        node.set_state("bad")


class _RouterInfo:
    """``session.info.routers_zid()`` as a zenoh client session gives it: the zids of the routers it is linked to."""
    def __init__(self):
        self.info, self.zids = self, []

    def routers_zid(self):
        return list(self.zids)


def test_lost_router_degrades_the_node_until_it_is_back():
    """A service whose session lost its router reports ``degraded`` naming the outage (guidance and the operator see
    it in its health once the link is back, the launcher's status from the last message), is ``ok`` again when a
    router is back, tells each change once (the health timer publishes at once on it), keeps its own detail after
    the outage's and never masks an error."""
    s = _RouterInfo()
    node = Node("unit", argparse.Namespace(vehicle="v", health_period_s=1.0), session=s)
    node._router = S.RouterWatch(s, clock=lambda: 0.0)
    s.zids = ["a1"]
    assert not node.check_router(10.0) and node.state == "ok"
    s.zids = []                                                     # the router's link closed
    assert node.check_router(11.0)
    assert (node.state, node.health_fields()["detail"]) == ("degraded", "no zenoh router for 0.0 s")
    node.set_state("degraded", "locate failing")
    assert not node.check_router(12.5)                              # still lost: no change to tell
    assert node.health_fields()["detail"] == "no zenoh router for 1.5 s; locate failing"
    s.zids = ["b2"]                                                 # reconnected (a restarted router: a new zid)
    assert node.check_router(13.0)
    assert (node.state, node.health_fields()["detail"]) == ("degraded", "locate failing")
    node.set_state("ok")
    assert node.state == "ok"
    s.zids = []
    node.check_router(14.0)
    node.fail("worker died")
    assert (node.state, node.health_fields()["detail"]) == ("error", "worker died")


def test_session_flags_build_config(tmp_path, monkeypatch):
    p = argparse.ArgumentParser()
    monkeypatch.setenv("EONAV_CONNECT", "tcp/127.0.0.1:7447, tcp/10.0.0.2:7447")
    S.add_session_arguments(p)
    a = p.parse_args([])
    d = S.config_dict(a)
    assert d == {"mode": "peer", "connect/endpoints": ["tcp/127.0.0.1:7447", "tcp/10.0.0.2:7447"],
                 "listen/endpoints": ["tcp/127.0.0.1:0"], "scouting/multicast/enabled": False,
                 "transport/shared_memory/enabled": False}
    cfg = S.build_config(a)
    assert json.loads(cfg.get_json("scouting/multicast/enabled")) is False
    assert json.loads(cfg.get_json("connect/endpoints")) == ["tcp/127.0.0.1:7447", "tcp/10.0.0.2:7447"]
    # a file is applied first; flags override it
    f = tmp_path / "z.json5"
    f.write_text('{ mode: "client", connect: { endpoints: ["tcp/192.0.2.1:7447"] }, /* comment */ }')
    a = p.parse_args(["--zenoh-config", str(f), "--connect", "tcp/127.0.0.1:9999"])
    cfg = S.build_config(a)
    assert json.loads(cfg.get_json("mode")) == "client"
    assert json.loads(cfg.get_json("connect/endpoints")) == ["tcp/127.0.0.1:9999"]
    a = p.parse_args(["--multicast", "--mode", "peer"])
    assert S.config_dict(a)["scouting/multicast/enabled"] is True
    # shared memory: off by default, on with --shm; with a config file and no flag the file decides
    assert json.loads(S.build_config(p.parse_args(["--shm"])).get_json("transport/shared_memory/enabled")) is True
    assert "transport/shared_memory/enabled" not in S.config_dict(p.parse_args(["--zenoh-config", str(f)]))
    assert S.config_dict(p.parse_args(["--zenoh-config", str(f), "--no-shm"]))["transport/shared_memory/enabled"] is False
    with pytest.raises(Exception, match="no such file"):
        S.build_config(p.parse_args(["--zenoh-config", str(tmp_path / "missing.json5")]))
    with pytest.raises(Exception, match="endpoint"):
        S.split_endpoints("localhost:7447")


def test_a_peer_with_a_config_file_keeps_the_files_listen_endpoints(tmp_path):
    """The loopback listener ``tcp/127.0.0.1:0`` is added only to a peer given ``--connect`` with neither
    ``--listen`` nor a config file: a deployment's file that names where the peer listens (here 0.0.0.0:7448, for
    the other host) must keep it, or the other host can no longer reach this peer."""
    f = tmp_path / "peer.json5"
    f.write_text('{ mode: "peer", listen: { endpoints: ["tcp/0.0.0.0:7448"] } }')
    p = argparse.ArgumentParser()
    S.add_session_arguments(p)
    a = p.parse_args(["--zenoh-config", str(f), "--mode", "peer", "--connect", "tcp/192.0.2.1:7447"])
    assert "listen/endpoints" not in S.config_dict(a)
    cfg = S.build_config(a)
    assert json.loads(cfg.get_json("listen/endpoints")) == ["tcp/0.0.0.0:7448"]
    assert json.loads(cfg.get_json("connect/endpoints")) == ["tcp/192.0.2.1:7447"]
    a = p.parse_args(["--mode", "peer", "--connect", "tcp/192.0.2.1:7447"])          # no file: loopback listener
    assert json.loads(S.build_config(a).get_json("listen/endpoints")) == ["tcp/127.0.0.1:0"]


def test_lost_links_are_retried_after_a_quarter_second_then_every_half_second():
    """Without a file setting ``connect/retry`` every session retries a lost link after 0.25 s, then every 0.5 s
    (docs/zenoh.md, "Router restarts": zenoh's own 1 s doubling to 4 s found a restarted router up to 3.5 s late).
    Hand values from that schedule, not the module's constant."""
    p = argparse.ArgumentParser()
    S.add_session_arguments(p)
    retry = json.loads(S.build_config(p.parse_args(["--connect", "tcp/127.0.0.1:7447"])).get_json("connect/retry"))
    assert retry == {"period_init_ms": 250, "period_max_ms": 500, "period_increase_factor": 2}


@pytest.mark.parametrize("value,on", [("1", True), ("TRUE", True), (" yes ", True), ("on", True),
                                      ("0", False), ("off", False), ("no", False)])
def test_multicast_and_shm_environment_switches(monkeypatch, value, on):
    """``EONAV_ZENOH_MULTICAST`` / ``EONAV_ZENOH_SHM`` read as booleans (1/true/yes/on, any case and spacing, else
    off) in deployed env files: ``=1`` must turn them on, ``=0`` must not."""
    monkeypatch.setenv("EONAV_ZENOH_MULTICAST", value)
    monkeypatch.setenv("EONAV_ZENOH_SHM", value)
    p = argparse.ArgumentParser()
    S.add_session_arguments(p)
    d = S.config_dict(p.parse_args([]))
    assert d["scouting/multicast/enabled"] is on
    assert d["transport/shared_memory/enabled"] is on


def test_gc_pauses_are_timed_into_latencies_and_unwatched():
    """Collections of generations 1 and 2 show up as latencies gc.gen1 / gc.gen2; unwatch_gc removes the hook."""
    import gc
    from types import SimpleNamespace
    node = Node("gcwatch", SimpleNamespace(vehicle="v"), None)
    n_callbacks = len(gc.callbacks)
    node.watch_gc()
    try:
        gc.collect(2)
        gc.collect(1)
        gc.collect(0)                                     # generation 0: not recorded
        lat = node.health_fields()["latency_ms"]
        assert lat["gc.gen2"]["n"] >= 1 and lat["gc.gen1"]["n"] >= 1 and "gc.gen0" not in lat
    finally:
        node.unwatch_gc()
    assert len(gc.callbacks) == n_callbacks
    node.unwatch_gc()                                     # twice: harmless
