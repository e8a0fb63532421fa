"""``framegate pub SERVICE/BUFFER --kind K``: publish test elements under a temporary service.

Like ``ros2 topic pub``: it starts a service named SERVICE for as long as it runs, offers
BUFFER with metadata of kind K, puts ``--count`` schema-valid test elements at ``--rate``
(stamped with this process's clock), keeps answering queries for ``--linger`` seconds so
that subscribers can fetch the last one, then ends. SERVICE must not be live already.
``--json`` prints JSON Lines: a ``published`` event per element, then a ``done`` event.
"""

from __future__ import annotations

import argparse
import struct
import sys
import threading
import time
from collections.abc import Callable
from typing import Any

from middleware import ConfigError, Node, Producer, make_metadata, now_ns, split_target
from services.lib.argtypes import (
    non_negative_float,
    non_negative_int,
    positive_float,
    positive_int,
    positive_rate,
)

from ._common import command_parser, counted, network, stop_on_signals
from ._target import print_json_line, unreachable

WIDTH_PX, HEIGHT_PX = 64, 48
EXPOSURE_NS = 10_000_000
GYRO_RECORD = struct.Struct("<qddd")  # timestamp_ns, x, y, z rad/s (schemas/gyro.xsd)


def _generic(i: int, t: int, _rate_hz: float) -> tuple[bytes, bytes]:
    text = f"test element {i}"
    return text.encode(), make_metadata("generic", t, {"index": i, "text": text})


def _frame(i: int, t: int, _rate_hz: float) -> tuple[bytes, bytes]:
    # A moving gradient, so that consecutive frames differ.
    payload = bytes((x + y + i) % 256 for y in range(HEIGHT_PX) for x in range(WIDTH_PX))
    fields = {
        "frame_id": i,
        "exposure_start_ns": t,
        "exposure_ns": EXPOSURE_NS,
        "encoding": "mono8",
        "width_px": WIDTH_PX,
        "height_px": HEIGHT_PX,
    }
    return payload, make_metadata("frame", t, fields)


def _gyro(_i: int, t: int, rate_hz: float) -> tuple[bytes, bytes]:
    fields = {"count": 1, "first_ns": t, "last_ns": t, "rate_hz": rate_hz, "layout": "i8,f8,f8,f8"}
    return GYRO_RECORD.pack(t, 0.0, 0.0, 0.0), make_metadata("gyro", t, fields)


def _decision(i: int, t: int, _rate_hz: float) -> tuple[bytes, bytes]:
    fields = {
        "frame_timestamp_ns": t,
        "frame_id": i,
        "blur_px": 0.0,
        "quality": 1.0,
        "load": 0.0,
        "accepted": True,
        "reason": "test",
        "policy": "paper",
        "b0_px": 5.0,
        "latency_ns": 0,
    }
    return b"", make_metadata("decision", t, fields)


def _detections(i: int, t: int, _rate_hz: float) -> tuple[bytes, bytes]:
    from services.lib.messages import detections_metadata

    return b"", detections_metadata(t, i, "pub", 0, [])


# kind -> (index, timestamp_ns, rate_hz) -> (payload, metadata)
KINDS: dict[str, Callable[[int, int, float], tuple[bytes, bytes]]] = {
    "generic": _generic,
    "frame": _frame,
    "gyro": _gyro,
    "decision": _decision,
    "detections": _detections,
}


def register(subparsers: Any) -> None:
    parser = command_parser(
        subparsers,
        "pub",
        "publish test elements of a kind under a temporary service",
        json_flag=True,
    )
    parser.add_argument("target", metavar="SERVICE/BUFFER", help="the buffer to offer")
    parser.add_argument("--kind", required=True, choices=sorted(KINDS), help="metadata kind")
    parser.add_argument(
        "--count", type=positive_int, default=1, metavar="N", help="elements (default 1)"
    )
    parser.add_argument(
        "--rate", type=positive_rate, default=1.0, metavar="HZ", help="elements/s (default 1)"
    )
    parser.add_argument(
        "--wait-subscribers",
        type=non_negative_int,
        default=0,
        metavar="N",
        help="first wait (up to --timeout) until N subscribers are registered, and fail if "
        "they are not (default: wait up to 1.5 s for those listening, as ros2 topic pub "
        "does, and publish in any case)",
    )
    parser.add_argument(
        "--timeout",
        type=positive_float,
        default=10.0,
        metavar="S",
        help="how long --wait-subscribers waits (default 10)",
    )
    parser.add_argument(
        "--linger",
        type=non_negative_float,
        default=2.0,
        metavar="S",
        help="keep answering queries this long after the last element (default 2)",
    )
    parser.set_defaults(func=run)


