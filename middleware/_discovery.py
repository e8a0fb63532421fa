"""Finding services on the network: what is live, what each offers (its ``@info``).

``Discovery`` is a part of ``Node`` (a base class): the methods here are the node's."""

from __future__ import annotations

import difflib
import threading
import time
from collections.abc import Callable, Iterator
from contextlib import suppress

import zenoh

from ._clock import now_ns
from ._config import NetworkConfig, check_name
from ._decode import MAX_REPLY_BYTES, listing
from ._errors import ConfigError, NotFoundError, QueryError
from ._executor import Executor
from ._info_codec import decode_service_info
from ._info_intake import InfoIntake, ask, heard_end
from ._liveliness import live_keys
from ._records import BufferInfo, ServiceInfo
from ._service import answering_sessions, offered
from ._session import zenoh_errors
from ._wire import Keys

# A fresh session needs a moment to learn the network's liveliness tokens and queryables;
# discovery asked earlier sees only part of it (measured: 2-3 of 4 services, through a router).
_SETTLE_S = 0.3


def split_target(target: str) -> tuple[str, str]:
    """``service/buffer`` → (service, buffer), with a message that says what is wrong."""
    parts = target.strip("/").split("/")
    if len(parts) != 2:
        raise QueryError(f"bad buffer name {target!r}: write SERVICE/BUFFER, e.g. camera/images")
    try:
        return check_name(parts[0], "service"), check_name(parts[1], "buffer")
    except ConfigError as exc:
        raise QueryError(str(exc)) from exc


# A description query that ended at once unanswered is asked again after this long.
_ASK_AGAIN_S = 0.1


