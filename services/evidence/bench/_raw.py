"""Raw-Zenoh worker roles: the baseline every framegate figure is divided by.

This is the one place outside ``middleware`` that imports zenoh (tests/middleware/test_api.py
allows it). Each role does the least a competent raw-Zenoh application would do for the same
job: a publisher with ``CongestionControl.BLOCK`` (lossless, like framegate's ``wait_s``), a
subscriber that copies the payload out to ``bytes`` (framegate's consumer also ends with
``bytes``), the same pair paced for one-way latency, and a callback queryable answering a
``session.get`` (what framegate's fetch and query use). Besides the baselines: the same
subscriber through each handler design zenoh-python offers (the ceiling each design allows),
an idle session (the idle floor) and a hostile peer that speaks framegate's wire.
"""

from __future__ import annotations

import gc
import json
import threading
import time
from typing import Any

import psutil
import zenoh

from ._serve import (
    Counter,
    LatencyLog,
    paced,
    profiled,
    reply,
    round_trips,
    serve,
    sleep_until,
)

KEY = "bench/raw/data"
ECHO_KEY = "bench/raw/echo"

# The subscriber handler designs zenoh-python offers, each measured as its own raw row:
# name -> label. "fifo" is what ``raw_sub`` (every raw baseline) uses.
HANDLER_DESIGNS = {
    "callback-direct": "Callback(fn, indirect=False)",
    "callback": "Callback(fn) (indirect)",
    "fifo": "FifoChannel(256), drained by a thread",
    "ring": "RingChannel(4096), try_recv in batches",
}
# How long the ring's drainer sleeps when it finds the ring empty.
RING_IDLE_S = 0.0005


def _config(params: dict[str, Any]) -> zenoh.Config:
    """Peer on loopback, multicast scouting off, the same lease and retry as framegate's."""
    conf = zenoh.Config()
    settings: dict[str, Any] = {
        "mode": "peer",
        "scouting/multicast/enabled": False,
        "transport/link/tx/lease": 1000,
        "transport/shared_memory/enabled": bool(params.get("shm", True)),
        "connect/retry": {
            "period_init_ms": 100,
            "period_max_ms": 1000,
            "period_increase_factor": 2,
        },
    }
    if params.get("listen"):
        settings["listen/endpoints"] = [params["listen"]]
    if params.get("connect"):
        settings["connect/endpoints"] = [params["connect"]]
    for key, value in settings.items():
        conf.insert_json5(key, json.dumps(value))
    return conf


def _wait_matching(publisher: Any, timeout_s: float) -> bool:
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        if publisher.matching_status.matching:
            return True
        time.sleep(0.01)
    return False


def raw_pub(params: dict[str, Any]) -> None:
    """Publishes ``size``-byte payloads as fast as BLOCK congestion control allows, or one
    every ``interval_s`` when the ``produce`` command gives one."""
    payload = bytes(int(params["size"]))
    with zenoh.open(_config(params)) as session:
        publisher = session.declare_publisher(KEY, congestion_control=zenoh.CongestionControl.BLOCK)

        def produce(command: dict[str, Any]) -> dict[str, Any]:
            if not _wait_matching(publisher, 10.0):
                raise RuntimeError("no subscriber matched within 10 s")
            end = time.monotonic() + float(command["seconds"])
            sent = 0
            put = publisher.put
            if float(command.get("interval_s") or 0) > 0:  # paced: a sensor's rate
                for tick in paced(float(command["seconds"]), float(command["interval_s"])):
                    sleep_until(tick)
                    put(payload)
                    sent += 1
                return {"sent": sent}
            while time.monotonic() < end:
                for _ in range(8):
                    put(payload)
                sent += 8
            return {"sent": sent}

        reply(ready=True)
        serve({"produce": produce})
        publisher.undeclare()


def raw_sub(params: dict[str, Any]) -> None:
    """Counts payloads, each copied out to ``bytes``, read from Zenoh's default FIFO handler.

    The default handler (a FIFO of 256 drained by an application thread) is what a raw
    application gets with no arguments, and here it is the fastest: a direct callback
    (``indirect=False``) made 64 B pub/sub ~8x slower.
    """
    counter = Counter()
    with zenoh.open(_config(params)) as session:
        subscriber = session.declare_subscriber(KEY, zenoh.handlers.FifoChannel(256))

        def drain() -> None:
            with profiled("raw-sub-drain"):
                for sample in subscriber:  # ends when the subscriber is undeclared
                    data = sample.payload.to_bytes()
                    counter.count += 1
                    counter.bytes += len(data)

        thread = threading.Thread(target=drain, daemon=True)
        thread.start()
        reply(ready=True)
        serve({"mark": counter.mark})
        subscriber.undeclare()
        thread.join(timeout=2.0)


