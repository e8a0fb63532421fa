"""Subscribe to a buffer with flow control: ``python examples/subscribe.py example/counter``.

A notification stays in this subscriber's queue until it is taken, so a slow consumer
(``--delay-s``) holds the producer back instead of losing elements.
"""

from __future__ import annotations

import argparse
import math
import signal
import sys
import time

from middleware import (
    FramegateError,
    NetworkConfig,
    Node,
    NotFoundError,
    add_network_arguments,
    network_from_args,
)


def main(network: NetworkConfig, target: str, *, count: int, queue: int, delay_s: float) -> int:
    with Node(network=network) as node:
        try:
            sub = node.subscribe(target, queue_size=queue, wait_s=5.0)
        except NotFoundError:
            service = target.split("/", 1)[0]
            if service in node.live_services():
                raise  # live, but no such buffer: the error names what it offers
            print(f"error: {_why_silent(node, service)}", file=sys.stderr)
            return 1
        taken = 0
        while taken < count:
            note = sub.take(timeout_s=10.0)
            if note is None:
                print(
                    f"error: no notification within 10 s; {_why_silent(node, sub.service)}",
                    file=sys.stderr,
                )
                return 1
            element = sub.fetch(note)
            print(f"took {note.timestamp_ns}: {shown(element.payload)}", flush=True)
            taken += 1
            time.sleep(delay_s)  # stands in for the work done on each element
    return 0


def _why_silent(node: Node, service: str) -> str:
    """What the user can do about a subscription that got nothing: is its service live?"""
    if service in node.live_services():
        return f"service {service!r} is live but put nothing (is it paused or finished?)"
    return (
        f"service {service!r} is not live (is python examples/offer.py running, "
        "and does --connect reach it?)"
    )


def positive(text: str) -> int:
    """A flag's count or size: an integer >= 1."""
    value = int(text)
    if value < 1:
        raise argparse.ArgumentTypeError(f"must be an integer >= 1, got {text!r}")
    return value


def seconds(text: str) -> float:
    """A flag's duration: a finite number >= 0 (``nan`` or ``-1`` is refused as it is parsed)."""
    value = float(text)
    if not math.isfinite(value) or value < 0:
        raise argparse.ArgumentTypeError(f"must be a number of seconds >= 0, got {text!r}")
    return value


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
        prog="subscribe", description=__doc__.splitlines()[0].replace("``", "")
    )
    add_network_arguments(parser)
    parser.add_argument("target", nargs="?", default="example/counter", help="SERVICE/BUFFER")
    parser.add_argument("--count", type=positive, default=10, help="notifications to take (10)")
    parser.add_argument("--queue", type=positive, default=2, help="queue size N (2)")
    parser.add_argument("--delay-s", type=seconds, default=0.0, help="work per element (0 s)")
    args = parser.parse_args()
    try:
        code = main(
            network_from_args(args),
            args.target,
            count=args.count,
            queue=args.queue,
            delay_s=args.delay_s,
        )
    except FramegateError as exc:  # e.g. the offering example is not running: one line
        print(f"error: {exc}", file=sys.stderr)
        code = 1
    except KeyboardInterrupt:
        code = 0
    raise SystemExit(code)