class Discovery:
    """What a node asks the network about services (see ``Node``)."""

    network: NetworkConfig
    keys: Keys
    _session: zenoh.Session
    _opened: float
    _executor: Executor

    def _await_peers(self, expected: int, deadline: float) -> None:
        """Return once the session is connected to ``expected`` peers (every other live
        process of the rendezvous), or at ``deadline``: discovery asked earlier would miss
        the services of a peer still connecting."""
        while time.monotonic() < deadline:
            with suppress(zenoh.ZError):
                if len(list(self._session.info.peers_zid())) >= expected:
                    return
            time.sleep(0.005)

    def _settle(self) -> None:
        if self.network.uses_local_default:
            return  # the constructor waited for every peer (_await_peers)
        time.sleep(max(0.0, self._opened + _SETTLE_S - time.monotonic()))

    def live_subscriptions(self, target: str, *, timeout_s: float = 1.0) -> int:
        """How many subscriptions of ``service/buffer`` are live now (their liveliness
        tokens), registered by its producer or not yet: what a publisher that must not
        start before its listeners (``framegate pub``, as ``ros2 topic pub``) waits for."""
        self._settle()
        service, buffer = split_target(target)
        with zenoh_errors(f"listing the subscriptions of {target}"):
            keyexpr = self.keys.subscription_tokens(service, buffer)
            return len(live_keys(self._session, keyexpr, timeout_s=timeout_s))

    def live_services(self, *, timeout_s: float = 1.0) -> list[str]:
        """Names of services whose liveliness token is visible now."""
        self._settle()
        prefix = self.keys.service_token("")
        with zenoh_errors("listing live services"):
            keys = live_keys(self._session, self.keys.service_token("*"), timeout_s=timeout_s)
            names = [key[len(prefix) :] for key in keys]
        return sorted(set(names))

    def offered_services(self, names: list[str], *, timeout_s: float = 1.0) -> list[str]:
        """Those of ``names`` offered now by a live service, as a service's own start judges
        it: a holder of the name's token that answers as that service. A bare liveliness token
        (any peer can declare one) gets a one-line warning and does not count, so that a
        launch or a demo refuses to start only where its service itself would."""
        live = set(self.live_services(timeout_s=timeout_s))
        with zenoh_errors("asking who offers the services"):
            return [
                name for name in names if name in live and offered(self._session, self.keys, name)
            ]

    def live_namespaces(self, *, timeout_s: float = 1.0) -> dict[str, list[str]]:
        """The live services of every namespace this node can see, its own included
        (to tell "nothing is live" from "live under another namespace")."""
        self._settle()
        found: dict[str, set[str]] = {}
        with zenoh_errors("listing live namespaces"):
            for key in live_keys(self._session, Keys("*").service_token("*"), timeout_s=timeout_s):
                namespace, _svc, service = key.split("/", 2)
                found.setdefault(namespace, set()).add(service)
        return {ns: sorted(names) for ns, names in sorted(found.items())}

    def connected(self) -> int:
        """How many other Zenoh sessions (peers and routers) this node is connected to now:
        0 means nothing answered at all, which a command tells from "nothing is live"."""
        with zenoh_errors("listing connected sessions"):
            info = self._session.info
            return len(list(info.peers_zid())) + len(list(info.routers_zid()))

    def _await_live(self, service: str, wait_s: float) -> None:
        """Return once ``service`` is live; NotFoundError (as ``_require_service``) if it is
        not within ``wait_s`` (a service being started is given that long)."""
        deadline = time.monotonic() + wait_s
        while time.monotonic() < deadline:
            if service in self.live_services(timeout_s=min(1.0, max(0.1, wait_s))):
                return
            time.sleep(0.05)
        self._require_service(
            service, " (to subscribe before it starts: subscribe(..., await_service=True))"
        )

    def _require_service(self, service: str, advice: str = "", *, timeout_s: float = 1.0) -> None:
        live = self.live_services(timeout_s=timeout_s)
        if service not in live:
            hint = difflib.get_close_matches(service, live, n=1)
            did_you_mean = f" (did you mean {hint[0]!r}?)" if hint else ""
            raise NotFoundError(
                f"no live service named {service!r}{did_you_mean}; "
                f"live services: {listing(live)}" + advice
            )

    def services(
        self, *, timeout_s: float = 2.0, invalid: list[str] | None = None
    ) -> list[ServiceInfo]:
        """Every live service with its buffers, clock offset and round trip. A service whose
        description is not valid is left out; ``invalid`` receives the one-line reason. At
        most ``MAX_DESCRIPTIONS`` descriptions are read, none decoded after ``timeout_s``
        (``_info_intake``); ``invalid`` says how many were left out so."""
        self._settle()
        out: list[ServiceInfo] = []
        start = now_ns()
        deadline = time.monotonic() + timeout_s
        # Who holds a token: answered from what the session knows, at once (see _info_intake).
        # Ends once every token holder's name has answered (``every_live``), not when every
        # queryable on ``@info/*`` has: a peer's may hold the query open to its timeout.
        intake = InfoIntake(deadline, self.live_services(timeout_s=timeout_s), every_live=True)

        with zenoh_errors("describing services"):
            ask(self._session, self.keys.info("*"), intake, timeout_s=timeout_s)
        while (kept := intake.take()) is not None:
            try:  # a peer that answers garbage is left out, not fatal
                out.append(decode_service_info(kept.raw, start, kept.arrived_ns, service=kept.name))
            except QueryError as exc:
                if invalid is not None:
                    invalid.append(str(exc))
        if invalid is not None:
            invalid.extend(intake.reasons())
        return sorted(out, key=lambda s: s.service)

    def service_info(
        self,
        service: str,
        *,
        timeout_s: float = 2.0,
        unambiguous: bool = False,
        session: str | None = None,
    ) -> ServiceInfo:
        """One live service's description; NotFoundError if it is not live.

        ``unambiguous``: for a decision that must not rest on a peer's word (a clock sample
        that may remove elements): QueryError when more than one Zenoh session answers with
        a valid description of ``service`` (any peer can answer, and Zenoh would pass on only
        the newest answer). ``session``: stricter, only that Zenoh session's answer counts
        (a subscription's ``producer_session``). A reply that is no valid description
        counts for nothing. Without ``session``, the answers that came by as long again
        after the first (``heard_end``) are read, not those of the query's timeout.

        A query that ended at once with no answer while the service's token is live is
        asked again until the timeout: its queryable may not be known here yet (a service
        that just started: its token came first) or it was busy."""
        began = time.monotonic()
        left_s = timeout_s
        while (found := self._service_info_once(service, left_s, unambiguous, session)) is None:
            left_s = began + timeout_s - time.monotonic() - _ASK_AGAIN_S
            if left_s <= _ASK_AGAIN_S:
                raise NotFoundError(
                    f"service {service!r} ended every query without an answer for "
                    f"{time.monotonic() - began:.1f} s (busy: it drops queries beyond its "
                    "inbox)"
                )
            time.sleep(_ASK_AGAIN_S)
        return found

    def _service_info_once(
        self, service: str, timeout_s: float, unambiguous: bool, session: str | None
    ) -> ServiceInfo | None:
        """One query of ``service_info``; None if it ended at once unanswered."""
        start, began = now_ns(), time.monotonic()
        answers = Answers(service, start)  # bounded: each session's first reply
        ended = threading.Event()

        heard: list[float] = []  # when the first answer came (no ``session``: see below)

        def on_reply(reply: zenoh.Reply) -> None:  # (Zenoh's thread, or this one) never waits
            answers.add(reply, now_ns())
            if session is not None and session in answers:
                ended.set()  # the one answer that counts came (see ``ask_service_info``)
            elif not heard and answers:
                heard.append(time.monotonic())

        # A callback, never a bounded channel: Zenoh delivers the replies of this session's
        # own queryables on this thread, inside ``get``, and a full channel parks it for good.
        with zenoh_errors(f"describing {service}"):
            self._session.get(
                self.keys.info(service),
                zenoh.handlers.Callback(on_reply, ended.set, indirect=False),
                consolidation=zenoh.ConsolidationMode.NONE,
                timeout=timeout_s,
            )
        # Named no session, it ends soon after the first answer (``heard_end``), not when
        # every queryable on the key has: a peer's that takes each query and never ends it
        # held ``info``, and every CLI look-up of a service, to the timeout.
        ends = began + timeout_s + _END_SLACK_S
        while not ended.is_set() and (now := time.monotonic()) < ends:
            if heard:
                ends = min(ends, heard_end(began, heard[0]))
            ended.wait(min(ends - now, _HEARD_POLL_S))
        if session is not None:
            found = answers.of_session(session)
        else:
            found = answers.trusted() if unambiguous else answers.first_valid()
        if found is not None:
            return found
        if answers:
            answers.first_error()  # raises: what was wrong with what came
        self._require_service(service, timeout_s=timeout_s)
        elapsed = time.monotonic() - began
        if elapsed < timeout_s * 0.9:
            # Ended before the timeout with nothing: the service finalized it unanswered
            # (its bounded inbox of queries was full), it did not time out.
            return None
        raise NotFoundError(f"service {service!r} did not answer within {timeout_s} s")

    def ask_service_info(
        self,
        service: str,
        answer: Callable[[ServiceInfo | None], object],
        *,
        timeout_s: float = 2.0,
        session: str | None = None,
    ) -> None:
        """Ask for one service's description without waiting for it: ``answer(info)``
        runs once on the node's executor when the query ends, with None when no valid
        description came within ``timeout_s``, or valid ones from more than one session
        (``service_info``'s unambiguous). ``session``: only that Zenoh session's answer
        counts (a subscription's ``producer_session``: a peer answering in the service's
        name while the service's own answer is late is not taken for it). For handlers:
        ``service_info`` there would hold up every other handler of the node for a round
        trip (100-250 ms measured on a loaded 2-core machine)."""
        # (Zenoh's thread) each session's first reply is kept with when it came (the round
        # trip that bounds a clock sample's error), and decoded on the executor: a peer
        # that answers garbage beside the service does not void its answer.
        answers = Answers(service, now_ns())
        once = threading.Lock()  # taken by the first of the two ends below, never released

        def on_reply(reply: zenoh.Reply) -> None:
            answers.add(reply, now_ns())
            # With ``session``, its answer is the only one that counts: delivered as it
            # comes. Any other queryable on the key may hold the query open to its timeout
            # (a peer that never ends it), and every clock sample of the mediator came that
            # much late: 17 frames skipped clock-unmeasured after each restart.
            if session is not None and session in answers:
                finished()

        def deliver(_now_ns: int) -> None:
            try:
                info = answers.trusted() if session is None else answers.of_session(session)
            except QueryError:
                info = None
            answer(info)

        def finished() -> None:  # (Zenoh's thread) the query ended: replied or timed out
            if once.acquire(blocking=False):
                self._executor.schedule(deliver, time.monotonic_ns())

        handler = zenoh.handlers.Callback(on_reply, finished, indirect=False)
        with zenoh_errors(f"describing {service}"):
            self._session.get(
                self.keys.info(service),
                handler,
                timeout=timeout_s,
                consolidation=zenoh.ConsolidationMode.NONE,
            )

    def service_session(self, service: str) -> str | None:
        """The one Zenoh session that answers as ``service`` (None: none does, or more than
        one: any peer can answer in a service's name), for ``query(session=)``."""
        ids = self._producer_ids(service)
        return next(iter(ids)) if len(ids) == 1 else None

    def _producer_ids(self, service: str) -> frozenset[str]:
        """The Zenoh sessions that answer as ``service`` (empty if none does): whose
        refusals a subscription trusts."""
        try:
            return answering_sessions(self._session, self.keys, service)
        except zenoh.ZError:
            return frozenset()

    def buffer_info(
        self,
        target: str,
        *,
        timeout_s: float = 2.0,
        unambiguous: bool = False,
        session: str | None = None,
    ) -> BufferInfo:
        """One buffer's description (retention, size, rate, subscriptions, counters);
        ``unambiguous`` and ``session`` as for ``service_info``."""
        service, _buffer = split_target(target)
        info = self.service_info(
            service, timeout_s=timeout_s, unambiguous=unambiguous, session=session
        )
        return buffer_of(info, target)


