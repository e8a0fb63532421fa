"""launch --check and --status, one launcher per deploy file, deaths by signal reported."""

from __future__ import annotations

import os
import queue
import signal
import socket
import subprocess
import sys
import threading
import time
from pathlib import Path

import psutil
import pytest

from middleware import ConfigError, NetworkConfig, Node
from services.launch import (
    LaunchLock,
    ProcessSpec,
    Supervisor,
    lock_path,
    parse_deployment,
    process_specs,
)
from tests.conftest import REPO, child_env, free_port, wait_until
from tests.helpers.timing import scaled

STARTUP_S = 60.0


class Launch:
    """``framegate launch ARGS`` as a child process whose output lines are read with a
    deadline; stopped at the end of the test."""

    def __init__(self, args: list[str], runtime_dir: Path, local_port: int) -> None:
        env = child_env()
        env["FRAMEGATE_RUNTIME_DIR"] = str(runtime_dir)
        env["FRAMEGATE_LOCAL_PORT"] = str(local_port)
        self.proc = subprocess.Popen(
            [sys.executable, "-m", "services.cli", "launch", "--no-colour", *args],
            cwd=REPO,
            env=env,
            stdout=subprocess.PIPE,
            stderr=subprocess.STDOUT,
            text=True,
        )
        self.lines: list[str] = []
        self._queue: queue.Queue[str | None] = queue.Queue()
        threading.Thread(target=self._pump, daemon=True).start()

    def _pump(self) -> None:
        assert self.proc.stdout is not None
        for line in self.proc.stdout:
            self._queue.put(line.rstrip("\n"))
        self._queue.put(None)

    def wait_line(self, predicate: object, timeout_s: float = STARTUP_S) -> str:
        deadline = time.monotonic() + scaled(timeout_s)
        while (remaining := deadline - time.monotonic()) > 0:
            try:
                line = self._queue.get(timeout=remaining)
            except queue.Empty:
                break
            if line is None:
                raise AssertionError(f"launch ended ({self.proc.wait()}): {self.lines}")
            self.lines.append(line)
            if predicate(line):  # type: ignore[operator]
                return line
        raise AssertionError(f"no such line within {timeout_s} s: {self.lines}")

    def finish(self, timeout_s: float = 30.0) -> int:
        code = self.proc.wait(timeout=scaled(timeout_s))
        while (line := self._queue.get(timeout=scaled(timeout_s))) is not None:
            self.lines.append(line)
        return code

    def close(self) -> None:
        if self.proc.poll() is None:
            self.proc.kill()
            self.proc.wait()


def _router_deploy(tmp_path: Path, *, restart: bool = True) -> Path:
    """A deploy file of one cheap process: a router on a free loopback port."""
    path = tmp_path / "router.yaml"
    path.write_text(
        "version: 1\nservices:\n"
        f"  hub: {{type: router, restart: {str(restart).lower()}, "
        f"network: {{listen: [tcp/127.0.0.1:{free_port()}]}}}}\n"
    )
    return path


def _child_pid(launch: Launch) -> int:
    def child() -> int | None:
        kids = psutil.Process(launch.proc.pid).children()
        return kids[0].pid if kids else None

    return int(wait_until(child, STARTUP_S, "the launched process"))


@pytest.mark.parametrize(
    ("args", "message"),
    [
        ("      frames: -5\n", r"x\.yaml:5: service 'camera': argument --frames: .*> 0"),
        ("      rate: .nan\n", r"x\.yaml:5: service 'camera': argument --rate: .*'nan'"),
        ("      rate: .inf\n", r"x\.yaml:5: .*argument --rate: .*'inf'"),
        ("      retention_frames: 0\n", r"x\.yaml:5: .*--retention-frames: .*> 0"),
    ],
)
def test_a_bad_value_in_a_deploy_file_names_its_line(args: str, message: str) -> None:
    text = "services:\n  camera:\n    args:\n      source: sim\n" + args
    deployment = parse_deployment(text, "x.yaml")
    with pytest.raises(ConfigError, match=message):
        process_specs(deployment, None, NetworkConfig(), text=text)


