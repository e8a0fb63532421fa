"""What the producer's protocol asks its wrapper to do (``Publish``, ``Retire``) and why a
put cannot be stored now (``Refusal``): plain values, no I/O."""

from __future__ import annotations

from dataclasses import dataclass
from typing import NamedTuple

from ._ledger_producer import RegistrationKey


class Publish(NamedTuple):
    """Send ``payload`` with ``attachment`` to ``key``'s subscriber on ``keyexpr``; ``block``:
    flow-controlled (Zenoh's BLOCK congestion control), else DROP. The first notification
    to a key declares its publisher (a control message is sent without one). (A named
    tuple: as immutable as a frozen dataclass, and built in a third of the time, once per
    put.)"""

    key: RegistrationKey
    keyexpr: str
    payload: bytes
    attachment: bytes
    block: bool
    # The registration epoch of a notification, None for a control message: a notification
    # whose send fails is reported back with it (``send_failed``).
    epoch: str | None = None

    @property
    def control(self) -> bool:
        """A control message (greeting, refusal): rare, sent once with DROP congestion
        control and no publisher declared; a notification leaves by its key's publisher."""
        return self.epoch is None


@dataclass(frozen=True, slots=True)
class Retire:
    """Undeclare ``key``'s publisher: the registration is gone."""

    key: RegistrationKey


Event = Publish | Retire


@dataclass(frozen=True, slots=True)
class Refusal:
    """Why ``count`` elements cannot be stored now: the registration ``sub_id`` of producer
    ``name`` has ``queued`` of its ``queue_size`` places taken, too few for them.
    ``wait``: the caller may wait for credit (it has time left and the batch can fit)."""

    name: str
    sub_id: str
    queued: int
    queue_size: int
    count: int
    wait: bool

    @property
    def never_fits(self) -> bool:
        return self.count > self.queue_size

    def message(self, first_ns: int) -> str:
        """The refusal as ``FlowControlRefused`` says it (``first_ns``: the first stamp)."""
        held = f"{self.name}: subscriber {self.sub_id} has {self.queued}/{self.queue_size}"
        if self.count == 1:
            return (
                f"{held} notifications queued; element {first_ns} was not stored (drop it, "
                "or put with wait_s to wait)"
            )
        if self.never_fits:
            advice = f"it can never fit: put batches of at most {self.queue_size}"
        else:
            advice = "drop it, or put_many with wait_s to wait"
        return (
            f"{held} notifications queued, no room for a batch of {self.count}; no element "
            f"of the batch (from {first_ns}) was stored ({advice})"
        )
