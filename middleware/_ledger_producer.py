"""The producer's half of the flow-control protocol, as a pure state machine (no Zenoh, no
threads, no clock of its own): the Zenoh layer feeds it tokens, acks, puts and the time, and
sends the notifications it returns.

Theory of operation
-------------------
A *registration* is one subscription token, identified by everything the token says:
``RegistrationKey(id, mode, queue size, push limit)``. The producer gives each registration
its own epoch ``<producer epoch>.<n>`` (n counts registrations of this producer instance)
and numbers its notifications 1, 2, ... under that epoch. Two tokens that share an id but
disagree on mode, queue size or push limit are two registrations; a token's withdrawal
removes only the registration with exactly its key; an ack counts only for the registration
whose epoch it names *and* whose id matches the ack key.

State per registration: ``sent`` (highest seq sent), ``acked`` (highest seq the subscriber
has taken, cumulative), and, for flow control, the headers of the un-acked notifications
(at most ``queue_size`` of them) so that they can be sent again.

Messages in, and what they do in every state:

``token_put(key)``
    unknown key: register it (new epoch, sent = acked = 0), unless the table holds its
    ``max_registrations`` already (``MAX_REGISTRATIONS`` by default; the producer's protocol
    passes its two pools of slots together): then ignored (the caller counts the refusal).
    Known key (a repeat, e.g. history and live both delivering it): nothing.
``token_delete(key)``
    known key: remove the registration (its credits with it) and hand it back so that the
    Zenoh layer can undeclare its publisher. Unknown key (never registered, or a token that
    names another registration's id with another mode or size): nothing.
``ack(id, epoch, seq)``
    no registration with this epoch and id (a foreign, stale or forged epoch, or an id that
    does not own the epoch): counted in ``foreign_acks``, nothing else. A seq beyond ``sent``
    (no subscriber took what was never sent: a forgery) is counted there too and changes
    nothing: taken as ``sent``, it would have acked what the subscriber still holds, and the
    producer would send past its window notifications the subscriber ignores and nobody
    resends (both sides held for good). So is a seq below 1 (seqs start at 1 and only taken
    ones are acked: a forgery, and distinct ones would otherwise fill the ack inbox, which
    keeps what ``plausible`` passes). Otherwise ``acked = max(acked, seq)``: duplicates
    and reordering cannot move it back; an ack that moves it records
    its time (``taken_ns``: when the producer last saw the subscriber take). An ack that
    moves nothing while notifications are outstanding is an idle subscriber's repeat: the
    outstanding ones are due again (a lost notification heals), at most once per
    ``REPEAT_RESEND_NS`` since the last progress or resend.
``put_many(n elements, now)``
    ``stored`` (the producer's element count; every registration's notifications carry the
    ``base`` it had when they registered) grows by n. The queue is counted in elements:
    refused, whole, while a flow registration has ``sent - acked + n > queue_size``
    (``full(n)``; nothing of the batch is counted); otherwise every registration gets seqs
    ``sent + 1 .. sent + n`` and one ``Send`` that covers them all (one notification for
    the batch). Each element stays outstanding on its own seq, so acks and resends work per
    element as if it had come alone.
``tick(now)``
    flow registrations with outstanding notifications and no progress for
    ``RETRANSMIT_NS`` get them again (``Send(..., again=True)``), oldest first, one element
    per notification (a resend never batches).
``send_failed(key, epoch)``
    the notification stays outstanding (its credit is not lost) and is due at the next tick.

Properties (checked by tests/middleware/test_protocol_model.py after every step):
- ``0 <= acked <= sent`` and, for flow control, ``sent - acked <= queue_size`` (elements,
  however they were batched);
- the table holds at most ``max_registrations`` registrations and each at most
  ``queue_size`` outstanding headers, whatever peers send;
- only the subscriber that owns an epoch (or a peer allowed to ack for it, see docs/protocol.md,
  *Trust*) can move its ``acked``.
"""

from __future__ import annotations

from collections import OrderedDict, deque
from dataclasses import dataclass, field
from typing import Generic, NamedTuple, TypeVar

from ._records import SubscriptionMode
from ._wire import descriptor_of

# Registrations one ledger keeps by default; tokens beyond it are ignored (and counted).
MAX_REGISTRATIONS = 1024
# Retired keys remembered with how far they were acked (``Registration.since``).
RETIRED_KEYS = 1024
# Outstanding flow-control notifications are sent again after this long without progress.
RETRANSMIT_NS = 500_000_000
# A repeated ack makes the outstanding ones due at most this often: a peer repeating a
# subscriber's last ack as fast as it can (the epoch and seq are on the wire) costs the
# producer at most one resend round per period, not one per ack.
REPEAT_RESEND_NS = 100_000_000

# What the Zenoh layer wants to resend with a notification (timestamp, metadata, ...).
H = TypeVar("H")