def _declare_design(
    session: zenoh.Session, design: str, on_sample: Any, stop: threading.Event
) -> tuple[Any, threading.Thread | None]:
    """A subscriber on KEY with ``design``'s handler, and the thread draining it (if any)."""
    handlers = zenoh.handlers
    if design == "callback-direct":  # runs on Zenoh's own receive thread, taking the GIL
        return session.declare_subscriber(KEY, handlers.Callback(on_sample, indirect=False)), None
    if design == "callback":  # zenoh-python hands samples to its own Python thread
        return session.declare_subscriber(KEY, handlers.Callback(on_sample)), None
    if design == "fifo":
        subscriber = session.declare_subscriber(KEY, handlers.FifoChannel(256))

        def drain_fifo() -> None:
            for sample in subscriber:  # ends when the subscriber is undeclared
                on_sample(sample)

        return subscriber, threading.Thread(target=drain_fifo, daemon=True)
    if design == "ring":  # drops the oldest sample when full: the loss is reported
        subscriber = session.declare_subscriber(KEY, handlers.RingChannel(4096))

        def drain_ring() -> None:
            try_recv = subscriber.try_recv
            while not stop.is_set():
                sample = try_recv()
                if sample is None:
                    stop.wait(RING_IDLE_S)
                    continue
                while sample is not None:  # a batch: everything the ring holds now
                    on_sample(sample)
                    sample = try_recv()

        return subscriber, threading.Thread(target=drain_ring, daemon=True)
    raise ValueError(f"unknown handler design {design!r}; known: {', '.join(HANDLER_DESIGNS)}")


def raw_handler_sub(params: dict[str, Any]) -> None:
    """Like ``raw_sub`` (each payload copied out to ``bytes`` and counted) through the
    handler design ``params["design"]`` (a key of HANDLER_DESIGNS)."""
    counter = Counter()
    stop = threading.Event()

    def on_sample(sample: zenoh.Sample) -> None:
        data = sample.payload.to_bytes()
        counter.count += 1
        counter.bytes += len(data)

    with zenoh.open(_config(params)) as session:
        subscriber, thread = _declare_design(session, str(params["design"]), on_sample, stop)
        if thread is not None:
            thread.start()
        reply(ready=True)
        serve({"mark": counter.mark})
        stop.set()
        subscriber.undeclare()
        if thread is not None:
            thread.join(timeout=2.0)


def raw_idle(params: dict[str, Any]) -> None:
    """The idle floor: a session holding ``publishers`` publishers and a liveliness token,
    or ``subscribers`` subscribers on the other side's keys, and no traffic."""
    with zenoh.open(_config(params)) as session:
        declared: list[Any] = [
            session.declare_publisher(f"bench/raw/idle/{i}")
            for i in range(int(params.get("publishers", 0)))
        ]
        declared += [
            session.declare_subscriber(f"bench/raw/idle/{i}", zenoh.handlers.FifoChannel(256))
            for i in range(int(params.get("subscribers", 0)))
        ]
        declared.append(session.liveliness().declare_token("bench/raw/idle/@alive"))
        reply(ready=True)
        serve({})
        for entity in declared:
            entity.undeclare()


def raw_hostile(params: dict[str, Any]) -> None:
    """A hostile peer of a framegate producer, speaking the wire with plain Zenoh: declares
    ``tokens`` flow-control subscription tokens asking for ``queue_size`` each (keys as
    ``middleware._wire.Keys.subscription_token`` builds them) and, with ``listen_notify``,
    receives their notifications but never acknowledges one."""
    ns, service, buffer = params["namespace"], params["service"], params["buffer"]
    queue_size, count = int(params["queue_size"]), int(params["tokens"])
    counter = Counter()

    def on_notification(sample: zenoh.Sample) -> None:
        counter.count += 1
        counter.bytes += len(sample.payload)

    with zenoh.open(_config(params)) as session:
        subscriber = None
        if params.get("listen_notify"):
            subscriber = session.declare_subscriber(
                f"{ns}/@notify/{service}/{buffer}/*", zenoh.handlers.Callback(on_notification)
            )
        liveliness = session.liveliness()
        tokens = [
            liveliness.declare_token(
                f"{ns}/@sub/{service}/{buffer}/hostile{i:04d}/flow/{queue_size}/-1/hostile~bench"
            )
            for i in range(count)
        ]
        reply(ready=True, tokens=len(tokens))
        serve({"mark": counter.mark})
        for token in tokens:
            token.undeclare()
        if subscriber is not None:
            subscriber.undeclare()


def _lat_key(size: int) -> str:
    return f"bench/raw/lat/{size}"


def raw_lat_pub(params: dict[str, Any]) -> None:
    """One-way latency source: a put every ``interval_s``, the monotonic clock in its first
    8 bytes (taken before the payload is handed to Zenoh, as framegate's key is)."""
    with zenoh.open(_config(params)) as session:
        publishers = {
            int(size): session.declare_publisher(
                _lat_key(int(size)), congestion_control=zenoh.CongestionControl.BLOCK
            )
            for size in params["sizes"]
        }

        def latency(command: dict[str, Any]) -> dict[str, Any]:
            size = int(command["size"])
            publisher, payload = publishers[size], bytearray(size)
            if not _wait_matching(publisher, 10.0):
                raise RuntimeError("no subscriber matched within 10 s")
            sent = 0
            for tick in paced(float(command["seconds"]), float(command["interval_s"])):
                sleep_until(tick)
                payload[:8] = time.monotonic_ns().to_bytes(8, "little")
                publisher.put(payload)
                sent += 1
            return {"sent": sent}

        reply(ready=True)
        serve({"latency": latency})
        for publisher in publishers.values():
            publisher.undeclare()


