"""Throughput scenarios: ``frames`` (1280×1024 mono8, SHM and TCP, and an inline size),
``small`` (64 B) and ``batch`` (64 B in batches), framegate's notify-then-fetch against raw
pub/sub of the same payload.

Each mode starts a raw pair and a framegate pair of processes once, then alternates runs
(raw, framegate, raw, framegate, ...). In a run the producer puts as fast as it may (raw:
BLOCK congestion control; framegate: ``put(..., wait_s=5)``, never refused) while the parent
marks the consumer's count at the start and end of the measured window; the rate comes from
the consumer's own clock. CPU is each process's user+system time over the same window, as
% of one core and as microseconds per element received; each throughput row is followed by
a producer and a consumer CPU row (framegate, raw and framegate - raw side by side).
Between runs the consumer drains everything, so the runs never overlap. ``batch`` is the
64 B row through ``put_many``/``take_many``.

``small`` also measures, in the same pairs, a raw subscriber through each handler design
zenoh-python offers (``_raw.HANDLER_DESIGNS``): one row per design with that design's
msg/s and subscriber CPU per message as the raw side and framegate's 64 B figures as the
other, so the ceiling each design allows stands next to framegate's. The FIFO design is
the raw baseline's own subscriber, so its row reuses the baseline's samples.
"""

from __future__ import annotations

import time
from dataclasses import dataclass
from typing import Any

from ._options import BenchOptions
from ._procs import BenchError, Worker, WorkerGroup, free_endpoint
from ._raw import HANDLER_DESIGNS
from ._records import Goal, Row, ScenarioResult, Side, extra_goal, ratio_goal

FRAME_BYTES = 1280 * 1024  # one mono8 frame
INLINE_BYTES = 64 * 1024  # the largest payload the middleware sends inline by default
SMALL_BYTES = 64

# Issue 18's targets, framegate/raw of elements per second.
FRAMES_GOAL = 0.9
INLINE_GOAL = 0.5
SMALL_GOAL = 0.1
BATCH_GOAL = 0.5
FETCHED_FRAMES_GOAL = 0.5
# framegate's CPU per 64 B element, on each side (us).
SMALL_CPU_US = 20.0
# framegate's extra CPU per pushed 1.3 MB frame, on each side (us).
FRAME_EXTRA_CPU_US = 50.0
# Elements per put_many / take_many in the batch row.
BATCH_ELEMENTS = 64


@dataclass(frozen=True, slots=True)
class Mode:
    """One throughput row: payload size, transport, the subscriber's queue size, goals."""

    name: str
    size: int
    shared_memory: bool
    queue_size: int
    goal: float
    # Framegate side: payloads pushed with their notification instead of fetched.
    push: bool = False
    # Framegate side: Producer.put_many / Subscription.take_many of BATCH_ELEMENTS.
    batch: bool = False
    # Goal on framegate's extra CPU per element on each side (us), if any.
    extra_cpu_us: float | None = None
    # Goal on framegate's CPU per element on each side (us), if any.
    cpu_us: float | None = None
    # Raw subscriber handler designs (keys of HANDLER_DESIGNS) measured in the same pairs.
    designs: tuple[str, ...] = ()
    # Also run raw paced at the rate framegate reached in the same pair: CPU per element at
    # equal rates (an isolated Zenoh put costs far more than one of a back-to-back stream).
    same_rate: bool = False

    def as_json(self) -> dict[str, Any]:
        return {
            "name": self.name,
            "payload_bytes": self.size,
            "shared_memory": self.shared_memory,
            "queue_size": self.queue_size,
            "push": self.push,
            "batch": BATCH_ELEMENTS if self.batch else None,
        }


FRAME_MODES = (
    Mode("1280x1024 mono8, shm", FRAME_BYTES, True, 8, FETCHED_FRAMES_GOAL),
    Mode(
        "1280x1024 mono8, shm, pushed",
        FRAME_BYTES,
        True,
        8,
        FRAMES_GOAL,
        push=True,
        extra_cpu_us=FRAME_EXTRA_CPU_US,
    ),
    Mode("1280x1024 mono8, tcp", FRAME_BYTES, False, 8, FETCHED_FRAMES_GOAL),
    Mode(
        "1280x1024 mono8, tcp, pushed",
        FRAME_BYTES,
        False,
        8,
        FRAMES_GOAL,
        push=True,
        extra_cpu_us=FRAME_EXTRA_CPU_US,
    ),
    Mode("64 KiB inline, shm", INLINE_BYTES, True, 8, INLINE_GOAL),
)
SMALL_MODES = (
    Mode(
        "64 B",
        SMALL_BYTES,
        True,
        8,
        SMALL_GOAL,
        cpu_us=SMALL_CPU_US,
        designs=tuple(HANDLER_DESIGNS),
        same_rate=True,
    ),
)
# Short labels of the handler designs, for row names.
DESIGN_LABELS = {
    "callback-direct": "Callback indirect=False",
    "callback": "Callback (indirect)",
    "fifo": "FifoChannel(256)+thread",
    "ring": "RingChannel(4096) batch",
}
BATCH_MODES = (
    Mode(
        f"64 B, batches of {BATCH_ELEMENTS}",
        SMALL_BYTES,
        True,
        2 * BATCH_ELEMENTS,  # a flow queue holds two batches: one taken, one arriving
        BATCH_GOAL,
        batch=True,
    ),
)


