"""Statistics, goals, rows, options and the table, on fixed inputs (no processes)."""

from __future__ import annotations

import math

import pytest

from services.evidence.bench import (
    SCENARIO_NAMES,
    BenchError,
    BenchOptions,
    Goal,
    Row,
    ScenarioResult,
    format_table,
    median,
    percentile,
    ratio,
    summarize,
)
from services.evidence.bench._records import extra_goal, ratio_goal


def test_median_of_odd_count_is_the_middle_value() -> None:
    assert median([5.0, 1.0, 3.0]) == 3.0


def test_median_of_even_count_is_the_mean_of_the_middle_two() -> None:
    assert median([4.0, 1.0, 3.0, 2.0]) == 2.5


def test_percentile_interpolates_between_closest_ranks() -> None:
    values = [float(v) for v in range(1, 101)]  # 1..100
    assert percentile(values, 0) == 1.0
    assert percentile(values, 100) == 100.0
    assert percentile(values, 50) == pytest.approx(50.5)
    assert percentile(values, 99) == pytest.approx(99.01)  # numpy's "linear" gives the same
    assert percentile([10.0, 20.0], 25) == pytest.approx(12.5)


def test_percentile_of_one_value_is_that_value() -> None:
    assert percentile([7.0], 99) == 7.0


def test_percentile_rejects_empty_input_and_bad_q() -> None:
    with pytest.raises(ValueError, match="no values"):
        percentile([], 50)
    with pytest.raises(ValueError, match="q=101"):
        percentile([1.0], 101)


def test_summary_has_median_min_max_and_count() -> None:
    summary = summarize([3.0, 9.0, 1.0, 5.0])
    assert (summary.median, summary.min, summary.max, summary.count) == (4.0, 1.0, 9.0, 4)
    assert summary.as_json() == {"median": 4.0, "min": 1.0, "max": 9.0, "count": 4}


def test_ratio_is_framegate_over_raw_and_none_without_a_baseline() -> None:
    assert ratio(450.0, 500.0) == pytest.approx(0.9)
    assert ratio(None, 500.0) is None
    assert ratio(450.0, None) is None
    assert ratio(450.0, 0.0) is None
    assert ratio(450.0, math.nan) is None


def test_goal_verdicts_follow_the_comparison() -> None:
    assert Goal("t", 0.9, True, 0.95).verdict == "PASS"
    assert Goal("t", 0.9, True, 0.85).verdict == "MISS"
    assert Goal("t", 1.5, False, 1.5).passed is True
    assert Goal("t", 1.5, False, 1.6).passed is False
    assert Goal("t", 1.5, False, None).verdict == "n/a"


def _throughput_row() -> Row:
    row = Row("64 B", "throughput", "msg/s", higher_is_better=True)
    for pair, (raw, fg) in enumerate([(100.0, 60.0), (120.0, 40.0), (80.0, 50.0)]):
        row.samples("raw").append(
            {"pair": pair, "value": raw, "cpu_producer_pct": 90.0, "cpu_consumer_pct": 50.0}
        )
        row.samples("framegate").append(
            {"pair": pair, "value": fg, "cpu_producer_pct": 70.0, "cpu_consumer_pct": 30.0}
        )
    return row


def test_row_ratio_divides_the_medians() -> None:
    row = _throughput_row()
    assert row.median("raw") == 100.0
    assert row.median("framegate") == 50.0
    assert row.ratio == pytest.approx(0.5)
    assert row.pair_ratios() == pytest.approx([0.6, 1 / 3, 0.625])
    assert row.cpu("framegate") == {"producer": 70.0, "consumer": 30.0}
    goal = ratio_goal(row, 0.5, at_least=True, what="throughput")
    assert goal.passed is True
    assert goal.text == "throughput >= 0.5x raw"


def test_row_without_raw_side_has_no_ratio() -> None:
    row = Row("center", "blur estimate", "us/frame", False, raw=None)
    row.samples("raw").append({"pair": 0, "value": 1.0})  # dropped: there is no raw side
    row.framegate.append({"pair": 0, "value": 30.0})
    assert row.raw is None
    assert row.ratio is None
    assert "raw" not in row.as_json()


