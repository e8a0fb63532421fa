"""``framegate record``: record buffers (payload + metadata + timestamps) to an MCAP file.

Buffering rule: record *observes* (``SubscriptionMode.OBSERVE``), so it never slows the
robot, yet it is lossless while the buffer's retention lasts. Notification sequence numbers
count every stored element, so a gap says exactly how many elements were missed between two
notifications, and one range query fetches them from the buffer's history; misses at the
end of a burst, which no later notification reports, are fetched as soon as the
subscription goes quiet. Only elements the buffer evicted before we could fetch them are
lost, and they are counted.
"""

from __future__ import annotations

import argparse
import json
import socket
import sys
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any

from middleware import (
    BufferInfo,
    ConfigError,
    DataObject,
    FramegateError,
    Node,
    Notification,
    Subscription,
    SubscriptionMode,
    TimeRange,
)
from services.lib.argtypes import positive_float, positive_int

from ._common import command_parser, exit_on_sigterm, format_bytes, network, print_json
from ._target import add_timeout_argument, resolve

if TYPE_CHECKING:
    from services.tools.bag import BagWriter

DEFAULT_QUEUE = 64
# After this long without a notification, check the buffer for elements we never heard of.
IDLE_PROBE_S = 1.0


def register(subparsers: Any) -> None:
    parser = command_parser(
        subparsers,
        "record",
        "record buffers to an MCAP file (lossless; Foxglove shows camera frames with the "
        "mediator's verdicts and the detections drawn on them)",
        json_flag=True,
    )
    parser.add_argument(
        "targets", nargs="*", metavar="SERVICE/BUFFER", help="the buffers to record"
    )
    parser.add_argument(
        "--all",
        action="store_true",
        help="record every buffer of every live service, and those that appear later",
    )
    parser.add_argument(
        "-o", "--output", required=True, type=Path, metavar="FILE.mcap", help="the MCAP file"
    )
    parser.add_argument("--duration", type=positive_float, metavar="S", help="stop after S seconds")
    parser.add_argument(
        "--count", type=positive_int, metavar="K", help="stop after K elements of each buffer"
    )
    parser.add_argument(
        "--queue",
        type=positive_int,
        default=DEFAULT_QUEUE,
        metavar="N",
        help=f"observer queue size (default {DEFAULT_QUEUE}); misses are backfilled anyway",
    )
    parser.add_argument(
        "--no-images",
        action="store_true",
        help="do not add foxglove.RawImage channels for camera frames (halves the file)",
    )
    parser.add_argument(
        "--compression", choices=("zstd", "lz4", "none"), default="zstd", help="chunk compression"
    )
    parser.add_argument("--overwrite", action="store_true", help="replace FILE if it exists")
    add_timeout_argument(parser)
    parser.set_defaults(func=run)


@dataclass
class _Progress:
    name: str
    kind: str
    recorded: int = 0
    backfilled: int = 0
    missed: int = 0
    lost: int = 0
    first_ns: int | None = None
    last_ns: int | None = None

    def json(self) -> dict[str, Any]:
        return {
            "name": self.name,
            "kind": self.kind,
            "recorded": self.recorded,
            "backfilled": self.backfilled,
            "missed": self.missed,
            "lost": self.lost,
            "first_ns": self.first_ns,
            "last_ns": self.last_ns,
        }


