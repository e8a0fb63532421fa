"""Every program in ``examples/`` runs as a user runs it, against real processes."""

from __future__ import annotations

import re
import signal
import subprocess
import sys

import pytest

from tests.conftest import REPO, child_env, free_port
from tests.helpers.timing import scaled

pytestmark = pytest.mark.integration


def _start(script: str, *args: str) -> subprocess.Popen[str]:
    return subprocess.Popen(
        [sys.executable, str(REPO / "examples" / script), *args],
        stdout=subprocess.PIPE,
        stderr=subprocess.STDOUT,
        text=True,
        env=child_env(),
    )


def _finish(proc: subprocess.Popen[str], timeout_s: float = 60) -> str:
    out, _ = proc.communicate(timeout=scaled(timeout_s))
    assert proc.returncode == 0, out
    return out


def test_offer_subscribe_and_query_examples_work_together() -> None:
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    # Until Ctrl-C, not a count: the offer must outlive the subscriber and the query however
    # slowly a loaded machine starts them; a refusal waits up to 60 s instead of 5.
    offer = _start("offer.py", "--listen", endpoint, "--period-s", "0.05", "--wait-s", "60")
    try:
        # The example subscriber gives the service 5 s to appear; a loaded machine can take
        # longer to start the offer: start the subscriber once the service has put something.
        assert offer.stdout is not None
        first = offer.stdout.readline()
        assert first.startswith("put "), first
        # A slow flow-controlled subscriber (queue 1) holds the producer back: the offer
        # example waits instead of losing, so every element it put is still in the buffer.
        sub = _start(
            "subscribe.py", "--connect", endpoint, "--count", "5", "--queue", "1",
            "--delay-s", "0.1",
        )  # fmt: skip
        taken = _finish(sub)
        assert taken.count("took ") == 5, taken
        query = _finish(_start("query.py", "--connect", endpoint, "--range", "[now(-60s)..]"))
        found = int(query.strip().splitlines()[-1].split()[0])
        assert found >= 5, query
        offer.send_signal(signal.SIGINT)  # Ctrl-C: the way to stop it
        out = first + _finish(offer)
    finally:
        if offer.poll() is None:
            offer.kill()
            offer.communicate()
    puts = [int(line.split()[1]) for line in out.splitlines() if line.startswith("put ")]
    assert puts == list(range(len(puts))) and len(puts) >= 5, out
    assert "refused" not in out, out


@pytest.mark.parametrize("signum", [signal.SIGINT, signal.SIGTERM])
def test_the_offer_example_stops_with_exit_0_on_ctrl_c_and_on_kill(signum: int) -> None:
    """As every framegate process: `kill` (SIGTERM) ended it with 143."""
    offer = _start("offer.py", "--listen", f"tcp/127.0.0.1:{free_port()}", "--period-s", "0.05")
    try:
        assert offer.stdout is not None
        first = offer.stdout.readline()
        assert first.startswith("put "), first
        offer.send_signal(signum)
        _finish(offer)
    finally:
        if offer.poll() is None:
            offer.kill()
            offer.communicate()


def test_custom_service_example_refuses_what_its_schema_forbids() -> None:
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    out = _finish(_start("custom_service.py", "--listen", endpoint, "21.5", "nan", "-300", "22"))
    assert "stored 21.5 C" in out and "stored 22.0 C" in out, out
    assert "refused nan C" in out and "refused -300.0 C" in out, out
    assert out.count("read ") == 2, out


def test_every_example_is_tested_here() -> None:
    # Here, or in another module of tests/examples/ (the vision examples have their own).
    tested = {"offer.py", "subscribe.py", "query.py", "custom_service.py"}
    beside = "".join(p.read_text() for p in (REPO / "tests" / "examples").glob("test_*.py"))
    untested = {p.name for p in (REPO / "examples").glob("*.py") if p.name not in tested} - {
        name for name in re.findall(r"[\w]+\.py", beside)
    }
    assert not untested, f"examples no test in tests/examples/ runs: {sorted(untested)}"
