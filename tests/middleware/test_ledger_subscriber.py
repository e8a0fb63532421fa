"""The subscriber ledger's fast path decides exactly as its full rules do."""

from __future__ import annotations

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from middleware._ledger_subscriber import (
    FORGOTTEN_EPOCHS,
    UNGREETED_EPOCHS,
    AckPolicy,
    Entry,
    SubscriberLedger,
)
from middleware._records import SubscriptionMode

EPOCHS = ["A.1", "A.2", "B.1", "C.7"]
DESCRIPTOR = "flow/3/-1"


class FullRulesOnly(SubscriberLedger[int]):
    """The same ledger with the fast paths switched off: ``receive``'s, the batch one of
    ``receive_many`` and the bulk ``take_many``."""

    def receive(self, epoch: str, seq: int, item: int, *, descriptor: str | None) -> bool:
        return self._receive(epoch, seq, item, descriptor)

    def receive_many(
        self, epoch: str, seq: int, items: list[int], *, descriptor: str | None
    ) -> int:
        return sum(self._receive(epoch, seq + i, x, descriptor) for i, x in enumerate(items))

    def take_many(self, max_count: int) -> list[Entry[int]]:
        entries = []
        while len(entries) < max_count and self._queue:  # the module doc's rule, one by one
            entry = self._queue.popleft()
            track = self._epochs[entry.epoch]
            track.queued -= 1
            track.taken = entry.seq
            track.unacked_takes += 1
            self._takes += 1
            entries.append(entry)
        return entries


# One step: receive (mostly the next seq of a recent epoch, as a real producer sends), a
# batch, a take, or an ack round (idle or not).
_receive = st.tuples(
    st.just("receive"),
    st.one_of(st.just(EPOCHS[0]), st.sampled_from(EPOCHS)),
    # The epoch's next seq plus an offset (0 most often), or any seq (encoded as 100 + seq).
    st.one_of(st.just(0), st.integers(-3, 3), st.integers(99, 112)),
    st.sampled_from([None, DESCRIPTOR, "observe/3/-1"]),
)
_step = st.one_of(
    _receive,
    _receive,
    st.tuples(st.just("batch"), st.sampled_from(EPOCHS), st.integers(1, 4), st.none()),
    st.tuples(st.just("take"), st.none(), st.integers(1, 3), st.none()),
    st.tuples(st.just("take_many"), st.none(), st.integers(1, 5), st.none()),
    st.tuples(st.just("acks"), st.none(), st.integers(0, 2 * 10**9), st.booleans()),
)


def _state(ledger: SubscriberLedger[int]) -> tuple[object, ...]:
    c = ledger.counters
    return (
        len(ledger),
        ledger.missed_total,
        (c.foreign, c.invalid, c.out_of_order, c.duplicates, c.refused),
        list(ledger.epochs().items()),  # the order is the LRU order: it must match too
    )


@pytest.mark.slow  # 600 programs: ~10 s alone, 26 s at load 10
@settings(deadline=None, max_examples=600)
@given(
    mode=st.sampled_from(list(SubscriptionMode)),
    queue_size=st.integers(1, 4),
    every=st.integers(1, 3),
    max_epochs=st.integers(1, 3),
    steps=st.lists(_step, max_size=80),
)
def test_the_fast_path_changes_no_decision(
    mode: SubscriptionMode,
    queue_size: int,
    every: int,
    max_epochs: int,
    steps: list[tuple[str, str | None, int, object]],
) -> None:
    policy = AckPolicy(every=every, reack_ns=10**9)
    fast = SubscriberLedger[int](mode, queue_size, DESCRIPTOR, policy=policy, max_epochs=max_epochs)
    full = FullRulesOnly(mode, queue_size, DESCRIPTOR, policy=policy, max_epochs=max_epochs)
    now = 0
    item = 0
    for kind, epoch, number, extra in steps:
        if kind in ("receive", "batch"):
            assert epoch is not None
            track = full.epochs().get(epoch)
            base = (track.last + 1) if track is not None else 1
            descriptor = extra if kind == "receive" else None
            assert descriptor is None or isinstance(descriptor, str)
            if kind == "receive":
                seq = number - 100 if number >= 99 else base + number
                item += 1
                got = fast.receive(epoch, seq, item, descriptor=descriptor)
                assert got == full.receive(epoch, seq, item, descriptor=descriptor)
            else:
                items = list(range(item + 1, item + 1 + number))
                item += number
                got_n = fast.receive_many(epoch, base, items, descriptor=None)
                assert got_n == full.receive_many(epoch, base, items, descriptor=None)
        elif kind == "take":
            for _ in range(number):
                assert fast.take_many(1) == full.take_many(1)
        elif kind == "take_many":
            assert fast.take_many(number) == full.take_many(number)
        else:
            now += number
            assert fast.acks_due(now, idle=bool(extra)) == full.acks_due(now, idle=bool(extra))
        assert _state(fast) == _state(full)


def test_a_busy_subscriber_repeats_no_ack_between_notifications() -> None:
    # A repeat that moves nothing makes the producer resend whatever is in flight, so an ack
    # is repeated only after reack_ns without any ack, not every reack_ns while idle.
    ms = 1_000_000
    ledger = SubscriberLedger[int](
        SubscriptionMode.FLOW, 2, DESCRIPTOR, policy=AckPolicy(reack_ns=500 * ms)
    )
    repeats = 0
    for seq in range(1, 21):  # one element every 100 ms, taken at once, then idle
        now = seq * 100 * ms
        assert ledger.receive("A.1", seq, seq, descriptor=None)
        assert ledger.take_many(1)
        assert ledger.acks_due(now, idle=False) == [("A.1", seq)]
        repeats += len(ledger.acks_due(now + 50 * ms, idle=True))
    assert repeats == 0
    quiet = 2_000 * ms + 500 * ms  # 500 ms after the last ack
    assert ledger.acks_due(quiet - 1, idle=True) == []
    assert ledger.acks_due(quiet, idle=True) == [("A.1", 20)]
    assert ledger.acks_due(quiet + 1, idle=True) == []


