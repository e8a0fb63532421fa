"""``framegate echo SERVICE/BUFFER``: each new element's metadata fields and payload summary.

Like ``ros2 topic echo``: it observes (never slows the producer), fetches each element it
is told about, and prints its decoded metadata; ``--field NAME`` prints one field per line,
``--json`` one JSON object per element (JSON Lines) with numbers as numbers.
"""

from __future__ import annotations

import argparse
import json
import sys
from typing import Any

from middleware import OBSERVE_QUEUE_MAX, FramegateError, Node, Notification, printable
from services.lib.argtypes import did_you_mean, positive_float, positive_int, queue_size

from ._common import command_parser, exit_on_sigterm, format_ns, network, notifications
from ._fields import decode_metadata, field_value, flat_names, payload_summary
from ._target import add_timeout_argument, observer, print_json_line, resolve

DEFAULT_QUEUE = 10


def register(subparsers: Any) -> None:
    parser = command_parser(
        subparsers,
        "echo",
        "print each new element of a buffer: decoded metadata fields and a payload summary "
        "(observing: never slows the producer)",
        json_flag=True,
    )
    parser.add_argument("target", metavar="SERVICE/BUFFER", help="the buffer, e.g. camera/images")
    parser.add_argument(
        "--field",
        metavar="NAME",
        action="append",
        help="print only this metadata field (dotted for nested ones: camera.fx_px); "
        "repeat it for several, printed on one line in that order",
    )
    parser.add_argument("--count", type=positive_int, metavar="K", help="stop after K elements")
    parser.add_argument("--duration", type=positive_float, metavar="S", help="stop after S s")
    parser.add_argument(
        "--queue",
        type=queue_size(OBSERVE_QUEUE_MAX),
        default=DEFAULT_QUEUE,
        metavar="N",
        help=f"notification queue size (default {DEFAULT_QUEUE}); a full one skips elements",
    )
    add_timeout_argument(parser)
    parser.epilog = "--json prints one JSON object per element (JSON Lines)."
    parser.set_defaults(func=run)


def element_json(note: Notification, payload: bytes, metadata: bytes) -> dict[str, Any]:
    kind, fields = decode_metadata(metadata)
    return {
        "timestamp_ns": note.timestamp_ns,
        "time": format_ns(note.timestamp_ns),
        "seq": note.seq,
        "missed": note.missed,
        "kind": kind,
        "fields": fields,
        "payload_bytes": len(payload),
        "payload": payload_summary(payload, kind, fields),
    }


def _text(value: Any) -> str:
    """A field's value for one line of a terminal: a producer's text may hold a newline (a
    forged ``error:`` line), an escape sequence or a bidi override; each is written as its
    escape (``--json`` escapes them as JSON does)."""
    if isinstance(value, str):
        return printable(value, len(value))
    return json.dumps(value)


def _print_element(row: dict[str, Any]) -> None:
    missed = f"  (missed {row['missed']} before this)" if row["missed"] else ""
    lines = [
        "---",
        f"time: {row['time']}  timestamp_ns: {row['timestamp_ns']}  seq: {row['seq']}{missed}",
        f"kind: {_text(row['kind'])}",
    ]
    lines += [f"{name}: {_text(value)}" for name, value in row["fields"].items()]
    lines.append(f"payload: {row['payload']}")
    print("\n".join(lines), flush=True)


def _field(row: dict[str, Any], name: str) -> Any:
    """One metadata field of an element's row; FramegateError naming the fields it has."""
    try:
        return field_value(row["fields"], name)
    except KeyError:
        hint = did_you_mean(name, flat_names(row["fields"]))
        raise FramegateError(
            f"{row['kind']} metadata has no field {name!r}{hint}; "
            f"it has: {', '.join(flat_names(row['fields'])) or 'none'}"
        ) from None


def run(args: argparse.Namespace) -> int:
    exit_on_sigterm()
    shown = came = 0
    with Node(network=network(args)) as node:
        resolve(node, args.target, args.timeout)
        sub = observer(node, args.target, args.queue, args.timeout)
        if not args.json and args.field is None:
            print(f"echoing {sub.name}; Ctrl-C to stop", file=sys.stderr, flush=True)
        try:
            for note in notifications(sub, args.duration):
                came += 1
                try:
                    element = sub.fetch(note, timeout_s=max(2.0, args.timeout))
                except FramegateError as exc:  # evicted before we asked: say so, go on
                    print(f"warning: element {note.timestamp_ns}: {exc}", file=sys.stderr)
                    continue
                row = element_json(note, element.payload, element.metadata)
                shown += 1
                if args.field is not None:
                    values = [_field(row, name) for name in args.field]
                    if args.json:
                        print_json_line(values[0] if len(values) == 1 else values)
                    else:
                        print(" ".join(_text(v) for v in values), flush=True)
                elif args.json:
                    print_json_line(row)
                else:
                    _print_element(row)
                if args.count is not None and shown >= args.count:
                    break
        except KeyboardInterrupt:
            pass
    if came == 0:
        # A buffer put once (camera/info) or quiet: echo shows only what is put from now on.
        print(
            f"note: no new element of {args.target} came; echo shows what is put from now on "
            f"(framegate query {args.target} --last 1 shows its newest)",
            file=sys.stderr,
            flush=True,
        )
    return 0
