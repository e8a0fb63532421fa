"""The flow-control protocol as a whole: both ledgers driven by hypothesis's stateful testing.

One producer (restartable), several subscribers (flow and observe, joining and leaving) and
an adversarial network that loses, duplicates, reorders and delays notifications and acks.
A rogue injects notifications (foreign epochs, past seqs, far-future seqs of the current
epoch, other registrations' descriptors), acks (foreign epochs, past seqs, colliding ids)
and observe tokens with colliding or fresh ids. Tokens travel reliably (Zenoh liveliness).
The invariants are checked after every step; ``heal`` lets the network deliver again and
checks liveness and no loss.

Outside the model, on purpose (see the README's trust profiles): a rogue that forges an
in-window notification or ack of the current epoch, or a token identical to another's.

CI runs a few thousand steps; ``python -m pytest tests/middleware --hypothesis-profile long``
runs over 100,000. A failing example is kept in an example database inside the repository
(``tests/middleware/protocol_examples/``, not the ignored ``.hypothesis/``) and replayed first
on every later run: commit what a failure leaves there beside its fix.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

from hypothesis import event, settings
from hypothesis import strategies as st
from hypothesis.database import DirectoryBasedExampleDatabase
from hypothesis.stateful import RuleBasedStateMachine, initialize, invariant, precondition, rule

from middleware._ledger_producer import (
    MAX_REGISTRATIONS,
    RETRANSMIT_NS,
    ProducerLedger,
    RegistrationKey,
)
from middleware._ledger_subscriber import ACK_DELAY_NS, MAX_EPOCHS, AckPolicy, SubscriberLedger
from middleware._records import SubscriptionMode

FLOW, OBSERVE = SubscriptionMode.FLOW, SubscriptionMode.OBSERVE
MS = 1_000_000
STEPS = [0]  # rule steps run, across programs (tests/middleware/conftest.py prints them)
EXAMPLES = [0]

# What a notification names: (producer instance, element timestamp); forged ones use -1.
Item = tuple[int, int]


@dataclass(frozen=True)
class Note:
    sub_id: str
    epoch: str
    seq: int
    acked: int | None
    descriptor: str | None
    # The elements of seqs seq, seq + 1, ...: one, or a batch (``put_many``).
    items: tuple[Item, ...]


@dataclass(frozen=True)
class Ack:
    sub_id: str
    epoch: str
    seq: int


@dataclass
class Sub:
    key: RegistrationKey
    ledger: SubscriberLedger[Item]
    alive: bool = True
    taken: list[tuple[str, int, Item]] = field(default_factory=list)


class ProtocolModel(RuleBasedStateMachine):
    def __init__(self) -> None:
        super().__init__()
        EXAMPLES[0] += 1
        self.now = 0
        self.instance = 0
        self.producer: ProducerLedger[int] = ProducerLedger("P0")
        self.next_t = 1
        self.subs: list[Sub] = []
        self.rogue_tokens: list[RegistrationKey] = []
        self.net: list[Note | Ack] = []
        # (epoch, seq) -> element timestamp, for every notification the producer made.
        self.sent: dict[tuple[str, int], int] = {}
        self.refused = 0
        # The epochs the producer gave each subscriber's key (a registration is its key).
        self.epochs_of: dict[RegistrationKey, set[str]] = {}

    # -- helpers ---------------------------------------------------------------------------
    def _emit(self, sends: list) -> None:  # type: ignore[type-arg]
        for s in sends:
            items = []
            for i, header in enumerate(s.headers):
                self.sent[(s.epoch, s.seq + i)] = header
                items.append((self.instance, header))
            note = Note(s.key.sub_id, s.epoch, s.seq, s.acked, s.key.descriptor, tuple(items))
            self.net.append(note)

    def _deliver(self, msg: Note | Ack) -> None:
        if isinstance(msg, Ack):
            self.producer.ack(msg.sub_id, msg.epoch, msg.seq, self.now)
            return
        for sub in self.subs:
            if sub.alive and sub.key.sub_id == msg.sub_id:
                items = list(msg.items)
                sub.ledger.receive_many(msg.epoch, msg.seq, items, descriptor=msg.descriptor)

    def _take_all(self, sub: Sub) -> None:
        while (entry := sub.ledger.take()) is not None:
            sub.taken.append((entry.epoch, entry.seq, entry.item))
            if sub.key.mode is FLOW:
                assert entry.missed == 0, "a flow-controlled subscription reported missed"
        self._acks(sub, idle=True)

    def _acks(self, sub: Sub, *, idle: bool) -> None:
        for epoch, seq in sub.ledger.acks_due(self.now, idle=idle):
            self.net.append(Ack(sub.key.sub_id, epoch, seq))

    def _register(self, key: RegistrationKey) -> None:
        reg = self.producer.token_put(key, self.now)
        if reg is not None:
            self.epochs_of.setdefault(key, set()).add(reg.epoch)

    def _live(self) -> list[Sub]:
        return [s for s in self.subs if s.alive]

    def _registered_keys(self) -> list[RegistrationKey]:
        return [s.key for s in self._live()] + self.rogue_tokens

    # -- subscribers -----------------------------------------------------------------------
    @initialize(
        sizes=st.lists(st.tuples(st.integers(1, 8), st.integers(1, 4)), min_size=1, max_size=3),
        observer=st.booleans(),
    )
    def start(self, sizes: list[tuple[int, int]], observer: bool) -> None:
        for size, every in sizes:
            self.subscribe(FLOW, size, every)
        if observer:
            self.subscribe(OBSERVE, 2)

    @precondition(lambda self: len(self._live()) < 4)
    @rule(
        mode=st.sampled_from([FLOW, FLOW, OBSERVE]),
        size=st.integers(1, 8),
        every=st.integers(1, 8),
        delay_ns=st.sampled_from([0, ACK_DELAY_NS]),
    )
    def subscribe(
        self, mode: SubscriptionMode, size: int, every: int = 1, delay_ns: int = 0
    ) -> None:
        """``every``: the ack policy coalesces that many takes into one ack (any value, even
        beyond the queue: liveness must not depend on it); ``delay_ns``: an emptied queue's
        ack waits that long (the flusher sends it, see ``flush``)."""
        STEPS[0] += 1
        key = RegistrationKey(f"s{len(self.subs)}", mode, size, -1)
        policy = AckPolicy(every=every, delay_ns=delay_ns)
        if every > 1:
            event("a subscriber that coalesces acks")
        if delay_ns:
            event("a subscriber that delays acks")
        ledger: SubscriberLedger[Item] = SubscriberLedger(mode, size, key.descriptor, policy=policy)
        self.subs.append(Sub(key, ledger))
        self._register(key)

    @precondition(lambda self: bool(self._live()))
    @rule(data=st.data())
    def unsubscribe(self, data: st.DataObject) -> None:
        STEPS[0] += 1
        sub = data.draw(st.sampled_from(self._live()))
        sub.alive = False
        self.producer.token_delete(sub.key)

    @precondition(lambda self: bool(self._live()))
    @rule(data=st.data(), count=st.integers(1, 3))
    def take(self, data: st.DataObject, count: int) -> None:
        STEPS[0] += 1
        sub = data.draw(st.sampled_from(self._live()))
        for _ in range(count):
            entry = sub.ledger.take()
            if entry is None:
                break
            sub.taken.append((entry.epoch, entry.seq, entry.item))
            if sub.key.mode is FLOW:
                assert entry.missed == 0, "a flow-controlled subscription reported missed"
        self._acks(sub, idle=False)

    @precondition(lambda self: bool(self._live()))
    @rule(data=st.data())
    def flush(self, data: st.DataObject) -> None:
        """The subscription's flusher thread: at the ledger's flush time, the delayed ack."""
        STEPS[0] += 1
        self._flush(data.draw(st.sampled_from(self._live())))

    def _flush(self, sub: Sub) -> None:
        due = sub.ledger.flush_at_ns()
        if due is not None:
            self.now = max(self.now, due)
            event("flush: a delayed ack sent by the flusher")
            self._acks(sub, idle=False)

    @precondition(lambda self: bool(self._live()))
    @rule(data=st.data())
    def idle(self, data: st.DataObject) -> None:
        STEPS[0] += 1
        self._acks(data.draw(st.sampled_from(self._live())), idle=True)

    # -- producer --------------------------------------------------------------------------
    @rule(
        count=st.integers(1, 3),
        batch=st.sampled_from([1, 1, 2, 3, 5]),
        fail=st.booleans(),
        at_once=st.booleans(),
    )
    def put(self, count: int, batch: int, fail: bool, at_once: bool) -> None:
        """Store ``count`` times ``batch`` elements (``put_many`` when batch > 1) unless
        refused; with ``fail`` a first send does not leave; with ``at_once`` the network
        delivers the notifications at once (the common case)."""
        STEPS[0] += 1
        before = len(self.net)
        for _ in range(count):
            self._emit(self.producer.tick(self.now))
            if self.producer.full(batch) is not None:
                self.refused += 1
                return
            headers = tuple(range(self.next_t, self.next_t + batch))
            sends = self.producer.put_many(headers, self.now)
            self.next_t += batch
            if batch > 1:
                event("a batch put")
            if fail and sends:
                for i, header in enumerate(sends[0].headers):
                    self.sent[(sends[0].epoch, sends[0].seq + i)] = header
                self.producer.send_failed(sends[0].key, sends[0].epoch)
                sends = sends[1:]
            self._emit(sends)
        if at_once:
            for msg in self.net[before:]:
                self._deliver(msg)
            del self.net[before:]

    @rule(dt=st.sampled_from([1 * MS, 100 * MS, RETRANSMIT_NS + 1]))
    def time_passes(self, dt: int) -> None:
        STEPS[0] += 1
        self.now += dt
        self._emit(self.producer.tick(self.now))

    @rule()
    def restart_producer(self) -> None:
        STEPS[0] += 1
        self.instance += 1
        self.producer = ProducerLedger(f"P{self.instance}")
        for key in self._registered_keys():  # liveliness history re-registers every token
            self._register(key)

    # -- the network -----------------------------------------------------------------------
    @precondition(lambda self: bool(self.net))
    @rule(i=st.integers(0, 1 << 16))
    def deliver(self, i: int) -> None:
        """Deliver any message in flight: reordering and delay."""
        STEPS[0] += 1
        self._deliver(self.net.pop(i % len(self.net)))

    @precondition(lambda self: bool(self.net))
    @rule(i=st.integers(0, 1 << 16))
    def lose(self, i: int) -> None:
        STEPS[0] += 1
        self.net.pop(i % len(self.net))

    @precondition(lambda self: bool(self.net) and len(self.net) < 64)
    @rule(i=st.integers(0, 1 << 16))
    def duplicate(self, i: int) -> None:
        STEPS[0] += 1
        self.net.append(self.net[i % len(self.net)])

    # -- the rogue -------------------------------------------------------------------------
    @precondition(lambda self: bool(self._live()))
    @rule(
        data=st.data(),
        foreign=st.booleans(),
        seq=st.integers(1, 2_000),
        direct=st.booleans(),
        descriptor=st.sampled_from(["own", "none", "other"]),
    )
    def rogue_notification(
        self, data: st.DataObject, foreign: bool, seq: int, direct: bool, descriptor: str
    ) -> None:
        STEPS[0] += 1
        sub = data.draw(st.sampled_from(self._live()))
        desc = {"own": sub.key.descriptor, "none": None, "other": "observe/9/-1"}[descriptor]
        reg = self.producer.get(sub.key)
        if foreign or reg is None:
            epoch = data.draw(st.sampled_from(["X", "Y", "P0.1", f"P{self.instance}.999"]))
            if epoch.startswith(f"P{self.instance}."):
                epoch = "X"  # a guess of a registration epoch yet to come is out of the model
            small = data.draw(st.integers(1, 3))  # seq 1 starts an epoch; others probe
            note = Note(sub.key.sub_id, epoch, small, None, desc, ((-1, 0),))
            if direct:
                self._deliver(note)
            else:
                self.net.append(note)
            return
        track = sub.ledger.epochs().get(reg.epoch)
        last = track.last if track is not None else 0
        if seq <= last:  # a replayed past seq, through the network like any message
            self.net.append(Note(sub.key.sub_id, reg.epoch, seq, None, desc, ((-1, 0),)))
        else:  # a far-future seq, beyond anything in flight: straight to the subscriber
            future = reg.sent + sub.key.queue_size + seq
            sub.ledger.receive(reg.epoch, future, (-1, 0), descriptor=desc)

    @precondition(lambda self: bool(self.subs))
    @rule(data=st.data(), kind=st.sampled_from(["foreign", "past", "colliding"]))
    def rogue_ack(self, data: st.DataObject, kind: str) -> None:
        STEPS[0] += 1
        sub = data.draw(st.sampled_from(self.subs))
        reg = self.producer.get(sub.key)
        if kind == "foreign" or reg is None:
            self.net.append(Ack(sub.key.sub_id, "X", data.draw(st.integers(0, 1_000))))
        elif kind == "past":
            self.net.append(Ack(sub.key.sub_id, reg.epoch, data.draw(st.integers(0, reg.acked))))
        else:  # another id claims this registration's epoch
            self.net.append(Ack("rogue", reg.epoch, data.draw(st.integers(0, 1_000))))

    @rule(data=st.data(), size=st.integers(1, 4), colliding=st.booleans())
    def rogue_token(self, data: st.DataObject, size: int, colliding: bool) -> None:
        """An observe token (all a read-only certificate may declare), often with a real id."""
        STEPS[0] += 1
        sub_id = "r"
        if colliding and self.subs:
            sub_id = data.draw(st.sampled_from(self.subs)).key.sub_id
        key = RegistrationKey(sub_id, OBSERVE, size, data.draw(st.sampled_from([-1, 0])))
        if key in self._registered_keys():
            return  # an identical token is the same registration: out of the model
        self.rogue_tokens.append(key)
        self._register(key)

    @precondition(lambda self: bool(self.rogue_tokens))
    @rule(data=st.data())
    def rogue_token_withdrawn(self, data: st.DataObject) -> None:
        STEPS[0] += 1
        key = data.draw(st.sampled_from(self.rogue_tokens))
        self.rogue_tokens.remove(key)
        self.producer.token_delete(key)

    # -- liveness --------------------------------------------------------------------------
    @rule()
    def heal(self) -> None:
        """The network delivers again and every subscriber takes everything: within a few
        resend periods the producer is free and no flow subscriber has lost anything."""
        STEPS[0] += 1
        for _ in range(3):  # about a second and a half: the liveness bound
            while self.net:
                self._deliver(self.net.pop(0))
            for sub in self._live():
                self._take_all(sub)
                self._flush(sub)
            while self.net:
                self._deliver(self.net.pop(0))
            regs = self.producer.registrations()
            if all(r.acked == r.sent for r in regs if r.flow) and not self.net:
                break
            self.now += RETRANSMIT_NS + 1
            self._emit(self.producer.tick(self.now))
        else:
            raise AssertionError("the producer stayed held after the network healed")
        assert self.producer.full() is None
        for sub in self._live():
            reg = self.producer.get(sub.key)
            assert reg is not None
            if sub.key.mode is not FLOW:
                continue
            got = [(e, s) for e, s, item in sub.taken if e == reg.epoch]
            event(f"heal: a flow subscriber checked, {min(len(got), 3)}+ notifications")
            if any(item[0] < 0 for _, _, item in sub.taken):
                event("heal: a flow subscriber that took forged notifications")
            if any(e != reg.epoch for e, _, _ in sub.taken):
                event("heal: a flow subscriber that took several epochs")
            wanted = [(reg.epoch, s) for s in range(1, reg.sent + 1)]
            assert got == wanted, f"{sub.key.sub_id} lost or reordered notifications"
            for epoch, seq, item in sub.taken:
                if epoch == reg.epoch:
                    assert item == (self.instance, self.sent[(epoch, seq)])

    # -- invariants ------------------------------------------------------------------------
    @invariant()
    def queues_and_tables_are_bounded(self) -> None:
        for sub in self.subs:
            assert len(sub.ledger) <= sub.key.queue_size
            assert len(sub.ledger.epochs()) <= max(MAX_EPOCHS, sub.key.queue_size + 1)
        regs = self.producer.registrations()
        assert len(regs) <= MAX_REGISTRATIONS
        for reg in regs:
            assert 0 <= reg.acked <= reg.sent
            if reg.flow:
                assert reg.queued <= reg.key.queue_size
                assert len(reg.outstanding) == reg.queued
            else:
                assert not reg.outstanding

    @invariant()
    def every_live_subscription_stays_registered_as_itself(self) -> None:
        for sub in self._live():
            reg = self.producer.get(sub.key)
            assert reg is not None, f"{sub.key} was removed by a token that is not its own"
            assert reg.key == sub.key

    @invariant()
    def the_producer_never_counts_fewer_than_the_subscriber_holds(self) -> None:
        for sub in self._live():
            reg = self.producer.get(sub.key)
            if reg is None or not reg.flow:
                continue
            held = sum(1 for _ in _entries_of(sub, reg.epoch))
            assert held <= reg.sent - reg.acked

    @invariant()
    def flow_subscribers_take_their_own_notifications_in_order_without_gaps(self) -> None:
        for sub in self.subs:
            if sub.key.mode is not FLOW:
                continue
            by_epoch: dict[str, list[int]] = {}
            for epoch, seq, item in sub.taken:
                if item[0] < 0:
                    continue  # a forgery the subscriber could not tell from the real thing
                assert epoch in self.epochs_of.get(sub.key, set()), "another registration's"
                assert item[1] == self.sent[(epoch, seq)]
                by_epoch.setdefault(epoch, []).append(seq)
            for seqs in by_epoch.values():
                assert seqs == list(range(1, len(seqs) + 1)), f"gap or reorder: {seqs}"

    @invariant()
    def nothing_is_taken_twice(self) -> None:
        for sub in self.subs:
            seen = [(e, s) for e, s, item in sub.taken if item[0] >= 0]
            assert len(seen) == len(set(seen))


def _entries_of(sub: Sub, epoch: str) -> list[int]:
    return [e.seq for e in sub.ledger._queue if e.epoch == epoch]


_EXAMPLES = DirectoryBasedExampleDatabase(str(Path(__file__).with_name("protocol_examples")))
ProtocolModel.TestCase.settings = (
    settings(max_examples=200, stateful_step_count=60, deadline=None, database=_EXAMPLES)
    if settings.get_current_profile_name() == "default"
    else settings(database=_EXAMPLES)
)
TestProtocol = ProtocolModel.TestCase
