"""``framegate hz``: a buffer's rate, interval jitter and bandwidth, like ``ros2 topic hz/bw``.

As ``ros2 topic hz``, the headline is the *arrival* rate: how often elements reach this
process, and min/max/std dev are of the intervals between arrivals. Beside it, named, is the
rate of the elements' *stamps* (the source's clock): the two differ while a recording is
played at another speed (``play --rate 0.5``: 15 Hz of stamps arrive at 7.5 Hz) or when a
source falls behind and catches up. A report after an interval in which nothing arrived
says so (``no new elements``, as ``ros2 topic hz`` says "no new messages") rather than
repeating the window's rate: a producer that stopped does not read as still producing.

A batch (``put_many``) arrives as one: its elements are taken together and share one
arrival instant. As ``ros2 topic hz`` counts messages, the arrival rate counts the elements
that arrived after the window's first arrival over the span from it to the last; the window
of arrivals holds ``--window`` of them (takes, not elements), so a producer whose batches
are larger than the element window still spans several arrivals.

Buffering rule: hz only observes (``SubscriptionMode.OBSERVE``), so measuring never slows
the producer. Missed notifications do not bias the numbers: both rates count sequence
numbers (every stored element gets one) over the span, and intervals are taken only between
consecutive elements.
"""

from __future__ import annotations

import argparse
import math
import time
from collections import deque
from collections.abc import Sequence
from dataclasses import dataclass
from itertools import pairwise
from typing import Any

from middleware import (
    OBSERVE_QUEUE_MAX,
    ConfigError,
    FramegateError,
    Node,
    Notification,
    Subscription,
)
from services.lib.argtypes import positive_float, positive_int, queue_size

from ._common import command_parser, exit_on_sigterm, format_bytes, network
from ._target import add_timeout_argument, observer, print_json_line, resolve

DEFAULT_WINDOW = 100
# Notifications taken at once: one arrival. Bounded so that fetching the sizes of one take
# never holds the reports back for long.
_TAKE_MAX = 1024


@dataclass(frozen=True, slots=True)
class Sample:
    seq: int
    timestamp_ns: int
    arrival_ns: int
    payload_bytes: int | None


def register(subparsers: Any) -> None:
    parser = command_parser(
        subparsers,
        "hz",
        "measure a buffer's rate, jitter and bandwidth (as an observer)",
        json_flag=True,
    )
    parser.add_argument("target", metavar="SERVICE/BUFFER", help="the buffer, e.g. camera/images")
    parser.add_argument(
        "--window",
        type=positive_int,
        default=DEFAULT_WINDOW,
        metavar="N",
        help=f"statistics over the last N elements, the rate over the last N arrivals "
        f"(default {DEFAULT_WINDOW})",
    )
    parser.add_argument("--duration", type=positive_float, metavar="S", help="stop after S seconds")
    parser.add_argument(
        "--interval",
        type=positive_float,
        default=1.0,
        metavar="S",
        help="report every S seconds (default 1)",
    )
    parser.add_argument(
        "--queue",
        type=queue_size(OBSERVE_QUEUE_MAX),
        default=100,
        metavar="N",
        help="observer queue size (default 100)",
    )
    add_timeout_argument(parser)
    parser.epilog = (
        "As ros2 topic hz, the average rate and min/max/std dev are of arrivals here; "
        "'stamps' is the rate of the elements' timestamps (the source's clock), which "
        "differs during play --rate or when a source catches up. --json prints JSON "
        "Lines (rate_hz: arrivals, stamp_rate_hz: stamps): one report per interval "
        "(new_elements: how many arrived in it; 0 prints 'no new elements' as text), the "
        "last one with event=summary."
    )
    parser.set_defaults(func=run)


def _intervals(samples: list[Sample], when: str) -> list[float]:
    """Seconds between consecutive elements (no missed one between), by ``when``."""
    return [
        (getattr(b, when) - getattr(a, when)) / 1e9
        for a, b in pairwise(samples)
        if b.seq == a.seq + 1
    ]


def arrival_rate_hz(arrivals: Sequence[tuple[int, int]]) -> float | None:
    """Elements per second from ``(arrival_ns, newest seq)`` per arrival, oldest first:
    the elements that came after the first arrival (by sequence number, so missed ones
    count) over the span from it to the last; None without a span."""
    if len(arrivals) < 2:
        return None
    (first_ns, first_seq), (last_ns, last_seq) = arrivals[0], arrivals[-1]
    if last_ns <= first_ns:
        return None
    return (last_seq - first_seq) / ((last_ns - first_ns) / 1e9)


def _arrivals(samples: list[Sample]) -> list[tuple[int, int]]:
    """One ``(arrival_ns, newest seq)`` per instant at which samples arrived together."""
    out: list[tuple[int, int]] = []
    for sample in samples:
        if out and out[-1][0] == sample.arrival_ns:
            out[-1] = (sample.arrival_ns, sample.seq)
        else:
            out.append((sample.arrival_ns, sample.seq))
    return out


