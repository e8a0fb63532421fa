"""The whole experiment: datasets per seed, the four runs each, statistics, table, figures."""

from __future__ import annotations

import json
import math
import os
import time
from collections.abc import Callable
from dataclasses import asdict, replace
from pathlib import Path
from typing import Any

from services.lib.decisions import make_policy
from services.lib.sim import Dataset

from ._config import MARKER_NAMES, PAPER_TABLE1, ExperimentConfig, RunKind
from ._datasets import cached_dataset, scenario_for
from ._detector import (
    ack_steps,
    clock_offset_ns,
    detector_overhead_ns,
    detector_steps,
    handover_steps,
)
from ._frames import FrameOutcome, frame_outcomes
from ._latency import decision_latencies
from ._metrics import blur_pairs, recognized_frames
from ._pipeline import RunSettings, run_configuration
from ._plots import plot_gyro_exposures, plot_quality_vs_blur, plot_timeline
from ._records import RunRecord
from ._replay import QueueModel, replay_policy
from ._stats import captured_fraction, correlations, improvement_pct, json_safe, mean_ci95
from ._sweep import marker_counts, oracle_counts, period_ns
from ._table import format_table

RESULTS_FILE = "results.json"
TABLE_FILE = "table.md"
FIG7_FILE = "fig7_gyro.png"
FIG8_FILE = "fig8_quality_vs_blur.png"
TIMELINE_FILE = "timeline.png"
OUTPUT_FILES = (RESULTS_FILE, TABLE_FILE, FIG7_FILE, FIG8_FILE, TIMELINE_FILE)

_COUNT_KEYS = ("all", "uncontrolled", "filtered", "beyond", "oracle")
# (key, base run, compared run) of the improvements reported per marker.
_IMPROVEMENTS = (
    ("improvement_pct", "uncontrolled", "filtered"),
    ("beyond_improvement_pct", "uncontrolled", "beyond"),
    ("beyond_vs_filtered_pct", "filtered", "beyond"),
)
# (key, run) of the shares of the oracle's gain reported per marker.
_CAPTURED = (("captured", "filtered"), ("beyond_captured", "beyond"))
_TIMED = (RunKind.UNCONTROLLED, RunKind.FILTERED, RunKind.BEYOND)
# The share of frames an uncontrolled run's camera may skip late for its detector to count
# as never idle (``detector_overhead_ns``).
_LATE_SHARE = 0.03
# The mediator's record of a frame it could not forward: its consumer's subscription lapsed.
_LAPSED = "consumer-lapsed"


def run_order(runs: tuple[RunKind, ...], seed_index: int) -> list[RunKind]:
    """``all`` first, then the timed runs rotated by seed, so that no configuration always
    runs last (when the machine's background load has drifted most)."""
    timed = [kind for kind in _TIMED if kind in runs]
    shift = seed_index % len(timed) if timed else 0
    return [RunKind.ALL, *timed[shift:], *timed[:shift]]


def seed_markers(counts: dict[str, dict[str, int]]) -> dict[str, dict[str, Any]]:
    """Per marker: the runs' recognized counts and the improvements between them.

    ``counts`` maps a run kind's value to {marker: count}; missing runs give None.
    """
    out: dict[str, dict[str, Any]] = {}
    for name in MARKER_NAMES:
        row: dict[str, Any] = {key: counts.get(key, {}).get(name) for key in _COUNT_KEYS}
        for key, base, new in _IMPROVEMENTS:
            row[key] = (
                improvement_pct(row[base], row[new])
                if row[base] is not None and row[new] is not None
                else None
            )
        for key, run in _CAPTURED:
            policy, base, best = row[run], row["uncontrolled"], row["oracle"]
            row[key] = (
                captured_fraction(policy, base, best) if None not in (policy, base, best) else None
            )
        out[name] = row
    return out


def seed_oracle(
    dataset: Dataset, recognized_all: dict[str, list[int]], queue: int, service_factor: float
) -> dict[str, int]:
    """The offline optimum per marker for this seed: the frames' arrivals (exposure ends)
    and what the ``all`` run recognized in each, under the run's queue N and service time
    (``service_factor`` × the mean frame period, as the detector emulates it)."""
    by_frame: dict[int, set[str]] = {}
    for name, ids in recognized_all.items():
        for frame_id in ids:
            by_frame.setdefault(frame_id, set()).add(name)
    frames = tuple(
        FrameOutcome(
            frame_id=f.frame_id,
            arrival_ns=f.exposure_start_ns + f.exposure_ns,
            blur_px=None,
            quality=None,
            recognized=frozenset(by_frame.get(f.frame_id, ())),
        )
        for f in dataset.frames
    )
    model = QueueModel(queue=queue, service_ns=round(service_factor * period_ns(frames)))
    return oracle_counts(frames, model)


