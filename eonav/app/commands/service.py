"""``eonav service NAME [args...]``: run ``eonav.services.NAME`` in the foreground (the remaining arguments go
to the service's own parser, e.g. ``eonav service camera_ingest --source flight.mp4 --help``).

The same as ``python -m eonav.services.NAME ...``: the module's ``if __name__ == "__main__"`` block is run
with ``runpy`` (``sys.argv`` set to the service's arguments), so every service works here without a
special entry point."""
from __future__ import annotations

import argparse


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("name", metavar="NAME", help="service module: eonav.services.NAME (or a dotted module path)")
    p.add_argument("service_args", nargs=argparse.REMAINDER, metavar="ARGS",
                   help="arguments passed to the service (try: eonav service NAME --help)")


def run(args) -> int:
    import runpy
    import sys

    from eonav import InputError
    from eonav.app.launcher import _module_path, module_exists

    module = _module_path(args.name)
    if not module_exists(module):
        import difflib
        names = available()
        close = difflib.get_close_matches(args.name, names, n=1)
        hint = f"did you mean {close[0]!r}? " if close else ""
        raise InputError(f"no service {args.name!r} (no module {module}); {hint}services: {', '.join(names)}, "
                         f"or a dotted module path")
    rest = list(args.service_args)
    if rest and rest[0] == "--":
        rest = rest[1:]
    old_argv = sys.argv
    sys.argv = [f"eonav service {args.name}", *rest]
    try:
        runpy.run_module(module, run_name="__main__", alter_sys=True)
    except SystemExit as e:
        code = e.code
        if code is None:
            return 0
        if isinstance(code, int):
            return code
        print(code, file=sys.stderr)
        return 1
    finally:
        sys.argv = old_argv
    return 0


def available() -> list[str]:
    import pkgutil
    try:
        from eonav import services
    except ImportError:
        return []
    return sorted(m.name for m in pkgutil.iter_modules(services.__path__) if not m.name.startswith("_"))
