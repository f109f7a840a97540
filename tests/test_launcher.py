"""eonav run: embedded router, supervision (restart with back-off, give up, config errors, missing
modules), --exit-when-done, --duration-s, and a clean stop on SIGINT, all with real processes."""
from __future__ import annotations

import json
import logging
import os
import signal
import subprocess
import sys
import textwrap
import time

import cv2
import numpy as np
import pytest
from service_pkg import install_service_package

from eonav import InputError
from eonav.app import launcher as L

zenoh = pytest.importorskip("zenoh")

from eonav.bus import keys as K  # noqa: E402
from eonav.bus.session import client_session  # noqa: E402
from eonav.app.processes import free_port, start_service, wait_until  # noqa: E402

# Test services live in a throw-away package on PYTHONPATH (the launcher spawns `python -m <module>`).
SVC = textwrap.dedent('''
    import os, time
    from eonav.bus.node import service_main, add_flag

    def add_arguments(p):
        add_flag(p, "--exit-after", env="T_EXIT_AFTER", type=float, default=-1.0)
        add_flag(p, "--exit-code", env="T_EXIT_CODE", type=int, default=0)

    def body(node, args):
        def loop():
            t0 = time.monotonic()
            while not node.stop_event.wait(0.05):
                node.tick("loop")
                if 0 <= args.exit_after < time.monotonic() - t0:
                    if args.exit_code == 0:
                        node.stop("done")
                        return
                    os._exit(args.exit_code)          # a crash: no clean shutdown
        node.worker(loop)

    if __name__ == "__main__":
        service_main("t", add_arguments, body)
''')


@pytest.fixture
def svc_pkg(tmp_path, monkeypatch):
    return install_service_package(tmp_path, monkeypatch, "lsvc", SVC)


def _gone(pid):
    """Whether ``pid`` has exited: no such process, or a zombie (ours is reaped here; an orphan's waits for init).
    A live process that is not our child (the orphans of a killed launcher: waitpid cannot see them) is NOT gone: an
    earlier version called every non-child gone, so the orphan test passed with a router that never stopped."""
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return True
    try:
        if os.waitpid(pid, os.WNOHANG)[0] == pid:
            return True
    except ChildProcessError:
        pass
    try:
        with open(f"/proc/{pid}/stat") as f:
            state = f.read().rsplit(")", 1)[1].split()[0]      # the field after "(comm)"
    except FileNotFoundError:
        assert os.path.exists("/proc/self/stat"), "needs /proc to tell a live process from a zombie"
        return True                                             # exited between the two looks
    return state in ("Z", "X")


# ---- spec -------------------------------------------------------------------------------------------

def test_parse_spec_validates(tmp_path):
    s = L.parse_spec({"services": [{"name": "camera_nose", "module": "camera_ingest", "args": ["--rate-hz", 0]},
                                   {"name": "x.y", "module": "pkg.mod", "restart": False, "enabled": False}]})
    assert s[0].module == "eonav.services.camera_ingest" and s[0].args == ["--rate-hz", "0"]
    assert s[1].module == "pkg.mod" and not s[1].restart and not s[1].enabled
    with pytest.raises(InputError, match="used twice"):
        L.parse_spec({"services": [{"name": "a"}, {"name": "a"}]})
    with pytest.raises(InputError, match="unknown key"):
        L.parse_spec({"services": [{"name": "a", "argz": []}]})
    with pytest.raises(InputError, match="service"):
        L.parse_spec({"services": [{"name": "bad/name"}]})
    f = tmp_path / "p.json"
    f.write_text(json.dumps({"services": [{"name": "a", "args": ["{spec_dir}/x"]}]}))
    (sp,) = L.parse_spec(str(f))
    assert sp.env["EONAV_SPEC_DIR"] == str(tmp_path.resolve())
    f.write_text("{nope")
    with pytest.raises(InputError, match="not valid JSON"):
        L.parse_spec(str(f))