# Beyond a query's timeout, how long to wait for Zenoh to say that it ended.
_END_SLACK_S = 1.0
# How often ``service_info`` looks whether its first answer has come (its wait's step).
_HEARD_POLL_S = 0.02
# Sessions whose answers to one ``@info`` query are kept; one more makes the answers
# ambiguous (a crowd of rogue repliers could otherwise push the real one out unseen).
MAX_REPLIERS = 8


class Answers:
    """The answers to one ``@info`` query: each replying session's first reply, with when
    it came; which of them count is decided when the query has ended (``trusted``)."""

    def __init__(self, service: str, start_ns: int) -> None:
        self.service = service
        self.start_ns = start_ns
        self._first: dict[str, tuple[bytes, int]] = {}
        self._turned_away = 0  # replies of further sessions, not kept

    def add(self, reply: zenoh.Reply, end_ns: int) -> None:
        """(any thread) Keep ``reply`` if it is its session's first (bounded, undecoded)."""
        if reply.ok is None:
            return
        replier = str(reply.replier_id.zid) if reply.replier_id is not None else "?"
        if replier in self._first:
            return
        if len(self._first) >= MAX_REPLIERS:
            self._turned_away += 1
        elif len(reply.ok.payload) <= MAX_REPLY_BYTES:
            self._first[replier] = (reply.ok.payload.to_bytes(), end_ns)

    def __len__(self) -> int:
        return len(self._first)

    def __contains__(self, session: object) -> bool:
        """Whether ``session`` answered (its first reply is kept)."""
        return session in self._first

    def _decoded(self) -> Iterator[ServiceInfo | QueryError]:
        for raw, end_ns in self._first.values():
            try:
                yield decode_service_info(raw, self.start_ns, end_ns, service=self.service)
            except QueryError as exc:
                yield exc

    def first_valid(self) -> ServiceInfo | None:
        """The first valid description among the answers (None: none is valid)."""
        return next((d for d in self._decoded() if isinstance(d, ServiceInfo)), None)

    def first_error(self) -> None:
        """Raise what was wrong with the first answer that is no valid description."""
        for decoded in self._decoded():
            if isinstance(decoded, QueryError):
                raise decoded

    def of_session(self, session: str) -> ServiceInfo | None:
        """``session``'s valid description of the service (None: it gave none)."""
        if session not in self._first:
            return None
        raw, end_ns = self._first[session]
        try:
            return decode_service_info(raw, self.start_ns, end_ns, service=self.service)
        except QueryError:
            return None

    def trusted(self) -> ServiceInfo | None:
        """The one valid description of the service among the answers (None: none came);
        QueryError when more than one session gave one, or more sessions answered than are
        kept. A reply that is no valid description of the service counts for nothing."""
        if self._turned_away:
            raise QueryError(
                f"more than {MAX_REPLIERS} Zenoh sessions answer as {self.service!r}: its "
                "description is not trusted (peers answer in its name)"
            )
        valid = [d for d in self._decoded() if isinstance(d, ServiceInfo)]
        if len(valid) > 1:
            raise QueryError(
                f"{len(valid)} Zenoh sessions answer as {self.service!r}: its description is "
                "not trusted (another process, or a peer, answers in its name)"
            )
        return valid[0] if valid else None


def buffer_of(info: ServiceInfo, target: str) -> BufferInfo:
    """The buffer of ``target`` in its service's answer ``info``; NotFoundError naming what
    the service offers."""
    service, buffer = split_target(target)
    for candidate in info.buffers:
        if candidate.buffer == buffer:
            return candidate
    names = [b.buffer for b in info.buffers]
    hint = difflib.get_close_matches(buffer, names, n=1)
    did_you_mean = f" (did you mean {hint[0]!r}?)" if hint else ""
    offered = ", ".join(names) or "none"
    raise NotFoundError(
        f"service {service!r} has no buffer {buffer!r}{did_you_mean}; it offers: {offered}"
    )