class _Recorder:
    """Records one buffer on its own thread."""

    def __init__(
        self,
        node: Node,
        sub: Subscription,
        writer: BagWriter,
        progress: _Progress,
        stop: threading.Event,
        count: int | None,
    ) -> None:
        self.node = node
        self.sub = sub
        self.writer = writer
        self.progress = progress
        self.stop = stop
        self.count = count
        self.error: BaseException | None = None
        # Sequence number of the last notification handled (0: none yet in this epoch), and
        # timestamps that backfills wrote after its element.
        self._anchor_seq = 0
        self._since_anchor: list[int] = []
        self._accounted_misses = 0
        self._idle_since = time.monotonic()
        self.thread = threading.Thread(target=self._run, name=f"record-{sub.name}", daemon=True)

    def _full(self) -> bool:
        return self.count is not None and self.progress.recorded >= self.count

    def _run(self) -> None:
        try:
            while not self.stop.is_set() and not self._full():
                note = self.sub.take(timeout_s=0.2)
                if note is not None:
                    self._idle_since = time.monotonic()
                    self._on_notification(note)
                elif self._unaccounted_misses() or self._buffer_is_ahead():
                    # Misses are only reported by the next notification; a burst that has
                    # ended brings none, so catch up from the buffer while it is quiet.
                    self._backfill(None)
            if not self._full() and (self._unaccounted_misses() or self._buffer_is_ahead(True)):
                self._backfill(None)  # the tail missed just before the stop
        except BaseException as exc:  # a failing file must stop the recording, not hang it
            self.error = exc
            self.stop.set()

    def _unaccounted_misses(self) -> bool:
        return self.sub.missed_total > self._accounted_misses

    def _buffer_is_ahead(self, now: bool = False) -> bool:
        """After a quiet second, whether the buffer holds newer elements than we wrote.

        Observer notifications travel with congestion control DROP, so the last ones of a
        burst can vanish without a later one to reveal the gap; the buffer's description
        (no payloads) tells.
        """
        last_ns = self.progress.last_ns
        if last_ns is None or (not now and time.monotonic() - self._idle_since < IDLE_PROBE_S):
            return False
        self._idle_since = time.monotonic()
        try:
            newest = self.node.buffer_info(self.sub.name).newest_ns
        except FramegateError:
            return False
        return newest is not None and newest > last_ns

    def _on_notification(self, note: Notification) -> None:
        p = self.progress
        if note.seq <= self._anchor_seq:
            self._anchor_seq, self._since_anchor = 0, []  # the producer restarted (new epoch)
        # Sequence numbers count every element stored since we subscribed: this many lie
        # between the previous notification we handled and this one.
        expected = note.seq - self._anchor_seq - 1
        if p.last_ns is not None and note.timestamp_ns <= p.last_ns:
            # A backfill already wrote it; it still anchors the count of what lies between.
            between = [t for t in self._since_anchor if t < note.timestamp_ns]
            p.lost += max(0, expected - len(between))
            self._anchor_seq = note.seq
            self._since_anchor = [t for t in self._since_anchor if t > note.timestamp_ns]
            return
        if expected > len(self._since_anchor):
            self._backfill(note.timestamp_ns - 1, newest=expected - len(self._since_anchor))
            if self._full():
                return
        p.lost += max(0, expected - len(self._since_anchor))
        self._anchor_seq, self._since_anchor = note.seq, []
        try:
            element = self.sub.fetch(note)
        except FramegateError:
            p.lost += 1  # evicted before we could fetch it
            return
        self._write(element)

    def _backfill(self, end_ns: int | None, newest: int | None = None) -> None:
        """Write the elements after the last one written, up to ``end_ns`` (open: all)."""
        p = self.progress
        self._accounted_misses = self.sub.missed_total
        start = None if p.last_ns is None else p.last_ns + 1
        if start is None:
            # Nothing written yet: only the newest few belong to this recording.
            newest = newest if newest is not None else self._accounted_misses
        try:
            gap = self.node.query(
                self.sub.name,
                time_range=TimeRange(start, end_ns),
                last=newest if start is None else None,
            )
        except FramegateError:
            return  # what stays missing is counted as lost when the next notification comes
        for element in gap:
            if self._full():
                return
            self._write(element)
            p.backfilled += 1
            self._since_anchor.append(element.timestamp_ns)

    def _write(self, element: DataObject) -> None:
        self.writer.write(self.progress.name, element)
        p = self.progress
        p.recorded += 1
        p.last_ns = element.timestamp_ns
        if p.first_ns is None:
            p.first_ns = element.timestamp_ns


def _check(args: argparse.Namespace) -> None:
    if not args.targets and not args.all:
        raise ConfigError("name the buffers to record (SERVICE/BUFFER ...), or pass --all")
    if args.targets and args.all:
        raise ConfigError("--all records every buffer: give it without SERVICE/BUFFER names")
    if args.queue < 1:
        raise ConfigError(f"--queue {args.queue}: must be >= 1")
    if args.count is not None and args.count < 1:
        raise ConfigError(f"--count {args.count}: must be >= 1")
    if args.duration is not None and args.duration <= 0:
        raise ConfigError(f"--duration {args.duration}: must be > 0 seconds")
    if args.output.exists() and not args.overwrite:
        raise ConfigError(f"{args.output} exists; choose another file or pass --overwrite")


def run(args: argparse.Namespace) -> int:
    from services.tools.bag import BagWriter  # imported here: only record and play need MCAP

    _check(args)
    exit_on_sigterm()
    targets = list(dict.fromkeys(t.strip("/") for t in args.targets))
    with Node(network=network(args)) as node:
        buffers: list[BufferInfo] = (
            _live_buffers(node, args.timeout)
            if args.all
            else [resolve(node, t, args.timeout)[1] for t in targets]
        )
        writer = BagWriter(
            args.output,
            images=not args.no_images,
            compression=args.compression,
            overwrite=args.overwrite,
        )
        with writer:
            for b in buffers:
                writer.add_buffer(b.service, b.buffer, kind=b.kind, retention=b.retention)
            recorders = _start(node, writer, buffers, args)
            started_ns = time.time_ns()
            if not args.json:
                names = ", ".join(f"{b.name} ({b.kind})" for b in buffers)
                print(f"recording {names} to {args.output}; Ctrl-C to stop", flush=True)
            discover = _discover(node, writer, recorders, args)

            def step() -> None:
                # A quiet buffer's last elements must not stay only in memory: a recorder
                # killed now keeps every chunk closed so far (at most CHUNK_AGE_S lost).
                writer.flush_if_due()
                if discover is not None:
                    discover()

            _wait(recorders, args.duration, step)
            stopped_ns = time.time_ns()
            for recorder in recorders:
                recorder.progress.missed = recorder.sub.missed_total
                recorder.sub.close()
            writer.add_metadata(
                "framegate.recording",
                {
                    "host": socket.gethostname(),
                    "started_ns": str(started_ns),
                    "stopped_ns": str(stopped_ns),
                    "buffers": json.dumps([r.progress.json() for r in recorders]),
                },
            )
            counts = writer.counts()
            derived = writer.derived_counts()
    for recorder in recorders:
        if recorder.error is not None:
            if isinstance(recorder.error, FramegateError):
                raise recorder.error
            from services.tools.bag import BagError

            raise BagError(f"recording {recorder.sub.name} failed: {recorder.error}")
    _summary(args, recorders, counts, derived, (stopped_ns - started_ns) / 1e9)
    return 0


