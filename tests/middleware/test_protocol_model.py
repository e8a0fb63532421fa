"""The flow-control protocol as a whole: the real sans-IO protocol objects of both sides
(``ProducerProtocol``, ``SubscriberProtocol``) driven by hypothesis's stateful testing, on
wire bytes, with the node executor's deadlines (``tick``, the delayed-ack flush) as rules.

One producer (restartable), several subscribers (flow and observe, joining and leaving) and
an adversarial network that loses, duplicates, reorders and delays notifications and acks.
A rogue injects notifications (foreign epochs, past seqs, far-future seqs of the current
epoch, other registrations' descriptors), acks (foreign epochs, past seqs, colliding ids)
and observe tokens with colliding or fresh ids; it floods the ack key (garbage of any size,
and a live subscriber's own last ack repeated hundreds of times) and churns tokens (bursts
of flow and observe tokens declared and withdrawn, from one holder or many, greedy queues
included). A live subscriber's token may lapse and come back (a link that dropped): what
was stored meanwhile must reach ``missed``. Tokens travel reliably (Zenoh liveliness).
The invariants are checked after every step; ``heal`` lets the network deliver again and
checks liveness and no loss.

Outside the model, on purpose (see docs/protocol.md, *Trust*): a rogue that forges an
in-window notification or ack of the current epoch, or a token identical to another's.

CI runs a few thousand steps; ``python -m pytest tests/middleware --hypothesis-profile long``
runs over 100,000. A failing example is kept in an example database inside the repository
(``tests/middleware/protocol_examples/``, not the ignored ``.hypothesis/``) and replayed first
on every later run: commit what a failure leaves there beside its fix.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import pytest
from hypothesis import event, settings
from hypothesis import strategies as st
from hypothesis.database import DirectoryBasedExampleDatabase
from hypothesis.stateful import RuleBasedStateMachine, initialize, invariant, precondition, rule

from middleware._ledger_producer import REPEAT_RESEND_NS, RETRANSMIT_NS, RegistrationKey
from middleware._ledger_subscriber import (
    ACK_DELAY_NS,
    DEEP_ACK_DELAY_NS,
    FORGOTTEN_EPOCHS,
    MAX_EPOCHS,
    REACK_NS,
    AckPolicy,
    Entry,
)
from middleware._protocol_events import Publish
from middleware._protocol_producer import (
    FLOW_QUEUE_MAX,
    MAX_FLOW_REGISTRATIONS,
    MAX_OBSERVE_REGISTRATIONS,
    QUEUE_BUDGET,
    RESEND_BURST,
    RESEND_PACE_NS,
    RESYNC_NS,
    ProducerProtocol,
)
from middleware._protocol_subscriber import Item, SubscriberProtocol
from middleware._records import DataObject, SubscriptionMode
from middleware._wire import (
    BatchHeader,
    Control,
    Header,
    Keys,
    decode_notification_header,
    encode_ack,
    encode_notification_header,
)

FLOW, OBSERVE = SubscriptionMode.FLOW, SubscriptionMode.OBSERVE
MS = 1_000_000
STEPS = [0]  # rule steps run, across programs (tests/middleware/conftest.py prints them)
EXAMPLES = [0]
KEYS = Keys("framegate")
SERVICE, BUFFER = "svc", "buf"
# Forged notifications carry this metadata; real ones the producer instance's number.
FORGED = b"-1"


@dataclass(frozen=True)
class Note:
    """A message on a subscription's notification key, as the wire carries it."""

    sub_id: str
    attachment: bytes
    payload: bytes


@dataclass(frozen=True)
class Ack:
    keyexpr: str
    payload: bytes


