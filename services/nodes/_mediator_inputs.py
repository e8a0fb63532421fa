"""The mediator's inputs: the gyro cache and the clock offset between camera and gyro (see
``services.nodes.mediator``, which re-exports them).
"""

from __future__ import annotations

import collections
import functools
import itertools
import logging
import threading
import time
from collections.abc import Callable

import numpy as np

from middleware import ClockSample, FramegateError, Node, Notification, ServiceInfo, Subscription
from services.lib.clock import best_sample
from services.lib.quality import GyroSamples
from services.lib.rewind import SourceClock

# A batch whose newest sample is this much older than the newest kept: the gyro restarted.
_GYRO_RESTART_NS = 10_000_000_000
# Samples kept at most (32 B each: 3.2 MB), whatever their spacing: 10 s of a 10 kHz gyro.
# Time alone bounds nothing: a peer offering gyro/rates can pack a million samples into
# one batch 1 ns apart, 32 MB a put, all of them within the 10 s kept.
MAX_GYRO_SAMPLES = 100_000
# Two batches of fewer samples are kept joined (every batch kept follows the one before in
# time), so at most 2 * MAX_GYRO_SAMPLES / JOIN_BELOW batches, and two per join span, are
# kept whatever the gyro's batch size: each arrival and each frame's look-up scans the
# batches, and 10,000 one-sample batches (10 s at 1 kHz, each notification taken alone)
# made each 5-6 ms, measured on the cache.
JOIN_BELOW = 64
# ... and only while the joined batch spans at most this part of ``keep_ns`` (100 ms of
# 10 s): a batch is forgotten whole, and one joined across an outage would keep its old
# samples past ``keep_ns``.
_JOIN_SPAN_PART = 100

log = logging.getLogger("mediator")


