"""Finding the ``SERVICE/BUFFER`` a command names on the live network, or saying why not.

(Also the one-line JSON output that the streaming commands share: ``watch``, ``hz``, ``play``.)

A peer whose ``--connect`` endpoint is unreachable still opens (Zenoh retries in the
background), so "nothing answers" must be detected here: wait a bounded time for the
service's liveliness token, then name the endpoint that was tried and what is live.
"""

from __future__ import annotations

import argparse
import json
import socket
import sys
import time
from typing import Any

from middleware import (
    BufferInfo,
    FramegateError,
    NetworkConfig,
    Node,
    NotFoundError,
    ServiceInfo,
    Subscription,
    SubscriptionMode,
    endpoint_parts,
    listing,
    split_target,
)
from services.lib.argtypes import did_you_mean, positive_float

DEFAULT_TIMEOUT_S = 3.0


def add_timeout_argument(parser: argparse.ArgumentParser) -> None:
    parser.add_argument(
        "--timeout",
        type=positive_float,
        default=DEFAULT_TIMEOUT_S,
        metavar="S",
        help=f"seconds to wait for the service to answer (default {DEFAULT_TIMEOUT_S:g})",
    )


def where(net: NetworkConfig) -> str:
    """The endpoints this process tried, for error messages."""
    if net.connect:
        return "via " + ", ".join(net.connect)
    if net.config_file:
        return f"with the {net.config_name}"
    if net.listen:
        return "listening on " + ", ".join(net.listen) + " (nobody connected)"
    return f"via the local rendezvous tcp/127.0.0.1:{net.local_port}"


def unreachable(net: NetworkConfig, timeout_s: float = 1.0) -> str | None:
    """The first ``--connect`` TCP endpoint that refuses a connection, with the reason.

    Zenoh keeps retrying such an endpoint in the background and says nothing, so a plain
    TCP connect tells "nothing answers there" from "nothing is live".
    """
    for endpoint in net.connect:
        proto, host, port = endpoint_parts(endpoint)
        if proto not in ("tcp", "tls"):
            continue  # udp, quic, serial...: no connection to try
        if not host or not port.isdigit():
            return f"{endpoint} (no port number: write {proto}/HOST:PORT)"
        if not 0 < int(port) < 65536:
            return f"{endpoint} ({port} is not a port number: use 1..65535)"
        try:
            with socket.create_connection((host.strip("[]"), int(port)), timeout=timeout_s):
                pass
        except OSError as exc:
            reason = exc.strerror or str(exc) or type(exc).__name__
            return f"{endpoint} ({reason})"
    return None


def connected_late(node: Node, timeout_s: float) -> bool:
    """Whether a ``--connect`` session that had no connection yet got one within
    ``timeout_s``: a loaded router completes its handshake late (seen after 2 s at load 40),
    and an empty answer given before it did is not the router's answer."""
    if not node.network.connect or node.connected() > 0 or unreachable(node.network):
        return False
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        if node.connected() > 0:
            return True
        time.sleep(0.05)
    return False


def nothing_answered(node: Node, waited_s: float) -> NotFoundError | None:
    """The error to raise when no process at all answered through the endpoints the user
    named (``--connect``), or None: a refused or unreachable endpoint is not "no services".

    Alone on the local rendezvous is a true answer (nothing runs on this host), not this."""
    if not node.network.connect or node.connected() > 0:
        return None
    if bad := unreachable(node.network):
        return NotFoundError(f"cannot reach {bad}; is the router or service running there?")
    return NotFoundError(
        f"nothing answered {where(node.network)} (waited {waited_s:g} s); "
        "is a router or service running there, and is the endpoint right (--connect, or "
        "FRAMEGATE_CONNECT)?"
    )


def _where_else(net: NetworkConfig) -> str:
    """Where else the service may be, when nothing was live where this process looked."""
    if net.connect or net.listen or net.config_file:
        return (
            "is the service running, and is the endpoint right (--connect, or FRAMEGATE_CONNECT)?"
        )
    # Alone on the loopback rendezvous: the services may meet on another port (a variable
    # set in one shell and not in the other), or run on another host.
    return (
        f"is the service running on this host with the same rendezvous port ({net.local_port}; "
        "FRAMEGATE_LOCAL_PORT sets it), or on another host (then --connect to it)?"
    )


