"""Reading buffers by time: the query API of a node (``Node.query``, ``get``, ``nearest``,
``latest``) and the exact fetches behind ``Subscription.fetch``.

``Queries`` is a part of ``Node`` (a base class): the methods here are the node's."""

from __future__ import annotations

import threading
import time
from collections import deque
from collections.abc import Callable, Iterator
from typing import Any

import zenoh

from ._decode import printable
from ._discovery import MAX_REPLIERS, Discovery, split_target
from ._errors import FramegateError, NotFoundError, QueryError
from ._records import DataObject
from ._service import END_MARK_BYTES, answer_end
from ._session import zenoh_errors
from ._timerange import TimeRange, parse_time_range
from ._wire import ERR_NOT_FOUND, decode_element

# Replies, and their payload bytes, an ``ask_query`` keeps at most (the rest is not read:
# the answer then reads as cut short, an error): any peer may answer a handler's question,
# and its answer must not hold unbounded memory until the query ends.
_ASK_REPLIES_MAX = 4096
_ASK_BYTES_MAX = 256 << 20
# How long a fetch started ahead, whose answer was empty, waits for its second ask.
_ASK_AGAIN_S = 2.0
# Replies of one session a fetch started ahead keeps: the element and its end mark, and
# room for an answer of a process that offers the buffer twice over a restart.
_FETCH_REPLIES = 4


