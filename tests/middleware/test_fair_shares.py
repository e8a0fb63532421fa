"""Fair shares, large-push caps and token churn on the producer's sans-IO protocol object:
what one holder (a token's ``<node>~<host>``) may take, and that churn leaves nothing
behind."""

from __future__ import annotations

import msgpack

from middleware._ledger_producer import RegistrationKey
from middleware._protocol_events import Publish
from middleware._protocol_producer import (
    FLOW_QUEUE_MAX,
    LARGE_PUSH_PER_HOLDER,
    LARGE_PUSH_TOTAL,
    MAX_OBSERVE_REGISTRATIONS,
    QUEUE_BUDGET,
    RESYNC_NS,
    RESYNC_TOKENS,
    ProducerProtocol,
)
from middleware._records import DataObject, SubscriptionMode
from middleware._wire import Keys, encode_ack

FLOW, OBSERVE = SubscriptionMode.FLOW, SubscriptionMode.OBSERVE
KEYS = Keys("framegate")
PUSH_ALL = 2**31 - 1


def _producer() -> ProducerProtocol:
    return ProducerProtocol(KEYS, "cam", "images", "P", inline_max_bytes=64)


def _token(key: RegistrationKey, holder: str) -> str:
    return KEYS.subscription_token(
        "cam", "images", key.sub_id, key.mode, key.queue_size, key.push_max_bytes, holder
    )


def _controls(producer: ProducerProtocol) -> list[tuple[str, str]]:
    """(kind, text) of the control messages the producer queued, in order."""
    out = []
    for event in producer.events():
        if isinstance(event, Publish) and event.epoch is None:
            kind, _descriptor, text, *_ = msgpack.unpackb(event.attachment)
            out.append((kind, text))
    return out


def test_one_holder_gets_at_most_half_of_what_others_leave_free() -> None:
    producer = _producer()
    greedy = RegistrationKey("big", FLOW, FLOW_QUEUE_MAX, -1)
    producer.token(_token(greedy, "g~x"), True, 0)
    more = RegistrationKey("more", FLOW, 8, -1)
    producer.token(_token(more, "g~x"), True, 0)
    mediator = RegistrationKey("med", FLOW, 4, -1)
    producer.token(_token(mediator, "mediator~x"), True, 0)
    assert _controls(producer) == [
        ("hello", "P.1"),
        (
            "refused",
            "queue size 8 exceeds the fair share of g~x in cam/images's flow-control budget: "
            f"at most {FLOW_QUEUE_MAX} (half of the {QUEUE_BUDGET} of {QUEUE_BUDGET} others "
            f"leave free), {FLOW_QUEUE_MAX} held already; the largest holder is g~x (queue "
            f"{FLOW_QUEUE_MAX} in 1 subscriptions); subscribe with a smaller queue",
        ),
        ("hello", "P.2"),
    ]
    assert {r.key for r in producer.registrations()} == {greedy, mediator}


def test_one_holder_takes_at_most_half_of_the_observe_slots() -> None:
    producer = _producer()
    for i in range(MAX_OBSERVE_REGISTRATIONS):
        producer.token(_token(RegistrationKey(f"o{i}", OBSERVE, 2, -1), "g~x"), True, 0)
    assert len(producer.registrations()) == MAX_OBSERVE_REGISTRATIONS // 2
    record = RegistrationKey("rec", OBSERVE, 64, -1)
    producer.token(_token(record, "record~x"), True, 0)
    assert producer.get(record) is not None


def test_large_pushes_are_capped_per_holder_and_in_total() -> None:
    producer = _producer()
    keys = [RegistrationKey(f"o{i}", OBSERVE, 1, PUSH_ALL) for i in range(40)]
    for i, key in enumerate(keys):
        producer.token(_token(key, f"h{i // 10}~x"), True, 0)  # 4 holders of 10 each
    producer.events()
    producer.put_many((DataObject(1, bytes(1000), b"<m/>"),), 0)
    pushed = [e for e in producer.events() if isinstance(e, Publish) and e.payload]
    assert len(pushed) == min(LARGE_PUSH_TOTAL, 4 * LARGE_PUSH_PER_HOLDER)


def test_token_churn_leaves_no_state_behind() -> None:
    """Thousands of tokens declared and withdrawn, refused or not, from many holders: the
    producer ends with exactly the registrations that stay, and no per-holder state."""
    producer = _producer()
    stay = RegistrationKey("stay", FLOW, 4, -1)
    producer.token(_token(stay, "mediator~x"), True, 0)
    for round_ in range(50):
        keys = [
            (
                RegistrationKey(f"c{round_}-{i}", FLOW if i % 2 else OBSERVE, 1 << (i % 16), -1),
                f"h{i % 7}~x",
            )
            for i in range(64)
        ]
        for key, holder in keys:
            producer.token(_token(key, holder), True, round_)
        producer.put_many((DataObject(round_ + 1, b"x", b"<m/>"),), round_)
        reg = producer.get(stay)
        assert reg is not None
        producer.ack(KEYS.ack("cam", "images", "stay"), encode_ack(reg.epoch, reg.sent), round_)
        for key, holder in keys:
            producer.token(_token(key, holder), False, round_)
        producer.events()
    assert [r.key for r in producer.registrations()] == [stay]
    assert producer._shares.holders() == {"mediator~x"}
    assert set(producer._holders) == {stay} and not producer._paced
    assert producer.counters.refused_registrations > 0


