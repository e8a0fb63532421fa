"""framegate worker roles: the same jobs as ``_raw``, through the public ``middleware`` API.

Producers put with ``wait_s`` (the lossless rule: a replay source waits rather than drops),
so throughput is the sustainable rate with flow control on. Consumers take each notification
and fetch its element (inline for small payloads, one query for frames): the
notify-then-fetch design as an application uses it.
"""

from __future__ import annotations

import gc
import threading
import time
from collections.abc import Callable
from functools import partial
from typing import Any

import psutil

from middleware import (
    PUSH_ALL,
    FlowControlRefused,
    FramegateError,
    NetworkConfig,
    Node,
    NotFoundError,
    Retention,
    Subscription,
    SubscriptionMode,
    make_metadata,
    now_ns,
)

from ._serve import (
    Counter,
    LatencyLog,
    RssMeter,
    paced,
    profiled,
    reply,
    serve,
    serve_while_consuming,
    sleep_until,
)

SERVICE = "bench"
# Query-scaling elements sit this many ns apart, so a range of k elements is easy to write.
STEP_NS = 1000


class Stamper:
    """Generic metadata for a timestamp, by formatting one template (not the cost we measure)."""

    def __init__(self) -> None:
        probe = 123_456_789
        template = make_metadata("generic", probe)
        marker = f'"{probe}"'.encode()
        if template.count(marker) != 1:
            raise RuntimeError(f"cannot find the timestamp in {template!r}")
        self._format = template.replace(marker, b'"%d"')
        if self(42) != make_metadata("generic", 42):
            raise RuntimeError("metadata template does not reproduce make_metadata")

    def __call__(self, timestamp_ns: int) -> bytes:
        return self._format % timestamp_ns


# How long a worker keeps trying to subscribe while its producer process is still starting.
SUBSCRIBE_PATIENCE_S = 60.0


def _subscribe(node: Node, target: str, **kwargs: Any) -> Subscription:
    """``node.subscribe`` that waits for the producer worker started alongside: its
    service may not be live yet (the subscription registers when it is), or visible before
    the buffer is offered (NotFoundError until then)."""
    deadline = time.monotonic() + SUBSCRIBE_PATIENCE_S
    while True:
        try:
            return node.subscribe(target, await_service=True, **kwargs)
        except NotFoundError:
            if time.monotonic() > deadline:
                raise
            time.sleep(0.1)


def _network(params: dict[str, Any]) -> NetworkConfig:
    """Explicit ``listen``/``connect`` endpoints, else the loopback rendezvous ``local_port``."""
    return NetworkConfig(
        listen=(params["listen"],) if params.get("listen") else (),
        connect=(params["connect"],) if params.get("connect") else (),
        shared_memory=bool(params.get("shm", True)),
        local_port=int(params.get("local_port") or NetworkConfig().local_port),
    )


def fg_pub(params: dict[str, Any]) -> None:
    """Puts ``size``-byte elements with ``wait_s`` as fast as the subscriber takes them, or
    one every ``interval_s`` when the ``produce`` command gives one."""
    payload = bytes(int(params["size"]))
    batch = int(params.get("batch") or 0)
    stamp = Stamper()
    clock = {"t": time.time_ns()}
    with Node(SERVICE, _network(params)) as node:
        inline: dict[str, Any] = {}
        if params.get("inline_max_bytes") is not None:
            inline["inline_max_bytes"] = int(params["inline_max_bytes"])
        retention = Retention(max_count=int(params.get("retain", 256)))
        producer = node.offer(params["buffer"], retention=retention, **inline)

        def produce(command: dict[str, Any]) -> dict[str, Any]:
            if not producer.wait_for_subscribers(1, timeout_s=10.0):
                raise RuntimeError("no subscription registered within 10 s")
            end = time.monotonic() + float(command["seconds"])
            sent = refused = 0
            t = clock["t"]
            interval_s = float(command.get("interval_s") or 0)
            if batch and interval_s > 0:  # paced batches: a sensor that batches (the gyro)
                for tick in paced(float(command["seconds"]), interval_s):
                    sleep_until(tick)
                    items = [(t + i, payload, stamp(t + i)) for i in range(1, batch + 1)]
                    t += batch
                    producer.put_many(items, wait_s=5.0)
                    sent += batch
            elif batch:
                # The batch API of issue 18 item 4: elements in, one wait, one notification.
                put_many = producer.put_many
                while time.monotonic() < end:
                    items = [(t + i, payload, stamp(t + i)) for i in range(1, batch + 1)]
                    t += batch
                    try:
                        put_many(items, wait_s=5.0)
                    except FlowControlRefused:
                        refused += batch
                    sent += batch
            elif interval_s > 0:  # paced: a sensor's rate
                for tick in paced(float(command["seconds"]), interval_s):
                    sleep_until(tick)
                    t += 1
                    producer.put(t, payload, stamp(t), wait_s=5.0)
                    sent += 1
            else:
                put = producer.put
                while time.monotonic() < end:
                    for _ in range(8):
                        t += 1
                        try:
                            put(t, payload, stamp(t), wait_s=5.0)
                        except FlowControlRefused:
                            refused += 1
                    sent += 8
            clock["t"] = t
            return {"sent": sent - refused, "refused": refused}

        reply(ready=True)
        serve({"produce": produce})