def test_default_spec_cameras():
    spec = L.default_spec(["nose=/dev/video0", "rtsp://cam/a?x=1", "tail=clip.mp4"], mavlink="udpin:0.0.0.0:14550")
    names = [s["name"] for s in spec["services"]]
    assert names[:3] == ["camera_nose", "camera_cam1", "camera_tail"]
    assert spec["services"][1]["args"] == ["--source", "rtsp://cam/a?x=1", "--camera-id", "cam1"]
    mav = next(s for s in spec["services"] if s["name"] == "mavlink")
    assert mav["args"] == ["--source", "udpin:0.0.0.0:14550"]
    assert {"sync", "locator", "obstacles"} <= set(names)
    L.parse_spec(spec)


# ---- router ------------------------------------------------------------------------------------------

def test_router_process_prints_ready_and_stops_on_sigint():
    port = free_port()
    proc = start_service(["-m", "eonav.bus.router", "--listen", f"tcp/127.0.0.1:{port}"])
    try:
        line = proc.stdout.readline()
        assert line.startswith("EONAV_ROUTER READY") and f"tcp/127.0.0.1:{port}" in line
        with client_session(f"tcp/127.0.0.1:{port}") as s:      # a client reaches it
            assert list(s.info.routers_zid())
        second = start_service(["-m", "eonav.bus.router", "--listen", f"tcp/127.0.0.1:{port}"])
        assert second.wait(15) == 2                              # port taken: configuration error
        assert "Address already in use" in second.stderr.read()
        proc.send_signal(signal.SIGINT)
        assert proc.wait(10) == 0
    finally:
        if proc.poll() is None:
            proc.kill()


# ---- supervision -------------------------------------------------------------------------------------

def test_restarts_crashing_service_then_gives_up_and_stops_cleanly(svc_pkg, tmp_path, caplog):
    caplog.set_level(logging.INFO, logger="eonav.app.launcher")
    spec = {"services": [
        {"name": "crashy", "module": svc_pkg, "args": ["--exit-after", "0.3", "--exit-code", "3"], "max_restarts": 2},
        {"name": "steady", "module": svc_pkg, "args": ["--health-period-s", "0.2"]},
        {"name": "badflags", "module": svc_pkg, "args": ["--no-such-flag"]},
        {"name": "ghost", "module": "services.not_written_yet"},
    ]}
    seen = []
    t0 = time.monotonic()
    code = L.run_pipeline(spec, vehicle="lt", duration=9.0, on_status=seen.append, quiet=True,
                          log_dir=str(tmp_path / "logs"))
    assert time.monotonic() - t0 < 25
    final = seen[-1]
    assert final["crashy"]["state"] == "failed" and final["crashy"]["restarts"] == 2
    assert final["crashy"]["exit_code"] == 3
    assert final["badflags"]["state"] == "config_error"
    assert final["ghost"]["state"] == "missing"
    assert final["steady"]["state"] == "stopped" and final["steady"]["exit_code"] == 0
    # the status came from the health topic: steady reported "ok" with a loop rate while running
    running = [s["steady"]["health"] for s in seen if s["steady"]["health"]]
    assert running and running[-1]["state"] == "ok" and running[-1]["rates_hz"]["loop"] > 5
    assert any(s["steady"]["alive"] for s in seen)
    # crashy ran 1 + max_restarts = 3 times, each restart after the back-off (0.5 s, then 1 s) from its crash
    assert (tmp_path / "logs" / "crashy.log").read_text().count("running (vehicle lt, pid") == 3
    events = [(r.created, r.getMessage()) for r in caplog.records if "service crashy" in r.getMessage()]
    crashes = [t for t, m in events if "exited 3; restart" in m]
    starts = [t for t, m in events if " started (pid " in m]
    assert [m.split("; ", 1)[1] for t, m in events if "exited 3; restart" in m] == ["restart 1/2 in 0.5 s",
                                                                                  "restart 2/2 in 1.0 s"]
    assert len(starts) == 3 and len(crashes) == 2
    for crash, start, delay in zip(crashes, starts[1:], (0.5, 1.0)):
        assert delay <= start - crash < delay + 0.5, (start - crash, delay)   # the launcher polls every 0.1 s
    assert any("service crashy exited 3; gave up after 2 restarts" in m for _, m in events)
    assert code == 1                       # a service failed for good
    pids = {s[n]["pid"] for s in seen for n in ("crashy", "steady") if s[n]["pid"]}
    assert all(_gone(p) for p in pids)
    assert (tmp_path / "logs" / "steady.log").read_text().count("stopped (SIGINT), exit 0") == 1



