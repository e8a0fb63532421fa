"""``framegate bench``: the quick run as a subprocess, and argument errors.

The quick run asserts only that every scenario produced numbers and that the JSON has the
documented keys — never a speed: this machine is shared and its speed is not ours to test.
"""

from __future__ import annotations

import json
import math
import shutil
import signal
import subprocess
import sys
from pathlib import Path
from typing import Any

import psutil
import pytest

from services.cli import main
from services.evidence.bench import SCENARIO_NAMES, SCHEMA
from tests.conftest import REPO, child_env, wait_until
from tests.helpers.timing import scaled

REPORT_KEYS = {"schema", "created_utc", "elapsed_s", "machine", "options", "scenarios", "goals"}
MACHINE_KEYS = {"cpu_count", "python", "zenoh", "numpy", "msgpack", "platform"}
OPTION_KEYS = {"scenarios", "duration_s", "pairs", "quick", "warmup_s"}
SCENARIO_KEYS = {"status", "reason", "params", "elapsed_s", "rows"}
ROW_KEYS = {
    "name",
    "metric",
    "unit",
    "higher_is_better",
    "framegate",
    "ratio",
    "extra",
    "pair_ratios",
    "goal",
    "note",
}
SIDE_KEYS = {"samples", "median", "min", "max", "count", "cpu_pct"}
GOAL_KEYS = {"scenario", "row", "text", "limit", "comparison", "measured", "passed"}


def _number(value: Any) -> bool:
    return isinstance(value, int | float) and not isinstance(value, bool) and math.isfinite(value)


def _bench_command() -> list[str]:
    exe = shutil.which("framegate")
    return [exe, "bench"] if exe else [sys.executable, "-m", "services.cli", "bench"]


@pytest.mark.integration
@pytest.mark.slow
@pytest.mark.timeout(960)
def test_quick_run_gives_numbers_for_every_scenario(tmp_path: Path) -> None:
    out = tmp_path / "bench.json"
    done = subprocess.run(
        [*_bench_command(), "--quick", "--json", str(out)],
        cwd=REPO,
        env=child_env(),
        capture_output=True,
        text=True,
        # A bench is CPU work: under two busy loops plus the rest of the suite at load 20-27
        # on 2 cores, 480 s were missed.
        timeout=scaled(900),
    )
    assert done.returncode == 0, done.stdout + done.stderr[-3000:]
    report = json.loads(out.read_text())
    assert set(report) >= REPORT_KEYS
    assert report["schema"] == SCHEMA
    assert set(report["machine"]) >= MACHINE_KEYS
    assert report["machine"]["cpu_count"] >= 1
    assert set(report["options"]) >= OPTION_KEYS
    assert report["options"]["quick"] is True
    assert list(report["scenarios"]) == list(SCENARIO_NAMES)
    for name, scenario in report["scenarios"].items():
        assert set(scenario) >= SCENARIO_KEYS, name
        assert scenario["status"] == "ok", (name, scenario["reason"])
        assert scenario["rows"], name
        for row in scenario["rows"]:
            where = f"{name}/{row['name']}"
            assert set(row) >= ROW_KEYS, where
            sides = ["framegate"] + (["raw"] if "raw" in row else [])
            for side in sides:
                assert set(row[side]) >= SIDE_KEYS, where
                assert row[side]["samples"], where
                for sample in row[side]["samples"]:
                    assert _number(sample["value"]) and isinstance(sample["pair"], int), where
                for key in ("median", "min", "max"):
                    assert _number(row[side][key]), (where, side, key)
            if "raw" in row and row["raw"]["median"] == 0:
                # A ratio to nothing is no number: e.g. a loaded machine's quick working
                # point forwarded no frame to the detector, so neither side had work.
                assert row["ratio"] is None, where
            elif "raw" in row:
                assert _number(row["ratio"]), where
                assert all(_number(r) for r in row["pair_ratios"]), where
            if row["metric"] == "throughput":
                for side in sides:
                    assert set(row[side]["cpu_pct"]) == {"producer", "consumer"}, where
            if row["metric"] == "CPU per element":
                assert _number(row["extra"]), where
    for goal in report["goals"]:
        assert set(goal) >= GOAL_KEYS
        assert _number(goal["measured"]), goal
        assert isinstance(goal["passed"], bool), goal
    goal_scenarios = {g["scenario"] for g in report["goals"]}
    assert goal_scenarios == set(SCENARIO_NAMES)
    for name in SCENARIO_NAMES:
        assert name in done.stdout
    assert all(len(line) <= 100 for line in done.stdout.splitlines()), done.stdout


def test_unknown_scenario_is_an_error_naming_it(capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["bench", "framez"]) == 1
    assert "unknown scenario(s) framez" in capsys.readouterr().err


def test_too_few_pairs_without_quick_is_refused(capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["bench", "--pairs", "1", "small"]) == 1
    assert "use --pairs 3 or more, or --quick" in capsys.readouterr().err


def test_json_into_a_missing_directory_is_refused(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    assert main(["bench", "--quick", "--json", str(tmp_path / "no" / "b.json"), "small"]) == 1
    assert "directory" in capsys.readouterr().err


@pytest.mark.integration
@pytest.mark.parametrize("signum", [signal.SIGINT, signal.SIGTERM])
def test_one_signal_stops_the_bench_and_its_workers_with_exit_0(signum: int) -> None:
    proc = subprocess.Popen(
        [*_bench_command(), "--quick", "idle"],
        cwd=REPO,
        env=child_env(),
        stdout=subprocess.DEVNULL,
        stderr=subprocess.DEVNULL,
    )
    try:
        me = psutil.Process(proc.pid)
        workers = wait_until(
            lambda: (
                [c for c in me.children(recursive=True) if "_worker" in " ".join(c.cmdline())]
                if len(me.children(recursive=True)) >= 4
                else None
            ),
            60.0,
            "the bench's idle workers to start",
        )
        proc.send_signal(signum)
        assert proc.wait(timeout=scaled(15.0)) == 0
        _gone, alive = psutil.wait_procs(workers, timeout=scaled(10.0))
        assert not alive, alive
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()
