"""docs/ros2-bridge.md says what it shows: its hand-written commands are deploy/ros2.yaml."""

from __future__ import annotations

import shlex
import subprocess
import sys
from typing import Any

from services.cli.run import service_parser
from services.nodes import service
from tests.conftest import REPO, child_env
from tests.helpers.timing import scaled

# The bridge's reference page (the paragraph moved there from the README).
README = REPO / "docs" / "ros2-bridge.md"
SAME_AS = "`deploy/ros2.yaml` runs the same as these three commands:"


def _readme_commands() -> list[list[str]]:
    """The ``framegate run`` lines of the code block after SAME_AS (continuations joined)."""
    text = README.read_text()
    assert SAME_AS in text, f"{README.name} lost the paragraph this test checks"
    block = text.split(SAME_AS, 1)[1].split("```bash\n", 1)[1].split("```", 1)[0]
    return [shlex.split(line) for line in block.replace("\\\n", " ").splitlines() if line.strip()]


def _launch_commands() -> list[list[str]]:
    out = subprocess.run(
        [sys.executable, "-m", "services.cli", "launch", "--check", "deploy/ros2.yaml"],
        cwd=REPO,
        env=child_env(),
        capture_output=True,
        text=True,
        timeout=scaled(60),
        check=True,
    ).stdout
    return [shlex.split(line) for line in out.splitlines() if line.strip().startswith("framegate")]


def _configs(commands: list[list[str]]) -> dict[str, Any]:
    configs = {}
    for words in commands:
        assert words[:2] == ["framegate", "run"], words
        name = words[2]
        parsed = service_parser(name).parse_args(words[3:])
        configs[name] = service(name).config_from_args(parsed)
    return configs


def test_the_readmes_commands_are_what_the_deploy_file_runs() -> None:
    readme, deploy = _configs(_readme_commands()), _configs(_launch_commands())
    assert set(readme) == {"ros2", "mediator", "detector"}
    assert readme == deploy
