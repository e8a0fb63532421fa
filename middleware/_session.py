"""The Zenoh session of a node: opening it, and the one place where ``zenoh.ZError``
becomes a framegate error."""

from __future__ import annotations

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


def open_session(network: NetworkConfig) -> zenoh.Session:
    configs = network.zenoh_configs()
    last: Exception | None = None
    for conf in configs:
        try:
            return zenoh.open(conf)
        except zenoh.ZError as exc:
            last = exc
    where = ", ".join(network.connect or network.listen) or f"local port {network.local_port}"
    raise TransportError(
        f"cannot open a Zenoh session ({where}): {zenoh_message(last) if last else 'no config'}; "
        f"check the endpoints ({ENDPOINT_FORM}) and that each to listen on is free on this host"
    ) from last
