"""``quality``: microseconds per frame of the blur estimate (``services.lib.quality``).

There is no raw counterpart: the goal is on the centre estimate itself. ``bench_quality``
times wall clock, so each sample also records ``cpu_share``, the fraction of that wall time
this thread was on a CPU: well below 1 means the machine was busy and the figure is high.
The scenario is skipped, not failed, when ``services.lib.quality.bench_quality`` cannot be
imported.
"""

from __future__ import annotations

import importlib
import inspect
import time
from collections.abc import Callable
from typing import Any

from ._options import BenchOptions
from ._records import Goal, Row, ScenarioResult

FULL_FRAMES = 500
QUICK_FRAMES = 100
CENTRE_GOAL_US = 50.0
_CENTRE_KEYS = ("center", "centre")


def _load() -> Callable[..., dict[str, float]] | None:
    try:
        module = importlib.import_module("services.lib.quality")
    except ImportError:
        return None
    found = getattr(module, "bench_quality", None)
    return found if callable(found) else None


def run_quality(options: BenchOptions) -> ScenarioResult:
    bench_quality = _load()
    if bench_quality is None:
        return ScenarioResult(
            "quality", status="skipped", reason="services.lib.quality not available"
        )
    frames = QUICK_FRAMES if options.quick else FULL_FRAMES
    kwargs: dict[str, Any] = {}
    if "frames" in inspect.signature(bench_quality).parameters:
        kwargs["frames"] = frames
    result = ScenarioResult(
        "quality",
        params={"bench_quality": kwargs, "what": "us per frame per blur mode (best of 3)"},
    )
    rows: dict[str, Row] = {}
    for pair in range(options.pairs):
        wall, cpu = time.perf_counter(), time.thread_time()
        timings = bench_quality(**kwargs)
        # bench_quality times wall clock: on a shared machine this says how much of it was ours.
        cpu_share = (time.thread_time() - cpu) / max(time.perf_counter() - wall, 1e-9)
        for mode, micros in timings.items():
            row = rows.setdefault(mode, Row(mode, "blur estimate", "us/frame", False, raw=None))
            row.framegate.append({"pair": pair, "value": float(micros), "cpu_share": cpu_share})
        centre = next((timings[k] for k in _CENTRE_KEYS if k in timings), None)
        options.progress(
            f"quality run {pair + 1}/{options.pairs}: "
            + ", ".join(f"{k} {v:.0f} us" for k, v in timings.items())
            + ("" if centre is None else f" (centre {centre:.1f} us)")
            + f"; this thread had the CPU {100 * cpu_share:.0f}% of the wall time"
        )
    shares = [s["cpu_share"] for row in rows.values() for s in row.framegate]
    if shares and min(shares) < 0.8:
        for row in rows.values():
            row.note = f"wall clock, busy machine: CPU share {min(shares):.2f}..{max(shares):.2f}"
    for key in _CENTRE_KEYS:
        if key in rows:
            rows[key].goal = Goal(
                f"centre estimate <= {CENTRE_GOAL_US:g} us/frame",
                CENTRE_GOAL_US,
                False,
                rows[key].median("framegate"),
            )
    result.rows = list(rows.values())
    return result
