"""``framegate simulate``: render the bumpy-approach scenario into a dataset directory."""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path
from typing import Any

from tqdm import tqdm

from middleware import ConfigError
from services.lib.argtypes import non_negative_int, positive_float, positive_int
from services.lib.sim import (
    ScenarioConfig,
    read_dataset,
    recognition_report,
    simulate,
    write_report,
)

from ._common import counted

# What a flag left out means: the scenario's own defaults, shown in the help.
_DEFAULTS = ScenarioConfig()


def register(subparsers: Any) -> None:
    """Add the ``simulate`` command."""
    parser = subparsers.add_parser(
        "simulate",
        help="render the bumpy-approach scenario (frames, gyro, truth) into a dataset",
        description="Render the paper's marker-approach scenario: motion-blurred mono8 frames, "
        "the gyro stream and per-frame ground truth, in the layout of services/lib/sim/DATASET.md. "
        "Parameters: defaults, then --config, then --set, then the named flags.",
    )
    parser.add_argument("--out", type=Path, required=True, help="dataset directory to write")
    parser.add_argument(
        "--seed", type=non_negative_int, help=f"random seed (default {_DEFAULTS.seed})"
    )
    parser.add_argument(
        "--frames", type=positive_int, help=f"number of frames (default {_DEFAULTS.frame_count})"
    )
    parser.add_argument(
        "--exposure-ms",
        type=positive_float,
        help=f"exposure time (default {_DEFAULTS.exposure_ns / 1e6:g})",
    )
    parser.add_argument(
        "--floor", choices=ScenarioConfig.floor_names(),
        help="bump preset: smooth, default or rough (applied before --config and --set)",
    )  # fmt: skip
    parser.add_argument(
        "--config", type=Path, help="a scenario.json to start from, e.g. another dataset's"
    )
    parser.add_argument(
        "--set",
        action="append",
        default=[],
        metavar="NAME=VALUE",
        help="override any ScenarioConfig parameter (JSON value), e.g. --set camera_tilt_deg=3",
    )
    parser.add_argument(
        "--report", action="store_true", help="decode every frame and print recognition vs blur"
    )
    parser.add_argument("--force", action="store_true", help="replace a dataset already in --out")
    parser.add_argument("--no-progress", action="store_true", help="no progress bar")
    parser.add_argument("--json", action="store_true", help="print the summary as JSON")
    parser.set_defaults(func=run)


def build_config(args: argparse.Namespace) -> ScenarioConfig:
    """The scenario from defaults, --config, --set and the named flags, in that order."""
    values: dict[str, Any] = {}
    if getattr(args, "floor", None) is not None:
        values.update(ScenarioConfig().with_floor(args.floor).to_dict())
        values.pop("seed")
    if args.config is not None:
        try:
            data = json.loads(args.config.read_text(encoding="utf-8"))
        except (OSError, ValueError) as exc:
            raise ConfigError(f"cannot read scenario file {args.config}: {exc}") from exc
        if not isinstance(data, dict):
            names = {"list": "an array", "str": "a string", "bool": "true or false"}
            found = names.get(type(data).__name__, "null" if data is None else "a number")
            raise ConfigError(
                f"scenario file {args.config} holds {found}; it needs an object of "
                'parameters, e.g. {"seed": 3, "frame_count": 120}'
            )
        values.update(data)
    for item in args.set:
        name, sep, text = item.partition("=")
        if not sep:
            raise ConfigError(f"--set expects NAME=VALUE, got {item!r}")
        try:
            values[name.strip()] = json.loads(text)
        except ValueError:
            values[name.strip()] = text
    if args.seed is not None:
        values["seed"] = args.seed
    if args.frames is not None:
        values["frame_count"] = args.frames
    if args.exposure_ms is not None:
        values["exposure_ns"] = round(args.exposure_ms * 1e6)
    defaults = ScenarioConfig()
    for name, value in values.items():
        # JSON gives 60000000.0 for an int field written as 6e7; accept whole numbers.
        current = getattr(defaults, name, None)
        if type(current) is int and isinstance(value, float) and value.is_integer():
            values[name] = int(value)
        elif type(current) is float and type(value) is int:
            values[name] = float(value)
    try:
        return ScenarioConfig.from_dict(values)
    except TypeError as exc:
        raise ConfigError(f"bad scenario parameter: {exc}") from exc


def run(args: argparse.Namespace) -> int:
    """Render the dataset; with --report also decode it and write report.json."""
    config = build_config(args)
    progress = not args.no_progress and not args.json
    try:
        result = simulate(config, args.out, progress=progress, overwrite=args.force)
    except KeyboardInterrupt:  # the writer removed the unfinished dataset
        print(f"simulate: stopped; nothing was kept in {args.out}", file=sys.stderr)
        raise
    summary: dict[str, Any] = {
        "dataset": str(result.root),
        "frames": result.frame_count,
        "render_s": round(result.render_s, 3),
        "frames_per_s": round(result.frames_per_s, 2),
    }
    report = None
    if args.report:
        dataset = read_dataset(result.root)
        # disable=None: no bar when stderr is no terminal (a log gets no \r updates).
        disable = None if progress else True
        with tqdm(total=len(dataset), desc="decoding", unit="frame", disable=disable) as bar:
            report = recognition_report(dataset, on_frame=lambda _i: bar.update())
        summary["report"] = str(write_report(result.root, report.to_dict()))
    if args.json:
        if report is not None:
            summary["recognition"] = report.to_dict()
        json.dump(summary, sys.stdout, indent=1)
        print()
        return 0
    print(
        f"rendered {counted(result.frame_count, 'frame')} in {result.render_s:.1f} s "
        f"({result.frames_per_s:.2f} frames/s) into {result.root}"
    )
    if report is not None:
        print(report.table())
        print(f"report written to {summary['report']}")
    return 0
