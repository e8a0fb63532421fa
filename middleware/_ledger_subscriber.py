"""The subscriber's half of the flow-control protocol, as a pure state machine (no Zenoh, no
threads, no clock of its own): the Zenoh layer feeds it decoded notifications, takes and
the time, and sends the acks it returns.

Theory of operation
-------------------
The subscriber owns one registration (its token ``id/mode/N/push``) but cannot know in
advance which epoch the producer gave it, and over its life it may meet several: a producer
restart or a token that lapsed and came back gives a new epoch, a second producer or a
replay brings an old or foreign one, any peer in the trusted profile can forge one. So the
ledger never trusts one "current" epoch: it tracks each epoch it has seen (a bounded table)
and acks every queued notification under the epoch it came with. Nothing is thrown away
because another epoch showed up; a foreign epoch's notifications are acked under that
epoch, which no producer counts, so they cannot hold anybody's credit.

State: the queue (at most N notifications, each tagged with its epoch and seq) and, per
epoch, ``last`` (highest seq accepted) and ``taken`` (highest seq taken, what is acked).

A notification ``(epoch, seq, descriptor)``:

1. ``descriptor`` present and not this subscription's ``mode/N/push``: the notification
   belongs to another registration with the same id (a colliding token): ignored,
   counted in ``foreign``.
2. seq < 1: ignored, counted in ``invalid``.
3. Unknown epoch: one evicted from the table earlier is restored from a bounded memory of
   evicted epochs (``FORGOTTEN_EPOCHS``). Otherwise flow control adopts it only at seq 1
   (the first notification of a new registration), observers at any seq (the seqs before
   it count as missed). Anything else is ignored (``out_of_order``): a forged far-future
   seq of an epoch not met yet must not become its starting point, and a real producer
   sends seq 1 again. Adopting evicts the least recently used epoch with nothing queued
   when the table is full (``max(MAX_EPOCHS, N + 1)`` entries); if every epoch has
   queued notifications the newcomer is ignored. The epoch the producer greeted this
   registration with (``pin``; until a greeting comes, the first epoch adopted) is never
   evicted, from the table or from that memory: a flood of made-up epochs at seq 1 (any
   peer can send one) would otherwise push the live epoch out of both, and every later seq
   of it would be ``out_of_order`` for good. Nor is an epoch adopted since the last
   greeting (``UNGREETED_EPOCHS`` at most; more are ignored, counted in ``refused``, until
   the next greeting): a restarted producer's first notification can come before its
   greeting (a lost or delayed one), and a flood between the two would otherwise push its
   epoch out, and the producer's resend of an element already taken would be taken again
   (an observer, which adopts at any seq, would take a delayed duplicate again, and would
   repeat no ack of the registration it holds). Until its greeting, a made-up epoch and a
   restarted producer's
   are alike; so the first ones are kept and the rest wait: the producer resends, and
   greets again with the resend while nothing of the registration was acked
   (``ProducerProtocol.tick``), so its epoch is adopted once the greeting has come.
4. ``seq <= last``: a duplicate or stale copy: ignored (``duplicates``). If nothing of
   that epoch is queued, the producer evidently missed our ack: it is repeated.
5. Flow control, ``seq > last + 1`` (a gap) or ``seq > taken + N`` (beyond any window the
   producer could have): ignored (``out_of_order``). A real producer resends the missing
   ones in order (go-back-N); a forged far-future seq changes nothing.
6. Flow control, queue already holds N: ignored (``refused``); the producer resends it once
   the queue has room. Only another epoch's notifications can fill the queue this way, so
   the queue never holds more than N and nothing of a conforming producer is lost.
7. Observer: ``seq > last`` is accepted; a gap counts as ``missed``. A full queue drops its
   oldest notification for the new one (keep-last: a slow observer takes the latest),
   counted as ``missed`` on the notification now at the head; observers use lossy delivery.
8. Otherwise: queued, ``last = seq``.

A batch notification ``(epoch, seq, n elements)`` is exactly the n notifications
``(epoch, seq + i)`` received one after another (``receive_many``): every rule above
applies per element, so a batch changes nothing the properties below depend on.

``take_many`` pops the oldest notifications; each sets ``taken`` of its epoch to its seq and
makes an ack ``(epoch, seq)`` due (cumulative: it covers every earlier seq of that epoch). The ack
policy decides when due acks leave: ``AckPolicy(every=1)`` sends each at once; a larger
``every`` coalesces acks of queues > 1 (fewer messages, same credits once sent);
``AckPolicy.for_queue(N)`` is what subscriptions use: each take for N <= 3 (a queue of 1
must ack every element or the producer stays refused), every ``N // 2`` takes above that.
Coalescing never holds the producer back for long: an ack is also due once the queue runs
empty or the caller waits idle and ``delay_ns`` has passed since the first take it covers
(``for_queue``: 1 ms above N = 3, so that a consumer that keeps up does not ack every
element; 20 ms from N = 16, a deep queue: see ``DEEP_QUEUE``), or at once when its takes
came ``delay_ns`` or more after the takes before them (a slow stream: no later take would
join the ack within the delay, and waiting would cost a timer per element); ``flush_at_ns``
says when, for the Zenoh layer to send it even if the caller does not come back
(``Subscription``: the caller waiting in ``take`` sends it then; one that stays away leaves
it to the executor's next turn, holding at most ``N // 2 - 1`` credits, as between two
coalesced acks). While idle the subscriber repeats the acks of known epochs once no ack has
left for ``reack_ns``, so a lost ack or a lost notification heals (the producer resends on a
repeated ack that moves nothing).
Timed from the last ack sent, not from the last repeat: a busy subscriber, idle only
between notifications, repeats nothing, since a repeat that moves nothing makes the
producer resend what is merely in flight.

Properties (checked by tests/middleware/test_protocol_model.py after every step): the
queue never exceeds N; the epoch table is bounded; a flow-controlled subscription reports
``missed`` only for what its caller counts with ``note_missed`` (a lapsed registration,
see ``SubscriberProtocol``); every notification of a conforming producer reaches ``take``
once.
"""

