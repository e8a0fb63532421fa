"""``framegate record``: record buffers (payload + metadata + timestamps) to an MCAP file.

Buffering rule: record *observes* (``SubscriptionMode.OBSERVE``), so it never slows the
robot, yet it is lossless while the buffer's retention lasts: what it missed it fetches
from the buffer's history (``services.tools.bag._recorder``). It counts apart what was
gone from a buffer before it could be fetched (``evicted``) and what it failed to keep
itself (``dropped``: its write queue was full), in its summary and in the file (shown by
``framegate info FILE.mcap``).

``--duration`` counts from the instant the recording starts (the buffers found, the file
open, each buffer's newest element asked for), as ``rosbag record --duration`` counts from
the opening of its bag: the start-up (imports, discovery) is not part of it. At its end the
stop instant is fixed (nothing stamped later is recorded), every fetch ends within
``STOP_SLACK_S`` of it (what was not fetched by then is counted ``evicted``, not waited
for; only the tail up to the stop is still asked for once by a recorder that a busy machine
starved past that, with ``TAIL_FLOOR_S``) and what was fetched is written uncompressed, so
the command ends about a second after the duration, two on a starved machine.

The start and the stop are instants of this process's clock (``now_ns``: a step of this
host's clock during the recording moves neither), turned into each producer's clock by the
offset measured when its service was found (``producer_offset_ns``): elements are stamped by
their producers, and a producer whose clock runs ahead of ours (another host not yet
synchronised, or this host's services slewing back after a backward step) stamps everything
it stores after our stop instant. Without the offset, ``--duration 5`` against a producer
30 s ahead recorded nothing, with no word.
"""

from __future__ import annotations

import argparse
import json
import socket
import sys
import threading
import time
from collections.abc import Callable
from pathlib import Path
from typing import TYPE_CHECKING, Any

from middleware import (
    OBSERVE_QUEUE_MAX,
    BufferInfo,
    ConfigError,
    FramegateError,
    Node,
    ServiceInfo,
    now_ns,
)
from services.lib.argtypes import positive_float, positive_int, queue_size
from services.tools.bag import STOP_SLACK_S, TAIL_FLOOR_S

from ._common import (
    command_parser,
    counted,
    exit_on_sigterm,
    format_bytes,
    network,
    print_json,
    recording_output,
)
from ._target import (
    add_timeout_argument,
    nothing_answered,
    observer,
    producer_offset_ns,
    resolve,
    where,
)

if TYPE_CHECKING:
    from services.tools.bag import BagWriter, Recorder, WriteQueue

DEFAULT_QUEUE = 64
# At the stop, a write backlog this large (about a second of raw frames) is worth a line.
SAY_BACKLOG_BYTES = 16 * 2**20


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
        "-o",
        "--output",
        required=True,
        type=Path,
        metavar="FILE.mcap",
        help="the MCAP file (.mcap is added to a name without it)",
    )
    parser.add_argument(
        "--duration",
        type=positive_float,
        metavar="S",
        help="record the elements stamped within S seconds of the recording's start (once "
        "the buffers are found and subscribed: start-up does not count, as with rosbag's "
        "--duration), then stop; the command ends about 1 s later",
    )
    parser.add_argument(
        "--count",
        type=positive_int,
        metavar="K",
        help="stop once each buffer has K elements (one put once, as camera/info, never has "
        "more than 1: with it, bound the recording with --duration)",
    )
    parser.add_argument(
        "--queue",
        type=queue_size(OBSERVE_QUEUE_MAX),
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
        "--compression",
        choices=("zstd", "lz4", "none"),
        default="zstd",
        help="chunk compression, default zstd (chunks written while the writer is behind, and "
        "at the stop, are stored uncompressed so that nothing waits for the compressor)",
    )
    parser.add_argument("--overwrite", action="store_true", help="replace FILE if it exists")
    add_timeout_argument(parser)
    parser.set_defaults(func=run)


