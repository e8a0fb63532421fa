"""Benchmarks: framegate against raw Zenoh, side by side in one run, and how cost grows.

Every scenario runs raw Zenoh and framegate alternately (raw, framegate, raw, ...), each
side in its own producer and consumer processes on loopback, and reports median, min and max
per side, the framegate/raw ratio and the goal it is held to. ``framegate bench`` is the
command; ``run_bench(BenchOptions.create(...))`` returns the JSON-ready report.
"""

from ._options import OPT_IN_SCENARIOS, SCENARIO_NAMES, BenchOptions
from ._procs import BenchError
from ._records import Goal, Row, ScenarioResult
from ._report import format_table
from ._runner import SCHEMA, machine_info, run_bench
from ._stats import Summary, median, percentile, ratio, summarize

__all__ = [
    "OPT_IN_SCENARIOS",
    "SCENARIO_NAMES",
    "SCHEMA",
    "BenchError",
    "BenchOptions",
    "Goal",
    "Row",
    "ScenarioResult",
    "Summary",
    "format_table",
    "machine_info",
    "median",
    "percentile",
    "ratio",
    "run_bench",
    "summarize",
]
