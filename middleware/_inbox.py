"""Zenoh input as a bounded inbox per object, filled on Zenoh's thread, emptied by the node.

An ``Inbox`` is a Zenoh subscriber with a direct callback (``indirect=False``: it runs on
the Zenoh thread that received the sample, no extra thread). The callback only checks the
sample's size, appends it to a bounded deque and signals the owning object to the node's
executor; nothing else of framegate runs on Zenoh's threads. The owner empties the inbox
in bounded batches (``take``) on the executor, or inline when a handler waits for it.

Bounds, so that a flood of any size and rate costs bounded memory and bounded work:

- a sample larger than ``max_bytes`` (payload plus attachment) is dropped and counted
  (``oversize``) before it is buffered: an ack is tens of bytes, a 1 MiB "ack" is garbage;
- at ``capacity`` the oldest sample (in a ``ControlInbox``: the arriving one, see there) is
  dropped and counted (``overflow``). The owner sizes
  the capacity from the protocol's credit bound, so honest traffic never fills it; what a
  flood of forged messages pushes out, the protocol recovers like any loss (resends,
  cumulative acks).

A deque, not a Zenoh FIFO: a full FIFO would block Zenoh's receive thread and stall the
whole link (docs/protocol.md, *Floods*).

A small Zenoh sample is a slice of the batch it arrived in (up to 64 KiB), and keeps all of
it alive: 8192 held 20-byte messages, each sent in its own batch (``express``), held 580 MB
here. A ``ControlInbox`` (a producer's acks and tokens: small by definition) therefore keeps
only a copy of the key and payload (``Control``), never the sample, so its bytes are bounded
by ``capacity`` x ``max_bytes``. An ``Inbox`` keeps the samples themselves (a subscription's
notifications: copying a large payload would cost a memcpy on Zenoh's thread).

Why a direct callback is cheap here: zenoh-python enters Python from its (non-Python)
receive thread with ``PyGILState_Ensure`` and leaves with ``PyGILState_Release``; on a
thread that owns no Python thread state, each call creates one and destroys it again,
which cost ~9-10 us per sample on a 2-core machine (measured with 64 B samples; 0.7 us
for a RingChannel drained in batches). The first callback on each Zenoh thread therefore
takes one more ``PyGILState_Ensure`` that it never releases, so the thread keeps its
thread state and every later entry costs ~0.8 us. Zenoh's threads live as long as the
process; each keeps one small thread state.
"""

from __future__ import annotations

import contextlib
import ctypes
import threading
import time
from collections import deque
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any, Generic, TypeVar

import zenoh

from ._ledger_producer import REPEAT_RESEND_NS
from ._wire import ACK_KEYS_REMEMBERED, AckFilter, decode_ack

# Zenoh threads whose Python thread state is kept (see the module doc).
_PINNED: set[int] = set()


def pin_thread_state() -> None:
    """(a Zenoh thread, in a direct callback) Keep this thread's Python thread state alive
    from its first callback on (see the module doc); later calls cost one set look-up."""
    ident = threading.get_ident()
    if ident not in _PINNED:
        _PINNED.add(ident)
        ctypes.pythonapi.PyGILState_Ensure()


T = TypeVar("T")

# A producer's control inboxes (``ControlInbox``). Acks: what honest subscribers can send
# between two turns of the executor (coalesced, a few per registration and queue window,
# plus a re-ack each per 0.5 s); an ack (msgpack {"e": epoch, "s": seq}) is a few dozen
# bytes, a larger one is dropped unread. Tokens come and go at human rates; a churning
# peer's excess is dropped and counted. A lost ack or token costs nothing lasting: acks are
# cumulative and repeated, a lost token change is recovered (``tokens_lost``).
ACK_INBOX = 8192
ACK_MAX_BYTES = 256
TOKEN_INBOX = 4096
# A key longer than this is no key of ours (names are short): dropped and counted.
KEY_MAX_BYTES = 1024
# What a subscription's notification inbox holds at most, in payload and attachment bytes
# (``Inbox``): its count bound alone let garbage of any size pile up.
NOTIFY_INBOX_BYTES = 64 * 1024 * 1024
# What one held ``Control`` costs beyond its payload and key: the object and the two
# Python objects it refers to (generous).
CONTROL_OVERHEAD_BYTES = 256