def _check(args: argparse.Namespace) -> None:
    args.output = recording_output(args.output)  # `-o run` writes run.mcap
    if not args.targets and not args.all:
        raise ConfigError("name the buffers to record (SERVICE/BUFFER ...), or pass --all")
    if args.targets and args.all:
        raise ConfigError("--all records every buffer: give it without SERVICE/BUFFER names")
    if args.count is not None and args.count < 1:
        raise ConfigError(f"--count {args.count}: must be >= 1")
    if args.duration is not None and args.duration <= 0:
        raise ConfigError(f"--duration {args.duration}: must be > 0 seconds")
    if args.output.is_dir():  # --overwrite would not help: say so before anything
        example = args.output / "run.mcap"
        raise ConfigError(f"{args.output} is a directory; give a file path, e.g. -o {example}")
    if args.output.exists() and not args.overwrite:
        raise ConfigError(f"{args.output} exists; choose another file or pass --overwrite")


def run(args: argparse.Namespace) -> int:
    from services.tools.bag import BagWriter, WriteQueue  # imported here: MCAP only for record

    _check(args)
    exit_on_sigterm()
    targets = list(dict.fromkeys(t.strip("/") for t in args.targets))
    with Node(network=network(args)) as node:
        found = (
            _live_buffers(node, args.timeout)
            if args.all
            else [resolve(node, t, args.timeout) for t in targets]
        )
        buffers: list[BufferInfo] = [b for _s, b in found]
        args.offsets = _offsets(node, [s.service for s, _b in found], args.timeout)
        writer = BagWriter(
            args.output,
            images=not args.no_images,
            compression=args.compression,
            overwrite=args.overwrite,
        )
        with writer:
            # Every channel before any subscription: a recording stopped at once is readable.
            for b in buffers:
                writer.add_buffer(b.service, b.buffer, kind=b.kind, retention=b.retention)
            queue = WriteQueue(writer)
            # The recording starts now: --duration counts from here (see the module).
            started_ns, started = now_ns(), time.monotonic()
            args.started_ns = started_ns
            # Known from the start with --duration, so that nothing stamped after the
            # duration's end is recorded even before the stop is noticed.
            args.stop_ns, args.fetch_deadline = None, None
            if args.duration is not None:
                args.stop_ns = started_ns + round(args.duration * 1e9)
                args.fetch_deadline = started + args.duration + STOP_SLACK_S
            # Written now, not only at the end: a recorder killed (SIGKILL, power) keeps
            # where and when it ran. The end record repeats these and adds the stop.
            writer.add_metadata(
                "framegate.recording.start",
                {
                    "host": socket.gethostname(),
                    "started_ns": str(started_ns + min(args.offsets.values(), default=0)),
                },
            )
            recorders = _start(node, queue, buffers, args)
            if not recorders:
                raise ConfigError(f"none of the {len(buffers)} live buffers could be recorded")
            if not args.json:
                names = ", ".join(f"{r.sub.name} ({r.progress.kind})" for r in recorders)
                print(f"recording {names} to {args.output}; Ctrl-C to stop", flush=True)
            discover = _discover(node, writer, queue, recorders, args)

            def step() -> None:
                # A quiet buffer's last elements must not stay only in memory: a recorder
                # killed now keeps every chunk closed so far (at most CHUNK_AGE_S lost).
                writer.flush_if_due()
                if discover is not None:
                    discover()

            stopped_ns, cut = _wait(recorders, started_ns, started, args.duration, step)
            waiting, waiting_bytes = queue.backlog()
            if waiting_bytes >= SAY_BACKLOG_BYTES and not args.json and not cut:
                # A disk or compressor slower than the buffers: say why the end takes a while.
                print(
                    f"stopped; writing the {waiting} elements ({format_bytes(waiting_bytes)}) "
                    "fetched but not yet written (Ctrl-C again: stop at once)",
                    file=sys.stderr,
                    flush=True,
                )
            try:
                # The subscriptions first: the notifications they would go on receiving cost
                # the writer its share of the interpreter (measured: a backlog written 5x
                # slower).
                for recorder in recorders:
                    recorder.progress.missed = recorder.sub.missed_total
                    recorder.progress.bad_notifications = (
                        recorder.sub.garbage + recorder.sub.dropped
                    )
                    recorder.sub.close()
                if not cut:
                    queue.close()  # what was fetched is written before the summary
            except KeyboardInterrupt:
                cut = True
            args.cut = cut
            if cut:
                # A second Ctrl-C: the file still gets its counts, and the user the summary.
                queue.abandon()
                if not args.json:
                    print(
                        "stopped at once (a second Ctrl-C): what was still being fetched or "
                        "written is not in the file; fetched but unwritten is counted dropped",
                        file=sys.stderr,
                        flush=True,
                    )
            earliest = min(args.offsets.values(), default=0)
            writer.add_metadata(
                "framegate.recording",
                {
                    "host": socket.gethostname(),
                    # In the clock of the producer furthest behind: where play starts.
                    "started_ns": str(started_ns + earliest),
                    "stopped_ns": str(stopped_ns + earliest),
                    "buffers": json.dumps([r.progress.json() for r in recorders]),
                },
            )
            counts = writer.counts()
            derived = writer.derived_counts()
    for error in [queue.error] + [r.error for r in recorders]:
        if error is not None:
            if isinstance(error, FramegateError):
                raise error
            from services.tools.bag import BagError

            raise BagError(f"recording to {args.output} failed: {error}")
    _summary(args, recorders, counts, derived, (stopped_ns - started_ns) / 1e9)
    return 0


