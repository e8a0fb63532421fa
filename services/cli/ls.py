"""``framegate ls``: live services, their buffers, sizes, spans, rates and subscribers."""

from __future__ import annotations

import argparse
import ipaddress
import socket
import sys
from collections.abc import Sequence
from typing import Any

from middleware import Node, NotFoundError, ServiceInfo, SubscriptionInfo
from services.lib.argtypes import positive_float, positive_int
from services.lib.clock import CLOCK_WARN_NS, ClockEstimate, clock_warning, estimate_clocks

from ._common import command_parser, format_bytes, format_ns, network, print_json
from ._target import connected_late, nothing_answered, other_namespaces, unreachable, where


def register(subparsers: Any) -> None:
    parser = command_parser(
        subparsers, "ls", "list live services and their buffers", json_flag=True
    )
    parser.add_argument(
        "--timeout",
        type=positive_float,
        default=2.0,
        help="seconds to wait for answers (default 2)",
    )
    parser.add_argument(
        "--clock-samples",
        type=positive_int,
        default=5,
        help="round trips per service on another host for its clock offset; the shortest "
        "counts (default 5)",
    )
    parser.set_defaults(func=run)


def service_json(info: ServiceInfo, clock: ClockEstimate | None = None) -> dict[str, Any]:
    """A service in the records' JSON form, with the clock estimate of ``ls``."""
    data = info.to_json()
    if clock is not None:  # the best of several round trips, not the one listing query
        data["clock_offset_ns"] = clock.offset_ns
        data["round_trip_ns"] = clock.round_trip_ns
    data["clock_error_ns"] = None if clock is None else clock.error_ns
    return data


def is_loopback_endpoint(endpoint: str) -> bool:
    """Whether a ``proto/host:port`` endpoint can only be reached from its own host."""
    _, _, address = endpoint.partition("/")
    host = address.rsplit(":", 1)[0].strip("[]").split("%", 1)[0]
    if host == "localhost":
        return True
    try:
        return ipaddress.ip_address(host).is_loopback
    except ValueError:
        return False


def listen_text(endpoints: Sequence[str]) -> str:
    """Listen endpoints for a human; one reachable from other hosts is flagged."""
    if not endpoints:
        return "none"
    return ", ".join(
        e if is_loopback_endpoint(e) else f"{e} (reachable from the network)" for e in endpoints
    )


def clock_steps_text(info: ServiceInfo) -> str:
    """``, clock stepped 2x, last -20.0 s (lead +20.0 s)`` when the service's system clock
    stepped, else ''.

    Its stamps never went backward (see the README's *Time model*); the last step's size is
    signed (- backward); the lead is how far its process clock is still ahead of its system
    clock after a backward step."""
    if not info.clock_steps:
        return ""
    last = (
        "" if info.clock_last_step_ns is None else f", last {info.clock_last_step_ns / 1e9:+.1f} s"
    )
    return (
        f", clock stepped {info.clock_steps}x{last} (lead {(info.clock_lead_ns or 0) / 1e9:+.1f} s)"
    )


def holder(sub: SubscriptionInfo) -> str:
    """Who holds a subscription: ``node@host`` (``?`` where its token does not say)."""
    node = "?" if sub.node is None else (sub.node or "client")
    return f"{node}@{'?' if sub.host is None else sub.host}"


def subscription_text(sub: SubscriptionInfo) -> str:
    return f"{holder(sub)} {sub.mode.value} {sub.queued}/{sub.queue_size}"


def offset_is_real(offset_ns: int, error_ns: int, host: str) -> bool:
    """Whether a clock offset is worth a warning: beyond the threshold and its own error
    bar, and measured against another host (processes of one host share its clock)."""
    return (
        host != socket.gethostname()
        and abs(offset_ns) > error_ns
        and abs(offset_ns) > CLOCK_WARN_NS
    )


def run(args: argparse.Namespace) -> int:
    net = network(args)
    with Node(network=net) as node:
        invalid: list[str] = []
        infos = node.services(timeout_s=args.timeout, invalid=invalid)
        if not infos and connected_late(node, args.timeout):
            invalid.clear()
            infos = node.services(timeout_s=args.timeout, invalid=invalid)
        # One query for every service shares one long round trip: ask each one again, but
        # only those on other hosts; the processes of this host read our own clock. Within
        # twice the timeout in all (any peer can add services that never answer): one not
        # asked by then shows the listing's own sample.
        clocks = {
            c.service: c
            for c in estimate_clocks(
                node,
                [i.service for i in infos if i.host != socket.gethostname()],
                samples=args.clock_samples,
                timeout_s=args.timeout,
                budget_s=2 * args.timeout,
            )
        }
        # Like `info`: an endpoint where nothing answered is an error, not an empty list.
        silent = nothing_answered(node, args.timeout) if not (infos or invalid) else None
        elsewhere = other_namespaces(node) if not (infos or invalid or silent) else None
    for reason in invalid:  # a peer answering garbage is named, never silently absent
        print(f"warning: left out: {reason}", file=sys.stderr)
    if silent is not None:
        raise silent
    if not infos and (bad := unreachable(net)):
        raise NotFoundError(f"cannot reach {bad}; is the router or service running there?")
    if args.json:
        print_json({"services": [service_json(i, clocks.get(i.service)) for i in infos]})
        return 0
    if not infos:
        hint = f"; {elsewhere}" if elsewhere else ""
        print(f"no live services {where(net)} in namespace {net.namespace!r}{hint}")
        return 0
    warnings = []
    for info in infos:
        clock = clocks.get(info.service)
        offset_ns = clock.offset_ns if clock else info.clock_offset_ns or 0
        error_ns = clock.error_ns if clock else (info.round_trip_ns or 0) // 2
        real = offset_is_real(offset_ns, error_ns, info.host)
        warn = "  CLOCK OFFSET!" if real else ""
        text = clock_warning(clock) if clock is not None else None
        if text is not None and info.host != socket.gethostname():
            assert clock is not None
            if real or clock.error_ns > CLOCK_WARN_NS:
                warnings.append(text)
        print(
            f"{info.service}  (host {info.host}, pid {info.pid}, "
            f"clock {offset_ns / 1e6:+.1f} ms ±{error_ns / 1e6:.1f}{clock_steps_text(info)})"
            f"{warn}"
        )
        if listen := info.listen:
            print(f"  listens on {listen_text(listen)}")
        for b in info.buffers:
            print(
                f"  {b.name:<24} {b.kind:<10} {b.count:>7} elements"
                f" {format_bytes(b.payload_bytes):>10}  {b.rate_hz:7.1f} Hz"
            )
            if b.oldest_ns is not None:
                print(f"    span {format_ns(b.oldest_ns)} .. {format_ns(b.newest_ns)}")
            if b.subscriptions:
                print("    subscribers " + ", ".join(subscription_text(s) for s in b.subscriptions))
    for text in warnings:
        print(f"warning: {text}", file=sys.stderr)
    return 0