def other_namespaces(node: Node, timeout_s: float = 1.0) -> str | None:
    """Where services are live when none is in the node's namespace, and how to go there
    (a FRAMEGATE_NAMESPACE left set in a shell hid every service), or None."""
    own = node.network.namespace
    try:
        found = node.live_namespaces(timeout_s=min(timeout_s, 1.0))
    except FramegateError:
        return None
    others = [(ns, names) for ns, names in found.items() if ns != own]
    if not others:
        return None
    listed = "; ".join(
        f"{ns!r} ({', '.join(names[:4])}{', ...' if len(names) > 4 else ''})"
        for ns, names in others[:3]
    )
    first = others[0][0]
    return (
        f"services are live under namespace {listed}: pass --namespace {first} "
        f"or set FRAMEGATE_NAMESPACE={first}"
    )


def wait_for_service(node: Node, service: str, timeout_s: float) -> None:
    """Return once ``service`` is live; NotFoundError naming the endpoint otherwise."""
    deadline = time.monotonic() + timeout_s
    live: list[str] = []
    while True:
        live = node.live_services(timeout_s=max(0.1, min(1.0, timeout_s)))
        if service in live:
            return
        if time.monotonic() >= deadline:
            break
        time.sleep(0.05)
    if not live:
        if error := nothing_answered(node, timeout_s):
            raise error
        if bad := unreachable(node.network):
            raise NotFoundError(f"cannot reach {bad}; is the router or service running there?")
        raise NotFoundError(
            f"no live services reachable {where(node.network)} in namespace "
            f"{node.network.namespace!r} (waited {timeout_s:g} s); "
            + (other_namespaces(node) or _where_else(node.network))
        )
    raise NotFoundError(
        f"no live service named {service!r}{did_you_mean(service, live, quote=True)}; "
        f"live services: {listing(live)}"
    )


def resolve(node: Node, target: str, timeout_s: float) -> tuple[ServiceInfo, BufferInfo]:
    """The live service and buffer ``target`` (``SERVICE/BUFFER``) names."""
    service, buffer = split_target(target)
    deadline = time.monotonic() + timeout_s
    wait_for_service(node, service, timeout_s)
    while True:
        info = node.service_info(service, timeout_s=timeout_s)
        for candidate in info.buffers:
            if candidate.buffer == buffer:
                return info, candidate
        # A service that has just started may not have offered all its buffers yet.
        if time.monotonic() >= deadline:
            break
        time.sleep(0.1)
    offered = [b.buffer for b in info.buffers]
    raise NotFoundError(
        f"service {service!r} has no buffer {buffer!r}{did_you_mean(buffer, offered, quote=True)}; "
        f"it offers: {', '.join(offered) or 'none'}"
    )


def observer(node: Node, target: str, queue: int, timeout_s: float) -> Subscription:
    """An observer of ``target`` with a queue of ``queue``: how ``echo``, ``hz`` and
    ``record`` watch a buffer (``resolve`` it first: a misspelt name is then one line)."""
    return node.subscribe(
        target, queue_size=queue, mode=SubscriptionMode.OBSERVE, wait_s=max(2.0, timeout_s)
    )


def print_json_line(data: Any) -> None:
    """One JSON object per line (JSON Lines): what streaming commands print with --json."""
    sys.stdout.write(json.dumps(data, default=str) + "\n")
    sys.stdout.flush()


# Clocks closer than this are taken to agree: a start or stop within it of an element's
# stamp is inside the stop's slack anyway, and on one host the measured offset is noise.
CLOCKS_AGREE_NS = 50_000_000


def producer_offset_ns(node: Node, service: str, timeout_s: float) -> int:
    """How far ``service``'s clock runs ahead of ours (negative: behind), when that is more
    than the measurement's error and ``CLOCKS_AGREE_NS``; else 0. Not on a peer's word: a
    peer answering ``@info`` in the service's name with a clock an hour behind would move
    the stop an hour early, so when more than one session answers (or none) it is 0."""
    try:
        info = node.service_info(service, timeout_s=timeout_s, unambiguous=True)
    except FramegateError:
        return 0
    offset = info.clock_offset_ns
    if offset is None:
        return 0
    error = (info.round_trip_ns or 0) // 2
    return offset if abs(offset) > max(error, CLOCKS_AGREE_NS) else 0
