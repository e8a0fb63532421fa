"""Samples lost between a ROS 2 publisher and the bridge, counted from rmw_zenoh's
per-sample attachment: every publisher numbers its samples 1, 2, 3, ... and names itself by
its gid, so a gap in one gid's numbers is that many samples lost in transport (Zenoh drops
best-effort samples under congestion, a link can break).

A publisher's *first* samples are a special case. A volatile rmw_zenoh publisher keeps no
cache, and samples it sends before its session has learnt of the bridge's subscription are
never sent: the bridge can count them but never get them. It counts them only for a
publisher it saw *appear* in the ROS graph after it knew the graph (its liveliness token
arrived after the bridge's snapshot of the graph, taken once connected to the ROS 2
router): such a publisher started at 1, so a first sample numbered n means n - 1 lost. For
a publisher that was already there, the first number seen is only where counting starts.

A peer can send samples under any gid, numbered as it likes: a gap counts as lost only
within the credit its publisher earned at ``MAX_RATE_HZ`` in the bridge's time, so the
count grows at most as fast as a real publisher's could, whatever the peer sends.

:class:`SequenceTracker` is the pure state (no Zenoh, no threads); :class:`SequenceWatch`
wraps it for the bridge. Threads: ``observe`` runs on Zenoh's callback thread and only
updates the tracker (a dictionary look-up under ``SequenceWatch``'s lock), ``announce`` and
``settle`` on the graph watcher's, ``take_lost`` on the input's worker, which counts the
losses in its producer (the producer's lock is never taken on Zenoh's thread).
"""

from __future__ import annotations

import collections
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass

from ._rmw import Attachment, EntityKind, gid, parse_endpoint

# Publishers remembered at once (least recently heard forgotten first): a peer inventing a
# gid per sample costs bounded memory. More than any robot runs on one topic.
MAX_PUBLISHERS = 256
# A forward jump larger than this is not counted as lost samples (a forged or reset
# sequence, not a network gap: at 1 kHz this is 17 minutes of samples): counting starts
# again there, and the jump itself is counted once as ``sequence-jump``.
MAX_GAP = 1 << 20
# A forward jump larger than this is believed only when the publisher's next sample
# continues from it: one sample numbered far ahead (a peer forging the gid, which its public
# token gives away) then neither adds phantom losses nor moves the count past the real
# publisher's numbers (each later gap would look "older" and go uncounted). A real burst of
# losses is continued by the next sample, and counted then.
CONFIRM_GAP = 1024
# No publisher sends faster than this (IMUs reach a few kHz). Each publisher earns credit
# for lost samples at this rate in the bridge's own time from its first sample, up to
# ``MAX_CREDIT`` (a link down for a minute at 1 kHz); a gap beyond its credit is a forged
# number (a peer may send samples under any gid, numbered as it likes), counted once as a
# ``sequence-jump`` and forgotten. Without it, 46,100 samples in 5 s numbered 1,000 apart
# counted 46 million samples lost in transport, and the real publisher's later gaps none.
MAX_RATE_HZ = 20_000
MAX_CREDIT = 1 << 16
# A newly started publisher's first number n says n - 1 lost (sent before it learnt of the
# bridge) only up to this many, plus ``MAX_RATE_HZ`` over the time between its token and
# its first sample: each token a peer declares, with one sample numbered 2**20, counted
# a million samples lost.
START_ALLOWANCE = 16


@dataclass(slots=True)
class _Publisher:
    last: int | None = None  # the highest number seen
    first: int | None = None
    fresh: bool | None = None  # appeared after the graph was known; None: not announced
    start_counted: bool = False
    pending: int | None = None  # a number past a large jump, until the next one confirms it
    heard_ns: int | None = None  # when credit was last earned (the bridge's monotonic clock)
    credit: int = 0  # samples this publisher may yet be found to have lost
    announced_ns: int | None = None  # when its token was seen (monotonic)
    first_ns: int | None = None  # when its first sample arrived (monotonic)


@dataclass(frozen=True, slots=True)
class Losses:
    """What the samples seen so far say was lost."""

    lost: int = 0  # samples lost in transport
    jumps: int = 0  # forward jumps too large to be losses


