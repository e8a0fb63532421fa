"""``latency``: producer put → consumer has the payload, against a raw query round trip.

framegate: the producer puts one element every few milliseconds with the monotonic clock at
the put as its key; the consumer takes the notification, fetches the element (inline for
64 B, one query for a frame) and subtracts that key from its own monotonic clock — the same
clock on one host. raw: ``session.get`` → one reply of the same size copied out to bytes,
timed in the querier. Both sides are paced the same, so neither measures queueing.
"""

from __future__ import annotations

from typing import Any

from ._options import BenchOptions
from ._procs import BenchError, Worker, WorkerGroup, free_endpoint
from ._records import Row, ScenarioResult, ratio_goal
from ._stats import percentile
from ._throughput import FRAME_BYTES

LATENCY_GOAL = 1.5
# Payload size → pause between puts (and between raw queries).
INTERVALS_S = {64: 0.002, FRAME_BYTES: 0.005}


def _label(size: int) -> str:
    return "64 B" if size == 64 else "1280x1024 mono8"


def run_latency(options: BenchOptions) -> ScenarioResult:
    sizes = list(INTERVALS_S)
    result = ScenarioResult(
        "latency",
        params={
            "sizes": sizes,
            "interval_s": {str(k): v for k, v in INTERVALS_S.items()},
            "window_s": options.duration_s,
            "shared_memory": True,
            "raw": "session.get -> one reply of the same size (callback queryable), to_bytes()",
            "framegate": "put -> take() + fetch(); key = monotonic clock at the put",
        },
    )
    p50 = {s: Row(f"{_label(s)} p50", "latency p50", "us", higher_is_better=False) for s in sizes}
    p99 = {s: Row(f"{_label(s)} p99", "latency p99", "us", higher_is_better=False) for s in sizes}
    raw_at, fg_at = free_endpoint(), free_endpoint()
    with WorkerGroup() as group:
        raw_server = group.start("raw-queryable", {"listen": raw_at})
        raw_client = group.start("raw-querier", {"connect": raw_at})
        fg_pub = group.start("fg-lat-pub", {"listen": fg_at, "sizes": sizes})
        fg_sub = group.start("fg-lat-sub", {"connect": fg_at, "sizes": sizes})
        group.wait_ready()
        del raw_server
        for pair in range(options.pairs):
            for size in sizes:
                runs = {
                    "raw": _raw_run(raw_client, size, options.duration_s),
                    "framegate": _fg_run(fg_pub, fg_sub, size, options.duration_s),
                }
                for side, latencies in runs.items():
                    if not latencies:
                        raise BenchError(f"{side} latency run for {size} B produced no samples")
                    base = {"pair": pair, "count": len(latencies)}
                    median_us, tail_us = percentile(latencies, 50), percentile(latencies, 99)
                    p50[size].samples("raw" if side == "raw" else "framegate").append(
                        {**base, "value": median_us, "mean": sum(latencies) / len(latencies)}
                    )
                    p99[size].samples("raw" if side == "raw" else "framegate").append(
                        {**base, "value": tail_us, "max": max(latencies)}
                    )
                    options.progress(
                        f"latency {_label(size)} pair {pair + 1}/{options.pairs} {side}: "
                        f"p50 {median_us:.0f} us, p99 {tail_us:.0f} us ({len(latencies)} samples)"
                    )
    for size in sizes:
        p50[size].goal = ratio_goal(p50[size], LATENCY_GOAL, at_least=False, what="p50")
        result.rows += [p50[size], p99[size]]
    return result


def _raw_run(client: Worker, size: int, seconds: float) -> list[float]:
    answer = client.call(
        "latency", timeout_s=seconds + 30, size=size, seconds=seconds, interval_s=INTERVALS_S[size]
    )
    return [float(v) for v in answer["latencies_us"]]


def _fg_run(producer: Worker, consumer: Worker, size: int, seconds: float) -> list[float]:
    consumer.call("collect", size=size, expect=0, wait_s=0)  # forget stragglers
    sent: dict[str, Any] = producer.call(
        "latency", timeout_s=seconds + 30, size=size, seconds=seconds, interval_s=INTERVALS_S[size]
    )
    answer = consumer.call("collect", timeout_s=30, size=size, expect=int(sent["sent"]), wait_s=10)
    return [float(v) for v in answer["latencies_us"]]
