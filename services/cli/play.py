"""``framegate play``: offer recorded buffers again, at the recorded pace, then keep serving.

Buffering rule: play is a lossless source, so it waits (``put(..., wait_s=...)``) while a
flow-controlled subscriber's queue is full instead of dropping elements; after such a wait
it keeps the recorded spacing from there rather than bursting to catch up.
"""

from __future__ import annotations

import argparse
import sys
import threading
import time
from contextlib import ExitStack
from dataclasses import dataclass, replace
from pathlib import Path
from typing import TYPE_CHECKING, Any

from middleware import (
    ConfigError,
    DataObject,
    FlowControlRefused,
    FramegateError,
    NetworkConfig,
    Node,
    Producer,
    Retention,
    check_name,
)
from services.lib.argtypes import did_you_mean, non_negative_float

from ._common import command_parser, counted, exit_on_sigterm, format_ns, network, recording_input
from ._target import print_json_line, unreachable

if TYPE_CHECKING:
    from services.tools.bag import Bag, RecordedBuffer

# How long one put waits for a flow-controlled subscriber before trying again (so Ctrl-C
# is honoured); each retry shows up once in the buffer's `refused` counter.
PUT_WAIT_S = 1.0
# Later than this behind schedule after a put, the schedule moves instead of bursting.
REANCHOR_S = 0.05


def register(subparsers: Any) -> None:
    parser = command_parser(
        subparsers,
        "play",
        "offer the buffers of an MCAP recording again, then keep answering queries",
        json_flag=True,
    )
    parser.add_argument("file", type=Path, metavar="FILE.mcap", help="made by framegate record")
    parser.add_argument(
        "--rate",
        type=non_negative_float,
        default=1.0,
        metavar="R",
        help="pace factor (default 1: as recorded; 0: as fast as flow control allows)",
    )
    parser.add_argument("--fast", action="store_true", help="same as --rate 0")
    parser.add_argument(
        "--loop",
        action="store_true",
        help="play again and again, each pass shifted later by the span played, as --rebase",
    )
    parser.add_argument(
        "--as-service",
        metavar="NAME",
        help="offer every buffer under this service name instead of the recorded one",
    )
    parser.add_argument(
        "--rebase",
        action="store_true",
        help=(
            "shift timestamps so the first element is now: keys, metadata timestamps and "
            "the sample times in gyro payloads all move by the same amount"
        ),
    )
    parser.add_argument(
        "--only",
        action="append",
        metavar="SERVICE/BUFFER",
        help="play only this recorded buffer (repeatable)",
    )
    parser.add_argument(
        "--keep-all",
        action="store_true",
        help="keep every element (default: the retention the buffer had when recorded); with "
        "--loop, as many as the recording holds",
    )
    parser.add_argument(
        "--start-delay",
        type=non_negative_float,
        default=0.5,
        metavar="S",
        help="seconds between offering and the first element, for subscribers to register "
        "(default 0.5)",
    )
    parser.add_argument(
        "--exit-when-done",
        action="store_true",
        help="exit after the last element instead of serving queries until Ctrl-C",
    )
    parser.epilog = (
        "--json prints JSON Lines: an 'offered' event, then a 'done' event. Pacing starts at "
        "the recording's start: each buffer's newest element at the start (a camera "
        "description put long before) is put at once. Looping shifts each pass by the span "
        "played plus one mean interval, so timestamps keep rising."
    )
    parser.set_defaults(func=run)


@dataclass
class _Played:
    recorded: RecordedBuffer
    service: str
    buffer: str
    producer: Producer | None = None

    @property
    def name(self) -> str:
        return f"{self.service}/{self.buffer}"


def _select(bag: Bag, args: argparse.Namespace) -> list[_Played]:
    chosen = list(bag.buffers)
    if args.only:
        names = {b.name: b for b in bag.buffers}
        missing = [n for n in args.only if n.strip("/") not in names]
        if missing:
            raise ConfigError(
                f"{args.file} has no buffer {missing[0]!r}"
                f"{did_you_mean(missing[0].strip('/'), names, quote=True)}; "
                f"it holds: {', '.join(names)}"
            )
        chosen = [names[n.strip("/")] for n in dict.fromkeys(args.only)]
    service = check_name(args.as_service, "service") if args.as_service else None
    played = [_Played(b, service or b.service, b.buffer) for b in chosen]
    seen: set[str] = set()
    for p in played:
        if p.name in seen:
            raise ConfigError(
                f"two recorded buffers would both be offered as {p.name}; "
                "drop --as-service or pick buffers with --only"
            )
        seen.add(p.name)
    return played