def window_stats(
    samples: list[Sample], arrivals: Sequence[tuple[int, int]] | None = None
) -> dict[str, Any]:
    """Arrival rate (``rate_hz``, as ``ros2 topic hz``: over ``arrivals``, by default those
    of ``samples``), arrival-interval statistics, the stamps' rate and jitter, and
    bandwidth of a window of samples."""
    out: dict[str, Any] = {
        "window": len(samples),
        "rate_hz": None,
        "receive_rate_hz": None,  # the same as rate_hz (its name before rate_hz meant it)
        "stamp_rate_hz": None,
        "min_s": None,
        "max_s": None,
        "mean_s": None,
        "std_s": None,
        "stamp_std_s": None,
        "mean_bytes": None,
        "bandwidth_bytes_s": None,
    }
    if len(samples) >= 2:
        first, last = samples[0], samples[-1]
        elements = last.seq - first.seq
        stamp_s = (last.timestamp_ns - first.timestamp_ns) / 1e9
        out["stamp_rate_hz"] = elements / stamp_s if stamp_s > 0 else None
        if intervals := _intervals(samples, "arrival_ns"):
            mean = sum(intervals) / len(intervals)
            out["min_s"], out["max_s"], out["mean_s"] = min(intervals), max(intervals), mean
            out["std_s"] = _std(intervals, mean)
        if stamps := _intervals(samples, "timestamp_ns"):
            out["stamp_std_s"] = _std(stamps, sum(stamps) / len(stamps))
    rate = arrival_rate_hz(_arrivals(samples) if arrivals is None else arrivals)
    out["rate_hz"] = out["receive_rate_hz"] = rate
    sizes = [s.payload_bytes for s in samples if s.payload_bytes is not None]
    if sizes:
        out["mean_bytes"] = sum(sizes) / len(sizes)
        if out["rate_hz"] is not None:
            out["bandwidth_bytes_s"] = out["mean_bytes"] * out["rate_hz"]
    return out


def _std(values: list[float], mean: float) -> float:
    return math.sqrt(sum((x - mean) ** 2 for x in values) / len(values))


def _print_report(stats: dict[str, Any], missed: int, idle_s: float | None = None) -> None:
    """One report; ``idle_s``: nothing arrived during the interval, the last that many
    seconds ago (the window's numbers would describe a stream that has stopped)."""
    if idle_s is not None:
        print(f"no new elements (the last arrived {idle_s:.1f} s ago)", flush=True)
        return
    if stats["rate_hz"] is None:
        print(f"not enough elements yet (window {stats['window']}, missed {missed})", flush=True)
        return
    stamps = stats["stamp_rate_hz"]
    beside = f"  (stamps: {stamps:.3f} Hz)" if stamps is not None else ""
    print(f"average rate: {stats['rate_hz']:.3f} Hz{beside}", flush=True)
    if stats["mean_s"] is not None:
        print(
            f"\tmin: {stats['min_s']:.4f}s max: {stats['max_s']:.4f}s "
            f"std dev: {stats['std_s']:.5f}s window: {stats['window']}"
        )
    if stats["bandwidth_bytes_s"] is not None:
        print(
            f"\tbandwidth: {format_bytes(int(stats['bandwidth_bytes_s']))}/s "
            f"(mean {format_bytes(int(stats['mean_bytes']))})  missed: {missed}",
            flush=True,
        )


def run(args: argparse.Namespace) -> int:
    if args.window < 2:
        raise ConfigError(f"--window {args.window}: needs at least 2 elements")
    if args.interval <= 0 or (args.duration is not None and args.duration <= 0):
        raise ConfigError("--interval and --duration must be > 0 seconds")
    exit_on_sigterm()
    samples: deque[Sample] = deque(maxlen=args.window)
    arrivals: deque[tuple[int, int]] = deque(maxlen=args.window)
    with Node(network=network(args)) as node:
        resolve(node, args.target, args.timeout)
        sub = observer(node, args.target, args.queue, args.timeout)
        deadline = None if args.duration is None else time.monotonic() + args.duration
        next_report = time.monotonic() + args.interval
        new_elements = 0  # arrived since the last report
        try:
            while deadline is None or time.monotonic() < deadline:
                now = time.monotonic()
                if now >= next_report:
                    next_report = now + args.interval
                    _report(
                        args,
                        "report",
                        list(samples),
                        list(arrivals),
                        sub.missed_total,
                        new_elements=new_elements,
                    )
                    new_elements = 0
                wait_s = max(0.0, next_report - now)
                if deadline is not None:
                    wait_s = min(wait_s, max(0.0, deadline - now))
                notes = sub.take_many(_TAKE_MAX, timeout_s=wait_s)
                arrival_ns = time.monotonic_ns()  # one instant for what came together
                for note in notes:
                    if samples and note.seq <= samples[-1].seq:
                        # The producer restarted: a new epoch counts from 1.
                        samples.clear()
                        arrivals.clear()
                    samples.append(
                        Sample(note.seq, note.timestamp_ns, arrival_ns, _size(sub, note))
                    )
                if notes:
                    arrivals.append((arrival_ns, samples[-1].seq))
                    new_elements += len(notes)
        except KeyboardInterrupt:
            pass
        missed = sub.missed_total
    _report(args, "summary", list(samples), list(arrivals), missed)
    return 0


def _size(sub: Subscription, note: Notification) -> int | None:
    if note.element is not None:
        return len(note.element.payload)
    try:  # large elements are not inline: fetch, as `ros2 topic bw` receives
        return len(sub.fetch(note).payload)
    except FramegateError:
        return None  # evicted already; the rate does not need it


def _report(
    args: argparse.Namespace,
    event: str,
    samples: list[Sample],
    arrivals: list[tuple[int, int]],
    missed: int,
    *,
    new_elements: int | None = None,
) -> None:
    """Print one report (``new_elements``: arrived during the interval) or the summary."""
    stats = window_stats(samples, arrivals)
    idle_s = None
    if new_elements == 0 and arrivals:
        idle_s = (time.monotonic_ns() - arrivals[-1][0]) / 1e9
    if args.json:
        extra = {} if new_elements is None else {"new_elements": new_elements}
        line = {"event": event, "target": args.target, "missed": missed, **stats, **extra}
        print_json_line(line)
    else:
        _print_report(stats, missed, idle_s)
