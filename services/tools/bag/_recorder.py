"""Recording live buffers without losing what they still hold (``framegate record``).

Buffering rule: a recorder *observes* (``SubscriptionMode.OBSERVE``), so it never slows the
robot, and it is lossless while the buffer's retention lasts. Notification sequence numbers
count every stored element, so a gap says exactly how many elements were missed between two
notifications, and one range query fetches them from the buffer's history; misses at the
end of a burst, which no later notification reports, are fetched as soon as the
subscription goes quiet, and at the stop everything up to the stop instant is fetched.
Each buffer's newest element at the start is recorded too (as ``ros2 bag record`` gets a
transient-local publisher's last message): a camera description put once is in the file.
"At the start" is by stamp: every element stamped after the recording's start instant is
recorded, also those stored before the recorder reached their buffer (``at_start``).

Two kinds of loss are counted apart, as rosbag2 splits lost-in-transport from
lost-in-recorder:

* ``evicted`` (lost in transport): the recorder never got the element: the buffer no longer
  held it when the recorder asked (its retention was too short for how far the recorder fell
  behind), or it was not fetched by the stop deadline;
* ``dropped`` (lost in recorder): the recorder had the element and did not keep it, because
  its write queue (elements fetched, waiting for the disk and compression) was full.

The end is bounded: every fetch ends by the recorder's ``deadline`` (``STOP_SLACK_S`` after
the stop instant), and what is known to be stored up to the stop instant but not fetched by
then (notification sequence numbers tell how many) is counted ``evicted`` rather than waited
for. The writer keeps up the same way: while it is more than ``CATCH_UP_S`` behind, and for
what is left at the stop, it closes chunks uncompressed (MCAP compresses per chunk), so a
compressor slower than the buffers costs file size, not seconds at the end nor elements.

Threads: one fetching thread per buffer (take notifications, fetch, backfill) puts elements
into one bounded ``WriteQueue``; its one writer thread compresses and writes them, so a slow
disk never delays a fetch into an eviction. ``Progress`` counters are written by the
fetching thread of their buffer (``backfilled``, ``evicted``, ``dropped``) and by the
writer thread (``recorded``, ``first_ns``, ``last_ns``), each under the queue's lock.
"""

from __future__ import annotations

import threading
import time
from collections import deque
from dataclasses import dataclass
from typing import Any

from middleware import DataObject, FramegateError, Node, Notification, Subscription, TimeRange

from ._writer import BagWriter

# After this long without a notification, check the buffer for elements we never heard of.
IDLE_PROBE_S = 1.0
# Elements fetched and waiting to be written, at most (bytes): ~20 s of 1.3 MB frames at
# 15 frames/s, so a disk that pauses for seconds drops nothing.
WRITE_QUEUE_BYTES = 384 * 2**20
# A query at the start waits at most this long.
STOP_QUERY_S = 1.0
# What ``at_start`` asks for after the start: the buffers are all asked within a few seconds
# of it; more would fetch at once the whole buffer of a producer whose clock runs far ahead.
AT_START_WINDOW_NS = 10_000_000_000
# Every fetch ends at most this long after the stop instant (what is not fetched by then is
# counted evicted), so a recording ends about this long after its duration.
STOP_SLACK_S = 1.0
# A writer this far behind (its oldest queued element waited this long) stops compressing
# until it has caught up.
CATCH_UP_S = 0.5
# The final backfill (the tail up to the stop) is asked with at least this long, even by a
# recorder that a busy machine starved past its deadline: unasked, the tail would be counted
# only as far as the notifications tell, and on such a machine they lag behind the buffer
# (measured at load 12: 843 gyro samples held, 64 counted).
TAIL_FLOOR_S = 1.0
# How often a backfill asks a buffer that did not answer before counting its range evicted.
BACKFILL_TRIES = 3
# The pause before the second ask (twice this before the third): long enough for a lapsed
# lease to be renewed, short beside the stop slack.
BACKFILL_PAUSE_S = 0.2


