"""Zenoh's runtimes in a framegate process: no acceptor or network threads unless the user
chose.

Each case runs in a fresh interpreter: Zenoh reads ``ZENOH_RUNTIME`` once, when the
process's first session starts its runtimes, and a pytest worker may have opened sessions
before.
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import pytest

from tests.conftest import free_port
from tests.helpers.timing import scaled

pytestmark = pytest.mark.integration

ROOT = Path(__file__).resolve().parents[2]

# Two nodes in one process exchange an element (so every runtime that would run has run),
# then the process reports its threads' names and what its environment says.
_SCRIPT = """
import json, os, sys
from middleware import NetworkConfig, Node, make_metadata
endpoint = sys.argv[1]
with Node("svc", NetworkConfig(listen=(endpoint,))) as service:
    images = service.offer("images")
    with Node(network=NetworkConfig(connect=(endpoint,))) as client:
        sub = client.subscribe("svc/images", queue_size=2, wait_s=30.0)
        images.put(1, b"x", make_metadata("generic", 1), wait_s=30.0)
        note = sub.take(timeout_s=30.0)
        names = sorted({open(f"/proc/self/task/{t}/comm").read().strip()
                        for t in os.listdir("/proc/self/task")})
        print(json.dumps({"taken": note is not None, "threads": names,
                          "env": os.environ.get("ZENOH_RUNTIME")}))
"""


def _run(env_runtime: str | None) -> dict[str, object]:
    env = {k: v for k, v in os.environ.items() if k != "ZENOH_RUNTIME"}
    env["PYTHONPATH"] = str(ROOT)
    if env_runtime is not None:
        env["ZENOH_RUNTIME"] = env_runtime
    done = subprocess.run(
        [sys.executable, "-c", _SCRIPT, f"tcp/127.0.0.1:{free_port()}"],
        env=env,
        capture_output=True,
        text=True,
        timeout=scaled(120),
        check=True,
    )
    result: dict[str, object] = json.loads(done.stdout.strip().splitlines()[-1])
    return result


def _zenoh_runtimes(threads: object) -> set[str]:
    """The Zenoh runtimes that have threads (Zenoh names them ``<runtime>-<n>``)."""
    assert isinstance(threads, list)
    return {name.split("-")[0] for name in threads} & {"acc", "app", "net", "rx", "tx"}


@pytest.mark.skipif(not Path("/proc/self/task").is_dir(), reason="needs /proc")
def test_zenoh_polls_its_sockets_on_its_receive_threads_by_default() -> None:
    out = _run(None)
    assert out["taken"] is True
    assert _zenoh_runtimes(out["threads"]) == {"app", "rx", "tx"}
    assert out["env"] is None  # set only around the first open: children inherit no change


@pytest.mark.skipif(not Path("/proc/self/task").is_dir(), reason="needs /proc")
def test_a_user_zenoh_runtime_is_kept() -> None:
    out = _run("()")  # Zenoh's own defaults: separate receive, send, network threads
    assert out["taken"] is True
    assert {"rx", "tx", "net"} <= _zenoh_runtimes(out["threads"])
    assert out["env"] == "()"