from __future__ import annotations

from collections import OrderedDict, deque
from dataclasses import dataclass
from typing import Generic, NamedTuple, TypeVar

from ._records import SubscriptionMode

# Epochs tracked at least; more when the queue is larger (every queued epoch is tracked).
MAX_EPOCHS = 8
# Evicted epochs remembered (last, taken), so that a live one is restored, not re-adopted.
FORGOTTEN_EPOCHS = 256
# Epochs a flow subscription adopts between two greetings (rule 3); well below the memory
# above, which never evicts them.
UNGREETED_EPOCHS = 32
# An idle subscriber repeats its acks this often.
REACK_NS = 500_000_000
# A coalescing subscriber whose queue ran empty acks at most this much later.
ACK_DELAY_NS = 1_000_000
# A queue this deep is a buffer against stalls (the mediator's 256 gyro samples), not the
# load signal the paper's rule reads from a queue of a few frames: its emptied queue acks
# within ``DEEP_ACK_DELAY_NS``, so a stream of up to 50 takes/s shares one ack among
# several takes. An ack is a wake-up of a Zenoh thread on each side (~100 us of CPU per
# ack at 100 Hz here), more than the notification costs. What it holds back: at most 20 ms
# of the producer's credit, far from such a queue's depth at any rate it keeps up with.
DEEP_QUEUE = 16
DEEP_ACK_DELAY_NS = 20_000_000

T = TypeVar("T")


def _earlier(epoch: tuple[str, str, str], than: tuple[str, str, str]) -> bool:
    """Whether ``epoch`` (``str.rpartition(".")`` of ``<instance>.<n>``) is a registration
    the same producer instance made before ``than``."""
    return (
        epoch[0] == than[0]
        and epoch[2].isdigit()
        and than[2].isdigit()
        and int(epoch[2][:18]) < int(than[2][:18])
    )


