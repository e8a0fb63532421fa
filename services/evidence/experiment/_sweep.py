"""The sweep: every floor, queue size N, service factor and policy, by discrete-event replay.

Each (floor, seed) dataset is rendered once (cached by scenario hash, as the experiment
does) and its frames scored offline (``frame_outcomes``); then every working point is a
replay of milliseconds: ``uncontrolled``, each causal policy through the mediator's own
``Decider`` with the mediator's decision latencies (``--latency measured``: drawn per frame
as measured on real runs, see ``_latency.py``; ``none``: decided on arrival), and the
offline-optimal ``oracle`` per marker. ``captured`` is
(policy − uncontrolled) / (oracle − uncontrolled) per marker and seed, then averaged.
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from services.lib.decisions import make_policy
from services.lib.quality import DEFAULT_B0_PX

from ._config import MARKER_NAMES, ExperimentError
from ._datasets import cached_dataset, scenario_for
from ._frames import FrameOutcome, frame_outcomes
from ._latency import LATENCY_MODES, measured_latencies
from ._oracle import optimal_schedule
from ._replay import QueueModel, replay_policy, replay_uncontrolled
from ._stats import captured_fraction, improvement_pct, json_safe, mean_ci95

SWEEP_RESULTS = "sweep.json"
SWEEP_TABLE = "sweep.md"
SWEEP_FIGURE = "captured.png"
DEFAULT_POLICIES = ("paper", "replace", "deadline", "adaptive")


@dataclass(frozen=True, slots=True)
class SweepConfig:
    """What ``framegate experiment --sweep`` runs (see the module docstring)."""

    out: Path
    seeds: tuple[int, ...] = (1, 2, 3, 4, 5)
    floors: tuple[str, ...] = ("smooth", "default", "rough")
    queues: tuple[int, ...] = (1, 2, 3)
    factors: tuple[float, ...] = (1.3, 1.6, 2.0)
    policies: tuple[str, ...] = DEFAULT_POLICIES
    b0_px: float = DEFAULT_B0_PX
    frames: int | None = None
    cache: Path | None = None
    progress: bool = True
    latency: str = "measured"

    def __post_init__(self) -> None:
        if not self.seeds or not self.floors or not self.queues or not self.factors:
            raise ExperimentError("a sweep needs at least one seed, floor, queue and factor")
        if self.latency not in LATENCY_MODES:
            raise ExperimentError(
                f"latency {self.latency!r}: use one of {', '.join(LATENCY_MODES)}"
            )
        for policy in self.policies:
            make_policy(policy)  # fails early, naming the policies there are


def period_ns(frames: tuple[FrameOutcome, ...]) -> int:
    """The mean time between frame arrivals."""
    if len(frames) < 2:
        raise ExperimentError("a replay needs at least two frames")
    return round((frames[-1].arrival_ns - frames[0].arrival_ns) / (len(frames) - 1))


def marker_counts(frames: tuple[FrameOutcome, ...], processed: tuple[int, ...]) -> dict[str, int]:
    """Recognitions per marker when exactly ``processed`` (frame ids) were processed."""
    by_id = {f.frame_id: f for f in frames}
    return {name: sum(by_id[i].value(name) for i in processed) for name in MARKER_NAMES}


def oracle_counts(frames: tuple[FrameOutcome, ...], model: QueueModel) -> dict[str, int]:
    """The offline optimum per marker (each marker's own best schedule) and ``total`` (the
    best schedule for the sum over markers)."""
    arrivals = [f.arrival_ns for f in frames]
    out = {
        name: optimal_schedule(
            arrivals, [f.value(name) for f in frames],
            service_ns=model.service_ns, capacity=model.queue,
        ).value
        for name in MARKER_NAMES
    }  # fmt: skip
    out["total"] = optimal_schedule(
        arrivals, [f.value() for f in frames], service_ns=model.service_ns, capacity=model.queue
    ).value
    return out


def working_point(
    frames: tuple[FrameOutcome, ...],
    queue: int,
    factor: float,
    policies: tuple[str, ...],
    latencies_ns: dict[int, int] | None = None,
) -> dict[str, dict[str, int]]:
    """Counts per run (uncontrolled, each policy, oracle) and marker at one working point;
    the mediator decides each frame ``latencies_ns[frame_id]`` after its exposure ended."""
    model = QueueModel(queue=queue, service_ns=round(factor * period_ns(frames)))
    counts = {"uncontrolled": marker_counts(frames, replay_uncontrolled(frames, model))}
    for policy in policies:
        processed = replay_policy(frames, model, make_policy(policy), latencies_ns)
        counts[policy] = marker_counts(frames, processed)
    for key in list(counts):
        counts[key]["total"] = sum(counts[key][name] for name in MARKER_NAMES)
    counts["oracle"] = oracle_counts(frames, model)
    return counts


def _summary(rows: list[dict[str, dict[str, int]]], policies: tuple[str, ...]) -> dict[str, Any]:
    out: dict[str, Any] = {}
    for key in ("uncontrolled", *policies, "oracle"):
        out[key] = {}
        for name in (*MARKER_NAMES, "total"):
            counts = mean_ci95([r[key][name] for r in rows])
            entry: dict[str, Any] = {"mean": counts.mean, "ci95": counts.ci95}
            if key != "uncontrolled":
                gain = mean_ci95(
                    [improvement_pct(r["uncontrolled"][name], r[key][name]) for r in rows]
                )
                entry["improvement_pct"] = {"mean": gain.mean, "ci95": gain.ci95}
            if key in policies:
                share = mean_ci95(
                    [
                        captured_fraction(r[key][name], r["uncontrolled"][name], r["oracle"][name])
                        for r in rows
                    ]
                )
                entry["captured"] = {"mean": share.mean, "ci95": share.ci95, "n": share.n}
                paper = [r[key][name] - r["paper"][name] for r in rows if "paper" in r]
                if key != "paper" and paper:
                    vs = mean_ci95(paper)
                    entry["vs_paper"] = {"mean": vs.mean, "ci95": vs.ci95}
            out[key][name] = entry
    return out


def run_sweep(config: SweepConfig, *, log: Any = None) -> dict[str, Any]:
    """Replay every working point; write sweep.json, sweep.md and captured.png."""
    say = log or (lambda text: print(text, flush=True))
    cache = config.cache if config.cache is not None else config.out / "datasets"
    config.out.mkdir(parents=True, exist_ok=True)
    points: list[dict[str, Any]] = []
    for floor in config.floors:
        per_seed: dict[tuple[int, float], list[dict[str, dict[str, int]]]] = {}
        for seed in config.seeds:
            dataset = cached_dataset(
                scenario_for(seed, config.frames, floor), cache, progress=config.progress
            )
            frames = frame_outcomes(dataset, config.b0_px)
            say(f"floor {floor} seed {seed}: {len(frames)} frames scored")
            latencies = measured_latencies(frames, seed) if config.latency == "measured" else None
            for queue in config.queues:
                for factor in config.factors:
                    counts = working_point(frames, queue, factor, config.policies, latencies)
                    per_seed.setdefault((queue, factor), []).append(counts)
        for (queue, factor), rows in per_seed.items():
            points.append(
                {
                    "floor": floor,
                    "queue": queue,
                    "service_factor": factor,
                    "seeds": list(config.seeds),
                    "per_seed": rows,
                    "summary": _summary(rows, config.policies),
                }
            )
    results = {
        "config": {
            "seeds": list(config.seeds),
            "floors": list(config.floors),
            "queues": list(config.queues),
            "factors": list(config.factors),
            "policies": list(config.policies),
            "b0_px": config.b0_px,
            "frames": config.frames,
            "latency": config.latency,
        },
        "points": points,
    }
    results = dict(json_safe(results))
    (config.out / SWEEP_RESULTS).write_text(json.dumps(results, indent=1) + "\n", "utf-8")
    (config.out / SWEEP_TABLE).write_text(format_sweep(results), "utf-8")
    from ._plots import plot_captured  # matplotlib only when writing figures

    plot_captured(results, config.out / SWEEP_FIGURE)
    return results


def _fmt(entry: dict[str, Any] | None, digits: int = 1, scale: float = 1.0) -> str:
    if not entry or entry.get("mean") is None:
        return "-"
    text = f"{entry['mean'] * scale:.{digits}f}"
    if entry.get("ci95") is not None:
        text += f" ± {entry['ci95'] * scale:.{digits}f}"
    return text


def format_sweep(results: dict[str, Any]) -> str:
    """One summary table: per floor, N, factor and marker, counts and captured fractions."""
    policies = results["config"]["policies"]
    seeds = results["config"]["seeds"]
    lines = [
        "# Sweep: floors × queue N × service factor (discrete-event replay)",
        "",
        f"Seeds {', '.join(map(str, seeds))}; mediator decision latency "
        f"{results['config'].get('latency', 'none')}; mean ± 95 % CI over seeds. Counts are frames "
        "with the marker recognized; *captured* = (policy − uncontrolled) / (oracle − "
        "uncontrolled) in %, per seed then averaged (seeds where the oracle gains nothing "
        "are left out); *oracle* is the offline optimum for that marker.",
        "",
        "| floor | N | factor | marker | uncontrolled | oracle | "
        + " | ".join(policies)
        + " | "
        + " | ".join(f"captured {p} %" for p in policies)
        + " |",
        "|---|--:|--:|---|" + "--:|" * (2 + 2 * len(policies)),
    ]
    for point in results["points"]:
        summary = point["summary"]
        for name in (*MARKER_NAMES, "total"):
            cells = [_fmt(summary["uncontrolled"][name]), _fmt(summary["oracle"][name])]
            cells += [_fmt(summary[p][name]) for p in policies]
            cells += [_fmt(summary[p][name].get("captured"), 0, 100.0) for p in policies]
            lines.append(
                f"| {point['floor']} | {point['queue']} | {point['service_factor']:g} | {name} | "
                + " | ".join(cells)
                + " |"
            )
    return "\n".join(lines) + "\n"
