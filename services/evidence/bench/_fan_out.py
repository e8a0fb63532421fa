"""``fan-out``: how the cost grows with consumers of one 1.3 MB frame buffer.

A camera buffer typically has one flow-controlled consumer (the mediator or a detector) and
observers (recorder, viewer, ``watch``). For 1, 4 and 16 subscribers, each its own process:
framegate has one ``FLOW`` subscription and the rest ``OBSERVE``, every one asking for the
payload pushed with its notification; raw has as many default-FIFO subscribers of a
``BLOCK`` publisher. Throughput is counted at the first (the flow-controlled) subscriber,
CPU per element at the producer. Runs alternate raw and framegate as in ``frames``.

Goal (issue 18): framegate/raw at 16 subscribers is at most 1.5× worse than at 1, i.e.
(ratio at 16) / (ratio at 1) >= 1/1.5.
"""

from __future__ import annotations

from ._options import BenchOptions
from ._procs import Worker, WorkerGroup, free_endpoint
from ._records import Goal, Row, ScenarioResult, Side
from ._stats import ratio
from ._throughput import FRAME_BYTES, measure

FULL_COUNTS = (1, 4, 16)
QUICK_COUNTS = (1, 4)
WORSENING_LIMIT = 1.5
QUEUE_SIZE = 8


def run_fan_out(options: BenchOptions) -> ScenarioResult:
    counts = QUICK_COUNTS if options.quick else FULL_COUNTS
    result = ScenarioResult(
        "fan-out",
        params={
            "subscribers": list(counts),
            "payload_bytes": FRAME_BYTES,
            "shared_memory": True,
            "queue_size": QUEUE_SIZE,
            "raw": "BLOCK publisher -> N default-FIFO subscribers (processes), to_bytes()",
            "framegate": "put(wait_s=5) -> 1 FLOW + (N-1) OBSERVE subscriptions (processes), "
            "all pushed; counted at the FLOW one",
        },
    )
    throughput: dict[int, Row] = {}
    for count in counts:
        row = Row(f"{count} subscriber(s)", "throughput", "msg/s", higher_is_better=True)
        cpu = Row(f"{count} subscriber(s): producer CPU", "CPU per element", "us", False)
        _run_count(count, row, cpu, options)
        throughput[count] = row
        result.rows += [row, cpu]
    first, last = throughput[counts[0]], throughput[counts[-1]]
    last.goal = Goal(
        f"fg/raw at {counts[-1]} subs >= fg/raw at {counts[0]} / {WORSENING_LIMIT:g}",
        round(1 / WORSENING_LIMIT, 4),
        True,
        ratio(last.ratio, first.ratio),
    )
    return result


def _run_count(count: int, row: Row, cpu: Row, options: BenchOptions) -> None:
    raw_at, fg_at = free_endpoint(), free_endpoint()
    common = {"shm": True, "size": FRAME_BYTES}
    with WorkerGroup() as group:
        raw_pub = group.start("raw-pub", {**common, "listen": raw_at})
        raw_subs = [group.start("raw-sub", {**common, "connect": raw_at}) for _ in range(count)]
        fg_pub = group.start("fg-pub", {**common, "listen": fg_at, "buffer": "frames"})
        fg_subs = [
            group.start(
                "fg-sub",
                {
                    **common,
                    "connect": fg_at,
                    "buffer": "frames",
                    "queue_size": QUEUE_SIZE,
                    "push": True,
                    "observe": i > 0,
                },
            )
            for i in range(count)
        ]
        # Many processes start at once on a shared machine: give them time.
        group.wait_ready(timeout_s=180.0 + 10.0 * count)
        sides: dict[Side, tuple[Worker, Worker]] = {
            "raw": (raw_pub, raw_subs[0]),
            "framegate": (fg_pub, fg_subs[0]),
        }
        for pair in range(options.pairs):
            for which, (producer, consumer) in sides.items():
                sample = measure(producer, consumer, options.warmup_s, options.duration_s)
                sample["pair"] = pair
                sample["subscribers"] = count
                row.samples(which).append(sample)
                cpu.samples(which).append({"pair": pair, "value": sample["cpu_producer_us"]})
                options.progress(
                    f"fan-out {count} pair {pair + 1}/{options.pairs} {which}: "
                    f"{sample['value']:,.0f} msg/s, producer {sample['cpu_producer_us']:.0f} us/el"
                )
