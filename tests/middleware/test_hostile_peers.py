"""Hostile peers of a producer, across real processes over Zenoh on loopback: greedy
holders, forged refusals, fake service tokens, hostile ``@info`` answers and data replies.
The hostile peers are raw Zenoh sessions in this process; token churn and ack floods from
worker processes: ``test_hostile_floods.py`` and ``test_ack_floods.py``."""

from __future__ import annotations

import contextlib
import json
import logging
import socket
import threading
import time
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from typing import Any

import msgpack
import pytest
import zenoh

from middleware import (
    FLOW_QUEUE_MAX,
    BufferInfo,
    DataObject,
    FramegateError,
    NameTakenError,
    NetworkConfig,
    Node,
    QueryError,
    ServiceInfo,
    SubscriptionMode,
    make_metadata,
    now_ns,
)
from middleware._inbox import control_inbox_bytes
from middleware._protocol_producer import MAX_OBSERVE_REGISTRATIONS, QUEUE_BUDGET
from middleware._wire import Keys, holder_chunk
from tests.conftest import NodeProcess, run_framegate, wait_until
from tests.helpers.raw_zenoh import open_session
from tests.helpers.timing import scaled

pytestmark = pytest.mark.integration

KEYS = Keys("framegate")


def _cam_images(node: Node) -> BufferInfo:
    """``cam/images`` as ``node`` reads it, with a deadline for a loaded machine's answer."""
    return node.buffer_info("cam/images", timeout_s=scaled(10.0))


def _token(sub_id: str, mode: SubscriptionMode, queue: int, holder: str) -> str:
    return KEYS.subscription_token("cam", "images", sub_id, mode, queue, -1, holder)


def test_a_greedy_holder_leaves_room_for_a_mediator_and_a_recorder(
    node_process: Callable[..., NodeProcess], endpoint: str
) -> None:
    """One peer asks for the largest queue a holder may get, then more, and holds every
    observe slot it may: a mediator's flow subscription and a recorder's observer still
    register, and ``info`` states the limits."""
    producer = node_process("cam", "--listen", endpoint)
    assert producer.call("offer", buffer="images")["ok"]
    with (
        open_session(endpoint) as rogue,
        Node("mediator", NetworkConfig(connect=(endpoint,))) as mediator,
        Node("record", NetworkConfig(connect=(endpoint,))) as record,
    ):
        live = rogue.liveliness()
        tokens = [live.declare_token(_token("big", SubscriptionMode.FLOW, FLOW_QUEUE_MAX, "g~x"))]
        tokens.append(live.declare_token(_token("big2", SubscriptionMode.FLOW, 4096, "g~x")))
        tokens += [
            live.declare_token(_token(f"obs{i}", SubscriptionMode.OBSERVE, 2, "g~x"))
            for i in range(MAX_OBSERVE_REGISTRATIONS)
        ]
        info = wait_until(
            lambda: (
                (i := _cam_images(mediator)).refused_subscriptions
                >= 1 + MAX_OBSERVE_REGISTRATIONS // 2
                and i
            ),
            scaled(15),
            "the greedy holder's tokens judged",
        )
        assert info.limits is not None and info.limits.queue_budget == QUEUE_BUDGET
        assert info.limits.flow_queue_max == FLOW_QUEUE_MAX
        assert info.limits.control_inbox_bytes == control_inbox_bytes()  # over the wire
        flow = mediator.subscribe("cam/images", queue_size=4, wait_s=scaled(5))
        observer = record.subscribe(
            "cam/images", queue_size=8, mode=SubscriptionMode.OBSERVE, wait_s=scaled(5)
        )
        subs = {s.subscription_id: s for s in _cam_images(mediator).subscriptions}
        assert flow.subscription_id in subs and observer.subscription_id in subs
        assert subs[flow.subscription_id].node == "mediator"
        for token in tokens:
            token.undeclare()


