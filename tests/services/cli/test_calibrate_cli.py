"""framegate calibrate: b0 from a recorded sequence."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import pytest

from services.lib.sim import Bump, ScenarioConfig, simulate
from tests.conftest import REPO, child_env
from tests.helpers.timing import scaled


@pytest.fixture(scope="module")
def shaky_dataset(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """The last 60 frames of an approach (markers readable), with strong pitch bumps."""
    out = tmp_path_factory.mktemp("shaky")
    config = ScenarioConfig(seed=4).replace(
        frame_count=60,
        start_distance_m=4.0,
        bumps=tuple(Bump(at_travel_m=0.1 + 0.12 * i, height_m=0.01) for i in range(16)),
    )
    simulate(config, out, progress=False)
    return out


def test_calibrate_derives_b0_from_recognition_against_blur(shaky_dataset: Path) -> None:
    out = subprocess.run(
        [
            sys.executable,
            "-m",
            "services.cli",
            "calibrate",
            str(shaky_dataset),
            "--json",
            "--no-progress",
        ],
        capture_output=True,
        text=True,
        cwd=REPO,
        env=child_env(),
        timeout=scaled(120),
    )
    if out.returncode != 0:
        # Not enough blur in a short sequence is a user-facing, one-line answer.
        assert out.stderr.startswith("error: ") and "Traceback" not in out.stderr, out.stderr
        assert "recognition never falls to half" in out.stderr or "too few" in out.stderr
        return
    result = json.loads(out.stdout)
    assert 0.5 < result["b0_px"] < 50
    assert result["trials"] >= 20
