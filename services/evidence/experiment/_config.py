"""What an experiment runs: the four configurations of §5.2, seeds, queue, load, b0."""

from __future__ import annotations

import enum
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from middleware import ConfigError, FramegateError
from services.lib.markers import BOARD_MARKERS
from services.lib.quality import DEFAULT_B0_PX

MARKER_NAMES: tuple[str, ...] = tuple(m.name for m in BOARD_MARKERS)

QUICK_FRAMES = 60
"""Frames of the one short approach ``--quick`` runs (a smoke test, not a measurement)."""

PAPER_TABLE1: dict[str, dict[str, float]] = {
    "large": {"recognizable": 246, "uncontrolled": 154, "filtered": 161, "improvement_pct": 4.5},
    "medium": {"recognizable": 272, "uncontrolled": 159, "filtered": 178, "improvement_pct": 11.9},
    "small": {"recognizable": 99, "uncontrolled": 62, "filtered": 71, "improvement_pct": 14.5},
}
"""Table 1 of Walter, Penzlin & Elkmann, quoted: one approach of 319 frames, real robot."""


class ExperimentError(FramegateError):
    """An experiment run could not be carried out or measured (names the run and why)."""


class RunKind(enum.Enum):
    """The configurations of paper §5.2, plus the best policy beyond the paper."""

    ALL = "all"
    """Every frame processed regardless of time: the 'recognizable' column."""
    UNCONTROLLED = "uncontrolled"
    """Detector straight on camera/images: frames dropped at the source when its queue is full."""
    FILTERED = "filtered"
    """Camera → mediator (policy paper: accept iff q > load) → detector."""
    BEYOND = "beyond"
    """Camera → mediator (policy adaptive: thresholds from recent qualities on the detector's
    clock, the best causal policy of the sweep) → detector."""

    @property
    def policy(self) -> str | None:
        """The mediator policy of this run, None when there is no mediator."""
        return {RunKind.FILTERED: "paper", RunKind.BEYOND: "adaptive"}.get(self)


RUN_KINDS: tuple[RunKind, ...] = tuple(RunKind)


@dataclass(frozen=True, slots=True)
class ExperimentConfig:
    """Everything ``framegate experiment`` can be told.

    ``queue`` is the detector's notification queue N; ``service_factor`` its emulated
    processing time as a multiple of the frame period (paper: about 1.6). ``frames``
    overrides the approach's frame count (None: the scenario default, 319; ``quick``: 60).
    ``cache`` holds rendered datasets by scenario hash (default ``out/datasets``), so runs
    with other queue sizes can share them. ``startup_s`` is how long the processes get to
    come up before the replay's time zero.
    """

    out: Path
    seeds: tuple[int, ...] = (1, 2, 3, 4, 5)
    queue: int = 2
    service_factor: float = 1.6
    b0_px: float = DEFAULT_B0_PX
    quick: bool = False
    frames: int | None = None
    cache: Path | None = None
    runs: tuple[RunKind, ...] = RUN_KINDS
    startup_s: float = 6.0
    progress: bool = True
    floor: str = "default"

    def __post_init__(self) -> None:
        if not self.seeds:
            raise ConfigError("experiment needs at least one seed (--seeds 1 2 3 4 5)")
        if len(set(self.seeds)) != len(self.seeds):
            raise ConfigError(f"seeds repeat: {list(self.seeds)}")
        if self.queue < 1:
            raise ConfigError(f"--queue must be >= 1, got {self.queue}")
        if not self.service_factor > 0:
            raise ConfigError(f"--service-factor must be > 0, got {self.service_factor}")
        if not self.b0_px > 0:
            raise ConfigError(f"--b0 must be > 0 px, got {self.b0_px}")
        if self.frames is not None and self.frames < 2:
            raise ConfigError(f"--frames must be >= 2, got {self.frames}")
        if RunKind.ALL not in self.runs:
            raise ConfigError("the 'all' run is the reference (recognizable frames); keep it")
        if not 1.0 <= self.startup_s <= 9.0:
            # Above 9 s the camera's first put, stamped with the replay's time zero, can be
            # 10 s ahead of its clock, which a producer refuses (the camera then exits).
            raise ConfigError(f"--startup must be 1-9 s, got {self.startup_s}")

    @property
    def frame_count(self) -> int | None:
        """Frames per approach, None for the scenario default."""
        if self.frames is not None:
            return self.frames
        return QUICK_FRAMES if self.quick else None

    @property
    def dataset_cache(self) -> Path:
        """Where rendered datasets are kept."""
        return self.cache if self.cache is not None else self.out / "datasets"

    def to_dict(self) -> dict[str, Any]:
        """JSON-ready form (results.json's ``config``)."""
        return {
            "seeds": list(self.seeds),
            "queue": self.queue,
            "service_factor": self.service_factor,
            "b0_px": self.b0_px,
            "quick": self.quick,
            "frames": self.frame_count,
            "runs": [r.value for r in self.runs],
            "startup_s": self.startup_s,
            "floor": self.floor,
        }
