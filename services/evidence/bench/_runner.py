"""Running the chosen scenarios and collecting one JSON-ready report.

Report keys (``SCHEMA`` = ``framegate-bench/1``): ``schema``, ``created_utc``,
``elapsed_s``, ``machine`` (cpu_count, physical_cores, memory_bytes, load_average_start/end,
platform, python, zenoh, numpy, msgpack, psutil), ``options`` (scenarios, duration_s,
pairs, quick, warmup_s), ``scenarios`` (name → status, reason, params, elapsed_s, rows) and
``goals`` (scenario, row, text, limit, comparison, measured, passed) and ``warnings``
(e.g. a load at start that makes the figures unreliable). Each row holds
``raw`` and ``framegate`` (samples, median, min, max, count, cpu_pct), ``ratio``
(framegate/raw medians), ``extra`` (framegate - raw medians), ``pair_ratios``
(framegate/raw of each pair), ``goal`` and ``note``.
"""

from __future__ import annotations

import os
import platform
import sys
import time
import traceback
from collections.abc import Callable
from datetime import UTC, datetime
from importlib import metadata
from typing import Any

import psutil

from middleware import TransportError

from ._fan_out import run_fan_out
from ._hostile import run_hostile
from ._idle import run_idle
from ._latency import run_latency
from ._memory import run_memory
from ._options import BenchOptions
from ._quality import run_quality
from ._query_scaling import run_query_scaling
from ._records import ScenarioResult
from ._report import load_warning
from ._ros2 import run_ros2
from ._ros2_loop import run_ros2_loop
from ._startup import run_startup
from ._throughput import run_batch, run_frames, run_small
from ._working_point import run_working_point

SCHEMA = "framegate-bench/1"
# Figures are flagged unreliable when the 1-min load at start exceeds this share of the cores.
LOAD_WARNING_SHARE = 0.5
# A scenario that could not open a Zenoh session is run again this many times: its private
# port, free when chosen, can be taken by another process before its session listens.
TRANSPORT_RETRIES = 1

SCENARIOS: dict[str, Callable[[BenchOptions], ScenarioResult]] = {
    "frames": run_frames,
    "small": run_small,
    "batch": run_batch,
    "latency": run_latency,
    "fan-out": run_fan_out,
    "working-point": run_working_point,
    "query-scaling": run_query_scaling,
    "memory": run_memory,
    "quality": run_quality,
    "idle": run_idle,
    "hostile": run_hostile,
    "ros2": run_ros2,
    "startup": run_startup,
    "ros2-loop": run_ros2_loop,
}


def _version(distribution: str) -> str | None:
    try:
        return metadata.version(distribution)
    except metadata.PackageNotFoundError:
        return None


def machine_info() -> dict[str, Any]:
    """Cores, memory, load and the versions that decide the numbers."""
    return {
        "cpu_count": os.cpu_count(),
        "physical_cores": psutil.cpu_count(logical=False),
        "memory_bytes": psutil.virtual_memory().total,
        "load_average_start": list(os.getloadavg()),
        "platform": platform.platform(),
        "python": sys.version.split()[0],
        "zenoh": _version("eclipse-zenoh"),
        "numpy": _version("numpy"),
        "msgpack": _version("msgpack"),
        "psutil": _version("psutil"),
    }


def _run_scenario(name: str, options: BenchOptions) -> ScenarioResult:
    for attempt in range(TRANSPORT_RETRIES + 1):
        try:
            return SCENARIOS[name](options)
        except TransportError as exc:
            if attempt == TRANSPORT_RETRIES:
                raise
            options.progress(f"{name}: {exc}; running it again")
    raise AssertionError("unreachable")


def run_bench(options: BenchOptions) -> dict[str, Any]:
    """Run ``options.scenarios`` in order; a failing scenario is reported, not raised."""
    started = time.monotonic()
    report: dict[str, Any] = {
        "schema": SCHEMA,
        "created_utc": datetime.now(UTC).isoformat(timespec="seconds"),
        "machine": machine_info(),
        "options": options.as_json(),
        "scenarios": {},
        "goals": [],
        "warnings": [],
    }
    warning = load_warning(report["machine"], LOAD_WARNING_SHARE)
    if warning is not None:
        report["warnings"].append(warning)
        options.progress(f"WARNING: {warning}")
    for name in options.scenarios:
        began = time.monotonic()
        options.progress(f"== {name}")
        try:
            result = _run_scenario(name, options)
        except Exception as exc:  # one broken scenario must not hide the others' numbers
            options.progress("".join(traceback.format_exception(exc)).rstrip())
            result = ScenarioResult(name, status="error", reason=f"{type(exc).__name__}: {exc}")
        result.elapsed_s = time.monotonic() - began
        report["scenarios"][name] = result.as_json()
        for row in result.rows:
            if row.goal is not None:
                report["goals"].append({"scenario": name, "row": row.name, **row.goal.as_json()})
    report["machine"]["load_average_end"] = list(os.getloadavg())
    report["elapsed_s"] = round(time.monotonic() - started, 3)
    return report
