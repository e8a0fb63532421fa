"""``framegate simulate`` as a user runs it."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import pytest

from services.lib.sim import read_dataset
from tests.conftest import REPO
from tests.helpers.timing import scaled


def _simulate(*args: str) -> subprocess.CompletedProcess[str]:
    return subprocess.run(
        [sys.executable, "-m", "services.cli", "simulate", *args],
        cwd=REPO, capture_output=True, text=True, timeout=scaled(120), check=False,
    )  # fmt: skip


def test_simulate_writes_the_layout_and_a_report(tmp_path: Path) -> None:
    out = tmp_path / "ds"
    result = _simulate(
        "--seed", "3", "--out", str(out), "--frames", "3", "--exposure-ms", "30",
        "--set", "width_px=320", "--set", "height_px=240", "--set", "wall_texel_m=0.016",
        "--report", "--json",
    )  # fmt: skip
    assert result.returncode == 0, result.stderr
    summary = json.loads(result.stdout)
    assert summary["frames"] == 3 and summary["frames_per_s"] > 0
    names = {p.name for p in out.iterdir()}
    assert names == {
        "camera.xml", "frames", "frames.csv", "gyro.csv", "report.json", "scenario.json",
        "truth.json",
    }  # fmt: skip
    assert sorted(p.name for p in (out / "frames").iterdir()) == [
        "000000.png", "000001.png", "000002.png",
    ]  # fmt: skip
    dataset = read_dataset(out)
    assert dataset.scenario is not None
    assert (dataset.scenario.seed, dataset.scenario.exposure_ns) == (3, 30_000_000)
    assert dataset.frames[0].exposure_ns == 30_000_000
    assert dataset.camera.width_px == 320
    report = json.loads((out / "report.json").read_text())
    assert [m["name"] for m in report["markers"]] == ["large", "medium", "small"]
    assert summary["recognition"] == report


def test_simulate_prints_a_one_line_error_for_a_bad_parameter(tmp_path: Path) -> None:
    result = _simulate("--out", str(tmp_path / "ds"), "--set", "exposure_ms=3")
    assert result.returncode == 1
    assert result.stderr.strip().splitlines()[-1].startswith("error: unknown scenario parameter")
    assert not (tmp_path / "ds").exists()


def test_simulate_names_an_output_directory_it_cannot_create(tmp_path: Path) -> None:
    """It said `error: Not a directory /tmp/file/ds`, the reason before the path."""
    (tmp_path / "file").write_text("")
    out = tmp_path / "file" / "ds"
    result = _simulate("--out", str(out), "--frames", "1")
    assert result.returncode == 1
    assert result.stderr.strip().splitlines() == [
        f"error: cannot create dataset directory {out}: Not a directory"
    ]


@pytest.mark.parametrize(("text", "found"), [("[1, 2]", "an array"), ('"seed"', "a string")])
def test_a_scenario_file_that_is_no_object_is_one_line(
    tmp_path: Path, text: str, found: str
) -> None:
    """A JSON array ended `simulate --config` in a TypeError's traceback."""
    scenario = tmp_path / "s.json"
    scenario.write_text(text)
    result = _simulate("--out", str(tmp_path / "ds"), "--config", str(scenario))
    assert result.returncode == 1
    assert result.stderr.strip().splitlines() == [
        f"error: scenario file {scenario} holds {found}; it needs an object of parameters, "
        'e.g. {"seed": 3, "frame_count": 120}'
    ]
