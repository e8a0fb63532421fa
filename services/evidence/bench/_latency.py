"""``latency``: producer put → consumer has the payload, against raw one-way pub → sub.

framegate: the producer puts one element every few milliseconds with the monotonic clock at
the put as its key; the consumer takes the notification, has the payload (inline for 64 B,
pushed with the notification for the pushed frame stream, one query for the fetched one)
and subtracts that key from its own monotonic clock — the same clock on one host. raw: a
publisher puts a payload of the same size with the monotonic clock in its first 8 bytes; a
subscriber copies it out to ``bytes`` and subtracts. Both are paced the same, so neither
measures queueing. The fetched frame has no goal: a fetch is a notification plus a query
round trip by design, beside the one-way baseline for scale.
"""

from __future__ import annotations

from dataclasses import dataclass

from ._options import BenchOptions
from ._procs import BenchError, Worker, WorkerGroup, free_endpoint
from ._records import Row, ScenarioResult, Side, ratio_goal
from ._stats import percentile
from ._throughput import FRAME_BYTES

LATENCY_GOAL = 1.3
LATENCY_P99_GOAL = 2.0
# Payload size → pause between puts.
INTERVALS_S = {64: 0.002, FRAME_BYTES: 0.005}


@dataclass(frozen=True, slots=True)
class Stream:
    """One framegate latency row pair (p50, p99) and the raw size it is compared with."""

    name: str
    label: str
    size: int
    push: bool
    goal: bool

    def as_json(self) -> dict[str, object]:
        return {"name": self.name, "size": self.size, "push": self.push}


STREAMS = (
    Stream("lat64", "64 B", 64, push=False, goal=True),
    Stream("latpush", "1280x1024 mono8 pushed", FRAME_BYTES, push=True, goal=True),
    Stream("latfetch", "1280x1024 mono8 fetched", FRAME_BYTES, push=False, goal=False),
)


def run_latency(options: BenchOptions) -> ScenarioResult:
    sizes = list(INTERVALS_S)
    result = ScenarioResult(
        "latency",
        params={
            "streams": [s.as_json() for s in STREAMS],
            "interval_s": {str(k): v for k, v in INTERVALS_S.items()},
            "window_s": options.duration_s,
            "shared_memory": True,
            "raw": "one-way: publisher (BLOCK) -> default FIFO subscriber, to_bytes(); "
            "monotonic clock in the payload",
            "framegate": "put -> take() (+ fetch() unless pushed or inline); "
            "key = monotonic clock at the put",
        },
    )
    p50 = {s.name: Row(f"{s.label} p50", "latency p50", "us", False) for s in STREAMS}
    p99 = {s.name: Row(f"{s.label} p99", "latency p99", "us", False) for s in STREAMS}
    raw_at, fg_at = free_endpoint(), free_endpoint()
    streams = [s.as_json() for s in STREAMS]
    with WorkerGroup() as group:
        raw_pub = group.start("raw-lat-pub", {"listen": raw_at, "sizes": sizes})
        raw_sub = group.start("raw-lat-sub", {"connect": raw_at, "sizes": sizes})
        fg_pub = group.start("fg-lat-pub", {"listen": fg_at, "streams": streams})
        fg_sub = group.start("fg-lat-sub", {"connect": fg_at, "streams": streams})
        group.wait_ready()
        for pair in range(options.pairs):
            for size in sizes:
                raw = _run(raw_pub, raw_sub, str(size), size, options.duration_s)
                _record(p50, p99, [s.name for s in STREAMS if s.size == size], "raw", raw, pair)
                _progress(options, pair, f"raw {size} B", raw)
            for stream in STREAMS:
                fg = _run(fg_pub, fg_sub, stream.name, stream.size, options.duration_s)
                _record(p50, p99, [stream.name], "framegate", fg, pair)
                _progress(options, pair, f"framegate {stream.label}", fg)
    for stream in STREAMS:
        if stream.goal:
            p50[stream.name].goal = ratio_goal(
                p50[stream.name], LATENCY_GOAL, at_least=False, what="p50"
            )
            p99[stream.name].goal = ratio_goal(
                p99[stream.name], LATENCY_P99_GOAL, at_least=False, what="p99"
            )
        else:
            p50[stream.name].note = "fetched: notification + query round trip, no goal"
        result.rows += [p50[stream.name], p99[stream.name]]
    return result


def _record(
    p50: dict[str, Row],
    p99: dict[str, Row],
    names: list[str],
    side: Side,
    latencies: list[float],
    pair: int,
) -> None:
    base = {"pair": pair, "count": len(latencies)}
    for name in names:
        p50[name].samples(side).append(
            {**base, "value": percentile(latencies, 50), "mean": sum(latencies) / len(latencies)}
        )
        p99[name].samples(side).append(
            {**base, "value": percentile(latencies, 99), "max": max(latencies)}
        )


def _progress(options: BenchOptions, pair: int, what: str, latencies: list[float]) -> None:
    options.progress(
        f"latency pair {pair + 1}/{options.pairs} {what}: p50 {percentile(latencies, 50):.0f}"
        f" us, p99 {percentile(latencies, 99):.0f} us ({len(latencies)} samples)"
    )


def _run(producer: Worker, consumer: Worker, stream: str, size: int, seconds: float) -> list[float]:
    """One paced run; the consumer's latencies (us). Raw streams are named by their size."""
    consumer.call("collect", stream=stream, expect=0, wait_s=0)  # forget stragglers
    interval_s = INTERVALS_S[size]
    sent = producer.call(
        "latency",
        timeout_s=seconds + 30,
        stream=stream,
        size=size,
        seconds=seconds,
        interval_s=interval_s,
    )
    answer = consumer.call("collect", timeout_s=30, stream=stream, expect=sent["sent"], wait_s=10)
    latencies = [float(v) for v in answer["latencies_us"]]
    if not latencies:
        raise BenchError(f"latency run of {stream} ({size} B) produced no samples")
    return latencies
