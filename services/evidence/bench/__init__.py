"""Benchmarks: framegate against raw Zenoh, side by side in one run, and how cost grows.

Every scenario runs raw Zenoh and framegate alternately (raw, framegate, raw, ...), each
side in its own producer and consumer processes on loopback, and reports median, min and max
per side, the framegate/raw ratio and the goal it is held to. ``framegate bench`` is the
command; ``run_bench(BenchOptions.create(...))`` returns the JSON-ready report.
"""

from __future__ import annotations

from importlib import import_module
from typing import TYPE_CHECKING, Any

if TYPE_CHECKING:
    from ._options import OPT_IN_SCENARIOS, SCENARIO_NAMES, BenchOptions
    from ._procs import BenchError
    from ._records import Goal, Row, ScenarioResult
    from ._report import format_table
    from ._runner import SCHEMA, machine_info, run_bench
    from ._stats import Summary, median, percentile, ratio, summarize

# Each name is imported from its module when first asked for: a worker process
# (``python -m services.evidence.bench._worker``) imports this package first, and importing
# every scenario here cost each of the hundred-odd workers of a quick run about a second of
# CPU before it measured anything (and put framegate's modules into the raw baseline's
# processes).
_HOMES = {
    **dict.fromkeys(("OPT_IN_SCENARIOS", "SCENARIO_NAMES", "BenchOptions"), "._options"),
    "BenchError": "._procs",
    **dict.fromkeys(("Goal", "Row", "ScenarioResult"), "._records"),
    "format_table": "._report",
    **dict.fromkeys(("SCHEMA", "machine_info", "run_bench"), "._runner"),
    **dict.fromkeys(("Summary", "median", "percentile", "ratio", "summarize"), "._stats"),
}

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


def __getattr__(name: str) -> Any:
    home = _HOMES.get(name)
    if home is None:
        raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
    value = getattr(import_module(home, __name__), name)
    globals()[name] = value
    return value
