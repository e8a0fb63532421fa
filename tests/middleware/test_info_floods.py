"""Answers to ``Node.services``' ``@info/*`` query beyond what a deployment gives: it reads
a bounded number of them, never waits past its deadline, and cannot be parked (real Zenoh
on loopback; the peers are raw sessions)."""

from __future__ import annotations

import json
import threading
from collections.abc import Iterator
from contextlib import contextmanager

import pytest
import zenoh

from middleware import FramegateError, NetworkConfig, Node, ServiceInfo
from middleware._info_intake import MAX_DESCRIPTIONS, TOKENLESS_DESCRIPTIONS
from middleware._wire import Keys
from tests.helpers.raw_zenoh import answering, flooding_session, open_session
from tests.helpers.timing import scaled, wait_until

pytestmark = pytest.mark.integration

KEYS = Keys("framegate")


def connect(endpoint: str) -> NetworkConfig:
    return NetworkConfig(connect=(endpoint,))


def _services_ends(node: Node, invalid: list[str]) -> list[ServiceInfo]:
    """``node.services()`` run on a daemon thread, which must end: its result."""
    out: list[list[ServiceInfo]] = []
    thread = threading.Thread(
        target=lambda: out.append(node.services(timeout_s=scaled(2), invalid=invalid)),
        daemon=True,
    )
    thread.start()
    thread.join(scaled(30))
    assert out, "services() never ended"
    return out[0]


def test_queryables_of_the_asking_session_cannot_park_services(listen_net: NetworkConfig) -> None:
    """Zenoh runs the queryables of the asking session on the asking thread, inside ``get``,
    and delivers what they reply there: 40 such replies into the 16-reply channel the query
    used parked ``services()`` inside ``get`` for good."""
    with Node("real", listen_net) as node:
        node.offer("b")
        session = node._session

        def answerer(key: str) -> zenoh.handlers.Callback[zenoh.Query]:
            def answer(query: zenoh.Query) -> None:
                with query:
                    query.reply(key, b"{}")

            return zenoh.handlers.Callback(answer, indirect=False)

        keys = [KEYS.info(f"local{i}") for i in range(40)]
        queryables = [session.declare_queryable(key, answerer(key)) for key in keys]
        try:
            invalid: list[str] = []
            services = _services_ends(node, invalid)
        finally:
            for queryable in queryables:
                queryable.undeclare()
    assert [s.service for s in services] == ["real"]
    assert invalid  # each local reply is named as no description


FLOOD = 200  # made-up services, each answering with a valid description


def _description_of(endpoint: str, service: str) -> bytes:
    """``service``'s own ``@info`` reply, as a peer reads it."""
    with open_session(endpoint) as peer:

        def ask() -> bytes | None:
            for reply in peer.get(KEYS.info(service), timeout=scaled(2)):
                if reply.ok is not None:
                    return reply.ok.payload.to_bytes()
            return None

        return wait_until(ask, 20, f"{service}'s description")


def _renamed(raw: bytes, name: str) -> bytes:
    body = json.loads(raw)
    body["service"] = name
    for buffer in body["buffers"]:
        buffer["service"] = name
    return json.dumps(body).encode()


@contextmanager
def _made_up(endpoint: str, template: bytes, *, tokens: bool) -> Iterator[None]:
    """A raw peer answering ``@info/*`` with ``FLOOD`` valid descriptions (``template``
    renamed ``fake000`` ...); ``tokens``: it holds a liveliness token for each as well."""
    blobs = [
        (f"fake{i:03d}", zenoh.ZBytes(_renamed(template, f"fake{i:03d}"))) for i in range(FLOOD)
    ]
    held = [KEYS.service_token(n) for n, _ in blobs] if tokens else []
    replies = [(KEYS.info(name), blob) for name, blob in blobs]
    with (
        flooding_session(endpoint) as rogue,
        answering(rogue, KEYS.info("*"), lambda _k: replies, held),
    ):
        yield


def test_a_flood_of_made_up_descriptions_cannot_push_out_a_real_service(
    listen_net: NetworkConfig, endpoint: str
) -> None:
    """200 valid descriptions of made-up services (no liveliness token): every one was
    decoded and kept (100 of 2.4 MB took ``ls`` 12-20 s); now at most
    ``TOKENLESS_DESCRIPTIONS`` of them are, and the real service is listed."""
    with Node("real", listen_net) as real:
        real.offer("b")
        template = _description_of(endpoint, "real")
        with _made_up(endpoint, template, tokens=False), Node(network=connect(endpoint)) as client:
            wait_until(lambda: "real" in client.live_services(), 20, "the real service's token")
            invalid: list[str] = []
            services = _services_ends(client, invalid)
    names = [s.service for s in services]
    assert "real" in names
    assert len(names) == 1 + TOKENLESS_DESCRIPTIONS, names
    assert any("holding no liveliness token" in line for line in invalid), invalid


def test_descriptions_kept_stay_at_the_cap_when_made_up_services_hold_tokens(
    listen_net: NetworkConfig, endpoint: str
) -> None:
    """The same flood, each made-up name also holding a token: at most ``MAX_DESCRIPTIONS``
    descriptions are kept, and the rest named in one line."""
    with Node("real", listen_net) as real:
        real.offer("b")
        template = _description_of(endpoint, "real")
        with _made_up(endpoint, template, tokens=True), Node(network=connect(endpoint)) as client:
            wait_until(lambda: len(client.live_services()) > FLOOD, 20, "the made-up tokens")
            invalid: list[str] = []
            services = _services_ends(client, invalid)
    assert len(services) == MAX_DESCRIPTIONS
    assert any(f"beyond the {MAX_DESCRIPTIONS}" in line for line in invalid), invalid


def test_queryables_of_the_asking_session_cannot_park_service_info(
    listen_net: NetworkConfig,
) -> None:
    """The same for one service's description (``info``, ``ls``'s clock samples): 40 replies
    of the asking session's own queryables on ``@info/real`` parked ``service_info`` in
    ``get`` for good; now it ends, with what it made of them."""
    with Node("real", listen_net) as node:
        node.offer("b")
        key = KEYS.info("real")

        def answer(query: zenoh.Query) -> None:
            with query:
                query.reply(key, b"{}")

        queryables = [
            node._session.declare_queryable(key, zenoh.handlers.Callback(answer, indirect=False))
            for _ in range(40)
        ]
        out: list[object] = []

        def ask() -> None:
            try:
                out.append(node.service_info("real", timeout_s=scaled(2)))
            except FramegateError as exc:
                out.append(exc)

        try:
            thread = threading.Thread(target=ask, daemon=True)
            thread.start()
            thread.join(scaled(30))
        finally:
            for queryable in queryables:
                queryable.undeclare()
    assert out, "service_info() never ended"