def raw_lat_sub(params: dict[str, Any]) -> None:
    """One-way latency sink: a default-FIFO subscriber per size drained by its own thread;
    latency = monotonic now − the clock in the payload, once the payload is ``bytes``."""
    sizes = [int(size) for size in params["sizes"]]
    log = LatencyLog([str(size) for size in sizes])
    with zenoh.open(_config(params)) as session:
        subscribers = [
            session.declare_subscriber(_lat_key(size), zenoh.handlers.FifoChannel(256))
            for size in sizes
        ]

        def drain(size: int, subscriber: Any) -> None:
            for sample in subscriber:  # ends when the subscriber is undeclared
                data = sample.payload.to_bytes()
                now = time.monotonic_ns()
                log.record(str(size), (now - int.from_bytes(data[:8], "little")) / 1000)

        threads = [
            threading.Thread(target=drain, args=(size, sub), daemon=True)
            for size, sub in zip(sizes, subscribers, strict=True)
        ]
        for thread in threads:
            thread.start()
        reply(ready=True)
        serve({"collect": log.collect})
        for subscriber in subscribers:
            subscriber.undeclare()
        for thread in threads:
            thread.join(timeout=2.0)


def raw_queryable(params: dict[str, Any]) -> None:
    """Answers ``echo?size=S;k=K`` with K replies of S bytes each (k defaults to 1)."""
    payloads: dict[int, bytes] = {}

    def on_query(query: zenoh.Query) -> None:
        with query:
            size = int(query.parameters.get("size") or 64)
            count = int(query.parameters.get("k") or 1)
            payload = payloads.get(size)
            if payload is None:
                payload = payloads[size] = bytes(size)
            for _ in range(count):
                query.reply(ECHO_KEY, payload)

    with zenoh.open(_config(params)) as session:
        queryable = session.declare_queryable(
            ECHO_KEY, zenoh.handlers.Callback(on_query, indirect=False)
        )
        reply(ready=True)
        serve({})
        queryable.undeclare()


def _ask(session: zenoh.Session, selector: str, expect: int) -> int:
    got = 0
    for answer in session.get(selector, consolidation=zenoh.ConsolidationMode.NONE, timeout=5.0):
        if answer.ok is None:
            raise RuntimeError(f"error reply to {selector}")
        answer.ok.payload.to_bytes()
        got += 1
    if got != expect:
        raise RuntimeError(f"{selector}: expected {expect} replies, got {got}")
    return got


def raw_querier(params: dict[str, Any]) -> None:
    """Round trips of ``session.get`` → K payloads copied out to ``bytes``."""
    with zenoh.open(_config(params)) as session:

        def latency(command: dict[str, Any]) -> dict[str, Any]:
            size, k = int(command["size"]), int(command.get("k", 1))
            selector = f"{ECHO_KEY}?size={size};k={k}"
            deadline = time.monotonic() + 10.0
            while True:  # the queryable may not be reachable yet
                try:
                    _ask(session, selector, k)
                    break
                except RuntimeError:
                    if time.monotonic() > deadline:
                        raise
                    time.sleep(0.05)
            latencies = round_trips(
                lambda: _ask(session, selector, k),
                float(command["seconds"]),
                float(command.get("interval_s", 0.0)),
                int(command.get("max_count", 1_000_000)),
            )
            return {"latencies_us": latencies}

        reply(ready=True)
        serve({"latency": latency})


def raw_memory(params: dict[str, Any]) -> None:
    """The floor: the same payloads held in a plain Python list (no buffer, no middleware)."""
    count, size = int(params["count"]), int(params["size"])
    template = bytearray(size)
    with zenoh.open(_config(params)):
        held: list[bytes] = []
        gc.collect()
        before = psutil.Process().memory_info().rss
        for i in range(count):
            template[:8] = i.to_bytes(8, "little")
            held.append(bytes(template))
        gc.collect()
        after = psutil.Process().memory_info().rss
        reply(ready=True, rss_before=before, rss_after=after, payload_bytes=count * size)
        serve({})
        del held


ROLES = {
    "raw-handler-sub": raw_handler_sub,
    "raw-hostile": raw_hostile,
    "raw-idle": raw_idle,
    "raw-lat-pub": raw_lat_pub,
    "raw-lat-sub": raw_lat_sub,
    "raw-memory": raw_memory,
    "raw-pub": raw_pub,
    "raw-querier": raw_querier,
    "raw-queryable": raw_queryable,
    "raw-sub": raw_sub,
}
