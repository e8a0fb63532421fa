"""``framegate launch FILE [--host NAME]``: start this host's services from a deploy file."""

from __future__ import annotations

import argparse
from pathlib import Path
from typing import Any

from middleware import NetworkConfig
from services.launch import Supervisor, load_deployment, process_specs

from ._common import command_parser, network, stop_on_signals


def register(subparsers: Any) -> None:
    parser = command_parser(
        subparsers, "launch", "start the services a deploy file assigns to this host"
    )
    parser.add_argument("file", help="deploy file (YAML), e.g. deploy/local.yaml")
    parser.add_argument("--host", help="which host of the file this machine is")
    parser.add_argument("--duration", type=float, help="stop after this many seconds")
    parser.add_argument("--no-colour", action="store_true", help="plain log prefixes")
    parser.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    deployment = load_deployment(args.file)
    text = Path(args.file).read_text()
    # defaults -> deploy file -> environment -> flags, for every process.
    specs = process_specs(
        deployment, args.host, NetworkConfig(), text=text, override=lambda net: network(args, net)
    )
    stop = stop_on_signals()
    supervisor = Supervisor(specs, colour=False if args.no_colour else None)
    names = ", ".join(s.name for s in specs)
    print(f"launching {names} (Ctrl-C stops everything)", flush=True)
    supervisor.start()
    try:
        supervisor.run(args.duration, stop=stop)
    except KeyboardInterrupt:  # a second Ctrl-C while stopping
        supervisor.stop(timeout_s=0.0)
    return 0
