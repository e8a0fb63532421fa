"""Finding services on the network: what is live, what each offers (its ``@info``).

``Discovery`` is a part of ``Node`` (a base class): the methods here are the node's."""

from __future__ import annotations

import difflib
import time
from collections.abc import Callable
from contextlib import suppress

import zenoh

from ._clock import now_ns
from ._config import NetworkConfig, check_name
from ._decode import decode_service_info
from ._errors import ConfigError, NotFoundError, QueryError
from ._executor import Executor
from ._records import BufferInfo, ServiceInfo
from ._service import answering_sessions
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

    def live_services(self, *, timeout_s: float = 1.0) -> list[str]:
        """Names of services whose liveliness token is visible now."""
        self._settle()
        prefix = self.keys.service_token("")
        with zenoh_errors("listing live services"):
            replies = self._session.liveliness().get(
                self.keys.service_token("*"), timeout=timeout_s
            )
            names = [str(r.ok.key_expr)[len(prefix) :] for r in replies if r.ok is not None]
        return sorted(set(names))

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
            listing = ", ".join(live) if live else "none"
            raise NotFoundError(
                f"no live service named {service!r}{did_you_mean}; live services: {listing}"
                + advice
            )

    def services(
        self, *, timeout_s: float = 2.0, invalid: list[str] | None = None
    ) -> list[ServiceInfo]:
        """Every live service with its buffers, clock offset and round trip. A service whose
        description is not valid is left out; ``invalid`` receives the one-line reason."""
        self._settle()
        out: list[ServiceInfo] = []
        start = now_ns()
        with zenoh_errors("describing services"):
            replies = list(
                self._session.get(
                    self.keys.info("*"),
                    consolidation=zenoh.ConsolidationMode.NONE,
                    timeout=timeout_s,
                )
            )
        end = now_ns()
        for reply in replies:
            if reply.ok is None:
                continue
            raw = reply.ok.payload.to_bytes()
            name = str(reply.ok.key_expr).rsplit("/", 1)[-1]
            try:  # a peer that answers garbage is left out, not fatal
                out.append(decode_service_info(raw, start, end, service=name))
            except QueryError as exc:
                if invalid is not None:
                    invalid.append(str(exc))
        return sorted(out, key=lambda s: s.service)

    def service_info(
        self, service: str, *, timeout_s: float = 2.0, unambiguous: bool = False
    ) -> ServiceInfo:
        """One live service's description; NotFoundError if it is not live.

        ``unambiguous``: for a decision that must not rest on a peer's word (a clock sample
        that may remove elements): QueryError when more than one Zenoh session answers as
        ``service`` (any peer can answer, and Zenoh would pass on only the newest answer)."""
        start = now_ns()
        consolidation = zenoh.ConsolidationMode.NONE if unambiguous else None
        with zenoh_errors(f"describing {service}"):
            replies = list(
                self._session.get(
                    self.keys.info(service), timeout=timeout_s, consolidation=consolidation
                )
            )
        end = now_ns()
        if unambiguous:
            _one_replier(replies, service)
        for reply in replies:
            if reply.ok is not None:
                raw = reply.ok.payload.to_bytes()
                return decode_service_info(raw, start, end, service=service)
        self._require_service(service, timeout_s=timeout_s)
        raise NotFoundError(f"service {service!r} did not answer within {timeout_s} s")

    def ask_service_info(
        self,
        service: str,
        answer: Callable[[ServiceInfo | None], object],
        *,
        timeout_s: float = 2.0,
    ) -> None:
        """Ask for one service's description without waiting for it: ``answer(info)``
        runs once on the node's executor when the query ends, with None when no valid
        description came within ``timeout_s``. For handlers: ``service_info`` there would
        hold up every other handler of the node for a round trip (100-250 ms measured on
        a loaded 2-core machine)."""
        start = now_ns()
        # (Zenoh's thread) only the first reply is kept, with when it came: the round trip
        # that bounds the clock sample's error. It is decoded on the executor. Every reply
        # is asked for (no consolidation): a description that more than one session gives
        # (any peer can answer as any service) is no answer (``service_info``'s unambiguous).
        first: list[tuple[bytes, int]] = []
        repliers: set[str] = set()

        def on_reply(reply: zenoh.Reply) -> None:
            if reply.ok is None:
                return
            if reply.replier_id is not None and len(repliers) <= 1:
                repliers.add(str(reply.replier_id.zid))
            if not first:
                first.append((reply.ok.payload.to_bytes(), now_ns()))

        def deliver(_now_ns: int) -> None:
            info = None
            if first and len(repliers) <= 1:
                raw, end = first[0]
                with suppress(QueryError):
                    info = decode_service_info(raw, start, end, service=service)
            answer(info)

        def finished() -> None:  # (Zenoh's thread) the query ended: replied or timed out
            self._executor.schedule(deliver, time.monotonic_ns())

        handler = zenoh.handlers.Callback(on_reply, finished, indirect=False)
        with zenoh_errors(f"describing {service}"):
            self._session.get(
                self.keys.info(service),
                handler,
                timeout=timeout_s,
                consolidation=zenoh.ConsolidationMode.NONE,
            )

    def _producer_ids(self, service: str) -> frozenset[str]:
        """The Zenoh sessions that answer as ``service`` (empty if none does): whose
        refusals a subscription trusts."""
        try:
            return answering_sessions(self._session, self.keys, service)
        except zenoh.ZError:
            return frozenset()

    def buffer_info(
        self, target: str, *, timeout_s: float = 2.0, unambiguous: bool = False
    ) -> BufferInfo:
        """One buffer's description (retention, size, rate, subscriptions, counters);
        ``unambiguous`` as for ``service_info``."""
        service, _buffer = split_target(target)
        info = self.service_info(service, timeout_s=timeout_s, unambiguous=unambiguous)
        return buffer_of(info, target)


def _one_replier(replies: list[zenoh.Reply], service: str) -> None:
    """QueryError unless at most one Zenoh session gave a description in ``replies``."""
    sessions = {str(r.replier_id.zid) for r in replies if r.ok is not None and r.replier_id}
    if len(sessions) > 1:
        raise QueryError(
            f"{len(sessions)} Zenoh sessions answer as {service!r}: its description is not "
            "trusted (another process, or a peer, answers in its name)"
        )


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