@dataclass
class Sub:
    key: RegistrationKey
    protocol: SubscriberProtocol
    alive: bool = True
    # (epoch, seq, (timestamp_ns, metadata, pushed payload)) of every notification taken.
    taken: list[tuple[str, int, tuple[int, bytes | None, object]]] = field(default_factory=list)
    # Elements reported missed, per producer instance (the epoch's prefix).
    missed: dict[str, int] = field(default_factory=dict)
    # Per producer instance, the elements stored before the first registration of this
    # subscriber it heard of (a greeting or a notification: what came before, it cannot
    # be told of), and whether its token lapsed since.
    first_base: dict[str, int] = field(default_factory=dict)
    lapsed: bool = False


def _token(key: RegistrationKey, holder: str = "n~h") -> str:
    return KEYS.subscription_token(
        SERVICE, BUFFER, key.sub_id, key.mode, key.queue_size, key.push_max_bytes, holder
    )


class ProtocolModel(RuleBasedStateMachine):
    def __init__(self) -> None:
        super().__init__()
        EXAMPLES[0] += 1
        self.now = 0
        self.instance = 0
        self.producer = self._new_producer()
        self.next_t = 1
        # Timestamps the producers before this instance used: element number = t - t0.
        self.t0 = 0
        self.subs: list[Sub] = []
        self.rogue_tokens: list[RegistrationKey] = []
        self.net: list[Note | Ack] = []
        # (epoch, seq) -> element timestamp, for every notification the producer made.
        self.sent: dict[tuple[str, int], int] = {}
        self.refused = 0
        # The epochs the producer gave each subscriber's key (a registration is its key).
        self.epochs_of: dict[RegistrationKey, set[str]] = {}
        self.made_up = 0  # epochs a rogue made up so far (each flood's are new)

    def _new_producer(self) -> ProducerProtocol:
        # Payloads up to 4 bytes are pushed with their notification; larger ones are not.
        return ProducerProtocol(KEYS, SERVICE, BUFFER, f"P{self.instance}", inline_max_bytes=4)

    # -- helpers ---------------------------------------------------------------------------
    def _emit(self, fail_first: bool = False) -> None:
        """Carry out the producer's events: notifications into the network (the first one
        failing to leave with ``fail_first``), retired publishers dropped."""
        for ev in self.producer.events():
            if not isinstance(ev, Publish):
                continue
            sub_id = ev.keyexpr.rsplit("/", 1)[-1]
            head = decode_notification_header(ev.attachment)
            if isinstance(head, Header | BatchHeader):
                stamps = (head.timestamp_ns,) if isinstance(head, Header) else head.timestamps_ns
                for i, t in enumerate(stamps):
                    self.sent[(head.epoch, head.seq + i)] = t
                if fail_first:
                    fail_first = False
                    assert ev.epoch is not None
                    self.producer.send_failed(ev.key, ev.epoch)
                    continue
            self.net.append(Note(sub_id, ev.attachment, ev.payload))

    def _deliver(self, msg: Note | Ack) -> None:
        if isinstance(msg, Ack):
            self.producer.ack(msg.keyexpr, msg.payload, self.now)
            return
        for sub in self.subs:
            if sub.alive and sub.key.sub_id == msg.sub_id:
                sub.protocol.receive(msg.attachment, msg.payload)
                _first_contact(sub, msg.attachment)

    def _take_all(self, sub: Sub) -> None:
        self._record(sub, sub.protocol.take_many(1 << 20))
        self._acks(sub, idle=True)

    def _record(self, sub: Sub, entries: list[Entry[Item]]) -> None:
        for entry in entries:
            sub.taken.append((entry.epoch, entry.seq, entry.item))
            if entry.missed:
                instance = entry.epoch.rpartition(".")[0]
                sub.missed[instance] = sub.missed.get(instance, 0) + entry.missed
                if sub.key.mode is FLOW:
                    assert sub.lapsed, "a flow subscription reported missed without a lapse"

    def _acks(self, sub: Sub, *, idle: bool) -> None:
        keyexpr = KEYS.ack(SERVICE, BUFFER, sub.key.sub_id)
        for ack in sub.protocol.acks(self.now, idle=idle):
            self.net.append(Ack(keyexpr, ack))

    def _register(self, key: RegistrationKey, holder: str = "n~h") -> None:
        self.producer.token(_token(key, holder), True, self.now)
        reg = self.producer.get(key)
        if reg is not None:
            self.epochs_of.setdefault(key, set()).add(reg.epoch)
        self._emit()

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
        every=st.integers(0, 8),
        delay_ns=st.sampled_from([0, ACK_DELAY_NS, DEEP_ACK_DELAY_NS]),
        push=st.sampled_from([-1, 0]),
    )
    def subscribe(
        self, mode: SubscriptionMode, size: int, every: int = 1, delay_ns: int = 0, push: int = -1
    ) -> None:
        """``every``: the ack policy coalesces that many takes into one ack (any value, even
        beyond the queue: liveness must not depend on it), 0 for what subscriptions use
        (``AckPolicy.for_queue``); ``delay_ns``: an emptied queue's ack waits that long (the
        node's executor sends it, see ``flush``); ``push``: -1 for the producer's default."""
        STEPS[0] += 1
        key = RegistrationKey(f"s{len(self.subs)}", mode, size, push)
        policy = None if every == 0 else AckPolicy(every=every, delay_ns=delay_ns)
        if every > 1:
            event("a subscriber that coalesces acks")
        protocol = SubscriberProtocol(mode, size, push, policy=policy)
        if protocol.ledger.policy.delay_ns:
            event("a subscriber that delays acks")
        self.subs.append(Sub(key, protocol))
        self._register(key)

    @precondition(lambda self: bool(self._live()))
    @rule(data=st.data())
    def unsubscribe(self, data: st.DataObject) -> None:
        STEPS[0] += 1
        sub = data.draw(st.sampled_from(self._live()))
        sub.alive = False
        self.producer.token(_token(sub.key), False, self.now)
        self._emit()

    @precondition(lambda self: bool(self._live()))
    @rule(data=st.data(), count=st.integers(1, 3))
    def take(self, data: st.DataObject, count: int) -> None:
        STEPS[0] += 1
        sub = data.draw(st.sampled_from(self._live()))
        self._record(sub, sub.protocol.take_many(count))
        self._acks(sub, idle=False)

    @precondition(lambda self: bool(self._live()))
    @rule(data=st.data())
    def flush(self, data: st.DataObject) -> None:
        """The node's executor: at the subscription's deadline, the delayed ack."""
        STEPS[0] += 1
        self._flush(data.draw(st.sampled_from(self._live())))

    def _flush(self, sub: Sub) -> None:
        due = sub.protocol.next_deadline_ns()
        if due is not None:
            self.now = max(self.now, due)
            event("flush: a delayed ack sent by the node's executor")
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
        size=st.sampled_from([0, 3, 9]),
    )
    def put(self, count: int, batch: int, fail: bool, at_once: bool, size: int) -> None:
        """Store ``count`` times ``batch`` elements (``put_many`` when batch > 1) of
        ``size``-byte payloads (pushed up to 4 bytes) unless refused; with ``fail`` a first
        send does not leave; with ``at_once`` the network delivers at once (the common case)."""
        STEPS[0] += 1
        before = len(self.net)
        meta = str(self.instance).encode()
        for _ in range(count):
            self.producer.tick(self.now)
            self._emit()
            if self.producer.admit(batch, may_wait=False) is not None:
                self.refused += 1
                return
            elements = tuple(
                DataObject(t, bytes(size), meta) for t in range(self.next_t, self.next_t + batch)
            )
            self.producer.put_many(elements, self.now)
            self.next_t += batch
            if batch > 1:
                event("a batch put")
            self._emit(fail_first=fail)
        if at_once:
            for msg in self.net[before:]:
                self._deliver(msg)
            del self.net[before:]

    @rule(dt=st.sampled_from([1 * MS, RESEND_PACE_NS, 100 * MS, RETRANSMIT_NS + 1]))
    def time_passes(self, dt: int) -> None:
        """The node's executor: ``tick`` at whatever time has come (paced resends included)."""
        STEPS[0] += 1
        self.now += dt
        self.producer.tick(self.now)
        self._emit()

    @rule()
    def restart_producer(self) -> None:
        STEPS[0] += 1
        self.instance += 1
        self.t0 = self.next_t - 1
        self.producer = self._new_producer()
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
    def _forged(self, sub: Sub, epoch: str, seq: int, descriptor: str | None) -> Note:
        header = encode_notification_header(
            epoch, seq, 0, FORGED, pushed=True, acked=None, descriptor=descriptor
        )
        return Note(sub.key.sub_id, header, b"")

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
            note = self._forged(sub, epoch, small, desc)
            if direct:
                self._deliver(note)
            else:
                self.net.append(note)
            return
        track = sub.protocol.ledger.epochs().get(reg.epoch)
        last = track.last if track is not None else 0
        if seq <= last:  # a replayed past seq, through the network like any message
            self.net.append(self._forged(sub, reg.epoch, seq, desc))
        else:  # a far-future seq, beyond anything in flight: straight to the subscriber
            future = reg.sent + sub.key.queue_size + seq
            self._deliver(self._forged(sub, reg.epoch, future, desc))

    @precondition(lambda self: bool(self._live()))
    @rule(data=st.data(), count=st.sampled_from([3, FORGOTTEN_EPOCHS + 16]), take=st.booleans())
    def rogue_epoch_flood(self, data: st.DataObject, count: int, take: bool) -> None:
        """Made-up epochs at seq 1, each one new, as fast as a peer can send them, the
        subscriber taking as they come (or not): its live epoch stays tracked, so nothing of
        it is lost (``heal``) and its producer is not held for good."""
        STEPS[0] += 1
        sub = data.draw(st.sampled_from(self._live()))
        for _ in range(count):
            self.made_up += 1
            self._deliver(self._forged(sub, f"F{self.made_up}.1", 1, sub.key.descriptor))
            if take:
                self._record(sub, sub.protocol.take_many(1))
        self._acks(sub, idle=True)

    @precondition(lambda self: bool(self._live()))
    @rule(data=st.data(), garbage=st.binary(max_size=12))
    def rogue_garbage(self, data: st.DataObject, garbage: bytes) -> None:
        """Bytes that are no header at all, on a subscription's key and on the ack key."""
        STEPS[0] += 1
        sub = data.draw(st.sampled_from(self._live()))
        self._deliver(Note(sub.key.sub_id, garbage, garbage))
        self._deliver(Ack(KEYS.ack(SERVICE, BUFFER, sub.key.sub_id), garbage))

    @precondition(lambda self: bool(self.subs))
    @rule(data=st.data(), kind=st.sampled_from(["foreign", "past", "colliding", "beyond"]))
    def rogue_ack(self, data: st.DataObject, kind: str) -> None:
        """Acks a peer makes up: of a foreign epoch, replaying a past one, under another id,
        or beyond what was sent (the epoch and id are on the wire, no seq is needed: it
        acked everything sent, and both sides stalled for good)."""
        STEPS[0] += 1
        sub = data.draw(st.sampled_from(self.subs))
        reg = self.producer.get(sub.key)
        own = KEYS.ack(SERVICE, BUFFER, sub.key.sub_id)
        if kind == "foreign" or reg is None:
            self.net.append(Ack(own, encode_ack("X", data.draw(st.integers(0, 1_000)))))
        elif kind == "past":
            self.net.append(Ack(own, encode_ack(reg.epoch, data.draw(st.integers(0, reg.acked)))))
        elif kind == "beyond":
            # Straight to the producer: held in the network until later puts, it would be an
            # in-window forgery, which only the secure profile prevents (docs/protocol.md).
            beyond = reg.sent + data.draw(st.sampled_from([1, 1_000, 2**62]))
            self._deliver(Ack(own, encode_ack(reg.epoch, beyond)))
        else:  # another id claims this registration's epoch
            rogue = KEYS.ack(SERVICE, BUFFER, "rogue")
            self.net.append(Ack(rogue, encode_ack(reg.epoch, data.draw(st.integers(0, 1_000)))))

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
        self.producer.token(_token(key), False, self.now)
        self._emit()

    @precondition(lambda self: bool(self._live()))
    @rule(
        data=st.data(),
        garbage=st.integers(0, 200),
        size=st.sampled_from([1, 16, 4096, 1 << 20]),
        repeats=st.integers(0, 300),
    )
    def rogue_flood(self, data: st.DataObject, garbage: int, size: int, repeats: int) -> None:
        """A flood on the ack key, delivered at once: ``garbage`` messages of ``size`` bytes,
        and a live subscriber's own last ack (epoch and seq are on the wire) ``repeats``
        times. However long it lasts, it may make each registration's outstanding
        notifications due at most once (one paced resend round), and frees no credit."""
        STEPS[0] += 1
        sub = data.draw(st.sampled_from(self._live()))
        keyexpr = KEYS.ack(SERVICE, BUFFER, sub.key.sub_id)
        blob = bytes(size)
        for _ in range(garbage):
            assert not self.producer.ack(keyexpr, blob, self.now)
        reg = self.producer.get(sub.key)
        if reg is not None and repeats:
            event("rogue flood: a subscriber's last ack repeated")
            acked = reg.acked
            for _ in range(repeats):
                assert not self.producer.ack(keyexpr, encode_ack(reg.epoch, acked), self.now)
            self.producer.tick(self.now)
            resent = [e for e in self.producer.events() if isinstance(e, Publish) and e.epoch]
            # One round of what is outstanding (other registrations' resends may fall due at
            # this tick too: not the flood's), however many repeats came.
            bought = [e for e in resent if e.key == sub.key]
            round_ = min(len(reg.outstanding), RESEND_BURST)
            assert len(bought) <= round_, "a flood of repeated acks bought more resends"
            for ev in resent:
                self.net.append(Note(ev.keyexpr.rsplit("/", 1)[-1], ev.attachment, ev.payload))

    @rule(
        count=st.integers(1, 40),
        holders=st.integers(1, 3),
        queue=st.sampled_from([1, 64, FLOW_QUEUE_MAX]),
        observe=st.booleans(),
        put_between=st.booleans(),
    )
    def rogue_churn(
        self, count: int, holders: int, queue: int, observe: bool, put_between: bool
    ) -> None:
        """A burst of tokens declared and then withdrawn (fresh ids, ``holders`` holder names,
        greedy queues): shares hold throughout, and once they are gone nothing of theirs
        remains (the invariants, and ``heal``, check the live subscribers)."""
        STEPS[0] += 1
        mode = OBSERVE if observe else FLOW
        keys = [
            (RegistrationKey(f"churn{i}", mode, queue, -1), f"rogue{i % holders}~x")
            for i in range(count)
        ]
        for key, holder in keys:
            self.producer.token(_token(key, holder), True, self.now)
            self._check_shares()
        self._emit()
        if put_between and self.producer.admit(1, may_wait=False) is None:
            meta = str(self.instance).encode()
            self.producer.put_many((DataObject(self.next_t, b"", meta),), self.now)
            self.next_t += 1
            self._emit()
        for key, holder in keys:
            self.producer.token(_token(key, holder), False, self.now)
        self._emit()
        left = {r.key.sub_id for r in self.producer.registrations()}
        assert not any(k.sub_id in left for k, _ in keys), "a churned token stayed registered"

    @rule(
        data=st.data(),
        whole=st.booleans(),
        lose_delete=st.booleans(),
        during=st.sampled_from(["nothing", "churn", "subscribe"]),
    )
    def lost_token_events(
        self, data: st.DataObject, whole: bool, lose_delete: bool, during: str
    ) -> None:
        """Token events were dropped (a churn overflowed the inbox), with a live subscriber's
        withdrawal among them (``lose_delete``), and the producer resyncs against a
        liveliness query whose answer is ``whole`` or not (it failed or timed out: any part
        of the live tokens), while token events are fed before it answers (``during``: a
        churned token the answer still names is withdrawn, or a subscriber joins that it
        does not name). No live subscriber may lose its registration, no withdrawn token
        may come back, and the lost withdrawal is repaired, at the latest by the query asked
        again after ``RESYNC_NS`` (``heal`` fails while it holds the producer)."""
        STEPS[0] += 1
        ghost = None
        if lose_delete and self._live():
            ghost = data.draw(st.sampled_from(self._live()))
            ghost.alive = False  # its token is withdrawn; the producer never hears of it
        churned = RegistrationKey(f"gone{self.now}", OBSERVE, 2, -1)
        if during == "churn":
            self.producer.token(_token(churned, "rogue~x"), True, self.now)
        self.producer.tokens_lost(self.now)
        while True:
            due = self.producer.next_deadline_ns()
            assert due is not None, "no resync after lost token events"
            self.now = max(self.now, due)
            if self.producer.resync_due(self.now):
                break
            self.producer.tick(self.now)
            self._emit()
        self.producer.resync_begin()
        answer = [_token(k) for k in self._registered_keys()]  # as Zenoh knows them now
        if during == "churn":
            answer.append(_token(churned, "rogue~x"))
            self.producer.token(_token(churned, "rogue~x"), False, self.now)
        elif during == "subscribe" and len(self._live()) < 4:
            self.subscribe(FLOW, 2)
        if not whole:
            event("a resync on an answer that did not end")
            answer = data.draw(st.lists(st.sampled_from(answer), unique=True)) if answer else []
        self.producer.resync(answer, self.now, ended=whole)
        self._emit()
        assert self.producer.get(churned) is None, "a withdrawn token came back at a resync"
        if not whole:  # asked again: this answer is whole
            self.now += RESYNC_NS
            assert self.producer.resync_due(self.now), "a partial answer was not asked again"
            self.producer.resync_begin()
            self.producer.resync([_token(k) for k in self._registered_keys()], self.now)
            self._emit()
        if ghost is not None:
            assert self.producer.get(ghost.key) is None, "a lost withdrawal held on"

    @precondition(lambda self: bool(self._acked_live()))
    @rule(data=st.data(), puts=st.integers(0, 3))
    def token_back_unheard(self, data: st.DataObject, puts: int) -> None:
        """Zenoh lost a token event with no sign of it (no inbox overflowed: "Unknown token
        id" under churn): a live subscriber's token was withdrawn and declared again, and
        the producer heard only the withdrawal. The subscriber, idle, repeats its ack of the
        registration it still holds; that ack names a registration the producer retired,
        so a resync falls due and registers the live token again, with ``puts`` elements
        stored meanwhile counted missed."""
        STEPS[0] += 1
        sub = data.draw(st.sampled_from(self._acked_live()))
        self._withdrawn(sub, puts)
        self.now += max(REACK_NS, REPEAT_RESEND_NS)  # a repeat, not one the filter drops
        keyexpr = KEYS.ack(SERVICE, BUFFER, sub.key.sub_id)
        acks = sub.protocol.acks(self.now, idle=True)
        assert acks, "an idle subscriber that took something repeats no ack"
        for ack in acks:
            self.producer.ack(keyexpr, ack, self.now)
        limit = self.now + RESYNC_NS
        while not self.producer.resync_due(self.now):
            due = self.producer.next_deadline_ns()
            assert due is not None and due <= limit, "an ack of a retired one: no resync"
            self.now = max(self.now, due)
            self.producer.tick(self.now)
            self._emit()
        self.producer.resync_begin()
        self.producer.resync([_token(k) for k in self._registered_keys()], self.now)
        reg = self.producer.get(sub.key)
        assert reg is not None, "a live subscriber whose token came back unheard stayed out"
        event(f"token back unheard: re-registered, {min(puts, 1)}+ stored meanwhile")
        self.epochs_of.setdefault(sub.key, set()).add(reg.epoch)
        self._emit()

    def _acked_live(self) -> list[Sub]:
        """Live subscribers that took something of the registration they hold now (only
        those repeat an ack while idle)."""
        out = []
        for sub in self._live():
            reg = self.producer.get(sub.key)
            if reg is not None and any(e == reg.epoch for e, _, _ in sub.taken):
                out.append(sub)
        return out

    @precondition(lambda self: bool(self._live()))
    @rule(data=st.data(), puts=st.integers(0, 3))
    def lapse(self, data: st.DataObject, puts: int) -> None:
        """A live subscriber's token is withdrawn and declared again (its link dropped and
        came back), with ``puts`` elements stored meanwhile: it must see them as missed."""
        STEPS[0] += 1
        sub = data.draw(st.sampled_from(self._live()))
        self._withdrawn(sub, puts)
        self._register(sub.key)

    def _withdrawn(self, sub: Sub, puts: int) -> None:
        """``sub``'s token withdrawn (a lapse: it counts what it misses), ``puts`` elements
        stored after. One producer session's messages to one key stay in order (Zenoh): what
        the old registration had in flight arrives (or is lost, by earlier moves) before the
        new registration's. Across a lapse the network may not reorder: the count of what
        was never notified rests on the element numbers seen so far."""
        sub.lapsed = True
        for msg in [m for m in self.net if isinstance(m, Note) and m.sub_id == sub.key.sub_id]:
            self.net.remove(msg)
            self._deliver(msg)
        self.producer.token(_token(sub.key), False, self.now)
        self._emit()
        meta = str(self.instance).encode()
        for _ in range(puts):
            if self.producer.admit(1, may_wait=False) is not None:
                break
            self.producer.put_many((DataObject(self.next_t, b"", meta),), self.now)
            self.next_t += 1
            self._emit()

    def _check_shares(self) -> None:
        """No holder holds more than the fair share of an idle producer, and the budget
        and the pools hold in total."""
        by_holder: dict[str, int] = {}
        flow = observe = 0
        for reg in self.producer.registrations():
            holder = self.producer._holders.get(reg.key, (None, None))
            name = f"{holder[0] or ''}~{holder[1] or ''}"
            if reg.flow:
                flow += 1
                by_holder[name] = by_holder.get(name, 0) + reg.key.queue_size
            else:
                observe += 1
        assert flow <= MAX_FLOW_REGISTRATIONS and observe <= MAX_OBSERVE_REGISTRATIONS
        assert sum(by_holder.values()) <= QUEUE_BUDGET
        assert all(q <= FLOW_QUEUE_MAX for q in by_holder.values()), by_holder

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
            self.producer.tick(self.now)
            self._emit()
        else:
            raise AssertionError("the producer stayed held after the network healed")
        assert self.producer.admit(1, may_wait=False) is None
        for sub in self._live():
            reg = self.producer.get(sub.key)
            assert reg is not None
            if sub.key.mode is not FLOW:
                continue
            got = [(e, s) for e, s, item in sub.taken if e == reg.epoch]
            event(f"heal: a flow subscriber checked, {min(len(got), 3)}+ notifications")
            if any(item[1] == FORGED for _, _, item in sub.taken):
                event("heal: a flow subscriber that took forged notifications")
            if any(e != reg.epoch for e, _, _ in sub.taken):
                event("heal: a flow subscriber that took several epochs")
            wanted = [(reg.epoch, s) for s in range(1, reg.sent + 1)]
            assert got == wanted, f"{sub.key.sub_id} lost or reordered notifications"
            # Every element this producer instance stored since the subscriber first
            # registered with it was taken or counted missed (a lapse loses none silently).
            instance = f"P{self.instance}"
            stamps = {
                item[0]
                for e, _, item in sub.taken
                if e.rpartition(".")[0] == instance and item[1] != FORGED
            }
            # (Up to the last one taken: a gap is reported with the next element, as an
            # observer's is.) Element numbers are the model's timestamps.
            newest = max(stamps, default=self.t0) - self.t0
            stored = newest - sub.first_base.get(instance, newest)
            assert len(stamps) + sub.missed.get(instance, 0) >= stored, (
                f"{sub.key.sub_id}: {stored} stored, {len(stamps)} taken, "
                f"{sub.missed.get(instance, 0)} counted missed"
            )
            for epoch, seq, item in sub.taken:
                if epoch == reg.epoch:
                    assert item[:2] == (self.sent[(epoch, seq)], str(self.instance).encode())

    # -- invariants ------------------------------------------------------------------------
    @invariant()
    def shares_hold(self) -> None:
        self._check_shares()

    @invariant()
    def queues_and_tables_are_bounded(self) -> None:
        for sub in self.subs:
            assert len(sub.protocol) <= sub.key.queue_size
            epochs = sub.protocol.ledger.epochs()
            assert len(epochs) <= max(MAX_EPOCHS, sub.key.queue_size + 1)
        regs = self.producer.registrations()
        assert len(regs) <= MAX_FLOW_REGISTRATIONS + MAX_OBSERVE_REGISTRATIONS
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
            own = self.epochs_of.get(sub.key, set())
            by_epoch: dict[str, list[int]] = {}
            for epoch, seq, item in sub.taken:
                if item[1] != FORGED:
                    assert epoch in own, "another registration's"
                    assert item[0] == self.sent[(epoch, seq)]
                elif epoch not in own:
                    continue  # a made-up epoch: its seqs are whatever the rogue sent
                # A forgery of one of our epochs at a seq not received yet (the rogue knew
                # the epoch: a restarted producer's old one, still in flight) is taken in
                # the real one's place, which then is a duplicate: the order still holds.
                by_epoch.setdefault(epoch, []).append(seq)
            for seqs in by_epoch.values():
                assert seqs == list(range(1, len(seqs) + 1)), f"gap or reorder: {seqs}"

    @invariant()
    def nothing_is_taken_twice(self) -> None:
        for sub in self.subs:
            seen = [(e, s) for e, s, item in sub.taken if item[1] != FORGED]
            assert len(seen) == len(set(seen))

    @invariant()
    def a_pushed_payload_is_the_element_and_a_resend_pushes_none(self) -> None:
        for sub in self.subs:
            for _, _, (_, meta, pushed) in sub.taken:
                if pushed is not None and meta != FORGED:
                    assert len(pushed) <= 4, "a payload beyond the push limit was pushed"


