"""kill -9 of a router that ``eonav run`` did not start (the deploy layout: the router is a unit of its own, restarted
by its supervisor, systemd's ``Restart=on-failure``). The test plays the supervisor: it runs the router process,
kills it and starts it again on the same port after ``RESTART_AFTER_S``. The services run as zenoh clients, plain or
under access control (the deploy's sessions, each with its own user), so everything, data included, goes through
the router: the pipeline stops for the outage. They must keep running (none exits or restarts), say the router was lost, reconnect
by themselves, and publish nothing stale once it is back; the launcher (``run_pipeline(router=EP)``) reports the lost
router in its status."""
from __future__ import annotations

import copy
import os
import signal
import threading
import time

import pytest

zenoh = pytest.importorskip("zenoh")

from eonav.app.bench_soak import BusWatch, lap_recording, looped_spec  # noqa: E402
from eonav.app.demo import replay_shift_us  # noqa: E402
from eonav.app.launcher import run_pipeline  # noqa: E402
from eonav.app.processes import free_port, start_router, stop_processes, wait_until  # noqa: E402
from test_faults import FPS, Pipe, _listening  # noqa: E402

pytestmark = pytest.mark.pipeline   # real services against real-time budgets: one such test at a time

VEHICLE = "routerfault"
RESTART_AFTER_S = 3.0     # past zenoh's own first retries (1 s, 3 s after the loss): with them 3.4 s late
RECOVERY_S = 1.5          # router listening again -> obstacle lists through it (a retry every 0.5 s, a frame, work)
SERVICES = ("camera", "mavlink", "sync", "locator", "obstacles")


class Supervisor:
    """The router as systemd runs it: started, and started again ``RESTART_AFTER_S`` after it died."""

    def __init__(self, port: int, zenoh_config: str | None = None):
        self.port, self.zenoh_config = port, zenoh_config
        self.proc, self.ep = start_router(port, zenoh_config=zenoh_config)
        self.stop = threading.Event()
        self.restarted_at: list[float] = []
        self.thread = threading.Thread(target=self._run, name="router-supervisor")
        self.thread.start()

    def _run(self):
        while not self.stop.wait(0.02):
            if self.proc.poll() is not None:
                if self.stop.wait(RESTART_AFTER_S):
                    return
                self.proc, _ = start_router(self.port, zenoh_config=self.zenoh_config)
                self.restarted_at.append(time.monotonic())

    def close(self):
        self.stop.set()
        self.thread.join(20)
        stop_processes([self.proc], 5.0)


@pytest.fixture(scope="module", params=["clients", "access-control"])
def pipe(request, tmp_path_factory):
    """The pipeline on a router of its own: services as plain clients, or under access control (the deploy's
    layout: each service a client with its own user; the router enforces the ACL after its restart too)."""
    from eonav.app.launcher import parse_spec, secure_sessions
    from eonav.bus import acl
    from eonav.fusion.sequence import prepare_kernels
    rec = lap_recording(FPS, (160, 160), nav_s=300.0)
    prepare_kernels()
    shift = replay_shift_us(rec, start_in_s=4.0)
    spec = looped_spec(rec, shift)
    acl_dir = watch_config = None
    if request.param == "access-control":
        acl_dir = tmp_path_factory.mktemp("router-fault-acl")
        _, watch_config = secure_sessions(acl_dir, parse_spec(spec), write=True)
        watch_config = str(watch_config)
    router = Supervisor(free_port(), zenoh_config=str(acl_dir / acl.ROUTER_FILE) if acl_dir else None)
    stop = threading.Event()
    status, history = {}, []
    logs = tmp_path_factory.mktemp("router-fault-logs")

    def on_status(st):
        status.update(st)
        history.append((time.monotonic(), copy.deepcopy(st)))

    def run():
        run_pipeline(spec, vehicle=VEHICLE, router=router.ep, on_status=on_status, stop_event=stop, quiet=True,
                     log_dir=str(logs), acl_dir=str(acl_dir) if acl_dir else None,
                     extra_env=None if acl_dir else {"EONAV_ZENOH_MODE": "client"})

    th = threading.Thread(target=run, name="pipeline")
    th.start()
    try:
        with BusWatch(router.ep, VEHICLE, zenoh_config=watch_config) as w:
            p = Pipe(w, status, th, history, router.ep)
            p.router, p.logs, p.variant = router, logs, request.param
            p.wait_flowing(60.0)
            yield p
    finally:
        stop.set()
        th.join(60.0)
        router.close()
        for f in sorted(logs.iterdir()):
            print(f"---- {f.name}\n{f.read_text()[-3000:]}")


