"""Statistics over seeds: mean, 95 % t-interval, improvement, correlations, aggregation."""

from __future__ import annotations

import math
from types import SimpleNamespace

import pytest

from services.evidence.experiment import (
    Estimate,
    aggregate_markers,
    correlations,
    improvement_pct,
    mean_ci95,
    seed_markers,
)
from services.evidence.experiment._config import RUN_KINDS
from services.evidence.experiment._experiment import policy_summary, seed_oracle

MS = 1_000_000


def test_mean_ci95_uses_students_t_with_n_minus_one_degrees_of_freedom() -> None:
    estimate = mean_ci95([1.0, 2.0, 3.0, 4.0, 5.0])
    # t(0.975, 4) = 2.7764451; sample std = sqrt(2.5); half-width = t * std / sqrt(5).
    assert estimate.mean == pytest.approx(3.0)
    assert estimate.ci95 == pytest.approx(2.7764451 * math.sqrt(2.5) / math.sqrt(5), rel=1e-6)
    assert estimate.n == 5


def test_mean_ci95_of_two_values_is_wide() -> None:
    # t(0.975, 1) = 12.7062047; std of (10, 12) = sqrt(2); half-width = t * sqrt(2) / sqrt(2).
    assert mean_ci95([10.0, 12.0]).ci95 == pytest.approx(12.7062047, rel=1e-6)


def test_mean_ci95_of_identical_values_has_zero_width() -> None:
    assert mean_ci95([7.0, 7.0, 7.0]) == Estimate(7.0, 0.0, 3)


def test_mean_ci95_of_one_value_has_no_interval() -> None:
    assert mean_ci95([4.5]) == Estimate(4.5, None, 1)


def test_mean_ci95_skips_undefined_values() -> None:
    assert mean_ci95([None, float("nan"), 2.0, 4.0]).mean == pytest.approx(3.0)
    assert mean_ci95([None]) == Estimate(None, None, 0)


def test_improvement_pct_is_relative_to_the_base() -> None:
    assert improvement_pct(154, 161) == pytest.approx(4.5454545)
    assert improvement_pct(62, 71) == pytest.approx(14.516129)
    assert improvement_pct(100, 90) == pytest.approx(-10.0)


def test_improvement_over_nothing_is_undefined() -> None:
    assert improvement_pct(0, 5) is None


def test_estimate_formats_mean_and_interval() -> None:
    assert Estimate(161.24, 3.46, 5).format(1) == "161.2 ± 3.5"
    assert Estimate(4.54, 2.0, 5).format(1, signed=True) == "+4.5 ± 2.0"
    assert Estimate(4.54, None, 1).format(1) == "4.5"
    assert Estimate(None, None, 0).format() == "-"


def test_correlations_of_a_monotonic_relation() -> None:
    true = [0.5, 1.0, 2.0, 4.0, 8.0]
    pearson, spearman = correlations([2 * v + 1 for v in true], true)
    assert pearson == pytest.approx(1.0)
    assert spearman == pytest.approx(1.0)
    pearson, spearman = correlations([v**2 for v in true], true)
    assert pearson < 1.0
    assert spearman == pytest.approx(1.0)


def test_correlations_are_undefined_for_constant_or_short_input() -> None:
    assert all(math.isnan(v) for v in correlations([1.0, 1.0, 1.0], [1.0, 2.0, 3.0]))
    assert all(math.isnan(v) for v in correlations([1.0, 2.0], [1.0, 2.0]))
    with pytest.raises(ValueError, match="3 estimates but 2"):
        correlations([1.0, 2.0, 3.0], [1.0, 2.0])


def _counts(all_: int, unc: int, filt: int, beyond: int) -> dict[str, dict[str, int]]:
    return {
        "all": {"large": all_, "medium": all_, "small": all_},
        "uncontrolled": {"large": unc, "medium": unc, "small": 0},
        "filtered": {"large": filt, "medium": filt, "small": 3},
        "beyond": {"large": beyond, "medium": beyond, "small": 4},
    }


