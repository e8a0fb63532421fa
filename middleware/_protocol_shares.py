"""Fair shares of one producer's flow-control resources, kept as running sums per holder
(the ``<node>~<host>`` a subscription token names): the part of ``ProducerProtocol`` that
decides whether a token may register, and whose payloads above the inline limit are pushed.
The rules and why they are chosen are in ``_protocol_producer``'s module doc (and
docs/limits.md for users). Pure: no Zenoh, no threads, no clock.
"""

from __future__ import annotations

from dataclasses import dataclass

from ._ledger_producer import RegistrationKey
from ._records import SubscriptionMode

MAX_FLOW_REGISTRATIONS = 256
MAX_OBSERVE_REGISTRATIONS = 256
# Sum of the queue sizes of all flow registrations of one producer.
QUEUE_BUDGET = 1 << 16
# The largest flow queue one subscriber can get: a holder's fair share of an idle producer.
FLOW_QUEUE_MAX = QUEUE_BUDGET // 2
# Registrations that get payloads above the producer's inline limit pushed.
LARGE_PUSH_PER_HOLDER = 4
LARGE_PUSH_TOTAL = 16


@dataclass(slots=True)
class _Share:
    """What one holder (or all of them, the totals) holds: running sums, so that judging a
    token costs O(1) whatever the table holds."""

    flow: int = 0
    observe: int = 0
    queue: int = 0  # queue sizes of its flow registrations, summed
    large_push: int = 0  # registrations that get payloads above the inline limit pushed

    def slots(self, mode: SubscriptionMode) -> int:
        return self.flow if mode is SubscriptionMode.FLOW else self.observe

    def add(self, key: RegistrationKey, large_push: bool, sign: int) -> None:
        if key.mode is SubscriptionMode.FLOW:
            self.flow += sign
            self.queue += sign * key.queue_size
        else:
            self.observe += sign
        self.large_push += sign * large_push

    def empty(self) -> bool:
        return not (self.flow or self.observe)


def fair_share(limit: int, others: int) -> int:
    """What one holder may hold of ``limit`` while the others hold ``others``: half of what
    they leave free, rounded up (so a lone holder of a pool of 1 still gets it)."""
    return (max(0, limit - others) + 1) // 2


def holder_of(node: str | None, host: str | None) -> str:
    """A token's holder as the shares count it: its ``<node>~<host>`` chunk."""
    return f"{node or ''}~{host or ''}"


class Shares:
    """What each holder holds of one producer, and whether a new token fits its share."""

    def __init__(self, name: str, budget: int, max_flow: int, max_observe: int) -> None:
        self.name = name
        self.budget = budget
        self._max = {SubscriptionMode.FLOW: max_flow, SubscriptionMode.OBSERVE: max_observe}
        self._by_holder: dict[str, _Share] = {}
        self._total = _Share()

    def holders(self) -> set[str]:
        return set(self._by_holder)

    def large_push_free(self, holder: str) -> bool:
        """Whether ``holder`` may have one more registration's large payloads pushed."""
        mine = self._by_holder.get(holder)
        held = mine.large_push if mine is not None else 0
        return held < LARGE_PUSH_PER_HOLDER and self._total.large_push < LARGE_PUSH_TOTAL

    def add(self, key: RegistrationKey, holder: str, large_push: bool, sign: int) -> None:
        """Count a registration (``sign`` 1) or forget one (-1)."""
        share = self._by_holder.setdefault(holder, _Share())
        share.add(key, large_push, sign)
        if share.empty():
            del self._by_holder[holder]
        self._total.add(key, large_push, sign)

    def refusal(self, key: RegistrationKey, holder: str) -> str | None:
        """Why ``holder`` may not register ``key`` (None: it may), naming the limit, what it
        holds and the largest holder."""
        mode, total = key.mode, self._total
        mine = self._by_holder.get(holder, _Share())
        used = total.slots(mode)
        if used >= self._max[mode]:
            return (
                f"{self.name} holds {used} {mode.value} subscriptions, its limit; the largest "
                f"holder is {self._largest(mode)}; close unused subscriptions"
            )
        slots = fair_share(self._max[mode], used - mine.slots(mode))
        if mine.slots(mode) + 1 > slots:
            return (
                f"{holder} holds {mine.slots(mode)} {mode.value} subscriptions of {self.name}, "
                f"its fair share (half of the {self._max[mode] - used + mine.slots(mode)} "
                f"others leave free); close unused subscriptions"
            )
        if mode is SubscriptionMode.FLOW:
            if total.queue + key.queue_size > self.budget:
                return (
                    f"queue size {key.queue_size} exceeds what {self.name} can still hold "
                    f"for flow control ({self.budget - total.queue} of {self.budget}); the "
                    f"largest holder is {self._largest(mode)}; subscribe with a smaller queue"
                )
            share = fair_share(self.budget, total.queue - mine.queue)
            if mine.queue + key.queue_size > share:
                return (
                    f"queue size {key.queue_size} exceeds the fair share of {holder} in "
                    f"{self.name}'s flow-control budget: at most {share} (half of the "
                    f"{self.budget - total.queue + mine.queue} of {self.budget} others "
                    f"leave free), {mine.queue} held already; the largest holder is "
                    f"{self._largest(mode)}; subscribe with a smaller queue"
                )
        return None

    def _largest(self, mode: SubscriptionMode) -> str:
        """The holder with the most of ``mode`` (queue for flow, slots for observe), for a
        refusal's message. Only on refusals: O(holders), and holders <= registrations."""
        flow = mode is SubscriptionMode.FLOW

        def size(share: _Share) -> int:
            return share.queue if flow else share.observe

        if not self._by_holder:
            return "nobody"
        holder, share = max(self._by_holder.items(), key=lambda item: size(item[1]))
        what = f"queue {share.queue} in {share.flow}" if flow else f"{share.observe}"
        return f"{holder} ({what} subscriptions)"
