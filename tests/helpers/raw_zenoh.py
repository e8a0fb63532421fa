"""A plain Zenoh session for tests that play a peer framegate does not control."""

from __future__ import annotations

import contextlib
import json
import threading
import time
from collections.abc import Callable, Iterable, Iterator, Sized
from contextlib import contextmanager
from typing import TypeVar

import zenoh

from tests.helpers.timing import scaled, wait_until

T = TypeVar("T")


def open_session(endpoint: str, *, listen: bool = False) -> zenoh.Session:
    """A peer session connected to ``endpoint`` (``listen``: listening on it), multicast
    scouting off."""
    conf = zenoh.Config()
    conf.insert_json5("mode", '"peer"')
    conf.insert_json5("scouting/multicast/enabled", "false")
    conf.insert_json5("listen/endpoints" if listen else "connect/endpoints", json.dumps([endpoint]))
    return zenoh.open(conf)


def reaching(session: zenoh.Session, key: str, what: str) -> zenoh.Publisher:
    """A publisher on ``key`` once a subscriber of it is reachable from ``session``. A peer
    session learns of the other peers' subscribers by gossip: on a loaded machine its first
    puts reached nobody for a while (a recorder counted none of a rogue's garbage)."""
    publisher = session.declare_publisher(key)
    wait_until(lambda: publisher.matching_status.matching, 30, what)
    return publisher


@contextmanager
def flooding_session(endpoint: str, *, listen: bool = False) -> Iterator[zenoh.Session]:
    """``open_session`` for a peer that floods with large replies: its close may time out
    (Zenoh's "close operation timed out") while replies it queued for a peer that has left
    are still unsent. That is the flooding peer's own business, not what a test checks."""
    session = open_session(endpoint, listen=listen)
    try:
        yield session
    finally:
        with contextlib.suppress(zenoh.ZError):
            session.close()


@contextmanager
def answering(
    session: zenoh.Session,
    keyexpr: str,
    replies: Callable[[str], Iterable[tuple[str, zenoh.ZBytes]]],
    tokens: Iterable[str] = (),
) -> Iterator[None]:
    """While open: ``session`` holds a liveliness token for each of ``tokens`` and answers
    every query on ``keyexpr`` with ``replies(the query's key)``, (key, payload) pairs, from
    a thread of its own."""
    held = [session.liveliness().declare_token(token) for token in tokens]
    queryable = session.declare_queryable(keyexpr, zenoh.handlers.FifoChannel(16))

    def serve() -> None:
        for query in queryable.handler:
            with query:
                for key, payload in replies(str(query.key_expr)):
                    query.reply(key, payload)

    thread = threading.Thread(target=serve, daemon=True)
    thread.start()
    try:
        yield
    finally:
        queryable.undeclare()
        for token in held:
            token.undeclare()
        thread.join(timeout=scaled(30))


def first_seen(call: Callable[[], T], seen: Sized, what: str) -> tuple[T, float]:
    """``call()`` repeated until a peer's queryable has seen one of its queries (``seen``
    grows), then its result and how long that call took. A queryable's declaration reaches
    the caller a moment after it is made: a call before then never met the peer, and is not
    the one a test measures."""
    deadline = time.monotonic() + scaled(30)
    while True:
        began = time.monotonic()
        result = call()
        took_s = time.monotonic() - began
        if len(seen):
            return result, took_s
        if time.monotonic() > deadline:
            raise AssertionError(f"the peer's queryable never saw {what}: the test proves nothing")
        time.sleep(0.05)