# How long pub waits, by default, for listeners to register before its first element.
_LISTENERS_S = 1.5


def run(args: argparse.Namespace) -> int:
    service, buffer = split_target(args.target)
    make = KINDS[args.kind]
    stop = stop_on_signals()
    net = network(args)
    if bad := unreachable(net):
        # Not an error (a publisher may start before its listeners, as with `ros2 topic
        # pub`), but not silence either: "published" would say nothing of where it went.
        print(f"warning: cannot reach {bad}; nobody there gets these", file=sys.stderr, flush=True)
    with Node(service, net) as node:
        producer = node.offer(buffer, kind=args.kind)
        if not args.wait_subscribers:
            # Those already listening get the first element too, as with ``ros2 topic pub``:
            # an echo or watch started first subscribes only once the buffer is offered, and
            # missed it. So wait a moment for them (for the subscriptions already live, or
            # for one), then publish in any case.
            listening = max(1, node.live_subscriptions(producer.name))
            _wait_for(producer, listening, min(args.timeout, _LISTENERS_S), stop)
        if (
            args.wait_subscribers
            and _wait_for(producer, args.wait_subscribers, args.timeout, stop) is False
        ):
            raise ConfigError(
                f"{len(producer.subscriptions())} of {args.wait_subscribers} subscribers "
                f"registered on {producer.name} within {args.timeout:g} s"
            )
        period_s = 1.0 / args.rate
        put = 0
        last_t = 0
        # A fixed schedule, as a timer's (`ros2 topic pub -r`): the time a put and its line
        # take does not lower the rate; one that fell a period behind starts afresh (no burst).
        due = time.monotonic()
        while put < args.count and not stop.is_set():
            t = max(now_ns(), last_t + 1)
            # Numbered from 0, as the elements' own `frame_id`/`index` fields are.
            index = put
            payload, metadata = make(index, t, args.rate)
            producer.put(t, payload, metadata)
            last_t = t
            put += 1
            if args.json:
                print_json_line(
                    {"event": "published", "target": producer.name, "index": index,
                     "timestamp_ns": t, "payload_bytes": len(payload)}
                )  # fmt: skip
            else:
                print(
                    f"published {producer.name} #{index} at {t} ({len(payload)} bytes)",
                    flush=True,
                )
            if put < args.count:
                due, wait_s = next_due(due, period_s, time.monotonic())
                if wait_s > 0:
                    stop.wait(wait_s)
        _linger(stop, args.linger)
    if args.json:
        print_json_line(
            {"event": "done", "target": args.target, "kind": args.kind, "published": put}
        )
    print(
        f"published {counted(put, args.kind + ' element')} to {service}/{buffer}", file=sys.stderr
    )
    return 0


def next_due(due: float, period_s: float, now: float) -> tuple[float, float]:
    """The next put's instant after the one ``due``, and how long to wait for it: a fixed
    schedule, except that one a period or more behind starts afresh from ``now``."""
    due += period_s
    if now - due > period_s:
        return now, 0.0
    return due, max(0.0, due - now)


def _wait_for(
    producer: Producer, count: int, timeout_s: float, stop: threading.Event
) -> bool | None:
    """True once ``count`` subscriptions are registered, False after ``timeout_s``, None as
    soon as ``stop`` is set: a Ctrl-C while waiting is a stop (exit 0, nothing published),
    not "0 of 1 subscribers registered" at the end of the timeout."""
    deadline = time.monotonic() + timeout_s
    while not stop.is_set():
        left_s = deadline - time.monotonic()
        if producer.wait_for_subscribers(count, timeout_s=max(0.0, min(0.1, left_s))):
            return True
        if left_s <= 0.1:
            return False
    return None


def _linger(stop: threading.Event, seconds: float) -> None:
    if seconds > 0:
        stop.wait(seconds)
