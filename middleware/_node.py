"""A Node owns one Zenoh session: it offers buffers (as a named service) and is a client.

with Node("camera") as node:                    # a service
    images = node.offer("images", kind="frame")
    images.put(t_ns, payload, metadata)

with Node() as node:                            # a client
    sub = node.subscribe("camera/images", queue_size=2)
    note = sub.take(timeout_s=1.0)
    frame = sub.fetch(note)
    recent = node.query("camera/images", time_range="[now(-2s)..]")

Timeouts, everywhere in the API: a blocking call takes ``timeout_s`` (seconds, float) as a
keyword-only argument. Asking the network what is live or how a buffer stands defaults to
1-2 s, fetching data to 5 s; ``Subscription.take`` waits for ever unless given one, and a
wait that a caller must bound (``Producer.wait_for_subscribers``) has no default.
"""

from __future__ import annotations

import difflib
import logging
import math
import threading
import time
from collections.abc import Iterator
from contextlib import contextmanager, suppress
from typing import Any

import zenoh

from ._clock import now_ns
from ._config import (
    ENDPOINT_FORM,
    RENDEZVOUS_WAIT_S,
    NetworkConfig,
    check_name,
    listening_endpoints,
    zenoh_message,
)
from ._decode import decode_service_info
from ._errors import (
    ConfigError,
    FramegateError,
    NotFoundError,
    QueryError,
    TransportError,
)
from ._loop import NodeLoop
from ._producer import HORIZON_NS, Producer
from ._records import (
    BufferInfo,
    DataObject,
    Retention,
    ServiceInfo,
    SubscriptionMode,
)
from ._rendezvous import announce, live_nodes, withdraw
from ._service import ServiceEndpoint, answering_sessions
from ._subscription import Subscription
from ._timerange import TimeRange
from ._wire import ERR_NOT_FOUND, Keys, decode_element
from ._xml import DEFAULT_LIMITS, XmlLimits

log = logging.getLogger("framegate.middleware")

_DEFAULT_INLINE_BYTES = 64 * 1024
# A fresh session needs a moment to learn the network's liveliness tokens and queryables;
# discovery asked earlier sees only part of it (measured: 2-3 of 4 services, through a router).
_SETTLE_S = 0.3


@contextmanager
def zenoh_errors(action: str) -> Iterator[None]:
    """The one place where zenoh.ZError becomes a framegate error."""
    try:
        yield
    except zenoh.ZError as exc:
        raise TransportError(f"{action} failed in Zenoh: {zenoh_message(exc)}") from exc


def split_target(target: str) -> tuple[str, str]:
    """``service/buffer`` → (service, buffer), with a message that says what is wrong."""
    parts = target.strip("/").split("/")
    if len(parts) != 2:
        raise QueryError(f"bad buffer name {target!r}: write SERVICE/BUFFER, e.g. camera/images")
    try:
        return check_name(parts[0], "service"), check_name(parts[1], "buffer")
    except ConfigError as exc:
        raise QueryError(str(exc)) from exc


