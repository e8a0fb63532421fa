"""The subscriber's side of the protocol as one sans-IO object: notification bytes and the
time go in, queued notifications and wire-ready acks come out.

``SubscriberProtocol`` owns every decision a subscription makes: its descriptor (the one
place it is built), the limits on what it may ask for (checked before any token is
declared, so ``subscribe`` refuses at once), decoding and judging each notification
(the pure ``SubscriberLedger`` keeps the rules), the producer's greeting or refusal, and
when acks leave (coalesced, delayed, repeated while idle). ``next_deadline_ns`` tells the
node's executor when a delayed ack falls due for a caller that does not come back to take.

Refusals are trusted only from the producer's own session: the Zenoh layer passes each
control message's sender (the Zenoh session id the producer stamps on it as its source)
and, when ``judge`` asks for them, the ids of the sessions that answer as the service
(``trust_producer``; asked again at most every ``RETRY_NS``, so a flood of forged refusals
costs one question per period); a refusal counts only when its sender is the one session
that answers as the service. From any other session, or while more than one session
answers in the service's name (a peer can answer as any service), it is ignored. A refused
subscription (or one that met a forged refusal) declares its token again every
``RETRY_NS`` (``retry_due``) until the producer greets it: the holder it lost to may
leave, and a real answer lost among forgeries is asked for again. A refusal from another
session than the one that greeted us is judged the same way: trusted, it voids the
greeting, so a peer's forged greeting cannot keep a refused subscription waiting unheard.
The session that greeted us (``greeted_by``) is the one whose answers in the service's name
count (a mediator's clock samples); a greeting of the same epoch from another session is
forged (an epoch is one instance's, in one session) and counted as garbage.

Lapses are counted: every notification carries its registration's ``base`` (the elements
the producer had stored when it registered us), so seq s is the producer's element number
``base + s``. When a new registration of the same producer instance (epoch
``<instance>.<n>``) starts, the elements stored between the last one of the previous
registration and its first were never notified (our token had lapsed, e.g. a link that
dropped and came back): they are counted in ``missed`` on the next notification taken
and reported once (``lapse_news``). The producer's greeting of the new registration carries
its base as well, so the count is made when the greeting comes (``missed_total`` at once;
the next notification taken carries it): a lapse at the end of a stream, with no element
after it, is counted too. A subscription that knows no element number of that instance
(every notification of its last registration was refused behind a peer's, and the greeting
lost) counts from the greeting's ``since``: how far the producer saw that registration
acked (the producer remembers it per key, for ``RETIRED_KEYS`` keys).
"""

from __future__ import annotations

from collections import OrderedDict
from collections.abc import Container
from typing import Any

from ._errors import ConfigError
from ._ledger_subscriber import AckPolicy, Entry, SubscriberCounters, SubscriberLedger
from ._protocol_producer import FLOW_QUEUE_MAX, INLINE_METADATA_MAX
from ._records import SubscriptionMode
from ._wire import (
    MAX_QUEUE_SIZE,
    BatchHeader,
    Control,
    Header,
    decode_notification_header,
    descriptor_of,
    encode_ack,
)

# What the queue holds per notification: timestamp_ns, metadata, the pushed payload (Zenoh's
# ZBytes for a single element, turned into bytes by ``take`` on the caller's thread; bytes
# cut out of a batch).
Item = tuple[int, bytes | None, Any]
# Greeters remembered per epoch (``data_session``) before the forgotten epochs' are dropped.
_GREETERS_MAX = 64
# Room for a notification header's fields besides its metadata (epoch, seq, descriptor, ...).
_HEADER_SLACK = 1024

# A refused subscription declares its token again this often.
RETRY_NS = 2_000_000_000
# Producer instances whose highest element number is remembered (for counting lapses).
_INSTANCES = 8


# The largest queue an observer may ask for (a flow-controlled one: ``FLOW_QUEUE_MAX``).
OBSERVE_QUEUE_MAX = MAX_QUEUE_SIZE
_WHY_LIMIT = {
    SubscriptionMode.FLOW: "a producer keeps every un-acked notification of a flow-controlled "
    "subscriber, and one subscriber may hold at most half of its budget",
    SubscriptionMode.OBSERVE: "the largest queue a producer registers",
}