def test_back_off_doubles_from_half_a_second_and_is_capped_at_ten():
    """A service's restart delays: 0.5, 1, 2, 4, 8 s, then 10 s however many more (docs/bus.md, "Running"); each
    due that long after the crash. Catches the cap dropped (the default 5 restarts never reach it: 8 s)."""
    p = L.Proc(L.ServiceSpec(name="s", module="m", max_restarts=20))
    delays = [p.schedule_restart(100.0) for _ in range(8)]
    assert delays == [0.5, 1.0, 2.0, 4.0, 8.0, 10.0, 10.0, 10.0]
    assert p.restarts == 8 and p.state == "restarting" and p.next_start_mono == 110.0


def test_restart_count_resets_after_thirty_seconds_of_stable_running():
    """A service that crashed 3 times and then ran stably for more than 30 s (STABLE_RESET_S) starts afresh: its
    count is back to 0, so its next crash restarts after the initial 0.5 s, not 4 s, and is restart 1 of its
    max_restarts. 29.9 s is not enough. A real child process (exits 3 when its stdin closes); the clock is given to
    poll(). Catches the reset dropped."""
    sup = L.Supervisor([L.ServiceSpec(name="s", module="m", max_restarts=3)], vehicle="lt", router="tcp/x:1", ctx={})
    (p,) = sup.procs
    p.popen = subprocess.Popen([sys.executable, "-c", "import sys; sys.stdin.read(); sys.exit(3)"],
                               stdin=subprocess.PIPE)
    try:
        p.state, p.restarts, p.started_mono = "running", 3, 1000.0
        assert sup.poll(now=1000.0 + 29.9) == [] and p.restarts == 3
        assert sup.poll(now=1000.0 + 30.1) == [] and p.restarts == 0
        p.popen.stdin.close()
        assert p.popen.wait(10) == 3
        assert sup.poll(now=1040.0) == [p]
        assert p.state == "restarting" and p.restarts == 1 and p.next_start_mono == 1040.5 and p.exit_code == 3
    finally:
        if p.popen.poll() is None:
            p.popen.kill()
            p.popen.wait()


# a child that appends the EONAV_RESTART_COUNT it was started with to $T_OUT, then exits $T_EXIT_CODE (a crash)
CRASH = textwrap.dedent('''
    import os, sys
    with open(os.environ["T_OUT"], "a") as f:
        f.write(os.environ.get("EONAV_RESTART_COUNT", "unset") + "\\n")
    sys.exit(int(os.environ["T_EXIT_CODE"]))
''')


@pytest.fixture
def crash_pkg(tmp_path, monkeypatch):
    return install_service_package(tmp_path, monkeypatch, "lcrash", CRASH)


def _reap(sup, p, now):
    assert p.popen.wait(10) is not None
    return sup.poll(now=now)