@dataclass
class Progress:
    """What one buffer's recording did (see the module docstring for the two losses)."""

    name: str
    kind: str
    recorded: int = 0
    backfilled: int = 0
    missed: int = 0
    evicted: int = 0
    dropped: int = 0
    # Messages on the notify key that were no notification (a peer's garbage, oversize, a
    # flood): nothing recorded is lost to them (what they push out is backfilled), but a
    # user sees that someone sent them.
    bad_notifications: int = 0
    first_ns: int | None = None
    last_ns: int | None = None

    @property
    def lost(self) -> int:
        return self.evicted + self.dropped

    def json(self) -> dict[str, Any]:
        return {
            "name": self.name,
            "kind": self.kind,
            "recorded": self.recorded,
            "backfilled": self.backfilled,
            "missed": self.missed,
            "evicted": self.evicted,
            "dropped": self.dropped,
            "lost": self.lost,
            "bad_notifications": self.bad_notifications,
            "first_ns": self.first_ns,
            "last_ns": self.last_ns,
        }


class WriteQueue:
    """Fetched elements on their way to the file, bounded in bytes; one writer thread."""

    def __init__(self, writer: BagWriter, max_bytes: int = WRITE_QUEUE_BYTES) -> None:
        self._writer = writer
        self._max_bytes = max_bytes
        self._items: deque[tuple[Progress, DataObject, float]] = deque()
        self._bytes = 0
        self._closing = False
        self._cond = threading.Condition()
        self.error: BaseException | None = None
        self._thread = threading.Thread(target=self._run, name="record-writer", daemon=True)
        self._thread.start()

    def put(self, progress: Progress, element: DataObject) -> bool:
        """Queue ``element``; False (counted ``dropped``) if the queue is full."""
        size = len(element.payload) + len(element.metadata)
        with self._cond:
            full = self._items and self._bytes + size > self._max_bytes
            if self.error is not None or self._closing or full:
                progress.dropped += 1
                return False
            self._items.append((progress, element, time.monotonic()))
            self._bytes += size
            self._cond.notify()
            return True

    def _run(self) -> None:
        while True:
            with self._cond:
                while not self._items and not self._closing:
                    self._cond.wait()
                if not self._items:
                    return
                progress, element, queued_at = self._items[0]
                behind = self._closing or time.monotonic() - queued_at > CATCH_UP_S
            try:
                self._writer.catch_up(behind)
                self._writer.write(progress.name, element)
            except BaseException as exc:  # a failing file stops the recording, not hangs it
                with self._cond:
                    self.error = exc
                    for queued, _, _ in self._items:
                        queued.dropped += 1
                    self._items.clear()
                    self._bytes = 0
                return
            with self._cond:
                self._items.popleft()
                self._bytes -= len(element.payload) + len(element.metadata)
                progress.recorded += 1
                progress.last_ns = element.timestamp_ns
                if progress.first_ns is None:
                    progress.first_ns = element.timestamp_ns

    def backlog(self) -> tuple[int, int]:
        """Elements and bytes fetched and not yet written."""
        with self._cond:
            return len(self._items), self._bytes

    def close(self) -> None:
        """Write what is queued (uncompressed: the recording is over), then end the writer
        thread; later ``put`` calls are counted dropped."""
        with self._cond:
            self._closing = True
            self._cond.notify()
        self._thread.join()

    def abandon(self) -> None:
        """Write nothing more (a second Ctrl-C): what is queued is counted ``dropped``, but
        the element the writer thread holds (the first), which it finishes; then end it."""
        with self._cond:
            self._closing = True
            while len(self._items) > 1:
                progress, element, _ = self._items.pop()
                progress.dropped += 1
                self._bytes -= len(element.payload) + len(element.metadata)
            self._cond.notify()
        self._thread.join()


