"""``framegate router``: a Zenoh router (a hub where peers cannot reach each other directly)."""

from __future__ import annotations

import argparse
import re
from dataclasses import replace
from typing import Any

from middleware import ConfigError, Node, TransportError, listening_endpoints
from services.nodes import exit_with_parent

from ._common import command_parser, network, stop_on_signals


def register(subparsers: Any) -> None:
    parser = command_parser(subparsers, "router", "run a Zenoh router until Ctrl-C")
    parser.epilog = (
        "With no --listen (or FRAMEGATE_LISTEN, or a --config that names endpoints) it listens "
        "on tcp/127.0.0.1:PORT, PORT being FRAMEGATE_LOCAL_PORT (default 7447)."
    )
    parser.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    config = network(args)
    if not config.listen and not config.config_file:
        # Loopback unless asked: a router reachable from the network is an explicit choice
        # (`--listen tcp/0.0.0.0:7447`, or a deploy/config file that says so). On the
        # rendezvous port (FRAMEGATE_LOCAL_PORT), where this host's processes look first.
        config = replace(config, listen=(f"tcp/127.0.0.1:{config.local_port}",))
    config = replace(config, mode="router")
    stop = stop_on_signals()
    exit_with_parent(stop)  # a router started by `launch` ends with it, however it ends
    endpoints = ", ".join(config.listen) or f"per {config.config_file}"
    try:
        node = Node(network=config)
    except TransportError as exc:
        if "Cannot assign requested address" in str(exc):  # EADDRNOTAVAIL
            found = re.search(r"bound to (\S+):\s", str(exc))
            where = found.group(1) if found else endpoints
            raise ConfigError(
                f"cannot listen on {where}: that address is not one of this machine's "
                "(a deploy file's --host for another machine, or a changed address?); run it "
                "on that machine or listen on an address of this one"
            ) from exc
        if "in use" not in str(exc):
            raise
        raise ConfigError(
            f"cannot listen on {endpoints}: the port is already in use (another router, or "
            "another program); choose another with --listen tcp/127.0.0.1:PORT (or "
            "FRAMEGATE_LOCAL_PORT / FRAMEGATE_LISTEN)"
        ) from exc
    with node:
        # What the process really listens on: a port 0 in --listen is any free port.
        listening = listening_endpoints(config.listen_endpoints())
        print(f"router listening on {', '.join(listening) or endpoints}", flush=True)
        stop.wait()
    return 0
