"""Zenoh input as a channel drained by framegate's own threads, not a Python callback.

An ``Inbox`` is a Zenoh subscriber with a ``RingChannel``: Zenoh's threads only enqueue
each sample (no Python, no GIL), and the object that owns the inbox drains it in batches
with ``try_recv`` on whichever thread needs the input now — a caller of ``take`` or ``put``
before it decides, or the node's loop for an object nobody calls. A caller that must wait
for input blocks in the channel's own ``recv`` (the GIL released), so one sample costs one
wake-up of the thread that uses it, instead of a wake-up of zenoh-python's callback thread
and then a second one of the waiting caller.

``recv`` has no timeout: a receiver that must stop waiting at a deadline asks the node's
loop to ``ring`` the doorbell then, a session-local put on the inbox's key that is never
fed to the protocol. Closing the inbox (undeclaring the subscriber) ends every ``recv``.

A ring, not a FIFO: a full FIFO would block Zenoh's receive thread and stall the whole link
(see the README's *Floods*). Its capacity is set by the owner from the protocol's credit
bound, so honest traffic never fills it; a flood of forged messages overwrites the oldest
samples, which the protocol recovers like any loss (resends, cumulative acks).
"""

from __future__ import annotations

import contextlib
import threading
import time
from collections.abc import Iterator

import zenoh

from ._loop import NodeLoop

# The attachment of a doorbell sample.
DOORBELL = b"fg-doorbell"
# With nobody waiting for input, the node's loop drains an inbox this often, on one grid so
# that a node's objects share a wake.
DRAIN_NS = 250_000_000


def _next_drain_ns(now_ns: int) -> int:
    return (now_ns // DRAIN_NS + 1) * DRAIN_NS


class Inbox:
    """One subscriber's channel. Not a lock holder: the owner serialises draining and says
    (under its own lock) which thread, if any, is blocked in ``recv``."""

    def __init__(
        self, session: zenoh.Session, keyexpr: str, *, capacity: int, doorbell_key: str
    ) -> None:
        self._session = session
        self._doorbell_key = doorbell_key
        self._subscriber = session.declare_subscriber(keyexpr, zenoh.handlers.RingChannel(capacity))
        self._handler = self._subscriber.handler
        self.closed = False

    def drain(self) -> Iterator[zenoh.Sample]:
        """Every sample waiting now, oldest first, doorbells left out (never blocks);
        nothing once closed."""
        if self.closed:
            return
        try_recv = self._handler.try_recv
        while True:
            try:
                sample = try_recv()
            except zenoh.ZError:  # closed under us: a ring's try_recv raises then
                return
            if sample is None:
                return
            attachment = sample.attachment
            if attachment is not None and attachment.to_bytes() == DOORBELL:
                continue
            yield sample

    def recv(self) -> zenoh.Sample | None:
        """Block until a sample arrives (the GIL released): the sample, or None for a
        doorbell or a closed inbox."""
        try:
            sample = self._handler.recv()
        except zenoh.ZError:  # closed: the subscriber was undeclared
            return None
        attachment = sample.attachment
        if attachment is not None and attachment.to_bytes() == DOORBELL:
            return None
        return sample

    def ring(self) -> None:
        """Wake the thread blocked in ``recv`` (a put that never leaves this session)."""
        with contextlib.suppress(zenoh.ZError):
            self._session.put(
                self._doorbell_key,
                b"",
                attachment=DOORBELL,
                allowed_destination=zenoh.Locality.SESSION_LOCAL,
            )

    def close(self) -> None:
        self.closed = True
        with contextlib.suppress(zenoh.ZError):
            self._subscriber.undeclare()


class Receiver:
    """Who waits for an inbox's input: at most one thread of its owner blocks in ``recv``
    (the *receiver*), the others wait in the owner's condition for its news; the node's
    loop rings the doorbell at the receiver's deadline and, with no receiver, drains the
    inbox every ``DRAIN_NS``. Every field is guarded by the owner's lock (the condition's)."""

    def __init__(self, inbox: Inbox, cond: threading.Condition, loop: NodeLoop) -> None:
        self._inbox = inbox
        self._cond = cond
        self._loop = loop
        self.active = False  # a thread blocks in ``recv``: the inbox's input is its to take
        self.wake_at_ns: int | None = None  # when the loop rings its doorbell (monotonic)
        self._drain_at_ns = _next_drain_ns(time.monotonic_ns())

    def wait(self, wait_s: float) -> zenoh.Sample | None:
        """(holding the owner's lock) Wait up to ``wait_s`` for input: as the receiver,
        blocked in ``recv`` with the lock released, returning the sample it got (None for
        the doorbell); or, when another thread is the receiver, in the condition (None).
        The owner then feeds the sample, drains the rest and tells the waiters."""
        if self.active:
            self._cond.wait(wait_s)
            return None
        self.active = True
        wake_at = time.monotonic_ns() + int(wait_s * 1e9)
        self.wake_at_ns = wake_at
        self._cond.release()
        try:
            self._loop.poke(wake_at)
            return self._inbox.recv()
        finally:
            self._cond.acquire()
            self.active = False
            self.wake_at_ns = None

    def wake(self) -> None:
        """(under the lock) Have the receiver's doorbell rung at once (news it must see)."""
        if self.active:
            self.wake_at_ns = 0

    def deadline_ns(self) -> int | None:
        """(under the lock) When the loop must act: ring the receiver, or drain."""
        return self.wake_at_ns if self.active else self._drain_at_ns

    def due(self, now_ns: int) -> tuple[bool, bool]:
        """(under the lock, on the loop) ``(ring, drain)``: whether to ring the receiver's
        doorbell now, and whether the drain grid is due (no receiver)."""
        if self.active:
            if self.wake_at_ns is not None and self.wake_at_ns <= now_ns:
                self.wake_at_ns = None
                return True, False
            return False, False
        if self._drain_at_ns <= now_ns:
            self._drain_at_ns = _next_drain_ns(now_ns)
            return False, True
        return False, False

    def ring(self) -> None:
        """(not under the lock) Ring the doorbell: the receiver's ``recv`` returns."""
        self._inbox.ring()
