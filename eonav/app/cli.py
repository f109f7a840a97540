"""``eonav`` command line: a thin dispatcher. Each subcommand lives in its own module exposing
``add_arguments(parser)`` and ``run(args) -> int``; those modules import heavy libraries (numpy, cv2,
zenoh) only inside ``run`` so that ``eonav --help`` is instant."""
from __future__ import annotations

import argparse
import importlib
import logging
import sys

COMMANDS = {
    "locate": ("eonav.app.commands.locate", "range map from a pair file (docs/pair-file.md)"),
    "fuse": ("eonav.app.commands.fuse", "fused range maps of a sequence of posed frames (docs/pair-file.md)"),
    "sim": ("eonav.sim.command", "render simulated scenes and flights with ground truth"),
    "bench": ("eonav.app.commands.bench", "benchmarks that print figures (locate, pipeline)"),
    "run": ("eonav.app.commands.run", "start the whole pipeline (embedded router + all services)"),
    "service": ("eonav.app.commands.service", "start one service in the foreground"),
    "record": ("eonav.app.commands.record", "record the bus into an MCAP file (raw + Foxglove channels)"),
    "replay": ("eonav.app.commands.replay", "put the raw channels of MCAP recordings back on the bus"),
    "acl": ("eonav.app.commands.acl", "access-control files: users, router and session configs (eonav.bus.acl)"),
}


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="eonav", description="Passive electro-optical obstacle ranging for aircraft.")
    p.add_argument("-v", "--verbose", action="count", default=0, help="more logging (-v info, -vv debug)")
    # -v also after the command (``eonav run -v``); SUPPRESS keeps a count given before it
    verbose = argparse.ArgumentParser(add_help=False)
    verbose.add_argument("-v", "--verbose", action="count", default=argparse.SUPPRESS,
                         help="more logging (-v info, -vv debug)")
    sub = p.add_subparsers(dest="command", metavar="COMMAND")
    for name, (mod, help_text) in COMMANDS.items():
        sp = sub.add_parser(name, help=help_text, description=help_text, parents=[verbose])
        sp.set_defaults(_module=mod)
        importlib.import_module(mod).add_arguments(sp)
    return p


def main(argv=None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    if not getattr(args, "_module", None):
        parser.print_help()
        return 2
    level = [logging.WARNING, logging.INFO, logging.DEBUG][min(args.verbose, 2)]
    logging.basicConfig(level=level, format="%(asctime)s %(levelname)s %(name)s: %(message)s")
    from eonav import EonavError
    try:
        return int(importlib.import_module(args._module).run(args) or 0)
    except EonavError as e:
        print(f"eonav {args.command}: error: {e}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        return 130


if __name__ == "__main__":
    sys.exit(main())
