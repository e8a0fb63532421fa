"""``ls`` names a live service that gave no description (its liveliness token is seen, its
``@info`` answer is not): it was left out with no word, a bare token as much as a real
service whose answer came late (under a churn of thousands of tokens a second, real
services went missing from ``ls`` and ``launch --status`` silently)."""

from __future__ import annotations

import pytest

from middleware import NetworkConfig, Node
from middleware._wire import Keys
from tests.conftest import run_framegate
from tests.helpers.raw_zenoh import open_session
from tests.helpers.timing import wait_until

pytestmark = pytest.mark.integration


def test_ls_names_a_token_holder_that_gives_no_description(endpoint: str) -> None:
    with (
        Node("real", NetworkConfig(listen=(endpoint,))) as real,
        open_session(endpoint) as peer,
    ):
        real.offer("b")
        token = peer.liveliness().declare_token(Keys("framegate").service_token("ghost"))
        try:
            wait_until(lambda: "ghost" in real.live_services(), 20, "the ghost's token")
            result = run_framegate("ls", "--connect", endpoint, timeout_s=60)
        finally:
            token.undeclare()
    assert result.returncode == 0, result.stderr
    assert "real/b" in result.stdout
    warnings = [line for line in result.stderr.splitlines() if "ghost" in line]
    assert len(warnings) == 1, result.stderr
    assert warnings[0].startswith("warning: left out: 1 live services"), warnings
