"""Benchmark results as plain records: rows of side-by-side samples, goals, scenarios."""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any, Literal

from ._stats import Summary, median, ratio, summarize

Side = Literal["raw", "framegate"]
SIDES: tuple[Side, Side] = ("raw", "framegate")


@dataclass(frozen=True, slots=True)
class Goal:
    """A target with its measured value: ``measured >= limit`` (at_least) or ``<= limit``."""

    text: str
    limit: float
    at_least: bool
    measured: float | None

    @property
    def passed(self) -> bool | None:
        """True/False once measured; None when there was nothing to compare."""
        if self.measured is None:
            return None
        return self.measured >= self.limit if self.at_least else self.measured <= self.limit

    @property
    def verdict(self) -> str:
        return {True: "PASS", False: "MISS", None: "n/a"}[self.passed]

    def as_json(self) -> dict[str, Any]:
        return {
            "text": self.text,
            "limit": self.limit,
            "comparison": ">=" if self.at_least else "<=",
            "measured": self.measured,
            "passed": self.passed,
        }


@dataclass(slots=True)
class Row:
    """One measured quantity, raw and framegate side by side, one sample per run.

    Each sample is a dict with at least ``pair`` (run index) and ``value`` (in ``unit``);
    throughput samples also carry ``cpu_producer_pct`` and ``cpu_consumer_pct`` (% of one
    core) and ``cpu_producer_us`` and ``cpu_consumer_us`` (CPU microseconds per element).
    ``raw`` is None where there is no raw counterpart (quality).
    """

    name: str
    metric: str
    unit: str
    higher_is_better: bool
    raw: list[dict[str, Any]] | None = field(default_factory=list)
    framegate: list[dict[str, Any]] = field(default_factory=list)
    goal: Goal | None = None
    note: str = ""

    def samples(self, side: Side) -> list[dict[str, Any]]:
        """The live sample list of one side (append to it); a new empty list for no raw."""
        if side == "framegate":
            return self.framegate
        return self.raw if self.raw is not None else []

    def summary(self, side: Side) -> Summary | None:
        values = [float(s["value"]) for s in self.samples(side)]
        return summarize(values) if values else None

    def median(self, side: Side) -> float | None:
        found = self.summary(side)
        return found.median if found else None

    @property
    def ratio(self) -> float | None:
        """framegate median / raw median."""
        return ratio(self.median("framegate"), self.median("raw"))

    @property
    def extra(self) -> float | None:
        """framegate median - raw median: what framegate adds (CPU per element)."""
        fg, raw = self.median("framegate"), self.median("raw")
        return None if fg is None or raw is None else fg - raw

    def pair_ratios(self) -> list[float | None]:
        """framegate/raw of each pair (the run after each raw run), in pair order."""
        raw = {s["pair"]: float(s["value"]) for s in self.samples("raw")}
        return [ratio(float(s["value"]), raw.get(s["pair"])) for s in self.framegate if raw]

    def cpu(self, side: Side) -> dict[str, float] | None:
        """Median CPU % of one core per process role, when the samples carry it."""
        out: dict[str, float] = {}
        for role in ("producer", "consumer"):
            values = [
                float(s[f"cpu_{role}_pct"])
                for s in self.samples(side)
                if s.get(f"cpu_{role}_pct") is not None
            ]
            if values:
                out[role] = median(values)
        return out or None

    def as_json(self) -> dict[str, Any]:
        sides: dict[str, Any] = {}
        for side in SIDES:
            if side == "raw" and self.raw is None:
                continue
            found = self.summary(side)
            sides[side] = {
                "samples": self.samples(side),
                **(found.as_json() if found else {}),
                "cpu_pct": self.cpu(side),
            }
        return {
            "name": self.name,
            "metric": self.metric,
            "unit": self.unit,
            "higher_is_better": self.higher_is_better,
            **sides,
            "ratio": self.ratio,
            "extra": self.extra,
            "pair_ratios": self.pair_ratios(),
            "goal": self.goal.as_json() if self.goal else None,
            "note": self.note,
        }


@dataclass(slots=True)
class ScenarioResult:
    """What one scenario produced: ``status`` is ok, skipped or error (then ``reason``)."""

    name: str
    status: Literal["ok", "skipped", "error"] = "ok"
    reason: str = ""
    params: dict[str, Any] = field(default_factory=dict)
    rows: list[Row] = field(default_factory=list)
    elapsed_s: float = 0.0

    def as_json(self) -> dict[str, Any]:
        return {
            "status": self.status,
            "reason": self.reason,
            "params": self.params,
            "elapsed_s": round(self.elapsed_s, 3),
            "rows": [row.as_json() for row in self.rows],
        }


def ratio_goal(row: Row, limit: float, *, at_least: bool, what: str) -> Goal:
    """A goal on framegate/raw of ``row``."""
    sign = ">=" if at_least else "<="
    return Goal(f"{what} {sign} {limit:g}x raw", limit, at_least, row.ratio)


def extra_goal(row: Row, limit: float, *, what: str) -> Goal:
    """A goal on framegate - raw of ``row`` (at most ``limit``, in the row's unit)."""
    return Goal(f"{what}: framegate - raw <= {limit:g} {row.unit}", limit, False, row.extra)
