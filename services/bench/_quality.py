"""``quality``: microseconds per frame of the blur estimate (``services.quality``).

There is no raw counterpart: the goal is on the centre estimate itself. The scenario is
skipped, not failed, when ``services.quality.bench_quality`` cannot be imported.
"""

from __future__ import annotations

import importlib
import inspect
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
        module = importlib.import_module("services.quality")
    except ImportError:
        return None
    found = getattr(module, "bench_quality", None)
    return found if callable(found) else None


def run_quality(options: BenchOptions) -> ScenarioResult:
    bench_quality = _load()
    if bench_quality is None:
        return ScenarioResult("quality", status="skipped", reason="services.quality not available")
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
        timings = bench_quality(**kwargs)
        for mode, micros in timings.items():
            row = rows.setdefault(mode, Row(mode, "blur estimate", "us/frame", False, raw=None))
            row.framegate.append({"pair": pair, "value": float(micros)})
        centre = next((timings[k] for k in _CENTRE_KEYS if k in timings), None)
        options.progress(
            f"quality run {pair + 1}/{options.pairs}: "
            + ", ".join(f"{k} {v:.0f} us" for k, v in timings.items())
            + ("" if centre is None else f" (centre {centre:.1f} us)")
        )
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
