"""``framegate view``: stream the running pipeline to Foxglove (WebSocket, ws://127.0.0.1:8765)."""

from __future__ import annotations

import argparse
import shutil
import sys
from typing import Any

from middleware import OBSERVE_QUEUE_MAX
from services.lib.argtypes import positive_float, positive_int, queue_size
from services.tools.view import (
    DEFAULT_BACKLOG,
    DEFAULT_HOST,
    DEFAULT_PORT,
    DEFAULT_QUEUE,
    VIEW_PORT_ENV,
    Status,
    ViewConfig,
    default_port,
    installed_layout,
    parse_target,
    run_view,
)

from ._common import command_parser, network, stop_on_signals
from ._target import add_timeout_argument, print_json_line, unreachable


def register(subparsers: Any) -> None:
    parser = command_parser(
        subparsers,
        "view",
        "stream buffers live to Foxglove, with the mediator's verdicts and the detections "
        "drawn on the frames (observing: never slows the pipeline)",
        json_flag=True,
    )
    parser.add_argument(
        "targets",
        nargs="*",
        metavar="SERVICE/BUFFER",
        help="buffers (or whole services) to stream; default: every live buffer",
    )
    parser.add_argument(
        "--port",
        type=int,
        help=f"WebSocket port (0: any free one; default ${VIEW_PORT_ENV}, else {DEFAULT_PORT})",
    )
    parser.add_argument(
        "--host",
        default=DEFAULT_HOST,
        help=f"address to listen on (default {DEFAULT_HOST}; 0.0.0.0 exposes the camera)",
    )
    parser.add_argument(
        "--jpeg",
        type=int,
        metavar="QUALITY",
        help="send frames as JPEG (foxglove.CompressedImage) of this quality, 1-100",
    )
    parser.add_argument(
        "--queue",
        type=queue_size(OBSERVE_QUEUE_MAX),
        default=DEFAULT_QUEUE,
        metavar="N",
        help=f"observer queue per frame buffer (default {DEFAULT_QUEUE}; others hold at least 32)",
    )
    parser.add_argument(
        "--backlog",
        type=positive_int,
        default=DEFAULT_BACKLOG,
        metavar="N",
        help=f"messages buffered per client before its oldest are dropped (default "
        f"{DEFAULT_BACKLOG})",
    )
    parser.add_argument("--duration", type=positive_float, metavar="S", help="stop after S seconds")
    add_timeout_argument(parser)
    parser.epilog = (
        "Open Foxglove, choose 'Open connection', 'Foxglove WebSocket', ws://127.0.0.1:8765, "
        "and import the layout view names at start (installed with framegate; also "
        "deploy/foxglove-layout.json). A named buffer that no live service offers is an error "
        "after --timeout. --json prints the status as JSON Lines."
    )
    parser.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    for target in args.targets:
        parse_target(target)  # a misspelt name fails now, not silently never
    config = ViewConfig(
        targets=tuple(args.targets),
        host=args.host,
        port=default_port() if args.port is None else args.port,
        jpeg_quality=args.jpeg,
        queue=args.queue,
        backlog=args.backlog,
        duration_s=args.duration,
        discovery_timeout_s=args.timeout,
    )
    stop = stop_on_signals()
    tty = sys.stdout.isatty() and not args.json

    def started(url: str) -> None:
        if config.exposed:
            print(
                f"warning: listening on {config.host}: anyone who can reach this machine on "
                f"port {url.rsplit(':', 1)[1]} can watch the camera",
                file=sys.stderr,
                flush=True,
            )
        layout = str(installed_layout())
        if args.json:
            print_json_line({"event": "listening", "url": url, "layout": layout})
        else:
            print(f"serving Foxglove on {url}; Ctrl-C to stop", flush=True)
            print(f"Foxglove layout: {layout}", flush=True)

    def report(status: Status) -> None:
        if args.json:
            print_json_line(status.json())
        else:
            line = status.line()
            if tty:  # one line redrawn in place: it must fit the terminal
                line = line[: shutil.get_terminal_size().columns - 1]
            print(("\r\x1b[K" if tty else "") + line, end="" if tty else "\n", flush=True)

    net = network(args)
    if bad := unreachable(net):
        # Not an error: a viewer may well start before the robot. But not silence either.
        print(
            f"warning: cannot reach {bad}; showing nothing until it answers",
            file=sys.stderr,
            flush=True,
        )
    counters = run_view(config, net, stop=stop, report=report, started=started)
    if tty:
        print()
    published = sum(counters.published.values())
    missed = sum(counters.missed.values())
    if args.json:
        print_json_line({"event": "stopped", "published": published, "missed": missed})
    else:
        print(f"stopped: {published} messages published, {missed} notifications missed")
    return 0
