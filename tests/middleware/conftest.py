"""Reports how many protocol state-machine steps ran (issue 14 asks for the count)."""

from __future__ import annotations

import sys

import pytest


def pytest_terminal_summary(terminalreporter: pytest.TerminalReporter) -> None:
    model = sys.modules.get("tests.middleware.test_protocol_model")
    if model is not None and model.STEPS[0]:
        terminalreporter.write_line(
            f"protocol model: {model.STEPS[0]} rule steps in {model.EXAMPLES[0]} programs"
        )