def test_a_resync_after_lost_token_events_repairs_the_table() -> None:
    """Token events dropped under churn: a withdrawn token's registration would hold the
    producer for ever, a live one would never register. The resync against the live
    tokens removes the first and registers the second."""
    producer = _producer()
    ghost = RegistrationKey("ghost", FLOW, 2, -1)
    live = RegistrationKey("live", FLOW, 2, -1)
    producer.token(_token(ghost, "churn~x"), True, 0)
    producer.put_many((DataObject(1, b"x", b"<m/>"),), 0)
    producer.put_many((DataObject(2, b"x", b"<m/>"),), 0)
    # The ghost, whose withdrawal was lost, holds it.
    assert producer.admit(1, may_wait=False) is not None
    producer.tokens_lost(0)
    assert producer.next_deadline_ns() is not None and producer.resync_due(0)
    producer.resync([_token(live, "mediator~x")], 0)
    assert [r.key for r in producer.registrations()] == [live]
    assert producer.admit(1, may_wait=False) is None and not producer.resync_due(0)


def test_a_resync_answer_cut_short_by_a_crowd_of_tokens_removes_no_registration() -> None:
    """A peer can declare more subscription tokens than a resync reads: a live subscriber
    left out of the answer lost its registration (and the elements it was owed)."""
    producer = _producer()
    real = RegistrationKey("real", FLOW, 2, -1)
    producer.token(_token(real, "mediator~x"), True, 0)
    crowd = [
        _token(RegistrationKey(f"c{i}", OBSERVE, 2, -1), "crowd~x") for i in range(RESYNC_TOKENS)
    ]
    producer.tokens_lost(0)
    producer.resync(crowd, 0)
    assert producer.get(real) is not None
    producer.tokens_lost(0)
    producer.resync(crowd[:-1], 0)  # a whole answer without it: it is gone
    assert producer.get(real) is None


def test_a_resync_on_an_answer_that_did_not_end_retires_no_one_and_asks_again() -> None:
    """A liveliness query that failed or timed out answers with part of the live tokens (or
    none): the registrations it left out were retired, and their subscribers, whose tokens
    still live, were never registered again (no element for 60 s under a token churn). A
    withdrawal that was lost is still repaired, by the answer asked again."""
    producer = _producer()
    real = RegistrationKey("real", FLOW, 8, -1)
    ghost = RegistrationKey("ghost", FLOW, 2, -1)
    producer.token(_token(real, "consumer~x"), True, 0)
    producer.token(_token(ghost, "churn~x"), True, 0)
    producer.tokens_lost(0)
    producer.resync_begin()
    producer.resync([], 0, ended=False)
    assert producer.get(real) is not None and producer.get(ghost) is not None
    assert not producer.resync_due(RESYNC_NS - 1) and producer.resync_due(RESYNC_NS)
    producer.resync_begin()
    producer.resync([_token(real, "consumer~x")], RESYNC_NS)
    assert producer.get(real) is not None and producer.get(ghost) is None


def test_a_token_event_fed_while_the_resync_query_was_out_wins_over_its_answer() -> None:
    """The executor asks for the live tokens outside the producer's lock, while a ``put``
    feeds token events: a subscriber that registered meanwhile is not in the answer, and a
    token withdrawn meanwhile still is; neither answer may undo the event."""
    producer = _producer()
    joined = RegistrationKey("joined", FLOW, 8, -1)
    left = RegistrationKey("left", FLOW, 2, -1)
    producer.tokens_lost(0)
    producer.resync_begin()
    answer = [_token(left, "churn~x")]  # as the query saw it
    producer.token(_token(joined, "consumer~x"), True, 0)
    producer.token(_token(left, "churn~x"), True, 0)
    producer.token(_token(left, "churn~x"), False, 0)
    producer.resync(answer, 0)
    assert producer.get(joined) is not None and producer.get(left) is None


def test_a_token_whose_id_or_holder_no_client_could_read_is_ignored_and_counted() -> None:
    """Every client reads a producer's subscriptions in ``@info``, whose decoder refuses a
    description with an unprintable or overlong name: such a token is a bad message, so
    that one peer's token cannot make the buffer unreadable to every CLI command."""
    producer = _producer()
    hostile = [
        _token(RegistrationKey("a\x1bb", OBSERVE, 2, -1), "n~h"),
        _token(RegistrationKey("a\x7fb", OBSERVE, 2, -1), "n~h"),
        _token(RegistrationKey("x" * 2000, OBSERVE, 2, -1), "n~h"),
        _token(RegistrationKey("ok", OBSERVE, 2, -1), "n\x0a~h"),
        _token(RegistrationKey("ok", OBSERVE, 2, -1), "n~" + "h" * 2000),
    ]
    for token in hostile:
        producer.token(token, True, 0)
    assert producer.registrations() == []
    assert producer.counters.bad_messages == len(hostile)
    fine = RegistrationKey("rec", OBSERVE, 2, -1)
    producer.token(_token(fine, "record~h\u00e9te"), True, 0)
    assert producer.get(fine) is not None
