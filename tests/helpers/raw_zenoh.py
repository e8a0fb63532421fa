"""A plain Zenoh session for tests that play a peer framegate does not control."""

from __future__ import annotations

import contextlib
import json
import threading
from collections.abc import Callable, Iterable, Iterator
from contextlib import contextmanager

import zenoh

from tests.helpers.timing import scaled


def open_session(endpoint: str, *, listen: bool = False) -> zenoh.Session:
    """A peer session connected to ``endpoint`` (``listen``: listening on it), multicast
    scouting off."""
    conf = zenoh.Config()
    conf.insert_json5("mode", '"peer"')
    conf.insert_json5("scouting/multicast/enabled", "false")
    conf.insert_json5("listen/endpoints" if listen else "connect/endpoints", json.dumps([endpoint]))
    return zenoh.open(conf)


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
