"""The Zenoh session of a node: opening it, and the one place where ``zenoh.ZError``
becomes a framegate error."""

from __future__ import annotations

import os
import threading
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


# Zenoh's acceptor and network runtimes handed over to its receive runtime, unless the user
# set ``ZENOH_RUNTIME`` themselves. By default each is a thread of its own, and every
# message framegate receives crossed two or three of them (the network thread's epoll wakes
# a receive worker by futex; an ack woke the acceptor and both receive workers); with the
# network runtime's socket polling in the receive runtime, the worker that polls a socket
# mostly reads it and runs the inbox callback itself (measured in docs/benchmarks.md).
# Kept apart, measured: the receive runtime's two workers (with one, the reads of an ack
# flood queued the honest acks behind them) and the send thread, which sends the
# keepalives (on the receiving thread, a callback waiting 2 s for the GIL made peers drop
# the process).
ZENOH_RUNTIME = "(acc: (handover: rx), net: (handover: rx))"
_RUNTIME_ENV = "ZENOH_RUNTIME"
# Zenoh reads the variable once, when the process's first session starts its runtimes; it
# is set only around the opens until one succeeded, so child processes (a raw-Zenoh
# benchmark worker, a tool) inherit the environment as it was. The lock keeps two threads'
# first opens from setting and removing it under each other.
_first_open = threading.Lock()
_runtime_started = False


def open_session(network: NetworkConfig) -> zenoh.Session:
    global _runtime_started
    if _runtime_started:
        return _open(network)
    with _first_open:
        ours = not _runtime_started and _RUNTIME_ENV not in os.environ
        if ours:
            os.environ[_RUNTIME_ENV] = ZENOH_RUNTIME
        try:
            session = _open(network)
            _runtime_started = True
            return session
        finally:
            if ours:
                os.environ.pop(_RUNTIME_ENV, None)


def _open(network: NetworkConfig) -> zenoh.Session:
    # Zenoh reads a config's certificates and keys only when it connects, and a missing one
    # then looks like an unreachable router after the connect timeout (10 s): name it now.
    network.check_files()
    configs = network.zenoh_configs()
    last: Exception | None = None
    for conf in configs:
        try:
            return zenoh.open(conf)
        except zenoh.ZError as exc:
            last = exc
    where = ", ".join(network.connect or network.listen) or (
        network.config_name if network.config_file else f"local port {network.local_port}"
    )
    raise TransportError(
        f"cannot open a Zenoh session ({where}): {zenoh_message(last) if last else 'no config'}; "
        f"check the endpoints ({ENDPOINT_FORM}) and that each to listen on is free on this host"
    ) from last