def _consume(sub: Subscription, stop: threading.Event, on_element: Any) -> None:
    with profiled(f"fg-consume-{sub.buffer}"):
        while not stop.is_set():
            note = sub.take(timeout_s=0.2)
            if note is None:
                continue
            try:
                element = sub.fetch(note)
            except FramegateError:
                on_element(None, note.timestamp_ns)
            else:
                on_element(element.payload, note.timestamp_ns)


def _consume_many(sub: Subscription, stop: threading.Event, on_element: Any, batch: int) -> None:
    """Like ``_consume`` through ``take_many`` (issue 18 item 4; see ``fg_pub``)."""
    take_many = sub.take_many
    with profiled(f"fg-consume-many-{sub.buffer}"):
        while not stop.is_set():
            for note in take_many(batch, timeout_s=0.2):
                try:
                    element = sub.fetch(note)
                except FramegateError:
                    on_element(None, note.timestamp_ns)
                else:
                    on_element(element.payload, note.timestamp_ns)


def fg_sub(params: dict[str, Any]) -> None:
    """Takes each notification and fetches its element, counting payload bytes.

    ``observe``: an observer (never holds the producer back), else flow-controlled;
    ``batch``: take up to that many notifications at once with ``take_many``.
    """
    counter = Counter()
    lock = threading.Lock()
    stop = threading.Event()

    def on_element(payload: bytes | None, _timestamp_ns: int) -> None:
        with lock:  # several consuming threads may count at once
            if payload is None:
                counter.errors += 1
                return
            counter.count += 1
            counter.bytes += len(payload)

    batch = int(params.get("batch") or 0)
    # Queues count elements: one that holds less than a batch would refuse every put_many,
    # and one of two batches lets the producer fill the next while this side takes.
    queue_size = max(int(params["queue_size"]), 2 * batch)
    with Node(network=_network(params)) as node:
        sub = _subscribe(
            node,
            f"{SERVICE}/{params['buffer']}",
            queue_size=queue_size,
            mode=SubscriptionMode.OBSERVE if params.get("observe") else SubscriptionMode.FLOW,
            wait_s=5.0,
            push_max_bytes=PUSH_ALL if params.get("push") else None,
        )
        consume: Callable[[], None] = (
            partial(_consume_many, sub, stop, on_element, batch)
            if batch
            else partial(_consume, sub, stop, on_element)
        )
        # Several consuming threads keep several fetches in flight (take() is thread-safe).
        fetchers = [consume] * int(params.get("fetchers", 1))
        serve_while_consuming(fetchers, stop, {"mark": counter.mark})


def fg_lat_pub(params: dict[str, Any]) -> None:
    """Puts one element every ``interval_s``; its key is the monotonic clock at the put.

    ``streams``: ``{name, size, push}`` each, one buffer per stream.
    """
    stamp = Stamper()
    with Node(SERVICE, _network(params)) as node:
        producers = {
            str(stream["name"]): (
                node.offer(str(stream["name"]), retention=Retention(max_count=64)),
                bytes(int(stream["size"])),
            )
            for stream in params["streams"]
        }

        def latency(command: dict[str, Any]) -> dict[str, Any]:
            producer, payload = producers[str(command["stream"])]
            if not producer.wait_for_subscribers(1, timeout_s=10.0):
                raise RuntimeError("no subscription registered within 10 s")
            sent = 0
            for tick in paced(float(command["seconds"]), float(command["interval_s"])):
                sleep_until(tick)
                t = time.monotonic_ns()
                producer.put(t, payload, stamp(t), wait_s=1.0)
                sent += 1
            return {"sent": sent}

        reply(ready=True)
        serve({"latency": latency})


