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
caller waits on an event, with a deadline, which a signal interrupts; or, an executor, it
does not wait at all and reads the answer when Zenoh says the query ended (``LiveQuery``).
"""

from __future__ import annotations

import threading
import time
from collections.abc import Callable

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
    query = LiveQuery(session, keyexpr, timeout_s=timeout_s, limit=limit)
    if query.error is not None:
        raise query.error
    query.wait()
    return query.answer()[0]


class LiveQuery:
    """One liveliness query in flight. Its replies are kept on Zenoh's thread (at most
    ``limit`` keys, never blocking); ``on_end`` runs there once Zenoh says that it ended.
    A waiter (``wait``) or an executor (``done`` at ``deadline_ns`` at the latest) then
    reads the ``answer``. A ``get`` that raised (``error``) is done at once, not whole."""

    def __init__(
        self,
        session: zenoh.Session,
        keyexpr: str,
        *,
        timeout_s: float,
        limit: int = LIVE_KEYS,
        on_end: Callable[[], object] | None = None,
    ) -> None:
        self._keys: list[str] = []
        self._error_reply = False
        self._ended = threading.Event()
        self._timeout_s = timeout_s
        self.deadline_ns = time.monotonic_ns() + int((timeout_s + _END_SLACK_S) * 1e9)

        def on_reply(reply: zenoh.Reply) -> None:
            if reply.ok is None:
                self._error_reply = True
            elif len(self._keys) < limit:
                self._keys.append(str(reply.ok.key_expr))

        def ended() -> None:
            self._ended.set()
            if on_end is not None:
                on_end()

        self.error: zenoh.ZError | None = None
        try:
            session.liveliness().get(
                keyexpr, zenoh.handlers.Callback(on_reply, ended, indirect=False), timeout=timeout_s
            )
        except zenoh.ZError as exc:  # e.g. the session is closing: an answer that is not whole
            self.error = exc
            self.deadline_ns = 0

    def wait(self) -> None:
        self._ended.wait(self._timeout_s + _END_SLACK_S)

    def done(self, now_ns: int) -> bool:
        return self._ended.is_set() or now_ns >= self.deadline_ns

    def answer(self) -> tuple[list[str], bool]:
        """The keys so far, and whether they are whole (the query ended, no error)."""
        whole = self._ended.is_set() and not self._error_reply and self.error is None
        return self._keys[:], whole