def test_seed_markers_compares_runs_per_marker() -> None:
    markers = seed_markers(_counts(246, 154, 161, 170))
    large = markers["large"]
    assert (large["all"], large["uncontrolled"], large["filtered"], large["beyond"]) == (
        246, 154, 161, 170,
    )  # fmt: skip
    assert large["improvement_pct"] == pytest.approx(700 / 154)
    assert large["beyond_improvement_pct"] == pytest.approx(1600 / 154)
    assert large["beyond_vs_filtered_pct"] == pytest.approx(900 / 161)
    assert markers["small"]["improvement_pct"] is None  # nothing recognized uncontrolled


def test_seed_markers_without_a_run_leaves_its_columns_empty() -> None:
    counts = _counts(10, 5, 6, 7)
    del counts["beyond"]
    small = seed_markers(counts)["large"]
    assert small["beyond"] is None and small["beyond_improvement_pct"] is None


def test_aggregate_markers_averages_seeds_with_intervals_and_quotes_the_paper() -> None:
    seeds = [
        {"markers": seed_markers(_counts(240, 150, 156, 160))},
        {"markers": seed_markers(_counts(250, 160, 168, 170))},
        {"markers": seed_markers(_counts(245, 155, 160, 165))},
    ]
    large = aggregate_markers(seeds)["large"]
    assert large["all"] == pytest.approx(245.0)
    assert large["all_ci95"] == pytest.approx(4.3026527 * 5.0 / math.sqrt(3), rel=1e-6)
    per_seed = [600 / 150, 800 / 160, 500 / 155]
    assert large["improvement_pct"] == pytest.approx(sum(per_seed) / 3)
    assert large["improvement_ci95"] == large["improvement_pct_ci95"]
    assert large["paper"] == {
        "recognizable": 246, "uncontrolled": 154, "filtered": 161, "improvement_pct": 4.5,
    }  # fmt: skip
    # Small: no seed recognized it uncontrolled, so there is no improvement to average.
    assert aggregate_markers(seeds)["small"]["improvement_pct"] is None


def test_the_oracle_gives_each_run_its_share_of_the_possible_gain() -> None:
    counts = _counts(246, 150, 160, 170)
    counts["oracle"] = {"large": 190, "medium": 150, "small": 3}
    large = seed_markers(counts)["large"]
    assert large["oracle"] == 190
    assert large["captured"] == pytest.approx(10 / 40)
    assert large["beyond_captured"] == pytest.approx(20 / 40)
    assert seed_markers(counts)["medium"]["captured"] is None  # the oracle gains nothing
    seeds = [{"markers": seed_markers(counts)}, {"markers": seed_markers(counts)}]
    aggregated = aggregate_markers(seeds)["large"]
    assert aggregated["captured"] == {"mean": pytest.approx(0.25), "ci95": 0.0, "n": 2}
    summary = policy_summary(aggregate_markers(seeds), RUN_KINDS)
    assert summary["paper"]["large"]["captured"]["mean"] == pytest.approx(0.25)
    assert summary["paper"]["large"]["oracle"]["mean"] == pytest.approx(190)


def test_seed_oracle_is_the_best_schedule_of_the_all_runs_recognitions() -> None:
    # Frames every 100 ms, the detector needs 250 ms, N = 1: after a frame that waits, the
    # next one finds the queue full unless a frame was skipped.
    dataset = SimpleNamespace(
        frames=[
            SimpleNamespace(frame_id=i, exposure_start_ns=i * 100 * MS, exposure_ns=MS)
            for i in range(5)
        ]
    )
    recognized = {"large": [0, 2, 3], "medium": [1, 2, 3, 4], "small": []}
    oracle = seed_oracle(dataset, recognized, queue=1, service_factor=2.5)  # type: ignore[arg-type]
    assert oracle["large"] == 3  # 0, skip 1, then 2 and 3 each wait their turn
    assert oracle["medium"] == 3  # 3 would be the second frame waiting: one must go
    assert oracle["small"] == 0
    assert oracle["total"] == 5  # 0, 2, 3 (5 recognitions) beats 1, 2, 4 (4)
