"""deploy/ as written: the install steps of deploy/README.md, run in a scratch root (``systemctl --root``), enable
everything that must come up after a reboot; the units pass ``systemd-analyze verify`` without a warning; every
file a unit or an env file names ships; and the services started exactly as the units start them, with the env
files, cameras file and access control the steps install, all come up on a real router."""
import configparser
import json
import re
import shlex
import shutil
import socket
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import zenoh

from eonav.app import cli
from eonav.app.processes import free_port, stop_processes, wait_until

ROOT = Path(__file__).resolve().parents[1]
DEPLOY = ROOT / "deploy"
UNITS = DEPLOY / "systemd"
needs_systemctl = pytest.mark.skipif(shutil.which("systemctl") is None, reason="systemctl not installed")


def install_steps() -> list[list[str]]:
    """The commands of the README's "Install on one host" block (``sudo`` dropped)."""
    text = (DEPLOY / "README.md").read_text()
    block = re.search(r"## Install on one host\s+```sh\n(.*?)```", text, re.S).group(1)
    out = []
    for line in block.splitlines():
        line = line.split("#", 1)[0].strip()
        if line:
            argv = shlex.split(line)
            out.append(argv[1:] if argv[0] == "sudo" else argv)
    return out


def in_root(root: Path, path: str) -> Path:
    return root / path.lstrip("/")


def run_install(root: Path, port: int) -> list[str]:
    """Run the README's steps with every path under ``root`` and the router on ``port``; returns the units
    the steps enable. User creation, the venv, chown and journalctl are the host's business: skipped."""
    enabled = []
    for argv in install_steps():
        cmd = argv[0].rsplit("/", 1)[-1]
        if cmd == "mkdir":
            for p in argv[1:]:
                if not p.startswith("-"):
                    in_root(root, p).mkdir(parents=True, exist_ok=True)
        elif cmd == "cp":
            args = [a for a in argv[1:] if not a.startswith("-")]
            dest = in_root(root, args[-1])
            for pattern in args[:-1]:
                srcs = sorted(ROOT.glob(pattern)) if "*" in pattern else [ROOT / pattern]
                assert srcs, f"install step {' '.join(argv)}: {pattern} matches nothing in the repository"
                for src in srcs:
                    target = dest / src.name if dest.is_dir() or args[-1].endswith("/") else dest
                    target.parent.mkdir(parents=True, exist_ok=True)
                    (shutil.copytree(src, target, dirs_exist_ok=True) if src.is_dir() else shutil.copy(src, target))
        elif cmd == "eonav":
            acl_args = [str(in_root(root, a)) if a.startswith("/etc/") else a for a in argv[1:]]
            ep = f"tcp/127.0.0.1:{port}"
            assert cli.main([*acl_args, "--listen", ep, "--session-connect", ep,
                             "--users-file", str(in_root(root, "/etc/eonav/zenoh-users.txt"))]) == 0
        elif cmd == "systemctl" and argv[1] == "enable":
            units = [a for a in argv[2:] if not a.startswith("-")]
            enabled += units
            r = subprocess.run(["systemctl", f"--root={root}", "enable", *units], capture_output=True, text=True)
            assert r.returncode == 0, r.stderr
        else:
            assert cmd in ("useradd", "python3.11", "pip", "chown", "chmod", "systemctl", "journalctl") \
                or cmd.endswith("pip"), f"install step not understood by this test: {' '.join(argv)}"
    return [u if "." in u else u + ".service" for u in enabled]


def unit_file(name: str) -> Path:
    """The unit file of ``name`` (an instance reads its template)."""
    f = UNITS / name
    return f if f.is_file() else UNITS / re.sub(r"@[^.]*\.", "@.", name)


def sections(path: Path) -> dict:
    """section -> list of (key, value), keys may repeat (systemd's format)."""
    out, cur = {}, None
    for line in path.read_text().splitlines():
        line = line.strip()
        if not line or line.startswith("#"):
            continue
        if line.startswith("["):
            cur = out.setdefault(line.strip("[]"), [])
        else:
            k, _, v = line.partition("=")
            cur.append((k.strip(), v.strip()))
    return out


def values(path: Path, section: str, key: str) -> list[str]:
    return [v for k, v in sections(path).get(section, []) if k == key]


def instance(name: str) -> str:
    m = re.search(r"@([^.]*)\.", name)
    return m.group(1) if m else ""


# --------------------------------------------------------------------------------------------------

