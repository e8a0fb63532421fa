"""``framegate run SERVICE [options]``: start one service by hand, in this process."""

from __future__ import annotations

import argparse
from typing import Any

from middleware import EXIT_NAME_TAKEN, ConfigError, NameTakenError, add_network_arguments
from services.lib.argtypes import FramegateParser, print_error
from services.nodes import SERVICES, describe, exit_with_parent, service

from ._common import command_parser, network, stop_on_signals


def register(subparsers: Any) -> None:
    parser = command_parser(
        subparsers,
        "run",
        "start one service (camera, gyro, mediator, detector, vision, ros2)",
        network=False,
    )
    # The service's own flags are parsed in run(): registering them here would import all
    # four services (OpenCV, SciPy) for every command and slow every restart.
    parser.add_argument(
        "service", nargs="?", choices=SERVICES, metavar="SERVICE", help=", ".join(SERVICES)
    )
    parser.add_argument(
        "args",
        nargs=argparse.REMAINDER,
        metavar="FLAGS",
        help="the service's flags (framegate run SERVICE --help)",
    )
    parser.usage = "framegate run [-h] SERVICE [FLAGS ...]"  # SERVICE is optional only to argparse
    parser.set_defaults(func=run)


def service_parser(name: str) -> argparse.ArgumentParser:
    """The parser of ``framegate run NAME``: the network flags plus the service's own."""
    parser = FramegateParser(prog=f"framegate run {name}", description=describe(name))
    add_network_arguments(parser)
    service(name).add_arguments(parser)
    return parser


def run(args: argparse.Namespace) -> int:
    if args.service is None:  # argparse would name its own "args" as missing too
        raise ConfigError(f"framegate run: name a service: {', '.join(SERVICES)}")
    svc = service(args.service)
    parsed = service_parser(args.service).parse_args(args.args)
    config = svc.config_from_args(parsed)
    # One Ctrl-C or SIGTERM sets ``stop``; the service returns and closes its session.
    stop = stop_on_signals()
    exit_with_parent(stop)
    try:
        return svc.run(config, network(parsed), stop)
    except NameTakenError as exc:
        # Its own exit code: a supervisor (launch) must not restart what cannot start.
        print_error(str(exc))
        return EXIT_NAME_TAKEN