def test_a_refused_service_logs_an_error_and_registers_once_room_is_free(
    node_process: Callable[..., NodeProcess], endpoint: str, caplog: pytest.LogCaptureFixture
) -> None:
    """Peers with many holder names take the whole budget; a service subscribing without
    waiting (as the mediator does) logs the refusal as an error naming the reason and
    itself, and registers by itself once they leave."""
    producer = node_process("cam", "--listen", endpoint)
    assert producer.call("offer", buffer="images")["ok"]
    with (
        open_session(endpoint) as rogue,
        Node("mediator", NetworkConfig(connect=(endpoint,))) as mediator,
    ):
        live, tokens, free, i = rogue.liveliness(), [], QUEUE_BUDGET, 0
        while free >= 4:  # each holder takes its fair share: half of what is free
            share = (free + 1) // 2
            tokens.append(
                live.declare_token(_token(f"g{i}", SubscriptionMode.FLOW, share, f"h{i}~x"))
            )
            free, i = free - share, i + 1
        wait_until(
            lambda: (
                sum(s.queue_size for s in _cam_images(mediator).subscriptions)
                == QUEUE_BUDGET - free
            ),
            scaled(15),
            "the budget taken",
        )
        with caplog.at_level(logging.ERROR, logger="framegate.middleware"):
            sub = mediator.subscribe("cam/images", queue_size=4, wait_s=0)
            wait_until(
                lambda: any(
                    "refused the subscription of mediator~" in r.message for r in caplog.records
                ),
                scaled(15),
                "the refusal logged as an error",
            )
        [record] = [r for r in caplog.records if "refused the subscription" in r.message]
        assert record.levelno == logging.ERROR and "queue size 4" in record.message
        assert "largest holder is h0~x" in record.message
        for token in tokens:
            token.undeclare()
        wait_until(
            lambda: (
                sub.subscription_id
                in {s.subscription_id for s in _cam_images(mediator).subscriptions}
            ),
            scaled(20),
            "the refused subscription registered once the budget was free",
        )