def _start(
    node: Node,
    writer: BagWriter,
    buffers: list[BufferInfo],
    args: argparse.Namespace,
    stop: threading.Event | None = None,
) -> list[_Recorder]:
    stop = stop or threading.Event()
    recorders = []
    for b in buffers:
        sub = node.subscribe(
            b.name,
            queue_size=args.queue,
            mode=SubscriptionMode.OBSERVE,
            wait_s=max(2.0, args.timeout),
        )
        recorders.append(_Recorder(node, sub, writer, _Progress(b.name, b.kind), stop, args.count))
    for recorder in recorders:
        recorder.thread.start()
    return recorders


def _live_buffers(node: Node, timeout_s: float) -> list[BufferInfo]:
    """Every buffer of every live service (``--all``); ConfigError if there is none."""
    deadline = time.monotonic() + timeout_s
    while True:
        buffers = [b for s in node.services(timeout_s=min(2.0, timeout_s)) for b in s.buffers]
        if buffers:
            return buffers
        if time.monotonic() >= deadline:
            raise ConfigError(f"no live service offers a buffer (waited {timeout_s:g} s)")
        time.sleep(0.2)


# ``--all`` looks for buffers that appeared since this often.
_DISCOVER_S = 2.0


def _discover(
    node: Node, writer: BagWriter, recorders: list[_Recorder], args: argparse.Namespace
) -> Callable[[], None] | None:
    """With ``--all``: a step that starts recording buffers that appeared since."""
    if not args.all:
        return None
    due = [time.monotonic() + _DISCOVER_S]

    def step() -> None:
        if time.monotonic() < due[0]:
            return
        due[0] = time.monotonic() + _DISCOVER_S
        known = {r.sub.name for r in recorders}
        try:
            services = node.services(timeout_s=1.0)
        except FramegateError:
            return
        new = [b for s in services for b in s.buffers if b.name not in known]
        for b in new:
            writer.add_buffer(b.service, b.buffer, kind=b.kind, retention=b.retention)
        if new:
            recorders.extend(_start(node, writer, new, args, recorders[0].stop))
            if not args.json:
                print(f"recording {', '.join(b.name for b in new)} too", flush=True)

    return step


def _wait(
    recorders: list[_Recorder], duration: float | None, step: Callable[[], None] | None = None
) -> None:
    """Until every recorder has its count, the duration is over, an error, or Ctrl-C."""
    stop = recorders[0].stop
    deadline = None if duration is None else time.monotonic() + duration
    try:
        while any(r.thread.is_alive() for r in recorders):
            if deadline is not None and time.monotonic() >= deadline:
                break
            if step is not None:
                step()
            stop.wait(0.1)
    except KeyboardInterrupt:
        pass
    finally:
        stop.set()
        for recorder in recorders:
            recorder.thread.join()


def _summary(
    args: argparse.Namespace,
    recorders: list[_Recorder],
    counts: dict[str, tuple[int, int]],
    derived: dict[str, int],
    duration_s: float,
) -> None:
    size = args.output.stat().st_size
    rows = []
    for r in recorders:
        row = r.progress.json()
        row["image_messages"] = counts.get(r.progress.name, (0, 0))[1]
        # Foxglove annotations and plots derived from it (services.tools.bag._derived).
        row["derived_messages"] = derived.get(r.progress.name, 0)
        rows.append(row)
    if args.json:
        print_json(
            {
                "file": str(args.output),
                "bytes": size,
                "duration_s": round(duration_s, 3),
                "messages": sum(m + i for m, i in counts.values()) + sum(derived.values()),
                "buffers": rows,
            }
        )
        return
    total = sum(r.progress.recorded for r in recorders)
    size_text = format_bytes(size)
    print(f"recorded {total} elements to {args.output} ({size_text}) in {duration_s:.1f} s")
    for r in recorders:
        p = r.progress
        print(f"  {p.name:<28} {p.recorded:>7} elements ({p.backfilled} backfilled, {p.lost} lost)")
        if p.lost:
            print(
                f"  warning: {p.lost} elements of {p.name} were evicted before they could be "
                "fetched; raise the buffer's retention or record fewer buffers",
                file=sys.stderr,
            )