def test_each_start_gets_its_restart_count(crash_pkg, tmp_path):
    """A service that crashes (exit 3) with max_restarts 2 is started 3 times, with EONAV_RESTART_COUNT 0, 1, 2 (docs/
    bus.md, "Supervision": a replay reads it to resume or end rather than start over), each restart due after the
    back-off (0.5 s, then 1 s) from the clock given to poll(), then fails for good. Real child processes. Catches a
    constant count passed (a restarted replay without a shift would present its recording's start as now)."""
    out = tmp_path / "counts.txt"
    spec = L.ServiceSpec(name="replay", module=crash_pkg, max_restarts=2, env={"T_OUT": str(out), "T_EXIT_CODE": "3"})
    sup = L.Supervisor([spec], vehicle="lt", router="tcp/127.0.0.1:1", ctx={})
    (p,) = sup.procs
    sup.start_all()
    assert _reap(sup, p, 100.0) == [p] and p.state == "restarting" and p.next_start_mono == 100.5
    assert sup.poll(now=100.49) == [] and p.state == "restarting"          # not before its time
    sup.poll(now=100.5)
    assert p.state == "running"
    assert _reap(sup, p, 200.0) == [p] and p.state == "restarting" and p.next_start_mono == 201.0
    sup.poll(now=201.0)
    assert _reap(sup, p, 300.0) == [p]
    assert (p.state, p.restarts, p.exit_code) == ("failed", 2, 3)
    assert out.read_text().split() == ["0", "1", "2"]


def test_a_service_with_restart_false_is_not_restarted_after_a_crash(crash_pkg, tmp_path):
    """``"restart": false``: a crash (exit 3) leaves the service failed with its exit code and no restart, while the
    same crash of a restartable service is restarted after 0.5 s; it is not started again however long the
    supervisor polls. Real child processes. Catches the restart flag ignored (only max_restarts consulted)."""
    out = tmp_path / "counts.txt"
    env = {"T_OUT": str(out), "T_EXIT_CODE": "3"}
    sup = L.Supervisor([L.ServiceSpec(name="once", module=crash_pkg, restart=False, env=env),
                        L.ServiceSpec(name="again", module=crash_pkg, env=env)],
                       vehicle="lt", router="tcp/127.0.0.1:1", ctx={})
    once, again = sup.procs
    sup.start_all()
    assert once.popen.wait(10) == 3 and again.popen.wait(10) == 3
    assert sup.poll(now=100.0) == [once, again]
    assert (once.state, once.restarts, once.exit_code) == ("failed", 0, 3)
    assert (again.state, again.restarts, again.next_start_mono) == ("restarting", 1, 100.5)
    pid = once.popen.pid
    sup.poll(now=100.5)
    sup.poll(now=1000.0)
    assert once.state == "failed" and once.popen.pid == pid and again.popen.pid != pid
    assert again.popen.wait(10) == 3
    assert out.read_text().split() == ["0", "0", "1"]       # once, again, again restarted


def test_exit_code_1_after_a_configuration_error(crash_pkg, tmp_path):
    """A service that exits 2 (configuration error) is not restarted and, once nothing is left running, ``eonav run``
    ends with exit 1 (docs/bus.md, "Running": a service failed for good) and says why. Catches config_error left out
    of the failed states the exit code counts (the run then exits 0 as if it had finished cleanly)."""
    import io
    err, seen = io.StringIO(), []
    spec = {"services": [{"name": "bad", "module": crash_pkg,
                          "env": {"T_OUT": str(tmp_path / "counts.txt"), "T_EXIT_CODE": "2"}}]}
    code = L.run_pipeline(spec, vehicle="lt7", duration=20, on_status=seen.append, status_stream=err)
    assert code == 1
    assert (seen[-1]["bad"]["state"], seen[-1]["bad"]["exit_code"], seen[-1]["bad"]["restarts"]) == \
        ("config_error", 2, 0)
    assert err.getvalue().splitlines()[-1] == "eonav run: no service left running; bad=config_error(2)"
    assert (tmp_path / "counts.txt").read_text().split() == ["0"]           # started once


def test_exit_code_1_when_no_service_could_be_started():
    """A pipeline none of whose modules exists starts nothing: ``eonav run`` stops at once with exit 1 and says so
    (a typo in every module name is not a clean run). Catches that run ending with exit 0."""
    import io
    err = io.StringIO()
    t0 = time.monotonic()
    code = L.run_pipeline({"services": [{"name": "ghost", "module": "services.not_written_yet"}]}, vehicle="lt8",
                          duration=20, status_stream=err)
    assert code == 1 and time.monotonic() - t0 < 10
    assert err.getvalue().splitlines()[-1] == "eonav run: no service could be started; ghost=missing"