def seed_replay(
    dataset: Dataset, records: dict[RunKind, RunRecord], config: ExperimentConfig
) -> dict[str, dict[str, Any]]:
    """The discrete-event replay of each mediator run on the same frames, beside the real
    run's counts: how far the replay the sweep relies on is from the real pipeline
    (``real − replay`` per marker), i.e. what the mediator's realization loses.

    Each run is replayed with what its own mediator was given, so that what the machine did
    to the pipeline around it is not counted against the policy: the frames it decided
    (not those the camera skipped late or refused, counted as ``not_decided``, nor those it
    could not forward to a detector whose subscription had lapsed, ``lapsed``), each at its
    own decision latency and with the quality it computed (None where the gyro did not
    cover the frame in time: the gyro-missing rule decides, as it did), and the detector's
    processing times when it took them (``_detector``; ``service_ms``: their mean,
    ``overhead_ms``: the cost per frame besides), and each take seen by the mediator as
    late as its ack reached the real one (``ack_ms``: the median delay)."""
    frames = frame_outcomes(dataset, config.b0_px)
    nominal_ns = round(config.service_factor * period_ns(frames))
    arrival = {f.frame_id: f.arrival_ns for f in frames}
    starts = {f.frame_id: f.exposure_start_ns for f in dataset.frames}
    uncontrolled = records.get(RunKind.UNCONTROLLED)
    overhead_ns = 0
    # Only a run whose camera kept up keeps the detector's queue full all along.
    if uncontrolled is not None and uncontrolled.skipped_late <= _LATE_SHARE * len(frames):
        overhead_ns = detector_overhead_ns(uncontrolled.detections, arrival)
    assert dataset.truth is not None
    out: dict[str, dict[str, Any]] = {}
    for kind, record in records.items():
        if kind.policy is None:
            continue
        # Frames the mediator could not give a detector whose subscription had lapsed (its
        # process did not run past its lease): the machine took them, as it took those the
        # camera skipped late; the replay's detector never lapses.
        lapsed = {
            d.frame_id for d in (*record.first_decisions, *record.decisions) if d.reason == _LAPSED
        }
        latencies = {
            i: ns for i, ns in decision_latencies(record.first_decisions).items() if i not in lapsed
        }
        quality = {d.frame_id: d.quality for d in record.first_decisions}
        seen = tuple(
            replace(f, quality=quality[f.frame_id]) for f in frames if f.frame_id in latencies
        )
        offset_ns = clock_offset_ns(record.first_decisions, starts)
        steps, overhead = detector_steps(
            record.detections, record.decisions, arrival, nominal_ns, overhead_ns, offset_ns
        )
        acks = ack_steps(record.detections, (*record.first_decisions, *record.decisions), offset_ns)
        handovers = handover_steps(
            record.detections, record.decisions, arrival, nominal_ns, offset_ns
        )
        model = QueueModel(
            queue=config.queue,
            service_ns=nominal_ns,
            service_steps=steps,
            ack_steps=acks,
            handover_steps=handovers,
        )
        taken = [s - overhead for _t, s in steps]
        service_ns = sum(taken) // len(taken) if taken else nominal_ns
        replayed = marker_counts(
            seen, replay_policy(seen, model, make_policy(kind.policy), latencies)
        )
        real = {
            n: len(ids) for n, ids in recognized_frames(record.detections, dataset.truth).items()
        }
        out[kind.value] = {
            "policy": kind.policy,
            "replay": replayed,
            "real": real,
            "real_minus_replay": {n: real[n] - replayed[n] for n in MARKER_NAMES},
            "not_decided": len(frames) - len(seen) - len(lapsed),
            "lapsed": len(lapsed),
            "service_ms": round(service_ns / 1e6, 1),
            "overhead_ms": round(overhead / 1e6, 1),
            # Median delays: until the mediator saw a take, until an idle detector took a put.
            "ack_ms": _median_ms(acks),
            "handover_ms": _median_ms(handovers),
        }
    return out


