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

import logging
import math
import os
import threading
import time
from collections.abc import Callable
from contextlib import suppress
from typing import Any

import zenoh

from ._config import RENDEZVOUS_WAIT_S, NetworkConfig, check_name, listening_endpoints
from ._discovery import buffer_of, split_target
from ._errors import ConfigError, FramegateError, NotFoundError
from ._executor import BUDGET, STALL_NS, Executor, Timer
from ._producer import HORIZON_NS, Producer
from ._query import Queries
from ._records import Retention, SubscriptionMode
from ._rendezvous import announce, live_nodes, withdraw
from ._service import ServiceEndpoint
from ._session import open_session, zenoh_errors
from ._subscription import Handler, Subscription
from ._wire import Keys
from ._xml import DEFAULT_LIMITS, XmlLimits

log = logging.getLogger("framegate.middleware")

_DEFAULT_INLINE_BYTES = 64 * 1024
# How often ``spin`` looks whether the node closed or a handler failed.
_SPIN_SLICE_S = 0.25


class Node(Queries):
    """A process's presence on the framegate network. Use as a context manager.

    Its parts: offering buffers and subscribing (here), the executor that runs what is
    registered on it (``on`` / ``every`` / ``at`` / ``spin``, here; ``_executor``), reading
    buffers by time (``Queries``, ``_query``) and finding services (``Discovery``,
    ``_discovery``)."""

    def __init__(self, name: str | None = None, network: NetworkConfig | None = None) -> None:
        # The same FRAMEGATE_* variables as every command (docs/networking.md's table).
        self.network = network or NetworkConfig().with_env()
        self.name = check_name(name, "service") if name else None
        self.keys = Keys(self.network.namespace)
        opening = time.monotonic()
        local = self.network.uses_local_default
        expected = live_nodes(self.network.local_port) if local else 0
        # This session's own listeners are the ones that appear while it opens: the process
        # may listen for other nodes of other rendezvous too, which must not be announced.
        before = set(listening_endpoints()) if local else set()
        self._session = open_session(self.network)
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
        self._executor = Executor(self.name or "client", on_stall=self._stalled)
        self._opened = time.monotonic()
        self._endpoint: ServiceEndpoint | None = None
        self._subscriptions: list[Subscription] = []
        self._lock = threading.Lock()
        self._stalled_until_ns = 0  # when the last stall said ended (``_stalled``)
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
                executor=self._executor,
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
        ack_each_take: bool = False,
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
        consumer started before its producer, as ``launch`` does). ``ack_each_take``: each
        take is acked at once, never coalesced (a take that means "done", not "started").
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
                executor=self._executor,
                push_max_bytes=-1 if push_max_bytes is None else max(0, push_max_bytes),
                holder=self.name,
                on_close=self._forget,
                producer_ids=self._producer_ids,
                ack_each_take=ack_each_take,
            )
        with self._lock:
            self._subscriptions.append(sub)
        if wait_s > 0:
            self._wait_registered(sub, wait_s)
        return sub

    # -- the executor ---------------------------------------------------------------------------
    def on(self, subscription: Subscription, handler: Handler, *, max_batch: int = BUDGET) -> None:
        """Run ``handler(notifications)`` on the node's executor whenever notifications of
        ``subscription`` are queued, with at most ``max_batch`` at a time (taken, so they
        left the queue, before the handler runs). ``take`` is then not for this
        subscription. A handler that raises is logged and ends ``spin`` with its error."""
        subscription.handle(handler, max_batch)

    def every(self, period_s: float, fn: Callable[[int], object]) -> Timer:
        """Run ``fn(now_ns)`` (monotonic ns) on the executor every ``period_s``, the first
        time one period from now; a run that falls a period behind is skipped, never made
        up in a burst. ``.cancel()`` on the returned handle stops it."""
        if not (math.isfinite(period_s) and period_s > 0):
            raise ConfigError(f"period_s must be a finite number of seconds > 0, got {period_s}")
        period_ns = max(1, int(period_s * 1e9))
        return self._executor.schedule(fn, time.monotonic_ns() + period_ns, period_ns)

    def at(self, deadline_ns: int, fn: Callable[[int], object]) -> Timer:
        """Run ``fn(now_ns)`` once on the executor at ``deadline_ns`` (``time.monotonic_ns``
        clock; at once if it has passed). ``.cancel()`` on the returned handle withdraws it."""
        return self._executor.schedule(fn, int(deadline_ns))

    def spin(self, stop: threading.Event) -> None:
        """Block the calling thread (a service's main thread) until ``stop`` is set or the
        node closes, while the executor runs what is registered. Raises the first error a
        handler raised (the node stays open: leaving its ``with`` closes it)."""
        executor = self._executor
        while not stop.is_set() and not self._closed:
            if executor.error is not None:
                raise executor.error
            # A signal handler's stop.set() ends the wait at once; a close or a handler's
            # error from another thread is seen within one slice.
            planned = time.monotonic_ns() + int(_SPIN_SLICE_S * 1e9)
            stop.wait(_SPIN_SLICE_S)
            # This thread does nothing else, so waking late means the process did not run.
            # The executor sees that only when the stop comes while it sleeps: a busy
            # mediator was stopped 14 s mid-turn and said "1.9 s" (a later starvation).
            late = time.monotonic_ns() - planned
            if late > STALL_NS:
                self._stalled(late)
        if executor.error is not None and not stop.is_set():
            raise executor.error

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
        sub.caller_waits = True  # a refusal is raised here, not also logged
        try:
            self._wait_answer(sub, deadline, wait_s)
        finally:
            sub.caller_waits = False

    def _wait_answer(self, sub: Subscription, deadline: float, wait_s: float) -> None:
        missing: NotFoundError | None = None
        while time.monotonic() < deadline:
            sub.judge_refusal()  # a refusal counts only from the service's own session
            try:
                if sub.wait_registered(min(0.25, max(0.0, deadline - time.monotonic()))):
                    return
            except FramegateError:
                sub.close()
                raise
            if sub.service not in self.live_services(timeout_s=min(1.0, wait_s)):
                return
            try:
                info = self.service_info(sub.service, timeout_s=1.0)
            except FramegateError:
                continue  # no answer is no verdict (a loaded machine): ask again
            try:
                buffer_of(info, sub.name)
                missing = None
            except NotFoundError as exc:
                missing = exc
        if missing is not None:
            sub.close()
            raise missing

    def _stalled(self, late_ns: int) -> None:
        """(the executor, or ``spin``) The process did not run for ``late_ns``: say so,
        once: a stop both saw (the executor slept through it) is said by the first."""
        lease_s = self.network.lease_ms / 1000
        now = time.monotonic_ns()
        with self._lock:
            seen = now - late_ns < self._stalled_until_ns
            self._stalled_until_ns = max(self._stalled_until_ns, now)
        if late_ns / 1e9 > lease_s and not seen:
            # Not only SIGSTOP: with more runnable threads than CPUs a thread can wait seconds
            # for one (measured: 2.3 s at load 22 on 2 cores), so the load is part of the answer.
            load = os.getloadavg()[0] if hasattr(os, "getloadavg") else math.nan
            log.warning(
                "%s: this process did not run for %.1f s (stopped, suspended, or starved of CPU: "
                "load average %.1f on %d CPUs), longer than the %.1f s lease: peers dropped it; "
                "it reconnects and its subscriptions re-register by themselves",
                self.name or "client",
                late_ns / 1e9,
                load,
                os.cpu_count() or 1,
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
        self._executor.close()
        withdraw(self._announced)
        with suppress(zenoh.ZError):
            self._session.close()

    def __enter__(self) -> Node:
        return self

    def __exit__(self, *_exc: Any) -> None:
        self.close()
