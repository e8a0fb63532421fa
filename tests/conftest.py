"""Shared fixtures: free loopback ports, multicast off, and real node processes."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from collections import Counter
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import pytest
from hypothesis import HealthCheck, settings

from middleware import NetworkConfig
from services.launch import free_port as free_port  # one for tests and tools
from services.lib.sim import FrameCache
from tests.helpers.timing import SCALE_VARIABLE, TIMEOUT_SCALE, scaled
from tests.helpers.timing import wait_until as wait_until

# The suite's hypothesis profile: no per-example deadline and no "too slow" health check.
# Hypothesis's default deadline (200 ms an example) is a wall-clock bound that a loaded
# machine exceeds on I/O and large inputs (XML documents, wire messages, buffers); a test's
# own @settings still chooses its number of examples.
settings.register_profile("framegate", deadline=None, suppress_health_check=[HealthCheck.too_slow])
settings.load_profile("framegate")
# ``--hypothesis-profile long``: the protocol state machine (tests/middleware/
# test_protocol_model.py) runs 3,000 programs of up to 80 steps (over 100,000 steps) instead
# of CI's few thousand. Registered here so that the option works from any test path.
settings.register_profile(
    "long",
    parent=settings.get_profile("framegate"),
    max_examples=3_000,
    stateful_step_count=80,
)

REPO = Path(__file__).resolve().parent.parent


@pytest.hookimpl(trylast=True)
def pytest_configure(config: pytest.Config) -> None:
    """pytest-timeout's per-test limit (``timeout`` in pyproject) is a deadline too: scaled."""
    env_timeout = getattr(config, "_env_timeout", None)
    if env_timeout:
        config._env_timeout = scaled(env_timeout)  # type: ignore[attr-defined]


def pytest_collection_modifyitems(items: list[pytest.Item]) -> None:
    """Files with slow tests run first; a test's own ``@pytest.mark.timeout(S)`` is scaled
    as well (the closest marker wins)."""
    items[:] = slow_files_first(items)
    if TIMEOUT_SCALE == 1.0:
        return
    for item in items:
        marker = item.get_closest_marker("timeout")
        if marker is not None and marker.args:
            item.add_marker(pytest.mark.timeout(scaled(float(marker.args[0]))), append=False)


def slow_files_first(items: list[pytest.Item]) -> list[pytest.Item]:
    """The files with the most tests marked ``slow`` first, the rest in their own order.

    The workers (``-n 3 --dist loadfile --no-loadscope-reorder``) take whole files in this
    order as they come free. xdist's own order, most tests per file first, put the files of
    one long test (a quick bench or experiment run, minutes each) last, and the suite ended
    with one worker busy for minutes while the others idled. (The suite is CPU-bound on 2
    cores: this shortens its tail, measured 12:34-13:20 against 12:54-13:23 before.)"""

    def file_of(item: pytest.Item) -> str:
        return item.nodeid.split("::")[0]

    slow = Counter(file_of(item) for item in items if item.get_closest_marker("slow"))
    return sorted(items, key=lambda item: -slow[file_of(item)])  # stable


@pytest.fixture(scope="session", autouse=True)
def _bytecode_cache(tmp_path_factory: pytest.TempPathFactory) -> Iterator[None]:
    """The processes the suite starts read compiled modules from one cache of the run.

    Under ``PYTHONDONTWRITEBYTECODE`` (set on some machines, the development VM among them)
    every service a test started compiled each framegate module it imports from source
    again: ~0.15 s of the ~0.65 s of CPU its start took, in each of hundreds of processes.
    The cache lives beside the run's base directories (``PYTHONPYCACHEPREFIX``): the source
    tree gets no ``__pycache__``."""
    with pytest.MonkeyPatch.context() as patch:
        patch.setenv("PYTHONPYCACHEPREFIX", str(tmp_path_factory.getbasetemp().parent / "pycache"))
        patch.delenv("PYTHONDONTWRITEBYTECODE", raising=False)
        yield