@needs_systemctl
def test_install_steps_enable_everything_after_a_reboot(tmp_path):
    root = tmp_path / "root"
    root.mkdir()
    enabled = run_install(root, 7447)
    etc = root / "etc/systemd/system"
    # multi-user.target (the boot target) wants eonav.target, which wants the router and every service
    assert (etc / "multi-user.target.wants/eonav.target").is_symlink()
    wants = {p.name for p in (etc / "eonav.target.wants").iterdir()}
    services = [u for u in enabled if u.endswith(".service")]
    assert set(services) <= wants, set(services) - wants
    assert {"zenohd.service", "eonav-camera@nose.service", "eonav@mavlink_ingest.service", "eonav@sync.service",
            "eonav@locator.service", "eonav@obstacles.service"} <= wants
    # every file a unit reads is installed
    for u in services:
        for ef in values(unit_file(u), "Service", "EnvironmentFile"):
            f = in_root(root, ef.lstrip("-").replace("%i", instance(u)))
            assert f.is_file(), f"{u}: EnvironmentFile {ef} is not installed by the steps"
    # every path an env file names is installed (the cameras file, each service's session config)
    for env in (root / "etc/eonav").glob("*.env"):
        for line in env.read_text().splitlines():
            if line and not line.startswith("#"):
                val = line.partition("=")[2]
                if val.startswith("/etc/eonav/"):
                    assert in_root(root, val).is_file(), f"{env.name}: {line} names a file the steps do not install"


def test_unit_settings_where_systemd_reads_them():
    for f in UNITS.glob("*.service"):
        sec = sections(f)
        for s, kv in sec.items():
            keys = {k for k, _ in kv}
            if s != "Unit":
                assert not keys & {"StartLimitIntervalSec", "StartLimitBurst"}, f"{f.name}: start limit in [{s}]"
        assert values(f, "Unit", "StartLimitIntervalSec") == ["0"], f"{f.name}: a vehicle's unit never gives up"
        assert values(f, "Install", "WantedBy") == ["eonav.target"], f.name
    assert values(UNITS / "eonav.target", "Install", "WantedBy") == ["multi-user.target"]
    # exit 2 stops the restarts only where it is a configuration error: the MAVLink links retry inside the
    # services, a camera that cannot be opened yet exits 2, so the camera ingest is restarted after it
    assert values(UNITS / "eonav@.service", "Service", "RestartPreventExitStatus") == ["2"]
    assert values(UNITS / "eonav-camera@.service", "Service", "RestartPreventExitStatus") == []
    assert values(UNITS / "eonav@camera_ingest.service.d" / "retry.conf", "Service", "RestartPreventExitStatus") == [""]
    assert not (UNITS / "eonav@mavlink_ingest.service.d").exists()


@pytest.mark.skipif(shutil.which("systemd-analyze") is None, reason="systemd-analyze not installed")
def test_units_pass_systemd_analyze_verify(tmp_path):
    """``systemd-analyze verify`` of every unit as installed (the interpreter path pointed at this venv, as the
    verifier checks that ExecStart exists); any warning fails."""
    d = tmp_path / "units"
    shutil.copytree(UNITS, d)
    for f in d.rglob("*"):
        if f.is_file():
            f.write_text(f.read_text().replace("/opt/eonav/venv/bin/python", sys.executable))
    names = ["eonav.target", "zenohd.service", "eonav-camera@nose.service", "eonav@camera_ingest.service",
             "eonav@mavlink_ingest.service", "eonav@sync.service", "eonav@locator.service", "eonav@obstacles.service"]
    r = subprocess.run(["systemd-analyze", "verify", *names], capture_output=True, text=True,
                       env={"SYSTEMD_UNIT_PATH": f"{d}:", "PATH": "/usr/bin:/bin:/usr/sbin:/sbin"})
    assert r.returncode == 0 and r.stderr.strip() == "" and r.stdout.strip() == "", r.stdout + r.stderr
    # the verifier does catch a misplaced key (the old units' StartLimitIntervalSec in [Service])
    bad = d / "eonav@.service"
    bad.write_text(bad.read_text().replace("[Service]\n", "[Service]\nStartLimitIntervalSec=60\n", 1))
    r = subprocess.run(["systemd-analyze", "verify", "eonav@locator.service"], capture_output=True, text=True,
                       env={"SYSTEMD_UNIT_PATH": f"{d}:", "PATH": "/usr/bin:/bin:/usr/sbin:/sbin"})
    assert "Unknown key 'StartLimitIntervalSec' in section [Service]" in r.stderr