@pytest.mark.parametrize("greeted", [True, False], ids=["greeted", "greeting-lost"])
def test_made_up_epochs_never_push_out_the_live_one(greeted: bool) -> None:
    """A peer sends seq 1 of ever new epochs, each taken as it comes: more than the table
    and the memory of evicted epochs hold. The epoch the producer greeted us with (or, the
    greeting lost, the first one adopted) stays tracked, so its next seq is still taken."""
    ledger = SubscriberLedger[str](SubscriptionMode.FLOW, 2, DESCRIPTOR)
    if greeted:
        ledger.pin("P.1")
    assert ledger.receive("P.1", 1, "real", descriptor=DESCRIPTOR)
    assert ledger.take_many(1)
    for i in range(FORGOTTEN_EPOCHS + 64):
        # The first ones are adopted (kept till the next greeting), the rest wait for it.
        adopted = i < UNGREETED_EPOCHS
        assert ledger.receive(f"F{i}.1", 1, "forged", descriptor=DESCRIPTOR) is adopted
        assert bool(ledger.take_many(1)) is adopted
    assert ledger.track("P.1") is not None
    assert ledger.receive("P.1", 2, "real", descriptor=DESCRIPTOR)


def test_an_observer_keeps_its_epoch_through_a_flood_before_its_greeting() -> None:
    """An observer adopts any epoch at any seq. A made-up epoch came first (so the greeting
    lost or late, it holds the pin), then the producer's, taken; then a flood of made-up
    epochs, more than the memory of evicted ones holds, then the greeting. The producer's
    epoch is still known: a delayed duplicate of what was taken is not taken again, and an
    idle observer repeats its ack (what tells a producer that lost its token it lives)."""
    observe = "observe/2/-1"
    ledger = SubscriberLedger[str](SubscriptionMode.OBSERVE, 2, observe)
    assert ledger.receive("X.1", 1, "forged", descriptor=observe)
    assert ledger.receive("P0.4", 1, "real", descriptor=observe)
    assert [e.item for e in ledger.take_many(2)] == ["forged", "real"]
    for i in range(FORGOTTEN_EPOCHS + 16):
        ledger.receive(f"F{i}.1", 1, "forged", descriptor=observe)
        ledger.take_many(1)
    ledger.pin("P0.4")
    assert not ledger.receive("P0.4", 1, "real", descriptor=observe)  # the duplicate
    assert ("P0.4", 1) in ledger.acks_due(10**12, idle=True)
    assert ledger.receive("P0.4", 2, "next", descriptor=observe)


@pytest.mark.parametrize("mode", [SubscriptionMode.FLOW, SubscriptionMode.OBSERVE])
def test_a_greeting_after_a_flood_keeps_the_evicted_epoch_acked(mode: SubscriptionMode) -> None:
    """The producer's epoch, taken from, was evicted by a flood of made-up epochs before
    its greeting came (the greeting late; the flood's first epoch held the pin). Idle, the
    subscriber still repeats the ack of the registration it holds, from the memory of
    evicted epochs: a producer that lost its token learns from that ack that it lives."""
    descriptor = f"{mode.value}/2/-1"
    ledger = SubscriberLedger[str](mode, 2, descriptor)
    assert ledger.receive("X.1", 1, "forged", descriptor=descriptor)
    assert ledger.receive("P2.1", 1, "real", descriptor=descriptor)
    assert len(ledger.take_many(2)) == 2
    for i in range(UNGREETED_EPOCHS - 2):  # adopted, each taken: P2.1 is evicted
        assert ledger.receive(f"F{i}.1", 1, "forged", descriptor=descriptor)
        ledger.take_many(1)
    assert ledger.track("P2.1") is None
    ledger.pin("P2.1")
    assert ("P2.1", 1) in ledger.acks_due(10**12, idle=True)


def test_a_restarted_producers_epoch_survives_a_flood_before_its_greeting() -> None:
    """The producer restarts: its new epoch's first notification comes before its
    greeting, then a flood of made-up epochs. The new epoch stays tracked (its resend of
    seq 1 is a duplicate, not taken twice; seq 2 is taken), and once the greeting has come
    new epochs are adopted again."""
    ledger = SubscriberLedger[str](SubscriptionMode.FLOW, 2, DESCRIPTOR)
    ledger.pin("P0.1")
    assert ledger.receive("P0.1", 1, "old", descriptor=DESCRIPTOR)
    assert ledger.take_many(1)
    assert ledger.receive("P1.1", 1, "new", descriptor=DESCRIPTOR)
    assert ledger.take_many(1)
    refused = ledger.counters.refused
    for i in range(FORGOTTEN_EPOCHS + 64):
        ledger.receive(f"F{i}.1", 1, "forged", descriptor=DESCRIPTOR)
        ledger.take_many(1)
    assert ledger.counters.refused - refused == FORGOTTEN_EPOCHS + 64 - (UNGREETED_EPOCHS - 1)
    assert not ledger.receive("P1.1", 1, "new", descriptor=DESCRIPTOR)  # the resend
    assert ledger.receive("P1.1", 2, "next", descriptor=DESCRIPTOR)
    assert [e.item for e in ledger.take_many(1)] == ["next"]
    ledger.pin("P1.1")
    assert ledger.receive("G.1", 1, "forged", descriptor=DESCRIPTOR)
