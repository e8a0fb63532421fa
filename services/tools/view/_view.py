"""``framegate view``: the running pipeline, live in Foxglove.

The main loop finds the buffers to stream (the named ones, or every live buffer, again
every few seconds so a pipeline started after the viewer appears too), starts one
``BufferStream`` per buffer and reports the status once per interval, until ``stop`` is
set. Stopping joins every stream (each wakes within 0.2 s), stops the server and closes the
Zenoh session.
"""

from __future__ import annotations

import logging
import threading
import time
from collections.abc import Callable
from contextlib import suppress

from middleware import (
    BufferInfo,
    FramegateError,
    NetworkConfig,
    Node,
    NotFoundError,
    ServiceInfo,
    check_name,
    listing,
    split_target,
)
from services.lib.argtypes import did_you_mean

from ._config import ViewConfig
from ._server import FoxgloveServer
from ._status import Counters, Status
from ._stream import BufferStream, FrameSizes

log = logging.getLogger("framegate.view")


def parse_target(target: str) -> tuple[str, str | None]:
    """``SERVICE/BUFFER`` or a bare ``SERVICE`` (all its buffers); errors name the mistake."""
    target = target.strip("/")
    if "/" in target:
        return split_target(target)
    return check_name(target, "service"), None


def _find(node: Node, config: ViewConfig) -> list[BufferInfo]:
    """The buffers to stream that are live now (a named one that is not yet live waits)."""
    try:
        services = node.services(timeout_s=1.0)
    except FramegateError:
        return []
    live = {b.name: b for s in services for b in s.buffers}
    if not config.targets:
        return list(live.values())
    chosen = []
    for target in config.targets:
        service, buffer = parse_target(target)
        if buffer is not None:
            if f"{service}/{buffer}" in live:
                chosen.append(live[f"{service}/{buffer}"])
        else:  # a bare SERVICE names all its buffers
            chosen += [b for b in live.values() if b.service == service]
    return chosen


def _missing(target: str, services: list[ServiceInfo]) -> str | None:
    """Why ``target`` names nothing live (None: it does)."""
    service, buffer = parse_target(target)
    by_name = {s.service: s for s in services}
    if service not in by_name:
        live = sorted(by_name)
        return (
            f"no live service named {service!r}{did_you_mean(service, live, quote=True)}; "
            f"live services: {listing(live)}"
        )
    offered = [b.buffer for b in by_name[service].buffers]
    if buffer is None or buffer in offered:
        return None
    return (
        f"service {service!r} has no buffer {buffer!r}{did_you_mean(buffer, offered, quote=True)}; "
        f"it offers: {', '.join(offered) or 'none'}"
    )


def check_targets(
    node: Node, targets: tuple[str, ...], timeout_s: float, stop: threading.Event | None = None
) -> bool:
    """True once every named target is live; ``NotFoundError`` with a did-you-mean for
    the first that is not within ``timeout_s`` (a pipeline starting meanwhile is waited for);
    False as soon as ``stop`` is set (a Ctrl-C while waiting is a stop, not that error)."""
    deadline = time.monotonic() + timeout_s
    while targets:
        if stop is not None and stop.is_set():
            return False
        try:
            services = node.services(timeout_s=max(0.2, min(1.0, timeout_s)))
        except FramegateError:
            services = []
        problems = [p for t in targets if (p := _missing(t, services)) is not None]
        if not problems:
            return True
        if time.monotonic() >= deadline:
            raise NotFoundError(f"{problems[0]} (waited {timeout_s:g} s; --timeout waits longer)")
        if stop is not None:
            stop.wait(0.1)
        else:
            time.sleep(0.1)
    return True


def _start_stream(
    node: Node,
    buffer: BufferInfo,
    config: ViewConfig,
    server: FoxgloveServer,
    counters: Counters,
    sizes: FrameSizes,
    stop: threading.Event,
) -> BufferStream | None:
    """A stream of ``buffer``, or None (said on stderr) when it cannot be subscribed to now:
    the next discovery tries again, and the other buffers go on."""
    try:
        return BufferStream(node, buffer, config, server, counters, sizes, stop)
    except FramegateError as exc:
        log.warning("view: cannot stream %s yet (%s); trying again", buffer.name, exc)
        return None


def _drop_dead(streams: dict[str, BufferStream]) -> None:
    """Forget streams whose thread ended with an error, so that discovery starts them again:
    a dead stream would leave its channels silent for good."""
    for name, stream in list(streams.items()):
        if stream.thread.is_alive():
            continue
        log.warning("view: streaming %s stopped (%r); starting it again", name, stream.error)
        with suppress(FramegateError):
            stream.close()
        del streams[name]


def run_view(
    config: ViewConfig,
    network: NetworkConfig,
    *,
    stop: threading.Event,
    report: Callable[[Status], None],
    started: Callable[[str], None] = lambda _url: None,
) -> Counters:
    """Serve until ``stop`` is set (or ``config.duration_s`` passes); the final counters."""
    counters = Counters()
    sizes = FrameSizes()
    streams: dict[str, BufferStream] = {}
    server = FoxgloveServer(config, counters)
    try:
        with Node(network=network) as node:
            if not check_targets(node, config.targets, config.discovery_timeout_s, stop):
                return counters  # stopped while waiting for them: nothing was served
            started(server.url)
            deadline = None if config.duration_s is None else time.monotonic() + config.duration_s
            next_find = next_status = time.monotonic()
            counters.snapshot(server.url, next_status)  # the zero point of the first rates
            next_status += config.status_interval_s
            try:
                while not stop.is_set():
                    now = time.monotonic()
                    if deadline is not None and now >= deadline:
                        break
                    if now >= next_find:
                        _drop_dead(streams)
                        for buffer in _find(node, config):
                            if buffer.name not in streams:
                                stream = _start_stream(
                                    node, buffer, config, server, counters, sizes, stop
                                )
                                if stream is not None:
                                    streams[buffer.name] = stream
                        next_find = time.monotonic() + config.discover_interval_s
                    if now >= next_status:
                        report(counters.snapshot(server.url, now))
                        next_status += config.status_interval_s
                    stop.wait(max(0.0, min(next_find, next_status) - time.monotonic()))
            finally:
                stop.set()
                for stream in streams.values():
                    stream.close()
    finally:
        server.stop()
    return counters
