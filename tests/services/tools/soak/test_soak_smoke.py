"""``framegate soak`` for a few seconds: it runs the pipeline and produces its numbers."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import pytest

from tests.conftest import REPO, child_env

pytestmark = pytest.mark.integration


def test_short_soak_reports_memory_and_lost_elements(tmp_path: Path) -> None:
    report_file = tmp_path / "soak.json"
    done = subprocess.run(
        [
            sys.executable,
            "-m",
            "services.cli.soak",
            "--duration",
            "20",
            "--sample",
            "2",
            "--check",
            "4",
            "--json",
            str(report_file),
        ],
        cwd=REPO,
        env=child_env(),
        capture_output=True,
        text=True,
        timeout=180,
    )
    # 3: a goal was missed, which 20 s (still warming up) may well do; this only runs it.
    assert done.returncode in (0, 3), done.stdout + done.stderr
    assert "lost (goal 0)" in done.stdout
    report = json.loads(report_file.read_text())
    assert set(report["processes"]) == {"camera", "gyro", "mediator", "detector"}
    for name, samples in report["memory_samples"].items():
        assert len(samples) >= 3, name
        assert all(rss > 0 for _t, _pid, rss in samples)
    assert isinstance(report["lost_total"], int)
    assert report["duration_s"] >= 20