def merge_batch(
    batches: list[GyroSamples], batch: GyroSamples, keep_ns: int
) -> tuple[list[GyroSamples], str | None]:
    """The kept batches after ``batch`` arrives, and what was unusual about it (or None).

    Only samples newer than every kept sample are kept: a late or re-delivered batch is
    dropped (``late-batch``), an overlapping one trimmed (``overlap``). A batch ending more
    than 10 s before the newest kept sample is a restarted gyro: the cache starts over
    (``restart``). Batches older than ``keep_ns`` before the newest sample are forgotten, and
    the oldest beyond ``MAX_GYRO_SAMPLES`` in all (``too-many-samples``: a batch itself
    larger keeps its newest samples).
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
    if len(batch) > MAX_GYRO_SAMPLES:
        outcome = "too-many-samples"
        batch = GyroSamples(
            np.asarray(batch.t_ns)[-MAX_GYRO_SAMPLES:],
            np.asarray(batch.rates_rad_s)[-MAX_GYRO_SAMPLES:],
            period_ns=batch.period_ns,
        )
    last = batches[-1] if batches and outcome != "restart" else None
    if (
        last is not None
        and len(last) < JOIN_BELOW > len(batch)
        and int(batch.t_ns[0]) - int(last.t_ns[0]) <= keep_ns // _JOIN_SPAN_PART
    ):
        batch = GyroSamples.concat([batches[-1], batch])
        batches = batches[:-1]
    kept = [*batches, batch]
    horizon = int(batch.t_ns[-1]) - keep_ns
    while kept and int(kept[0].t_ns[-1]) < horizon:
        kept.pop(0)
    total = sum(len(b) for b in kept)
    while total > MAX_GYRO_SAMPLES:  # the newest batch alone fits (trimmed above)
        total -= len(kept.pop(0))
        outcome = "too-many-samples"
    return kept, outcome


# Gyro notifications taken at once: a few of the gyro's batches of samples.
GYRO_TAKE_MAX = 64


class GyroCache:
    """Recent gyro batches; fed with the gyro's notifications (``feed``), read by pairing.

    Threads: ``_lock`` guards the batch list, so the feeding and the reading may run on
    different threads (they run on one in the mediator).
    """

    def __init__(self, keep_ns: int = 10_000_000_000) -> None:
        self._keep_ns = keep_ns
        self._batches: list[GyroSamples] = []
        self._lock = threading.Lock()
        self.dropped = collections.Counter[str]()
        self._producer: str | None = None  # the gyro's producer instance, as last greeted

    def feed(self, sub: Subscription, notes: list[Notification]) -> bool:
        """Add the batches of gyro notifications taken together; True when the gyro's
        producer is another instance than at the last feed (another process: another clock,
        so the camera-gyro offset measured is not its own).

        The gyro puts its samples as elements in batches (put_many); taking up to a
        batch's worth at once and joining them keeps the cache at batch granularity.
        """
        producer = sub.producer_epoch  # greeted: a peer's made-up epoch does not move it
        changed = producer is not None and self._producer not in (None, producer)
        self._producer = producer or self._producer
        parts: list[GyroSamples] = []
        for note in notes:
            try:
                parts.append(GyroSamples.from_bytes(sub.fetch(note).payload))
            except (FramegateError, ValueError, OverflowError):
                self.dropped["bad-batch"] += 1
        if parts:
            self.add_parts(parts)
        return changed

    def add_parts(self, parts: list[GyroSamples]) -> None:
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
        with self._lock:
            self._batches, outcome = merge_batch(self._batches, batch, self._keep_ns)
            if outcome is not None:
                self.dropped[outcome] += 1
                if outcome == "too-many-samples" and self.dropped[outcome] == 1:
                    log.warning(
                        "gyro batches hold more than %d samples within %.0f s: the oldest "
                        "are dropped (a gyro faster than 10 kHz, or a peer offering gyro data)",
                        MAX_GYRO_SAMPLES,
                        self._keep_ns / 1e9,
                    )

    @property
    def newest_ns(self) -> int | None:
        with self._lock:
            return int(self._batches[-1].t_ns[-1]) if self._batches else None

    def window(self, start_ns: int, end_ns: int, margin_ns: int = 20_000_000) -> GyroSamples:
        """Samples from batches overlapping [start - margin, end + margin]."""
        with self._lock:
            chosen = [
                b
                for b in self._batches
                if b.t_ns[-1] >= start_ns - margin_ns and b.t_ns[0] <= end_ns + margin_ns
            ]
        return GyroSamples.concat(chosen) if chosen else GyroSamples.empty()


# How often the mediator asks camera and gyro for their clocks, and how many answers count.
OFFSET_PERIOD_S = 2.0
_OFFSET_SAMPLES = 5
# How long one service may take to describe itself (a loaded machine: 100-250 ms measured).
# ``measure`` does not wait for it (the answers come on the executor later), and asks only
# while a source's data keeps coming or its back-off has passed (``due``), so a stopped
# camera or gyro is not asked in vain every period.
_ASK_TIMEOUT_S = 1.0
# A service that did not answer is asked again after 1, 2, 4 ... periods, at most this many.
_RETRY_MAX_PERIODS = 16


class ClockOffsets:
    """How far the camera's clock is from the gyro's, measured by asking both.

    Each ``measure`` (every ``OFFSET_PERIOD_S``, and at once after ``forget``) asks the
    services for their descriptions, which give each clock's offset from ours and the round
    trip that bounds its error (NTP-style); the camera-minus-gyro offset is that of the
    sample with the shortest round trips among the last ``_OFFSET_SAMPLES``, its
    uncertainty half the sum of those round trips. Unknown (None) until both have answered.
    The samples describe two particular clocks: when either service is another process
    (restarted, or a rogue that held the name before) or its clock has stepped since, they
    are forgotten, or a camera restarted after a clock error would be judged by the clock
    it no longer has for up to ``_OFFSET_SAMPLES`` periods.

    Each source's own latest clock sample is kept too (``clock``): what a rewind of the
    mediator's output is judged by (``services.lib.rewind``).

    ``measure`` never waits for the answers (on the mediator's executor a round trip would
    hold up every frame, gyro batch and hold for 100-250 ms on a loaded machine, every
    period): they arrive on the node's executor, and ``then`` runs once both are in.

    Threads: the answers arrive on the node's executor, the readers may be another thread
    (the tests'); ``_lock`` guards the samples.
    """

    def __init__(
        self, node: Node, camera: str, gyro: str, session_of: Callable[[str], str | None]
    ) -> None:
        self._node = node
        # The Zenoh session that greeted our subscription to a service's data: only its
        # answer is a sample of that service's clock (a peer answering in the service's name
        # while the service's own answer is late or dropped gave the mediator a false clock,
        # and every frame went unpaired).
        self._session_of = session_of
        self._camera = camera
        self._gyro = gyro
        # (camera - gyro offset, twice its uncertainty as the round trip that bounds it)
        self._samples: collections.deque[ClockSample] = collections.deque(maxlen=_OFFSET_SAMPLES)
        # (host, pid, clock steps) of camera and gyro when the samples were taken.
        self._clocks: tuple[tuple[str, int, int | None], ...] | None = None
        self._lock = threading.Lock()
        self.asked = threading.Event()  # set: measure again at once (a source started over)
        # Counts ``forget``: an answer to a question asked before belongs to clocks that
        # may be gone, and is not added.
        self._generation = 0
        # Per service that did not answer its last ask: (failures in a row, when to ask
        # again regardless of data, monotonic ns). Absent: it answered.
        self._unanswered: dict[str, tuple[int, int]] = {}
        # The camera's latest clock sample, whoever asked (a step of its clock shows here
        # first; a stream's start keeps the one sampled when it began, for rewinds).
        self.camera_clock: SourceClock | None = None
        self.measuring = False  # a measurement's questions are out
        self.began_ns = 0  # when the last measurement began (monotonic ns)

    def session_of(self, service: str) -> str | None:
        """The Zenoh session that speaks for ``service`` (None: not registered yet)."""
        return self._session_of(service)

    def due(self, service: str, now_ns: int) -> bool:
        """Whether to ask ``service`` although no data of it came: it answered last time
        (asking costs no timeout), or it did not and its back-off (one period, doubling up
        to ``_RETRY_MAX_PERIODS``) has passed: a transient miss under load is retried, a
        stopped process costs one timeout per back-off."""
        missed = self._unanswered.get(service)
        return missed is None or now_ns >= missed[1]

    def _answered(self, service: str, answered: bool) -> None:
        """Keep the back-off of ``due``: cleared by an answer, doubled by a miss."""
        if answered:
            self._unanswered.pop(service, None)
            return
        failures = self._unanswered.get(service, (0, 0))[0] + 1
        periods = min(2 ** (failures - 1), _RETRY_MAX_PERIODS)
        self._unanswered[service] = (
            failures,
            time.monotonic_ns() + int(periods * OFFSET_PERIOD_S * 1e9),
        )

    def ask(self, service: str, then: Callable[[SourceClock | None], object]) -> None:
        """Ask one service for its clock without waiting: ``then(clock)`` runs on the
        node's executor with its sample, or None when it did not answer (or answered more
        than once, or without a clock)."""

        def answered(info: ServiceInfo | None) -> None:
            self._answered(service, info is not None)
            clock = SourceClock.of(info) if info is not None else None
            if clock is not None and service == self._camera:
                self.camera_clock = clock
            then(clock)

        session = self.session_of(service)
        if session is None:  # not registered yet: nothing of it to pair, nobody to believe
            answered(None)
            return
        try:
            self._node.ask_service_info(
                service, answered, timeout_s=_ASK_TIMEOUT_S, session=session
            )
        except FramegateError:
            answered(None)

    def measure(
        self,
        *,
        camera_alive: bool = True,
        gyro_alive: bool = True,
        then: Callable[[], object] | None = None,
    ) -> None:
        """Ask camera and gyro for their clocks once, without waiting: when both have
        answered, on the node's executor, the sample is added and ``then()`` runs. A
        service that does not answer, or whose data stopped coming (``*_alive`` False: it
        may be stopped and would not answer either), leaves the samples as they are."""
        self.asked.clear()
        self.began_ns = time.monotonic_ns()
        # One question per service: camera and gyro may be one (the ros2 bridge offers both).
        wanted = list(
            dict.fromkeys(
                service
                for service, alive in ((self._camera, camera_alive), (self._gyro, gyro_alive))
                if alive
            )
        )
        if not wanted:
            if then is not None:
                then()
            return
        answers: dict[str, SourceClock | None] = {}
        generation = self._generation

        def answered(service: str, clock: SourceClock | None) -> None:
            answers[service] = clock
            if len(answers) < len(wanted):
                return
            self.measuring = False
            camera, gyro = answers.get(self._camera), answers.get(self._gyro)
            if generation == self._generation and camera is not None and gyro is not None:
                self.add(camera, gyro)
            if then is not None:
                then()

        self.measuring = True
        for service in wanted:
            self.ask(service, functools.partial(answered, service))

    def add(self, camera: SourceClock, gyro: SourceClock) -> None:
        """One sample of both clocks (``measure``'s, or a test's)."""
        offset = camera.offset_ns - gyro.offset_ns
        error = camera.error_ns + gyro.error_ns
        clocks = (camera.identity, gyro.identity)
        with self._lock:
            if clocks != self._clocks:
                self._samples.clear()
                self._clocks = clocks
            self._samples.append(ClockSample(offset, 2 * error))

    def forget(self) -> None:
        """Drop the samples (a source started over): unknown until measured again."""
        with self._lock:
            self._samples.clear()
            self._clocks = None
            self._generation += 1

    def current(self) -> tuple[int, int] | None:
        """(camera - gyro offset, its uncertainty) in ns, or None while unknown: the recent
        sample with the shortest round trip (the tightest bound, as NTP picks)."""
        with self._lock:
            if not self._samples:
                return None
            best = best_sample(self._samples)
        return best.offset_ns, best.round_trip_ns // 2
