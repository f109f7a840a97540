"""``eonav replay IN.mcap``: the replay service (``eonav.recording.replayer``) in the foreground."""
from __future__ import annotations

import argparse


def add_arguments(p: argparse.ArgumentParser) -> None:
    from eonav.bus.node import add_common_arguments
    from eonav.recording.replayer import add_arguments as replayer_arguments
    replayer_arguments(p)
    add_common_arguments(p, "replay")


def run(args) -> int:
    import logging
    from eonav.bus.node import run_node
    from eonav.recording.replayer import body
    logging.getLogger().setLevel(args.log_level.upper())
    return run_node("replay", args, body)