def run_frames(options: BenchOptions) -> ScenarioResult:
    return _run("frames", FRAME_MODES, options)


def run_small(options: BenchOptions) -> ScenarioResult:
    return _run("small", SMALL_MODES, options)


def run_batch(options: BenchOptions) -> ScenarioResult:
    return _run("batch", BATCH_MODES, options)


def wakeup_rows(name: str) -> tuple[Row, Row]:
    """Producer and consumer thread wake-ups per element of one throughput row (see
    ``Worker.wakeups``): the structural cost that CPU figures on a shared machine blur."""
    note = "voluntary context switches of all the process's threads / elements received"
    return (
        Row(f"{name}: producer wake-ups", "wake-ups per element", "/el", False, note=note),
        Row(f"{name}: consumer wake-ups", "wake-ups per element", "/el", False, note=note),
    )


def cpu_rows(name: str, note: str = "") -> tuple[Row, Row]:
    """Producer and consumer CPU per element of one throughput row."""
    return (
        Row(f"{name}: producer CPU", "CPU per element", "us", higher_is_better=False, note=note),
        Row(f"{name}: consumer CPU", "CPU per element", "us", higher_is_better=False, note=note),
    )


def same_rate_rows(name: str) -> tuple[Row, Row]:
    """CPU per element with raw paced at framegate's rate of the same pair."""
    note = (
        "raw side: raw Zenoh's publisher paced at the rate framegate reached in the same "
        "pair (one put every 1/rate s); framegate side: framegate's figure. Per element at "
        "equal rates, where the as-fast-as-possible raw rows compare a back-to-back stream"
    )
    return cpu_rows(f"{name} at framegate's rate", note)


def _run(scenario: str, modes: tuple[Mode, ...], options: BenchOptions) -> ScenarioResult:
    result = ScenarioResult(
        scenario,
        params={
            "modes": [m.as_json() for m in modes],
            "warmup_s": options.warmup_s,
            "window_s": options.duration_s,
            "raw": "publisher CongestionControl.BLOCK -> default FIFO subscriber, to_bytes()",
            "framegate": "put(wait_s=5) -> subscribe(queue_size) take() + fetch() "
            "(pushed: the payload comes with the notification; batch: put_many/take_many)",
            "cpu": "user+system CPU of each process over the window / elements received",
        },
    )
    for mode in modes:
        row = Row(mode.name, "throughput", "msg/s", higher_is_better=True)
        producer_cpu, consumer_cpu = cpu_rows(mode.name)
        woken = wakeup_rows(mode.name)
        designs = {design: design_rows(mode.name, design) for design in mode.designs}
        same_rate = same_rate_rows(mode.name) if mode.same_rate else None
        _run_mode(
            scenario, mode, (row, producer_cpu, consumer_cpu), woken, designs, same_rate, options
        )
        row.goal = ratio_goal(row, mode.goal, at_least=True, what="throughput")
        if mode.extra_cpu_us is not None:
            for cpu_row in (producer_cpu, consumer_cpu):
                cpu_row.goal = extra_goal(cpu_row, mode.extra_cpu_us, what="CPU per frame")
        if mode.cpu_us is not None:
            for cpu_row in (producer_cpu, consumer_cpu):
                cpu_row.goal = cpu_goal(cpu_row, mode.cpu_us)
        result.rows += [row, producer_cpu, consumer_cpu, *woken, *(same_rate or ())]
        for design_row, design_cpu in designs.values():
            result.rows += [design_row, design_cpu]
    if any(mode.designs for mode in modes):
        result.params["designs"] = {d: HANDLER_DESIGNS[d] for mode in modes for d in mode.designs}
    return result


def design_rows(mode_name: str, design: str) -> tuple[Row, Row]:
    """A raw handler design's throughput and subscriber CPU rows (raw: the design,
    framegate: framegate's figure of the same mode, so the ratio is the share of the
    ceiling that design allows)."""
    name = f"{mode_name} sub {DESIGN_LABELS[design]}"
    note = (
        f"raw side of the '{mode_name} sub ...' rows: a raw subscriber through that "
        "zenoh-python handler design (same publisher, same pairs); framegate side: "
        f"framegate's {mode_name} figure; a RingChannel drops the oldest sample when full "
        "(each sample's 'lost' in --json)"
    )
    return (
        Row(name, "throughput", "msg/s", higher_is_better=True, note=note),
        Row(f"{name}: CPU", "CPU per element", "us", higher_is_better=False, note=note),
    )


