"""``framegate faults``: kill each service again and again; how fast it produces again.

A benchmark, not a CI check: it runs its own private pipeline on a free loopback port and
prints restart times (kill to the first element stored by the new process) per service.
Exit code 0 when every p95 meets the goal (3 s), 3 when one misses it.
"""

from __future__ import annotations

import argparse
from typing import Any

from services.evidence.faultbench import FaultConfig, format_faults, run_faults
from services.lib.argtypes import port_number, positive_int, report_file

from ._common import command_parser, stop_on_signals, write_report

GOAL_MISSED = 3


def register(subparsers: Any) -> None:
    parser = command_parser(
        subparsers,
        "faults",
        "kill each service repeatedly; report restart time (p95) per service",
        network=False,
    )
    d = FaultConfig()
    parser.add_argument(
        "--kills",
        type=positive_int,
        default=d.kills,
        help="kills per service (default %(default)s)",
    )
    parser.add_argument(
        "--port", type=port_number, help="private rendezvous port (default: a free one)"
    )
    parser.add_argument(
        "--json", type=report_file, metavar="FILE", help="also write the report as JSON"
    )
    parser.add_argument("--show-logs", action="store_true", help="print the services' logs")
    parser.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    stop = stop_on_signals()
    config = FaultConfig(kills=args.kills, port=args.port, show_logs=args.show_logs)
    print(f"faults: killing each service {config.kills} times (Ctrl-C stops early)", flush=True)
    report = run_faults(config, stop)
    print(format_faults(report), flush=True)
    if args.json:
        write_report(args.json, report)
    if stop.is_set():  # stopped early: a stop is a clean exit, never a verdict
        print("faults: stopped early; no verdict on the goal", flush=True)
        return 0
    p95 = [v for v in report["p95_s"].values() if v is not None]
    return 0 if p95 and all(v <= report["goal_p95_s"] for v in p95) else GOAL_MISSED
