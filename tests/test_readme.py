"""The README's Python examples run as written, against real Zenoh on loopback."""

from __future__ import annotations

import re
import subprocess
import sys

import pytest

from tests.conftest import REPO, child_env, free_port
from tests.helpers.timing import scaled

pytestmark = pytest.mark.integration


def _python_blocks() -> list[str]:
    text = (REPO / "README.md").read_text()
    return re.findall(r"```python\n(.*?)```", text, flags=re.S)


def test_api_example_runs_and_prints_what_it_says() -> None:
    example = next(b for b in _python_blocks() if "from middleware import" in b)
    env = child_env()
    env["FRAMEGATE_LOCAL_PORT"] = str(free_port())
    out = subprocess.run(
        [sys.executable, "-c", example], env=env, capture_output=True, text=True, timeout=scaled(60)
    )
    assert out.returncode == 0, out.stderr
    assert "refused:" in out.stdout
    assert "took 1000 b'frame-1'" in out.stdout
    assert "[2000, 3000]" in out.stdout


def test_quick_start_has_exactly_two_command_lines() -> None:
    text = (REPO / "README.md").read_text()
    section = text.split("## Quick start", 1)[1].split("##", 1)[0]
    block = re.search(r"```bash\n(.*?)```", section, flags=re.S)
    assert block is not None
    lines = [line for line in block.group(1).splitlines() if line.strip()]
    assert len(lines) == 2
    ci = (REPO / ".ci" / "run").read_text()
    assert lines[1] in ci  # CI runs the README's test command


def test_deploy_file_example_parses() -> None:
    from services.launch import parse_deployment

    text = (REPO / "README.md").read_text()
    blocks = re.findall(r"```yaml\n(.*?)```", text, flags=re.S)
    assert blocks
    for block in blocks:
        deployment = parse_deployment(block, "README.md")
        assert deployment.services
