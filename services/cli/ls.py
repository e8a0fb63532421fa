"""``framegate ls``: live services, their buffers, sizes, spans, rates and subscribers."""

from __future__ import annotations

import argparse
from dataclasses import asdict
from typing import Any

from middleware import Node, ServiceInfo

from ._common import command_parser, format_bytes, format_ns, network, print_json

# Warn when a host's clock differs from ours by more than this (a fraction of an exposure).
CLOCK_WARN_NS = 2_000_000


def register(subparsers: Any) -> None:
    parser = command_parser(
        subparsers, "ls", "list live services and their buffers", json_flag=True
    )
    parser.add_argument("--timeout", type=float, default=2.0, help="seconds to wait for answers")
    parser.set_defaults(func=run)


def service_json(info: ServiceInfo) -> dict[str, Any]:
    data = asdict(info)
    for buffer in data["buffers"]:
        for sub in buffer["subscriptions"]:
            sub["mode"] = sub["mode"].value
            sub["fill"] = min(1.0, sub["queued"] / sub["queue_size"])
    return data


def run(args: argparse.Namespace) -> int:
    with Node(network=network(args)) as node:
        infos = node.services(timeout_s=args.timeout)
    if args.json:
        print_json({"services": [service_json(i) for i in infos]})
        return 0
    if not infos:
        print("no live services")
        return 0
    for info in infos:
        offset_ms = (info.clock_offset_ns or 0) / 1e6
        warn = "  CLOCK OFFSET!" if abs(info.clock_offset_ns or 0) > CLOCK_WARN_NS else ""
        print(
            f"{info.service}  (host {info.host}, pid {info.pid}, clock {offset_ms:+.1f} ms){warn}"
        )
        for b in info.buffers:
            subs = (
                ", ".join(
                    f"{s.subscription_id}:{s.mode.value} {s.queued}/{s.queue_size}"
                    for s in b.subscriptions
                )
                or "no subscribers"
            )
            print(
                f"  {b.name:<28} {b.kind:<10} {b.count:>7} elements"
                f" {format_bytes(b.payload_bytes):>10}"
                f"  {b.rate_hz:6.1f} Hz  {format_ns(b.oldest_ns)} .. {format_ns(b.newest_ns)}"
                f"  [{subs}]"
            )
    return 0
