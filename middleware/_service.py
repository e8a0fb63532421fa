"""Serving a process's buffers: one queryable for elements, one for the service description.

Queries are answered on one thread per service (``fg-serve-<service>``), never on Zenoh's
own threads, nor on the node's executor (a handler that runs long there, a camera's render
or a slow vision function, must not hold up the answers). Zenoh's callback only appends a
query to a bounded inbox (``QueryInbox``) and wakes that thread, which otherwise sleeps: an
idle service costs no wake-ups here. Every malformed query gets an error reply
(``code: message``) and the thread keeps serving.

One producer per name: before declaring its token, an endpoint asks whether the service is
live elsewhere and refuses, naming that instance's host and pid (a restarted service whose
old instance is dead finds no token and takes over). Two instances started at the same
moment can both pass that check; right after declaring, each asks again and the younger one
(later ``started_ns``, then larger instance id) withdraws with the same error. A token counts
as "offered elsewhere" only when its holder answers as that service (a valid ``@info``
description naming it, decoded by ``_info_codec``): a bare liveliness token, or one whose holder
answers garbage, gets a one-line warning naming the token, and the service starts.
"""

from __future__ import annotations

import contextlib
import difflib
import logging
import os
import secrets
import socket
import threading
import time
from collections import deque
from collections.abc import Callable, Iterator
from typing import Any, cast

import msgpack
import zenoh

from ._buffer import TimeSeries
from ._clock import CLOCK, now_ns
from ._config import listening_endpoints
from ._errors import FramegateError, NameTakenError, NotFoundError, QueryError
from ._inbox import pin_thread_state
from ._info_codec import decode_instance, encode_service_info
from ._info_intake import InfoIntake, Kept, ask
from ._liveliness import live_keys
from ._producer import Producer
from ._records import DataObject, ServiceInfo
from ._timerange import parse_time_range
from ._wire import ERR_BAD_QUERY, ERR_NOT_FOUND, Keys, encode_element_attachment, error_text

log = logging.getLogger("framegate.middleware")

# Selector parameters a data query may use.
_PARAMS = {"_time", "last", "at", "ts"}

# The last reply of every data answer: an empty payload whose attachment is the msgpack map
# {"end": number of elements sent}. When the answering service's link drops in the middle of
# an answer (its lease lapsed: a process without CPU for over a second on a loaded machine),
# Zenoh ends the query as if every reply had come, with no error; without this mark the
# querier would take the first part of an answer for all of it. An element's attachment is a
# map of two ("t", "m"), so it never starts with these bytes.
_END_PREFIX = b"\x81\xa3end"


def encode_answer_end(count: int) -> bytes:
    """The attachment of an answer's last reply: ``count`` elements came before it."""
    return _END_PREFIX + bytes(msgpack.packb(count))


def answer_end(attachment: bytes | None) -> int | None:
    """How many elements an answer sent, if ``attachment`` is its end mark (else None)."""
    if attachment is None or not attachment.startswith(_END_PREFIX):
        return None
    with contextlib.suppress(ValueError, TypeError, msgpack.UnpackException):
        count = msgpack.unpackb(attachment[len(_END_PREFIX) :])
        if isinstance(count, int) and count >= 0:
            return count
    return None


def answer(series: TimeSeries, parameters: dict[str, str]) -> list[DataObject]:
    """The elements a data query asks for. QueryError names what is malformed."""
    unknown = set(parameters) - _PARAMS
    if unknown:
        raise QueryError(
            f"unknown query parameter(s) {', '.join(sorted(unknown))}; "
            "use _time=[a..b], last=N, at=<ns> (nearest) or ts=<ns> (exact)"
        )
    if "at" in parameters or "ts" in parameters:
        if len(parameters) != 1:
            raise QueryError("at= and ts= stand alone; do not combine them with other parameters")
        name = "at" if "at" in parameters else "ts"
        timestamp = _int_param(parameters, name)
        found = series.nearest(timestamp) if name == "at" else series.exact(timestamp)
        return [found] if found is not None else []
    last = _int_param(parameters, "last") if "last" in parameters else None
    if last is not None and last < 1:
        raise QueryError(f"last={last}: ask for at least 1 element")
    if "_time" in parameters:
        rng = parse_time_range(parameters["_time"])
        return series.range(rng.start_ns, rng.end_ns, last=last)
    return series.range(last=last if last is not None else None)


def _int_param(parameters: dict[str, str], name: str) -> int:
    raw = parameters[name]
    try:
        return int(raw)
    except ValueError as exc:
        raise QueryError(f"{name}={raw!r} is not an integer") from exc


