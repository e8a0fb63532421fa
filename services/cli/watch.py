"""``framegate watch``: subscribe to a buffer and print each notification as it is taken.

Buffering rule: by default watch *observes* (``SubscriptionMode.OBSERVE``): a terminal
looking at a running robot must never hold its camera back, so when watch's queue is full
it misses notifications and says how many. ``--flow-control`` makes it a real consumer
(``FLOW``): while its queue is full the producer is refused, and with ``--delay`` it is a
deliberately slow one, so the producer's ``refused`` counter in ``info`` rises.
"""

from __future__ import annotations

import argparse
import time
from typing import Any

from middleware import (
    FLOW_QUEUE_MAX,
    OBSERVE_QUEUE_MAX,
    ConfigError,
    Node,
    Notification,
    SubscriptionMode,
)
from services.lib.argtypes import non_negative_float, positive_float, positive_int, queue_size

from ._common import (
    command_parser,
    exit_on_sigterm,
    format_bytes,
    format_ns,
    network,
    notifications,
)
from ._target import add_timeout_argument, print_json_line, resolve

DEFAULT_QUEUE = 10


def register(subparsers: Any) -> None:
    parser = command_parser(
        subparsers,
        "watch",
        "print a buffer's notifications as they arrive (observing, unless --flow-control)",
        json_flag=True,
    )
    parser.add_argument("target", metavar="SERVICE/BUFFER", help="the buffer, e.g. camera/images")
    parser.add_argument(
        "--queue",
        type=queue_size(OBSERVE_QUEUE_MAX),
        default=DEFAULT_QUEUE,
        metavar="N",
        help=f"notification queue size (default {DEFAULT_QUEUE})",
    )
    parser.add_argument(
        "--delay",
        type=non_negative_float,
        default=0.0,
        metavar="S",
        help="sleep S seconds after taking each notification (a deliberately slow consumer)",
    )
    parser.add_argument(
        "--flow-control",
        action="store_true",
        help="take part in flow control: while this queue is full the producer is refused",
    )
    parser.add_argument(
        "--count", type=positive_int, metavar="K", help="stop after K notifications"
    )
    parser.add_argument("--duration", type=positive_float, metavar="S", help="stop after S seconds")
    add_timeout_argument(parser)
    parser.epilog = "--json prints one JSON object per line (JSON Lines), then a summary line."
    parser.set_defaults(func=run)


def _check(args: argparse.Namespace) -> None:
    if args.flow_control and args.queue > FLOW_QUEUE_MAX:
        raise ConfigError(
            f"--queue {args.queue}: at most {FLOW_QUEUE_MAX} with --flow-control (a producer "
            "keeps every un-acked notification of a flow-controlled subscriber, and one "
            "subscriber may hold at most half of its budget)"
        )
    if args.delay < 0:
        raise ConfigError(f"--delay {args.delay}: must be >= 0 seconds")
    if args.count is not None and args.count < 1:
        raise ConfigError(f"--count {args.count}: must be >= 1")
    if args.duration is not None and args.duration <= 0:
        raise ConfigError(f"--duration {args.duration}: must be > 0 seconds")


def _note_json(note: Notification) -> dict[str, Any]:
    element = note.element
    return {
        "event": "notification",
        "timestamp_ns": note.timestamp_ns,
        "time": format_ns(note.timestamp_ns),
        "seq": note.seq,
        "missed": note.missed,
        "inline": element is not None,
        "payload_bytes": len(element.payload) if element is not None else None,
    }


def _print_note(note: Notification) -> None:
    inline = f"  inline {format_bytes(len(note.element.payload))}" if note.element else ""
    missed = f"  MISSED {note.missed}" if note.missed else ""
    print(
        f"{format_ns(note.timestamp_ns)}  {note.timestamp_ns}  seq {note.seq}{missed}{inline}",
        flush=True,
    )


def run(args: argparse.Namespace) -> int:
    _check(args)
    mode = SubscriptionMode.FLOW if args.flow_control else SubscriptionMode.OBSERVE
    exit_on_sigterm()
    received = 0
    with Node(network=network(args)) as node:
        resolve(node, args.target, args.timeout)
        sub = node.subscribe(
            args.target, queue_size=args.queue, mode=mode, wait_s=max(2.0, args.timeout)
        )
        if not args.json:
            print(
                f"watching {sub.name} ({mode.value}, queue {args.queue}"
                f"{f', delay {args.delay:g} s' if args.delay else ''}); Ctrl-C to stop",
                flush=True,
            )
        try:
            for note in notifications(sub, args.duration):
                received += 1
                if args.json:
                    print_json_line(_note_json(note))
                else:
                    _print_note(note)
                if args.delay:
                    time.sleep(args.delay)
                if args.count is not None and received >= args.count:
                    break
        except KeyboardInterrupt:
            pass
        missed = sub.missed_total
    summary = {
        "event": "summary",
        "target": args.target,
        "mode": mode.value,
        "queue_size": args.queue,
        "received": received,
        "missed": missed,
    }
    if args.json:
        print_json_line(summary)
    else:
        print(f"received {received} notifications, missed {missed}")
    return 0
