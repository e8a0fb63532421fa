"""``framegate demo``: the whole pipeline on this host, filtered against uncontrolled."""

from __future__ import annotations

import argparse
import sys
from pathlib import Path
from typing import Any

from middleware import NotFoundError
from services.lib.argtypes import non_negative_float, non_negative_int, positive_float, positive_int
from services.lib.decisions import POLICIES
from services.lib.sim import ScenarioConfig, approach_cache_dir
from services.tools.demo import SOURCES, DemoConfig, print_summary, run_demo

from ._common import (
    command_parser,
    network,
    print_json,
    report_failures,
    stop_on_signals,
)
from ._target import unreachable


def register(subparsers: Any) -> None:
    parser = command_parser(
        subparsers,
        "demo",
        "run camera, gyro, mediator and two detectors (behind the mediator, and uncontrolled) "
        "on this host; show the markers each recognizes",
        json_flag=True,
    )
    d = DemoConfig()
    parser.add_argument(
        "--duration",
        type=positive_float,
        default=d.duration_s,
        help="seconds to run, after the approach is rendered (default %(default)g)",
    )
    parser.add_argument(
        "--seed", type=non_negative_int, default=d.seed, help="simulator seed (default %(default)s)"
    )
    parser.add_argument(
        "--policy",
        choices=sorted(POLICIES),
        default=d.policy,
        help="the mediator's policy (default %(default)s)",
    )
    parser.add_argument(
        "--source",
        choices=SOURCES,
        default=d.source,
        help="prerendered: the approach rendered once and cached (keeps 15 frames/s); "
        "sim: rendered live (too slow for small machines); default %(default)s",
    )
    parser.add_argument(
        "--floor",
        choices=ScenarioConfig.floor_names(),
        default=d.floor,
        help="floor of the approach (rough: bumpy enough for blur to matter; default %(default)s)",
    )
    parser.add_argument(
        "--cache",
        type=Path,
        help=f"where prerendered approaches are kept (default {approach_cache_dir()})",
    )
    parser.add_argument(
        "--b0", type=positive_float, default=d.b0_px, help="blur scale b0 (px; default %(default)g)"
    )
    parser.add_argument(
        "--queue", type=positive_int, default=d.queue, help="detector queue N (default %(default)s)"
    )
    parser.add_argument(
        "--service-factor",
        type=non_negative_float,
        default=d.service_factor,
        help="detector processing time as a multiple of the frame period (both detectors; "
        "default %(default)g)",
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
        source=args.source,
        floor=args.floor,
        cache=args.cache,
        show_logs=args.logs,
    )
    net = network(args)
    if bad := unreachable(net):
        # A --connect (or FRAMEGATE_CONNECT) replaces the rendezvous: the demo's services
        # would meet nowhere and it would show zeros for its whole duration.
        raise NotFoundError(
            f"cannot reach {bad}; the demo's services meet there: start the router first, "
            "or run the demo without --connect (and FRAMEGATE_CONNECT unset)"
        )
    # With --json, stdout is the summary alone; the status lines go to stderr.
    summary = run_demo(config, net, stop, status_out=sys.stderr if args.json else None)
    if args.json:
        print_json(summary)
    else:
        print_summary(summary)
    return report_failures(summary.get("failures", []))
