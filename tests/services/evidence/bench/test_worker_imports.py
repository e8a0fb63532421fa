"""A benchmark worker imports what its role needs and no more: a quick run starts a
hundred-odd workers, and the raw baseline's processes should carry no framegate."""

from __future__ import annotations

import subprocess
import sys

from tests.conftest import REPO, child_env

_PROBE = """
import sys
from services.evidence.bench._worker import find_role
assert find_role({role!r}) is not None
print(" ".join(sorted(m for m in sys.modules if m.split(".")[0] in {names})))
"""


def _imported(role: str, *names: str) -> set[str]:
    probe = _PROBE.format(role=role, names=set(names))
    done = subprocess.run(
        [sys.executable, "-c", probe], cwd=REPO, env=child_env(), capture_output=True, text=True
    )
    assert done.returncode == 0, done.stderr
    return set(done.stdout.split())


def test_a_raw_worker_imports_no_framegate_and_no_scenario() -> None:
    imported = _imported("raw-pub", "middleware", "numpy", "cv2", "services")
    assert not {"middleware", "numpy", "cv2"} & imported, imported
    assert "services.evidence.bench._runner" not in imported, imported


def test_a_framegate_worker_imports_no_scenario() -> None:
    imported = _imported("fg-pub", "middleware", "services")
    assert "middleware" in imported
    assert not {"services.evidence.bench._runner", "services.launch"} & imported, imported


def test_the_package_still_offers_its_names() -> None:
    import services.evidence.bench as bench

    for name in bench.__all__:
        assert getattr(bench, name) is not None, name
