"""What a benchmark run was asked to do."""

from __future__ import annotations

import sys
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

from ._procs import BenchError

SCENARIO_NAMES = (
    "frames",
    "small",
    "batch",
    "latency",
    "fan-out",
    "working-point",
    "query-scaling",
    "memory",
    "quality",
    "idle",
    "hostile",
    "ros2",
    "startup",
)
# Run only when named (minutes each, and the simulated approach rendered first).
OPT_IN_SCENARIOS = ("ros2-loop",)

# Measured window per sample (s) and runs per side, unless the command line says otherwise.
FULL_DURATION_S = 4.0
FULL_PAIRS = 3
QUICK_DURATION_S = 0.5
QUICK_PAIRS = 1
# The hostile scenario's attacked window (s), unless --duration says otherwise.
FULL_HOSTILE_S = 120.0
QUICK_HOSTILE_S = 10.0


def _stderr(message: str) -> None:
    print(message, file=sys.stderr, flush=True)


@dataclass(frozen=True, slots=True)
class BenchOptions:
    """Scenarios to run, the measured window per sample, and raw/framegate pairs per row.

    Each sample measures ``duration_s`` (query-scaling: a quarter of it per (n, k); idle: at
    least 5 s; hostile: ``hostile_s``, which a given duration also sets; ros2-loop: at least
    45 s, quick 15, a run of the approach per window);
    ``quick`` also shrinks sizes (memory, query-scaling) for a CI smoke test.
    """

    scenarios: tuple[str, ...] = SCENARIO_NAMES
    duration_s: float = FULL_DURATION_S
    pairs: int = FULL_PAIRS
    quick: bool = False
    hostile_s: float = FULL_HOSTILE_S
    progress: Callable[[str], None] = field(default=_stderr, compare=False)

    def __post_init__(self) -> None:
        known = SCENARIO_NAMES + OPT_IN_SCENARIOS
        unknown = [s for s in self.scenarios if s not in known]
        if unknown:
            from services.lib.argtypes import did_you_mean

            hint = did_you_mean(unknown[0], known)
            raise BenchError(
                f"unknown scenario(s) {', '.join(unknown)}{hint}; choose from {', '.join(known)}"
            )
        for value in (self.duration_s, self.hostile_s):
            if not value > 0 or value == float("inf"):  # NaN fails both comparisons
                raise BenchError(f"duration {value} s must be a number > 0")
        if self.pairs < 1:
            raise BenchError(f"pairs {self.pairs} must be >= 1")
        if self.pairs < 3 and not self.quick:
            raise BenchError(
                f"{self.pairs} pair(s) is too few to compare: use --pairs 3 or more, "
                "or --quick for a smoke test"
            )

    @classmethod
    def create(
        cls,
        scenarios: tuple[str, ...] = (),
        *,
        duration_s: float | None = None,
        pairs: int | None = None,
        quick: bool = False,
        progress: Callable[[str], None] = _stderr,
    ) -> BenchOptions:
        """Fill unset values with the quick or full defaults; a given ``duration_s`` is also
        the hostile scenario's window."""
        default_hostile = QUICK_HOSTILE_S if quick else FULL_HOSTILE_S
        return cls(
            scenarios=scenarios or SCENARIO_NAMES,
            duration_s=(QUICK_DURATION_S if quick else FULL_DURATION_S)
            if duration_s is None
            else duration_s,
            pairs=(QUICK_PAIRS if quick else FULL_PAIRS) if pairs is None else pairs,
            quick=quick,
            hostile_s=default_hostile if duration_s is None else duration_s,
            progress=progress,
        )

    @property
    def warmup_s(self) -> float:
        """Unmeasured running before each throughput window."""
        return 0.3 if self.quick else 0.5

    def as_json(self) -> dict[str, Any]:
        return {
            "scenarios": list(self.scenarios),
            "duration_s": self.duration_s,
            "pairs": self.pairs,
            "quick": self.quick,
            "warmup_s": self.warmup_s,
            "hostile_s": self.hostile_s,
        }