def cpu_goal(row: Row, limit_us: float) -> Goal:
    """framegate's own CPU per element (not the difference to raw) at most ``limit_us``."""
    return Goal(
        f"framegate CPU per element <= {limit_us:g} us", limit_us, False, row.median("framegate")
    )


def _run_mode(
    scenario: str,
    mode: Mode,
    rows: tuple[Row, Row, Row],
    woken: tuple[Row, Row],
    designs: dict[str, tuple[Row, Row]],
    same_rate: tuple[Row, Row] | None,
    options: BenchOptions,
) -> None:
    row, producer_cpu, consumer_cpu = rows
    raw_at, fg_at = free_endpoint(), free_endpoint()
    common = {"shm": mode.shared_memory, "size": mode.size}
    with WorkerGroup() as group:
        design_pairs: dict[str, tuple[Worker, Worker]] = {}
        for design in designs:
            if design == "fifo":  # the baseline's own subscriber: its samples are reused
                continue
            at = free_endpoint()
            design_pairs[design] = (
                group.start("raw-pub", {**common, "listen": at}),
                group.start("raw-handler-sub", {**common, "connect": at, "design": design}),
            )
        sides = {
            "raw": (
                group.start("raw-pub", {**common, "listen": raw_at}),
                group.start("raw-sub", {**common, "connect": raw_at}),
            ),
            "framegate": (
                group.start(
                    "fg-pub",
                    {**common, "listen": fg_at, "buffer": "data", "batch": _batch(mode)},
                ),
                group.start(
                    "fg-sub",
                    {
                        **common,
                        "connect": fg_at,
                        "buffer": "data",
                        "queue_size": mode.queue_size,
                        "push": mode.push,
                        "batch": _batch(mode),
                    },
                ),
            ),
        }
        group.wait_ready()
        for pair in range(options.pairs):
            for side in ("raw", "framegate"):
                producer, consumer = sides[side]
                sample = measure(producer, consumer, options.warmup_s, options.duration_s)
                sample["pair"] = pair
                which: Side = "raw" if side == "raw" else "framegate"
                row.samples(which).append(sample)
                for cpu_row, role in ((producer_cpu, "producer"), (consumer_cpu, "consumer")):
                    cpu_row.samples(which).append({"pair": pair, "value": sample[f"cpu_{role}_us"]})
                for woken_row, role in zip(woken, ("producer", "consumer"), strict=True):
                    woken_row.samples(which).append(
                        {"pair": pair, "value": sample[f"wakeups_{role}"]}
                    )
                options.progress(_progress(scenario, mode.name, pair, options.pairs, side, sample))
                if side == "raw":
                    for design, (design_pub, design_sub) in design_pairs.items():
                        found = measure(
                            design_pub, design_sub, options.warmup_s, options.duration_s
                        )
                        found["pair"] = pair
                        designs[design][0].samples("raw").append(found)
                        designs[design][1].samples("raw").append(
                            {"pair": pair, "value": found["cpu_consumer_us"]}
                        )
                        options.progress(
                            _progress(scenario, mode.name, pair, options.pairs, design, found)
                        )
                    if "fifo" in designs:
                        designs["fifo"][0].samples("raw").append(sample)
                        designs["fifo"][1].samples("raw").append(
                            {"pair": pair, "value": sample["cpu_consumer_us"]}
                        )
            for design_row, design_cpu in designs.values():
                design_row.framegate.append(row.framegate[-1])
                design_cpu.framegate.append(consumer_cpu.framegate[-1])
            if same_rate is not None:
                _measure_same_rate(sides["raw"], row, (producer_cpu, consumer_cpu), same_rate)
                producer_us, consumer_us = (r.samples("raw")[-1]["value"] for r in same_rate)
                options.progress(
                    f"{scenario} {mode.name} pair {pair + 1}/{options.pairs} raw at "
                    f"framegate's rate: CPU producer {producer_us:.1f} us/el, consumer "
                    f"{consumer_us:.1f} us/el"
                )


def _measure_same_rate(
    raw: tuple[Worker, Worker],
    row: Row,
    cpu: tuple[Row, Row],
    same_rate: tuple[Row, Row],
) -> None:
    """One raw run paced at the rate framegate's last sample of ``row`` reached, into the
    raw side of ``same_rate``; framegate's CPU of that sample into its framegate side."""
    fg = row.framegate[-1]
    pair = fg["pair"]
    window_s = fg["window_s"]
    sample = measure(*raw, min(1.0, window_s), window_s, interval_s=1.0 / fg["value"])
    for paced_row, fg_row, role in zip(same_rate, cpu, ("producer", "consumer"), strict=True):
        paced_row.samples("raw").append(
            {"pair": pair, "value": sample[f"cpu_{role}_us"], "rate": sample["value"]}
        )
        paced_row.samples("framegate").append(fg_row.framegate[-1])