@dataclass(frozen=True, slots=True)
class RegistrationKey:
    """Everything a subscription token says: the identity of a registration."""

    sub_id: str
    mode: SubscriptionMode
    queue_size: int
    push_max_bytes: int
    # ``mode/N/push`` as in the token; notifications carry it so that a subscriber can tell
    # its own registration's notifications from those of a colliding token. Computed once:
    # every notification sent needs it.
    descriptor: str = field(init=False, compare=False, repr=False)
    # Keys are looked up several times per put; an Enum field makes the generated hash a
    # Python call, so it is computed once.
    _hash: int = field(init=False, compare=False, repr=False)

    def __post_init__(self) -> None:
        descriptor = descriptor_of(self.mode, self.queue_size, self.push_max_bytes)
        object.__setattr__(self, "descriptor", descriptor)
        identity = (self.sub_id, self.mode.value, self.queue_size, self.push_max_bytes)
        object.__setattr__(self, "_hash", hash(identity))

    def __hash__(self) -> int:
        return self._hash


@dataclass(slots=True)
class Registration(Generic[H]):
    """One registered subscription as the producer counts it."""

    key: RegistrationKey
    epoch: str
    sent: int = 0
    acked: int = 0
    # (seq, header) of un-acked flow-control notifications, oldest first.
    outstanding: deque[tuple[int, H]] = field(default_factory=deque)
    progress_ns: int = 0
    # When an ack last freed credit (the subscriber took something); None before any.
    taken_ns: int | None = None
    # Set by a failed send or an idle subscriber's repeated ack: resend at the next tick.
    resend_now: bool = False
    # Elements the producer had stored when this registration was made: seq s is the
    # producer's element number base + s, so a subscriber whose registration lapsed and came
    # back under a new epoch counts what was stored in between (``missed``).
    base: int = 0
    # A key registered before (its token lapsed and came back): the element number its
    # last registration was acked up to (base + acked), for the subscriber's count of what
    # the lapse lost when it knows no element number of ours (``SubscriberProtocol``).
    since: int | None = None

    @property
    def queued(self) -> int:
        return self.sent - self.acked

    @property
    def flow(self) -> bool:
        return self.key.mode is SubscriptionMode.FLOW


class Send(NamedTuple, Generic[H]):
    """A notification to send under ``epoch`` to ``key``'s subscriber: ``headers[i]`` is the
    element of seq ``seq + i`` (one element, or a batch from ``put_many``). (A named tuple:
    as immutable as a frozen dataclass, built in half the time, once per put and
    registration.)"""

    key: RegistrationKey
    epoch: str
    seq: int
    acked: int
    headers: tuple[H, ...]
    again: bool = False
    base: int = 0


@dataclass(slots=True)
class ProducerCounters:
    """What the ledger ignored, reported by ``info`` (``BufferInfo.foreign_acks``)."""

    foreign_acks: int = 0


