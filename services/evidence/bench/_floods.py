"""Hostile peers that flood a framegate producer's control keys, speaking the wire with plain
Zenoh (like ``_raw``, the one place besides it where tools import ``zenoh``): the workers of
``framegate bench hostile``'s flood rows and of the hostile-peer tests.

Role ``flood`` (params: ``connect``, ``namespace``, ``service``, ``buffer``, ``kind``):

- ``acks``: ``size``-byte garbage on the producer's ack keys as fast as it can;
- ``forged-acks``: valid-looking acks: it watches the producer's notifications to learn the
  live registrations' epochs and ids, then repeats each one's last seen window base as an
  ack (what an idle subscriber sends), as fast as it can;
- ``churn``: subscription tokens (``mode`` flow or observe, queue ``queue_size``) with fresh
  ids declared and withdrawn as fast as it can, ``batch`` at a time.

It floods on a thread from ``ready`` until ``stop`` or exit; ``count`` answers how many
messages (or tokens) it sent. ``nice`` (optional): the process lowers its scheduling priority
by that much first, so that on a machine shared with the producer the flooders' own busy
loops take only the CPU the producer leaves (a remote attacker's CPU is not the producer's):
what is then measured is the producer's cost of receiving and dropping the flood.

Role ``flood-sink`` (params: ``listen``, ``namespace``, ``service``, ``buffer``): the same
keys as a producer's, received by plain Zenoh and dropped at once (a no-op callback on the
ack keys, a liveliness subscriber on the subscription tokens), so that a flood aimed at it
measures what Zenoh itself holds for the flood: its receive buffers, and the shared-memory
pool of each local peer that sends it large messages (mapped into this process). ``run``
``{seconds}`` samples for that long and answers its RSS growth (``RssMeter``) from ``ready``
to the maximum seen.
"""

from __future__ import annotations

import itertools
import os
import threading
import time
from typing import Any

import msgpack
import zenoh

from ._raw import _config
from ._serve import RssMeter, reply, serve


class _Flood:
    def __init__(self) -> None:
        self.sent = 0
        self.stop = threading.Event()


def _acks(session: zenoh.Session, prefix: str, params: dict[str, Any], flood: _Flood) -> None:
    blob = bytes(int(params.get("size", 16)))
    publisher = session.declare_publisher(
        f"{prefix}/flood", congestion_control=zenoh.CongestionControl.DROP
    )
    while not flood.stop.is_set():
        for _ in range(256):
            publisher.put(blob)
        flood.sent += 256
    publisher.undeclare()


def _forged_acks(session: zenoh.Session, ns: str, service: str, buffer: str, flood: _Flood) -> None:
    seen: dict[str, tuple[str, int]] = {}  # sub id -> (epoch, window base)

    def spy(sample: zenoh.Sample) -> None:
        attachment = sample.attachment
        if attachment is None:
            return
        try:
            head = msgpack.unpackb(attachment.to_bytes(), use_list=False)
        except Exception:  # a control message or anything else: not a notification
            return
        if type(head) is tuple and len(head) >= 7 and isinstance(head[0], str):
            base = head[5] if isinstance(head[5], int) else 0
            seen[str(sample.key_expr).rsplit("/", 1)[-1]] = (head[0], base)

    spy_sub = session.declare_subscriber(f"{ns}/@notify/{service}/{buffer}/*", spy)
    while not flood.stop.is_set():
        if not seen:
            flood.stop.wait(0.01)
            continue
        for sub_id, (epoch, base) in list(seen.items()):
            ack = bytes(msgpack.packb({"e": epoch, "s": base}))
            key = f"{ns}/@ack/{service}/{buffer}/{sub_id}"
            for _ in range(64):
                session.put(key, ack, congestion_control=zenoh.CongestionControl.DROP)
            flood.sent += 64
    spy_sub.undeclare()


def _churn(session: zenoh.Session, prefix: str, params: dict[str, Any], flood: _Flood) -> None:
    queue, batch = int(params.get("queue_size", 2)), int(params.get("batch", 8))
    mode = str(params.get("mode", "flow"))
    liveliness = session.liveliness()
    ids = itertools.count()
    while not flood.stop.is_set():
        tokens = [
            liveliness.declare_token(f"{prefix}/churn{next(ids)}/{mode}/{queue}/-1/churn~bench")
            for _ in range(batch)
        ]
        for token in tokens:
            token.undeclare()
        flood.sent += batch


def flood(params: dict[str, Any]) -> None:
    """The ``flood`` role (see the module doc)."""
    ns, service, buffer = params["namespace"], params["service"], params["buffer"]
    kind = params["kind"]
    if params.get("nice"):
        os.nice(int(params["nice"]))
    state = _Flood()
    with zenoh.open(_config(params)) as session:
        if kind == "acks":
            target: Any = (_acks, (session, f"{ns}/@ack/{service}/{buffer}", params, state))
        elif kind == "forged-acks":
            target = (_forged_acks, (session, ns, service, buffer, state))
        elif kind == "churn":
            target = (_churn, (session, f"{ns}/@sub/{service}/{buffer}", params, state))
        else:
            raise ValueError(f"unknown flood kind {kind!r}")
        thread = threading.Thread(target=target[0], args=target[1], daemon=True, name="flood")
        thread.start()
        reply(ready=True)

        def stop(_command: dict[str, Any]) -> dict[str, Any]:
            state.stop.set()
            thread.join(timeout=10.0)
            return {"count": state.sent}

        serve({"count": lambda _c: {"count": state.sent}, "stop": stop})
        state.stop.set()
        thread.join(timeout=10.0)


def flood_sink(params: dict[str, Any]) -> None:
    """The ``flood-sink`` role (see the module doc)."""
    prefix = f"{params['namespace']}/@%s/{params['service']}/{params['buffer']}/**"

    def drop(_sample: zenoh.Sample) -> None:
        return None

    with zenoh.open(_config(params)) as session:
        handler = zenoh.handlers.Callback(drop, indirect=False)
        acks = session.declare_subscriber(prefix % "ack", handler)
        tokens = session.liveliness().declare_subscriber(
            prefix % "sub", zenoh.handlers.Callback(drop, indirect=False)
        )
        meter = RssMeter()  # before any flood: its growth is from here
        reply(ready=True)

        def run(command: dict[str, Any]) -> dict[str, Any]:
            end = time.monotonic() + float(command["seconds"])
            while time.monotonic() < end:
                time.sleep(0.5)
                meter.sample()
            return {
                "growth": meter.total_max - meter.start_total,
                "private_growth": meter.private_max - meter.start_private,
                "shared_growth": meter.shared_max - meter.start_shared,
            }

        serve({"run": run})
        acks.undeclare()
        tokens.undeclare()


ROLES = {"flood": flood, "flood-sink": flood_sink}
