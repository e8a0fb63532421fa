"""``memory``: resident memory of a service process holding a buffer full of frames.

Each sample is a fresh process (RSS never shrinks reliably after frees): it opens its
session and offers its buffer, reads its RSS, puts ``count`` distinct frames (retention large
enough to keep them all), reads its RSS again and reports (after − before) / payload bytes.
The raw side holds the same payloads in a plain Python list: the floor for any Python
process. The goal is on framegate's value itself, not on the ratio.
"""

from __future__ import annotations

from ._options import BenchOptions
from ._procs import WorkerGroup, free_endpoint
from ._records import Goal, Row, ScenarioResult
from ._throughput import FRAME_BYTES

FULL_COUNT = 800  # 1.05 GB of frames
QUICK_COUNT = 40  # 52 MB
MEMORY_GOAL = 1.1


def run_memory(options: BenchOptions) -> ScenarioResult:
    count = QUICK_COUNT if options.quick else FULL_COUNT
    result = ScenarioResult(
        "memory",
        params={
            "count": count,
            "payload_bytes_each": FRAME_BYTES,
            "payload_bytes_total": count * FRAME_BYTES,
            "raw": "the same bytes objects in a Python list",
            "framegate": "Producer.put, Retention(max_count=None, max_bytes=None)",
        },
    )
    row = Row("RSS growth / payload bytes", "memory", "x payload", higher_is_better=False)
    for pair in range(options.pairs):
        for side, role in (("raw", "raw-memory"), ("framegate", "fg-memory")):
            with WorkerGroup() as group:
                worker = group.start(
                    role, {"listen": free_endpoint(), "count": count, "size": FRAME_BYTES}
                )
                group.wait_ready(timeout_s=300.0)
                ready = worker.ready
            grown = int(ready["rss_after"]) - int(ready["rss_before"])
            sample = {
                "pair": pair,
                "value": grown / int(ready["payload_bytes"]),
                "rss_before": ready["rss_before"],
                "rss_after": ready["rss_after"],
                "payload_bytes": ready["payload_bytes"],
            }
            row.samples("raw" if side == "raw" else "framegate").append(sample)
            options.progress(
                f"memory pair {pair + 1}/{options.pairs} {side}: "
                f"{grown / 1e6:.1f} MB for {int(ready['payload_bytes']) / 1e6:.1f} MB of payload"
                f" = {sample['value']:.3f}x"
            )
    row.goal = Goal(
        f"RSS growth <= {MEMORY_GOAL:g}x payload", MEMORY_GOAL, False, row.median("framegate")
    )
    result.rows.append(row)
    return result