def check_request(mode: SubscriptionMode, queue_size: int, push_max_bytes: int) -> None:
    """Refuse what no producer would register, with the limit named."""
    if type(queue_size) is not int or queue_size < 1:
        raise ConfigError(f"queue_size must be an integer >= 1, got {queue_size!r}")
    limit = FLOW_QUEUE_MAX if mode is SubscriptionMode.FLOW else OBSERVE_QUEUE_MAX
    if queue_size > limit:
        raise ConfigError(
            f"queue_size {queue_size} exceeds the {mode.value} limit of {limit} "
            f"({_WHY_LIMIT[mode]}); choose a smaller queue"
        )
    if push_max_bytes < -1:
        raise ConfigError(f"push_max_bytes must be >= 0, got {push_max_bytes}")


class SubscriberProtocol:
    """One subscription's protocol. Not thread-safe: the caller serialises every call."""

    def __init__(
        self,
        mode: SubscriptionMode,
        queue_size: int,
        push_max_bytes: int,
        *,
        policy: AckPolicy | None = None,
    ) -> None:
        check_request(mode, queue_size, push_max_bytes)
        self.mode = mode
        self.queue_size = queue_size
        self.push_max_bytes = push_max_bytes
        self.descriptor = descriptor_of(mode, queue_size, push_max_bytes)
        self.ledger: SubscriberLedger[Item] = SubscriberLedger(
            mode, queue_size, self.descriptor, policy=policy or AckPolicy.for_queue(queue_size)
        )
        self.garbage = 0
        # The producer's answer to our token: its registration's epoch, or why it refused
        # and which session said so (judged once the producer's sessions are known).
        self.registered_epoch: str | None = None
        self._refusal: tuple[str, str | None] | None = None
        self._unjudged = False
        # Which session greeted us (as its control named it): a refusal from another one
        # contests the greeting; answers in the service's name count only from it (a clock).
        self.greeted_by: str | None = None
        # Who greeted each epoch: the one whose notifications we queue last speaks for the
        # service (``data_session``), not the last greeting's (a forged one from a peer).
        self._greeters: dict[str, str | None] = {}
        self._greeted_mark: tuple[str | None, int] = (None, 0)  # (epoch, last) at a greeting
        self._producer_ids: frozenset[str] | None = None
        self._ids_at_ns = 0
        self._refusal_reported = False
        self._retry_at_ns: int | None = None
        self.registrations = 0  # greetings under distinct epochs
        self._registered_again = 0  # since ``registration_news``
        # Lapses: the epoch of the last notification queued and its base; per producer
        # instance the highest element number queued; elements counted as never notified.
        self._epoch: str | None = None
        self._base = 0
        self._high: OrderedDict[str, int] = OrderedDict()
        self._lapsed = 0
        # Counted at a greeting, not yet carried by a queued notification.
        self._ahead = 0
        # Fetch ahead: set once the consumer had to query for an element (see ``fetch_ahead``).
        self.fetching = False

    # -- input -----------------------------------------------------------------------------
    def receive(self, attachment: bytes | None, payload: Any, sender: str | None = None) -> bool:
        """One notification (or control message) as it arrived; True if something was
        queued. ``payload`` is the Zenoh payload (anything with ``to_bytes()``, or bytes);
        ``sender`` the Zenoh session id the message names as its source (None: none)."""
        try:
            if attachment is None:
                raise ValueError("notification without a header")
            head = decode_notification_header(attachment)
            if (
                not isinstance(head, Control)
                and head.epoch != self.registered_epoch
                and self._retired(head.epoch)
            ):
                self.ledger.counters.duplicates += 1
                return False
            if type(head) is Header:
                if head.epoch != self._epoch and head.base is not None:
                    return self._first_of_epoch(head, [_item(head, payload)])
                metadata = head.metadata
                pushed = payload if head.pushed and metadata is not None else None
                return self.ledger.receive(
                    head.epoch,
                    head.seq,
                    (head.timestamp_ns, metadata, pushed),
                    descriptor=head.descriptor,
                )
            if type(head) is BatchHeader:
                items = _batch_items(head, payload)
                if head.epoch != self._epoch and head.base is not None:
                    return self._first_of_epoch(head, items)
                return (
                    self.ledger.receive_many(
                        head.epoch, head.seq, items, descriptor=head.descriptor
                    )
                    > 0
                )
            assert type(head) is Control
            self._control(head, sender)
            return False
        except Exception:  # garbage on our key is counted, never raised
            self.garbage += 1
            return False

    def _first_of_epoch(self, head: Header | BatchHeader, items: list[Item]) -> bool:
        """A notification of another epoch than the last one queued: queue it as usual and,
        if it starts a later registration of the same producer instance, count the elements
        stored before that registration and after the last one queued as missed (our token
        had lapsed meanwhile)."""
        assert head.base is not None
        ledger = self.ledger
        self._raise_current()
        known = ledger.track(head.epoch)
        new = known is None or known.last == 0  # nothing of this epoch accepted yet
        queued = ledger.receive_many(head.epoch, head.seq, items, descriptor=head.descriptor)
        track = ledger.track(head.epoch)
        if not queued or track is None:
            return False
        # The first of them still queued: counted from the end, since a full observer's
        # queue pushed its oldest out for them (from the start it was past the end).
        before = max(0, len(ledger) - queued)
        high = self._high.get(head.epoch.rpartition(".")[0])
        if new and high is not None and head.base > high:
            gap = head.base - high
            ledger.note_missed(gap, before)
            self._lapsed += gap
        if new and self._ahead:
            ledger.note_missed(self._ahead, before, counted=True)
            self._ahead = 0
        self._epoch, self._base = head.epoch, head.base
        self._raise_high(head.epoch, head.base + track.last)
        return True

    def _retired(self, epoch: str) -> bool:
        """Whether ``epoch`` is an earlier registration of the producer instance that greeted
        us last (``<instance>.<n>``, n counting its registrations): retired, so none of its
        notifications can be in flight any more. One that arrives now was held back or is
        replayed, after the greeting counted what it carries as missed (our token lapsed):
        taken as well, it was counted twice and came after newer elements. (The greeting is
        trusted here: a forged one of a made-up instance can still move it.)"""
        registered = self.registered_epoch
        if registered is None:
            return False
        instance, _, number = epoch.rpartition(".")
        ours, _, latest = registered.rpartition(".")
        if instance != ours:
            return False
        try:
            return int(number) < int(latest)
        except ValueError:
            return False

    def _raise_current(self) -> None:
        """Remember how far the registration of the last notification queued has got."""
        if self._epoch is not None:
            track = self.ledger.track(self._epoch)
            if track is not None:
                self._raise_high(self._epoch, self._base + track.last)

    def _raise_high(self, epoch: str, number: int) -> None:
        instance = epoch.rpartition(".")[0]
        self._high[instance] = max(number, self._high.get(instance, 0))
        self._high.move_to_end(instance)
        if len(self._high) > _INSTANCES:
            self._high.popitem(last=False)

    @staticmethod
    def needs_sender(payload: Any) -> bool:
        """Whether ``receive`` needs to know who sent this message: only a control message
        (a greeting or a refusal: an empty payload) is judged by its sender."""
        return not len(payload)

    @property
    def refusal_to_judge(self) -> bool:
        """A refusal arrived that is not judged yet (the executor judges it at once)."""
        return self._unjudged

    def registration_news(self) -> int:
        """How often the subscription was registered again (the producer restarted, or the
        subscription had lapsed) since the last call (to log)."""
        again, self._registered_again = self._registered_again, 0
        return again

    def lapse_news(self) -> int:
        """Elements counted as never notified since the last call (to log once each)."""
        lapsed, self._lapsed = self._lapsed, 0
        return lapsed

    def _last_of(self, epoch: str | None) -> int:
        track = None if epoch is None else self.ledger.track(epoch)
        return 0 if track is None else track.last

    @property
    def data_session(self) -> str | None:
        """The session that greeted the registration whose notifications came last (the
        producer whose elements we take), or the last greeting's while no notification
        came after it (a restarted producer greets before it notifies) or the registration
        of the last ones is unknown.

        A peer can greet us under a made-up epoch from its own session (any peer can put on
        our key): the last greeting's session then named the peer, and a mediator that asked
        it for the camera's clock never got an answer (every frame ``clock-unmeasured``, for
        good, after one forged greeting and one notification). Its notifications cannot
        follow once the real producer's come again."""
        epoch = self._epoch
        since = self._greeted_mark != (epoch, self._last_of(epoch))
        if since and epoch is not None and epoch in self._greeters:
            return self._greeters[epoch]
        return self.greeted_by

    def _forget_greeters(self) -> None:
        """Keep the greeters of the epochs still known: the greeted one, the last queued and
        those the ledger tracks (its table is bounded and kept against floods)."""
        keep = {self.registered_epoch, self._epoch}
        self._greeters = {
            epoch: sender
            for epoch, sender in self._greeters.items()
            if epoch in keep or self.ledger.track(epoch) is not None
        }
        if len(self._greeters) > _GREETERS_MAX:  # a flood the ledger tracks: the two
            self._greeters = {e: s for e, s in self._greeters.items() if e in keep}

    def _greeted(self, epoch: str, base: int, since: int | None) -> None:
        """A registration of ours starts at element ``base`` of its producer instance;
        ``since``: how far the producer saw our previous registration acked, if it had
        one (what we know ourselves counts first: we may have taken more than was acked)."""
        self._raise_current()
        high = self._high.get(epoch.rpartition(".")[0])
        if high is None:
            # Nothing of that registration came through (refused behind a peer's
            # notifications, its greeting lost) or it is forgotten: the producer's word.
            high = since
        if high is not None and base > high:
            # A later registration of an instance we had: what it stored since the last
            # element queued was never notified (our token lapsed meanwhile).
            gap = base - high
            self.ledger.missed_total += gap
            self._ahead += gap
            self._lapsed += gap
        # First contact: what the producer stored before our registration was never ours;
        # a later lapse counts from here.
        self._raise_high(epoch, base)

    def _control(self, control: Control, sender: str | None) -> None:
        if control.descriptor != self.descriptor:
            return  # meant for another registration of this key: not ours to judge
        if control.kind == "hello":
            if (
                control.text == self.registered_epoch
                and self.greeted_by is not None
                and sender != self.greeted_by
            ) or self._retired(control.text):
                # An epoch is one producer instance's, greeting from its one session: the
                # same epoch in another session's name is forged (it would make that session
                # the one whose answers speak for the service: a mediator's clock). A
                # greeting of a retired registration is a replay: it would move the pin off
                # the live epoch (``SubscriberLedger`` rule 3).
                self.garbage += 1
                return
            if self.registered_epoch is not None and self.registered_epoch != control.text:
                self.registrations += 1  # a producer restart, or our token had lapsed
                self._registered_again += 1
            elif self.registered_epoch is None:
                self.registrations = 1
            self.registered_epoch = control.text
            self.ledger.pin(control.text)
            self.greeted_by = sender
            self._greeters[control.text] = sender
            self._greeted_mark = (self._epoch, self._last_of(self._epoch))
            if len(self._greeters) > _GREETERS_MAX:
                self._forget_greeters()
            if control.base is not None:
                self._greeted(control.text, control.base, control.since)
            self._refusal = None
            self._retry_at_ns = None
        elif self.registered_epoch is None or sender != self.greeted_by:
            # Unanswered yet, or a refusal from another session than the greeting's: one of
            # the two is forged, and the producer's sessions decide which (``judge``).
            self._refusal = (control.text, sender)
            self._unjudged = True
        # else: the greeting's own session refusing after it, an old message: it stands

    # -- refusals --------------------------------------------------------------------------
    def judge(self, now_ns: int) -> bool:
        """Judge a refusal that waits (see the module doc): kept if its sender is one of the
        producer's sessions, else dropped (the token is declared again at the next retry,
        in case the producer's sessions changed). True if the producer's sessions must be
        asked first (``trust_producer``): unknown, or older than ``RETRY_NS`` and the
        sender not among them."""
        if not self._unjudged or self._refusal is None:
            return False
        ids, sender = self._producer_ids, self._refusal[1]
        if ids is None or (sender not in ids and now_ns - self._ids_at_ns >= RETRY_NS):
            return True
        self._unjudged = False
        if ids != {sender}:
            # Not from the producer's session (a forgery), or more than one session answers
            # as the service (any peer can answer as any service): not trusted.
            self._refusal = None
        elif self.registered_epoch is not None:
            # The producer refused us after another session greeted us in its name: that
            # greeting was forged, and the refusal stands (logged, retried).
            self.registered_epoch = None
            self.greeted_by = None
        if self._retry_at_ns is None:
            self._retry_at_ns = now_ns + RETRY_NS
        return False

    def trust_producer(self, session_ids: frozenset[str], now_ns: int) -> None:
        """The Zenoh session ids that answer as the producer's service now: only their
        refusals count."""
        self._producer_ids = session_ids
        self._ids_at_ns = now_ns
        self.judge(now_ns)

    @property
    def refusal(self) -> str | None:
        """Why the producer refused this subscription (None: it did not, or not yet, or
        the refusal is not known to come from its session)."""
        if self._refusal is None or self._unjudged:
            return None
        return self._refusal[0]

    def refusal_news(self) -> str | None:
        """A refusal not reported yet, to log as an error once (the same subscription
        refused again after a retry is not reported again)."""
        text = self.refusal
        if text is None or self._refusal_reported:
            return None
        self._refusal_reported = True
        return text

    def retry_due(self, now_ns: int) -> bool:
        """True when a refused subscription should declare its token again: the refusal is
        forgotten, the producer's next answer decides."""
        if self._retry_at_ns is None or now_ns < self._retry_at_ns or self.registered_epoch:
            return False
        self._retry_at_ns = now_ns + RETRY_NS
        self._refusal = None
        self._unjudged = False
        return True

    # -- taking and acking -----------------------------------------------------------------
    def take_many(self, max_count: int) -> list[Entry[Item]]:
        """Up to ``max_count`` queued notifications, oldest first (they leave the queue)."""
        return self.ledger.take_many(max_count)

    def acks(self, now_ns: int, *, idle: bool) -> list[bytes]:
        """The acks to send now, wire-ready (see ``SubscriberLedger.acks_due``)."""
        return [encode_ack(epoch, seq) for epoch, seq in self.ledger.acks_due(now_ns, idle=idle)]

    def next_deadline_ns(self) -> int | None:
        """When a delayed ack falls due with nobody taking, or a refused subscription tries
        again (None: none waits)."""
        if self._unjudged:
            return 0  # a refusal to judge (``refusal_to_judge``): at once
        due = self.ledger.flush_at_ns()
        retry = self._retry_at_ns if self.registered_epoch is None else None
        if retry is not None and (due is None or retry < due):
            return retry
        return due

    def fetch_ahead(self, taken_missing: list[int], inflight: Container[int]) -> list[int]:
        """The stamps whose queries to start now, once ``fetching``: the taken notifications
        that came without their element (``taken_missing``) and every queued one, oldest
        first, less those in flight, at most a queue's worth."""
        queued = [e.item[0] for e in self.ledger.queued() if e.item[2] is None]
        wanted = [t for t in taken_missing + queued if t not in inflight]
        return wanted[: self.queue_size]

    def max_message_bytes(self) -> int:
        """The largest message (payload and header) an honest producer sends this
        subscription; a larger one is garbage, dropped before it is buffered. Unbounded
        while the push limit is the producer's (``push_max_bytes`` -1), and for observers
        (a batch of any length may reach them)."""
        if self.push_max_bytes < 0 or self.mode is not SubscriptionMode.FLOW:
            return 1 << 62
        per_element = self.push_max_bytes + INLINE_METADATA_MAX + _HEADER_SLACK
        return self.queue_size * per_element + _HEADER_SLACK

    # -- reading ---------------------------------------------------------------------------
    def __len__(self) -> int:
        return len(self.ledger)

    @property
    def missed_total(self) -> int:
        return self.ledger.missed_total

    def counters(self) -> SubscriberCounters:
        c = self.ledger.counters
        return SubscriberCounters(c.foreign, c.invalid, c.out_of_order, c.duplicates, c.refused)


def _item(head: Header, payload: Any) -> Item:
    pushed = payload if head.pushed and head.metadata is not None else None
    return (head.timestamp_ns, head.metadata, pushed)


def _batch_items(head: BatchHeader, payload: Any) -> list[Item]:
    """The elements of a decoded batch notification, payloads cut out when pushed."""
    times, metas, sizes = head.timestamps_ns, head.metadata, head.payload_sizes
    if sizes is None:
        return [(t, m, None) for t, m in zip(times, metas, strict=True)]
    raw = payload if type(payload) is bytes else payload.to_bytes()
    if sum(sizes) != len(raw):
        raise ValueError("batch payload sizes do not add up to the payload")
    items: list[Item] = []
    offset = 0
    for t, m, size in zip(times, metas, sizes, strict=True):
        items.append((t, m, raw[offset : offset + size] if m is not None else None))
        offset += size
    return items
