"""The mediator's inputs and readings: the gyro cache, the detector's load and the clock
offset between camera and gyro (see ``services.nodes.mediator``, which re-exports them).
"""

from __future__ import annotations

import collections
import contextlib
import itertools
import threading
import time

import numpy as np

from middleware import (
    FramegateError,
    Node,
    Producer,
    Subscription,
    SubscriptionInfo,
    SubscriptionMode,
)
from services.lib.decisions import Load
from services.lib.quality import GyroSamples

# A batch whose newest sample is this much older than the newest kept: the gyro restarted.
_GYRO_RESTART_NS = 10_000_000_000


def merge_batch(
    batches: list[GyroSamples], batch: GyroSamples, keep_ns: int
) -> tuple[list[GyroSamples], str | None]:
    """The kept batches after ``batch`` arrives, and what was unusual about it (or None).

    Only samples newer than every kept sample are kept: a late or re-delivered batch is
    dropped (``late-batch``), an overlapping one trimmed (``overlap``). A batch ending more
    than 10 s before the newest kept sample is a restarted gyro: the cache starts over
    (``restart``). Batches older than ``keep_ns`` before the newest sample are forgotten.
    """
    if len(batch) == 0:
        return batches, "empty-batch"
    outcome = None
    newest = int(batches[-1].t_ns[-1]) if batches else None
    if newest is not None and int(batch.t_ns[-1]) < newest - _GYRO_RESTART_NS:
        batches, outcome = [], "restart"  # start over rather than mix clocks
    elif newest is not None and int(batch.t_ns[0]) <= newest:
        fresh = np.asarray(batch.t_ns) > newest
        if not fresh.any():
            return batches, "late-batch"
        outcome = "overlap"
        batch = GyroSamples(
            np.asarray(batch.t_ns)[fresh],
            np.asarray(batch.rates_rad_s)[fresh],
            period_ns=batch.period_ns,
        )
    kept = [*batches, batch]
    horizon = int(batch.t_ns[-1]) - keep_ns
    while kept and int(kept[0].t_ns[-1]) < horizon:
        kept.pop(0)
    return kept, outcome


# Gyro notifications taken at once: a few of the gyro's batches of samples.
_GYRO_TAKE_MAX = 64


class GyroCache:
    """Recent gyro batches, fed by a thread that takes gyro notifications at once."""

    def __init__(self, sub: Subscription, keep_ns: int = 10_000_000_000) -> None:
        self._sub = sub
        self._keep_ns = keep_ns
        self._batches: list[GyroSamples] = []
        self._cond = threading.Condition()
        self._stop = threading.Event()
        self.dropped = collections.Counter[str]()
        self._thread = threading.Thread(target=self._run, daemon=True, name="gyro-cache")
        self._thread.start()

    def _run(self) -> None:
        while not self._stop.is_set():
            # The gyro puts its samples as elements in batches (put_many); taking up to a
            # batch's worth at once and joining them keeps the cache at batch granularity
            # and sends one ack per call.
            notes = self._sub.take_many(_GYRO_TAKE_MAX, timeout_s=0.2)
            parts: list[GyroSamples] = []
            for note in notes:
                try:
                    parts.append(GyroSamples.from_bytes(self._sub.fetch(note).payload))
                except (FramegateError, ValueError, OverflowError):
                    self.dropped["bad-batch"] += 1
            if parts:
                self._add_parts(parts)

    def _add_parts(self, parts: list[GyroSamples]) -> None:
        """Add consecutive parts; joined when in order, one by one (trimmed) when not."""
        ordered = all(len(p) for p in parts) and all(
            int(a.t_ns[-1]) < int(b.t_ns[0]) for a, b in itertools.pairwise(parts)
        )
        if ordered and len(parts) > 1:
            self.add(GyroSamples.concat(parts))
        else:
            for part in parts:
                self.add(part)

    def add(self, batch: GyroSamples) -> None:
        """Keep what is new in ``batch`` (see ``merge_batch``)."""
        with self._cond:
            self._batches, outcome = merge_batch(self._batches, batch, self._keep_ns)
            if outcome is not None:
                self.dropped[outcome] += 1
            self._cond.notify_all()

    @property
    def newest_ns(self) -> int | None:
        with self._cond:
            return int(self._batches[-1].t_ns[-1]) if self._batches else None

    def wait_covering(self, end_ns: int, timeout_s: float) -> bool:
        """Wait until a sample at or after ``end_ns`` (gyro clock) has arrived."""
        deadline = time.monotonic() + timeout_s
        with self._cond:
            while not self._batches or self._batches[-1].t_ns[-1] < end_ns:
                remaining = deadline - time.monotonic()
                if remaining <= 0:
                    return False
                self._cond.wait(remaining)
            return True

    def window(self, start_ns: int, end_ns: int, margin_ns: int = 20_000_000) -> GyroSamples:
        """Samples from batches overlapping [start - margin, end + margin]."""
        with self._cond:
            chosen = [
                b
                for b in self._batches
                if b.t_ns[-1] >= start_ns - margin_ns and b.t_ns[0] <= end_ns + margin_ns
            ]
        return GyroSamples.concat(chosen) if chosen else GyroSamples.empty()

    def stop(self) -> None:
        self._stop.set()
        self._thread.join(timeout=2)


