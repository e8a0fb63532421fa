"""``framegate experiment --quick`` as a user runs it: real processes, every output file."""

from __future__ import annotations

import json
import signal
import subprocess
import sys
from pathlib import Path
from typing import Any

import pytest

from services.evidence.experiment import MARKER_NAMES, OUTPUT_FILES
from tests.conftest import REPO, child_env
from tests.helpers.timing import scaled

_PNG = b"\x89PNG\r\n\x1a\n"


@pytest.mark.integration
@pytest.mark.slow
@pytest.mark.timeout(280)
def test_quick_experiment_writes_every_output(tmp_path: Path) -> None:
    out = tmp_path / "exp"
    proc = subprocess.Popen(
        [sys.executable, "-m", "services.cli", "experiment", "--quick", "--out", str(out),
         "--no-progress"],
        cwd=REPO, env=child_env(), stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
    )  # fmt: skip
    try:
        stdout, stderr = proc.communicate(timeout=scaled(240))
    except subprocess.TimeoutExpired:
        # SIGTERM first: the experiment then stops the service processes it started.
        proc.terminate()
        stdout, stderr = proc.communicate(timeout=scaled(30))
        pytest.fail(f"experiment --quick took over 240 s\n{stdout[-2000:]}{stderr[-2000:]}")
    assert proc.returncode == 0, stdout[-3000:] + stderr[-3000:]
    for name in OUTPUT_FILES:
        assert (out / name).is_file(), name
    for name in ("fig7_gyro.png", "fig8_quality_vs_blur.png", "timeline.png"):
        assert (out / name).read_bytes()[:8] == _PNG, name

    results = json.loads((out / "results.json").read_text())
    assert set(results["markers"]) == set(MARKER_NAMES)
    for row in results["markers"].values():
        for key in ("all", "uncontrolled", "filtered", "beyond", "improvement_pct",
                    "improvement_ci95"):  # fmt: skip
            assert key in row
        assert isinstance(row["all"], float)
    assert set(results["quality_vs_blur"]) >= {"pearson", "spearman"}
    assert results["quality_vs_blur"]["pearson"] > 0.8  # gyro and truth agree at all
    assert [s["seed"] for s in results["seeds"]] == [1]
    assert results["config"]["quick"] is True and results["config"]["queue"] == 2
    assert set(results["camera_drops"]) == {"all", "uncontrolled", "filtered", "beyond"}

    seed = results["seeds"][0]
    runs = seed["runs"]
    frames = seed["frames"]
    assert frames == 60
    # `all` processes every frame; the camera refuses none of them.
    all_log = (out / "logs" / "seed1-all.log").read_text(errors="replace")
    assert runs["all"]["processed"] == frames - runs["all"]["skipped_late"], all_log[-3000:]
    assert runs["all"]["dropped_at_camera"] == 0
    # Every frame the camera handled was stored or refused; the detector drained its input,
    # unless its process was starved past its lease (a loaded machine): then its
    # subscription lapsed, the frames stored meanwhile never reached it, and its log says so.
    for name in ("uncontrolled", "filtered", "beyond"):
        run = runs[name]
        assert run["stored"] + run["dropped_at_camera"] + run["skipped_late"] == frames
        given = run["forwarded"] if run["forwarded"] is not None else run["stored"]
        log = (out / "logs" / f"seed1-{name}.log").read_text(errors="replace")
        if run["processed"] != given:
            assert not run["drained"] and "had lapsed" in log, (run, log[-3000:])
    # With a mediator in front the camera never has to drop: it discards by quality instead.
    assert runs["filtered"]["dropped_at_camera"] == 0
    assert runs["filtered"]["accepted"] == runs["filtered"]["forwarded"]
    assert seed["markers"]["large"]["all"] >= seed["markers"]["large"]["uncontrolled"]

    table = (out / "table.md").read_text()
    assert "| large | paper (quoted) | 246 | 154 | 161 | +4.5 |" in table
    assert "| large | framegate |" in table
    assert (out / "runs" / "seed1-filtered.json").is_file()
    assert "wrote" in stdout


def test_experiment_command_is_registered() -> None:
    result = subprocess.run(
        [sys.executable, "-m", "services.cli", "experiment", "--help"],
        cwd=REPO, env=child_env(), capture_output=True, text=True, timeout=scaled(60), check=False,
    )  # fmt: skip
    assert result.returncode == 0, result.stderr
    for flag in ("--seeds", "--out", "--queue", "--service-factor", "--b0", "--quick"):
        assert flag in result.stdout


def test_bad_flag_value_is_one_error_line(tmp_path: Path) -> None:
    result = subprocess.run(
        [sys.executable, "-m", "services.cli", "experiment", "--out", str(tmp_path), "--queue",
         "0"],
        cwd=REPO, env=child_env(), capture_output=True, text=True, timeout=scaled(60), check=False,
    )  # fmt: skip
    assert result.returncode == 1
    assert result.stderr.strip() == (
        "error: framegate experiment: argument --queue: must be an integer > 0, got '0'"
    )


def test_sweep_latency_flag_reaches_the_sweep(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    import services.evidence.experiment as experiment
    from services.cli import main

    seen: list[Any] = []

    def fake_sweep(config: Any, *, log: Any = None) -> dict[str, Any]:
        seen.append(config)
        (config.out / experiment.SWEEP_TABLE).write_text("table\n", encoding="utf-8")
        return {}

    monkeypatch.setattr(experiment, "run_sweep", fake_sweep)
    # The command makes SIGTERM unwind like Ctrl-C; give pytest its handler back afterwards.
    monkeypatch.setattr(signal, "signal", lambda *_args: None)
    for flag, expected in (([], "measured"), (["--latency", "none"], "none")):
        code = main(["experiment", "--sweep", "--out", str(tmp_path), "--no-progress", *flag])
        assert code == 0
        assert seen[-1].latency == expected


def test_a_command_without_flags_runs_the_configs_own_defaults(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """The parser writes its defaults apart from ExperimentConfig and SweepConfig (it must not
    import the experiment package); what `--help` says they are is what they are."""
    import dataclasses

    import services.evidence.experiment as experiment
    from services.cli import experiment as command
    from services.cli import main
    from services.evidence.experiment._config import QUICK_FRAMES

    seen: list[Any] = []

    def fake(config: Any, *, log: Any = None) -> dict[str, Any]:
        seen.append(config)
        for name in (*experiment.OUTPUT_FILES, experiment.SWEEP_TABLE):
            (config.out / name).write_text("x\n", encoding="utf-8")
        return {}

    monkeypatch.setattr(experiment, "run_experiment", fake)
    monkeypatch.setattr(experiment, "run_sweep", fake)
    monkeypatch.setattr(signal, "signal", lambda *_args: None)
    assert main(["experiment", "--out", str(tmp_path), "--no-progress"]) == 0
    assert main(["experiment", "--sweep", "--out", str(tmp_path), "--no-progress"]) == 0
    assert main(["experiment", "--quick", "--out", str(tmp_path), "--no-progress"]) == 0
    run, sweep, quick = seen
    for got, expected in ((run, experiment.ExperimentConfig), (sweep, experiment.SweepConfig)):
        for field in dataclasses.fields(expected):
            if field.name not in ("out", "progress"):
                assert getattr(got, field.name) == field.default, field.name
    assert quick.frame_count == QUICK_FRAMES == command.QUICK_FRAMES
    assert quick.seeds == (1,) and quick.startup_s == command.QUICK_STARTUP_S
