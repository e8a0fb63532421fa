"""Offer a buffer and put one element per period: ``python examples/offer.py``.

It runs until Ctrl-C (or ``--count`` elements), at a pace a person can follow in a second
terminal (``--period-s``, 0.5 s).

The service ``example`` offers ``example/counter``. While a flow-controlled subscriber's
queue is full the put is refused; this producer may lose nothing, so it waits (``wait_s``)
instead of dropping, as a replayed log would. A camera would drop the frame and count it.
"""

from __future__ import annotations

import argparse
import itertools
import math
import signal
import sys
import time

from middleware import (
    FlowControlRefused,
    FramegateError,
    NetworkConfig,
    Node,
    add_network_arguments,
    make_metadata,
    network_from_args,
)


def main(network: NetworkConfig, *, count: int, period_s: float, wait_s: float) -> int:
    """Put ``count`` elements (0: until Ctrl-C), one per ``period_s``."""
    with Node("example", network) as node:
        counter = node.offer("counter", kind="generic")
        for i in range(count) if count else itertools.count():
            timestamp_ns = time.time_ns()
            try:
                counter.put(
                    timestamp_ns,
                    f"value {i}".encode(),
                    make_metadata("generic", timestamp_ns),
                    wait_s=wait_s,
                )
            except FlowControlRefused as exc:
                print(f"refused {i}: {exc}", flush=True)
                continue
            print(f"put {i} at {timestamp_ns}", flush=True)
            time.sleep(period_s)
    return 0


def seconds(text: str) -> float:
    """A flag's duration: a finite number >= 0 (``nan`` or ``-1`` is refused as it is parsed)."""
    value = float(text)
    if not math.isfinite(value) or value < 0:
        raise argparse.ArgumentTypeError(f"must be a number of seconds >= 0, got {text!r}")
    return value


def count(text: str) -> int:
    """A flag's count: an integer >= 0."""
    value = int(text)
    if value < 0:
        raise argparse.ArgumentTypeError(f"must be an integer >= 0, got {text!r}")
    return value


if __name__ == "__main__":
    # Ctrl-C stops it even when its parent ignores SIGINT (a job a script put in the
    # background starts that way, and Python then never raises KeyboardInterrupt).
    signal.signal(signal.SIGINT, signal.default_int_handler)
    signal.signal(signal.SIGTERM, signal.default_int_handler)  # `kill`: the same clean stop
    parser = argparse.ArgumentParser(
        prog="offer", description=__doc__.splitlines()[0].replace("``", "")
    )
    add_network_arguments(parser)
    parser.add_argument("--count", type=count, default=0, help="elements to put (0: until Ctrl-C)")
    parser.add_argument("--period-s", type=seconds, default=0.5, help="between puts (0.5 s)")
    parser.add_argument("--wait-s", type=seconds, default=5.0, help="wait when refused (5 s)")
    args = parser.parse_args()
    try:
        code = main(
            network_from_args(args), count=args.count, period_s=args.period_s, wait_s=args.wait_s
        )
    except KeyboardInterrupt:  # Ctrl-C: the way to stop it
        code = 0
    except FramegateError as exc:
        print(f"error: {exc}", file=sys.stderr)
        code = 1
    raise SystemExit(code)
