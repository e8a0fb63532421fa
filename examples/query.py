"""Query a buffer by time: ``python examples/query.py example/counter --range "[now(-10s)..]"``.

The range uses Zenoh's time-range syntax (``[a..b]``, open ends, ``now(-2s)``, RFC 3339,
or integer nanoseconds since the epoch).
"""

from __future__ import annotations

import argparse
import signal
import sys

from middleware import (
    FramegateError,
    NetworkConfig,
    Node,
    add_network_arguments,
    network_from_args,
)


def main(network: NetworkConfig, target: str, *, time_range: str) -> int:
    with Node(network=network) as node:
        elements = node.query(target, time_range=time_range)
        for element in elements:
            print(f"{element.timestamp_ns}: {shown(element.payload)}")
        print(f"{len(elements)} elements", flush=True)
    return 0


def shown(payload: bytes) -> str:
    """A short text payload as text; anything else (an image) by its size."""
    text = payload.decode(errors="replace")
    return repr(text) if len(payload) <= 64 and text.isprintable() else f"{len(payload)} bytes"


if __name__ == "__main__":
    # Ctrl-C stops it even when its parent ignores SIGINT (a job a script put in the
    # background starts that way, and Python then never raises KeyboardInterrupt).
    signal.signal(signal.SIGINT, signal.default_int_handler)
    signal.signal(signal.SIGTERM, signal.default_int_handler)  # `kill`: the same clean stop
    parser = argparse.ArgumentParser(
        prog="query", description=__doc__.splitlines()[0].replace("``", "")
    )
    add_network_arguments(parser)
    parser.add_argument("target", nargs="?", default="example/counter", help="SERVICE/BUFFER")
    parser.add_argument("--range", default="[now(-60s)..]", help="time range ([now(-60s)..])")
    args = parser.parse_args()
    try:
        code = main(network_from_args(args), args.target, time_range=args.range)
    except FramegateError as exc:  # a bad range, a service that is not running: one line
        print(f"error: {exc}", file=sys.stderr)
        code = 1
    except KeyboardInterrupt:
        code = 0
    raise SystemExit(code)
