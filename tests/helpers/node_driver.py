"""A real framegate node in its own process, driven by JSON lines on stdin.

Tests start it with ``python -m tests.helpers.node_driver NAME [--connect/--listen ...]``
and send one JSON command per line; it answers one JSON line each:
{"ok": true, ...} or {"ok": false, "error": "<ExceptionClass>", "message": "..."}.
Every wait a command asks for (``timeout``, ``wait_s``) is scaled by the suite's timeout
scale (``tests/helpers/timing.py``), which the test process passes on in the environment.
"""

from __future__ import annotations

import argparse
import base64
import json
import sys
from typing import Any

from middleware import (
    FramegateError,
    Node,
    Producer,
    Retention,
    Subscription,
    SubscriptionMode,
    add_network_arguments,
    make_metadata,
    network_from_args,
    tightest_flow,
)
from tests.helpers.timing import scaled


def _element_json(element: Any) -> dict[str, Any]:
    return {
        "t": element.timestamp_ns,
        "payload": base64.b64encode(element.payload).decode(),
        "metadata": element.metadata.decode(),
    }


class _FailingPublisher:
    def __init__(self, inner: Any, owner: _FailingSession) -> None:
        self._inner, self._owner = inner, owner

    def put(self, *args: Any, **kwargs: Any) -> Any:
        if self._owner.failures > 0:
            self._owner.failures -= 1
            import zenoh

            raise zenoh.ZError("injected send failure")
        return self._inner.put(*args, **kwargs)

    def undeclare(self) -> None:
        self._inner.undeclare()


class _FailingSession:
    """A session whose publishers' next ``failures`` puts raise."""

    def __init__(self, inner: Any, failures: int) -> None:
        self._inner, self.failures = inner, failures

    def declare_publisher(self, *args: Any, **kwargs: Any) -> _FailingPublisher:
        return _FailingPublisher(self._inner.declare_publisher(*args, **kwargs), self)

    def __getattr__(self, name: str) -> Any:
        return getattr(self._inner, name)


def main() -> int:
    parser = argparse.ArgumentParser()
    parser.add_argument("name", nargs="?")
    add_network_arguments(parser)
    args = parser.parse_args()
    producers: dict[str, Producer] = {}
    subs: dict[str, Subscription] = {}
    with Node(args.name or None, network_from_args(args)) as node:
        print(json.dumps({"ok": True, "ready": True}), flush=True)
        for line in sys.stdin:
            cmd = json.loads(line)
            op = cmd.pop("op")
            try:
                result = _do(node, producers, subs, op, cmd)
                reply = {"ok": True, **result}
            except FramegateError as exc:
                reply = {"ok": False, "error": type(exc).__name__, "message": str(exc)}
            print(json.dumps(reply), flush=True)
            if op == "exit":
                break
    return 0


def _do(
    node: Node,
    producers: dict[str, Producer],
    subs: dict[str, Subscription],
    op: str,
    cmd: dict[str, Any],
) -> dict[str, Any]:
    if op == "offer":
        retention = Retention(**cmd.get("retention", {}))  # e.g. {"max_payload_bytes": 1024}
        if cmd.get("unchecked"):
            # An attacker does not ask whether the name is taken: skip that courtesy check,
            # so that a test can show what the router (not framegate) stops.
            import middleware._service as service_module

            service_module._instances = lambda *_args, **_kwargs: []
        producers[cmd["buffer"]] = node.offer(
            cmd["buffer"], kind=cmd.get("kind", "generic"), retention=retention
        )
        return {}
    if op == "put":
        producer = producers[cmd["buffer"]]
        # Values pass through untouched (wrong types included): the API must say what is wrong.
        t = cmd["t"]
        if "payload" in cmd:
            payload: Any = base64.b64decode(cmd["payload"])
        elif "payload_size" in cmd:
            payload = bytes(int(cmd["payload_size"]))
        elif "payload_raw" in cmd:
            payload = cmd["payload_raw"]
        else:
            payload = b"p%d" % t if isinstance(t, int) else b"p"
        if "metadata_b64" in cmd:
            metadata: Any = base64.b64decode(cmd["metadata_b64"])
        elif "metadata" in cmd:
            metadata = cmd["metadata"]
        else:
            metadata = make_metadata(producer.kind, t if isinstance(t, int) else 0)
        producer.put(t, payload, metadata, wait_s=scaled(float(cmd.get("wait_s", 0))))
        return {}
    if op == "fill":
        subs = producers[cmd["buffer"]].subscriptions()
        tightest = tightest_flow(subs)  # the load indicator, as the mediator reads it
        return {
            "fill": tightest.fill if tightest is not None else 0.0,
            "subscriptions": [
                {"id": s.subscription_id, "mode": s.mode.value, "queued": s.queued} for s in subs
            ],
        }
    if op == "wait_subscribers":
        ok = producers[cmd["buffer"]].wait_for_subscribers(
            int(cmd["count"]), timeout_s=scaled(float(cmd["timeout"]))
        )
        return {"registered": ok}
    if op == "subscribe":
        sub = node.subscribe(
            cmd["target"],
            queue_size=int(cmd["queue"]),
            mode=SubscriptionMode(cmd.get("mode", "flow")),
        )
        subs[cmd["target"]] = sub
        return {"id": sub.subscription_id}
    if op == "take":
        sub = subs[cmd["target"]]
        note = sub.take(timeout_s=scaled(float(cmd.get("timeout", 2.0))))
        if note is None:
            return {"notification": None, "missed_total": sub.missed_total}
        element = sub.fetch(note)
        return {
            "notification": {"t": note.timestamp_ns, "missed": note.missed},
            "element": _element_json(element),
            "missed_total": sub.missed_total,
        }
    if op == "stats":
        sub = subs[cmd["target"]]
        return {"pending": sub.pending, "missed_total": sub.missed_total}
    if op == "query":
        elements = node.query(cmd["target"], time_range=cmd.get("time_range"), last=cmd.get("last"))
        return {"elements": [_element_json(e) for e in elements]}
    if op == "fail_sends":
        # The next ``count`` notification sends of this buffer fail as a Zenoh error would.
        producer = producers[cmd["buffer"]]
        producer._session = _FailingSession(producer._session, int(cmd["count"]))  # type: ignore[assignment]
        return {}
    if op == "exit":
        return {}
    raise FramegateError(f"unknown op {op!r}")


if __name__ == "__main__":
    sys.exit(main())
