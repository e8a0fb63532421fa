"""launch --check as data: the plan as JSON, and --json refused without --check."""

from __future__ import annotations

import json

import pytest

from services.cli import main
from tests.conftest import REPO


def test_check_json_gives_each_process_with_its_command_and_starts_nothing(
    capsys: pytest.CaptureFixture[str],
) -> None:
    assert main(["launch", str(REPO / "deploy" / "local.yaml"), "--check", "--json"]) == 0
    plan = json.loads(capsys.readouterr().out)
    assert plan["started"] is False
    by_name = {p["name"]: p for p in plan["processes"]}
    assert sorted(by_name) == ["camera", "detector", "gyro", "mediator"]
    assert by_name["camera"]["command"][:5] == ["framegate", "run", "camera", "--name", "camera"]
    assert by_name["detector"]["type"] == "detector" and by_name["detector"]["restart"] is True


def test_json_without_check_is_one_line_and_exit_1(capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["launch", str(REPO / "deploy" / "local.yaml"), "--json"]) == 1
    err = capsys.readouterr().err
    assert err.startswith("error: --json prints the plan of --check") and err.count("\n") == 1