# How long the checks for another live instance wait for answers.
_CLAIM_TIMEOUT_S = 1.0
# Beyond a query's timeout, how long to wait for Zenoh to say that it ended.
_END_SLACK_S = 1.0


def _instances(
    session: zenoh.Session, keys: Keys, service: str, *, busy: bool = False
) -> list[dict[str, Any]]:
    """Descriptions of every instance that answers as ``service`` (empty if none is live, or
    if its token's holder does not answer as that service: then a warning names the token).
    ``busy``: a holder that gives no description but answers data queries of the service's
    buffers as a service does is one too, busy (``{"session": id}``: its inbox of ``@info``
    queries was full, as in a flood of them; a bare token answers neither).

    The descriptions are asked whether or not the token was seen: a fresh session's look at
    the tokens came back empty at once in 2 of 20 tries (7 under a flood) while the live
    instance answered, and a second instance started beside it."""
    token = keys.service_token(service)
    held = bool(live_keys(session, token, timeout_s=_CLAIM_TIMEOUT_S, limit=1))
    found: list[dict[str, Any]] = []
    for kept in _described(session, keys, service, held=held):
        try:
            found.append(decode_instance(kept.raw, service))
        except QueryError as exc:
            log.debug("%s: an answer that does not count as an instance: %s", service, exc)
    if found:
        return found
    if busy and (answering := _answers_data(session, keys, service)) is not None:
        return [{"session": answering}]
    if held:
        log.warning(
            "the liveliness token %s is held by a session that does not answer as %r; "
            "starting anyway",
            token,
            service,
        )
    return []


def _described(session: zenoh.Session, keys: Keys, service: str, *, held: bool) -> Iterator[Kept]:
    """The replies to ``service``'s ``@info`` query, through the bounded intake of every
    ``@info`` read (``_info_intake``): a peer may answer with any number of replies of any
    size, and read through Zenoh's default channel (256 replies, each held whole) 300 replies
    of 4 MiB held a starting service 3.9 s at 545 MB. ``held``: its token is live (else its
    answers count as those of a token-less name). Ends by the query's deadline."""
    intake = InfoIntake(time.monotonic() + _CLAIM_TIMEOUT_S, [service] if held else [])
    ask(session, keys.info(service), intake, timeout_s=_CLAIM_TIMEOUT_S)
    while (kept := intake.take()) is not None:
        yield kept
    for reason in intake.reasons():
        log.debug("%s: answers left out: %s", service, reason)


# An answer end's attachment is a few bytes; a reply's larger attachment is not read.
END_MARK_BYTES = 64


def _answers_data(session: zenoh.Session, keys: Keys, service: str) -> str | None:
    """The Zenoh session whose data query of ``service``'s buffers (for no element) gets a
    service's answer end (None: none): a data query waits in its own inbox, which a flood of
    ``@info`` does not fill. Replies go to a callback that keeps only the first such session
    (a peer may answer with any number of replies of any size)."""
    found: list[str] = []
    ended = threading.Event()

    def on_reply(reply: zenoh.Reply) -> None:  # (Zenoh's thread, or this one) never waits
        attachment = reply.ok.attachment if reply.ok is not None else None
        if found or attachment is None or len(attachment) > END_MARK_BYTES:
            return
        if answer_end(attachment.to_bytes()) is not None:
            who = reply.replier_id
            found.append(str(who.zid) if who is not None else "unknown")
            ended.set()  # one is enough: a peer that never ends the query does not hold it

    session.get(
        f"{keys.service_data(service)}?ts=0",
        zenoh.handlers.Callback(on_reply, ended.set, indirect=False),
        consolidation=zenoh.ConsolidationMode.NONE,
        timeout=_CLAIM_TIMEOUT_S,
    )
    ended.wait(_CLAIM_TIMEOUT_S + _END_SLACK_S)
    return found[0] if found else None


def offered(session: zenoh.Session, keys: Keys, service: str) -> bool:
    """Whether ``service`` is offered now as its own start judges it (``_instances``): a
    session answers as it, or is a busy one; a bare liveliness token is not (a warning)."""
    return bool(_instances(session, keys, service, busy=True))


def answering_sessions(session: zenoh.Session, keys: Keys, service: str) -> frozenset[str]:
    """The Zenoh session ids that answer as ``service`` (a valid description naming it):
    whose control messages a subscriber of its buffers trusts."""
    ids: set[str] = set()
    for kept in _described(session, keys, service, held=True):
        if not kept.replier:
            continue  # a sender Zenoh does not name is no one to trust
        try:
            decode_instance(kept.raw, service)
        except QueryError:
            continue
        ids.add(kept.replier)
    return frozenset(ids)


