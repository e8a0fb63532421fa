"""The quick run of ``framegate bench`` as a subprocess, and what its report must hold.

Three test files run it in parts, so that the suite's workers share them and each part has
its own time budget (a whole quick run took 283 s at a load of 18-20 on 2 cores, once 834
s): the transport scenarios (``test_bench_command.py``), the rest
(``test_bench_quick_rest.py``) and the hostile one (``test_bench_hostile_quick.py``).
Asserted: every scenario produced numbers and the JSON has the documented keys, never a
speed: this machine is shared and its speed is not ours to test.
"""

from __future__ import annotations

import json
import math
import shutil
import subprocess
import sys
from pathlib import Path
from typing import Any

from services.evidence.bench import SCENARIO_NAMES, SCHEMA
from tests.conftest import REPO, child_env
from tests.helpers.timing import scaled

# The quick run's parts: the transport scenarios, hostile, and the rest of them.
TRANSPORT = ("frames", "small", "batch", "latency")
REST = tuple(name for name in SCENARIO_NAMES if name not in (*TRANSPORT, "hostile"))

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


def number(value: Any) -> bool:
    return isinstance(value, int | float) and not isinstance(value, bool) and math.isfinite(value)


def bench_command() -> list[str]:
    exe = shutil.which("framegate")
    return [exe, "bench"] if exe else [sys.executable, "-m", "services.cli", "bench"]


def quick_run(tmp_path: Path, scenarios: list[str], *flags: str) -> None:
    """``framegate bench --quick FLAGS SCENARIO...``: exit 0, and a report with numbers for
    each scenario."""
    out = tmp_path / "bench.json"
    done = subprocess.run(
        [*bench_command(), "--quick", "--json", str(out), *flags, *scenarios],
        cwd=REPO,
        env=child_env(),
        capture_output=True,
        text=True,
        # A bench is CPU work: under two busy loops plus the rest of the suite at load 20-27
        # on 2 cores, 480 s were missed; the whole quick run once took 834 s of 900.
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
    assert list(report["scenarios"]) == scenarios
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
                    assert number(sample["value"]) and isinstance(sample["pair"], int), where
                for key in ("median", "min", "max"):
                    assert number(row[side][key]), (where, side, key)
            if "raw" in row and row["raw"]["median"] == 0:
                # A ratio to nothing is no number: e.g. a loaded machine's quick working
                # point forwarded no frame to the detector, so neither side had work.
                assert row["ratio"] is None, where
            elif "raw" in row:
                assert number(row["ratio"]), where
                assert all(number(r) for r in row["pair_ratios"]), where
            if row["metric"] == "throughput":
                for side in sides:
                    assert set(row[side]["cpu_pct"]) == {"producer", "consumer"}, where
            if row["metric"] == "CPU per element":
                assert number(row["extra"]), where
    for goal in report["goals"]:
        assert set(goal) >= GOAL_KEYS
        assert number(goal["measured"]), goal
        assert isinstance(goal["passed"], bool), goal
    if "small" in report["scenarios"]:  # CPU per element at equal rates, both sides
        names = [row["name"] for row in report["scenarios"]["small"]["rows"]]
        assert "64 B at framegate's rate: producer CPU" in names, names
        assert "64 B at framegate's rate: consumer CPU" in names, names
    goal_scenarios = {g["scenario"] for g in report["goals"]}
    assert goal_scenarios == set(scenarios)
    for name in scenarios:
        assert name in done.stdout
    assert all(len(line) <= 100 for line in done.stdout.splitlines()), done.stdout