def _first_contact(sub: Sub, attachment: bytes) -> None:
    """Note the base of a registration the subscriber heard of (see ``Sub.first_base``)."""
    try:
        head = decode_notification_header(attachment)
    except ValueError:
        return
    epoch = head.text if isinstance(head, Control) else head.epoch
    if head.base is None or (isinstance(head, Control) and head.kind != "hello"):
        return
    if isinstance(head, Control) and head.descriptor != sub.key.descriptor:
        return
    if not isinstance(head, Control) and head.descriptor not in (None, sub.key.descriptor):
        return
    instance = epoch.rpartition(".")[0]
    sub.first_base[instance] = min(sub.first_base.get(instance, head.base), head.base)


def _entries_of(sub: Sub, epoch: str) -> list[int]:
    return [e.seq for e in sub.protocol.ledger._queue if e.epoch == epoch]


_EXAMPLES = DirectoryBasedExampleDatabase(str(Path(__file__).with_name("protocol_examples")))
ProtocolModel.TestCase.settings = (
    settings(max_examples=200, stateful_step_count=60, deadline=None, database=_EXAMPLES)
    if settings.get_current_profile_name() == "default"
    else settings(database=_EXAMPLES)
)
TestProtocol = ProtocolModel.TestCase
# A failure found here is shrunk for up to five minutes (hypothesis's own limit); the
# suite's per-test timeout would cut that short and leave a "flaky" report of the cut.
pytestmark = pytest.mark.timeout(900)
