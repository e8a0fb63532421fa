"""``framegate info``: one buffer's retention, size, span, rate, subscriptions and counters;
or, given a recording (``FILE.mcap``), what it holds, like ``ros2 bag info``."""

from __future__ import annotations

import argparse
from pathlib import Path
from typing import TYPE_CHECKING, Any

from middleware import BufferInfo, Node, ServiceInfo, check_name

from ._common import (
    command_parser,
    counted,
    format_bytes,
    format_ns,
    format_seconds,
    network,
    print_json,
    recording_input,
)
from ._target import add_timeout_argument, resolve, wait_for_service
from .ls import clock_steps_text, holder, listen_text

if TYPE_CHECKING:  # the bag code loads MCAP: only `info FILE.mcap` pays for it
    from services.tools.bag import ChannelInfo


SECOND_NS = 1_000_000_000


def register(subparsers: Any) -> None:
    parser = command_parser(
        subparsers,
        "info",
        "describe a buffer: retention, size, span, rate, subscriptions, producer counters",
        json_flag=True,
    )
    parser.add_argument(
        "target",
        metavar="SERVICE/BUFFER|FILE.mcap",
        help="the buffer, just SERVICE for all its buffers, or a recording",
    )
    add_timeout_argument(parser)
    parser.set_defaults(func=run)


def buffer_json(b: BufferInfo) -> dict[str, Any]:
    """A buffer in the records' JSON form (as ``ls --json`` shows it), plus its name and
    readable times."""
    data = b.to_json()
    for sub in data["subscriptions"]:
        del sub["taken_ns"]  # never known of a peer's subscription (left out, as always here)
    data["name"] = b.name
    data["oldest"] = format_ns(b.oldest_ns) if b.oldest_ns is not None else None
    data["newest"] = format_ns(b.newest_ns) if b.newest_ns is not None else None
    return data


def service_json(info: ServiceInfo) -> dict[str, Any]:
    """A service in the records' JSON form, without its buffers (the caller adds those) and
    its raw clock reading (left out, as always here: its offset says what it means)."""
    data = info.to_json()
    del data["buffers"], data["clock_ns"]
    return data


def run(args: argparse.Namespace) -> int:
    recording = recording_input(Path(args.target))  # `info run`: run.mcap, as record wrote it
    if args.target.endswith(".mcap") or recording.is_file():
        return _recording(args, recording)
    whole_service = "/" not in args.target.strip("/")
    with Node(network=network(args)) as node:
        if whole_service:
            name = check_name(args.target.strip("/"), "service")
            wait_for_service(node, name, args.timeout)
            service = node.service_info(name, timeout_s=args.timeout)
            buffers = list(service.buffers)
        else:
            service, buffer = resolve(node, args.target, args.timeout)
            buffers = [buffer]
    if args.json:
        if whole_service:
            print_json({**service_json(service), "buffers": [buffer_json(b) for b in buffers]})
        else:
            print_json({**service_json(service), **buffer_json(buffers[0])})
        return 0
    for b in buffers:
        _print_buffer(service, b)
    if not buffers:
        print(f"{service.service} offers no buffers")
    return 0


def _limit(value: int | None, fmt: Any = str) -> str:
    return "unlimited" if value is None else str(fmt(value))


