"""A plain Zenoh session for tests that play a peer framegate does not control."""

from __future__ import annotations

import json

import zenoh


def open_session(endpoint: str, *, listen: bool = False) -> zenoh.Session:
    """A peer session connected to ``endpoint`` (``listen``: listening on it), multicast
    scouting off."""
    conf = zenoh.Config()
    conf.insert_json5("mode", '"peer"')
    conf.insert_json5("scouting/multicast/enabled", "false")
    conf.insert_json5("listen/endpoints" if listen else "connect/endpoints", json.dumps([endpoint]))
    return zenoh.open(conf)