class Queries(Discovery):
    """Elements of live buffers, by time (see ``Node``)."""

    def query(
        self,
        target: str,
        *,
        time_range: TimeRange | str | None = None,
        last: int | None = None,
        timeout_s: float = 5.0,
        session: str | None = None,
    ) -> list[DataObject]:
        """Elements of ``service/buffer`` in a time range (``TimeRange`` or a ``_time`` string
        such as ``[now(-2s)..]``) and/or the newest ``last``, in timestamp order.
        ``session``: only that Zenoh session's replies count (a subscription's
        ``producer_session``): a peer answering inside the range asked is not taken for the
        service. Not named, it is the one session that answers as the service, if one does.

        Any peer may answer: with a ``TimeRange``, an element outside it is no answer to the
        question and is left out (a peer's one element stamped an hour ahead became a
        recorder's newest, and every later one looked recorded already). A string's
        ``now()`` is the answering service's clock, unknown here: it is not checked."""
        params: dict[str, str] = {}
        if time_range is not None:
            params["_time"] = _time_value(time_range)
        if last is not None:
            params["last"] = str(last)
        elements = self._get(target, params, timeout_s, most=last, session=session)
        if isinstance(time_range, TimeRange):
            elements = [e for e in elements if time_range.contains(e.timestamp_ns)]
        return elements

    def ask_query(
        self,
        target: str,
        answer: Callable[[list[DataObject] | FramegateError], object],
        *,
        time_range: TimeRange | str,
        timeout_s: float = 5.0,
        session: str | None = None,
    ) -> None:
        """``query`` without waiting, for handlers: ``answer(elements)`` runs once on the
        node's executor when the query ends, ``answer(error)`` when it failed or was cut
        short. Asked once (``query`` asks again an answer that reached no one; a handler
        that needs the elements asks again itself, later). Only elements within the range
        asked, one per timestamp: any peer may answer, and a handler may act on each (the
        mediator records each frame it never saw). ``session``: only that Zenoh session's
        replies count (a subscription's ``producer_session``)."""
        asked = time_range if isinstance(time_range, TimeRange) else parse_time_range(time_range)
        replies: list[zenoh.Reply] = []
        kept_bytes = [0]
        once = threading.Lock()  # taken by the first of the two ends below, never released

        def on_reply(reply: zenoh.Reply) -> None:  # (Zenoh's thread) kept, decoded later
            if not _from(reply, session):
                return
            size = len(reply.ok.payload) if reply.ok is not None else 0
            if len(replies) < _ASK_REPLIES_MAX and kept_bytes[0] + size <= _ASK_BYTES_MAX:
                kept_bytes[0] += size
                replies.append(reply)
            # With ``session``, its end mark ends the answer (as in ``_answer``): a peer's
            # queryable that holds the query open does not hold the answer to its timeout.
            attachment = reply.ok.attachment if reply.ok is not None else None
            if (
                session is not None
                and attachment is not None
                and len(attachment) <= END_MARK_BYTES
                and answer_end(attachment.to_bytes()) is not None
            ):
                finished()

        def deliver(ended_ns: int) -> None:
            # Judged by when the query ended, not by when the executor got to it.
            timed_out = ended_ns / 1e9 >= deadline
            try:
                elements = self._answer(
                    target, replies, deadline=deadline if timed_out else None, timeout_s=timeout_s
                )[0]
            except FramegateError as exc:
                answer(exc)
                return
            within = {
                e.timestamp_ns: e for e in reversed(elements) if asked.contains(e.timestamp_ns)
            }
            answer([within[t] for t in sorted(within)])

        def finished() -> None:  # (Zenoh's thread) the query ended: replied or timed out
            if once.acquire(blocking=False):
                self._executor.schedule(deliver, time.monotonic_ns())

        handler = zenoh.handlers.Callback(on_reply, finished, indirect=False)
        deadline = time.monotonic() + timeout_s
        self._start_get(target, {"_time": _time_value(time_range)}, timeout_s, handler)

    def get(
        self, target: str, timestamp_ns: int, *, timeout_s: float = 5.0, session: str | None = None
    ) -> DataObject:
        """The element with exactly this timestamp; NotFoundError if there is none.
        ``session`` as for ``query``."""
        answer = self._get(target, {"ts": str(timestamp_ns)}, timeout_s, most=1, session=session)
        found = _exactly(answer, timestamp_ns)
        if found is None:
            raise NotFoundError(f"{target} has no element with timestamp {timestamp_ns}")
        return found

    def nearest(
        self, target: str, timestamp_ns: int, *, timeout_s: float = 5.0, session: str | None = None
    ) -> DataObject:
        """The element closest in time; NotFoundError if the buffer is empty. ``session``
        as for ``query``."""
        found = self._get(target, {"at": str(timestamp_ns)}, timeout_s, most=1, session=session)
        if not found:
            raise NotFoundError(f"{target} is empty")
        return found[0]

    def latest(self, target: str, n: int = 1, *, timeout_s: float = 5.0) -> list[DataObject]:
        """The newest ``n`` elements, oldest first (the owning session's: see ``_get``)."""
        return self._get(target, {"last": str(n)}, timeout_s, most=n)

    def _fetch_exact(
        self, target: str, timestamp_ns: int, timeout_s: float, session: str | None
    ) -> DataObject:
        return self.get(target, timestamp_ns, timeout_s=timeout_s, session=session)

    def _start_exact(
        self, target: str, timestamp_ns: int, timeout_s: float, session: str | None = None
    ) -> Collected:
        """Start fetching one element (returns at once; ``_finish_exact`` collects it).
        ``session``: only its replies are kept meanwhile (``Collected``)."""
        collected = Collected(session)
        handler = zenoh.handlers.Callback(collected.add, collected.end, indirect=False)
        self._start_get(target, {"ts": str(timestamp_ns)}, timeout_s, handler)
        return collected

    def _finish_exact(
        self, target: str, timestamp_ns: int, pending: Any, session: str | None = None
    ) -> DataObject:
        elements, answered = self._answer(target, pending, most=1, session=session)
        found = _exactly(elements, timestamp_ns)
        if found is None:
            if answered:
                raise NotFoundError(f"{target} has no element with timestamp {timestamp_ns}")
            # Started ahead, it reached no one (see ``_get``): asked again as ``get`` asks.
            return self.get(target, timestamp_ns, timeout_s=_ASK_AGAIN_S, session=session)
        return found

    def _start_get(
        self, target: str, params: dict[str, str], timeout_s: float, handler: Any = None
    ) -> Any:
        service, buffer = split_target(target)
        selector = zenoh.Selector(self.keys.data(service, buffer), params)
        with zenoh_errors(f"querying {target}"):
            return self._session.get(
                selector, handler, consolidation=zenoh.ConsolidationMode.NONE, timeout=timeout_s
            )

    def _ask(
        self, target: str, params: dict[str, str], timeout_s: float, session: str | None
    ) -> Any:
        """Start a query whose replies ``_answer`` reads. Asked of ``session``: its replies
        alone, taken as they come (``Collected``; all of them: what was asked for, read as it
        comes), others dropped at once. Its end mark ends the reading while a peer's
        queryable may still answer, and Zenoh's channel would hold those replies whole until
        the query's timeout. Of no session: Zenoh's channel, read to the end."""
        if session is None:
            return self._start_get(target, params, timeout_s)
        collected = Collected(session, None)
        handler = zenoh.handlers.Callback(collected.add, collected.end, indirect=False)
        self._start_get(target, params, timeout_s, handler)
        return collected

    def _answer(
        self,
        target: str,
        replies: Any,
        *,
        most: int | None = None,
        session: str | None = None,
        deadline: float | None = None,
        timeout_s: float = 0.0,
    ) -> tuple[list[DataObject], bool]:
        """The elements of an answer, and whether any service answered (its end mark came).

        QueryError if it was cut short: elements came but not the service's end mark
        counting them (``_service.encode_answer_end``), as when its link dropped while
        answering or the query's ``timeout_s`` (asked to end at the monotonic ``deadline``)
        passed first; the first part of an answer never reads as all of it. The error says
        which of the two it was: Zenoh ends the replies the same way for both, but only a
        timeout ends them at or after the deadline. No reply at all (no end mark) is a
        query that reached no one: see ``_get``.

        Any session may answer a query: ``most`` (what was asked for: ``last=N``, one
        element) bounds what each answering session adds, and an error reply counts only
        when no session answered (a peer replying "not found" to every query must not void
        the service's answer)."""
        elements: list[DataObject] = []
        kept: dict[str | None, int] = {}
        error: str | None = None
        answered = False
        # Per answering session (two may answer at once, their replies interleaved: a
        # producer and its restarted self, or a process's own buffer beside a peer's): the
        # elements since its last end mark, and whether a mark disagreed with its count
        # (one mark per buffer answered, counting its own).
        since: dict[str | None, int] = {}
        short: set[str | None] = set()
        with zenoh_errors(f"querying {target}"):
            for reply in replies:
                if not _from(reply, session):
                    continue  # not the session asked for: read nothing of it
                if reply.ok is not None:
                    who = reply.replier_id
                    replier = None if who is None else str(who)
                    sample = reply.ok
                    attachment = sample.attachment
                    raw = attachment.to_bytes() if attachment is not None else None
                    end = answer_end(raw)
                    if end is not None:
                        if end != since.get(replier, 0):
                            short.add(replier)
                        since[replier], answered = 0, True
                        if session is not None:
                            # The one session asked for has answered (one buffer, one end
                            # mark): any other queryable on the key may hold the query open
                            # to its timeout, a peer that never finalizes it for nothing, and
                            # every fetch waited that long (5 s: a mediator fetching frames
                            # fell from 15 to 0-2 frames/s and throttled the camera).
                            break
                        continue
                    since[replier] = since.get(replier, 0) + 1
                    if most is not None and kept.get(replier, 0) >= most:
                        continue  # more than was asked for: not read
                    kept[replier] = kept.get(replier, 0) + 1
                    elements.append(decode_element(sample.payload.to_bytes(), raw))
                else:
                    assert reply.err is not None
                    if error is None:
                        # Any bytes (a peer's): not UTF-8 is read, replaced, not raised.
                        error = reply.err.payload.to_bytes().decode("utf-8", "replace")
        if error is not None and not elements and not answered:
            raise _error_from_reply(target, error)
        complete = not short and not any(since.values())
        if elements and not complete and deadline is not None and time.monotonic() >= deadline:
            # A slow answer (a long range, a service without CPU on a busy machine) is no
            # dropped link: said as one, the user asked again with the same timeout in vain.
            raise QueryError(
                f"the answer from {target} ended early ({len(elements)} elements, no end "
                f"mark): the query's timeout ({timeout_s:g} s) passed before its service had "
                "answered all of it (a long range, or a busy machine); ask again with a "
                "longer timeout or a shorter range"
            )
        if elements and not complete:
            raise QueryError(
                f"the answer from {target} ended early ({len(elements)} elements, no end "
                "mark): its service's link dropped while answering (a process without CPU "
                "past its lease, or one that exited); ask again"
            )
        return elements, answered

    def _get(
        self,
        target: str,
        params: dict[str, str],
        timeout_s: float,
        *,
        most: int | None = None,
        session: str | None = None,
    ) -> list[DataObject]:
        deadline = time.monotonic() + timeout_s
        if session is None:
            # Not named: the session that answers as the service is its owner, asked for its
            # answer alone (as a subscription's fetches are), so its end mark ends the query.
            # Waiting for every queryable on the key instead, a peer that takes each query
            # and never finalizes it held every query, latest and backfill to its timeout.
            # None (no one, or more than one, answers as it): every reply counts, as before.
            session = self.service_session(split_target(target)[0])
        replies = self._ask(target, params, timeout_s, session)
        elements, answered = self._answer(
            target, replies, most=most, session=session, deadline=deadline, timeout_s=timeout_s
        )
        if not elements:
            # NotFoundError, with a did-you-mean, if there is none; asked with the caller's
            # patience (a loaded machine's service answers late, and is not "gone" for it).
            self.buffer_info(target, timeout_s=timeout_s)
            # No end mark: the query reached no one (the service's lease lapsed for a
            # moment; Zenoh then answers with nothing, not an error). Asked once more.
            left_s = deadline - time.monotonic()
            if not answered and left_s > 0:
                replies = self._ask(target, params, left_s, session)
                elements = self._answer(
                    target,
                    replies,
                    most=most,
                    session=session,
                    deadline=deadline,
                    timeout_s=timeout_s,
                )[0]
        elements.sort(key=lambda e: e.timestamp_ns)
        return elements


