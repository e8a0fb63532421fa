"""The loopback rendezvous: no single process is the door (a frozen port holder)."""

from __future__ import annotations

import contextlib
import json
import os
import re
import signal
import subprocess
import sys
import threading
import time
from collections.abc import Iterator
from pathlib import Path

import pytest

from middleware import NetworkConfig, Node, make_metadata
from middleware._rendezvous import directory, known_peers
from tests.conftest import REPO, child_env, free_port, wait_until
from tests.helpers.timing import answered, scaled


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
            assert answered(lambda: newcomer.query("other/data", last=1), "other/data") == []
    finally:
        os.kill(hub.proc.pid, signal.SIGCONT)


def test_dead_processes_leave_no_trace_in_the_directory(
    monkeypatch: pytest.MonkeyPatch, tmp_path: Path
) -> None:
    monkeypatch.setenv("XDG_RUNTIME_DIR", str(tmp_path))
    folder = directory(4242)
    folder.mkdir(parents=True)
    (folder / "999999999-1").write_text("tcp/127.0.0.1:5555\n")  # no such pid
    (folder / f"{os.getppid()}-1").write_text("tcp/127.0.0.1:6666\ntcp/0.0.0.0:7777\n")
    assert known_peers(4242) == ["tcp/127.0.0.1:6666"]  # loopback only, the live one
    assert not (folder / "999999999-1").exists()


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
        assert sub.call("take", target="cam/images", timeout=30)["notification"]["t"] == 1
        wait_until(lambda: "did not run for" in capfd.readouterr().err, 30, "the stop logged")


# A service whose executor is nearly always inside a handler (sleeping there, not in its
# own wait), as a loaded mediator's is: a stop then comes mid-turn.
BUSY_SERVICE = """
import logging, sys, threading, time
from middleware import NetworkConfig, Node
logging.basicConfig(level=logging.INFO, format="%(message)s")
def busy(_now):
    print("busy", flush=True)
    time.sleep(0.5)
with Node("busy", NetworkConfig(listen=(sys.argv[1],))) as node:
    node.every(0.01, busy)
    node.spin(threading.Event())
"""


@pytest.mark.integration
def test_a_stop_that_comes_mid_turn_is_said_whole(endpoint: str) -> None:
    proc = subprocess.Popen(
        [sys.executable, "-c", BUSY_SERVICE, endpoint],
        cwd=REPO, env=child_env(), stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
    )  # fmt: skip
    said: list[float] = []

    def pump() -> None:
        assert proc.stderr is not None
        for line in proc.stderr:
            found = re.search(r"did not run for ([0-9.]+) s", line)
            if found:
                said.append(float(found.group(1)))

    threading.Thread(target=pump, daemon=True).start()
    try:
        assert proc.stdout is not None and proc.stdout.readline().strip() == "busy"
        os.kill(proc.pid, signal.SIGSTOP)
        try:
            time.sleep(3.0)  # the stop's length (a duration, not a condition)
        finally:
            os.kill(proc.pid, signal.SIGCONT)
        # At least the stop less one 0.25 s slice of ``spin``, less the log's rounding: a
        # lower bound that no slow machine can miss (the stop lasted that long).
        wait_until(lambda: any(s >= 2.7 for s in said), 30, lambda: f"the stop said whole: {said}")
    finally:
        proc.kill()
        proc.wait()


def _framegate(argv: list[str], port: int, runtime: Path) -> subprocess.Popen[str]:
    env = child_env()
    env["FRAMEGATE_LOCAL_PORT"] = str(port)
    env["XDG_RUNTIME_DIR"] = str(runtime)
    return subprocess.Popen(
        [sys.executable, "-m", "services.cli", *argv],
        cwd=REPO, env=env, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True,
    )  # fmt: skip


def _run(argv: list[str], port: int, runtime: Path) -> tuple[int, str, float]:
    """``framegate ARGV`` to its end: exit code, output, seconds taken."""
    start = time.monotonic()
    proc = _framegate(argv, port, runtime)
    out, _ = proc.communicate(timeout=scaled(60))
    return proc.returncode, out, time.monotonic() - start


def _holder_of(port: int) -> int | None:
    """The pid listening on the rendezvous port (from /proc/net/tcp and the fd tables)."""
    inode = None
    for line in Path("/proc/net/tcp").read_text().splitlines()[1:]:
        fields = line.split()
        if fields[1] == f"0100007F:{port:04X}" and fields[3] == "0A":  # LISTEN
            inode = fields[9]
    if inode is None:
        return None
    for fd_dir in Path("/proc").glob("[0-9]*/fd"):
        with contextlib.suppress(OSError):
            for fd in fd_dir.iterdir():
                with contextlib.suppress(OSError):
                    if os.readlink(fd) == f"socket:[{inode}]":
                        return int(fd_dir.parent.name)
    return None