def _unit_process(root: Path, unit: str, overrides: dict) -> tuple[list[str], dict]:
    """argv and environment of ``unit`` as systemd would start it (paths under ``root``)."""
    f = unit_file(unit)
    inst = instance(unit)
    env = {"PATH": "/usr/bin:/bin", "PYTHONUNBUFFERED": "1", "EONAV_LOG_LEVEL": "info"}
    for kv in values(f, "Service", "Environment"):
        k, _, v = kv.partition("=")
        if k != "NUMBA_CACHE_DIR":               # the unit's cache dir is /var/cache/eonav (CacheDirectory=)
            env[k] = v
    for ef in values(f, "Service", "EnvironmentFile"):
        for line in in_root(root, ef.replace("%i", inst)).read_text().splitlines():
            if line.strip() and not line.startswith("#"):
                k, _, v = line.partition("=")
                env[k] = str(in_root(root, v)) if v.startswith("/etc/eonav/") else v
    env.update(overrides)
    argv = shlex.split(values(f, "Service", "ExecStart")[0].replace("%i", inst))
    argv[0] = sys.executable
    argv = [str(in_root(root, a)) if a.startswith("/etc/eonav/") else a for a in argv]
    return argv, env


@needs_systemctl
def test_every_service_starts_as_installed(tmp_path):
    """The router and the five services, each with its unit's command line, env files, cameras file and session
    config from the install steps: every one declares its liveliness token and publishes health on the ACL
    router. Replaced for this machine: the camera device (a folder of images) and the UDP port of the autopilot
    link (a free one)."""
    import cv2
    root = tmp_path / "root"
    root.mkdir()
    port = free_port()
    enabled = run_install(root, port)
    frames = tmp_path / "frames"
    frames.mkdir()
    rng = np.random.default_rng(0)
    for i in range(3):
        cv2.imwrite(str(frames / f"{i:03d}.png"), rng.integers(0, 255, (720, 1280), dtype=np.uint8))
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
        s.bind(("127.0.0.1", 0))
        udp = s.getsockname()[1]
    overrides = {"EONAV_CAMERA_SOURCE": str(frames), "EONAV_CAMERA_LOOP": "1", "EONAV_CAMERA_RATE": "2",
                 "EONAV_MAVLINK_SOURCE": f"udpin:127.0.0.1:{udp}"}
    procs = []
    try:
        argv, env = _unit_process(root, "zenohd.service", {})
        out = tmp_path / "router.out"                # the unit's RUST_LOG=info goes to stdout too
        with open(out, "w") as f:
            procs.append(subprocess.Popen(argv, env=env, stdout=f, stderr=subprocess.STDOUT, start_new_session=True))
        wait_until(lambda: "EONAV_ROUTER READY" in out.read_text(), 15.0, what="the router")
        services = [u for u in enabled if u.startswith("eonav") and u.endswith(".service")]
        names = {}
        for u in services:
            argv, env = _unit_process(root, u, overrides)
            names[u] = env.get("EONAV_SERVICE_NAME") or f"camera_{instance(u)}"
            procs.append(subprocess.Popen(argv, env=env, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE,
                                          text=True, start_new_session=True))
        cfg = zenoh.Config.from_file(str(root / "etc/eonav/zenoh-operator.json5"))
        # the generated session waits for its router for ever: a router not listening where the sessions connect
        # (caught --listen ignored by eonav acl init) fails here instead of hanging the test
        cfg.insert_json5("connect/timeout_ms", "15000")
        cfg.insert_json5("connect/exit_on_failure", "true")
        with zenoh.open(cfg) as op:
            vehicle = _unit_process(root, services[0], {})[1]["EONAV_VEHICLE"]
            alive = op.liveliness().declare_subscriber(f"eonav/{vehicle}/alive/*", zenoh.handlers.FifoChannel(64),
                                                       history=True)
            health = op.declare_subscriber(f"eonav/{vehicle}/health/*", zenoh.handlers.FifoChannel(256))
            seen_alive, seen_health = set(), {}

            def all_up():
                for p, u in zip(procs[1:], services):
                    assert p.poll() is None, f"{u} exited {p.returncode}: {p.stderr.read()[-2000:]}"
                while (s := alive.try_recv()) is not None:
                    seen_alive.add(str(s.key_expr).rsplit("/", 1)[-1])
                while (s := health.try_recv()) is not None:
                    from eonav.bus import schema
                    m = schema.decode(s.payload.to_bytes(), expect="health")
                    seen_health[m["service"]] = m["state"]
                return set(names.values()) <= seen_alive and set(names.values()) <= set(seen_health)
            wait_until(all_up, 30.0, period=0.2, what=f"every service up ({sorted(names.values())})")
        print(json.dumps(seen_health))
        assert set(names.values()) == {"camera_nose", "mavlink", "sync", "locator", "obstacles"}
    finally:
        stop_processes(procs[::-1], 10.0)
    for p, u in zip(procs[1:], services):
        assert p.returncode == 0, f"{u} exit {p.returncode}"