def control_inbox_bytes() -> int:
    """The most a producer's two control inboxes can hold (``BufferLimits``), with the last
    ack kept per key (``AckInbox``)."""
    per_ack = ACK_MAX_BYTES + KEY_MAX_BYTES + CONTROL_OVERHEAD_BYTES
    tokens = TOKEN_INBOX * (KEY_MAX_BYTES + CONTROL_OVERHEAD_BYTES)
    return (ACK_INBOX + ACK_KEYS_REMEMBERED) * per_ack + tokens


@dataclass(frozen=True, slots=True)
class Control:
    """A control message detached from Zenoh's buffers: its key, its payload, and whether it
    is a put (for a token: alive) or a delete; an ack also as the ack inbox decoded it
    (epoch, seq), so that the protocol does not decode it again."""

    key: str
    payload: bytes
    alive: bool
    ack: tuple[str, int] | None = None


class _Bounded(Generic[T]):
    """One subscriber's bounded inbox of ``T``; ``signal`` is called after each append."""

    # At capacity, drop the arriving sample instead of the oldest one.
    drop_newest = False

    def __init__(self, *, capacity: int, max_bytes: int, signal: Callable[[], None]) -> None:
        self.capacity = capacity
        self.max_bytes = max_bytes
        self.overflow = 0  # samples pushed out by newer ones (a flood)
        self.oversize = 0  # samples larger than max_bytes, never buffered
        self.closed = False
        self._items: deque[T] = deque()
        self._signal = signal
        self._count_lock = threading.Lock()  # the drop counters (Zenoh may use two threads)
        self._subscriber: Any = None

    def declare(self, session: zenoh.Session, keyexpr: str, *, liveliness: bool = False) -> None:
        """Start receiving. Separate from the constructor because the callback may run at
        once (a liveliness history), when the owner must already hold this inbox."""
        handler = zenoh.handlers.Callback(self._on_sample, indirect=False)
        if liveliness:
            self._subscriber = session.liveliness().declare_subscriber(
                keyexpr, handler, history=True
            )
        else:
            self._subscriber = session.declare_subscriber(keyexpr, handler)

    def _on_sample(self, sample: zenoh.Sample) -> None:
        """(Zenoh's thread) Check the size, append, signal; never blocks, never calls Zenoh."""
        if threading.get_ident() not in _PINNED:  # once per thread: no call per sample
            pin_thread_state()
        if self.closed:
            return
        payload = sample.payload  # one wrapper, read once (each access makes a new one)
        size = len(payload)
        attachment = sample.attachment
        if attachment is not None:
            size += len(attachment)
        items = self._items
        if size > self.max_bytes:
            with self._count_lock:
                self.oversize += 1
            return
        if len(items) >= self.capacity:
            if self.drop_newest:
                with self._count_lock:
                    self.overflow += 1
                return
            self._push_out()
        kept = self._keep(sample, payload)
        if kept is None:  # not ours to keep (``ControlInbox``: a key too long)
            with self._count_lock:
                self.oversize += 1
            return
        if kept is DROPPED:  # dropped and counted by ``_keep`` (``AckInbox``)
            return
        items.append(kept)  # type: ignore[arg-type]
        self._signal()

    def _push_out(self) -> None:
        """(Zenoh's thread) Drop the oldest item to make room, counted in ``overflow``."""
        with self._count_lock, contextlib.suppress(IndexError):
            self._items.popleft()
            self.overflow += 1

    def __len__(self) -> int:
        return len(self._items)

    @property
    def dropped(self) -> int:
        """Samples dropped unread, for their size or by newer ones (``AckInbox``: also
        for their first byte, or as repeats)."""
        return self.oversize + self.overflow

    def _keep(self, sample: zenoh.Sample, payload: zenoh.ZBytes) -> T | _Drop | None:
        """What to hold of ``sample`` (on Zenoh's thread), None to drop it as oversize, or
        ``DROPPED`` when it dropped and counted it itself."""
        raise NotImplementedError

    def take(self, budget: int) -> list[T]:
        """Up to ``budget`` items, oldest first (never blocks)."""
        items = self._items
        if not items:  # the common case on a hot path: nothing came
            return []
        out: list[T] = []
        popleft = items.popleft
        with contextlib.suppress(IndexError):
            while len(out) < budget:
                out.append(popleft())
        return out

    def close(self) -> None:
        self.closed = True
        if self._subscriber is not None:
            with contextlib.suppress(zenoh.ZError):
                self._subscriber.undeclare()
        self._items.clear()