def _retention(recorded: RecordedBuffer, keep_all: bool, loop: bool = False) -> Retention:
    if not keep_all:
        return recorded.retention
    if loop:
        # A loop never ends: keeping every pass grew without bound (`--loop --fast
        # --keep-all` of a 78 MB recording: 838 MB in 30 s). One pass's worth is every
        # element the recording holds; a count the file does not give falls back to the
        # recorded retention.
        if not recorded.count:
            return recorded.retention
        return replace(
            recorded.retention, max_count=recorded.count, max_bytes=None, max_age_ns=None
        )
    return replace(recorded.retention, max_count=None, max_bytes=None, max_age_ns=None)


def _offer(
    stack: ExitStack, net: NetworkConfig, played: list[_Played], keep_all: bool, loop: bool
) -> None:
    nodes: dict[str, Node] = {}
    for p in played:
        if p.service not in nodes:
            node = stack.enter_context(Node(p.service, net))
            if p.service in node.live_services(timeout_s=0.5):
                raise ConfigError(
                    f"a service named {p.service!r} is already live; stop it, "
                    "or play under another name with --as-service NAME"
                )
            nodes[p.service] = node
        p.producer = nodes[p.service].offer(
            p.buffer, kind=p.recorded.kind, retention=_retention(p.recorded, keep_all, loop)
        )


def _put(producer: Producer, element: DataObject) -> None:
    while True:
        try:
            producer.put(element.timestamp_ns, element.payload, element.metadata, wait_s=PUT_WAIT_S)
            return
        except FlowControlRefused:
            continue  # a flow-controlled subscriber is still busy: a lossless source waits


class _Skips:
    """Elements of the file that its buffer refused to store (a damaged or hand-made file:
    metadata that is not XML, a stamp out of order): each skipped and counted, the rest
    played; one warning per buffer and reason."""

    def __init__(self) -> None:
        self.counts: dict[str, int] = {}

    def skip(self, name: str, timestamp_ns: int | None, exc: FramegateError) -> None:
        key = f"{name}: {type(exc).__name__}"
        if key not in self.counts:
            which = "an element" if timestamp_ns is None else f"the element stamped {timestamp_ns}"
            print(
                f"warning: {name}: skipped {which}: {exc} (further ones like it are counted, "
                "not shown)",
                file=sys.stderr,
                flush=True,
            )
        self.counts[key] = self.counts.get(key, 0) + 1