def _taken(service: str, other: dict[str, Any]) -> NameTakenError:
    if "pid" not in other:  # see ``_instances``
        return NameTakenError(
            f"service {service!r} is already offered by Zenoh session {other['session']} (it "
            "answers for its buffers but not, now, for its description: it is busy); stop "
            "that instance first, or choose another name"
        )
    return NameTakenError(
        f"service {service!r} is already offered by pid {other.get('pid')} on host "
        f"{other.get('host')}; stop that instance first, or choose another name"
    )


# An ``@info`` answer reads the process's listeners (a scan of its sockets: 8.0 of the
# answer's 8.2 ms, measured) at most this often: listeners open with the session, and at
# 40 queries/s a flood of them kept a loaded camera's answers from its mediator's clock.
_LISTEN_FRESH_NS = 5_000_000_000


# Queries waiting to be answered, per queryable. Beyond, an arriving query is finalized
# unanswered (its querier sees an empty answer, as after a lost reply, and a framegate
# querier asks again) and counted: a peer that asks faster than the service answers loses
# its excess, and while it floods, an honest query may be among what is dropped; what is
# already waiting is answered.
DATA_QUERIES = 256
INFO_QUERIES = 64
# A query's payload, attachment and selector parameters together, at most: framegate's
# queries carry no payload or attachment and a few short parameters (``_time=[a..b]``), and a
# waiting query holds all of it, so 256 queries with 4 MB payloads each, sent faster than a
# 16 MB answer goes out, grew a producer from 57 to 411 MB (parameters of any length go as
# well). A larger one is finalized unanswered and counted as an overflow is.
QUERY_BODY_MAX_BYTES = 1024


class QueryInbox:
    """The queries of a service's two queryables, appended by Zenoh's callbacks and taken by
    its serving thread; bounded, and the only thing Zenoh's threads do here."""

    def __init__(self) -> None:
        self._cond = threading.Condition()
        self._waiting: dict[str, deque[zenoh.Query]] = {"data": deque(), "info": deque()}
        self._capacity = {"data": DATA_QUERIES, "info": INFO_QUERIES}
        self._order = ("info", "data")  # whose turn is first; they alternate
        self.dropped = 0
        self.closed = False

    def callback(self, which: str) -> zenoh.handlers.Callback[zenoh.Query]:
        """A direct callback (on the Zenoh thread that received the query) for ``which``."""
        waiting, capacity = self._waiting[which], self._capacity[which]

        def on_query(query: zenoh.Query) -> None:
            pin_thread_state()
            too_large = _body_bytes(query) > QUERY_BODY_MAX_BYTES  # (a copy: not under the lock)
            with self._cond:
                if self.closed:
                    return
                if len(waiting) >= capacity or too_large:
                    self.dropped += 1  # finalized when dropped: its querier's answer ends
                    return
                waiting.append(query)
                self._cond.notify()

        return zenoh.handlers.Callback(on_query, indirect=False)

    def take(self) -> tuple[str, zenoh.Query] | None:
        """The next query, data and info in turn (a flood of one kind cannot hold up the
        other); None once closed. Sleeps until one comes."""
        with self._cond:
            while not self.closed:
                for which in self._order:
                    if self._waiting[which]:
                        self._order = self._order[::-1] if which == self._order[0] else self._order
                        return which, self._waiting[which].popleft()
                self._cond.wait()
            return None

    def close(self) -> None:
        with self._cond:
            self.closed = True
            for waiting in self._waiting.values():
                waiting.clear()
            self._cond.notify_all()


def _body_bytes(query: zenoh.Query) -> int:
    """What ``query`` carries beside its key: payload, attachment and selector parameters."""
    payload, attachment = query.payload, query.attachment
    return (
        (len(payload) if payload is not None else 0)
        + (len(attachment) if attachment is not None else 0)
        + len(str(query.parameters))
    )


