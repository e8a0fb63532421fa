"""``framegate calibrate DIR``: derive the mediator's blur scale b0 from a recorded sequence."""

from __future__ import annotations

import argparse
from dataclasses import asdict
from pathlib import Path
from typing import Any

from ._common import command_parser, print_json


def register(subparsers: Any) -> None:
    parser = command_parser(
        subparsers,
        "calibrate",
        "derive b0 (px) from a dataset: the blur at which marker recognition halves",
        network=False,
        json_flag=True,
    )
    parser.add_argument(
        "dataset",
        help="dataset directory in the layout of services/lib/sim/DATASET.md, as "
        "framegate simulate writes it (not an .mcap recording)",
    )
    parser.add_argument("--no-progress", action="store_true", help="no progress bar")
    parser.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    from services.lib.calibrate import calibrate_b0

    result = calibrate_b0(Path(args.dataset), progress=not args.no_progress)
    if args.json:
        print_json(asdict(result))
        return 0
    print(f"b0 = {result.b0_px:.2f} px  ({result.trials} trials over {result.frames} frames)")
    for name, value in sorted(result.per_marker_b0_px.items()):
        print(f"  {name:<8} b0 = {value:.2f} px")
    if result.skipped_no_gyro:
        print(f"  {result.skipped_no_gyro} frames had no gyro coverage and were skipped")
    print(f"use it with: framegate run mediator --b0 {result.b0_px:.1f}")
    return 0