def _play(
    bag: Bag, played: list[_Played], rate: float, args: argparse.Namespace, skips: _Skips
) -> int:
    """Put every element (forever with --loop); return how many were put."""
    from services.tools.bag import recording_started_ns, shift_element

    # Pace from the recording's start: what is stamped before it (each buffer's newest
    # element at the start, e.g. a camera description put once an hour earlier) is put at
    # once, not after the hour between its stamp and the recording.
    started_ns = recording_started_ns(bag.metadata)
    by_channel = {p.recorded.channel_id: p for p in played}
    count = 0
    t0: int | None = None
    wall0 = 0.0
    rebase_ns = 0
    period_ns = 0
    passes = 0

    def undecodable(recorded: RecordedBuffer, exc: FramegateError) -> None:
        skips.skip(by_channel[recorded.channel_id].name, None, exc)

    while True:
        first = last = None
        n = 0
        spans: dict[int, tuple[int, int]] = {}  # per buffer: first and last stamp of the pass
        for recorded, element in bag.elements([p.recorded for p in played], undecodable):
            if t0 is None:
                t0, wall0 = element.timestamp_ns, time.monotonic()
                if started_ns is not None:
                    t0 = max(t0, started_ns)
                rebase_ns = time.time_ns() - t0 if args.rebase else 0
            first = max(element.timestamp_ns, t0) if first is None else first
            last, n = element.timestamp_ns, n + 1
            b_first = spans.get(recorded.channel_id, (element.timestamp_ns, 0))[0]
            spans[recorded.channel_id] = (b_first, element.timestamp_ns)
            loop_ns = passes * period_ns
            due = 0.0
            if rate > 0:
                paced_ns = max(element.timestamp_ns, t0)
                due = wall0 + (paced_ns + loop_ns - t0) / 1e9 / rate
                _sleep_until(due)
            p = by_channel[recorded.channel_id]
            assert p.producer is not None
            try:
                _put(p.producer, shift_element(element, recorded.kind, rebase_ns + loop_ns))
                count += 1
            except FramegateError as exc:  # this element only: the rest is played
                skips.skip(p.name, element.timestamp_ns, exc)
            late = time.monotonic() - due
            if rate > 0 and late > REANCHOR_S:
                wall0 += late
        passes += 1
        if not args.loop or first is None or last is None:
            return count
        if passes == 1:
            # Each pass is shifted by the span played plus one mean interval, so each
            # buffer's timestamps rise (at least by its own span: a newest element at the
            # start is stamped before the recording's start).
            gap = max((last - first) // (n - 1) if n > 1 else 1_000_000, 1)
            longest = max(b_last - b_first for b_first, b_last in spans.values())
            period_ns = max(last - first, longest) + gap


def _sleep_until(due: float) -> None:
    while (remaining := due - time.monotonic()) > 0:
        time.sleep(min(remaining, 0.2))


def run(args: argparse.Namespace) -> int:
    from services.tools.bag import open_bag  # imported here: only record and play need MCAP

    args.file = recording_input(args.file)  # `play run`: the run.mcap `record -o run` wrote
    rate = 0.0 if args.fast else args.rate
    if rate < 0:
        raise ConfigError(
            f"--rate {args.rate}: use a positive factor, or 0 for as fast as possible"
        )
    exit_on_sigterm()
    started = time.monotonic()
    with open_bag(args.file) as bag, ExitStack() as stack:
        integrity = bag.integrity
        if not integrity.complete:  # a cut-short or damaged file: say what was recovered
            end = format_ns(integrity.end_ns) if integrity.end_ns is not None else "its start"
            print(f"warning: {args.file}: {integrity.describe(end)}", file=sys.stderr, flush=True)
        played = _select(bag, args)
        net = network(args)
        if bad := unreachable(net):
            # Played anyway (a player may start before its listeners, as `pub` does), but
            # "offering" alone would say nothing of where it went.
            message = f"warning: cannot reach {bad}; nobody there gets what is played"
            print(message, file=sys.stderr, flush=True)
        _offer(stack, net, played, args.keep_all, args.loop)
        _event(
            args,
            {
                "event": "offered",
                "file": str(args.file),
                "buffers": [
                    {
                        "name": p.name,
                        "recorded_as": p.recorded.name,
                        "kind": p.recorded.kind,
                        "elements": p.recorded.count,
                    }
                    for p in played
                ],
            },
        )
        try:
            _sleep_until(time.monotonic() + max(0.0, args.start_delay))
            skips = _Skips()
            count = _play(bag, played, rate, args, skips)
            _event(
                args,
                {
                    "event": "done",
                    "played": count,
                    "skipped": skips.counts,
                    "elapsed_s": round(time.monotonic() - started, 3),
                    "serving": not args.exit_when_done,
                },
            )
            if not args.exit_when_done:
                threading.Event().wait()
        except KeyboardInterrupt:
            pass
    return 0


def _event(args: argparse.Namespace, event: dict[str, Any]) -> None:
    if args.json:
        print_json_line(event)
        return
    if event["event"] == "offered":
        for b in event["buffers"]:
            print(
                f"offering {b['name']} ({b['kind']}, {counted(b['elements'], 'element')}) from "
                f"{args.file}",
                flush=True,
            )
    elif event["event"] == "done":
        then = "serving queries until Ctrl-C" if event["serving"] else "exiting"
        skipped = sum(event["skipped"].values())
        also = f" ({skipped} skipped: see the warnings above)" if skipped else ""
        print(
            f"played {counted(event['played'], 'element')} in {event['elapsed_s']:.1f} s"
            f"{also}; {then}",
            flush=True,
        )