def test_table_shows_each_scenario_ratio_goal_and_skips() -> None:
    row = _throughput_row()
    row.goal = ratio_goal(row, 0.9, at_least=True, what="throughput")
    ok = ScenarioResult("small", rows=[row])
    skipped = ScenarioResult(
        "quality", status="skipped", reason="services.lib.quality not available"
    )
    report = {
        "machine": {"cpu_count": 2, "python": "3.11", "zenoh": "1.10.2", "numpy": "2"},
        "options": {"pairs": 3, "duration_s": 4.0, "quick": False},
        "scenarios": {"small": ok.as_json(), "quality": skipped.as_json()},
        "goals": [{"scenario": "small", "row": row.name, **row.goal.as_json()}],
    }
    table = format_table(report)
    line = next(line for line in table.splitlines() if line.startswith("  64 B"))
    assert line.split() == [
        "64",
        "B",
        "msg/s",
        "100",
        "50.0",
        "0.500",
        "MISS",
        "0.500",
        ">=",
        "0.9x",
    ]
    assert "quality: skipped: services.lib.quality not available" in table
    assert "goals: 0/1 passed, 1 missed" in table


def test_options_default_to_all_scenarios_and_three_pairs() -> None:
    options = BenchOptions.create()
    assert options.scenarios == SCENARIO_NAMES
    assert options.pairs == 3
    assert BenchOptions.create(quick=True).pairs == 1


def test_options_refuse_unknown_scenarios_and_too_few_pairs() -> None:
    with pytest.raises(BenchError, match=r"unknown scenario\(s\) framez"):
        BenchOptions.create(("framez",))
    # A misspelt one gets a did-you-mean, as every other name the command line takes.
    with pytest.raises(BenchError, match=r"unknown scenario\(s\) fram \(did you mean frames\?\);"):
        BenchOptions.create(("fram",))
    with pytest.raises(BenchError, match="2 pair"):
        BenchOptions.create(pairs=2)


def _cpu_row(raw: list[float], fg: list[float]) -> Row:
    row = Row("frame: producer CPU", "CPU per element", "us", higher_is_better=False)
    for pair, (r, f) in enumerate(zip(raw, fg, strict=True)):
        row.samples("raw").append({"pair": pair, "value": r})
        row.samples("framegate").append({"pair": pair, "value": f})
    return row


def test_extra_is_what_framegate_adds_to_the_raw_median() -> None:
    row = _cpu_row([20.0, 30.0, 25.0], [90.0, 60.0, 70.0])
    assert row.extra == pytest.approx(45.0)
    assert row.as_json()["extra"] == pytest.approx(45.0)


def test_extra_goal_holds_the_difference_to_its_limit() -> None:
    within = extra_goal(_cpu_row([20.0], [60.0]), 50.0, what="CPU per frame")
    beyond = extra_goal(_cpu_row([20.0], [80.0]), 50.0, what="CPU per frame")
    assert within.text == "CPU per frame: framegate - raw <= 50 us"
    assert (within.passed, beyond.passed) == (True, False)
    assert beyond.measured == pytest.approx(60.0)


def test_row_without_raw_side_has_no_extra() -> None:
    row = Row("camera: process CPU", "CPU", "% of a core", False, raw=None)
    row.framegate.append({"pair": 0, "value": 40.0})
    assert row.extra is None


def test_table_shows_an_extra_goal_with_its_measured_difference() -> None:
    throughput = _throughput_row()
    cpu = _cpu_row([20.0], [80.0])
    cpu.goal = extra_goal(cpu, 50.0, what="CPU per frame")
    report = {
        "machine": {"cpu_count": 2, "python": "3.11", "zenoh": "1.10.2", "numpy": "2"},
        "options": {"pairs": 1, "duration_s": 0.5, "quick": True},
        "scenarios": {"frames": ScenarioResult("frames", rows=[throughput, cpu]).as_json()},
        "goals": [{"scenario": "frames", "row": cpu.name, **cpu.goal.as_json()}],
    }
    lines = format_table(report).splitlines()
    cpu_line = next(line for line in lines if line.startswith("  frame: producer CPU"))
    assert cpu_line.split()[-6:] == ["80.0", "4.000", "MISS", "60.0", "<=", "50"]