class Node:
    """A process's presence on the framegate network. Use as a context manager."""

    def __init__(self, name: str | None = None, network: NetworkConfig | None = None) -> None:
        # The same FRAMEGATE_* variables as every command (see the README's table).
        self.network = network or NetworkConfig().with_env()
        self.name = check_name(name, "service") if name else None
        self.keys = Keys(self.network.namespace)
        opening = time.monotonic()
        local = self.network.uses_local_default
        expected = live_nodes(self.network.local_port) if local else 0
        # This session's own listeners are the ones that appear while it opens: the process
        # may listen for other nodes of other rendezvous too, which must not be announced.
        before = set(listening_endpoints()) if local else set()
        self._session = _open(self.network)
        if local:
            self._await_peers(expected, opening + RENDEZVOUS_WAIT_S)
        self._announced = (
            announce(
                self.network.local_port,
                [e for e in listening_endpoints() if e not in before],
            )
            if local
            else None
        )
        self._loop = NodeLoop(self.name or "client", on_stall=self._stalled)
        self._opened = time.monotonic()
        self._endpoint: ServiceEndpoint | None = None
        self._subscriptions: list[Subscription] = []
        self._lock = threading.Lock()
        self._closed = False

    # -- service side ----------------------------------------------------------------------
    def offer(
        self,
        buffer: str,
        *,
        kind: str = "generic",
        retention: Retention | None = None,
        inline_max_bytes: int = _DEFAULT_INLINE_BYTES,
        xml_limits: XmlLimits = DEFAULT_LIMITS,
        horizon_s: float = HORIZON_NS / 1e9,
    ) -> Producer:
        """Offer a named buffer ``<node name>/<buffer>`` holding metadata of ``kind``.

        ``put`` refuses elements stamped more than ``horizon_s`` ahead of this process's
        clock (``now_ns``), so one future stamp cannot stop its consumers' time order.
        """
        if self.name is None:
            raise ConfigError("only a named Node can offer buffers: Node('camera', ...)")
        check_name(buffer, "buffer")
        if not (math.isfinite(horizon_s) and horizon_s > 0):
            raise ConfigError(f"horizon_s must be a finite number of seconds > 0, got {horizon_s}")
        from ._xml import _schema  # a missing kind should fail here, not at the first put

        _schema(kind)
        if self._endpoint is None:
            self._settle()  # a fresh session must see the network before claiming a name
        with zenoh_errors(f"offering {self.name}/{buffer}"), self._lock:
            if self._endpoint is None:
                self._endpoint = ServiceEndpoint(self._session, self.keys, self.name)
            producer = Producer(
                self._session,
                self.keys,
                self.name,
                buffer,
                kind=kind,
                retention=retention or Retention(),
                inline_max_bytes=inline_max_bytes,
                xml_limits=xml_limits,
                loop=self._loop,
                horizon_ns=int(horizon_s * 1e9),
            )
            self._endpoint.add(producer)
        return producer

    # -- client side ------------------------------------------------------------------------
    def subscribe(
        self,
        target: str,
        *,
        queue_size: int = 2,
        mode: SubscriptionMode = SubscriptionMode.DEFAULT,
        wait_s: float = 2.0,
        push_max_bytes: int | None = None,
        await_service: bool = False,
    ) -> Subscription:
        """Subscribe to ``service/buffer`` notifications with a queue of ``queue_size``.

        Payloads up to ``push_max_bytes`` arrive with their notification (None: the
        producer's ``inline_max_bytes``, 64 KiB by default); larger ones are fetched by
        ``Subscription.fetch`` with one query. A consumer that takes every element (a
        detector) asks for everything pushed; one that picks some (an inspector) does not.
        Waits up to ``wait_s`` for a live producer to register the subscription.

        A service that is not live within ``wait_s`` is a NotFoundError naming the live
        ones (a misspelt name fails here, not silently later); with ``await_service=True``
        the subscription is returned anyway and registers when the service appears (a
        consumer started before its producer, as ``launch`` does).
        """
        service, buffer = split_target(target)
        if not await_service:
            self._await_live(service, wait_s)
        with zenoh_errors(f"subscribing to {target}"):
            sub = Subscription(
                self._session,
                self.keys,
                service,
                buffer,
                queue_size=queue_size,
                mode=mode,
                fetch=self._fetch_exact,
                prefetch=(self._start_exact, self._finish_exact),
                loop=self._loop,
                push_max_bytes=-1 if push_max_bytes is None else max(0, push_max_bytes),
                holder=self.name,
                on_close=self._forget,
                producer_ids=self._producer_ids,
            )
        with self._lock:
            self._subscriptions.append(sub)
        if wait_s > 0:
            self._wait_registered(sub, wait_s)
        return sub

    def _producer_ids(self, service: str) -> frozenset[str]:
        """The Zenoh sessions that answer as ``service`` (empty if none does)."""
        try:
            return answering_sessions(self._session, self.keys, service)
        except zenoh.ZError:
            return frozenset()

    def _forget(self, sub: Subscription) -> None:
        with self._lock:
            if sub in self._subscriptions:
                self._subscriptions.remove(sub)

    def _wait_registered(self, sub: Subscription, wait_s: float) -> None:
        """Wait for the producer's greeting; RegistrationRefused (the subscription closed)
        if it refused, NotFoundError if the live service still does not offer the buffer
        when ``wait_s`` is up (a service offers its buffers one after another). A service
        that is not live returns at once: the subscription registers when it appears."""
        deadline = time.monotonic() + wait_s
        missing: NotFoundError | None = None
        while time.monotonic() < deadline:
            if sub.needs_producer:  # a refusal counts only from the service's own session
                sub.trust_producer(self._producer_ids(sub.service))
            try:
                if sub.wait_registered(min(0.25, max(0.0, deadline - time.monotonic()))):
                    return
            except FramegateError:
                sub.close()
                raise
            if sub.service not in self.live_services(timeout_s=min(1.0, wait_s)):
                return
            try:
                self.buffer_info(sub.name, timeout_s=1.0)
                missing = None
            except NotFoundError as exc:
                missing = exc
            except FramegateError:
                pass
        if missing is not None:
            sub.close()
            raise missing

    def query(
        self,
        target: str,
        *,
        time_range: TimeRange | str | None = None,
        last: int | None = None,
        timeout_s: float = 5.0,
    ) -> list[DataObject]:
        """Elements of ``service/buffer`` in a time range (``TimeRange`` or a ``_time`` string
        such as ``[now(-2s)..]``) and/or the newest ``last``, in timestamp order."""
        params: dict[str, str] = {}
        if time_range is not None:
            params["_time"] = (
                time_range.to_selector_value() if isinstance(time_range, TimeRange) else time_range
            )
        if last is not None:
            params["last"] = str(last)
        return self._get(target, params, timeout_s)

    def get(self, target: str, timestamp_ns: int, *, timeout_s: float = 5.0) -> DataObject:
        """The element with exactly this timestamp; NotFoundError if there is none."""
        found = self._get(target, {"ts": str(timestamp_ns)}, timeout_s)
        if not found:
            raise NotFoundError(f"{target} has no element with timestamp {timestamp_ns}")
        return found[0]

    def nearest(self, target: str, timestamp_ns: int, *, timeout_s: float = 5.0) -> DataObject:
        """The element closest in time; NotFoundError if the buffer is empty."""
        found = self._get(target, {"at": str(timestamp_ns)}, timeout_s)
        if not found:
            raise NotFoundError(f"{target} is empty")
        return found[0]

    def latest(self, target: str, n: int = 1, *, timeout_s: float = 5.0) -> list[DataObject]:
        """The newest ``n`` elements, oldest first."""
        return self._get(target, {"last": str(n)}, timeout_s)

    def _fetch_exact(self, target: str, timestamp_ns: int, timeout_s: float) -> DataObject:
        return self.get(target, timestamp_ns, timeout_s=timeout_s)

    def _start_exact(self, target: str, timestamp_ns: int, timeout_s: float) -> Any:
        """Start fetching one element (returns at once; ``_finish_exact`` collects it)."""
        return self._start_get(target, {"ts": str(timestamp_ns)}, timeout_s)

    def _finish_exact(self, target: str, timestamp_ns: int, pending: Any) -> DataObject:
        found = self._collect(target, pending)
        if not found:
            raise NotFoundError(f"{target} has no element with timestamp {timestamp_ns}")
        return found[0]

    def _start_get(self, target: str, params: dict[str, str], timeout_s: float) -> Any:
        service, buffer = split_target(target)
        selector = zenoh.Selector(self.keys.data(service, buffer), params)
        with zenoh_errors(f"querying {target}"):
            return self._session.get(
                selector, consolidation=zenoh.ConsolidationMode.NONE, timeout=timeout_s
            )

    def _collect(self, target: str, replies: Any) -> list[DataObject]:
        elements: list[DataObject] = []
        with zenoh_errors(f"querying {target}"):
            for reply in replies:
                if reply.ok is not None:
                    sample = reply.ok
                    attachment = sample.attachment
                    elements.append(
                        decode_element(
                            sample.payload.to_bytes(),
                            attachment.to_bytes() if attachment is not None else None,
                        )
                    )
                else:
                    assert reply.err is not None
                    raise _error_from_reply(target, reply.err.payload.to_string())
        return elements

    def _get(self, target: str, params: dict[str, str], timeout_s: float) -> list[DataObject]:
        elements = self._collect(target, self._start_get(target, params, timeout_s))
        if not elements:
            self.buffer_info(target)  # NotFoundError, with a did-you-mean, if there is none
        elements.sort(key=lambda e: e.timestamp_ns)
        return elements

    # -- discovery -----------------------------------------------------------------------------
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

    def _require_service(self, service: str, advice: str = "") -> None:
        live = self.live_services()
        if service not in live:
            hint = difflib.get_close_matches(service, live, n=1)
            did_you_mean = f" (did you mean {hint[0]!r}?)" if hint else ""
            listing = ", ".join(live) if live else "none"
            raise NotFoundError(
                f"no live service named {service!r}{did_you_mean}; live services: {listing}"
                + advice
            )

    def services(self, *, timeout_s: float = 2.0) -> list[ServiceInfo]:
        """Every live service with its buffers, clock offset and round trip."""
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
            try:
                out.append(decode_service_info(raw, start, end, service=name))
            except QueryError as exc:
                log.debug("left out a service description: %s", exc)
                continue  # a peer that answers garbage is left out, not fatal
        return sorted(out, key=lambda s: s.service)

    def service_info(self, service: str, *, timeout_s: float = 2.0) -> ServiceInfo:
        """One live service's description; NotFoundError if it is not live."""
        start = now_ns()
        with zenoh_errors(f"describing {service}"):
            replies = list(self._session.get(self.keys.info(service), timeout=timeout_s))
        end = now_ns()
        for reply in replies:
            if reply.ok is not None:
                raw = reply.ok.payload.to_bytes()
                return decode_service_info(raw, start, end, service=service)
        self._require_service(service)
        raise NotFoundError(f"service {service!r} did not answer within {timeout_s} s")

    def buffer_info(self, target: str, *, timeout_s: float = 2.0) -> BufferInfo:
        """One buffer's description (retention, size, rate, subscriptions, counters)."""
        service, buffer = split_target(target)
        info = self.service_info(service, timeout_s=timeout_s)
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

    def _stalled(self, late_ns: int) -> None:
        """(the node's loop) The process did not run for ``late_ns``: say so, once."""
        lease_s = self.network.lease_ms / 1000
        if late_ns / 1e9 > lease_s:
            log.warning(
                "%s: this process did not run for %.1f s (stopped or suspended), longer than "
                "the %.1f s lease: peers dropped it; it reconnects and its subscriptions "
                "re-register by themselves",
                self.name or "client",
                late_ns / 1e9,
                lease_s,
            )

    # -- lifetime ---------------------------------------------------------------------------------
    def close(self) -> None:
        """Withdraw everything and close the Zenoh session.

        Always close: an open session with Python callbacks may keep the process from exiting.
        """
        if self._closed:
            return
        self._closed = True
        with self._lock:
            subs = list(self._subscriptions)
        for sub in subs:
            sub.close()
        if self._endpoint is not None:
            self._endpoint.close()
        self._loop.close()
        withdraw(self._announced)
        with suppress(zenoh.ZError):
            self._session.close()

    def __enter__(self) -> Node:
        return self

    def __exit__(self, *_exc: Any) -> None:
        self.close()


def _open(network: NetworkConfig) -> zenoh.Session:
    configs = network.zenoh_configs()
    last: Exception | None = None
    for conf in configs:
        try:
            return zenoh.open(conf)
        except zenoh.ZError as exc:
            last = exc
    where = ", ".join(network.connect or network.listen) or f"local port {network.local_port}"
    raise TransportError(
        f"cannot open a Zenoh session ({where}): {zenoh_message(last) if last else 'no config'}; "
        f"check the endpoints ({ENDPOINT_FORM}) and that each to listen on is free on this host"
    ) from last


def _error_from_reply(target: str, text: str) -> QueryError:
    if text.startswith(ERR_NOT_FOUND + ":"):
        return NotFoundError(text.split(":", 1)[1].strip())
    if text == "Timeout":
        return QueryError(f"query of {target} timed out; is the service overloaded or unreachable?")
    return QueryError(f"{target}: {text.split(':', 1)[1].strip() if ':' in text else text}")