def at_start(
    node: Node,
    target: str,
    started_ns: int,
    stop_ns: int | None = None,
    session: str | None = None,
) -> list[DataObject]:
    """What ``target`` holds of the recording already: its newest element stamped at or
    before the start, and every one stamped after it (up to ``stop_ns``). Asked before
    subscribing, so that nothing stored in between escapes both the query and the
    notifications; by stamp, not as "the newest now", because buffers are asked one after
    another: the last is asked tens of ms after the start, and a 1 kHz gyro stores dozens of
    samples meanwhile, which would have been in no buffer's query and in no notification.

    The second query starts right after the element the first one found, not at the start:
    a batch stored between the two (a gyro's ten samples, some stamped before the start)
    would otherwise leave a gap behind that element that no later backfill reaches.

    ``session``: the producer's Zenoh session, when one alone answers as its service: a
    peer's element stamped inside the window (5 s ahead) became the newest recorded, and
    the real ones before it were skipped as recorded already."""
    try:
        before = node.query(
            target,
            time_range=TimeRange(None, started_ns),
            last=1,
            timeout_s=STOP_QUERY_S,
            session=session,
        )
        end_ns = started_ns + AT_START_WINDOW_NS
        after = node.query(
            target,
            time_range=TimeRange(
                (before[-1].timestamp_ns if before else started_ns) + 1,
                end_ns if stop_ns is None else min(stop_ns, end_ns),
            ),
            timeout_s=STOP_QUERY_S,
            session=session,
        )
    except FramegateError:
        return []
    return before + after


