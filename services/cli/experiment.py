"""``framegate experiment``: the paper's marker experiment end to end (Table 1, Fig. 7, 8).

Every seed's approach is replayed through real camera, gyro, mediator and detector
processes at real-time pace, once per configuration (all, uncontrolled, filtered, beyond);
the outputs land in ``--out``. A full run of 5 seeds takes about 15 minutes (plus rendering
the first time); ``--quick`` is a one-minute smoke test.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path
from typing import Any

from services.lib.argtypes import non_negative_float, non_negative_int, positive_float, positive_int
from services.lib.quality import DEFAULT_B0_PX
from services.lib.sim import ScenarioConfig

from ._common import exit_on_sigterm

# services.evidence.experiment is imported when the command runs, not here: it pulls in scipy and
# matplotlib (seconds on a busy machine), and every framegate command, including each
# service process, builds the parser that registers this module. So the defaults below are
# written here, each help shows the parser's own (%(default)s), and a test checks them
# against ExperimentConfig's and SweepConfig's.
SEEDS = (1, 2, 3, 4, 5)
STARTUP_S = 6.0
QUICK_STARTUP_S = 4.0  # --quick: one short seed, so a shorter start-up suffices
QUICK_FRAMES = 60
SWEEP_FLOORS = ("smooth", "default", "rough")
SWEEP_QUEUES = (1, 2, 3)
SWEEP_FACTORS = (1.3, 1.6, 2.0)
SWEEP_POLICIES = ("paper", "replace", "deadline", "adaptive")


def _words(values: tuple[object, ...]) -> str:
    """``1 2 3``: a list default as it is typed on the command line."""
    return " ".join(map(str, values))


def register(subparsers: Any) -> None:
    """Add the ``experiment`` command."""
    parser = subparsers.add_parser(
        "experiment",
        help="reproduce the paper's marker experiment (Table 1, Fig. 7, Fig. 8)",
        description="Replay simulated approaches through the real multi-process pipeline in "
        "four configurations (all, uncontrolled, filtered, beyond) and write table.md, "
        "results.json and the figures into --out.",
    )
    parser.add_argument("--out", type=Path, required=True, help="directory for the outputs")
    parser.add_argument(
        "--seeds", type=non_negative_int, nargs="+", default=None, metavar="SEED",
        help=f"simulator seeds, one approach each (default {_words(SEEDS)}; "
        "--quick: 1)",
    )  # fmt: skip
    parser.add_argument(
        "--queue", type=positive_int, default=2, help="detector queue size N (default %(default)s)"
    )
    parser.add_argument(
        "--service-factor", type=positive_float, default=1.6,
        help="detector processing time as a multiple of the frame period (default %(default)s)",
    )  # fmt: skip
    parser.add_argument(
        "--b0", type=positive_float, default=DEFAULT_B0_PX, dest="b0_px",
        help="the mediator's blur scale b0 in px: q = exp(-blur/b0) (default %(default)s)",
    )  # fmt: skip
    parser.add_argument(
        "--frames", type=positive_int,
        help=f"frames per approach (default {ScenarioConfig().frame_count}; "
        f"--quick: {QUICK_FRAMES})",
    )  # fmt: skip
    parser.add_argument(
        "--floor", default="default", choices=("smooth", "default", "rough"),
        help="the simulated floor's bumps (default %(default)s)",
    )  # fmt: skip
    parser.add_argument(
        "--sweep", action="store_true",
        help="no processes: replay every --floors x --queues x --factors working point "
        "(discrete-event, with the oracle and every policy) and print one summary table",
    )  # fmt: skip
    parser.add_argument(
        "--floors",
        nargs="+",
        default=list(SWEEP_FLOORS),
        help=f"sweep: floors (default {_words(SWEEP_FLOORS)})",
    )
    parser.add_argument(
        "--queues",
        type=positive_int,
        nargs="+",
        default=list(SWEEP_QUEUES),
        help=f"sweep: detector queue sizes N (default {_words(SWEEP_QUEUES)})",
    )
    parser.add_argument(
        "--factors",
        type=positive_float,
        nargs="+",
        default=list(SWEEP_FACTORS),
        help=f"sweep: detector service factors (default {_words(SWEEP_FACTORS)})",
    )
    parser.add_argument(
        "--policies", nargs="+", default=list(SWEEP_POLICIES),
        help=f"mediator policies the sweep replays (default {_words(SWEEP_POLICIES)})",
    )  # fmt: skip
    parser.add_argument(
        "--latency", choices=("measured", "none"), default="measured",
        help="sweep: the mediator decides each frame after a decision latency drawn as "
        "measured on real runs (default), or the moment it arrives (none)",
    )  # fmt: skip
    parser.add_argument(
        "--cache", type=Path,
        help="directory of rendered datasets to reuse (default OUT/datasets)",
    )  # fmt: skip
    parser.add_argument(
        "--startup", type=non_negative_float, dest="startup_s", metavar="S",
        help="seconds the processes get to come up before each replay starts "
        f"(default {STARTUP_S:g}; --quick: {QUICK_STARTUP_S:g})",
    )  # fmt: skip
    parser.add_argument(
        "--quick", action="store_true", help=f"one short seed ({QUICK_FRAMES} frames): a smoke test"
    )
    parser.add_argument("--no-progress", action="store_true", help="no progress bars")
    parser.add_argument("--json", action="store_true", help="print results.json to stdout")
    parser.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    """Run the experiment and print the table (or the results as JSON)."""
    from services.evidence.experiment import OUTPUT_FILES, ExperimentConfig, run_experiment

    # SIGTERM unwinds like Ctrl-C, so every service process of the current run is stopped.
    exit_on_sigterm()
    seeds = args.seeds if args.seeds is not None else ([1] if args.quick else list(SEEDS))
    if args.sweep:
        return _sweep(args, seeds)
    config = ExperimentConfig(
        out=args.out,
        seeds=tuple(seeds),
        queue=args.queue,
        service_factor=args.service_factor,
        b0_px=args.b0_px,
        quick=args.quick,
        frames=args.frames,
        cache=args.cache,
        startup_s=args.startup_s
        if args.startup_s is not None
        else (QUICK_STARTUP_S if args.quick else STARTUP_S),
        progress=not args.no_progress and not args.json,
        floor=args.floor,
    )
    quiet = args.json
    results = run_experiment(config, log=(lambda _text: None) if quiet else None)
    if args.json:
        json.dump(results, sys.stdout, indent=1)
        print()
        return 0
    print((args.out / "table.md").read_text(encoding="utf-8"))
    print("wrote " + ", ".join(str(args.out / name) for name in OUTPUT_FILES))
    return 0


def _sweep(args: argparse.Namespace, seeds: list[int]) -> int:
    from services.evidence.experiment import SWEEP_TABLE, SweepConfig, run_sweep

    config = SweepConfig(
        out=args.out,
        seeds=tuple(seeds),
        floors=tuple(args.floors),
        queues=tuple(args.queues),
        factors=tuple(args.factors),
        policies=tuple(args.policies),
        b0_px=args.b0_px,
        frames=args.frames if args.frames is not None else (QUICK_FRAMES if args.quick else None),
        cache=args.cache,
        progress=not args.no_progress and not args.json,
        latency=args.latency,
    )
    results = run_sweep(config, log=(lambda _text: None) if args.json else None)
    if args.json:
        json.dump(results, sys.stdout, indent=1)
        print()
        return 0
    print((args.out / SWEEP_TABLE).read_text(encoding="utf-8"))
    return 0
