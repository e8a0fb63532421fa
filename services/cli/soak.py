"""``framegate soak``: the whole pipeline at full speed for minutes; memory and lost elements.

A benchmark, not a CI check: it runs its own private pipeline on a free loopback port (so
it takes no connection flags), prints a table and optionally writes the report as JSON.
Exit code 0 when every goal is met (memory growth <= 5 % after warm-up, nothing lost, no
restarts, no stalled stage), 3 when one is missed.
"""

from __future__ import annotations

import argparse
import sys
from typing import Any

from services.evidence.soak import SoakConfig, format_report, run_soak
from services.lib.argtypes import (
    non_negative_float,
    non_negative_int,
    port_number,
    positive_float,
    report_file,
)

from ._common import command_parser, stop_on_signals, write_report

GOAL_MISSED = 3


def register(subparsers: Any) -> None:
    parser = command_parser(
        subparsers,
        "soak",
        "run the whole pipeline at full speed; report memory growth and lost elements",
        network=False,
    )
    add_arguments(parser)
    parser.set_defaults(func=run)


def add_arguments(parser: argparse.ArgumentParser) -> None:
    d = SoakConfig()
    parser.add_argument(
        "--duration",
        type=positive_float,
        default=d.duration_s,
        help="seconds (default %(default)s)",
    )
    parser.add_argument(
        "--json", type=report_file, metavar="FILE", help="also write the report as JSON"
    )
    parser.add_argument(
        "--warmup",
        type=non_negative_float,
        help="seconds before memory counts (default: 1/4, at most 60)",
    )
    parser.add_argument(
        "--sample",
        type=positive_float,
        default=d.sample_s,
        help="seconds between memory samples (default %(default)g)",
    )
    parser.add_argument(
        "--check",
        type=positive_float,
        default=d.check_s,
        help="seconds between lost-element audits (default %(default)g)",
    )
    parser.add_argument(
        "--rate",
        type=positive_float,
        default=d.rate,
        help="scenario speed of camera and gyro (default %(default)g)",
    )
    parser.add_argument(
        "--seed", type=non_negative_int, default=d.seed, help="simulator seed (default %(default)s)"
    )
    parser.add_argument(
        "--service-factor",
        type=non_negative_float,
        help="emulate a slow detector (x frame period); default: no emulated load",
    )
    parser.add_argument(
        "--port", type=port_number, help="private rendezvous port (default: a free one)"
    )
    parser.add_argument("--show-logs", action="store_true", help="print the services' logs")


def config_from_args(args: argparse.Namespace) -> SoakConfig:
    return SoakConfig(
        duration_s=args.duration,
        warmup_s=args.warmup,
        sample_s=args.sample,
        check_s=args.check,
        rate=args.rate,
        seed=args.seed,
        service_factor=args.service_factor,
        port=args.port,
        show_logs=args.show_logs,
    )


def run(args: argparse.Namespace) -> int:
    config = config_from_args(args)
    stop = stop_on_signals()
    print(
        f"soak: running camera, gyro, mediator and detector for {config.duration_s:.0f} s "
        "(Ctrl-C stops early)",
        flush=True,
    )
    report = run_soak(config, stop)
    print(format_report(report), flush=True)
    if args.json:
        write_report(args.json, report)
    if stop.is_set():  # stopped early: a stop is a clean exit, never a verdict
        print("soak: stopped early; no verdict on the goals", flush=True)
        return 0
    goals = report["goals"]
    if not all(v for k, v in goals.items() if k != "memory_growth_at_most"):
        print("soak: a goal was missed (see the table above)", file=sys.stderr)
        return GOAL_MISSED
    return 0