def _start(
    node: Node,
    queue: WriteQueue,
    buffers: list[BufferInfo],
    args: argparse.Namespace,
    stop: threading.Event | None = None,
) -> list[Recorder]:
    from services.tools.bag import Progress, Recorder, at_start

    stop = stop or threading.Event()
    recorders = []
    for b in buffers:
        # The start and the stop in this producer's clock: its elements' stamps are.
        offset = args.offsets.get(b.service, 0)
        stop_ns = None if args.stop_ns is None else args.stop_ns + offset
        try:
            session = node.service_session(b.service)  # its replies alone, if it is one
            initial = at_start(node, b.name, args.started_ns + offset, stop_ns, session)
            sub = observer(node, b.name, args.queue, args.timeout)
        except FramegateError as exc:
            if not args.all:
                raise
            # With --all the buffers are whatever answered: one that cannot be recorded
            # (gone since, or a peer's invention) must not cost the others their recording.
            print(f"warning: not recording {b.name}: {exc}", file=sys.stderr, flush=True)
            continue
        progress = Progress(b.name, b.kind)
        recorder = Recorder(node, sub, queue, progress, stop, args.count, initial)
        recorder.stop_ns, recorder.deadline = stop_ns, args.fetch_deadline
        recorder.offset_ns = offset
        recorders.append(recorder)
    for recorder in recorders:
        recorder.thread.start()
    return recorders


def _live_buffers(node: Node, timeout_s: float) -> list[tuple[ServiceInfo, BufferInfo]]:
    """Every buffer of every live service (``--all``), with its service; ConfigError if
    there is none."""
    deadline = time.monotonic() + timeout_s
    while True:
        services = _with_token(node, node.services(timeout_s=min(2.0, timeout_s)))
        buffers = [(s, b) for s in services for b in s.buffers]
        if buffers:
            return buffers
        if time.monotonic() >= deadline:
            if error := nothing_answered(node, timeout_s):
                raise error  # an endpoint that does not answer is not "no buffers"
            raise ConfigError(
                f"no live service offers a buffer {where(node.network)} (waited {timeout_s:g} s)"
            )
        time.sleep(0.2)


def _with_token(node: Node, services: list[ServiceInfo]) -> list[ServiceInfo]:
    """Those of ``services`` that hold their liveliness token: an ``@info`` answer alone is
    any peer's to give (20 made-up services answering it, holding no token, kept
    ``record --all`` starting for 126 s and then failed it)."""
    if not services:
        return []
    live = set(node.live_services(timeout_s=1.0))
    return [s for s in services if s.service in live]


def _offsets(node: Node, services: list[str], timeout_s: float) -> dict[str, int]:
    """Each service's clock offset (``producer_offset_ns``), all of them within twice the
    timeout: a service not asked by then is taken to share our clock."""
    deadline = time.monotonic() + 2 * timeout_s
    offsets = {}
    for name in dict.fromkeys(services):
        wait_s = min(2.0, timeout_s, deadline - time.monotonic())
        offsets[name] = producer_offset_ns(node, name, wait_s) if wait_s > 0 else 0
    return offsets


# A recorder thread gets this long after its fetch deadline to hand over what it fetched
# (its final backfill may run ``TAIL_FLOOR_S`` past the deadline).
_JOIN_GRACE_S = TAIL_FLOOR_S + 0.5