class Recorder:
    """Records one buffer on its own thread into ``queue`` until ``stop``; see the module."""

    def __init__(
        self,
        node: Node,
        sub: Subscription,
        queue: WriteQueue,
        progress: Progress,
        stop: threading.Event,
        count: int | None,
        initial: list[DataObject] | None = None,
    ) -> None:
        """``initial``: what the buffer held of the recording, queried *before* ``sub`` was
        made (see ``at_start``), so that everything stored after it is fetched by range."""
        self.node = node
        self._initial = list(initial or ())
        self.sub = sub
        self.queue = queue
        self.progress = progress
        self.stop = stop
        self.count = count
        # The stop instant: nothing stamped later is recorded (None: not known yet; known
        # from the start with a duration).
        self.stop_ns: int | None = None
        # How far the producer's clock runs ahead of the recording's (``stop_ns`` is in
        # the producer's clock: its elements' stamps are).
        self.offset_ns = 0
        # The monotonic instant by which every fetch ends (None: not known yet); set before
        # the thread starts when the duration is known, else at the stop.
        self.deadline: float | None = None
        self.error: BaseException | None = None
        self._fetched = 0
        self._last_ns: int | None = None  # the newest element handed to the queue
        # Sequence number of the last notification handled (0: none yet in this epoch), and
        # timestamps that backfills queued after its element.
        self._anchor_seq = 0
        self._since_anchor: list[int] = []
        self._accounted_misses = 0
        self._idle_since = time.monotonic()
        self.thread = threading.Thread(target=self._run, name=f"record-{sub.name}", daemon=True)

    def _full(self) -> bool:
        return self.count is not None and self._fetched >= self.count

    def _run(self) -> None:
        try:
            self._latest_at_start()
            while not self.stop.is_set() and not self._full():
                note = self.sub.take(timeout_s=0.2)
                if note is not None:
                    self._idle_since = time.monotonic()
                    self._on_notification(note)
                elif self._unaccounted_misses() or self._buffer_is_ahead():
                    # Misses are only reported by the next notification; a burst that has
                    # ended brings none, so catch up from the buffer while it is quiet.
                    self._backfill(None)
            if not self._full():
                self._until_past_stop()
                # The tail up to the stop.
                self._backfill(self.stop_ns, timeout_s=STOP_SLACK_S, floor_s=TAIL_FLOOR_S)
                self.progress.evicted += self._unfetched_at_stop()
        except BaseException as exc:  # a failing recorder must stop the recording, not hang it
            self.error = exc
            self.stop.set()

    def _until_past_stop(self) -> None:
        """Handle notifications until one is stamped past the stop, or the deadline.

        An element stamped before the stop may be stored after it (a camera stamps a frame
        at its exposure and stores it a render later: ~60 ms at load 12), so at the stop
        instant neither the buffer nor the notifications hold it yet; the final backfill
        alone missed it, uncounted."""
        if self.stop_ns is None or self.deadline is None:
            return
        # Half the slack at most: the other half is the final backfill's.
        until = self.deadline - STOP_SLACK_S / 2
        while not self._full():
            timeout_s = min(0.2, until - time.monotonic())
            if timeout_s <= 0:
                return
            note = self.sub.take(timeout_s=timeout_s)
            if note is None:
                continue
            if note.timestamp_ns > self.stop_ns:
                return  # the producer is past the stop: the final backfill finds the rest
            self._on_notification(note)

    def _latest_at_start(self) -> None:
        for element in self._initial:
            self._queue(element)

    def _unaccounted_misses(self) -> bool:
        return self.sub.missed_total > self._accounted_misses

    def _buffer_is_ahead(self) -> bool:
        """After a quiet second, whether the buffer holds newer elements than we fetched.

        Observer notifications travel with congestion control DROP, so the last ones of a
        burst can vanish without a later one to reveal the gap; the buffer's description
        (no payloads) tells.
        """
        if self._last_ns is None or time.monotonic() - self._idle_since < IDLE_PROBE_S:
            return False
        self._idle_since = time.monotonic()
        timeout_s = self._timeout(STOP_QUERY_S)
        if timeout_s <= 0:
            return False
        try:
            newest = self.node.buffer_info(
                self.sub.name, timeout_s=timeout_s, session=self.sub.producer_session
            ).newest_ns
        except FramegateError:
            return False
        return newest is not None and newest > self._last_ns

    def _on_notification(self, note: Notification) -> None:
        p = self.progress
        if self.stop_ns is not None and note.timestamp_ns > self.stop_ns:
            return  # past the stop: the final backfill fetches what lies before it
        new_epoch = note.seq <= self._anchor_seq
        if new_epoch:  # the producer restarted, or our registration lapsed and came back
            self._anchor_seq, self._since_anchor = 0, []
        # Sequence numbers count every element stored since we subscribed: this many lie
        # between the previous notification we handled and this one.
        expected = note.seq - self._anchor_seq - 1
        if new_epoch:
            # Across a lapse the seqs start over; what was stored meanwhile comes as the
            # note's missed count (which also holds this epoch's seqs before it, if dropped).
            expected = max(expected, note.missed)
        if self._last_ns is not None and note.timestamp_ns <= self._last_ns:
            # A backfill already queued it; it still anchors the count of what lies between.
            between = [t for t in self._since_anchor if t < note.timestamp_ns]
            p.evicted += max(0, expected - len(between))
            self._anchor_seq = note.seq
            self._since_anchor = [t for t in self._since_anchor if t > note.timestamp_ns]
            return
        # The first notification of an epoch after something was recorded (the newest
        # element at the start, or the previous epoch) cannot count what was stored in
        # between (before the subscription, or before the restart): fetch that range too.
        first_after = self._anchor_seq == 0 and self._last_ns is not None
        if expected > len(self._since_anchor) or first_after:
            self._backfill(note.timestamp_ns - 1, newest=expected - len(self._since_anchor))
            if self._full():
                return
        p.evicted += max(0, expected - len(self._since_anchor))
        self._anchor_seq, self._since_anchor = note.seq, []
        timeout_s = self._timeout(5.0)
        try:
            if timeout_s <= 0:
                raise FramegateError("past the stop deadline")
            element = self.sub.fetch(note, timeout_s=timeout_s)
        except FramegateError:
            p.evicted += 1  # gone from the buffer before we could fetch it
            return
        self._queue(element)

    def _timeout(self, timeout_s: float) -> float:
        """``timeout_s``, cut to what is left before the deadline (<= 0: none left)."""
        if self.deadline is None:
            return timeout_s
        return min(timeout_s, self.deadline - time.monotonic())

    def _unfetched_at_stop(self) -> int:
        """Elements stored up to the stop instant that were never fetched (after the last
        fetch): the notifications still queued tell, by their sequence numbers, how many
        elements were stored after the last one handled."""
        # The queue is bounded (the subscription's queue size), so this ends.
        notes = self.sub.take_many(1 << 16, timeout_s=0)
        if self.stop_ns is not None:
            notes = [n for n in notes if n.timestamp_ns <= self.stop_ns]
        if not notes:
            return 0
        newest = max(notes, key=lambda n: n.seq)
        if self._anchor_seq == 0 or newest.seq <= self._anchor_seq:
            # A new epoch (or none handled yet): only the notifications themselves are known.
            return sum(1 for n in notes if self._last_ns is None or n.timestamp_ns > self._last_ns)
        fetched = sum(1 for t in self._since_anchor if t <= newest.timestamp_ns)
        return max(0, newest.seq - self._anchor_seq - fetched)

    def _backfill(
        self,
        end_ns: int | None,
        newest: int | None = None,
        timeout_s: float = 5.0,
        floor_s: float = 0.0,
    ) -> None:
        """Queue the elements after the last one queued, up to ``end_ns`` (open: all); the
        first ask waits at least ``floor_s``, even past the deadline."""
        timeout_s = max(self._timeout(timeout_s), floor_s)
        if timeout_s <= 0:
            return  # past the deadline: what stays missing is counted at the stop
        self._accounted_misses = self.sub.missed_total
        start = None if self._last_ns is None else self._last_ns + 1
        if start is None:
            # Nothing recorded yet: only the newest few belong to this recording.
            newest = newest if newest is not None else self._accounted_misses
            if not newest:
                return
        if start is not None and end_ns is not None and end_ns < start:
            return
        gap = None
        # A loaded machine's producer may not answer once, or lose its lease for a moment:
        # then the query either fails or reaches no one and comes back empty although the
        # sequence numbers say ``newest`` elements lie in the range. Either is asked again
        # (after a pause, within the deadline) before the range counts as evicted; an
        # answer that is short but not empty is the buffer's (it evicted the oldest).
        for attempt in range(BACKFILL_TRIES):
            if attempt:
                time.sleep(min(BACKFILL_PAUSE_S * attempt, max(0.0, self._timeout(1.0))))
                timeout_s = self._timeout(timeout_s)
                if timeout_s <= 0:
                    break
            try:
                gap = self.node.query(
                    self.sub.name,
                    time_range=TimeRange(start, end_ns),
                    last=newest if start is None else None,
                    timeout_s=timeout_s,
                    # The producer's replies alone: a peer's element inside an open range
                    # would become the newest recorded, and real ones look recorded.
                    session=self.sub.producer_session,
                )
            except FramegateError:
                continue
            if gap or not newest:
                break
        if gap is None:
            return  # what stays missing is counted evicted when the next notification comes
        for element in gap:
            if self._full():
                return
            if self._queue(element):
                self.progress.backfilled += 1
            self._since_anchor.append(element.timestamp_ns)

    def _queue(self, element: DataObject) -> bool:
        """Hand ``element`` to the writer (unless stamped after the stop); whether kept."""
        if self.stop_ns is not None and element.timestamp_ns > self.stop_ns:
            return False
        if self._last_ns is not None and element.timestamp_ns <= self._last_ns:
            return False  # queued already (the newest at the start, notified again)
        self._last_ns = element.timestamp_ns
        self._fetched += 1
        return self.queue.put(self.progress, element)
