"""A SIGINT or SIGTERM at any instant of a command's first second ends it with exit 0, no
traceback, and no process of its own left behind.

Each command is started as a real process; the test polls ``/proc/PID/status`` until the
process exists as a framegate process (it catches SIGTERM: framegate's first work, before
any command module is imported), then signals it at once or at an instant of its first
second, so the signal lands in the imports, the parsing, the opening of the Zenoh session
or the command's first work. (Before the interpreter runs framegate's first line, a signal
has the operating system's default effect: no program can catch it; on an idle machine
that is the first ~30 ms.) No time bound is asserted: only the exit code, the output and
that nothing of the process is still running at a generous deadline.
"""

from __future__ import annotations

import contextlib
import signal
import subprocess
import sys
import time
from pathlib import Path

import psutil
import pytest

from tests.conftest import child_env, free_port, wait_until

pytestmark = pytest.mark.integration

# When to signal, after the process exists: at once, and at instants while a command's
# modules (NumPy, Zenoh, OpenCV) are imported, its session opens, its children start.
INSTANTS = (0.0, 0.05, 0.2, 0.6)
# Generous: a loaded machine may need this long to finish a stop and reap a launch's children.
ENDS_WITHIN_S = 60.0


def _catches(pid: int, signum: int) -> bool:
    """Whether ``pid`` has a handler for ``signum``: SIGINT once the Python interpreter is
    up, SIGTERM once framegate installed its own (Python installs none for it)."""
    with contextlib.suppress(OSError):
        for line in Path(f"/proc/{pid}/status").read_text().splitlines():
            if line.startswith("SigCgt:"):
                return bool(int(line.split()[1], 16) & (1 << (signum - 1)))
    return False


def _descendants_of(pid: int) -> list[psutil.Process]:
    """Processes a launcher started (they carry its pid in their environment), alive now."""
    out = []
    for proc in psutil.process_iter():
        with contextlib.suppress(psutil.Error):
            mine = proc.environ().get("FRAMEGATE_PARENT_PID") == str(pid)
            if mine and proc.is_running() and proc.status() != psutil.STATUS_ZOMBIE:
                out.append(proc)
    return out


def _signal_early(argv: list[str], signum: int, delay_s: float, tmp_path: Path) -> None:
    env = child_env()
    env["FRAMEGATE_LOCAL_PORT"] = str(free_port())
    env["FRAMEGATE_RUNTIME_DIR"] = str(tmp_path / "run")
    proc = subprocess.Popen(
        [sys.executable, "-m", "services.cli", *argv],
        cwd=tmp_path,
        env=env,
        stdout=subprocess.PIPE,
        stderr=subprocess.STDOUT,
        text=True,
    )
    try:
        # Poll for the process to exist as a framegate process, then signal at once.
        wait_until(
            lambda: _catches(proc.pid, signal.SIGTERM) or proc.poll() is not None,
            ENDS_WITHIN_S,
            "the process to exist",
        )
        if delay_s:
            time.sleep(delay_s)  # an instant to signal at, not a wait for a condition
        children = _descendants_of(proc.pid)
        proc.send_signal(signum)
        out, _ = proc.communicate(timeout=ENDS_WITHIN_S)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.communicate()
    what = f"{argv} signalled {signal.Signals(signum).name} {delay_s} s in"
    assert "Traceback" not in out, f"{what}:\n{out}"
    assert proc.returncode == 0, f"{what}: exit {proc.returncode}\n{out}"
    # Nothing left behind: every child the launcher had started ends with it.
    left = children + _descendants_of(proc.pid)
    wait_until(
        lambda: not [c for c in left if c.is_running() and c.status() != psutil.STATUS_ZOMBIE],
        ENDS_WITHIN_S,
        f"the children of {what} to end",
    )


# A launch with two quick services (no camera to render); test_launch_child_signals too.
GYRO_AND_MEDIATOR = """\
version: 1
services:
  gyro:
    args: {source: sim, seed: 1, loop: true}
  mediator:
    args: {policy: paper, b0: 5.0}
"""


@pytest.mark.parametrize("delay_s", INSTANTS)
@pytest.mark.parametrize("signum", [signal.SIGINT, signal.SIGTERM], ids=["INT", "TERM"])
@pytest.mark.parametrize(
    "argv",
    [
        ["run", "gyro", "--source", "sim", "--loop"],
        ["launch", "deploy.yaml", "--no-colour"],
    ],
    ids=["run-gyro", "launch"],
)
def test_a_signal_in_the_first_second_exits_0_and_leaves_nothing(
    argv: list[str], signum: int, delay_s: float, tmp_path: Path
) -> None:
    (tmp_path / "deploy.yaml").write_text(GYRO_AND_MEDIATOR)
    _signal_early(argv, signum, delay_s, tmp_path)


COMMANDS = [
    ["run", "camera", "--source", "sim", "--loop"],
    ["ls"],
    ["hz", "cam/log"],
    ["echo", "cam/log"],
    ["query", "cam/log"],
    ["record", "cam/log", "-o", "out.mcap"],
    ["view", "cam/log", "--port", "0"],
    ["router", "--listen", "tcp/127.0.0.1:0"],
    ["watch", "cam/log"],
    ["pub", "tmp/x", "--kind", "generic", "--count", "100"],
    ["demo", "--duration", "60"],
]


@pytest.mark.parametrize("signum", [signal.SIGINT, signal.SIGTERM], ids=["INT", "TERM"])
@pytest.mark.parametrize("argv", COMMANDS, ids=["-".join(a[:2]) for a in COMMANDS])
def test_every_command_exits_0_on_a_signal_at_its_first_instant(
    argv: list[str], signum: int, tmp_path: Path
) -> None:
    for delay_s in INSTANTS[:2]:
        _signal_early(argv, signum, delay_s, tmp_path)
