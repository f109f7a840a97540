"""The launcher's staged start (a service's ``after``: started once those services are alive, i.e. their ``body``
returned, or after a timeout) and lazily computed ``{name}`` substitutions, with real processes on a real router."""
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