def test_a_refused_cli_tool_says_so_in_one_line(
    node_process: Callable[..., NodeProcess], endpoint: str
) -> None:
    """A peer holds every observe slot the anonymous clients of this host may have (under
    their holder name, which the default profile does not check): ``watch`` is refused and
    says so in one ``error:`` line, exit 1, with no retry message beside it."""
    producer = node_process("cam", "--listen", endpoint)
    assert producer.call("offer", buffer="images")["ok"]
    anonymous = holder_chunk(None, socket.gethostname())
    with (
        open_session(endpoint) as rogue,
        Node("mediator", NetworkConfig(connect=(endpoint,))) as client,
    ):
        live = rogue.liveliness()
        tokens = [
            live.declare_token(_token(f"o{i}", SubscriptionMode.OBSERVE, 1, anonymous))
            for i in range(MAX_OBSERVE_REGISTRATIONS // 2 + 2)
        ]
        # The share is taken once the producer has judged the tokens (a loaded machine's
        # producer may take a while), not when they were declared.
        wait_until(
            lambda: _cam_images(client).refused_subscriptions >= 2,
            scaled(30),
            "the rogue's tokens judged",
        )
        done = run_framegate("watch", "cam/images", "--connect", endpoint)
        for token in tokens:
            token.undeclare()
    lines = done.stderr.strip().splitlines()
    assert done.returncode == 1, done.stderr
    assert len(lines) == 1 and lines[0].startswith("error:"), done.stderr
    assert "refused this subscription" in lines[0], done.stderr


def _watch_tokens(session: zenoh.Session, fn: Callable[[str], None]) -> Callable[[], None]:
    """Call ``fn(token key)`` for every new subscription token of cam/images, on a thread."""
    watcher = session.liveliness().declare_subscriber(
        KEYS.subscription_tokens("cam", "images"), zenoh.handlers.FifoChannel(256)
    )

    def run() -> None:
        for sample in watcher.handler:
            if sample.kind == zenoh.SampleKind.PUT:
                fn(str(sample.key_expr))

    thread = threading.Thread(target=run, daemon=True)
    thread.start()

    def stop() -> None:
        watcher.undeclare()
        thread.join(timeout=5)

    return stop


@contextmanager
def _answering_as(
    rogue: zenoh.Session, service: str, garbage: bytes | None = None
) -> Iterator[None]:
    """``rogue`` answers ``@info`` of ``service`` too, with a copy of the real description
    (or with ``garbage``)."""
    copy = garbage
    if copy is None:
        copy = next(r.ok.payload.to_bytes() for r in rogue.get(KEYS.info(service)) if r.ok)

    def answer(query: zenoh.Query) -> None:
        with query:
            query.reply(query.key_expr, copy)

    queryable = rogue.declare_queryable(KEYS.info(service), zenoh.handlers.Callback(answer))
    try:
        yield
    finally:
        queryable.undeclare()


@pytest.mark.parametrize("also_answers", [False, True], ids=["forger", "forger-answering-as-cam"])
def test_a_forged_refusal_does_not_refuse(
    listen_net: NetworkConfig, endpoint: str, also_answers: bool
) -> None:
    """A peer answers every new subscription token with a ``refused`` on its notify key,
    before the producer's greeting: it is not from the producer's session, so it does not
    count, and each subscription registers. ``also_answers``: the peer answers ``@info`` in
    the producer's name too, so two sessions answer as the service: no refusal is trusted."""
    with _cam_rogue_client(listen_net, endpoint) as (service, rogue, client):
        images = service.offer("images")
        wait_until(lambda: "cam" in client.live_services(), scaled(10), "the service")

        def refuse(token: str) -> None:
            parts = token.split("/")
            sub_id, descriptor = parts[4], "/".join(parts[5:8])
            forged = msgpack.packb(("refused", descriptor, "forged: go away"))
            rogue.put(
                KEYS.notify("cam", "images", sub_id),
                b"",
                attachment=forged,
                source_info=zenoh.SourceInfo(rogue.id, 0),
            )

        with _answering_as(rogue, "cam") if also_answers else contextlib.nullcontext():
            stop = _watch_tokens(rogue, refuse)
            try:
                for t in range(1, 6):
                    sub = client.subscribe("cam/images", queue_size=2, wait_s=scaled(10))
                    images.put(t, b"x", make_metadata("generic", t), wait_s=scaled(30))
                    note = sub.take(timeout_s=scaled(30))
                    assert note is not None and note.timestamp_ns == t
                    sub.close()
            finally:
                stop()


@contextmanager
def _cam_rogue_client(
    listen_net: NetworkConfig, endpoint: str
) -> Iterator[tuple[Node, zenoh.Session, Node]]:
    """The service ``cam`` (no buffer yet), a rogue's raw session and a client, all met."""
    with (
        Node("cam", listen_net) as service,
        open_session(endpoint) as rogue,
        Node(network=NetworkConfig(connect=(endpoint,))) as client,
    ):
        yield service, rogue, client


def test_a_description_two_sessions_give_decides_nothing(
    listen_net: NetworkConfig, endpoint: str
) -> None:
    """What may decide a rewind (a source's clock sample) is taken only from a description one
    session alone gives: a peer answering in the service's name makes it no answer."""
    with _cam_rogue_client(listen_net, endpoint) as (service, rogue, client):
        service.offer("images")
        wait_until(lambda: "cam" in client.live_services(), scaled(10), "the service")
        assert client.service_info("cam", unambiguous=True).service == "cam"
        with _answering_as(rogue, "cam"):

            def refused() -> str | None:
                # Until the rogue's queryable has reached the client (a loaded machine's
                # declaration can take a while), one session still answers alone.
                try:
                    client.service_info("cam", unambiguous=True, timeout_s=scaled(2))
                except QueryError as exc:
                    return str(exc)
                return None

            said = wait_until(refused, scaled(30), "the two answers to be refused")
            assert "2 Zenoh sessions answer as 'cam'" in said, said
            answers: list[object] = []
            client.ask_service_info("cam", answers.append, timeout_s=scaled(2))
            wait_until(lambda: answers, scaled(10), "the answer")
            assert answers == [None]
            assert client.service_info("cam").service == "cam"  # for reading, as before


def test_only_the_session_that_greeted_a_subscription_speaks_for_its_service(
    listen_net: NetworkConfig, endpoint: str
) -> None:
    """A mediator's clock samples and a detector's rewinds ask with their subscription's
    ``producer_session``: a peer answering with a copy of the service's description (a stale
    clock) counts for nothing, even when the service's own answer does not come (measured:
    with the camera's answers dropped by a flood, the copy alone was trusted, and every frame
    went unpaired)."""
    with _cam_rogue_client(listen_net, endpoint) as (service, rogue, client):
        images = service.offer("images")
        sub = client.subscribe("cam/images", queue_size=2, wait_s=scaled(10))
        assert sub.wait_registered(scaled(10))
        images.put(1, b"x", make_metadata("generic", 1), wait_s=scaled(30))
        real = sub.producer_session
        assert real == str(service._session.zid()), real  # type: ignore[attr-defined]

        def ask(session: str | None) -> object:
            answers: list[object] = []
            client.ask_service_info("cam", answers.append, timeout_s=scaled(2), session=session)
            wait_until(lambda: answers, scaled(10), "the answer")
            return answers[0]

        with _answering_as(rogue, "cam"):
            wait_until(lambda: ask(None) is None, scaled(30), "the rogue's answer to arrive")
            found = ask(real)  # the producer's own answer, beside the rogue's
            assert isinstance(found, ServiceInfo) and found.service == "cam"
            service.close()  # its answers stop; the rogue's copy goes on
            wait_until(lambda: ask(None) is not None, scaled(30), "the rogue to answer alone")
            assert ask(real) is None
            with pytest.raises(FramegateError):
                client.service_info("cam", session=real, timeout_s=scaled(2))


@pytest.mark.parametrize(
    "garbage", [b"\xff\xfe not json", b"{}", b"[" * 1000], ids=["not-utf8", "empty-map", "deep"]
)
def test_garbage_beside_the_real_description_does_not_void_it(
    listen_net: NetworkConfig, endpoint: str, garbage: bytes
) -> None:
    """A peer that answers ``@info`` of a service with something that is no description of
    it is no second instance: the real description still decides (a mediator's clock
    samples, a detector's rewinds), asked and asked without waiting."""
    with _cam_rogue_client(listen_net, endpoint) as (service, rogue, client):
        service.offer("images")
        wait_until(lambda: "cam" in client.live_services(), scaled(10), "the service")
        with _answering_as(rogue, "cam", garbage):

            def garbage_seen() -> bool:
                replies = list(
                    client._session.get(
                        KEYS.info("cam"), consolidation=zenoh.ConsolidationMode.NONE
                    )
                )
                return sum(r.ok is not None for r in replies) == 2

            wait_until(garbage_seen, scaled(30), "the rogue's answer to reach the client")
            assert client.service_info("cam", unambiguous=True).service == "cam"
            assert client.service_info("cam").service == "cam"
            answers: list[object] = []
            client.ask_service_info("cam", answers.append, timeout_s=scaled(2))
            wait_until(lambda: answers, scaled(10), "the answer")
            assert isinstance(answers[0], ServiceInfo) and answers[0].service == "cam"


def test_a_crowd_of_repliers_makes_the_description_ambiguous(
    listen_net: NetworkConfig, endpoint: str
) -> None:
    """Seven garbage answers and one forged valid one come before the real one: the real
    one, turned away as the ninth session, must not leave the forgery trusted."""
    from types import SimpleNamespace

    from middleware._discovery import MAX_REPLIERS, Answers

    with _cam_rogue_client(listen_net, endpoint) as (service, rogue, _client):
        service.offer("images")
        real = next(r.ok.payload.to_bytes() for r in rogue.get(KEYS.info("cam")) if r.ok)

    def reply(session: str, payload: bytes) -> object:
        return SimpleNamespace(
            ok=SimpleNamespace(payload=zenoh.ZBytes(payload)),
            replier_id=SimpleNamespace(zid=session),
        )

    answers = Answers("cam", now_ns())
    for i in range(MAX_REPLIERS - 1):
        answers.add(reply(f"garbage{i}", b"garbage!"), now_ns())  # type: ignore[arg-type]
    answers.add(reply("forger", real), now_ns())  # type: ignore[arg-type]
    answers.add(reply("camera", real), now_ns())  # type: ignore[arg-type]
    with pytest.raises(QueryError, match="more than 8 Zenoh sessions answer as 'cam'"):
        answers.trusted()
    alone = Answers("cam", now_ns())
    alone.add(reply("garbage", b"garbage!"), now_ns())  # type: ignore[arg-type]
    alone.add(reply("camera", real), now_ns())  # type: ignore[arg-type]
    found = alone.trusted()
    assert found is not None and found.service == "cam"


def test_a_bare_service_token_does_not_stop_the_service(
    node_process: Callable[..., NodeProcess], endpoint: str
) -> None:
    """A liveliness token ``framegate/@svc/cam`` whose holder does not answer as ``cam``
    (no ``@info``) is not another instance: the real ``cam`` starts (with a warning)."""
    with open_session(endpoint) as rogue:
        token = rogue.liveliness().declare_token(KEYS.service_token("cam"))
        service = node_process("cam", "--listen", "tcp/127.0.0.1:0", "--connect", endpoint)
        assert service.call("offer", buffer="images")["ok"]
        token.undeclare()


def test_a_live_service_whose_token_is_not_seen_yet_keeps_its_name(
    listen_net: NetworkConfig, endpoint: str, monkeypatch: pytest.MonkeyPatch
) -> None:
    """A fresh session's look at the liveliness tokens can come back empty at once while
    the live instance answers (2 in 20 tries measured; 7 under a flood): the descriptions
    are asked anyway, and the second instance is refused, not started beside the first.
    Played here by having the second look for a token nobody holds."""
    from middleware._wire import Keys

    with Node("cam", listen_net) as first:
        first.offer("images")
        endpoint_of_first = first._endpoint
        assert endpoint_of_first is not None
        with Node("cam", NetworkConfig(connect=(endpoint,))) as second:
            wait_until(lambda: "cam" in second.live_services(), scaled(10), "the first")
            monkeypatch.setattr(
                Keys, "service_token", lambda self, service: f"{self.namespace}/x/y"
            )
            with pytest.raises(NameTakenError, match="already offered by pid"):
                second.offer("images")
            # And while a flood drops its descriptions too (measured: 1 start in 4 beside
            # the live camera under 200 queries/s): its data answer still counts.
            endpoint_of_first._handlers["info"] = lambda _query: None
            with pytest.raises(NameTakenError, match="busy"):
                second.offer("images")


def test_a_live_service_whose_descriptions_do_not_come_keeps_its_name(
    listen_net: NetworkConfig, endpoint: str
) -> None:
    """A flood of ``@info`` queries fills a live service's bounded inbox of them, so a new
    instance's question is dropped: it asks for data too (its own inbox, which the flood does
    not fill), gets a service's answer, and is refused as a second instance (measured: it
    took the token for a bare one and started, two cameras on one name)."""
    with Node("cam", listen_net) as first:
        first.offer("images")
        endpoint_of_first = first._endpoint
        assert endpoint_of_first is not None
        # Every description dropped unanswered, as beyond a full inbox.
        endpoint_of_first._handlers["info"] = lambda _query: None
        with Node("cam", NetworkConfig(connect=(endpoint,))) as second:
            wait_until(lambda: "cam" in second.live_services(), scaled(10), "the first")
            with pytest.raises(NameTakenError, match="busy"):
                second.offer("images")


def test_a_handlers_query_keeps_only_the_range_it_asked_once_per_timestamp(
    listen_net: NetworkConfig, endpoint: str
) -> None:
    """A peer answers a handler's query (the mediator's look-up of frames it never saw)
    beside the service, with elements outside the range and again within it: each would
    become a record of its own. Only the range asked comes back, one element per stamp."""
    from middleware._service import encode_answer_end
    from middleware._wire import encode_element_attachment

    with _cam_rogue_client(listen_net, endpoint) as (service, rogue, client):
        images = service.offer("images")
        for t in range(1, 6):
            images.put(t, b"x", make_metadata("generic", t))

        def forge(query: zenoh.Query) -> None:
            with query:
                for t in (3, 3, 1000, 2**62):
                    element = DataObject(t, b"rogue", make_metadata("generic", t))
                    query.reply(
                        query.key_expr, b"rogue", attachment=encode_element_attachment(element)
                    )
                query.reply(query.key_expr, b"", attachment=encode_answer_end(4))

        queryable = rogue.declare_queryable(KEYS.data("cam", "images"), forge)
        try:

            def rogue_heard() -> bool:
                selector = f"{KEYS.data('cam', 'images')}?_time=[2..4]"
                return any(
                    r.ok is not None and r.ok.payload.to_bytes() == b"rogue"
                    for r in client._session.get(selector)  # type: ignore[attr-defined]
                )

            wait_until(rogue_heard, scaled(30), "the rogue's queryable to reach the client")
            got: list[Any] = []
            client.ask_query("cam/images", got.append, time_range="[2..4]", timeout_s=scaled(5))
            wait_until(lambda: got, scaled(10), "the answer")
            assert isinstance(got[0], list), got
            assert [e.timestamp_ns for e in got[0]] == [2, 3, 4], got[0]
            # Asked of the producer's session alone, the rogue's element 3 is not taken
            # for the service's (whichever reply came first).
            real = str(service._session.zid())  # type: ignore[attr-defined]
            mine: list[Any] = []
            client.ask_query(
                "cam/images", mine.append, time_range="[2..4]", timeout_s=scaled(5), session=real
            )
            wait_until(lambda: mine, scaled(10), "the answer")
            assert [(e.timestamp_ns, e.payload) for e in mine[0]] == [
                (2, b"x"),
                (3, b"x"),
                (4, b"x"),
            ], mine[0]
        finally:
            queryable.undeclare()


def _forge(rogue: zenoh.Session, sub: Any, *header: object) -> None:
    """One notification header ``header`` on ``sub``'s notify key, sent by ``rogue``."""
    rogue.put(
        KEYS.notify("cam", "images", sub.subscription_id),
        b"",
        attachment=msgpack.packb(header, use_bin_type=True),
    )


def test_a_flood_of_made_up_epochs_does_not_hold_the_producer(
    listen_net: NetworkConfig, endpoint: str
) -> None:
    """A peer sends seq 1 of 600 ever new epochs to a flow subscriber, which takes them as
    they come: more than it remembers of evicted epochs. Its producer's epoch stays
    tracked, so every later element is still notified (it stalled for good when the flood
    pushed the live epoch out of memory)."""
    with _cam_rogue_client(listen_net, endpoint) as (service, rogue, client):
        images = service.offer("images")
        sub = client.subscribe("cam/images", queue_size=2, wait_s=scaled(10))
        images.put(1, b"x", make_metadata("generic", 1), wait_s=scaled(30))
        note = sub.take(timeout_s=scaled(30))
        assert note is not None and note.timestamp_ns == 1
        for i in range(600):
            _forge(rogue, sub, f"F{i}.1", 1, 999, None, False, None, "flow/2/-1", None)
            while sub.take(timeout_s=0) is not None:
                pass  # the forged ones: an hour-old stamp the consumer cannot fetch
        deadline = time.monotonic() + scaled(10)
        while time.monotonic() < deadline:  # the last forged ones, still on their way
            if sub.take(timeout_s=0.5) is None:
                break
        for t in range(2, 8):
            images.put(t, b"x", make_metadata("generic", t), wait_s=scaled(10))
            taken = sub.take(timeout_s=scaled(10))
            while taken is not None and taken.timestamp_ns == 999:
                taken = sub.take(timeout_s=scaled(10))
            assert taken is not None and taken.timestamp_ns == t, f"element {t} not notified"


def test_an_observer_survives_a_batch_whose_seqs_overflow(
    listen_net: NetworkConfig, endpoint: str
) -> None:
    """One batch notification whose seqs pass 2^63 is garbage (its ack could not be
    encoded and killed ``watch``, ``echo``, ``record``): counted, and the observer goes on."""
    with _cam_rogue_client(listen_net, endpoint) as (service, rogue, client):
        images = service.offer("images")
        sub = client.subscribe(
            "cam/images", queue_size=4, mode=SubscriptionMode.OBSERVE, wait_s=scaled(10)
        )
        now = now_ns()
        header = ("rogue.1", 2**64 - 1, [now, now + 1], [None, None], None, None)
        # Forged again until counted: the rogue's put can go nowhere until the subscriber's
        # declaration reaches its session (at load 11 the one put made never arrived).
        wait_until(
            lambda: _forge(rogue, sub, *header, "observe/4/-1", None) is None and sub.garbage,
            30,
            "the forged batch counted",
        )
        for t in range(1, 4):
            images.put(t, b"x", make_metadata("generic", t))
            note = sub.take(timeout_s=scaled(10))
            assert note is not None and note.timestamp_ns == t


def test_a_token_no_client_could_read_leaves_the_buffer_readable(
    listen_net: NetworkConfig, endpoint: str
) -> None:
    """A subscription token whose id holds an escape character: the producer ignores it, so
    its description (which every CLI command reads) stays readable."""
    with _cam_rogue_client(listen_net, endpoint) as (service, rogue, client):
        service.offer("images")
        wait_until(lambda: "cam" in client.live_services(), scaled(10), "the service")
        live = rogue.liveliness()
        token = live.declare_token(_token("a\x1bb", SubscriptionMode.OBSERVE, 1, "n~h"))
        info = wait_until(
            lambda: (i := _cam_images(client)).bad_messages >= 1 and i,
            scaled(10),
            "the token ignored",
        )
        assert info.subscriptions == ()
        token.undeclare()


HOSTILE_INFO = {
    "no subscriptions": json.dumps(
        {
            "service": "evil",
            "host": "h",
            "pid": 1,
            "clock_ns": 1,
            "buffers": [{"buffer": "b", "service": "evil", "kind": "generic"}],
        }
    ).encode(),
    "invalid UTF-8": b'{"service": "\xff\xfe"}',
    "100,000 nested brackets": b"[" * 100_000 + b"]" * 100_000,
}


def _valid_description(**changes: Any) -> dict[str, Any]:
    """A well-formed description of ``evil`` with one buffer and one subscription, and
    ``changes`` applied: ``buffer.<field>``, ``sub.<field>`` or a top-level field."""
    sub = {"id": "s1", "mode": "flow", "queue_size": 2, "queued": 0, "node": "n", "host": "h"}
    buffer = {
        "buffer": "b",
        "service": "evil",
        "kind": "generic",
        "retention": {"max_count": 10},
        "count": 1,
        "payload_bytes": 1,
        "oldest_ns": 1,
        "newest_ns": 1,
        "rate_hz": 1.0,
        "puts": 1,
        "refused": 0,
        "rejected": 0,
        "subscriptions": [sub],
    }
    body: dict[str, Any] = {
        "service": "evil",
        "host": "h",
        "pid": 1,
        "clock_ns": time.time_ns(),
        "buffers": [buffer],
    }
    for name, value in changes.items():
        where, _, field = name.rpartition(".")
        {"buffer": buffer, "sub": sub, "": body}[where][field] = value
    return body


# Schema-valid is not sane: values a terminal, a clock formatter or a division cannot take,
# each as the raw JSON text a peer sends.
INSANE_INFO = {
    "a stamp of 10^30": ("buffer.newest_ns", "1" + "0" * 30),
    "a negative stamp": ("buffer.oldest_ns", "-100000000000000000000"),
    "a queue of 0": ("sub.queue_size", "0"),
    "a lone surrogate in host": ("host", '"\\ud800"'),
    "an escape sequence in host": ("host", '"\\u001b[2J\\u001b[31mowned"'),
    "a newline in a buffer name": ("buffer.buffer", '"b\\nerror: fake"'),
    "a rate of NaN": ("buffer.rate_hz", "NaN"),
}


@pytest.mark.parametrize("case", sorted(INSANE_INFO))
def test_ls_and_info_of_an_insane_description_say_so_in_one_line(endpoint: str, case: str) -> None:
    field, raw = INSANE_INFO[case]
    text = json.dumps(_valid_description(**{field: "@@"})).replace('"@@"', raw)
    with _hostile_service(endpoint, text.encode()):
        for command in (["info", "evil"], ["ls"], ["ls", "--json"]):
            done = run_framegate(*command, "--connect", endpoint)
            said = done.stdout + done.stderr
            assert "Traceback" not in said, (command, said)
            assert "\x1b" not in said and "error: fake" not in said, (command, said)
            lines = done.stderr.strip().splitlines()
            if command[0] == "info":
                assert done.returncode == 1, done.stderr
                assert len(lines) == 1 and lines[0].startswith("error:"), done.stderr
            else:  # listed as left out, in one line, never silently absent
                assert lines == [line for line in lines if line.startswith("warning: left out")]
                assert len(lines) == 1, done.stderr


@contextmanager
def _hostile_service(endpoint: str, answer: bytes) -> Iterator[zenoh.Session]:
    """A peer listening on ``endpoint`` that offers ``evil`` and answers its ``@info`` with
    ``answer``; its session."""
    with open_session(endpoint, listen=True) as rogue:
        token = rogue.liveliness().declare_token(KEYS.service_token("evil"))
        queryable = rogue.declare_queryable(KEYS.info("evil"), zenoh.handlers.FifoChannel(16))

        def serve() -> None:
            for query in queryable.handler:
                with query:
                    query.reply(KEYS.info("evil"), answer)

        thread = threading.Thread(target=serve, daemon=True)
        thread.start()
        try:
            yield rogue
        finally:
            queryable.undeclare()
            token.undeclare()
            thread.join(timeout=5)


@pytest.mark.parametrize("case", sorted(HOSTILE_INFO))
def test_info_of_a_hostile_service_is_one_error_line(endpoint: str, case: str) -> None:
    with _hostile_service(endpoint, HOSTILE_INFO[case]):
        done = run_framegate("info", "evil", "--connect", endpoint)
    lines = done.stderr.strip().splitlines()
    assert done.returncode == 1, done.stderr
    assert len(lines) == 1 and lines[0].startswith("error:"), done.stderr
    assert "Traceback" not in done.stderr


@contextmanager
def _hostile_data(endpoint: str, reply: Callable[[zenoh.Query], None]) -> Iterator[None]:
    """``evil/b`` described validly, its data queries answered by ``reply``."""
    body = json.dumps(_valid_description()).encode()
    # On the service's own session: declared before the CLI connects, it is there with it.
    with _hostile_service(endpoint, body) as rogue:
        queryable = rogue.declare_queryable(KEYS.data("evil", "b"), zenoh.handlers.Callback(reply))
        try:
            yield
        finally:
            queryable.undeclare()


def _element_reply(stamp: object) -> Callable[[zenoh.Query], None]:
    def reply(query: zenoh.Query) -> None:
        with query:
            head = msgpack.packb({"t": stamp, "m": make_metadata("generic", 5).decode()})
            query.reply(KEYS.data("evil", "b"), b"x", attachment=head)
            query.reply(KEYS.data("evil", "b"), b"", attachment=msgpack.packb({"end": 1}))

    return reply


def _error_reply(query: zenoh.Query) -> None:
    with query:
        query.reply_err(b"bad-query: \x1b[2J\x1b[31mowned\nerror: fake second line")


def _not_utf8_error_reply(query: zenoh.Query) -> None:
    with query:  # raised a ValueError out of Node.query (the mediator exited)
        query.reply_err(b"bad-query: \xff\xfe not UTF-8")


HOSTILE_REPLIES = {
    "an error reply that is not UTF-8": _not_utf8_error_reply,
    "a float stamp": _element_reply(1e300),
    "a negative stamp": _element_reply(-(2**63)),
    "a stamp of True": _element_reply(True),
    "an error reply with escapes and a newline": _error_reply,
}


@pytest.mark.parametrize("case", sorted(HOSTILE_REPLIES))
def test_query_of_a_hostile_reply_is_one_clean_error_line(endpoint: str, case: str) -> None:
    with _hostile_data(endpoint, HOSTILE_REPLIES[case]):
        done = run_framegate("query", "evil/b", "--connect", endpoint)
    lines = done.stderr.strip().splitlines()
    assert done.returncode == 1, done.stderr
    assert len(lines) == 1 and lines[0].startswith("error:"), done.stderr
    assert "\x1b" not in done.stderr and "Traceback" not in done.stderr, done.stderr


def _rogue_answers(rogue: zenoh.Session, how: str, seen: list[str]) -> zenoh.Queryable[None]:
    """``rogue`` also answers the data queries of cam/images: with an error, with 300
    elements to any query, or with the element stamped one before the one asked for; each
    query it answered goes into ``seen``."""

    def element(query: zenoh.Query, stamp: int) -> None:
        head = msgpack.packb({"t": stamp, "m": make_metadata("generic", stamp).decode()})
        query.reply(KEYS.data("cam", "images"), b"rogue", attachment=head)

    def reply(query: zenoh.Query) -> None:
        seen.append(str(query.selector))
        with query:
            if how == "error":
                query.reply_err(b"not-found: rogue says no")
                return
            asked = int(query.selector.parameters.get("ts") or 10**9)
            stamps = range(1, 301) if how == "many" else [asked - 1]
            for stamp in stamps:
                element(query, stamp)
            end = msgpack.packb({"end": len(stamps)})
            query.reply(KEYS.data("cam", "images"), b"", attachment=end)

    return rogue.declare_queryable(KEYS.data("cam", "images"), zenoh.handlers.Callback(reply))


@pytest.mark.parametrize("how", ["error", "many", "off by one"])
def test_a_second_session_answering_data_queries_cannot_void_or_swamp_them(
    listen_net: NetworkConfig, endpoint: str, how: str
) -> None:
    """Any session may answer a query: an error from another one does not void the service's
    answer, what it adds is bounded by what was asked (``last=1``, one element), and a fetch
    is of exactly the timestamp asked for."""
    with _cam_rogue_client(listen_net, endpoint) as (service, rogue, client):
        images = service.offer("images")
        for t in (1000, 2000, 3000):
            images.put(t, b"real", make_metadata("generic", t))
        seen: list[str] = []
        queryable = _rogue_answers(rogue, how, seen)
        try:

            def reached() -> bool:  # the rogue's queryable has reached the client
                with contextlib.suppress(FramegateError):
                    client.query("cam/images", last=1, timeout_s=scaled(2))
                return bool(seen)

            wait_until(reached, scaled(30), "the rogue to answer the client's queries")
            last = client.query("cam/images", last=1, timeout_s=scaled(5))
            assert [e.timestamp_ns for e in last if e.payload == b"real"] == [3000]
            assert len(last) <= 2  # the service's one, and at most one of the rogue's
            assert client.get("cam/images", 2000, timeout_s=scaled(5)).payload == b"real"
        finally:
            queryable.undeclare()