def detector_load(producer: Producer) -> Load:
    """The flow-controlled subscription with the fewest free slots (0/0 with none)."""
    return _tightest(producer.subscriptions())[0]


def _tightest(subs: list[SubscriptionInfo]) -> tuple[Load, SubscriptionInfo | None]:
    flows = [s for s in subs if s.mode is SubscriptionMode.FLOW]
    if not flows:
        return Load(0, 0), None
    tightest = min(flows, key=lambda s: (s.queue_size - s.queued, -s.fill))
    load = Load(min(tightest.queued, tightest.queue_size), tightest.queue_size, tightest.taken_ns)
    return load, tightest


# How often the mediator asks camera and gyro for their clocks, and how many answers count.
_OFFSET_PERIOD_S = 2.0
_OFFSET_SAMPLES = 5


class ClockOffsets:
    """How far the camera's clock is from the gyro's, measured by asking both (a thread).

    Every ``_OFFSET_PERIOD_S`` the services' descriptions give each clock's offset from
    ours and the round trip that bounds its error (NTP-style); the camera-minus-gyro
    offset is that of the sample with the shortest round trips among the last
    ``_OFFSET_SAMPLES``, its uncertainty half the sum of those round trips. Unknown (None)
    until both have answered. The samples describe two particular clocks: when either
    service is another process (restarted, or a rogue that held the name before) or its
    clock has stepped since, they are forgotten, or a camera restarted after a clock error
    would be judged by the clock it no longer has for up to ``_OFFSET_SAMPLES`` periods.

    Threads: one daemon thread asks (it only calls ``Node.services``); ``_lock`` guards
    the samples.
    """

    def __init__(self, node: Node, camera: str, gyro: str) -> None:
        self._node = node
        self._camera = camera
        self._gyro = gyro
        self._samples: collections.deque[tuple[int, int]] = collections.deque(
            maxlen=_OFFSET_SAMPLES
        )
        # (host, pid, clock steps) of camera and gyro when the samples were taken.
        self._clocks: tuple[tuple[str, int, int | None], ...] | None = None
        self._lock = threading.Lock()
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, daemon=True, name="clock-offsets")
        self._thread.start()

    def _run(self) -> None:
        while not self._stop.is_set():
            with contextlib.suppress(FramegateError):
                self.measure()
            self._stop.wait(_OFFSET_PERIOD_S)

    def measure(self) -> None:
        found = {s.service: s for s in self._node.services(timeout_s=1.0)}
        camera, gyro = found.get(self._camera), found.get(self._gyro)
        if camera is None or gyro is None:
            return
        if camera.clock_offset_ns is None or gyro.clock_offset_ns is None:
            return
        offset = camera.clock_offset_ns - gyro.clock_offset_ns
        error = ((camera.round_trip_ns or 0) + (gyro.round_trip_ns or 0)) // 2
        clocks = tuple((s.host, s.pid, s.clock_steps) for s in (camera, gyro))
        with self._lock:
            if clocks != self._clocks:
                self._samples.clear()
                self._clocks = clocks
            self._samples.append((offset, error))

    def forget(self) -> None:
        """Drop the samples (a source started over): unknown until measured again."""
        with self._lock:
            self._samples.clear()
            self._clocks = None

    def current(self) -> tuple[int, int] | None:
        """(camera - gyro offset, its uncertainty) in ns, or None while unknown: the recent
        sample with the shortest round trip (the tightest bound, as NTP picks)."""
        with self._lock:
            if not self._samples:
                return None
            return min(self._samples, key=lambda sample: sample[1])

    def stop(self) -> None:
        self._stop.set()
        self._thread.join(timeout=2)
