"""The Zenoh session of a node: opening it, and the one place where ``zenoh.ZError``
becomes a framegate error."""

from __future__ import annotations

import os
from collections.abc import Iterator
from contextlib import contextmanager

import zenoh

from ._config import ENDPOINT_FORM, NetworkConfig, zenoh_message
from ._errors import TransportError


@contextmanager
def zenoh_errors(action: str) -> Iterator[None]:
    """The one place where zenoh.ZError becomes a framegate error."""
    try:
        yield
    except zenoh.ZError as exc:
        raise TransportError(f"{action} failed in Zenoh: {zenoh_message(exc)}") from exc


# Zenoh's acceptor, receive and network runtimes handed over to its application runtime (one
# thread), unless the user set ``ZENOH_RUNTIME`` themselves. By default each is a thread of
# its own (receive: two), and every message framegate receives crossed two or three of them
# (the network thread's epoll wakes a receive worker by futex; an ack woke the acceptor and
# both receive workers); on one thread the worker that polls a socket reads it and runs the
# inbox callback itself (measured in docs/benchmarks.md). Framegate's callbacks only append
# to bounded inboxes, under the one GIL, so no parallelism is lost. The send runtime keeps
# its own thread: it sends the keepalives, which must not wait for a callback waiting for
# the GIL (with it on the same thread, a C extension holding the GIL for 2 s made peers
# drop the process), nor for a flood's reads.
ZENOH_RUNTIME = "(acc: (handover: app), rx: (handover: app), net: (handover: app))"
_RUNTIME_ENV = "ZENOH_RUNTIME"


def open_session(network: NetworkConfig) -> zenoh.Session:
    configs = network.zenoh_configs()
    last: Exception | None = None
    # Zenoh reads the variable once, when the process's first session starts its runtimes;
    # it is set only around that open, so child processes (a raw-Zenoh benchmark worker, a
    # tool) inherit the environment as it was.
    ours = _RUNTIME_ENV not in os.environ
    if ours:
        os.environ[_RUNTIME_ENV] = ZENOH_RUNTIME
    try:
        for conf in configs:
            try:
                return zenoh.open(conf)
            except zenoh.ZError as exc:
                last = exc
    finally:
        if ours:
            os.environ.pop(_RUNTIME_ENV, None)
    where = ", ".join(network.connect or network.listen) or f"local port {network.local_port}"
    raise TransportError(
        f"cannot open a Zenoh session ({where}): {zenoh_message(last) if last else 'no config'}; "
        f"check the endpoints ({ENDPOINT_FORM}) and that each to listen on is free on this host"
    ) from last
