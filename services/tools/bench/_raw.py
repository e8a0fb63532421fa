"""Raw-Zenoh worker roles: the baseline every framegate figure is divided by.

This is the one place outside ``middleware`` that imports zenoh (tests/middleware/test_api.py
allows it). Each role does the least a competent raw-Zenoh application would do for the same
job: a publisher with ``CongestionControl.BLOCK`` (lossless, like framegate's ``wait_s``), a
subscriber that copies the payload out to ``bytes`` (framegate's consumer also ends with
``bytes``), the same pair paced for one-way latency, and a callback queryable answering a
``session.get`` (what framegate's fetch and query use).
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
    "raw-lat-pub": raw_lat_pub,
    "raw-lat-sub": raw_lat_sub,
    "raw-memory": raw_memory,
    "raw-pub": raw_pub,
    "raw-querier": raw_querier,
    "raw-queryable": raw_queryable,
    "raw-sub": raw_sub,
}