def fg_lat_sub(params: dict[str, Any]) -> None:
    """One consuming thread per stream; latency = monotonic now − the element's key.

    A pushed stream's payload comes with its notification; the others are fetched (64 B
    comes inline anyway, a frame costs one query).
    """
    stop = threading.Event()
    streams = {str(s["name"]): s for s in params["streams"]}
    log = LatencyLog(list(streams))

    def recorder(name: str) -> Any:
        size = int(streams[name]["size"])

        def on_element(payload: bytes | None, timestamp_ns: int) -> None:
            now = time.monotonic_ns()
            if payload is not None and len(payload) == size:
                log.record(name, (now - timestamp_ns) / 1000)

        return on_element

    with Node(network=_network(params)) as node:
        consumers: list[Callable[[], None]] = []
        for name, stream in streams.items():
            sub = _subscribe(
                node,
                f"{SERVICE}/{name}",
                queue_size=2,
                wait_s=5.0,
                push_max_bytes=PUSH_ALL if stream.get("push") else None,
            )
            consumers.append(partial(_consume, sub, stop, recorder(name)))
        serve_while_consuming(consumers, stop, {"collect": log.collect})


def fg_query_server(params: dict[str, Any]) -> None:
    """Offers ``n<count>`` buffers of ``count`` small elements, keys STEP_NS apart."""
    stamp = Stamper()
    payload = bytes(int(params.get("size", 64)))
    with Node(SERVICE, _network(params)) as node:
        started = time.monotonic()
        for count in params["counts"]:
            producer = node.offer(
                f"n{int(count)}", retention=Retention(max_count=None, max_bytes=None)
            )
            for i in range(1, int(count) + 1):
                producer.put(i * STEP_NS, payload, stamp(i * STEP_NS))
        reply(ready=True, fill_s=time.monotonic() - started)
        serve({})


