"""``framegate run SERVICE [options]``: start one service by hand, in this process."""

from __future__ import annotations

import argparse
import importlib
from typing import Any

from ._common import command_parser, exit_on_sigterm, network

# Service type -> module with add_arguments, config_from_args and run(config, network).
SERVICES = {
    "camera": "services.nodes.camera",
    "gyro": "services.nodes.gyro",
    "mediator": "services.nodes.mediator",
    "detector": "services.nodes.detector",
}


def register(subparsers: Any) -> None:
    parser = command_parser(
        subparsers, "run", "start one service (camera, gyro, mediator, detector)", network=False
    )
    kinds = parser.add_subparsers(dest="service", metavar="SERVICE", required=True)
    for kind in SERVICES:
        module = importlib.import_module(SERVICES[kind])
        doc = (module.__doc__ or kind).strip().splitlines()[0]
        sub = command_parser(kinds, kind, doc)
        module.add_arguments(sub)
        sub.set_defaults(func=run, module=module)


def run(args: argparse.Namespace) -> int:
    exit_on_sigterm()
    config = args.module.config_from_args(args)
    try:
        return int(args.module.run(config, network(args)))
    except KeyboardInterrupt:
        return 0