class ProducerLedger(Generic[H]):
    """Registrations, credits and epochs of one buffer's producer. Not thread-safe: the
    caller serialises every call (see ``Producer``'s Threads paragraph)."""

    def __init__(self, epoch: str, *, max_registrations: int = MAX_REGISTRATIONS) -> None:
        self.epoch = epoch
        self._max = max_registrations
        self._regs: dict[RegistrationKey, Registration[H]] = {}
        self._by_epoch: dict[str, Registration[H]] = {}
        self._count = 0
        # Elements stored so far (``put_many`` counts them): a new registration's base.
        self.stored = 0
        # Retired keys and how far they were acked (``Registration.since``); the oldest
        # are forgotten beyond ``RETIRED_KEYS``.
        self._retired: OrderedDict[RegistrationKey, int] = OrderedDict()
        self.counters = ProducerCounters()

    # -- tokens ----------------------------------------------------------------------------
    def token_put(self, key: RegistrationKey, now_ns: int) -> Registration[H] | None:
        """Register ``key``; the new registration, or None if known or the table is full."""
        if key in self._regs:
            return None
        if len(self._regs) >= self._max:
            return None
        self._count += 1
        reg: Registration[H] = Registration(
            key,
            f"{self.epoch}.{self._count}",
            progress_ns=now_ns,
            base=self.stored,
            since=self._retired.pop(key, None),
        )
        self._regs[key] = reg
        self._by_epoch[reg.epoch] = reg
        return reg

    def token_delete(self, key: RegistrationKey) -> Registration[H] | None:
        """Remove exactly ``key``'s registration; it is returned (None if there was none)."""
        reg = self._regs.pop(key, None)
        if reg is not None:
            del self._by_epoch[reg.epoch]
            self._retired[key] = reg.base + reg.acked
            if len(self._retired) > RETIRED_KEYS:
                self._retired.popitem(last=False)
        return reg

    # -- acks ------------------------------------------------------------------------------
    def plausible(self, sub_id: str, epoch: str, seq: int) -> bool:
        """Whether ``ack`` would look at this ack at all: a live registration owns the
        epoch, under this id, and sent at least ``seq`` (itself at least 1). The one method
        safe to call from another thread (an ack inbox on Zenoh's thread: one dict look-up
        and two reads, each atomic under the GIL; a registration made or retired meanwhile is
        seen either way, and ``ack`` checks again)."""
        reg = self._by_epoch.get(epoch)
        return reg is not None and reg.key.sub_id == sub_id and 1 <= seq <= reg.sent

    def retired(self, epoch: str) -> bool:
        """Whether ``epoch`` is one this ledger gave a registration that it has retired since
        (safe from another thread, as ``plausible``)."""
        prefix, _, count = epoch.rpartition(".")
        return (
            prefix == self.epoch
            and count.isdigit()
            and 0 < int(count[:9]) <= self._count
            and epoch not in self._by_epoch
        )

    def ack(self, sub_id: str, epoch: str, seq: int, now_ns: int) -> bool:
        """Apply a cumulative ack; True if it freed credit."""
        if not self.plausible(sub_id, epoch, seq):
            self.counters.foreign_acks += 1
            return False
        reg = self._by_epoch[epoch]
        new = seq
        if new <= reg.acked:
            if (
                reg.flow
                and reg.sent > reg.acked
                and seq == reg.acked
                and now_ns - reg.progress_ns >= REPEAT_RESEND_NS
            ):
                reg.resend_now = True  # an idle subscriber that lacks the rest
            return False
        reg.acked = new
        while reg.outstanding and reg.outstanding[0][0] <= new:
            reg.outstanding.popleft()
        reg.progress_ns = now_ns
        reg.taken_ns = now_ns
        reg.resend_now = False
        return True

    # -- producing -------------------------------------------------------------------------
    def full(self, count: int = 1) -> Registration[H] | None:
        """A flow registration without room for ``count`` more elements (a put of that many
        must be refused), or None."""
        for reg in self._regs.values():
            if reg.flow and reg.queued + count > reg.key.queue_size:
                return reg
        return None

    def put_many(self, headers: tuple[H, ...], now_ns: int) -> list[Send[H]]:
        """Count ``len(headers)`` stored elements, in order; one notification per
        registration covers them all. Call only when not ``full(len(headers))``."""
        count = len(headers)
        if count < 1:
            raise ValueError("put_many needs at least one element")
        if self.full(count) is not None:
            raise RuntimeError("put while a flow-controlled queue has no room for it")
        sends: list[Send[H]] = []
        self.stored += count
        for reg in self._regs.values():
            first = reg.sent + 1
            reg.sent += count
            if reg.flow:
                if not reg.outstanding:
                    reg.progress_ns = now_ns  # the retransmit clock starts now
                reg.outstanding.extend(zip(range(first, first + count), headers, strict=True))
            sends.append(Send(reg.key, reg.epoch, first, reg.acked, headers, base=reg.base))
        return sends

    def send_failed(self, key: RegistrationKey, epoch: str) -> None:
        """A notification did not leave: keep it outstanding and resend it at the next tick."""
        reg = self._regs.get(key)
        if reg is not None and reg.epoch == epoch and reg.flow:
            reg.resend_now = True

    def tick(self, now_ns: int) -> list[Send[H]]:
        """Outstanding flow notifications that are due again, oldest first per registration."""
        sends: list[Send[H]] = []
        for reg in self._regs.values():
            if not reg.outstanding:
                continue
            if not reg.resend_now and now_ns - reg.progress_ns < RETRANSMIT_NS:
                continue
            reg.resend_now = False
            reg.progress_ns = now_ns  # at most one resend per period while nothing moves
            sends.extend(
                Send(reg.key, reg.epoch, seq, reg.acked, (header,), again=True, base=reg.base)
                for seq, header in reg.outstanding
            )
        return sends

    def next_retransmit_ns(self) -> int | None:
        """When ``tick`` next has a resend due (None: nothing outstanding)."""
        due = [
            reg.progress_ns if reg.resend_now else reg.progress_ns + RETRANSMIT_NS
            for reg in self._regs.values()
            if reg.outstanding
        ]
        return min(due, default=None)

    # -- reading ---------------------------------------------------------------------------
    def registrations(self) -> list[Registration[H]]:
        return list(self._regs.values())

    def get(self, key: RegistrationKey) -> Registration[H] | None:
        return self._regs.get(key)

    def by_epoch(self, epoch: str) -> Registration[H] | None:
        return self._by_epoch.get(epoch)

    def clear(self) -> list[Registration[H]]:
        """Forget every registration (the producer closes); they are returned."""
        gone = list(self._regs.values())
        self._regs.clear()
        self._by_epoch.clear()
        return gone
