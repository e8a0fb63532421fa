"""``framegate bench``: framegate against raw Zenoh, side by side in one run.

Each scenario alternates raw Zenoh and framegate runs (at least 3 pairs, or 1 with
``--quick``) in separate producer/consumer processes on loopback, then prints one line per
row (the raw and framegate medians, framegate/raw and the goal with PASS or MISS) within
100 columns; ``--json`` keeps every sample. A 1-minute load average above half the cores at
the start is flagged (the figures are then unreliable). Exit code 1 when a scenario could
not run; with ``--check``, 3 when a goal is missed (without it, a missed goal exits 0).
Ctrl-C or SIGTERM stops the workers and exits 0 without a report.
"""

from __future__ import annotations

import argparse
import sys
from collections.abc import Callable
from pathlib import Path
from typing import Any

from services.evidence.bench import (
    OPT_IN_SCENARIOS,
    SCENARIO_NAMES,
    BenchOptions,
    format_table,
    run_bench,
)
from services.lib.argtypes import positive_float, positive_int, report_file

from ._common import command_parser, exit_on_sigterm, write_report

GOAL_MISSED = 3


def register(subparsers: Any) -> None:
    parser = command_parser(
        subparsers, "bench", "benchmark framegate against raw Zenoh", network=False
    )
    parser.add_argument(
        "scenarios",
        nargs="*",
        metavar="SCENARIO",
        help=f"scenarios to run (default: all): {', '.join(SCENARIO_NAMES)}; "
        f"only when named: {', '.join(OPT_IN_SCENARIOS)}",
    )
    parser.add_argument(
        "--duration",
        type=positive_float,
        metavar="S",
        help="measured seconds per sample (4, quick 0.5); also the hostile scenario's "
        "window (120, quick 10); ros2-loop's windows are at least 45 s (quick 15)",
    )
    parser.add_argument(
        "--pairs",
        type=positive_int,
        metavar="N",
        help="raw/framegate run pairs per row (3, quick 1)",
    )
    parser.add_argument(
        "--json", type=report_file, metavar="FILE", help="also write the full report as JSON"
    )
    parser.add_argument(
        "--quick", action="store_true", help="short smoke test: small sizes, one pair (~2 min)"
    )
    parser.add_argument(
        "--check", action="store_true", help=f"exit {GOAL_MISSED} when any goal is missed"
    )
    parser.add_argument(
        "-v", "--verbose", action="store_true", help="print every sample while running"
    )
    parser.set_defaults(func=run)


def progress_printer(verbose: bool) -> Callable[[str], None]:
    """Progress on stderr: every message with ``verbose``, else scenario starts and warnings
    (a failed scenario's reason is in the table either way)."""

    def show(message: str) -> None:
        if verbose or message.startswith(("== ", "WARNING")):
            print(message, file=sys.stderr, flush=True)

    return show


def exit_code(report: dict[str, Any], check: bool) -> int:
    """1 when a scenario failed; with ``check``, GOAL_MISSED when a goal was missed; else 0."""
    if any(s["status"] == "error" for s in report["scenarios"].values()):
        return 1
    if check and any(goal["passed"] is False for goal in report["goals"]):
        return GOAL_MISSED
    return 0


def run(args: argparse.Namespace) -> int:
    options = BenchOptions.create(
        tuple(args.scenarios),
        duration_s=args.duration,
        pairs=args.pairs,
        quick=args.quick,
        progress=progress_printer(args.verbose),
    )
    target: Path | None = args.json  # checked as it was parsed (``report_file``)
    exit_on_sigterm()  # SIGTERM stops the workers as Ctrl-C does
    try:
        report = run_bench(options)
    except KeyboardInterrupt:
        print("bench: interrupted; no report", file=sys.stderr, flush=True)
        return 0
    print(format_table(report, notes=args.verbose), flush=True)
    if target is not None:
        write_report(target, report)
    return exit_code(report, args.check)