def test_status_line_shows_health_older_than_five_seconds_as_stale():
    """A running service's status entry: its last health state while that message is under 5 s old, ``stale`` after
    (the service stopped reporting: its "ok" no longer says anything), with its rate and restarts either way. Hand
    values; the clock is given. Catches the age's sign flipped (an old health shown as current)."""
    p = L.Proc(L.ServiceSpec(name="sync", module="m"), state="running", restarts=1, health_mono=1000.0,
               health={"state": "ok", "detail": "", "rates_hz": {"frames": 4.96, "nav": 50.0}, "latency_ms": {},
                       "counters": {}})
    assert L._fmt_service(p, 1004.9) == "sync ok 50.0Hz r1"
    assert L._fmt_service(p, 1005.0) == "sync stale 50.0Hz r1"
    assert L._fmt_service(p, 1060.0) == "sync stale 50.0Hz r1"
    p.health = dict(p.health, state="degraded", detail="no frames for 1.3 s; no nav for 0.6 s")
    assert L._fmt_service(p, 1001.0) == "sync degraded(no frames for 1.3 s) 50.0Hz r1"
    assert L._fmt_service(p, 1006.0) == "sync stale 50.0Hz r1"

def test_stop_processes_grace_is_in_total_not_per_process():
    """stop_processes: SIGINT to each, ``grace_s`` in total, then SIGKILL the rest. Three children that ignore
    SIGINT are killed about 1 s after the call (not 3 x 1 s: the bound leaves a loaded machine 1.5 s); one that exits
    on SIGINT exits by itself (code 0). Catches the grace waited per process (a stuck pipeline then takes N x grace
    to stop)."""
    from eonav.app.processes import stop_processes
    stuck = "import signal, sys; signal.signal(signal.SIGINT, signal.SIG_IGN); print('ready', flush=True); " \
            "sys.stdin.read()"
    polite = "import sys\ntry:\n    print('ready', flush=True); sys.stdin.read()\nexcept KeyboardInterrupt:\n" \
             "    sys.exit(0)"
    procs = [subprocess.Popen([sys.executable, "-c", code], stdin=subprocess.PIPE, stdout=subprocess.PIPE, text=True)
             for code in (stuck, stuck, stuck, polite)]
    try:
        assert all(pp.stdout.readline() == "ready\n" for pp in procs)     # handlers in place
        t0 = time.monotonic()
        stop_processes(procs, 1.0)
        elapsed = time.monotonic() - t0
        assert 1.0 <= elapsed < 2.5, elapsed
        assert [pp.returncode for pp in procs] == [-signal.SIGKILL] * 3 + [0]
    finally:
        for pp in procs:
            if pp.poll() is None:
                pp.kill()
                pp.wait()


def test_exit_when_done(svc_pkg):
    spec = {"services": [{"name": "replay", "module": svc_pkg, "args": ["--exit-after", "1.0"]},
                         {"name": "worker", "module": svc_pkg}]}
    t0 = time.monotonic()
    code = L.run_pipeline(spec, vehicle="lt2", duration=30, exit_when_done="replay", quiet=True)
    assert code == 0
    assert time.monotonic() - t0 < 15
    with pytest.raises(InputError, match="no such service"):
        L.run_pipeline(spec, exit_when_done="nope", quiet=True)


def test_eonav_run_camera_replay_until_done(tmp_path):
    d = tmp_path / "rec"
    d.mkdir()
    for i in range(5):
        cv2.imwrite(str(d / f"{i}.png"), np.full((24, 32), 40 * i, np.uint8))
    spec = tmp_path / "pipeline.json"
    spec.write_text(json.dumps({"services": [
        {"name": "camera_nose", "module": "camera_ingest",
         "args": ["--source", "{spec_dir}/rec", "--camera-id", "nose", "--rate-hz", "10", "--wait-subscribers-s", "0"]}]}))
    out = start_service(["-m", "eonav.app.cli", "run", "--pipeline", str(spec), "--vehicle", "lt3",
                         "--exit-when-done", "camera_nose"])
    code = out.wait(60)
    err = out.stderr.read()
    assert code == 0, err
    assert "camera_nose=done" in err