@pytest.fixture(scope="module")
def frozen_holder(tmp_path_factory: pytest.TempPathFactory) -> Iterator[tuple[int, Path]]:
    """A rendezvous whose port holder (a gyro) is stopped with SIGSTOP, beside a live gyro2.
    One for the module: its tests only run commands against it, and two gyros started and
    a holder frozen past its lease took seconds a test."""
    port, runtime = free_port(), tmp_path_factory.mktemp("run")
    hub = _framegate(["run", "gyro", "--source", "sim", "--loop"], port, runtime)
    other: subprocess.Popen[str] | None = None
    try:
        wait_until(lambda: _holder_of(port) == hub.pid, 60, "the first gyro on the port")
        with pytest.MonkeyPatch.context() as monkeypatch:  # the probe's rendezvous files
            monkeypatch.setenv("XDG_RUNTIME_DIR", str(runtime))
            with Node(network=NetworkConfig(local_port=port)) as probe:
                wait_until(lambda: "gyro" in probe.live_services(), 60, "the first gyro")
                other = _framegate(["run", "gyro", "--source", "sim", "--loop", "--name",
                                    "gyro2"], port, runtime)  # fmt: skip
                wait_until(lambda: "gyro2" in probe.live_services(), 60, "gyro2")
        os.kill(hub.pid, signal.SIGSTOP)
        # Past the lease, so that the others have dropped it too.
        wait_until(lambda: Path(f"/proc/{hub.pid}/stat").read_text().split()[2] == "T", 30, "stop")
        yield port, runtime
    finally:
        os.kill(hub.pid, signal.SIGCONT)
        for proc in (hub, other):
            if proc is not None and proc.poll() is None:
                proc.send_signal(signal.SIGINT)
                try:
                    proc.wait(timeout=scaled(20))
                except subprocess.TimeoutExpired:
                    proc.kill()
                    proc.wait()


@pytest.mark.integration
def test_ls_query_and_watch_work_while_the_port_holder_is_frozen(
    frozen_holder: tuple[int, Path],
) -> None:
    port, runtime = frozen_holder
    code, out, _ = _run(["ls", "--timeout", str(scaled(10.0))], port, runtime)
    assert code == 0 and "gyro2" in out, out
    code, out, _ = _run(["query", "gyro2/rates", "--last", "1"], port, runtime)
    assert code == 0 and "\n1 element\n" in out, out
    code, out, _ = _run(["watch", "gyro2/rates", "--count", "3", "--timeout", "30"], port, runtime)
    assert code == 0 and "seq" in out, out


@pytest.mark.integration
def test_ls_ends_promptly_while_the_port_holder_is_frozen(frozen_holder: tuple[int, Path]) -> None:
    # A deadline for answers a 10x slower machine meets (at load 36 the default 2 s missed gyro2).
    code, out, took = _run(["ls", "--timeout", str(scaled(10.0))], *frozen_holder)
    assert code == 0 and "gyro2" in out, out
    # ls answered although the holder never completes a handshake. How soon is a speed, not
    # a test's business (1.9 s at load 8 on 2 cores, 11.7 s at load 40): what makes it soon
    # is the rendezvous's handshake timeout, checked below in the configuration itself.
    print(f"ls with the port holder frozen took {took:.2f} s")


def test_a_rendezvous_handshake_gives_up_after_a_second() -> None:
    """Without this, a newcomer waits Zenoh's default 10 s on a frozen port holder."""
    from middleware._config import RENDEZVOUS_OPEN_TIMEOUT_MS

    assert RENDEZVOUS_OPEN_TIMEOUT_MS <= 1_000
    for conf in NetworkConfig(local_port=free_port()).zenoh_configs():
        timeout = json.loads(conf.get_json("transport/unicast/open_timeout"))
        assert timeout == RENDEZVOUS_OPEN_TIMEOUT_MS


@pytest.mark.integration
def test_a_process_on_two_rendezvous_ports_keeps_them_apart(
    monkeypatch: pytest.MonkeyPatch, tmp_path: Path
) -> None:
    monkeypatch.setenv("XDG_RUNTIME_DIR", str(tmp_path))
    first, second = free_port(), free_port()
    with (
        Node(network=NetworkConfig(local_port=first)),
        Node(network=NetworkConfig(local_port=second)),
    ):

        def announced(port: int) -> set[str]:
            return {
                endpoint
                for path in directory(port).glob(f"{os.getpid()}-*")
                for endpoint in path.read_text().split()
            }

        on_first, on_second = announced(first), announced(second)
        assert f"tcp/127.0.0.1:{first}" in on_first and on_second, (on_first, on_second)
        assert not on_first & on_second, (on_first, on_second)