@pytest.fixture(scope="session")
def _sim_cache(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """One frame cache for every worker of the run (their base directories' parent)."""
    return tmp_path_factory.getbasetemp().parent / "sim-cache"


@pytest.fixture
def live_render(monkeypatch: pytest.MonkeyPatch) -> None:
    """For a test whose simulated cameras must render (a stop that reaches a render): no
    frame comes from the suite's frame cache."""
    monkeypatch.delenv(FrameCache.ENV, raising=False)


@pytest.fixture(autouse=True)
def _no_framegate_environment(monkeypatch: pytest.MonkeyPatch, _sim_cache: Path) -> None:
    """A developer's shell (``FRAMEGATE_CONNECT``, ``FRAMEGATE_LOCAL_PORT``...) must not leak
    into a test or the processes it starts; a test that wants one sets it itself. The suite's
    own setting (the timeout scale) stays: helpers a test starts read it too.

    And the suite's simulated cameras share one frame cache (``FRAMEGATE_SIM_CACHE``): the
    same few hundred frames of the approach were rendered live by every pipeline test,
    each at ~50 ms of CPU. A test about rendering itself removes the variable."""
    for name in list(os.environ):
        if name.startswith("FRAMEGATE_") and name != SCALE_VARIABLE:
            monkeypatch.delenv(name)
    monkeypatch.setenv(FrameCache.ENV, str(_sim_cache))


@pytest.fixture
def endpoint() -> str:
    """A fresh loopback endpoint for this test (multicast scouting is off by default)."""
    return f"tcp/127.0.0.1:{free_port()}"


@pytest.fixture
def listen_net(endpoint: str) -> NetworkConfig:
    return NetworkConfig(listen=(endpoint,))


@pytest.fixture
def connect_net(endpoint: str) -> NetworkConfig:
    return NetworkConfig(connect=(endpoint,))


def child_env() -> dict[str, str]:
    env = dict(os.environ)
    env["PYTHONPATH"] = str(REPO) + os.pathsep + env.get("PYTHONPATH", "")
    env.setdefault("PYTHONUNBUFFERED", "1")
    return env


def run_framegate(
    *argv: str,
    cwd: Path = REPO,
    env: dict[str, str] | None = None,
    timeout_s: float = 60.0,
) -> subprocess.CompletedProcess[str]:
    """``framegate ARGV`` run to its end (stdout and stderr apart, as text); ``timeout_s``
    is scaled for a slow machine."""
    return run_python(["-m", "services.cli", *argv], cwd=cwd, env=env, timeout_s=timeout_s)


def run_python(
    argv: list[str],
    *,
    cwd: Path = REPO,
    env: dict[str, str] | None = None,
    timeout_s: float = 60.0,
) -> subprocess.CompletedProcess[str]:
    """``python ARGV`` run to its end (stdout and stderr apart, as text); ``timeout_s`` is
    scaled for a slow machine."""
    return subprocess.run(
        [sys.executable, *argv],
        capture_output=True,
        text=True,
        cwd=cwd,
        env=env or child_env(),
        timeout=scaled(timeout_s),
        check=False,
    )


def start_python(argv: list[str]) -> subprocess.Popen[str]:
    """``python ARGV`` in a child process run from the repository, stdout and stderr apart,
    as text (pipes: read them, or ``communicate``)."""
    return subprocess.Popen(
        [sys.executable, *argv],
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
        cwd=REPO,
        env=child_env(),
    )


def start_framegate(argv: list[str], *, local_port: int) -> subprocess.Popen[str]:
    """``framegate ARGV`` in a child process meeting others on the rendezvous ``local_port``;
    stdout and stderr together, as text."""
    env = child_env()
    env["FRAMEGATE_LOCAL_PORT"] = str(local_port)
    return subprocess.Popen(
        [sys.executable, "-m", "services.cli", *argv],
        cwd=REPO,
        env=env,
        stdout=subprocess.PIPE,
        stderr=subprocess.STDOUT,
        text=True,
    )


class NodeProcess:
    """A framegate node in a separate OS process, driven over stdin/stdout."""

    def __init__(self, name: str | None, net_args: list[str]) -> None:
        cmd = [sys.executable, "-m", "tests.helpers.node_driver"]
        if name:
            cmd.append(name)
        self.proc = subprocess.Popen(
            cmd + net_args,
            stdin=subprocess.PIPE,
            stdout=subprocess.PIPE,
            text=True,
            cwd=REPO,
            env=child_env(),
        )
        ready = self._read()
        assert ready.get("ready"), ready

    def _read(self) -> dict[str, Any]:
        assert self.proc.stdout is not None
        line = self.proc.stdout.readline()
        if not line:
            raise AssertionError(f"node process exited with {self.proc.wait()}")
        result: dict[str, Any] = json.loads(line)
        return result

    def call(self, op: str, **kwargs: Any) -> dict[str, Any]:
        assert self.proc.stdin is not None
        self.proc.stdin.write(json.dumps({"op": op, **kwargs}) + "\n")
        self.proc.stdin.flush()
        return self._read()

    def kill(self) -> None:
        self.proc.kill()
        self.proc.wait()

    def close(self) -> None:
        if self.proc.poll() is None:
            try:
                self.call("exit")
                self.proc.wait(timeout=scaled(5))
            except (OSError, AssertionError, subprocess.TimeoutExpired, ValueError):
                self.proc.kill()
                self.proc.wait()


@pytest.fixture
def node_process() -> Iterator[Callable[..., NodeProcess]]:
    """Factory: ``node_process(name, "--connect", ep)``; every process is stopped after."""
    started: list[NodeProcess] = []

    def start(name: str | None, *net_args: str) -> NodeProcess:
        proc = NodeProcess(name, list(net_args))
        started.append(proc)
        return proc

    yield start
    for proc in started:
        proc.close()
