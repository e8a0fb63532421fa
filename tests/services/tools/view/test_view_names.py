"""``framegate view`` with a name that no live service offers: one line, exit 1."""

from __future__ import annotations

import time
from collections.abc import Iterator

import pytest

from middleware import NetworkConfig, Node, make_metadata
from tests.conftest import free_port, start_framegate
from tests.helpers.timing import scaled

pytestmark = pytest.mark.integration


@pytest.fixture
def port() -> Iterator[int]:
    """A rendezvous port with a live ``camera`` service offering ``images``."""
    port = free_port()
    with Node("camera", NetworkConfig(local_port=port)) as node:
        images = node.offer("images")
        t = time.time_ns()
        images.put(t, b"x", make_metadata("generic", t))
        yield port


@pytest.mark.parametrize(
    ("target", "said"),
    [
        ("camera/imags", "service 'camera' has no buffer 'imags' (did you mean 'images'?)"),
        ("camra/images", "no live service named 'camra' (did you mean 'camera'?)"),
    ],
)
def test_a_name_no_live_service_offers_fails_with_one_line_and_a_did_you_mean(
    port: int, target: str, said: str
) -> None:
    # Long enough to meet the live camera on a loaded machine (2 s once saw no service at all,
    # so no did-you-mean): the misspelt service never comes, so the view waits all of it.
    wait = str(scaled(5))
    proc = start_framegate(["view", target, "--port", "0", "--timeout", wait], local_port=port)
    out, _ = proc.communicate(timeout=scaled(60))
    lines = out.strip().splitlines()
    assert proc.returncode == 1, out
    assert len(lines) == 1, out
    assert lines[0].startswith("error: ") and said in lines[0], out
