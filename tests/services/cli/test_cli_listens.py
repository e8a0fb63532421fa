"""``ls`` and ``info`` show what a service's process really listens on."""

from __future__ import annotations

import json
from collections.abc import Callable

import pytest

from tests.conftest import NodeProcess, run_framegate, wait_until
from tests.helpers.timing import scaled

pytestmark = pytest.mark.integration


def test_ls_and_info_show_the_endpoint_a_service_listens_on(
    node_process: Callable[..., NodeProcess], endpoint: str
) -> None:
    service = node_process("cam", "--listen", endpoint)
    assert service.call("offer", buffer="images")["ok"]

    def listed() -> list[str] | None:
        done = run_framegate("ls", "--json", "--connect", endpoint)
        if done.returncode != 0:
            return None
        services = {s["service"]: s for s in json.loads(done.stdout)["services"]}
        return services["cam"]["listen"] if "cam" in services else None

    listen = wait_until(listed, scaled(20), "cam listed")
    assert endpoint in listen, listen
    shown = run_framegate("info", "cam/images", "--connect", endpoint)
    assert shown.returncode == 0, shown.stderr
    [line] = [line for line in shown.stdout.splitlines() if "listens on" in line]
    assert endpoint in line, line
