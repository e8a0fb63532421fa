"""The suite's own timing rules: one scale for every deadline, no per-example deadline in
hypothesis tests (a loaded machine exceeds hypothesis's default 200 ms)."""

from __future__ import annotations

import ast
import functools
import subprocess
import sys

import pytest
from hypothesis import settings

from tests.conftest import REPO, child_env
from tests.helpers import timing


@functools.cache  # parsed once, for collection and the test alike
def _hypothesis_tests() -> list[tuple[str, ast.FunctionDef]]:
    found = []
    for path in sorted((REPO / "tests").rglob("*.py")):
        tree = ast.parse(path.read_text(), str(path))
        for node in ast.walk(tree):
            if isinstance(node, ast.FunctionDef) and any(
                isinstance(d, ast.Call) and getattr(d.func, "id", "") == "given"
                for d in node.decorator_list
            ):
                found.append((f"{path.relative_to(REPO)}::{node.name}", node))
    return found


def _deadline_set(node: ast.FunctionDef) -> bool:
    return any(
        isinstance(d, ast.Call)
        and getattr(d.func, "id", "") == "settings"
        and any(k.arg == "deadline" for k in d.keywords)
        for d in node.decorator_list
    )


def test_the_suite_finds_its_hypothesis_tests() -> None:
    assert len(_hypothesis_tests()) >= 20


@pytest.mark.parametrize(
    ("where", "node"), _hypothesis_tests(), ids=lambda v: v[:80] if isinstance(v, str) else ""
)
def test_every_hypothesis_test_sets_its_deadline(where: str, node: ast.FunctionDef) -> None:
    assert _deadline_set(node), f"{where}: say @settings(deadline=...) (None for I/O, big input)"


def test_the_suites_hypothesis_profile_has_no_deadline() -> None:
    assert settings.default.deadline is None


def test_the_scale_multiplies_every_wait(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setattr(timing, "TIMEOUT_SCALE", 3.0)
    assert timing.scaled(2.0) == 6.0
    calls = iter([None, None, "done"])
    assert timing.wait_until(lambda: next(calls), 1.0, "the third call") == "done"
    with pytest.raises(AssertionError, match=r"timed out after 0.03 s waiting for nothing"):
        timing.wait_until(lambda: None, 0.01, "nothing")


@pytest.mark.parametrize("value", ["0.5", "nan", "inf", "fast", "-2"])
def test_a_bad_scale_is_refused_naming_the_variable(value: str) -> None:
    env = child_env()
    env[timing.SCALE_VARIABLE] = value
    out = subprocess.run(
        [sys.executable, "-c", "import tests.helpers.timing"],
        cwd=REPO,
        env=env,
        capture_output=True,
        text=True,
        timeout=timing.scaled(60),
    )
    assert out.returncode != 0
    assert f"{timing.SCALE_VARIABLE}={value!r}: must be a finite number >= 1" in out.stderr


def test_the_scale_reaches_the_processes_a_test_starts() -> None:
    env = child_env()
    env[timing.SCALE_VARIABLE] = "2.5"
    out = subprocess.run(
        [sys.executable, "-c", "from tests.helpers.timing import scaled; print(scaled(4))"],
        cwd=REPO,
        env=env,
        capture_output=True,
        text=True,
        timeout=timing.scaled(60),
    )
    assert out.stdout.strip() == "10.0", out.stderr