def test_check_prints_the_plan_and_starts_nothing(tmp_path: Path) -> None:
    port = free_port()
    launch = Launch([str(REPO / "deploy" / "local.yaml"), "--check"], tmp_path, port)
    try:
        code = launch.finish(timeout_s=120)
    finally:
        launch.close()
    out = "\n".join(launch.lines)
    assert code == 0, out
    for service in ("camera", "gyro", "mediator", "detector"):
        assert f"framegate run {service} --name {service}" in out, out
    assert "nothing started" in out
    with Node(network=NetworkConfig(local_port=port)) as node:
        assert node.live_services(timeout_s=scaled(1.0)) == []


def test_check_of_a_bad_deploy_file_is_one_line_and_exit_1(tmp_path: Path) -> None:
    bad = tmp_path / "bad.yaml"
    bad.write_text("services:\n  camera:\n    args: {source: sim, rate: .nan}\n")
    launch = Launch([str(bad), "--check"], tmp_path, free_port())
    try:
        code = launch.finish(timeout_s=120)
    finally:
        launch.close()
    assert code == 1, launch.lines
    assert len(launch.lines) == 1 and launch.lines[0].startswith(f"error: {bad}:3:"), launch.lines


@pytest.mark.integration
def test_a_second_launch_of_a_running_deploy_file_refuses_with_the_first_pid(
    tmp_path: Path,
) -> None:
    deploy = _router_deploy(tmp_path)
    port = free_port()
    first = Launch([str(deploy)], tmp_path, port)
    second: Launch | None = None
    try:
        first.wait_line(lambda line: line.startswith("launching"))
        _child_pid(first)
        second = Launch([str(deploy)], tmp_path, port)  # same file, host and rendezvous
        # At once, not after a restart storm: the whole process ends on its own.
        code = second.finish(timeout_s=60)
        assert code == 1, second.lines
        assert any(f"already launched by pid {first.proc.pid}" in li for li in second.lines), (
            second.lines
        )
        assert first.proc.poll() is None, "the first launcher must be untouched"
    finally:
        first.close()
        if second is not None:
            second.close()


@pytest.mark.integration
def test_the_same_deploy_file_launches_again_against_another_rendezvous(tmp_path: Path) -> None:
    # Two rendezvous ports are two separate sets of services: the lock must not mix them.
    deploy = tmp_path / "gyro.yaml"
    deploy.write_text("version: 1\nservices:\n  gyro:\n    args: {source: sim, loop: true}\n")
    first = Launch([str(deploy)], tmp_path, free_port())
    second: Launch | None = None
    try:
        first.wait_line(lambda line: "simulated gyro" in line)
        second = Launch([str(deploy)], tmp_path, free_port())
        second.wait_line(lambda line: "simulated gyro" in line)
        assert first.proc.poll() is None and second.proc.poll() is None, second.lines
        second.proc.send_signal(signal.SIGINT)
        assert second.finish(timeout_s=60) == 0, second.lines
    finally:
        first.close()
        if second is not None:
            second.close()


