"""``framegate bench``: framegate against raw Zenoh, side by side in one run.

Each scenario alternates raw Zenoh and framegate runs (at least 3 pairs, or 1 with
``--quick``) in separate producer/consumer processes on loopback, then prints median, min and
max per side, the framegate/raw ratio, CPU use and each goal with PASS or MISS.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path
from typing import Any

from services.tools.bench import SCENARIO_NAMES, BenchError, BenchOptions, format_table, run_bench

from ._common import command_parser


def register(subparsers: Any) -> None:
    parser = command_parser(
        subparsers, "bench", "benchmark framegate against raw Zenoh", network=False
    )
    parser.add_argument(
        "scenarios",
        nargs="*",
        metavar="SCENARIO",
        help=f"scenarios to run (default: all): {', '.join(SCENARIO_NAMES)}",
    )
    parser.add_argument(
        "--duration", type=float, metavar="S", help="measured seconds per sample (4, quick 0.5)"
    )
    parser.add_argument(
        "--pairs", type=int, metavar="N", help="raw/framegate run pairs per row (3, quick 1)"
    )
    parser.add_argument("--json", metavar="FILE", help="also write the full report as JSON")
    parser.add_argument(
        "--quick", action="store_true", help="short smoke test: small sizes, one pair (~1 min)"
    )
    parser.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    options = BenchOptions.create(
        tuple(args.scenarios),
        duration_s=args.duration,
        pairs=args.pairs,
        quick=args.quick,
    )
    target = Path(args.json) if args.json else None
    if target is not None and not target.parent.is_dir():
        raise BenchError(f"cannot write --json {target}: directory {target.parent} does not exist")
    report = run_bench(options)
    print(format_table(report), flush=True)
    if target is not None:
        target.write_text(json.dumps(report, indent=2) + "\n")
    failed = [name for name, s in report["scenarios"].items() if s["status"] == "error"]
    return 1 if failed else 0
