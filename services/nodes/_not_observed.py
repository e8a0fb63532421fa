"""Counting the frames a runner will never see (``not-observed``) while they are lost, not
only when it takes its next frame.

Two sources tell the same monotonic total, each a lower bound of it: the notifications
taken (each carries what was lost before it, ``Notification.missed``) and the
subscription's ``missed_total`` (raised the moment a full observer queue drops its oldest
notification, or a lapse is known). Counted from the notes alone, a handler that runs for
minutes left ``framegate info NAME/detections`` at 0 while its queue dropped every frame;
the subscription's total, read on the node's executor while the handler runs, keeps the
count current. The output counts the larger of the two as each is read, so nothing is
counted twice.

Threads: ``carried`` runs on the runner's loop thread, ``total_is`` on the node's executor
(a timer); the lock guards the two sums and the count given to the output.
"""

from __future__ import annotations

import threading
from collections.abc import Callable

from middleware import Producer

SKIP_REASON = "not-observed"


class _Total:
    """A monotonic total counted on ``output`` as skips of ``reason``: told the total now,
    the output is told what it adds (a total read twice is never counted twice)."""

    def __init__(self, output: Producer, reason: str) -> None:
        self._output = output
        self._reason = reason
        self._counted = 0  # what the output has been told

    def raise_to(self, total: int) -> bool:
        """Count what ``total`` adds; whether it added anything."""
        if total <= self._counted:
            return False
        self._output.count_skip(self._reason, total - self._counted)
        self._counted = total
        return True


class NotObserved:
    """Frames lost before the runner saw them, counted on ``output`` as ``not-observed``."""

    def __init__(self, output: Producer) -> None:
        self._lock = threading.Lock()
        self._carried = 0  # the sum of the ``missed`` of the notifications taken
        self._total = _Total(output, SKIP_REASON)

    def carried(self, missed: int) -> None:
        """A notification taken carried ``missed`` frames lost before it."""
        with self._lock:
            self._carried += missed
            self._total.raise_to(self._carried)

    def total_is(self, missed_total: int) -> None:
        """The subscription's ``missed_total`` now (it includes what notes carry later)."""
        with self._lock:
            self._total.raise_to(missed_total)


BAD_NOTIFICATION = "bad-notification"


class BadNotifications:
    """Messages on a service's notification keys that were no notification of its inputs
    (garbage, larger than any the subscription can be sent, or pushed out of its inbox by a
    flood of them), counted on ``output`` as ``bad-notification`` with one warning: the
    subscriptions counted them, but nothing showed them, so a peer flooding a key left
    ``framegate info`` and the log silent while the service slowed (the vision runner's
    results, the mediator's decisions).

    Threads: ``total_is`` runs on the node's executor (a timer) only.
    """

    def __init__(self, output: Producer, warn: Callable[[str, str], None]) -> None:
        self._name = output.name
        self._warn = warn
        self._warned = False
        self._total = _Total(output, BAD_NOTIFICATION)

    def total_is(self, total: int) -> None:
        """The subscriptions' garbage and dropped messages, summed, now."""
        if self._total.raise_to(total) and not self._warned:
            self._warned = True
            self._warn(
                BAD_NOTIFICATION,
                f"{total} messages on this service's notification keys were no notification "
                f"of its inputs (garbage, oversize, or a flood); counted as {BAD_NOTIFICATION} "
                f"in 'framegate info {self._name}', not logged again",
            )
