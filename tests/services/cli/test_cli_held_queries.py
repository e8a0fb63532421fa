"""``ls``, ``info`` and ``query`` beside a peer whose queryables on ``@info/*`` and on the
buffer's data key take each query and never finalize it: each waited its whole timeout
(``--timeout 20``); now each ends with the answers of the services themselves."""

from __future__ import annotations

import json
import time

import pytest
import zenoh

from middleware import NetworkConfig, Node, make_metadata
from middleware._wire import Keys
from tests.conftest import run_framegate
from tests.helpers.raw_zenoh import open_session
from tests.helpers.timing import scaled, wait_until

pytestmark = pytest.mark.integration


def test_ls_info_and_query_end_with_the_services_answers(endpoint: str) -> None:
    timeout_s = scaled(60)
    held: list[zenoh.Query] = []
    took: dict[str, float] = {}
    with (
        Node("cam", NetworkConfig(listen=(endpoint,))) as cam,
        open_session(endpoint) as rogue,
    ):
        cam.offer("images").put(5, b"x", make_metadata("generic", 5))
        keys = Keys("framegate")
        queryables = [
            rogue.declare_queryable(key, zenoh.handlers.Callback(held.append))
            for key in (keys.info("*"), keys.data("cam", "images"))
        ]
        try:
            wait_until(lambda: "cam" in cam.live_services(), 20, "the service's token")
            results = {}
            query = ["query", "cam/images", "--last", "1", "--json"]
            for command in (["ls"], ["info", "cam"], query):
                began = time.monotonic()
                results[command[0]] = run_framegate(
                    *command, "--connect", endpoint, "--timeout", str(timeout_s), timeout_s=120
                )
                took[command[0]] = time.monotonic() - began
            reached = len(held)
        finally:
            for queryable in queryables:
                queryable.undeclare()
            held.clear()
    assert reached, "the rogue's queryables never saw a query: the test proves nothing"
    for name, result in results.items():
        assert result.returncode == 0, (name, result.stderr)
    assert "cam/images" in results["ls"].stdout
    assert "images" in results["info"].stdout
    assert json.loads(results["query"].stdout)["count"] == 1, results["query"].stdout
    # Before: each at least timeout_s. Hang detectors, not speed bounds.
    assert all(s < timeout_s / 2 for s in took.values()), took