def fg_query_client(params: dict[str, Any]) -> None:
    """Range queries returning exactly k elements from the middle of n-element buffers.

    The buffers of all requested n are queried in turn (n1, n2, n3, n1, ...), so every n
    sees the same machine: only then is "flat in n" a fair comparison on a shared host.
    """
    with Node(network=_network(params)) as node:

        def asker(n: int, k: int) -> Callable[[], None]:
            first = max(1, n // 2 - k // 2)
            time_range = f"[{first * STEP_NS}..{(first + k - 1) * STEP_NS}]"
            target = f"{SERVICE}/n{n}"

            def ask() -> None:
                got = node.query(target, time_range=time_range)
                if len(got) != k:
                    raise RuntimeError(f"{target} {time_range}: expected {k}, got {len(got)}")

            return ask

        def latency(command: dict[str, Any]) -> dict[str, Any]:
            k, ns = int(command["k"]), [int(n) for n in command["ns"]]
            askers = [asker(n, k) for n in ns]
            deadline = time.monotonic() + 10.0
            while True:  # the service may not be visible yet
                try:
                    for ask in askers:
                        ask()
                    break
                except FramegateError:
                    if time.monotonic() > deadline:
                        raise
                    time.sleep(0.05)
            latencies: list[list[float]] = [[] for _ in ns]
            end = time.monotonic() + float(command["seconds"])
            max_count = int(command.get("max_count", 1_000_000))
            while time.monotonic() < end and len(latencies[-1]) < max_count:
                for ask, out in zip(askers, latencies, strict=True):
                    began = time.perf_counter_ns()
                    ask()
                    out.append((time.perf_counter_ns() - began) / 1000)
            return {"latencies_us": {str(n): out for n, out in zip(ns, latencies, strict=True)}}

        reply(ready=True)
        serve({"latency": latency})


def fg_idle(params: dict[str, Any]) -> None:
    """A node at rest: offers ``offers`` buffers (named ``service``) and holds a subscription
    per ``subscribe`` entry (``{target, mode}``), then does nothing until told to exit.

    Ready once every subscription is registered (or refused: then the role fails), so what
    is measured afterwards is the idle cost, not the handshake.
    """
    with Node(params.get("service"), _network(params)) as node:
        producers = [node.offer(str(name)) for name in params.get("offers", [])]
        subscriptions = [
            _subscribe(
                node,
                str(entry["target"]),
                queue_size=int(entry.get("queue_size", 8)),
                mode=SubscriptionMode(str(entry["mode"])),
                wait_s=10.0,
            )
            for entry in params.get("subscribe", [])
        ]
        reply(ready=True, buffers=len(producers), subscriptions=len(subscriptions))
        serve({})
        for sub in subscriptions:
            sub.close()


def fg_camera(params: dict[str, Any]) -> None:
    """A camera-like producer: ``size``-byte frames (a fresh ``bytes`` each, as a camera
    makes) at ``rate_hz``, put without waiting (a camera cannot wait), into a buffer that
    retains ``retain`` frames. A frame that would be put more than one period late is
    skipped, as the camera service does. Samples its own RSS while it runs.

    ``run`` ``{seconds}``: ticks, frames stored, refused (flow control), skipped late, failed;
    RSS at the start, its maximum and at the end (``private_growth`` and ``shared_growth``
    since ``offer``: ``RssMeter``); and the buffer's subscription counts.
    """
    frame = bytearray(int(params["size"]))
    period_s = 1.0 / float(params["rate_hz"])
    stamp = Stamper()
    with Node(SERVICE, _network(params)) as node:
        producer = node.offer(
            str(params["buffer"]), retention=Retention(max_count=int(params["retain"]))
        )
        offered = RssMeter()

        def run(command: dict[str, Any]) -> dict[str, Any]:
            ticks = paced(float(command["seconds"]), period_s)
            stored = refused = late = failed = 0
            meter = RssMeter()
            next_rss = time.monotonic()
            errors: list[str] = []
            started = time.monotonic()
            for tick in ticks:
                sleep_until(tick)
                now = time.monotonic()
                if now - tick > period_s:
                    late += 1
                    continue
                t = now_ns()
                frame[:8] = t.to_bytes(8, "little")
                try:
                    producer.put(t, bytes(frame), stamp(t))
                    stored += 1
                except FlowControlRefused:
                    refused += 1
                except FramegateError as exc:
                    failed += 1
                    if len(errors) < 3:
                        errors.append(str(exc))
                if now >= next_rss:
                    meter.sample()
                    next_rss = now + 0.5
            elapsed_s = time.monotonic() - started
            meter.sample()
            info = producer.info()
            return {
                "ticks": len(ticks),
                "stored": stored,
                "refused": refused,
                "late": late,
                "failed": failed,
                "errors": errors,
                "elapsed_s": elapsed_s,
                "rate_hz": stored / elapsed_s if elapsed_s > 0 else 0.0,
                "rss_offered": offered.start_total,
                "rss_start": meter.start_total,
                "rss_max": meter.total_max,
                "rss_end": meter.private + meter.shared,
                "private_growth": meter.private_max - offered.start_private,
                "shared_growth": meter.shared_max - offered.start_shared,
                "buffer_bytes": info.payload_bytes,
                "subscriptions": len(info.subscriptions),
                "refused_subscriptions": info.refused_subscriptions,
                "dropped_messages": info.dropped_messages,
            }

        reply(ready=True, rss_offered=offered.start_total)
        serve({"run": run})


def fg_memory(params: dict[str, Any]) -> None:
    """RSS of a service process before and after holding ``count`` × ``size`` bytes."""
    count, size = int(params["count"]), int(params["size"])
    stamp = Stamper()
    template = bytearray(size)
    with Node(SERVICE, _network(params)) as node:
        producer = node.offer("frames", retention=Retention(max_count=None, max_bytes=None))
        gc.collect()
        before = psutil.Process().memory_info().rss
        t0 = time.time_ns()
        for i in range(count):
            template[:8] = i.to_bytes(8, "little")
            producer.put(t0 + i, bytes(template), stamp(t0 + i))
        gc.collect()
        after = psutil.Process().memory_info().rss
        held = producer.info().payload_bytes
        reply(
            ready=True,
            rss_before=before,
            rss_after=after,
            payload_bytes=count * size,
            buffer_bytes=held,
        )
        serve({})


ROLES = {
    "fg-camera": fg_camera,
    "fg-idle": fg_idle,
    "fg-lat-pub": fg_lat_pub,
    "fg-lat-sub": fg_lat_sub,
    "fg-memory": fg_memory,
    "fg-pub": fg_pub,
    "fg-query-client": fg_query_client,
    "fg-query-server": fg_query_server,
    "fg-sub": fg_sub,
}