def start_launcher(spec: dict, kwargs: str):
    """``run_pipeline(spec, <kwargs>)`` in its own process (so the test can signal or kill the launcher)."""
    return start_service(["-c", "import sys, json; from eonav.app.launcher import run_pipeline; "
                          f"sys.exit(run_pipeline(json.loads({json.dumps(spec)!r}), {kwargs}))"])


def test_sigint_to_launcher_stops_everything(svc_pkg):
    port = free_port()
    proc = start_launcher({"services": [{"name": "s1", "module": svc_pkg}, {"name": "s2", "module": svc_pkg}]},
                          "vehicle='lt4', port=%d" % port)
    try:
        _wait_port(port)
        with client_session(f"tcp/127.0.0.1:{port}") as s:
            alive = s.liveliness().declare_subscriber(K.alive_all("lt4"), zenoh.handlers.FifoChannel(64), history=True)
            state = {}

            def poll():
                while (x := alive.try_recv()) is not None:
                    state[str(x.key_expr).rsplit("/", 1)[-1]] = x.kind == zenoh.SampleKind.PUT
                return state
            wait_until(lambda: poll().get("s1") and poll().get("s2"), 30, what="both services alive")
            proc.send_signal(signal.SIGINT)
            assert proc.wait(20) == 0
            alive.undeclare()
    finally:
        if proc.poll() is None:
            proc.kill()
    err = proc.stderr.read()
    assert "eonav run: SIGINT" in err and "s1=stopped" in err and "s2=stopped" in err, err
    assert err.count("stopped (SIGINT), exit 0") == 2, err    # each service got exactly one SIGINT


def _wait_port(port, timeout=20):
    import socket
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        with socket.socket() as s:
            if s.connect_ex(("127.0.0.1", port)) == 0:
                return True
        time.sleep(0.05)
    raise AssertionError(f"router port {port} never opened")


def test_eonav_service_command_passes_args(tmp_path):
    proc = start_service(["-m", "eonav.app.cli", "service", "camera_ingest", "--source", str(tmp_path / "missing"),
                          "--vehicle", "x"])
    assert proc.wait(30) == 2
    assert "not a directory" in proc.stderr.read()
    proc = start_service(["-m", "eonav.app.cli", "service", "nope_service"])
    assert proc.wait(30) == 2
    err = proc.stderr.read()
    services = ("camera_ingest", "locator", "mavlink_ingest", "obstacles", "sync")
    assert all(s in err for s in services) and "did you mean" not in err, err    # lists what exists
    proc = start_service(["-m", "eonav.app.cli", "service", "camera"])              # the instance name, not the module
    assert proc.wait(30) == 2
    assert "did you mean 'camera_ingest'?" in proc.stderr.read()
    # each service's --help names the command that runs it
    procs = {s: start_service(["-m", "eonav.app.cli", "service", s, "--help"]) for s in services}
    for s, proc in procs.items():
        assert proc.wait(60) == 0
        assert proc.stdout.read().startswith(f"usage: eonav service {s} "), s


def test_watch_mode_shows_remote_services(svc_pkg):
    from eonav.app.processes import router_process, stop_service
    with router_process() as ep:
        svc = start_service(["-m", svc_pkg, "--connect", ep, "--vehicle", "lt5", "--name", "elsewhere",
                             "--health-period-s", "0.2"])
        try:
            seen = []
            code = L.run_pipeline({"services": []}, vehicle="lt5", router=ep, duration=4.0, on_status=seen.append,
                                  quiet=True)
            assert code == 0
            assert seen[-1]["elsewhere"]["state"] == "remote" and seen[-1]["elsewhere"]["alive"]
            assert seen[-1]["elsewhere"]["health"]["state"] == "ok"
            assert svc.poll() is None                      # watching never touches other processes
        finally:
            code, err = stop_service(svc)
        assert code == 0, err


