"""``eonav bench locate|fuse|pipeline|soak``: benchmarks that print figures."""
from __future__ import annotations

import importlib

TARGETS = {"locate": "eonav.app.bench_locate", "fuse": "eonav.app.bench_fuse", "pipeline": "eonav.app.bench_pipeline",
           "soak": "eonav.app.bench_soak"}


def add_arguments(p) -> None:
    sub = p.add_subparsers(dest="bench", metavar="BENCH", required=True)
    for name, mod in TARGETS.items():
        sp = sub.add_parser(name, help=f"{name} benchmark")
        sp.set_defaults(_bench_module=mod)
        importlib.import_module(mod).add_arguments(sp)


def run(args) -> int:
    return importlib.import_module(args._bench_module).run(args)
