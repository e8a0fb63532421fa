"""The compact table, the load warning, ``--check`` and the hostile window (no processes)."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import pytest

from services.cli import bench as bench_cli
from services.cli import main
from services.evidence.bench import (
    SCENARIO_NAMES,
    BenchError,
    BenchOptions,
    Goal,
    Row,
    ScenarioResult,
    format_table,
)
from services.evidence.bench._report import WIDTH, load_warning, short_goal
from services.evidence.bench._runner import LOAD_WARNING_SHARE


def _report(goals_passed: list[bool | None], *, load: float = 0.1) -> dict[str, Any]:
    rows = []
    for i, passed in enumerate(goals_passed):
        row = Row(
            f"a rather long row name that would not fit in any column number {i}",
            "CPU",
            "% of a core",
            higher_is_better=False,
        )
        row.samples("raw").append({"pair": 0, "value": 1_234_567.0})
        row.framegate.append({"pair": 0, "value": 7_654_321.0})
        measured = None if passed is None else (1.0 if passed else 3.0)
        row.goal = Goal("framegate CPU <= 2 % of a core", 2.0, False, measured)
        rows.append(row)
    result = ScenarioResult("working-point", rows=rows)
    return {
        "machine": {
            "cpu_count": 2,
            "python": "3.11.7",
            "zenoh": "1.10.2",
            "load_average_start": [load, load, load],
        },
        "options": {"pairs": 3, "duration_s": 4.0, "quick": False},
        "scenarios": {
            "working-point": result.as_json(),
            "memory": ScenarioResult(
                "memory", status="error", reason="BenchError: " + "x" * 300
            ).as_json(),
        },
        "goals": [
            {"scenario": "working-point", "row": r.name, **r.goal.as_json()} for r in rows if r.goal
        ],
        "warnings": [
            w
            for w in [
                load_warning({"cpu_count": 2, "load_average_start": [load]}, LOAD_WARNING_SHARE)
            ]
            if w
        ],
    }


def test_every_line_of_the_table_fits_the_width_and_rows_take_one_line() -> None:
    report = _report([True, False, None], load=5.1)
    table = format_table(report, notes=True)
    assert all(len(line) <= WIDTH for line in table.splitlines()), table
    assert sum(1 for line in table.splitlines() if "rather long row name" in line) == 3
    assert "1,234,567" in table and "7,654,321" in table
    assert "memory: error: BenchError: xxx" in table


def test_the_header_gives_each_scenarios_own_window_and_a_legend_names_other_columns() -> None:
    """ros2-loop runs 15 s windows and compares a node uncontrolled with the node in the
    loop: the header said "pair(s) of 0.5 s" under --quick, and raw/framegate went unsaid."""
    report = _report([True])
    legend = "columns: raw = the node uncontrolled; framegate = the node in the loop"
    loop = ScenarioResult("ros2-loop", params={"window_s": 15.0, "legend": legend})
    row = Row("recognitions, all markers (15 s runs)", "recognitions", "count", True)
    row.samples("raw").append({"pair": 0, "value": 100.0})
    row.framegate.append({"pair": 0, "value": 110.0})
    loop.rows = [row]
    report["options"] = {"pairs": 1, "duration_s": 0.5, "quick": True}
    report["scenarios"] = {"ros2-loop": loop.as_json()}
    table = format_table(report).splitlines()
    assert "1 pair(s) of 15 s;" in table[0], table[0]
    assert table[table.index("ros2-loop") + 1] == f"  {legend}", table
    report["scenarios"]["working-point"] = ScenarioResult("working-point").as_json()
    assert "1 pair(s) of 0.5 s (ros2-loop 15 s);" in format_table(report).splitlines()[0]


def test_short_goal_shows_verdict_measured_and_limit() -> None:
    goal = Goal("throughput >= 0.1x raw", 0.1, True, 0.019).as_json()
    assert short_goal(goal) == "MISS 0.019 >= 0.1x"
    idle = Goal("idle CPU <= 0.5 % of a core", 0.5, False, 0.2).as_json()
    assert short_goal(idle) == "PASS 0.200 <= 0.5"
    assert short_goal(Goal("t", 1.0, True, None).as_json()) == "n/a - >= 1"


def test_load_above_half_the_cores_warns_that_figures_are_unreliable() -> None:
    assert load_warning({"cpu_count": 2, "load_average_start": [0.9, 0, 0]}, 0.5) is None
    warning = load_warning({"cpu_count": 2, "load_average_start": [5.1, 0, 0]}, 0.5)
    assert warning is not None and warning.startswith("figures unreliable: load 5.10")
    table = format_table(_report([True], load=5.1))
    assert table.splitlines()[1].startswith("WARNING: figures unreliable: load 5.10")
    assert "WARNING" not in format_table(_report([True], load=0.2))


def test_check_exit_code_follows_the_goals_and_errors() -> None:
    ok = {"scenarios": {"a": {"status": "ok"}}, "goals": [{"passed": True}, {"passed": None}]}
    missed = {"scenarios": {"a": {"status": "ok"}}, "goals": [{"passed": False}]}
    broken = {"scenarios": {"a": {"status": "error"}}, "goals": []}
    assert bench_cli.exit_code(ok, check=True) == 0
    assert bench_cli.exit_code(missed, check=False) == 0
    assert bench_cli.exit_code(missed, check=True) == bench_cli.GOAL_MISSED
    assert bench_cli.exit_code(broken, check=False) == 1


def test_command_prints_the_compact_table_and_check_fails_on_a_miss(
    monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str], tmp_path: Path
) -> None:
    # The runner is replaced (no processes): this checks the command's own wiring.
    report = _report([True, False])
    seen: list[BenchOptions] = []

    def fake_run(options: BenchOptions) -> dict[str, Any]:
        seen.append(options)
        return report

    monkeypatch.setattr(bench_cli, "run_bench", fake_run)
    out = tmp_path / "b.json"
    assert main(["bench", "--quick", "idle", "--json", str(out)]) == 1  # memory errored
    del report["scenarios"]["memory"]
    assert main(["bench", "--quick", "idle"]) == 0
    assert main(["bench", "--quick", "--check", "idle"]) == bench_cli.GOAL_MISSED
    printed = capsys.readouterr().out
    assert all(len(line) <= WIDTH for line in printed.splitlines())
    assert "goals: 1/2 passed, 1 missed" in printed
    assert json.loads(out.read_text())["goals"][1]["passed"] is False
    assert seen[0].scenarios == ("idle",) and seen[0].quick


def test_quiet_progress_shows_scenario_starts_and_warnings_only(
    capsys: pytest.CaptureFixture[str],
) -> None:
    show = bench_cli.progress_printer(verbose=False)
    for message in ("== idle", "idle pair 1/1: raw producer 0.00%", "WARNING: figures"):
        show(message)
    assert capsys.readouterr().err.splitlines() == ["== idle", "WARNING: figures"]
    bench_cli.progress_printer(verbose=True)("idle pair 1/1")
    assert capsys.readouterr().err == "idle pair 1/1\n"


def test_duration_sets_the_hostile_window_and_defaults_are_two_minutes() -> None:
    assert BenchOptions.create().hostile_s == 120.0
    assert BenchOptions.create(quick=True).hostile_s < 120.0
    assert BenchOptions.create(("hostile",), duration_s=20.0).hostile_s == 20.0
    assert {"idle", "hostile"} <= set(SCENARIO_NAMES)
    for bad in (0.0, -1.0, float("nan"), float("inf")):
        with pytest.raises(BenchError, match="must be a number > 0"):
            BenchOptions.create(duration_s=bad)