class Inbox(_Bounded[zenoh.Sample]):
    """A bounded inbox of Zenoh samples (each keeps the batch it arrived in alive), bounded
    in bytes as well: a subscription's notifications may be of any size (a pushed frame),
    so a count alone let a peer's 4 MiB garbage on one notify key hold 96 of them (a
    mediator grew 42 -> 362 MB). Past ``max_held_bytes`` (payloads and attachments) the
    oldest are pushed out, counted in ``squeezed``, not ``overflow``: honest pushed frames
    fill it too (32 of 3 MiB), so they are no sign of a flood (``dropped``). The newest sample
    is always kept, so an element of any size still passes. What honest traffic loses so is
    resent (flow control) or counted in ``missed`` (an observer)."""

    def __init__(
        self,
        *,
        capacity: int,
        max_bytes: int,
        signal: Callable[[], None],
        max_held_bytes: int = NOTIFY_INBOX_BYTES,
    ) -> None:
        super().__init__(capacity=capacity, max_bytes=max_bytes, signal=signal)
        self.max_held_bytes = max_held_bytes
        self.held_bytes = 0  # under _count_lock
        self.squeezed = 0  # samples pushed out for the byte bound (under _count_lock)
        self._sizes: deque[int] = deque()  # one per held sample, in the same order

    def _keep(self, sample: zenoh.Sample, payload: zenoh.ZBytes) -> zenoh.Sample:
        attachment = sample.attachment
        size = len(payload) + (len(attachment) if attachment is not None else 0)
        while self.held_bytes + size > self.max_held_bytes and self._items:
            self._push_out(squeeze=True)
        with self._count_lock:
            self._sizes.append(size)
            self.held_bytes += size
        return sample

    def _push_out(self, *, squeeze: bool = False) -> None:
        with self._count_lock, contextlib.suppress(IndexError):
            self._items.popleft()
            self.held_bytes -= self._sizes.popleft()
            if squeeze:
                self.squeezed += 1
            else:
                self.overflow += 1

    def take(self, budget: int) -> list[zenoh.Sample]:
        if not self._items:  # the common case on a hot path: nothing came
            return []
        with self._count_lock:  # items and their sizes leave together
            out = super().take(budget)
            for _ in out:
                self.held_bytes -= self._sizes.popleft()
        return out

    def close(self) -> None:
        super().close()
        with self._count_lock:
            self._sizes.clear()
            self.held_bytes = 0


class _Drop:
    """``_keep``'s answer for a sample that was dropped and counted by ``_keep`` itself."""


DROPPED = _Drop()


class ControlInbox(_Bounded[Control]):
    """A bounded inbox of small control messages, copied out of Zenoh's buffers; a key
    longer than ``KEY_MAX_BYTES`` counts as oversize. When full (only a flood fills it) it
    drops what arrives, uncopied: a copy costs ~1 us of Zenoh's thread, paid for nothing
    when a newer message pushes it out, and either loss is recovered alike (acks are
    cumulative and repeated; a lost token change triggers a resync)."""

    drop_newest = True

    def _keep(self, sample: zenoh.Sample, payload: zenoh.ZBytes) -> Control | _Drop | None:
        key = str(sample.key_expr)
        if len(key) > KEY_MAX_BYTES:
            return None
        return Control(key, payload.to_bytes(), sample.kind == zenoh.SampleKind.PUT)