def test_deploy_configs_are_valid_zenoh_configs():
    from pathlib import Path
    root = Path(__file__).resolve().parents[1] / "deploy"
    r = zenoh.Config.from_file(str(root / "zenoh" / "router.json5"))
    assert json.loads(r.get_json("mode")) == "router"
    assert "tcp/127.0.0.1:7447" in json.loads(r.get_json("listen/endpoints"))
    assert json.loads(r.get_json("scouting/multicast/enabled")) is False
    p = zenoh.Config.from_file(str(root / "zenoh" / "peer.json5"))
    assert json.loads(p.get_json("mode")) == "peer"
    assert json.loads(p.get_json("connect/endpoints")) == ["tcp/127.0.0.1:7447"]
    assert json.loads(p.get_json("scouting/multicast/enabled")) is False
    unit = (root / "systemd" / "eonav@.service").read_text()
    for line in ("EnvironmentFile=/etc/eonav/%i.env",
                 "KillSignal=SIGINT", "Restart=on-failure", "After=network-online.target zenohd.service"):
        assert line in unit
    # every unit starts a module that exists: eonav@<service> for each deploy/env/<service>.env, eonav-camera@<id>
    # (camera_nose.env is eonav-camera@nose's, checked with the instances below)
    services = sorted(f.stem for f in (root / "env").glob("*.env") if f.stem not in ("common", "camera_nose"))
    assert services == ["camera_ingest", "locator", "mavlink_ingest", "obstacles", "sync"]
    for name, instances in (("eonav@.service", services), ("eonav-camera@.service", ["nose"])):
        (cmd,) = [ln for ln in (root / "systemd" / name).read_text().splitlines() if ln.startswith("ExecStart=")]
        module = cmd.split(" -m ", 1)[1].split()[0]
        assert module.startswith("eonav.services."), module     # the wheel installs the services under eonav only
        for i in instances:
            assert L.module_exists(module.replace("%i", i)), (name, module, i)
    for env in (root / "env").glob("*.env"):
        for ln in env.read_text().splitlines():
            if ln.strip() and not ln.startswith("#"):
                assert "=" in ln and (ln.startswith("EONAV_") or ln.split("=")[0] in ("RUST_LOG",
                                                                                   "OPENCV_FFMPEG_CAPTURE_OPTIONS")), ln


def test_children_stop_when_launcher_is_killed(svc_pkg):
    """A launcher killed outright (SIGKILL: no clean-up) leaves its router and service orphaned; both see their
    supervisor gone (EONAV_SUPERVISOR_PID) and exit by themselves. Catches a router that logs the supervisor gone
    and keeps running (a planted ``continue`` for the ``break`` in eonav.bus.router.serve)."""
    import shutil
    if not shutil.which("pgrep"):
        pytest.skip("needs pgrep (procps)")
    port = free_port()
    proc = start_launcher({"services": [{"name": "orphan", "module": svc_pkg}]},
                          "vehicle='lt6', port=%d, quiet=True" % port)
    pids = []
    try:
        _wait_port(port)
        with client_session(f"tcp/127.0.0.1:{port}") as s:
            alive = s.liveliness().declare_subscriber(K.alive_all("lt6"), zenoh.handlers.FifoChannel(64), history=True)
            wait_until(lambda: alive.try_recv() is not None, 30, what="service alive")
            alive.undeclare()
        import subprocess
        for pattern in ("--vehicle lt6", f"eonav.bus.router --listen tcp/127.0.0.1:{port}"):
            out = subprocess.run(["pgrep", "-P", str(proc.pid), "-f", "--", pattern], capture_output=True,
                                 text=True).stdout.split()                  # this launcher's children only
            pids += [int(p) for p in out]
        assert len(pids) == 2, pids                           # the service and the router
        proc.kill()                                           # no chance to clean up
        proc.wait(10)
        wait_until(lambda: all(_gone(p) for p in pids), 15, what="orphaned service and router to exit")
    finally:
        if proc.poll() is None:
            proc.kill()
        for p in pids:                                        # a failed run leaves no orphan behind
            if not _gone(p):
                try:
                    os.kill(p, signal.SIGKILL)
                except ProcessLookupError:
                    pass


