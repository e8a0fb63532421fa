"""Liveliness queries that no number of tokens can hang: the one way framegate asks which
tokens are live (services, subscriptions).

Zenoh answers a liveliness query from what the session already knows of the network's
tokens, and delivers those replies on the *caller's* thread, inside ``get``, before the
caller holds the handler. With the default handler (a FIFO channel of 256) a 257th reply
waits for room that only the caller could make: the thread parks inside ``get`` for good,
past its timeout, and (a Python thread in Rust code) past Ctrl-C and SIGTERM. Any peer can
declare tokens: 300 under ``framegate/@svc/`` hung every ``echo``, ``watch``, ``record`` and
``play`` at start; 300 under a buffer's subscription key hung its producer's executor at
its next resync (after a churn), so it neither registered a subscriber nor stopped.

Here the replies go to a callback that keeps at most ``limit`` keys (never blocks) and the
caller waits on an event, with a deadline, which a signal interrupts.
"""

from __future__ import annotations

import threading

import zenoh

# Keys read from one liveliness query at most: a service name or a subscription token is
# at most 1,024 characters, so at most ~64 MiB of them; the rest are not read.
LIVE_KEYS = 65_536
# Beyond the query's timeout, how long to wait for Zenoh to say that it ended.
_END_SLACK_S = 1.0


def live_keys(
    session: zenoh.Session, keyexpr: str, *, timeout_s: float, limit: int = LIVE_KEYS
) -> list[str]:
    """The keys of the liveliness tokens matching ``keyexpr`` that answer within
    ``timeout_s`` (at most ``limit`` of them). Raises what ``get`` raises (``ZError``)."""
    return _ask(session, keyexpr, timeout_s, limit)[0]


def live_keys_whole(
    session: zenoh.Session, keyexpr: str, *, timeout_s: float, limit: int = LIVE_KEYS
) -> tuple[list[str], bool]:
    """``live_keys``, and whether the answer is whole: it ended within ``timeout_s`` with
    no error reply (a timeout is one) and ``get`` raised nothing (then: [], False). Who
    removes what a partial answer lacks would remove live tokens' owners."""
    try:
        return _ask(session, keyexpr, timeout_s, limit)
    except zenoh.ZError:
        return [], False


def _ask(
    session: zenoh.Session, keyexpr: str, timeout_s: float, limit: int
) -> tuple[list[str], bool]:
    keys: list[str] = []
    errors: list[bool] = []
    ended = threading.Event()

    def on_reply(reply: zenoh.Reply) -> None:
        if reply.ok is None:
            errors.append(True)
        elif len(keys) < limit:
            keys.append(str(reply.ok.key_expr))

    session.liveliness().get(
        keyexpr, zenoh.handlers.Callback(on_reply, ended.set, indirect=False), timeout=timeout_s
    )
    whole = ended.wait(timeout_s + _END_SLACK_S) and not errors
    return keys[:], whole
