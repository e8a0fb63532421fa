"""``framegate soak`` for a few seconds: it runs the pipeline and loses nothing."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import pytest

from tests.conftest import REPO, child_env
from tests.helpers.timing import scaled

pytestmark = pytest.mark.integration


@pytest.mark.slow
def test_short_soak_loses_nothing_and_reports_memory(tmp_path: Path) -> None:
    report_file = tmp_path / "soak.json"
    done = subprocess.run(
        [
            sys.executable,
            "-m",
            "services.cli",
            "soak",
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
        timeout=scaled(180),
    )
    # 3: a goal was missed, which 20 s (still warming up) may well do; this only runs it.
    assert done.returncode in (0, 3), done.stdout + done.stderr
    assert "lost (goal 0)" in done.stdout
    report = json.loads(report_file.read_text())
    assert set(report["processes"]) == {"camera", "gyro", "mediator", "detector"}
    for name, samples in report["memory_samples"].items():
        assert len(samples) >= 3, name
        assert all(rss > 0 for _t, _pid, rss in samples)
    # What soak promises: every frame decided, every accepted frame forwarded intact and
    # detected, audited while the pipeline ran.
    assert report["audit"]["checks"] >= 2, report["audit"]
    assert report["audit"]["frames_decided"] > 0, report["audit"]
    assert report["audit"]["accepted"] > 0, report["audit"]
    assert report["lost_total"] == 0, report["audit"]["lost"]
    assert report["goals"]["lost_ok"]
    assert not any(report["restarts"].values()), report["restarts"]
    assert report["duration_s"] >= 20