class Collected:
    """The replies of a fetch started ahead, kept on Zenoh's thread until it is collected
    (an iterable for ``_answer``, ending with the query). A Zenoh channel held every reply
    whole until then: a peer answering each fetch of a subscription that fetches ahead with
    40 replies of 16 MiB grew the subscriber from 93 MB to 1.36 GB. So: with ``session``
    (the producer's), only its replies are kept, at most ``_FETCH_REPLIES`` (an element and
    its end mark); without, at most ``_FETCH_REPLIES`` of each of ``MAX_REPLIERS`` sessions
    and ``_ASK_BYTES_MAX`` in all. The rest are dropped as they come, never held.
    ``per_replier`` None (a query asked of ``session``, read as it comes: ``_ask``): all of
    that session's replies, what was asked of it.

    Threads: ``add`` and ``end`` run on Zenoh's threads, iterating on the fetching one;
    ``_cond`` guards the replies."""

    def __init__(self, session: str | None, per_replier: int | None = _FETCH_REPLIES) -> None:
        self._session = session
        self._most = per_replier
        self._cond = threading.Condition()
        self._replies: deque[zenoh.Reply] = deque()
        self._per_replier: dict[str, int] = {}
        self._bytes = 0
        self._ended = False

    def add(self, reply: zenoh.Reply) -> None:
        if not _from(reply, self._session):
            return
        who = str(reply.replier_id.zid) if reply.replier_id is not None else "?"
        size = len(reply.ok.payload) if reply.ok is not None else 0
        with self._cond:
            count = self._per_replier.get(who)
            if count is None and len(self._per_replier) >= MAX_REPLIERS:
                return
            if self._most is not None and (count or 0) >= self._most:
                return
            if self._session is None and self._bytes + size > _ASK_BYTES_MAX:
                return
            self._per_replier[who] = (count or 0) + 1
            self._bytes += size
            self._replies.append(reply)
            self._cond.notify()

    def end(self) -> None:
        with self._cond:
            self._ended = True
            self._cond.notify()

    def __iter__(self) -> Iterator[zenoh.Reply]:
        while True:
            with self._cond:
                while not self._replies and not self._ended:
                    self._cond.wait()
                if not self._replies:
                    return
                reply = self._replies.popleft()
            yield reply


def _time_value(time_range: TimeRange | str) -> str:
    """A ``_time`` selector value (a ``TimeRange`` or already a string)."""
    return time_range.to_selector_value() if isinstance(time_range, TimeRange) else time_range


def _exactly(elements: list[DataObject], timestamp_ns: int) -> DataObject | None:
    """The element stamped ``timestamp_ns`` among an answer's (another is a peer's)."""
    return next((e for e in elements if e.timestamp_ns == timestamp_ns), None)


def _error_from_reply(target: str, raw: str) -> QueryError:
    text = printable(raw)  # a peer's words: one line, no terminal escapes
    if text.startswith(ERR_NOT_FOUND + ":"):
        return NotFoundError(text.split(":", 1)[1].strip())
    if text == "Timeout":
        return QueryError(f"query of {target} timed out; is the service overloaded or unreachable?")
    return QueryError(f"{target}: {text.split(':', 1)[1].strip() if ':' in text else text}")


def _from(reply: zenoh.Reply, session: str | None) -> bool:
    """Whether ``reply`` counts when only ``session``'s replies do (None: every one does)."""
    return session is None or (
        reply.replier_id is not None and str(reply.replier_id.zid) == session
    )
