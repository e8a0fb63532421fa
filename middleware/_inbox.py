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
from collections.abc import Iterator

import zenoh

# The attachment of a doorbell sample.
DOORBELL = b"fg-doorbell"


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
