"""Watch services from inside a namespace: one JSON line per poll on stdout (test helper).

    ip netns exec NS python -m tests.multihost.observer --connect tcp/127.0.0.1:7447 \
        --watch camera,detector [--clock] [--polls N]

Each line: ``{"t_ns": <our wall clock>, "services": {NAME: null | {"pid", "offset_ns",
"round_trip_ns", "buffers": {BUFFER: {"puts", "refused", "subscriptions",
"queued" (the fullest subscription's)}}}}}``; with ``--clock``
the first line is ``{"clock": [ClockEstimate as a dict, ...]}`` from ``services.lib.clock``.
An unreachable service is ``null`` (asked with a short timeout, so polls stay frequent).
"""

from __future__ import annotations

import argparse
import json
import signal
import sys
import time
from dataclasses import asdict, replace
from types import FrameType
from typing import Any

from middleware import (
    FramegateError,
    NetworkConfig,
    Node,
    ServiceInfo,
    TransportError,
    add_network_arguments,
    network_from_args,
)
from services.lib.clock import estimate_clocks


def _describe(info: ServiceInfo) -> dict[str, Any]:
    return {
        "pid": info.pid,
        "offset_ns": info.clock_offset_ns,
        "round_trip_ns": info.round_trip_ns,
        "buffers": {
            b.buffer: {
                "puts": b.puts,
                "refused": b.refused,
                "subscriptions": len(b.subscriptions),
                "queued": max((s.queued for s in b.subscriptions), default=0),
            }
            for b in info.buffers
        },
    }


def _emit(data: dict[str, Any]) -> None:
    sys.stdout.write(json.dumps(data) + "\n")
    sys.stdout.flush()


def _open(network: NetworkConfig, wait_s: float) -> Node:
    # A client fails at once while the router is not up yet: retry until it is.
    deadline = time.monotonic() + wait_s
    while True:
        try:
            return Node(network=network)
        except TransportError:
            if time.monotonic() > deadline:
                raise
            time.sleep(0.2)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="observer")
    add_network_arguments(parser)
    parser.add_argument("--watch", required=True, help="comma-separated service names")
    parser.add_argument("--interval", type=float, default=0.1, help="seconds between polls")
    parser.add_argument("--timeout", type=float, default=0.3, help="seconds per info query")
    parser.add_argument("--clock", action="store_true", help="first estimate clock offsets")
    parser.add_argument("--wait", type=float, default=120.0, help="seconds to wait for a router")
    parser.add_argument("--polls", type=int, default=0, help="stop after this many (0: never)")
    args = parser.parse_args(argv)
    names = [n for n in args.watch.split(",") if n]

    def on_term(_signum: int, _frame: FrameType | None) -> None:
        raise KeyboardInterrupt

    signal.signal(signal.SIGTERM, on_term)
    # A client: it must not become a hop of the mesh it observes.
    network = replace(network_from_args(args), mode="client")
    try:
        with _open(network, args.wait) as node:
            if args.clock:
                deadline = time.monotonic() + 20
                while set(node.live_services()) < set(names) and time.monotonic() < deadline:
                    time.sleep(0.1)
                estimates = estimate_clocks(node, names, samples=8)
                _emit({"clock": [{**asdict(e), "error_ns": e.error_ns} for e in estimates]})
            polls = 0
            while args.polls == 0 or polls < args.polls:
                polls += 1
                services: dict[str, Any] = {}
                for name in names:
                    try:
                        services[name] = _describe(node.service_info(name, timeout_s=args.timeout))
                    except FramegateError:
                        services[name] = None
                _emit({"t_ns": time.time_ns(), "services": services})
                time.sleep(args.interval)
    except KeyboardInterrupt:
        pass
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
