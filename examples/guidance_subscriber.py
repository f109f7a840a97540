"""Print the nearest threat from eonav's obstacle-track topic (docs/guidance.md), one line per message.

    python examples/guidance_subscriber.py --connect tcp/127.0.0.1:7447 --vehicle demo [--count N]

A line reads, e.g.:
    seq 42 ok map 0.06 s | 3 tracks | threat id 7 in 2.41 s at 48.2 m (surface 47.9 m) az +3.1 el -1.0 deg
        closing 19.9 m/s
    seq 43 stale map 0.71 s | 3 tracks | no threat
A "stale" or "no_map" status means the range maps have stopped: the tracks are only predictions (see the docs).
Ctrl-C stops it.
"""
from __future__ import annotations

import argparse
import math
import signal
import sys
import threading

from eonav.bus import keys
from eonav.bus.session import add_flag, add_session_arguments, open_session
from eonav.bus.guidance_msg import decode
from eonav.bus.schema import SchemaError


def describe(msg: dict) -> str:
    """One line for a decoded obstacle_tracks message."""
    head = f"seq {msg['seq']} {msg['status']} map {msg['map_age_s']:.2f} s | {len(msg['tracks'])} tracks"
    th = msg["nearest_threat"]
    if th is None:
        return head + " | no threat"
    return (f"{head} | threat id {th['id']} in {th['time_to_contact_s']:.2f} s at {th['distance_m']:.1f} m "
            f"(surface {th['surface_distance_m']:.1f} m) az {math.degrees(th['azimuth_frd_rad']):+.1f} "
            f"el {math.degrees(th['elevation_frd_rad']):+.1f} deg closing {th['closing_speed_mps']:.1f} m/s")


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    add_flag(p, "--vehicle", env="EONAV_VEHICLE", default="demo", help="vehicle name (key prefix eonav/<vehicle>)")
    p.add_argument("--count", type=int, default=0, help="exit after this many messages (0: run until Ctrl-C)")
    add_session_arguments(p)
    args = p.parse_args(argv)
    import zenoh

    done = threading.Event()
    for sig in (signal.SIGINT, signal.SIGTERM):           # Ctrl-C and SIGTERM stop it the same way
        signal.signal(sig, lambda *_: done.set())
    with open_session(args) as session:
        key = keys.obstacle_tracks(args.vehicle)
        # a ring: a reader that falls behind gets the newest messages and never blocks the session's receiving
        # (a full FifoChannel stalls the router's forwarding to every subscriber: docs/zenoh.md)
        sub = session.declare_subscriber(key, zenoh.handlers.RingChannel(16))

        def consume():                                    # a blocked recv() does not see signals: read here
            n = 0
            for sample in sub:                            # ends when the subscriber is undeclared
                try:
                    msg = decode(sample.payload.to_bytes())
                except SchemaError as e:
                    print(f"bad message: {e}", file=sys.stderr, flush=True)
                    continue
                print(describe(msg), flush=True)
                n += 1
                if args.count and n >= args.count:
                    break
            done.set()

        reader = threading.Thread(target=consume, name="reader", daemon=True)
        print(f"listening on {key}", flush=True)
        reader.start()
        while not done.wait(0.1):
            pass
        sub.undeclare()
        reader.join(2.0)
    return 0


if __name__ == "__main__":
    sys.exit(main())
