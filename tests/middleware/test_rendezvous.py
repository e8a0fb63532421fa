"""The loopback rendezvous: no single process is the door (a frozen port holder)."""

from __future__ import annotations

import os
import signal
from pathlib import Path

import pytest

from middleware import NetworkConfig, Node
from middleware._rendezvous import directory, known_peers
from tests.conftest import free_port, wait_until


@pytest.mark.integration
def test_a_frozen_port_holder_does_not_keep_newcomers_out(
    node_process, monkeypatch: pytest.MonkeyPatch, tmp_path: Path
) -> None:
    port = free_port()
    monkeypatch.setenv("XDG_RUNTIME_DIR", str(tmp_path))
    monkeypatch.setenv("FRAMEGATE_LOCAL_PORT", str(port))
    hub = node_process("hub")  # first: holds the port
    hub.call("offer", buffer="data")
    other = node_process("other")
    other.call("offer", buffer="data")
    local = NetworkConfig(local_port=port)
    with Node(network=local) as probe:
        wait_until(lambda: {"hub", "other"} <= set(probe.live_services()), 10.0, "both")
    os.kill(hub.proc.pid, signal.SIGSTOP)
    try:
        with Node(network=local) as newcomer:
            wait_until(lambda: "other" in newcomer.live_services(), 10.0, "other seen")
            assert newcomer.query("other/data", last=1) == []
    finally:
        os.kill(hub.proc.pid, signal.SIGCONT)


def test_dead_processes_leave_no_trace_in_the_directory(
    monkeypatch: pytest.MonkeyPatch, tmp_path: Path
) -> None:
    monkeypatch.setenv("XDG_RUNTIME_DIR", str(tmp_path))
    folder = directory(4242)
    folder.mkdir(parents=True)
    (folder / "999999999").write_text("tcp/127.0.0.1:5555\n")  # no such pid
    (folder / str(os.getppid())).write_text("tcp/127.0.0.1:6666\ntcp/0.0.0.0:7777\n")
    assert known_peers(4242) == ["tcp/127.0.0.1:6666"]  # loopback only, the live one
    assert not (folder / "999999999").exists()