def _progress(
    scenario: str, mode: str, pair: int, pairs: int, side: str, sample: dict[str, Any]
) -> str:
    return (
        f"{scenario} {mode} pair {pair + 1}/{pairs} {side}: "
        f"{sample['value']:,.0f} msg/s, CPU producer {sample['cpu_producer_pct']:.0f}%"
        f" ({sample['cpu_producer_us']:.1f} us/el), consumer "
        f"{sample['cpu_consumer_pct']:.0f}% ({sample['cpu_consumer_us']:.1f} us/el)"
    )


def _batch(mode: Mode) -> int:
    return BATCH_ELEMENTS if mode.batch else 0


# Runs whose window received nothing are repeated this often before the row fails: on a
# loaded machine a short (--quick) window can fall into one scheduling stall of a process.
EMPTY_WINDOW_RETRIES = 2


def measure(
    producer: Worker,
    consumer: Worker,
    warmup_s: float,
    window_s: float,
    *,
    interval_s: float = 0.0,
) -> dict[str, Any]:
    """One run: produce for warm-up + window (as fast as allowed, or one element every
    ``interval_s``), mark the consumer around the window, drain. A run whose window stayed
    empty is repeated (at most ``EMPTY_WINDOW_RETRIES`` times); the sample says how many
    were (``empty_windows``)."""
    for attempt in range(EMPTY_WINDOW_RETRIES + 1):
        sample = _measure_once(producer, consumer, warmup_s, window_s, interval_s)
        if sample["count"] > 0:
            return {**sample, "empty_windows": attempt}
    raise BenchError(f"the consumer received nothing in {attempt + 1} windows of {window_s} s")


def _measure_once(
    producer: Worker, consumer: Worker, warmup_s: float, window_s: float, interval_s: float
) -> dict[str, Any]:
    start = consumer.call("mark")
    producer.send("produce", seconds=warmup_s + window_s + 0.3, interval_s=interval_s)
    time.sleep(warmup_s)
    cpu0 = (time.monotonic(), producer.cpu_s(), consumer.cpu_s())
    woken0 = (producer.wakeups(), consumer.wakeups())
    first = consumer.call("mark")
    time.sleep(window_s)
    cpu1 = (time.monotonic(), producer.cpu_s(), consumer.cpu_s())
    woken1 = (producer.wakeups(), consumer.wakeups())
    last = consumer.call("mark")
    done = producer.recv(timeout_s=warmup_s + window_s + 30.0)
    received = _drain(consumer, start["count"], int(done["sent"]))
    elapsed_s = (last["t_ns"] - first["t_ns"]) / 1e9
    wall_s = cpu1[0] - cpu0[0]
    if elapsed_s <= 0 or wall_s <= 0:
        raise BenchError(f"empty measuring window ({elapsed_s} s)")
    count = last["count"] - first["count"]
    if count <= 0:
        return {"count": 0}
    return {
        "value": count / elapsed_s,
        "mb_s": (last["bytes"] - first["bytes"]) / elapsed_s / 1e6,
        "count": count,
        "window_s": elapsed_s,
        "sent": int(done["sent"]),
        "received": received,
        "lost": int(done["sent"]) - received,
        "errors": last["errors"] - first["errors"],
        "cpu_producer_pct": 100.0 * (cpu1[1] - cpu0[1]) / wall_s,
        "cpu_consumer_pct": 100.0 * (cpu1[2] - cpu0[2]) / wall_s,
        "cpu_producer_us": 1e6 * (cpu1[1] - cpu0[1]) / count,
        "cpu_consumer_us": 1e6 * (cpu1[2] - cpu0[2]) / count,
        # A thread that ended in the window takes its count with it: never below 0.
        "wakeups_producer": max(0, woken1[0] - woken0[0]) / count,
        "wakeups_consumer": max(0, woken1[1] - woken0[1]) / count,
    }


def _drain(consumer: Worker, base: int, sent: int, timeout_s: float = 10.0) -> int:
    """Wait until the consumer has everything the producer sent (or stops receiving)."""
    deadline = time.monotonic() + timeout_s
    previous, still_since = -1, time.monotonic()
    while True:
        received = int(consumer.call("mark")["count"]) - base
        now = time.monotonic()
        if received >= sent or now > deadline:
            return received
        if received != previous:
            previous, still_since = received, now
        elif now - still_since > 1.0:  # nothing more is coming: report the loss
            return received
        time.sleep(0.02)
