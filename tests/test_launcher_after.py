"""The launcher's staged start (a service's ``after``: started once those services are alive, i.e. their ``body``
returned, or after a timeout) and lazily computed ``{name}`` substitutions, with real processes on a real router;
the start rule and the substitution's reuse also in process (a stand-in start, the clock given)."""
from __future__ import annotations

import json
import textwrap
import threading
import time

import pytest
from service_pkg import install_service_package

from eonav import InputError
from eonav.app import launcher as L

pytest.importorskip("zenoh")

# "slow" takes --delay s in its body (as the locator loading its kernels); "mark" writes when it started and the
# value it was given
SVC = textwrap.dedent('''
    import json, time
    from eonav.bus.node import service_main, add_flag

    def add_arguments(p):
        add_flag(p, "--delay", env="T_DELAY", type=float, default=0.0)
        add_flag(p, "--out", env="T_OUT", default="")
        add_flag(p, "--value", env="T_VALUE", default="")

    def body(node, args):
        time.sleep(args.delay)
        with open(args.out, "w") as f:
            json.dump({"t": time.time(), "value": args.value}, f)

    if __name__ == "__main__":
        service_main("t", add_arguments, body)
''')


@pytest.fixture
def svc(tmp_path, monkeypatch):
    return install_service_package(tmp_path, monkeypatch, "lsvc_after", SVC)


def _run(spec, substitutions, until, timeout_s=40.0):
    stop, seen, out = threading.Event(), [], {}

    def on_status(st):
        seen.append(st)
        if until(st):
            stop.set()
    th = threading.Thread(target=lambda: out.update(code=L.run_pipeline(
        spec, vehicle="after", on_status=on_status, stop_event=stop, quiet=True, substitutions=substitutions)))
    th.start()
    th.join(timeout_s)
    stop.set()
    th.join(20)
    return out.get("code"), seen


def test_after_starts_once_the_dependency_is_alive_and_substitutes_then(svc, tmp_path):
    called = []

    def value():
        called.append(time.time())
        return "v42"
    spec = {"services": [
        {"name": "slow", "module": svc, "args": ["--delay", "3", "--out", str(tmp_path / "slow.json")]},
        {"name": "mark", "module": svc, "after": ["slow"], "restart": False,
         "args": ["--out", str(tmp_path / "mark.json"), "--value", "{value}"]}]}
    code, seen = _run(spec, {"value": value}, lambda st: (tmp_path / "mark.json").exists()
                      and st.get("mark", {}).get("alive"))
    assert code == 0
    slow = json.loads((tmp_path / "slow.json").read_text())
    mark = json.loads((tmp_path / "mark.json").read_text())
    assert mark["value"] == "v42" and len(called) == 1          # computed once, when "mark" started
    assert called[0] >= slow["t"] and mark["t"] >= slow["t"]     # after "slow"'s body returned
    assert any(st["mark"]["state"] == "waiting" for st in seen)


def test_after_gives_up_waiting_after_the_timeout(svc, tmp_path, monkeypatch):
    monkeypatch.setattr(L, "AFTER_TIMEOUT_S", 1.5)
    spec = {"services": [
        {"name": "stuck", "module": svc, "args": ["--delay", "30", "--out", str(tmp_path / "stuck.json")]},
        {"name": "mark", "module": svc, "after": ["stuck"], "restart": False,
         "args": ["--out", str(tmp_path / "mark.json")]}]}
    t0 = time.time()
    code, seen = _run(spec, None, lambda st: (tmp_path / "mark.json").exists())
    assert (tmp_path / "mark.json").exists() and not (tmp_path / "stuck.json").exists()
    assert json.loads((tmp_path / "mark.json").read_text())["t"] - t0 >= 1.5


def test_after_names_services_of_the_pipeline():
    with pytest.raises(InputError, match=r"after: \['nope'\] not other services"):
        L.parse_spec({"services": [{"name": "a"}, {"name": "b", "after": ["nope"]}]})
    with pytest.raises(InputError, match="after: expected a list"):
        L.parse_spec({"services": [{"name": "a", "after": "b"}]})


def _staged(after_state: str, alive: bool = False):
    """A supervisor of "dep" and "w" (after dep), started with a stand-in ``start`` that records the names; dep then
    put in ``after_state``."""
    sup = L.Supervisor([L.ServiceSpec(name="dep", module="m"), L.ServiceSpec(name="w", module="m", after=["dep"])],
                       vehicle="after", router="tcp/127.0.0.1:1", ctx={})
    started = []

    def start(p):
        started.append(p.name)
        p.state = "running"
    sup.start = start
    sup.start_all()
    dep, w = sup.procs
    assert started == ["dep"] and w.state == "waiting"
    dep.state, dep.alive = after_state, alive
    return sup, w, started


def test_after_starts_at_once_when_the_dependency_ended_or_never_started():
    """A waiting service starts as soon as each of its ``after`` services is alive or has ended (finished, failed,
    configuration error, module missing, disabled: docs/bus.md, "Running"), not 90 s later; one still starting (running,
    not alive yet) keeps it waiting until the timeout. Catches the ended dependencies dropped from the rule (the
    default pipeline's replays would then wait 90 s for a missing service)."""
    for state in ("done", "failed", "config_error", "missing", "disabled"):
        sup, w, started = _staged(state)
        sup.start_waiting(now=w.next_start_mono - L.AFTER_TIMEOUT_S + 0.1)
        assert started == ["dep", "w"], state
    sup, w, started = _staged("running")
    sup.start_waiting(now=w.next_start_mono - 0.1)
    assert started == ["dep"] and w.state == "waiting"
    sup.start_waiting(now=w.next_start_mono)
    assert started == ["dep", "w"]
    sup, w, started = _staged("running", alive=True)
    sup.start_waiting(now=w.next_start_mono - L.AFTER_TIMEOUT_S + 0.1)
    assert started == ["dep", "w"]


def test_a_lazy_substitution_is_computed_once_for_every_service_and_restart():
    """``{replay_shift_us}`` is a callable (the joint replay shift, computed when the replays start): the first
    service that needs it calls it, and every later argv (the other replay, a restart of either) gets that same
    value. A stand-in clock returns a new value at each call. Catches the value computed again at each use (the
    camera and the tlog replays then apart by the time between their starts, a restarted replay shifted anew)."""
    calls = []

    def shift():
        calls.append(1)
        return 1_000_000 * len(calls)
    sup = L.Supervisor([L.ServiceSpec(name=n, module="m", args=["--source", "x", "--replay-shift-us",
                                                                "{replay_shift_us}"]) for n in ("cam", "mav")],
                       vehicle="after", router="tcp/127.0.0.1:1", ctx={"replay_shift_us": shift, "vehicle": "after"})
    cam, mav = (p.spec for p in sup.procs)
    argvs = [sup.argv(cam), sup.argv(mav), sup.argv(cam)]
    assert [a[a.index("--replay-shift-us") + 1] for a in argvs] == ["1000000"] * 3
    assert len(calls) == 1 and sup.ctx["replay_shift_us"] == 1_000_000
