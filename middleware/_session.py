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


# Zenoh's runtimes (``ZENOH_RUNTIME``: acceptor, receive, send, network) all handed over to
# its one application worker thread, unless the user set ``ZENOH_RUNTIME`` themselves. By
# default each is a thread of its own (receive: two), so every message framegate sends or
# receives crosses two or three of them (the network thread's epoll wakes a receive worker;
# each put wakes the send thread); on one thread the worker that polls the socket reads it
# and runs the inbox callback itself. Measured on a 2-core machine (docs/benchmarks.md):
# wake-ups per 64 B element halved, CPU per element down by a fifth to a third. Framegate's
# callbacks only append to bounded inboxes, so no parallelism is lost: they all need the
# one GIL anyway.
ZENOH_RUNTIME = (
    "(acc: (handover: app), rx: (handover: app), tx: (handover: app), net: (handover: app))"
)
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
