"""What a fresh interpreter has imported after running a script (start-up cost checks)."""

from __future__ import annotations

import json
import subprocess
import sys

from tests.conftest import REPO, child_env
from tests.helpers.timing import scaled

_LISTING = "\nimport json as _j, sys as _s\nprint(_j.dumps(sorted(_s.modules)))\n"


def modules_after(script: str) -> set[str]:
    """The names in ``sys.modules`` once ``script`` ran in a new Python process."""
    result = subprocess.run(
        [sys.executable, "-c", script + _LISTING],
        capture_output=True,
        text=True,
        cwd=REPO,
        env=child_env(),
        timeout=scaled(120),
        check=True,
    )
    return set(json.loads(result.stdout.splitlines()[-1]))