@dataclass(frozen=True, slots=True)
class AckPolicy:
    """When acks leave: after ``every`` takes of one epoch, or once the queue ran empty (or
    the subscriber waits) and ``delay_ns`` passed since the first take not yet acked.
    ``every=1`` (the default) acks each take at once."""

    every: int = 1
    reack_ns: int = REACK_NS
    delay_ns: int = 0

    @classmethod
    def for_queue(cls, queue_size: int) -> AckPolicy:
        """Coalesce up to half a queue's worth of takes into one ack (each take below 4):
        the producer then sees at most ``N // 2 - 1`` elements as queued that are already
        taken, and a queue that runs empty acks within ``ACK_DELAY_NS`` (a consumer that
        keeps up would otherwise ack nearly every element), a deep one within
        ``DEEP_ACK_DELAY_NS``."""
        every = max(1, queue_size // 2)
        if every == 1:
            return cls()
        return cls(
            every=every, delay_ns=DEEP_ACK_DELAY_NS if queue_size >= DEEP_QUEUE else ACK_DELAY_NS
        )


@dataclass(slots=True)
class EpochTrack:
    """What the subscriber knows of one epoch."""

    last: int
    taken: int
    queued: int = 0
    missed: int = 0  # observers: lost since the last notification taken
    unacked_takes: int = 0
    reack_due: bool = False
    # When acks_due first saw an unacked take of this epoch (the delay counts from there).
    unacked_since_ns: int | None = None


class Entry(NamedTuple, Generic[T]):
    """A queued notification (a named tuple: as immutable as a frozen dataclass, and built
    in a third of the time, once per element)."""

    epoch: str
    seq: int
    item: T
    missed: int


@dataclass(slots=True)
class SubscriberCounters:
    """Notifications the ledger ignored, by reason."""

    foreign: int = 0
    invalid: int = 0
    out_of_order: int = 0
    duplicates: int = 0
    refused: int = 0


class SubscriberLedger(Generic[T]):
    """Queue, seq tracking and ack policy of one subscription. Not thread-safe: the caller
    serialises every call (see ``Subscription``'s Threads paragraph)."""

    def __init__(
        self,
        mode: SubscriptionMode,
        queue_size: int,
        descriptor: str,
        *,
        policy: AckPolicy = AckPolicy(),
        max_epochs: int = MAX_EPOCHS,
    ) -> None:
        if queue_size < 1:
            raise ValueError(f"queue_size must be >= 1, got {queue_size}")
        self.mode = mode
        self.queue_size = queue_size
        self.descriptor = descriptor
        self.policy = policy
        self._max_epochs = max(max_epochs, queue_size + 1)
        self._queue: deque[Entry[T]] = deque()
        self._epochs: OrderedDict[str, EpochTrack] = OrderedDict()
        self._forgotten: OrderedDict[str, tuple[int, int]] = OrderedDict()
        self._pinned: str | None = None  # never evicted (``pin``)
        # Flow control: epochs adopted since the last greeting, never evicted either.
        self._ungreeted: set[str] = set()
        self._acked_ns: int | None = None  # when acks last left
        # Takes so far, and how many and when ``acks_due`` last saw: a take that comes the
        # delay or more after the one before is a slow stream's (see ``acks_due``).
        self._takes = 0
        self._takes_seen = 0
        self._takes_seen_ns: int | None = None
        # The most recently used epoch (the last one in ``_epochs``) and its track: what the
        # fast path of ``receive`` compares against.
        self._recent: str | None = None
        self._recent_track = EpochTrack(last=0, taken=0)
        self.missed_total = 0
        self.counters = SubscriberCounters()

    @property
    def flow(self) -> bool:
        return self.mode is SubscriptionMode.FLOW

    def __len__(self) -> int:
        return len(self._queue)

    def queued(self) -> list[Entry[T]]:
        """The queued notifications, oldest first (they stay queued)."""
        return list(self._queue)

    def epochs(self) -> dict[str, EpochTrack]:
        return dict(self._epochs)

    def track(self, epoch: str) -> EpochTrack | None:
        """What is known of ``epoch`` (None: not tracked now)."""
        return self._epochs.get(epoch)

    def note_missed(self, count: int, index: int, *, counted: bool = False) -> None:
        """Count ``count`` elements lost before the queued notification at ``index`` (the
        caller knows of a gap the seqs cannot show: a lapsed registration); ``counted``:
        already in ``missed_total``, only carried by that notification now."""
        entry = self._queue[index]
        self._queue[index] = entry._replace(missed=entry.missed + count)
        if not counted:
            self.missed_total += count

    def pin(self, epoch: str) -> None:
        """Keep ``epoch`` (the one the producer greeted this registration with) tracked
        whatever other epochs arrive; a later greeting moves the pin, and frees the epochs
        adopted before it (rule 3)."""
        self._pinned = epoch
        self._ungreeted.clear()

    # -- notifications in ------------------------------------------------------------------
    def receive(self, epoch: str, seq: int, item: T, *, descriptor: str | None) -> bool:
        """Feed one decoded notification; True if it was queued."""
        # Fast path, the common case of a conforming producer: the epoch of the previous
        # notification (already the most recently used, so the table's order stands), the
        # next seq, within the window, room in the queue. Rules 1-7 let exactly this through
        # (an observer has no gap to count); anything else takes the full path below.
        track = self._recent_track
        if (
            epoch == self._recent
            and (descriptor is None or descriptor == self.descriptor)
            and seq == track.last + 1
            and len(self._queue) < self.queue_size
            and (seq <= track.taken + self.queue_size or self.mode is not SubscriptionMode.FLOW)
        ):
            track.last = seq
            track.queued += 1
            self._queue.append(Entry(epoch, seq, item, track.missed))
            track.missed = 0
            return True
        return self._receive(epoch, seq, item, descriptor)

    def _receive(self, epoch: str, seq: int, item: T, descriptor: str | None) -> bool:
        """``receive`` for every case, the rules of the module docstring in their order."""
        c = self.counters
        if descriptor is not None and descriptor != self.descriptor:
            c.foreign += 1
            return False
        if seq < 1:
            c.invalid += 1
            return False
        track = self._epochs.get(epoch)
        if track is None:
            known = self._forgotten.get(epoch)
            if known is None and self.flow and seq != 1:
                c.out_of_order += 1
                return False
            ungreeted = known is None and self._pinned is not None and epoch != self._pinned
            if (ungreeted and len(self._ungreeted) >= UNGREETED_EPOCHS) or not self._make_room():
                c.refused += 1
                return False
            if known is not None:
                del self._forgotten[epoch]
            last, taken = known if known is not None else (0, 0)
            track = EpochTrack(last=last, taken=taken)
            self._epochs[epoch] = track
            if self._pinned is None:  # the greeting was lost, or is still on its way
                self._pinned = epoch
            elif ungreeted:
                self._ungreeted.add(epoch)
        self._epochs.move_to_end(epoch)
        self._recent, self._recent_track = epoch, track
        if seq <= track.last:
            c.duplicates += 1
            if track.queued == 0:
                track.reack_due = True
            return False
        if self.flow:
            if seq != track.last + 1 or seq > track.taken + self.queue_size:
                c.out_of_order += 1
                return False
            if len(self._queue) >= self.queue_size:
                c.refused += 1
                return False
        else:
            gap = seq - track.last - 1
            track.missed += gap
            self.missed_total += gap
            if len(self._queue) >= self.queue_size:
                self._drop_oldest()
        track.last = seq
        track.queued += 1
        self._queue.append(Entry(epoch, seq, item, track.missed))
        track.missed = 0
        return True

    def _drop_oldest(self) -> None:
        """(observers, queue full) Drop the oldest queued notification to make room for the
        newest, as a keep-last queue does: what a slow observer misses is old, and what it
        takes next is the latest (dropping the newest instead would leave the last element
        of a burst unseen, and its count unreported, until another came). The drop, and what
        it carried, count as missed on the notification now first when that is of the same
        epoch, else on the epoch's next one (the arriving one, when of that epoch): missed
        counts stay with the producer instance they belong to."""
        dropped = self._queue.popleft()
        track = self._epochs[dropped.epoch]
        track.queued -= 1
        self.missed_total += 1
        carried = dropped.missed + 1
        head = self._queue[0] if self._queue else None
        if head is not None and head.epoch == dropped.epoch:
            self._queue[0] = head._replace(missed=head.missed + carried)
        else:
            track.missed += carried

    def receive_many(self, epoch: str, seq: int, items: list[T], *, descriptor: str | None) -> int:
        """Feed a batch notification: element i as the notification of seq ``seq + i``, in
        order. How many were queued."""
        count = len(items)
        track = self._recent_track
        if (
            count
            and epoch == self._recent
            and (descriptor is None or descriptor == self.descriptor)
            and seq == track.last + 1
            and len(self._queue) + count <= self.queue_size
            and (
                seq + count - 1 <= track.taken + self.queue_size
                or self.mode is not SubscriptionMode.FLOW
            )
        ):
            # ``receive``'s fast path for every element at once: each one in turn would take
            # it (the next seq, within the window, room in the queue), so the outcome is the
            # same; the first element carries what was missed before it.
            missed = track.missed
            self._queue.extend(
                [
                    Entry(epoch, seq + i, item, missed if i == 0 else 0)
                    for i, item in enumerate(items)
                ]
            )
            track.last = seq + count - 1
            track.queued += count
            track.missed = 0
            return count
        queued = 0
        for i, item in enumerate(items):
            queued += self.receive(epoch, seq + i, item, descriptor=descriptor)
        return queued

    def _make_room(self) -> bool:
        """Make room for one more epoch; False if every tracked epoch has queued entries."""
        if len(self._epochs) < self._max_epochs:
            return True
        for name, track in self._epochs.items():  # least recently used first
            if track.queued == 0 and name != self._pinned:
                del self._epochs[name]
                if name == self._recent:
                    self._recent = None
                self._forgotten[name] = (track.last, track.taken)
                if len(self._forgotten) > FORGOTTEN_EPOCHS:
                    self._forget_oldest()
                return True
        return False

    def _forget_oldest(self) -> None:
        """Drop the oldest remembered epoch that is neither pinned nor adopted since the last
        greeting (there is one: those are at most ``UNGREETED_EPOCHS + 1``, far fewer than
        the memory holds, so this looks at that many at most)."""
        for name in self._forgotten:
            if name != self._pinned and name not in self._ungreeted:
                del self._forgotten[name]
                return

    # -- taking and acking -----------------------------------------------------------------
    def take_many(self, max_count: int) -> list[Entry[T]]:
        """Up to ``max_count`` of the oldest queued notifications (they leave the queue)."""
        queue = self._queue
        entries = [queue.popleft() for _ in range(min(max_count, len(queue)))]
        name, track = None, None
        for entry in entries:
            if entry.epoch != name:
                name, track = entry.epoch, self._epochs[entry.epoch]
            assert track is not None
            track.queued -= 1
            track.taken = entry.seq
            track.unacked_takes += 1
        self._takes += len(entries)
        return entries

    def acks_due(self, now_ns: int, *, idle: bool) -> list[tuple[str, int]]:
        """The acks to send now: (epoch, seq) pairs, each cumulative for its epoch.

        ``idle``: the caller is waiting for a notification; then every known epoch's ack is
        repeated once no ack has left for ``reack_ns`` (but that of a registration the
        greeted one replaced): the table's, and those the memory of evicted epochs keeps for
        good (the pinned one and those adopted since: the registration we hold may be one).
        """
        acks: list[tuple[str, int]] = []
        repeat = idle and (
            self._acked_ns is None or now_ns - self._acked_ns >= self.policy.reack_ns
        )
        delay = self.policy.delay_ns
        # A slow stream's take (the delay or more after the one before it): waiting the
        # delay for the next takes to join its ack would only hold the producer's credit
        # that long and cost a timer per element, so an emptied queue acks it at once.
        slow = False
        if self._takes != self._takes_seen:
            seen_ns = self._takes_seen_ns
            slow = seen_ns is None or now_ns - seen_ns >= delay
            self._takes_seen, self._takes_seen_ns = self._takes, now_ns
        # A registration the producer replaced by the greeted one (a lapse of our token: the
        # same producer instance, an earlier epoch) is retired there: an ack repeated for it
        # would only make the producer check its subscription table (``tokens_lost``). A
        # later one (adopted from notifications, its greeting lost) is live: repeated.
        pinned = self._pinned.rpartition(".") if self._pinned is not None else None
        for epoch, track in self._epochs.items():
            replaced = pinned is not None and _earlier(epoch.rpartition("."), pinned)
            due = False
            if track.unacked_takes > 0:
                if track.unacked_since_ns is None:
                    track.unacked_since_ns = now_ns
                due = track.unacked_takes >= self.policy.every or (
                    (idle or track.queued == 0)
                    and (slow or now_ns - track.unacked_since_ns >= delay)
                )
            if due or track.reack_due or (repeat and track.taken > 0 and not replaced):
                acks.append((epoch, track.taken))
                track.unacked_takes = 0
                track.unacked_since_ns = None
                track.reack_due = False
        if repeat and pinned is not None:
            for epoch, (_, taken) in self._forgotten.items():  # at most FORGOTTEN_EPOCHS
                kept = epoch == self._pinned or epoch in self._ungreeted
                if kept and taken > 0 and not _earlier(epoch.rpartition("."), pinned):
                    acks.append((epoch, taken))
        if acks:
            self._acked_ns = now_ns
        return acks

    def flush_at_ns(self) -> int | None:
        """When a delayed ack falls due for a subscriber that does not come back to take:
        the earliest ``unacked_since_ns + delay`` of an epoch with nothing queued (None if no
        ack waits on the delay). The Zenoh layer calls ``acks_due`` then (see the module
        doc for who does, and when)."""
        if not self.policy.delay_ns:
            return None
        due = [
            track.unacked_since_ns + self.policy.delay_ns
            for track in self._epochs.values()
            if track.unacked_takes > 0 and track.queued == 0 and track.unacked_since_ns is not None
        ]
        return min(due, default=None)
