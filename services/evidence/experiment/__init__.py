"""The paper's marker experiment (§5.2, Table 1, Fig. 7, Fig. 8) through the real pipeline.

For each seed a simulated approach is rendered once (cached by scenario hash) and replayed,
frame for frame and gyro sample for gyro sample, through camera, gyro, mediator and detector
processes on a private loopback rendezvous: ``all`` (every frame), ``uncontrolled`` (frames
dropped at the source), ``filtered`` (the paper's mediator) and ``beyond`` (the ``adaptive``
policy). ``run_experiment`` writes results.json, table.md and the figures.
"""

from ._config import (
    MARKER_NAMES,
    PAPER_TABLE1,
    QUICK_FRAMES,
    RUN_KINDS,
    ExperimentConfig,
    ExperimentError,
    RunKind,
)
from ._datasets import cached_dataset, scenario_for, scenario_hash
from ._experiment import (
    OUTPUT_FILES,
    aggregate_markers,
    run_experiment,
    run_order,
    seed_markers,
)
from ._frames import FrameOutcome, frame_outcomes
from ._metrics import blur_pairs, recognized_counts, recognized_frames
from ._oracle import OracleSchedule, feasible, optimal_schedule
from ._pipeline import RunSettings, deployment_for, run_configuration
from ._records import FrameDetections, RunRecord
from ._replay import QueueModel, replay_policy, replay_uncontrolled
from ._stats import Estimate, captured_fraction, correlations, improvement_pct, mean_ci95
from ._sweep import SWEEP_TABLE, SweepConfig, format_sweep, run_sweep
from ._table import format_table

__all__ = [
    "MARKER_NAMES",
    "OUTPUT_FILES",
    "PAPER_TABLE1",
    "QUICK_FRAMES",
    "RUN_KINDS",
    "SWEEP_TABLE",
    "Estimate",
    "ExperimentConfig",
    "ExperimentError",
    "FrameDetections",
    "FrameOutcome",
    "OracleSchedule",
    "QueueModel",
    "RunKind",
    "RunRecord",
    "RunSettings",
    "SweepConfig",
    "aggregate_markers",
    "blur_pairs",
    "cached_dataset",
    "captured_fraction",
    "correlations",
    "deployment_for",
    "feasible",
    "format_sweep",
    "format_table",
    "frame_outcomes",
    "improvement_pct",
    "mean_ci95",
    "optimal_schedule",
    "recognized_counts",
    "recognized_frames",
    "replay_policy",
    "replay_uncontrolled",
    "run_configuration",
    "run_experiment",
    "run_order",
    "run_sweep",
    "scenario_for",
    "scenario_hash",
    "seed_markers",
]