def test_children_import_the_installed_eonav_not_a_folder_of_that_name_in_the_working_directory(tmp_path, monkeypatch):
    """``eonav run`` from a folder that holds a checkout called ``eonav`` (a namespace package to ``python -m``):
    the router and the services start with ``python -P`` and import the installed eonav, and the pipeline runs; a
    plain ``python -m`` there picks the folder and fails to import (the control)."""
    from eonav.app.processes import start_router, stop_processes
    (tmp_path / "eonav").mkdir()                                   # a checkout's root: no __init__.py
    monkeypatch.chdir(tmp_path)
    plain = subprocess.run([sys.executable, "-m", "eonav.bus.router", "--help"], capture_output=True, text=True,
                           timeout=60)
    assert plain.returncode != 0 and "ImportError" in plain.stderr
    proc, ep = start_router(free_port())
    try:
        assert proc.poll() is None and ep.startswith("tcp/")
    finally:
        stop_processes([proc], 5.0)
    spec = L.ServiceSpec("sync", "eonav.services.sync")
    argv = L.Supervisor([spec], vehicle="v", router="tcp/127.0.0.1:1", ctx={}).argv(spec)
    assert argv[:4] == [sys.executable, "-P", "-m", "eonav.services.sync"]
    started = subprocess.run([*argv[:4], "--help"], capture_output=True, text=True, timeout=60)
    assert started.returncode == 0 and "usage" in started.stdout


STUCK_SVC = textwrap.dedent('''
    import os, threading
    from eonav.bus.node import service_main

    def body(node, args):
        never = threading.Event()
        node.worker(never.wait, name="stuck")          # ignores stop_event: a call that never returns
        node.worker(never.wait, name="stuck2")
        node.worker(lambda: node.stop_event.wait(), name="fine")
        open(os.environ["T_READY"], "w").close()

    if __name__ == "__main__":
        service_main("stuck", None, body)
''')


def test_a_service_whose_workers_do_not_stop_still_exits_after_the_join_deadline(tmp_path, monkeypatch):
    """SIGINT to a service two of whose workers ignore ``stop_event``: it logs each stuck worker, exits with code 1
    (the shutdown failed) and does so within one join deadline (``JOIN_TIMEOUT_S``, 5 s, shared by all workers,
    not 5 s each), instead of waiting forever for its non-daemon threads at interpreter exit."""
    from eonav.app.processes import stop_service
    from eonav.bus.node import JOIN_TIMEOUT_S
    module = install_service_package(tmp_path, monkeypatch, "stucksvc", STUCK_SVC)
    ready = tmp_path / "ready"
    proc = start_service(["-m", module, "--vehicle", "st", "--listen", f"tcp/127.0.0.1:{free_port()}"],
                         env={"T_READY": str(ready)})
    try:
        wait_until(lambda: proc.poll() is not None or ready.exists(), timeout=30, what="the service's workers")
        assert proc.poll() is None, proc.communicate()
    except AssertionError:
        proc.kill()
        raise
    t0 = time.monotonic()
    code, err = stop_service(proc, timeout=30.0)
    took = time.monotonic() - t0
    assert code == 1, err
    assert "worker stuck.stuck did not stop" in err and "worker stuck.stuck2 did not stop" in err
    assert "exiting without waiting for threads still running: " in err
    assert JOIN_TIMEOUT_S - 0.5 < took < 2 * JOIN_TIMEOUT_S, took
