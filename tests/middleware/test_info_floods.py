"""Answers to ``Node.services``' ``@info/*`` query beyond what a deployment gives: it reads
a bounded number of them, never waits past its deadline, and cannot be parked (real Zenoh
on loopback; the peers are raw sessions)."""

from __future__ import annotations

import threading

import pytest
import zenoh

from middleware import NetworkConfig, Node, ServiceInfo
from middleware._wire import Keys
from tests.helpers.timing import scaled

pytestmark = pytest.mark.integration

KEYS = Keys("framegate")


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
