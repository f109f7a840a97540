"""``eonav record OUT.mcap``: the recorder service (``eonav.recording.recorder``) in the foreground."""
from __future__ import annotations

import argparse


def add_arguments(p: argparse.ArgumentParser) -> None:
    from eonav.bus.node import add_common_arguments
    from eonav.recording.recorder import add_arguments as recorder_arguments
    recorder_arguments(p)
    add_common_arguments(p, "recorder")


def run(args) -> int:
    import logging
    from eonav.bus.node import run_node
    from eonav.recording.recorder import body
    logging.getLogger().setLevel(args.log_level.upper())
    return run_node("recorder", args, body)