def test_a_lock_is_per_rendezvous(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setenv("FRAMEGATE_RUNTIME_DIR", str(tmp_path / "run"))
    deploy = tmp_path / "d.yaml"
    deploy.write_text("services: {}\n")
    with LaunchLock(deploy, None, NetworkConfig(local_port=7001)):
        with pytest.raises(ConfigError, match=r"7001.* already launched by pid"):
            LaunchLock(deploy, None, NetworkConfig(local_port=7001)).acquire()
        LaunchLock(deploy, None, NetworkConfig(local_port=7002)).acquire()
        LaunchLock(deploy, None, NetworkConfig(connect=("tcp/10.0.0.2:7447",))).acquire()


def test_a_lock_is_exclusive_and_a_dead_holders_lock_is_taken_over(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    monkeypatch.setenv("FRAMEGATE_RUNTIME_DIR", str(tmp_path / "run"))
    deploy = tmp_path / "d.yaml"
    deploy.write_text("services: {}\n")
    # A lock file left by a launcher that died (its pid in it, no flock held).
    stale = lock_path(deploy, None)
    stale.parent.mkdir(parents=True)
    stale.write_text("999999999\n")
    with LaunchLock(deploy):
        assert stale.read_text().strip() == str(os.getpid())
        with pytest.raises(ConfigError, match=rf"already launched by pid {os.getpid()}"):
            LaunchLock(deploy).acquire()
        LaunchLock(deploy, "other-host").acquire()  # another host of the file: its own lock
    with LaunchLock(deploy):  # released on exit
        pass


def test_supervisor_names_a_death_by_signal() -> None:
    lines: list[str] = []
    suicide = "import os, signal; os.kill(os.getpid(), signal.SIGABRT)"
    supervisor = Supervisor(
        [
            ProcessSpec("aborts", (sys.executable, "-c", suicide), restart=False),
            ProcessSpec("fine", (sys.executable, "-c", "pass"), restart=False),
        ],
        colour=False,
        out=lines.append,
    )
    supervisor.start()
    try:
        wait_until(
            lambda: (supervisor.poll(), supervisor.signal_deaths())[1], 30, "the abort noticed"
        )
        wait_until(lambda: (supervisor.poll(), any("fine" in li for li in lines))[1], 30, "fine")
    finally:
        supervisor.stop()
    assert supervisor.signal_deaths() == {"aborts": ["died by signal SIGABRT (6)"]}
    assert any("died by signal SIGABRT (6); not restarting" in li for li in lines), lines


@pytest.mark.integration
def test_launch_reports_a_child_killed_by_a_signal_and_exits_1(tmp_path: Path) -> None:
    launch = Launch([str(_router_deploy(tmp_path, restart=False))], tmp_path, free_port())
    try:
        launch.wait_line(lambda line: line.startswith("launching"))
        os.kill(_child_pid(launch), signal.SIGKILL)
        launch.wait_line(lambda line: "died by signal SIGKILL (9)" in line)
        launch.proc.send_signal(signal.SIGINT)
        code = launch.finish()
    finally:
        launch.close()
    assert code == 1, launch.lines
    assert "error: hub died by signal SIGKILL (9)" in launch.lines, launch.lines


@pytest.mark.integration
def test_a_ctrl_c_after_a_restarted_death_exits_0(tmp_path: Path) -> None:
    """A service killed and restarted, up again at the stop: said when it died, and the
    stop of a running pipeline is a success (exit 0, no error line)."""
    launch = Launch([str(_router_deploy(tmp_path))], tmp_path, free_port())
    try:
        launch.wait_line(lambda line: line.startswith("launching"))
        first = _child_pid(launch)
        os.kill(first, signal.SIGKILL)
        launch.wait_line(lambda line: "died by signal SIGKILL (9); restarting" in line)
        launch.wait_line(lambda line: "restarting (restart 1)" in line)
        wait_until(lambda: _child_pid(launch) != first, STARTUP_S, "the restarted process")
        launch.proc.send_signal(signal.SIGINT)
        code = launch.finish()
    finally:
        launch.close()
    assert code == 0, launch.lines
    assert not any(line.startswith("error:") for line in launch.lines), launch.lines


@pytest.mark.integration
def test_status_prints_one_short_line_per_service(tmp_path: Path) -> None:
    launch = Launch([str(_router_deploy(tmp_path)), "--status", "0.5"], tmp_path, free_port())
    try:
        line = launch.wait_line(lambda li: li.startswith("[status] hub"))
        assert f"pid {_child_pid(launch)}" in line and "restarts 0" in line, line
        assert len(line) <= 100, line
        launch.proc.send_signal(signal.SIGINT)
        assert launch.finish() == 0, launch.lines
    finally:
        launch.close()


def test_supervisor_reports_a_process_its_own_exit_left_down_at_the_stop() -> None:
    supervisor = Supervisor(
        [
            ProcessSpec("fails", (sys.executable, "-c", "raise SystemExit(3)"), restart=False),
            ProcessSpec("done", (sys.executable, "-c", "pass"), restart=False),
            ProcessSpec("runs", (sys.executable, "-c", "import time; time.sleep(600)")),
        ],
        colour=False,
        out=lambda line: None,
    )
    supervisor.start()
    try:
        wait_until(
            lambda: (supervisor.poll(), supervisor.uptimes()["fails"] is None)[1],
            30,
            "the failed exit noticed",
        )
    finally:
        supervisor.stop()
    assert supervisor.failures(recovered=False) == [
        "fails exited with 3 and was not running at the stop"
    ]
    # A demo reports every death, a process's own exit included: its figures lack what the
    # process would have done.
    assert supervisor.failures() == ["fails exited with 3"]


@pytest.mark.integration
def test_launch_exits_1_when_a_service_that_failed_to_start_is_down_at_the_stop(
    tmp_path: Path,
) -> None:
    """A router whose port is taken exits 1 (not by a signal) and is not restarted: the
    launch must not end as a success, as docs/pipeline.md says."""
    with socket.socket() as holder:
        holder.bind(("127.0.0.1", 0))
        holder.listen()
        port = holder.getsockname()[1]
        deploy = tmp_path / "taken.yaml"
        deploy.write_text(
            "version: 1\nservices:\n  hub: {type: router, restart: false, "
            f"network: {{listen: [tcp/127.0.0.1:{port}]}}}}\n"
        )
        launch = Launch([str(deploy)], tmp_path, free_port())
        try:
            launch.wait_line(lambda line: "exited with 1; not restarting" in line)
            launch.proc.send_signal(signal.SIGINT)
            code = launch.finish()
        finally:
            launch.close()
    assert code == 1, launch.lines
    assert "error: hub exited with 1 and was not running at the stop" in launch.lines


@pytest.mark.integration
def test_status_says_nothing_once_the_stop_began() -> None:
    """A tick that falls in the stop (`--duration 20 --status 5`) printed each service
    without its buffers, as if they had gone: the end is said by the services' totals."""
    from services.cli.launch import _status_loop

    supervisor = Supervisor(
        [ProcessSpec("runs", (sys.executable, "-c", "import time; time.sleep(600)"))],
        colour=False,
        out=lambda line: None,
    )
    supervisor.start()
    supervisor.stop()
    lines: list[str] = []
    loop = threading.Thread(
        target=_status_loop,
        args=(
            supervisor,
            NetworkConfig(local_port=free_port()),
            0.01,
            threading.Event(),
            lines.append,
        ),
        daemon=True,
    )
    loop.start()
    loop.join(timeout=scaled(30))
    assert not loop.is_alive() and lines == [], lines


@pytest.mark.integration
def test_status_says_when_a_service_that_answered_stops_answering() -> None:
    """A service that answered an earlier tick and is silent now (stopped here; on a loaded
    machine the launcher's own session went deaf) got a line without buffers, as if it had
    none: it says `no answer this tick`, and its rates come back when it answers again."""
    from services.cli.launch import _status_loop

    port = free_port()
    argv = (sys.executable, "-m", "services.cli", "pub", "test/x", "--kind", "generic")
    supervisor = Supervisor(
        [ProcessSpec("test", (*argv, "--rate", "5"), env=(("FRAMEGATE_LOCAL_PORT", str(port)),))],
        colour=False,
        out=lambda line: None,
    )
    lines: queue.Queue[str] = queue.Queue()
    stop = threading.Event()
    loop = threading.Thread(
        target=_status_loop,
        args=(supervisor, NetworkConfig(local_port=port), 0.5, stop, lines.put),
        daemon=True,
    )

    def a_line(says: str) -> str | None:
        while True:
            try:
                line = lines.get(timeout=0.1)
            except queue.Empty:
                return None
            if says in line:
                return line

    supervisor.start()
    try:
        loop.start()
        wait_until(lambda: a_line(" x "), scaled(60), "a status line with test/x's rate")
        pid = supervisor.pids()["test"]
        assert pid is not None
        os.kill(pid, signal.SIGSTOP)
        try:
            wait_until(lambda: a_line("no answer this tick"), scaled(60), "'no answer'")
        finally:
            os.kill(pid, signal.SIGCONT)
        wait_until(lambda: a_line(" x "), scaled(60), "test/x's rate again")
    finally:
        stop.set()
        supervisor.stop()
        loop.join(timeout=scaled(30))