def _print_buffer(service: ServiceInfo, b: BufferInfo) -> None:
    offset_ms = (service.clock_offset_ns or 0) / 1e6
    rtt_ms = (service.round_trip_ns or 0) / 1e6
    r = b.retention
    age = _limit(r.max_age_ns, lambda ns: f"{ns / 1e9:g} s")
    span = ""
    if b.oldest_ns is not None and b.newest_ns is not None:
        span = f" ({(b.newest_ns - b.oldest_ns) / 1e9:.3f} s)"
    print(f"{b.name}  (kind {b.kind})")
    print(
        f"  service        host {service.host}, pid {service.pid}, "
        f"clock offset {offset_ms:+.1f} ms (round trip {rtt_ms:.1f} ms)"
        f"{clock_steps_text(service)}"
    )
    print(f"  listens on     {listen_text(service.listen)}")
    print(
        f"  retention      max {_limit(r.max_count)} elements, "
        f"{_limit(r.max_bytes, format_bytes)}, age {age}, "
        f"element payload <= {format_bytes(r.max_payload_bytes)}"
    )
    print(f"  size           {counted(b.count, 'element')}, {format_bytes(b.payload_bytes)}")
    print(f"  span           {format_ns(b.oldest_ns)} .. {format_ns(b.newest_ns)}{span}")
    print(f"  rate           {b.rate_hz:.1f} Hz")
    skipped = "".join(f", skipped {reason} {n}" for reason, n in sorted(b.skipped.items()))
    print(f"  producer       puts {b.puts}, refused {b.refused}, rejected {b.rejected}{skipped}")
    if control := _control_text(b):  # a flood, churn or a hostile peer (docs/limits.md)
        print(f"  control        {control}")
    for w in b.rewinds:  # what a rewind removed is shown, never only logged
        print(f"  rewound        {w.count} after {format_ns(w.after_ns)} ({w.cause})")
    if b.limits is not None:  # docs/limits.md
        lim = b.limits
        print(
            f"  limits         {lim.flow_registrations} flow + {lim.observe_registrations} "
            f"observe subscriptions, queue budget {lim.queue_budget} (one queue at most "
            f"{lim.flow_queue_max}); each node~host at most half of what others leave free; "
            f"refused {b.refused_subscriptions}"
        )
        if lim.control_inbox_bytes:
            print(
                f"  memory         retention, kept headers (queue budget), control inboxes at "
                f"most {format_bytes(lim.control_inbox_bytes)}; plus Zenoh's receive buffers "
                "and each local peer's shared-memory pool (docs/limits.md)"
            )
    if not b.subscriptions:
        print("  subscriptions  none")
        return
    print("  subscriptions")
    for s in b.subscriptions:
        print(
            f"    {holder(s):<32} {s.mode.value:<8} queue {s.queue_size:<4}"
            f" queued {s.queued:<4} fill {s.fill:.0%}  ({s.subscription_id})"
        )


def _control_text(b: BufferInfo) -> str:
    """The producer's counts of control messages it ignored, those that are not 0."""
    counts = (
        (b.bad_messages, "malformed acks or tokens ignored"),
        (b.dropped_messages, "dropped unread"),
        (b.foreign_acks, "acks of no live registration ignored"),
        (b.collapsed_tokens, "tokens withdrawn before they registered"),
    )
    return ", ".join(f"{n} {what}" for n, what in counts if n)


def _recording(args: argparse.Namespace, path: Path) -> int:
    from services.tools.bag import recording_info  # MCAP only for a recording

    info = recording_info(path)
    if args.json:
        print_json(info.json())
        return 0
    span = (
        f"{format_ns(info.start_ns)} .. {format_ns(info.end_ns)} ({info.duration_s:.1f} s)"
        if info.start_ns is not None and info.end_ns is not None
        else "no messages"
    )
    print(f"Files:         {info.path}")
    print(f"Size:          {format_bytes(info.size_bytes)}")
    print(f"Status:        {info.integrity}")
    if info.recorded is not None:  # as `ros2 bag info`'s start and duration: the recorder's
        start_ns, stop_ns, host = info.recorded
        where = f", on host {host}" if host else ""
        if stop_ns is None:  # killed before its end record
            print(f"Recorded:      from {format_ns(start_ns)} (the recorder never stopped{where})")
        else:
            print(
                f"Recorded:      {format_ns(start_ns)} .. {format_ns(stop_ns)} "
                f"({(stop_ns - start_ns) / 1e9:.1f} s{where})"
            )
        if info.start_ns is not None and info.start_ns < start_ns - SECOND_NS:
            early = format_seconds((start_ns - info.start_ns) / 1e9)
            span = span[:-1] + (
                f"; it begins {early} before the recording: each buffer's newest element at "
                "the start is kept, however old)"
            )
    print(f"Span:          {span}")
    print(f"Messages:      {counted(info.messages, 'message')} in {counted(info.chunks, 'chunk')}")
    print(f"Compression:   {', '.join(info.compressions) or 'none'}")
    print("Channels:")
    width = max((len(c.topic) for c in info.channels), default=0)
    for c in info.channels:
        print(channel_line(c, width))
    if info.buffers:
        # As `ros2 bag record` reports lost-in-transport apart from lost-in-recorder.
        print("Recorder:")
        name_width = max(len(b.name) for b in info.buffers)
        for b in info.buffers:
            print(
                f"  {b.name:<{name_width}}  {b.recorded:>8} recorded ({b.backfilled} backfilled), "
                f"{b.evicted} lost in transport (evicted, or not fetched by the stop), "
                f"{b.dropped} dropped by the recorder"
            )
    return 0


def channel_line(channel: ChannelInfo, width: int) -> str:
    """One channel of ``info FILE.mcap``: topic, message count, schema and framegate kind."""
    kind = f" ({channel.kind})" if channel.kind else ""
    # A schemaless channel (the JSON verdicts and gyro rates) would leave the column blank.
    schema = channel.schema or "no schema"
    return f"  {channel.topic:<{width}}  {channel.messages:>8} msgs  {schema}{kind}"