class AckInbox(ControlInbox):
    """A producer's ack inbox: besides a ``ControlInbox``'s bounds, it drops on Zenoh's
    thread, before any object is made or anyone is woken, the two things an ack flood is
    made of, and counts them:

    - ``malformed``: a payload whose first byte is not an ack's (a msgpack map of two,
      ``encode_ack``): garbage, never decoded (the protocol would count and drop it too);
    - ``repeats``: the same payload on the same key as the last one kept for that key, within
      ``REPEAT_RESEND_NS`` of it. Acks are cumulative, and the protocol ignores such a repeat
      (it can only make resends due, at most that often), so it carries nothing, an honest
      subscriber's included (it repeats an ack when a resent notification crosses its ack):
      an ack that never reached the inbox is no repeat of anything kept, and a repeat after
      the window passes;
    - ``foreign``: an ack that cannot count (``plausible`` says no: no live registration owns
      its epoch under its key's id, or it acks more than was sent): forged acks of made-up
      epochs, ids or numbers, distinct each (undecodable ones count as ``malformed``);
      reported with the protocol's own count of them (``BufferInfo.foreign_acks``). Those of
      a registration the producer retired are counted apart too (``retired``; see
      ``ProducerProtocol.tokens_lost`` for why), and ``on_retired`` is called, at most every
      ``REPEAT_RESEND_NS`` whatever a flood sends.

    Garbage and forged acks then cost Zenoh's thread a copy of at most ``max_bytes``, a
    comparison or a decode, and the executor nothing (those of a retired registration: a
    turn every ``REPEAT_RESEND_NS`` at most): they never fill the inbox, so an
    honest ack that arrives among them is kept (measured: ``docs/limits.md``). Only acks a
    live registration could take reach it (a peer that read a subscriber's epoch off its
    notify key can still send those: the default profile's limit, docs/security.md)."""

    def __init__(
        self,
        *,
        capacity: int = ACK_INBOX,
        max_bytes: int,
        signal: Callable[[], None],
        plausible: Callable[[str, str, int], bool],
        retired: Callable[[str], bool],
        on_retired: Callable[[], None],
    ) -> None:
        super().__init__(capacity=capacity, max_bytes=max_bytes, signal=signal)
        self.malformed = 0
        self.repeats = 0
        self.foreign = 0
        self.retired = 0  # of the foreign ones: of a registration the producer retired
        self._on_retired = on_retired  # told of them, at most every REPEAT_RESEND_NS
        self._retired_told_ns: int | None = None
        self._filter = AckFilter(REPEAT_RESEND_NS)  # only a shortcut: the protocol checks again
        self._plausible = plausible
        self._retired = retired

    @property
    def dropped(self) -> int:
        return self.oversize + self.overflow + self.malformed + self.repeats  # foreign: apart

    def _keep(self, sample: zenoh.Sample, payload: zenoh.ZBytes) -> Control | _Drop | None:
        data = payload.to_bytes()  # at most ``max_bytes``: checked before
        if self._filter.malformed(data):
            with self._count_lock:
                self.malformed += 1
            return DROPPED
        key = str(sample.key_expr)
        if len(key) > KEY_MAX_BYTES:
            return None
        now_ns = time.monotonic_ns()
        if self._filter.repeat(key, data, now_ns):
            with self._count_lock:
                self.repeats += 1
            return DROPPED
        try:
            epoch, seq = decode_ack(data)
        except Exception:  # garbage that starts like an ack: the protocol would drop it too
            with self._count_lock:
                self.malformed += 1
            return DROPPED
        if not self._plausible(key.rsplit("/", 1)[-1], epoch, seq):
            retired = self._retired(epoch)
            with self._count_lock:
                self.foreign += 1
                self.retired += retired
                told = self._retired_told_ns
                tell = retired and (told is None or now_ns - told >= REPEAT_RESEND_NS)
                if tell:
                    self._retired_told_ns = now_ns
            if tell:
                self._on_retired()
            return DROPPED
        self._filter.remember(key, data, now_ns)
        return Control(key, data, sample.kind == zenoh.SampleKind.PUT, (epoch, seq))


class TokenInbox(ControlInbox):
    """A producer's subscription-token inbox. A token that comes and goes between two looks
    (churn: declared and withdrawn at once) is its withdrawal alone: ``take`` drops a put
    that a later delete of the same key in the same batch undoes, counted in ``collapsed``
    (not a loss: a put then a delete leaves the table as the delete alone does, whether the
    key was registered before or not), so such a token costs no registration, greeting or
    retirement."""

    def __init__(self, *, capacity: int, signal: Callable[[], None]) -> None:
        super().__init__(capacity=capacity, max_bytes=0, signal=signal)
        self.collapsed = 0

    def take(self, budget: int) -> list[Control]:
        batch = super().take(budget)
        last_delete: dict[str, int] = {}
        for index, message in enumerate(batch):
            if not message.alive:
                last_delete[message.key] = index
        if not last_delete:
            return batch
        kept = [
            message
            for index, message in enumerate(batch)
            if not message.alive or last_delete.get(message.key, -1) < index
        ]
        self.collapsed += len(batch) - len(kept)  # under the producer's lock, as every take
        return kept
