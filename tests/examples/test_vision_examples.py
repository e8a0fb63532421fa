"""The vision examples run as a user runs them: the handler alone, its deploy file, and the
cheap-vs-expensive measurement against real processes."""

from __future__ import annotations

import subprocess
import sys

import pytest

from tests.conftest import REPO, child_env
from tests.helpers.timing import scaled


def _run(*argv: str, timeout_s: float) -> subprocess.CompletedProcess[str]:
    return subprocess.run(
        [sys.executable, *argv],
        capture_output=True,
        text=True,
        cwd=REPO,
        env=child_env(),
        timeout=scaled(timeout_s),
    )


def test_the_template_example_finds_its_marker_and_says_what_it_costs() -> None:
    result = _run("examples/vision_template.py", "--frames", "2", timeout_s=120)
    assert result.returncode == 0, result
    assert "ms per frame" in result.stdout and "found marker 0" in result.stdout, result


def test_the_vision_deploy_file_checks() -> None:
    result = _run("-m", "services.cli", "launch", "examples/vision.yaml", "--check", timeout_s=120)
    assert result.returncode == 0, result
    assert "examples.vision_template:find_marker" in result.stdout, result


@pytest.mark.integration
@pytest.mark.slow
def test_the_compare_example_measures_both_handlers_from_one_camera() -> None:
    result = _run("examples/vision_compare.py", "--seconds", "4", "--warmup-s", "1", timeout_s=300)
    assert result.returncode == 0, result
    rows = {line.split()[0]: line.split()[1:] for line in result.stdout.splitlines()[2:]}
    assert sorted(rows) == ["cheap", "expensive"], result.stdout
    for values in rows.values():
        assert len(values) == 5 and values[-1].endswith("%"), result.stdout
