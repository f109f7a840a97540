"""``eonav bench locate|pipeline``: benchmarks that print figures."""
from __future__ import annotations

import importlib

TARGETS = {"locate": "eonav.bench_locate", "pipeline": "eonav.bench_pipeline"}


def add_arguments(p) -> None:
    sub = p.add_subparsers(dest="bench", metavar="BENCH", required=True)
    for name, mod in TARGETS.items():
        sp = sub.add_parser(name, help=f"{name} benchmark")
        sp.set_defaults(_bench_module=mod)
        try:
            importlib.import_module(mod).add_arguments(sp)
        except ImportError as e:  # a benchmark whose module is not installed in this build
            sp.set_defaults(_bench_missing=str(e))


def run(args) -> int:
    if getattr(args, "_bench_missing", None):
        from .. import EonavError
        raise EonavError(f"benchmark {args.bench} unavailable: {args._bench_missing}")
    return importlib.import_module(args._bench_module).run(args)