# ``--all`` looks for buffers that appeared since this often.
_DISCOVER_S = 2.0


def _discover(
    node: Node,
    writer: BagWriter,
    queue: WriteQueue,
    recorders: list[Recorder],
    args: argparse.Namespace,
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
            services = _with_token(node, node.services(timeout_s=1.0))
        except FramegateError:
            return
        new = [b for s in services for b in s.buffers if b.name not in known]
        unmeasured = [b.service for b in new if b.service not in args.offsets]
        args.offsets.update(_offsets(node, unmeasured, 1.0))
        for b in new:
            writer.add_buffer(b.service, b.buffer, kind=b.kind, retention=b.retention)
        started = _start(node, queue, new, args, recorders[0].stop)
        recorders.extend(started)
        if started and not args.json:
            print(f"recording {', '.join(r.sub.name for r in started)} too", flush=True)

    return step


def _wait(
    recorders: list[Recorder],
    started_ns: int,
    started: float,
    duration: float | None,
    step: Callable[[], None] | None = None,
) -> tuple[int, bool]:
    """Until every recorder has its count, the duration is over, an error, or Ctrl-C; the
    stop instant (wall-clock ns): nothing stamped later is recorded, everything before is
    fetched until the recorders' deadline (``STOP_SLACK_S`` after the stop). And whether a
    second Ctrl-C cut that wait short (the recorders still fetching are left behind)."""
    cut = False
    stop = recorders[0].stop
    end = None if duration is None else started + duration
    stopped_ns = None
    try:
        # A failing file (a full disk) ends the recording at once, not at its duration.
        while any(r.thread.is_alive() for r in recorders) and recorders[0].queue.error is None:
            if end is not None and time.monotonic() >= end:
                # The duration's own end, not the instant this loop noticed it (late on a
                # busy machine): the file spans the duration, in the producers' stamps.
                stopped_ns = started_ns + round((end - started) * 1e9)
                break
            if step is not None:
                step()
            stop.wait(0.1)
    except KeyboardInterrupt:
        pass
    finally:
        if stopped_ns is None:
            stopped_ns = now_ns()
        deadline = time.monotonic() + STOP_SLACK_S
        for recorder in recorders:
            stop_ns = stopped_ns + recorder.offset_ns  # in its producer's clock
            if recorder.stop_ns is None or recorder.stop_ns > stop_ns:
                recorder.stop_ns = stop_ns
            if recorder.deadline is None or recorder.deadline > deadline:
                recorder.deadline = deadline
        stop.set()
        for recorder in recorders:
            # Each fetch ends by the deadline; a recorder still busy after it (inside a
            # call that overran its timeout) is left behind: what it fetches later is
            # counted dropped, as the writer is closed by then.
            left_s = (recorder.deadline or deadline) - time.monotonic()
            try:
                recorder.thread.join(timeout=max(0.0, left_s) + _JOIN_GRACE_S)
            except KeyboardInterrupt:
                cut = True
                break
    return stopped_ns, cut


def _summary(
    args: argparse.Namespace,
    recorders: list[Recorder],
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
    recorded = counted(total, "element")
    print(f"recorded {recorded} to {args.output} ({size_text}) in {duration_s:.1f} s")
    for r in recorders:
        p = r.progress
        print(
            f"  {p.name:<28} {counted(p.recorded, 'element'):>15} ({p.backfilled} backfilled, "
            f"{p.evicted} evicted, {p.dropped} dropped)"
        )
        if p.evicted:
            print(
                f"  warning: {p.evicted} elements of {p.name} were not fetched: evicted from "
                "the buffer before they could be, or not answered within "
                f"{STOP_SLACK_S:g} s of the stop; raise its retention or record fewer buffers",
                file=sys.stderr,
            )
        if p.dropped and not args.cut:  # after a second Ctrl-C, its line said why
            print(
                f"  warning: the recorder dropped {p.dropped} elements of {p.name}: its write "
                "queue was full (the disk too slow); try --no-images",
                file=sys.stderr,
            )
        if p.bad_notifications:
            print(
                f"  warning: {p.bad_notifications} messages on the notification key of "
                f"{p.name} were no notification (a peer's garbage, oversize, or a flood); "
                "what they pushed out was fetched again (counted evicted if it could not be)",
                file=sys.stderr,
            )