def _median_ms(steps: tuple[tuple[int, int], ...]) -> float | None:
    """The median of steps' values in ms (None without steps: not recorded, 0 replayed)."""
    return round(sorted(v for _t, v in steps)[len(steps) // 2] / 1e6, 1) if steps else None


def aggregate_replay(seeds: list[dict[str, Any]]) -> dict[str, dict[str, Any]]:
    """Per mediator run and marker: real and replay counts and their difference, mean and
    95 % CI over seeds."""
    out: dict[str, dict[str, Any]] = {}
    runs = sorted({run for seed in seeds for run in seed.get("replay", {})})
    for run in runs:
        rows = [seed["replay"][run] for seed in seeds if run in seed.get("replay", {})]
        out[run] = {"policy": rows[0]["policy"]}
        # What the replay was given, per seed.
        for key in ("not_decided", "lapsed", "service_ms", "overhead_ms", "ack_ms", "handover_ms"):
            out[run][key] = [row.get(key) for row in rows]
        for name in MARKER_NAMES:
            entry: dict[str, Any] = {}
            for key in ("real", "replay", "real_minus_replay"):
                estimate = mean_ci95([row[key][name] for row in rows])
                entry[key] = {"mean": estimate.mean, "ci95": estimate.ci95}
            out[run][name] = entry
    return out


def aggregate_markers(seeds: list[dict[str, Any]]) -> dict[str, dict[str, Any]]:
    """Mean and 95 % CI half-width over seeds of every per-seed marker value."""
    out: dict[str, dict[str, Any]] = {}
    for name in MARKER_NAMES:
        row: dict[str, Any] = {}
        for key in (*_COUNT_KEYS, *(k for k, _b, _n in _IMPROVEMENTS)):
            estimate = mean_ci95([seed["markers"][name].get(key) for seed in seeds])
            row[key] = estimate.mean
            row[f"{key}_ci95"] = estimate.ci95
        # The name for the filtered improvement's interval.
        row["improvement_ci95"] = row["improvement_pct_ci95"]
        for key, _run in _CAPTURED:
            share = mean_ci95([seed["markers"][name].get(key) for seed in seeds])
            row[key] = {"mean": share.mean, "ci95": share.ci95, "n": share.n}
        row["paper"] = dict(PAPER_TABLE1[name])
        out[name] = row
    return out


def policy_summary(
    markers: dict[str, dict[str, Any]], runs: tuple[RunKind, ...]
) -> dict[str, dict[str, Any]]:
    """Per mediator policy and marker: its run, recognized count, the oracle's count and
    ``captured`` (mean, ci95, n over seeds) — the gain as a share of the possible."""
    out: dict[str, dict[str, Any]] = {}
    for key, run in _CAPTURED:
        kind = RunKind(run)
        if kind not in runs or kind.policy is None:
            continue
        out[kind.policy] = {
            name: {
                "run": run,
                "recognized": {"mean": row[run], "ci95": row[f"{run}_ci95"]},
                "oracle": {"mean": row["oracle"], "ci95": row["oracle_ci95"]},
                "captured": row[key],
            }
            for name, row in markers.items()
        }
    return out


def _write_run(path: Path, record: RunRecord, recognized: dict[str, list[int]]) -> None:
    data = {
        "kind": record.kind.value,
        "seed": record.seed,
        "summary": record.summary(),
        "processed": record.processed_ids,
        "recognized": recognized,
        "detections": [asdict(d) for d in record.detections],
        "decisions": [asdict(d) for d in record.decisions],
        "first_decisions": [asdict(d) for d in record.first_decisions],
    }
    path.write_text(json.dumps(json_safe(data)) + "\n", encoding="utf-8")


def run_experiment(
    config: ExperimentConfig, *, log: Callable[[str], None] | None = None
) -> dict[str, Any]:
    """Run every seed's configurations through the real pipeline; write the outputs to
    ``config.out`` (results.json, table.md, the figures, runs/ and logs/) and return the
    results mapping."""
    say = log or (lambda text: print(text, flush=True))
    out = config.out
    out.mkdir(parents=True, exist_ok=True)
    (out / "runs").mkdir(exist_ok=True)
    settings = RunSettings(
        queue=config.queue,
        service_factor=config.service_factor,
        b0_px=config.b0_px,
        startup_s=config.startup_s,
        progress=config.progress,
        log_dir=out / "logs",
    )
    started = time.monotonic()
    load_before = os.getloadavg()
    cpus = os.cpu_count() or 1
    if load_before[0] > cpus:
        say(
            f"warning: load average {load_before[0]:.1f} on {cpus} CPUs; real-time runs will "
            "be disturbed (slower detector, late frames): measure on a quiet machine"
        )
    seeds: list[dict[str, Any]] = []
    blur_series: dict[str, tuple[list[float], list[float], list[float]]] = {}
    first: tuple[Dataset, dict[RunKind, RunRecord]] | None = None
    for index, seed in enumerate(config.seeds):
        dataset = cached_dataset(
            scenario_for(seed, config.frame_count, config.floor),
            config.dataset_cache,
            progress=config.progress,
        )
        assert dataset.truth is not None  # cached_dataset guarantees it
        records: dict[RunKind, RunRecord] = {}
        recognized: dict[str, dict[str, list[int]]] = {}
        for kind in run_order(config.runs, index):
            record = run_configuration(kind, dataset, seed, settings)
            # A busy machine needed more start-up time: keep it for the runs that follow.
            settings = replace(settings, startup_s=max(settings.startup_s, record.startup_s))
            records[kind] = record
            recognized[kind.value] = recognized_frames(record.detections, dataset.truth)
            _write_run(
                out / "runs" / f"seed{seed}-{kind.value}.json", record, recognized[kind.value]
            )
            say(
                f"seed {seed} {kind.value:<12} processed {len(record.detections):3d}, "
                f"dropped at camera {record.dropped:3d}, late {record.skipped_late}; recognized "
                + ", ".join(f"{n} {len(ids)}" for n, ids in recognized[kind.value].items())
            )
        counts = {k: {n: len(ids) for n, ids in v.items()} for k, v in recognized.items()}
        counts["oracle"] = seed_oracle(
            dataset, recognized[RunKind.ALL.value], config.queue, config.service_factor
        )
        seed_result: dict[str, Any] = {
            "seed": seed,
            "frames": len(dataset),
            "dataset": str(dataset.root),
            "markers": seed_markers(counts),
            "runs": {kind.value: records[kind].summary() for kind in config.runs},
            "replay": seed_replay(dataset, records, config),
        }
        if RunKind.FILTERED in records:
            estimated, true = blur_pairs(records[RunKind.FILTERED], dataset.truth)
            q = [
                d.quality
                for d in records[RunKind.FILTERED].decisions
                if d.blur_px is not None and math.isfinite(d.blur_px) and d.quality is not None
            ]
            pearson, spearman = correlations(estimated, true)
            seed_result["quality_vs_blur"] = {
                "pearson": pearson,
                "spearman": spearman,
                "frames": len(true),
            }
            if len(q) == len(true):
                blur_series[f"seed {seed}"] = (estimated, q, true)
        seeds.append(seed_result)
        if first is None:
            first = (dataset, records)
    results = _results(config, seeds, blur_series, started, load_before)
    _write_outputs(config, results, blur_series, first)
    return results


def _results(
    config: ExperimentConfig, seeds: list[dict[str, Any]],
    blur_series: dict[str, tuple[list[float], list[float], list[float]]], started: float,
    load_before: tuple[float, float, float],
) -> dict[str, Any]:  # fmt: skip
    estimated = [v for series in blur_series.values() for v in series[0]]
    true = [v for series in blur_series.values() for v in series[2]]
    pearson, spearman = correlations(estimated, true)
    markers = aggregate_markers(seeds)
    per_seed_r = mean_ci95([s.get("quality_vs_blur", {}).get("pearson") for s in seeds])
    drops = {
        kind.value: [s["runs"][kind.value]["dropped_at_camera"] for s in seeds]
        for kind in config.runs
    }
    results: dict[str, Any] = json_safe(
        {
            "markers": markers,
            "policies": policy_summary(markers, config.runs),
            "replay_vs_real": aggregate_replay(seeds),
            "quality_vs_blur": {
                "pearson": pearson,
                "spearman": spearman,
                "frames": len(true),
                "source": "mediator decisions of the filtered runs, all seeds pooled",
                "pearson_mean_over_seeds": per_seed_r.mean,
                "pearson_ci95_over_seeds": per_seed_r.ci95,
            },
            "camera_drops": drops,
            "seeds": seeds,
            "config": config.to_dict(),
            "paper_table1": PAPER_TABLE1,
            "machine": {
                "cpus": os.cpu_count(),
                "load_avg_before": list(load_before),
                "load_avg_after": list(os.getloadavg()),
            },
            "elapsed_s": round(time.monotonic() - started, 1),
        }
    )
    return results


def _write_outputs(
    config: ExperimentConfig, results: dict[str, Any],
    blur_series: dict[str, tuple[list[float], list[float], list[float]]],
    first: tuple[Dataset, dict[RunKind, RunRecord]] | None,
) -> None:  # fmt: skip
    out = config.out
    (out / RESULTS_FILE).write_text(json.dumps(results, indent=1) + "\n", encoding="utf-8")
    (out / TABLE_FILE).write_text(format_table(results), encoding="utf-8")
    quality = results["quality_vs_blur"]
    nan = float("nan")
    plot_quality_vs_blur(
        blur_series,
        quality["pearson"] if quality["pearson"] is not None else nan,
        quality["spearman"] if quality["spearman"] is not None else nan,
        out / FIG8_FILE,
        b0_px=config.b0_px,
    )
    if first is None:
        return
    dataset, records = first
    filtered = records.get(RunKind.FILTERED)
    decisions = filtered.decisions if filtered is not None else ()
    title = (
        f"seed {config.seeds[0]}, N = {config.queue}, detector {config.service_factor} × "
        f"frame period, b0 {config.b0_px:g} px"
    )
    plot_gyro_exposures(dataset, decisions, out / FIG7_FILE, title=title)
    processed = {kind.value: records[kind].processed_ids for kind in records}
    plot_timeline(dataset, decisions, processed, out / TIMELINE_FILE, title=title)