def test_separate_router_killed_and_restarted_by_its_supervisor(pipe):
    pipe.wait_flowing()
    before = {n: (pipe.pid(n), pipe.status[n]["restarts"]) for n in SERVICES}
    assert pipe.status["router"]["state"] == "external" and pipe.status["router"]["health"]["state"] == "ok"
    t_kill = time.monotonic()
    os.kill(pipe.router.proc.pid, signal.SIGKILL)
    wait_until(lambda: not _listening(pipe.endpoint), 5, 0.01, "the router's port closed")
    t_listen = wait_until(lambda: _listening(pipe.endpoint) and time.monotonic(), 15, 0.01,
                          "the router's port open again")
    # the launcher's status said degraded (no router) while it was gone, reported at once
    down = [(t, st["router"]["health"]) for t, st in pipe.history if t_kill < t < t_listen]
    assert down and down[0][0] - t_kill < 0.5, down[:1]
    assert all(h["state"] == "degraded" and "no zenoh router" in h["detail"] for _, h in down[:-1]), down
    first_list = wait_until(lambda: min((x["t"] for x in pipe.w.snapshot()["lists"] if x["t"] > t_listen),
                                        default=None), 10, 0.05, "an obstacle list through the restarted router")
    t_flow = pipe.wait_flowing(15.0)
    time.sleep(2.0)
    snap = pipe.assert_fresh_and_ordered(since_t=t_kill)
    in_outage = [x for x in snap["lists"] if t_kill + 0.1 < x["t"] < t_listen]
    assert not in_outage, in_outage[:3]                  # clients: nothing goes around the router
    after = {n: (pipe.pid(n), pipe.status[n]["restarts"]) for n in SERVICES}
    assert after == before, (before, after)             # no service exited, none was restarted
    assert pipe.status["router"]["health"]["state"] == "ok"
    for n in SERVICES[2:]:                              # each noticed and logged the loss and the return
        text = (pipe.logs / f"{n}.log").read_text()
        assert "zenoh router lost" in text and "zenoh router back" in text, n
    first = next(x for x in snap["lists"] if x["t"] > t_listen)
    recovery_s = first_list - t_listen
    print(f"separate router ({pipe.variant}): listening again {t_listen - t_kill:.2f} s after the kill, obstacle lists through it "
          f"{recovery_s:.2f} s after that (first list {first['frame_age_ms']:.0f} ms old), pipeline ok "
          f"{t_flow - t_listen:.2f} s after its return")
    assert recovery_s <= RECOVERY_S, recovery_s
    # a session without credentials: refused by the restarted router under access control (it enforces the ACL
    # again), let in without
    import json
    cfg = zenoh.Config()
    for k, v in (("mode", "client"), ("connect/endpoints", [pipe.endpoint]), ("connect/timeout_ms", 0),
                 ("connect/exit_on_failure", True), ("scouting/multicast/enabled", False)):
        cfg.insert_json5(k, json.dumps(v))
    if pipe.variant == "access-control":
        with pytest.raises(Exception):
            zenoh.open(cfg).close()
    else:
        zenoh.open(cfg).close()


class _Info:
    def __init__(self):
        self.zids = []

    def routers_zid(self):
        return list(self.zids)


class _Session:
    def __init__(self):
        self.info = _Info()


def test_router_watch_reports_a_lost_router_only_once_one_was_there():
    from eonav.bus.session import RouterWatch
    s = _Session()
    w = RouterWatch(s, clock=lambda: 0.0)
    assert w.check(0.0) is None and w.check(5.0) is None        # peer to peer, no router ever: nothing to lose
    s.info.zids = ["a1"]
    assert w.check(6.0) is None
    s.info.zids = []
    assert w.check(7.0) == "no zenoh router for 0.0 s"
    assert w.check(8.5) == "no zenoh router for 1.5 s"
    s.info.zids = ["b2"]                                          # a new router (a new zid) counts as back
    assert w.check(9.0) is None
    s.info.zids = []
    assert w.check(10.0) == "no zenoh router for 0.0 s"          # the outage is timed from its own start


def test_embedded_router_restarts_with_back_off_then_gives_up():
    from eonav.app.launcher import BACKOFF_INITIAL_S, EmbeddedRouter
    rt = EmbeddedRouter(free_port(), max_restarts=1)
    rt.start()
    try:
        p = rt.proc
        assert p.state == "running" and p.health["state"] == "ok"
        old = p.popen.pid
        os.kill(old, signal.SIGKILL)
        p.popen.wait()
        t = time.monotonic()
        assert rt.poll(t) is True
        assert p.state == "restarting" and p.restarts == 1 and p.health["state"] == "degraded"
        assert p.next_start_mono == pytest.approx(t + BACKOFF_INITIAL_S)
        assert rt.poll(t + BACKOFF_INITIAL_S - 0.01) is False and p.state == "restarting"   # not before its time
        assert rt.poll(t + BACKOFF_INITIAL_S) is True
        assert p.state == "running" and p.popen.pid != old and p.health["state"] == "ok"
        assert _listening(f"tcp/127.0.0.1:{rt.port}")
        os.kill(p.popen.pid, signal.SIGKILL)
        p.popen.wait()
        assert rt.poll() is True
        assert p.state == "failed" and p.health["state"] == "error" and "gave up" in p.health["detail"]
    finally:
        rt.stop(2.0)


def test_sessions_retry_a_lost_router_every_half_second_unless_the_file_says(tmp_path):
    import argparse
    import json
    from eonav.bus.session import CONNECT_RETRY, build_config
    args = argparse.Namespace(mode="client", connect="tcp/127.0.0.1:7447", listen=None, zenoh_config=None,
                              multicast=False)
    assert json.loads(build_config(args).get_json("connect/retry")) == CONNECT_RETRY
    assert CONNECT_RETRY["period_max_ms"] == 500
    f = tmp_path / "z.json5"
    f.write_text('{connect: {retry: {period_init_ms: 2000, period_max_ms: 8000, period_increase_factor: 3}}}')
    args.zenoh_config = str(f)
    assert json.loads(build_config(args).get_json("connect/retry")) == {
        "period_init_ms": 2000, "period_max_ms": 8000, "period_increase_factor": 3.0}


def test_a_service_may_not_take_the_routers_name():
    from eonav import InputError
    from eonav.app.launcher import parse_spec
    with pytest.raises(InputError, match="'router' is the launcher's own"):
        parse_spec([{"name": "router", "module": "sync"}])
    assert [s.name for s in parse_spec([{"name": "router2", "module": "sync"}])] == ["router2"]
