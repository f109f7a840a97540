"""The package map holds: each room of eonav/ imports only the rooms below it, no module import circle, the math
never loads the transport, and the wheel installs nothing outside ``eonav``. Imports are read with ``ast`` (function-
level imports included), so a lazy import that breaks the map is caught too."""
import ast
import subprocess
import sys
import tomllib
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]

# room -> the rooms it may import (docs/architecture.md draws the same map)
ALLOWED = {
    "geometry": set(),
    "io": {"geometry"},
    "ranging": {"geometry"},
    "fusion": {"geometry", "ranging"},
    "obstacles": {"geometry", "ranging"},
    "nav": {"geometry", "obstacles"},
    "bus": {"geometry", "io"},
    "sim": {"geometry", "io", "nav"},
    "recording": {"bus", "geometry", "io", "ranging"},
    "services": {"bus", "geometry", "io", "nav", "obstacles", "ranging", "fusion"},
    "app": None,                                   # the top: anything
    None: set(),                                   # eonav/__init__.py: the error types only
}
MATH = ["eonav.geometry", "eonav.ranging", "eonav.obstacles", "eonav.io", "eonav.sim", "eonav.fusion"]


def _modules():
    out = {}
    for base, prefix in ((ROOT / "eonav", "eonav"), (ROOT / "services", "eonav.services")):
        for p in base.rglob("*.py"):
            parts = list(p.relative_to(base).with_suffix("").parts)
            if parts[-1] == "__init__":
                parts = parts[:-1]
            out[".".join([prefix, *parts])] = p
    return out


def _imports(path: Path, known: dict) -> set:
    found = set()
    for node in ast.walk(ast.parse(path.read_text())):
        if isinstance(node, ast.ImportFrom) and node.level == 0 and (node.module or "").startswith("eonav"):
            found.add(node.module)
            found.update(f"{node.module}.{a.name}" for a in node.names if f"{node.module}.{a.name}" in known)
        elif isinstance(node, ast.Import):
            found.update(a.name for a in node.names if a.name.startswith("eonav"))
    return found


def _room(mod: str) -> str | None:
    parts = mod.split(".")
    return parts[1] if len(parts) > 1 else None


def test_every_room_imports_only_the_rooms_below_it():
    mods = _modules()
    bad = []
    for m, p in mods.items():
        src = _room(m)
        assert src in ALLOWED, f"{m}: room {src!r} is not in the package map (tests/test_layering.py ALLOWED)"
        if ALLOWED[src] is None:
            continue
        for t in _imports(p, mods):
            dst = _room(t)
            if dst not in (None, src) and dst not in ALLOWED[src]:
                bad.append(f"{m} -> {t}")
    assert not bad, "imports against the package map:\n" + "\n".join(sorted(bad))


def test_no_module_import_circle():
    mods = _modules()
    graph = {m: {t for t in _imports(p, mods) if t in mods and t != m} for m, p in mods.items()}
    state, stack = {}, []

    def visit(m):
        state[m] = "open"
        stack.append(m)
        for t in sorted(graph[m]):
            if state.get(t) == "open":
                raise AssertionError("import circle: " + " -> ".join(stack[stack.index(t):] + [t]))
            if t not in state:
                visit(t)
        stack.pop()
        state[m] = "done"

    for m in sorted(graph):
        if m not in state:
            visit(m)


def test_math_modules_do_not_load_the_transport():
    mods = [m for m in _modules() if any(m == r or m.startswith(r + ".") for r in MATH)]
    code = "import sys\n" + "".join(f"import {m}\n" for m in sorted(mods)) + \
        "print('zenoh' in sys.modules, 'pymavlink' in sys.modules)"
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True)
    assert out.returncode == 0, out.stderr
    # the simulator writes tlogs through eonav.nav, so pymavlink is allowed there only lazily: never at import
    assert out.stdout.split() == ["False", "False"]


def test_nav_and_bus_schema_do_not_load_zenoh():
    code = "import sys, eonav.nav.mavlink_in, eonav.nav.mavlink_out, eonav.nav.timesync, eonav.bus.schema, " \
        "eonav.bus.keys\nprint('zenoh' in sys.modules)"
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True)
    assert out.returncode == 0, out.stderr
    assert out.stdout.strip() == "False"


def test_the_wheel_installs_only_eonav():
    cfg = tomllib.loads((ROOT / "pyproject.toml").read_text())["tool"]["setuptools"]
    packages = set(cfg["packages"])
    assert all(p == "eonav" or p.startswith("eonav.") for p in packages), packages
    assert cfg["package-dir"] == {"eonav.services": "services"}
    # every package folder of the tree is listed (a forgotten one would be missing from the wheel)
    on_disk = {".".join(["eonav", *p.parent.relative_to(ROOT / "eonav").parts]) for p in (ROOT / "eonav").rglob("__init__.py")}
    assert on_disk | {"eonav.services"} == packages


def test_cli_help_is_light():
    code = "import sys\nfrom eonav.app.cli import build_parser\nbuild_parser()\nprint(sorted(m for m in ('zenoh', 'cv2', 'scipy') if m in sys.modules))"
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True)
    assert out.returncode == 0, out.stderr
    assert out.stdout.strip() == "[]"
