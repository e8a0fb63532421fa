"""The loopback rendezvous: no single process is the door (a frozen port holder)."""

from __future__ import annotations

import os
import signal
import time
from pathlib import Path

import pytest

from middleware import NetworkConfig, Node, make_metadata
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


@pytest.mark.integration
def test_a_subscriber_resumed_after_a_stop_registers_again_and_says_why(
    node_process, listen_net, endpoint, capfd: pytest.CaptureFixture[str]
) -> None:
    with Node("cam", listen_net) as service:
        images = service.offer("images")
        sub = node_process(None, "--connect", endpoint)
        sub.call("subscribe", target="cam/images", queue=2)
        wait_until(lambda: images.subscriptions(), 10.0, "registered")
        os.kill(sub.proc.pid, signal.SIGSTOP)
        stopped = time.monotonic()
        try:
            wait_until(lambda: not images.subscriptions(), 10.0, "the stopped one lapses")
            # A stop of 3 s, well beyond the 1 s lease (a duration, not a condition).
            time.sleep(max(0.0, stopped + 3.0 - time.monotonic()))
        finally:
            os.kill(sub.proc.pid, signal.SIGCONT)
        wait_until(lambda: images.subscriptions(), 10.0, "registered again after SIGCONT")
        images.put(1, b"x", make_metadata("generic", 1))
        assert sub.call("take", target="cam/images", timeout=5.0)["notification"]["t"] == 1
        wait_until(lambda: "did not run for" in capfd.readouterr().err, 5.0, "the stop logged")
