"""A few simulated frames on disk, for a camera that replays them instead of rendering live.

A live ``sim`` camera keeps a core busy for as long as it runs, and its first frame takes
seconds; where the rendering is not what a test is about, a camera replaying a handful of
simulated frames in a loop (``--source replay --path DIR --loop``) is a real camera process
at a fraction of the CPU.
"""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

from tests.conftest import REPO, child_env
from tests.helpers.timing import scaled


def simulated_frames(out: Path, count: int = 8) -> Path:
    """``framegate simulate`` of ``count`` frames into ``out`` (a dataset directory)."""
    argv = ["simulate", "--out", str(out), "--frames", str(count), "--no-progress"]
    subprocess.run(
        [sys.executable, "-m", "services.cli", *argv],
        cwd=REPO,
        env=child_env(),
        check=True,
        capture_output=True,
        timeout=scaled(300),
    )
    return out
