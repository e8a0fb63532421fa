"""``framegate demo``: the whole pipeline on this host, no router, no configuration."""

from __future__ import annotations

import argparse
from typing import Any

from services.tools.demo import DemoConfig, print_summary, run_demo

from ._common import command_parser, network, print_json, stop_on_signals


def register(subparsers: Any) -> None:
    parser = command_parser(
        subparsers,
        "demo",
        "run camera, gyro, mediator and detector on this host with a live status view",
        json_flag=True,
    )
    d = DemoConfig()
    parser.add_argument("--duration", type=float, default=d.duration_s, help="seconds to run")
    parser.add_argument("--seed", type=int, default=d.seed, help="simulator seed")
    parser.add_argument("--policy", choices=["paper", "replace"], default=d.policy)
    parser.add_argument("--b0", type=float, default=d.b0_px, help="blur scale b0 in pixels")
    parser.add_argument("--queue", type=int, default=d.queue, help="detector queue size N")
    parser.add_argument(
        "--service-factor",
        type=float,
        default=d.service_factor,
        help="detector processing time as a multiple of the frame period",
    )
    parser.add_argument("--logs", action="store_true", help="show the services' own logs")
    parser.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    stop = stop_on_signals()
    config = DemoConfig(
        duration_s=args.duration,
        seed=args.seed,
        policy=args.policy,
        b0_px=args.b0,
        queue=args.queue,
        service_factor=args.service_factor,
        show_logs=args.logs,
    )
    summary = run_demo(config, network(args), stop)
    if args.json:
        print_json(summary)
    else:
        print_summary(summary)
    return 0