class ServiceEndpoint:
    """The Zenoh face of a named service: token, data queryable and info queryable.

    Threads: one serving thread (``fg-serve-*``) answers the queries that Zenoh's callbacks
    left in the ``QueryInbox``. ``_lock`` guards the producer table only; no Zenoh call is
    made while holding it.
    """

    def __init__(self, session: zenoh.Session, keys: Keys, service: str) -> None:
        self.service = service
        self._keys = keys
        self._producers: dict[str, Producer] = {}
        self._lock = threading.Lock()
        self.instance = secrets.token_hex(6)
        self.started_ns = now_ns()
        others = _instances(session, keys, service, busy=True)
        if others:
            raise _taken(service, others[0])
        self._token = session.liveliness().declare_token(keys.service_token(service))
        self._queries = QueryInbox()
        self._data = session.declare_queryable(
            keys.service_data(service), self._queries.callback("data")
        )
        self._info = session.declare_queryable(keys.info(service), self._queries.callback("info"))
        self._handlers: dict[str, Callable[[zenoh.Query], None]] = {
            "data": self._on_data,
            "info": self._on_info,
        }
        # (``_on_info``, on the serve thread) what the process listens on, and until when.
        self._listen: tuple[str, ...] = ()
        self._listen_until_ns = 0
        self._thread = threading.Thread(target=self._serve, daemon=True, name=f"fg-serve-{service}")
        self._thread.start()
        mine = (self.started_ns, self.instance)
        for other in _instances(session, keys, service):
            started, instance = other["started_ns"], other["instance"]
            # The older instance keeps the name.
            if (started, instance) != mine and (started, instance) < mine:
                self.close()
                raise _taken(service, other)

    def add(self, producer: Producer) -> None:
        with self._lock:
            if producer.buffer in self._producers:
                raise FramegateError(
                    f"buffer {self.service}/{producer.buffer} is already offered by this process"
                )
            self._producers[producer.buffer] = producer

    def producers(self) -> list[Producer]:
        with self._lock:
            return list(self._producers.values())

    def _serve(self) -> None:
        while (taken := self._queries.take()) is not None:
            which, query = taken
            handle = self._handlers[which]
            with query:
                try:
                    handle(query)
                except NotFoundError as exc:
                    _reply_err(query, error_text(ERR_NOT_FOUND, str(exc)))
                except FramegateError as exc:
                    _reply_err(query, error_text(ERR_BAD_QUERY, str(exc)))
                except Exception as exc:  # never let one query kill the service
                    log.exception("%s: query %s failed", self.service, query.selector)
                    _reply_err(query, error_text(ERR_BAD_QUERY, f"internal error: {exc}"))

    def _on_data(self, query: zenoh.Query) -> None:
        key = zenoh.KeyExpr(str(query.key_expr))
        matches = [
            p for p in self.producers() if key.intersects(self._keys.data(self.service, p.buffer))
        ]
        if not matches:
            buffers = sorted(p.buffer for p in self.producers())
            asked = str(query.key_expr).rsplit("/", 1)[-1]
            close = difflib.get_close_matches(asked, buffers, n=1)
            hint = f" (did you mean {close[0]!r}?)" if close else ""
            raise NotFoundError(
                f"service {self.service!r} has no buffer {asked!r}{hint}; "
                f"it offers: {', '.join(buffers) or 'none'}"
            )
        # The stub types Parameters.__iter__ oddly; it yields (key, value) pairs.
        parameters = dict(cast(Any, query.parameters))
        for producer in matches:
            reply_key = self._keys.data(self.service, producer.buffer)
            elements = answer(producer.series, parameters)
            for element in elements:
                query.reply(
                    reply_key, element.payload, attachment=encode_element_attachment(element)
                )
            query.reply(reply_key, b"", attachment=encode_answer_end(len(elements)))

    def _on_info(self, query: zenoh.Query) -> None:
        now = time.monotonic_ns()
        if now >= self._listen_until_ns:
            self._listen = tuple(listening_endpoints())  # so `framegate ls` shows a wide one
            self._listen_until_ns = now + _LISTEN_FRESH_NS
        info = ServiceInfo(
            service=self.service,
            host=socket.gethostname(),
            pid=os.getpid(),
            clock_ns=now_ns(),
            buffers=tuple(p.info() for p in self.producers()),
            listen=self._listen,
            threads=tuple(sorted(t.name for t in threading.enumerate())),  # docs/threads.md
            dropped_queries=self._queries.dropped,
        )
        body = encode_service_info(
            info, CLOCK.status(), instance=self.instance, started_ns=self.started_ns
        )
        query.reply(self._keys.info(self.service), body)

    def close(self) -> None:
        for producer in self.producers():
            producer.close()
        for entity in (self._data, self._info, self._token):
            with contextlib.suppress(zenoh.ZError):
                entity.undeclare()
        self._queries.close()
        if self._thread is not threading.current_thread():
            self._thread.join(timeout=2.0)


def _reply_err(query: zenoh.Query, text: str) -> None:
    try:
        query.reply_err(text.encode("utf-8"))
    except zenoh.ZError:
        log.warning("could not send error reply: %s", text)