class SequenceTracker:
    """Per-gid sequence numbers → samples lost (one caller at a time)."""

    def __init__(self, max_publishers: int = MAX_PUBLISHERS) -> None:
        self._publishers: collections.OrderedDict[bytes, _Publisher] = collections.OrderedDict()
        self._max = max_publishers
        self.settled = False
        self.lost = 0
        self.jumps = 0

    def _get(self, source_gid: bytes) -> _Publisher:
        publisher = self._publishers.get(source_gid)
        if publisher is None:
            publisher = self._publishers[source_gid] = _Publisher()
            if len(self._publishers) > self._max:
                self._publishers.popitem(last=False)
        else:
            self._publishers.move_to_end(source_gid)
        return publisher

    def announce(self, source_gid: bytes, received_ns: int | None = None) -> None:
        """The publisher's liveliness token was seen (at monotonic ``received_ns``): it is
        fresh if the graph was known."""
        publisher = self._get(source_gid)
        if publisher.fresh is None:
            publisher.fresh = self.settled
            publisher.announced_ns = received_ns
            self._count_start(publisher)

    def settle(self) -> None:
        """The graph is known: publishers announced from now on are newly started."""
        self.settled = True

    def sample(self, source_gid: bytes, sequence: int, received_ns: int | None = None) -> None:
        """One sample numbered ``sequence`` from ``source_gid``, received at ``received_ns``
        (monotonic; None: unknown, no gap is then checked against ``MAX_RATE_HZ``)."""
        if sequence < 1:
            return  # rmw_zenoh numbers from 1: nothing to learn from this one
        publisher = self._get(source_gid)
        if publisher.last is None:
            publisher.first = publisher.last = sequence
            publisher.heard_ns = publisher.first_ns = received_ns
            publisher.credit = 0
            self._count_start(publisher)
            return
        if not self._possible(publisher, sequence, received_ns):
            self.jumps += 1  # not sent by any publisher in the time it had: nothing lost
            return
        if publisher.pending is not None:
            pending, publisher.pending = publisher.pending, None
            if 0 < sequence - pending <= CONFIRM_GAP:  # continued: the jump was real
                self._gap(pending - publisher.last - 1)
                publisher.last = pending
            else:
                self.jumps += 1  # one number far off, not continued: nothing lost
        gap = sequence - publisher.last - 1
        if gap > CONFIRM_GAP:
            publisher.pending = sequence
            return
        self._gap(gap)
        # Older or equal numbers (a duplicate, a reordering) lose nothing and change nothing.
        if sequence > publisher.last:
            publisher.last = sequence

    @staticmethod
    def _possible(publisher: _Publisher, sequence: int, received_ns: int | None) -> bool:
        """Whether the numbers between the publisher's last and ``sequence`` fit in the
        credit it earned (see ``MAX_RATE_HZ``); the credit they take is spent."""
        if received_ns is None:
            return True
        if publisher.heard_ns is not None:
            earned = max(0, received_ns - publisher.heard_ns) * MAX_RATE_HZ // 1_000_000_000
            if earned:  # unspent time carries over to the next sample
                publisher.credit = min(MAX_CREDIT, publisher.credit + earned)
                publisher.heard_ns += earned * 1_000_000_000 // MAX_RATE_HZ
        else:
            publisher.heard_ns = received_ns
        last = publisher.pending if publisher.pending is not None else publisher.last
        gap = sequence - (last or 0) - 1
        if gap <= 0:
            return True
        if gap > publisher.credit:
            return False
        publisher.credit -= gap
        return True

    def _gap(self, gap: int) -> None:
        if gap > MAX_GAP:
            self.jumps += 1
        elif gap > 0:
            self.lost += gap

    def _count_start(self, publisher: _Publisher) -> None:
        if publisher.fresh and publisher.first is not None and not publisher.start_counted:
            publisher.start_counted = True
            allowed = MAX_GAP
            if publisher.first_ns is not None and publisher.announced_ns is not None:
                elapsed_ns = abs(publisher.first_ns - publisher.announced_ns)
                allowed = START_ALLOWANCE + elapsed_ns * MAX_RATE_HZ // 1_000_000_000
            if publisher.first - 1 > min(allowed, MAX_GAP):
                self.jumps += 1
            else:
                self.lost += publisher.first - 1


class SequenceWatch:
    """The sequence numbers of one ROS 2 topic's publishers (see the module docstring)."""

    def __init__(self, topic_fqn: str, clock: Callable[[], int] = time.monotonic_ns) -> None:
        self.topic = topic_fqn
        self._clock = clock
        self._lock = threading.Lock()
        self._tracker = SequenceTracker()
        self._counted = Losses()

    def observe(self, attachment: bytes | None) -> None:
        """Note one received sample's attachment (a sample without one tells nothing)."""
        if attachment is None:
            return
        try:
            decoded = Attachment.decode(attachment)
        except ValueError:
            return
        with self._lock:
            self._tracker.sample(decoded.source_gid, decoded.sequence_number, self._clock())

    def announce(self, token: str) -> None:
        """A liveliness token of the ROS graph; only this topic's publishers matter."""
        endpoint = parse_endpoint(token)
        if endpoint is None or endpoint.kind is not EntityKind.PUBLISHER:
            return
        if endpoint.topic != self.topic:
            return
        with self._lock:
            self._tracker.announce(gid(token), self._clock())

    def settle(self) -> None:
        with self._lock:
            self._tracker.settle()

    def take_lost(self) -> Losses:
        """Losses found since the last call."""
        with self._lock:
            lost, jumps = self._tracker.lost, self._tracker.jumps
        new = Losses(lost - self._counted.lost, jumps - self._counted.jumps)
        self._counted = Losses(lost, jumps)
        return new
