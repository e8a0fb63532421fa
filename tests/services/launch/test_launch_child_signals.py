"""A SIGTERM or SIGINT that reaches a child of ``framegate launch`` at any instant of its
first second, before its Python has installed a handler included, ends it with exit 0.

A real ``framegate launch`` runs a gyro and a mediator, restarting each one that exits. The
test watches the launcher's children and signals every new one directly (not through the
launcher) at an instant of its first second, from the moment its pid exists (between fork
and exec, or in the interpreter's own start-up) to well into its imports and session; each
restart gives a fresh first second. The launcher reports each child's exit, which must be
``exited with 0``, never ``died by signal``. No time bound is asserted: deadlines are
generous and only wait for the restarts to happen.
"""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path

import psutil
import pytest

from tests.conftest import child_env, free_port, wait_until
from tests.helpers.timing import scaled
from tests.services.cli.test_cli_first_second import GYRO_AND_MEDIATOR

pytestmark = pytest.mark.integration

# Instants after the child's pid appears: at once (often before exec), in the interpreter's
# start-up, in the imports (NumPy, Zenoh), the session's opening and the first work.
INSTANTS_S = (0.0, 0.0, 0.005, 0.02, 0.05, 0.1, 0.2, 0.35, 0.5, 0.8)
SIGNALS = (signal.SIGTERM, signal.SIGINT)
# Generous: the launcher backs off 0.2 s, doubling up to 10 s, between restarts.
RUN_S = 240.0


def _read(proc: subprocess.Popen[str], out: list[str]) -> None:
    assert proc.stdout is not None
    for line in proc.stdout:
        out.append(line.rstrip())


def _children(parent: int, others: set[int]) -> list[int]:
    """The pids of ``parent``'s children: one listing of ``/proc``, and the ``stat`` read of
    each pid not yet found to be another's (kept in ``others``). ``psutil``'s
    ``children()`` reads every process's ``stat`` on each call: ~15 s of CPU in this test's
    1 ms loop. A child's parent is set at its fork, so it shows from the moment its pid
    exists."""
    children = []
    for entry in os.scandir("/proc"):
        if not entry.name.isdigit() or int(entry.name) in others:
            continue
        pid = int(entry.name)
        try:
            stat = Path(f"/proc/{pid}/stat").read_text()
        except OSError:
            continue  # already gone
        if int(stat.rsplit(")", 1)[1].split()[1]) == parent:
            children.append(pid)
        else:
            others.add(pid)
    return children


def _exits(lines: list[str]) -> list[str]:
    """The launcher's reports of a child's end."""
    return [line for line in list(lines) if "exited with" in line or "died by signal" in line]


@pytest.mark.slow
def test_a_launched_child_signalled_in_its_first_second_exits_0(tmp_path: Path) -> None:
    (tmp_path / "deploy.yaml").write_text(GYRO_AND_MEDIATOR)
    env = child_env()
    env["FRAMEGATE_LOCAL_PORT"] = str(free_port())
    env["FRAMEGATE_RUNTIME_DIR"] = str(tmp_path / "run")
    launcher = subprocess.Popen(
        [sys.executable, "-m", "services.cli", "launch", "deploy.yaml", "--no-colour"],
        cwd=tmp_path,
        env=env,
        stdout=subprocess.PIPE,
        stderr=subprocess.STDOUT,
        text=True,
    )
    out: list[str] = []
    reader = threading.Thread(target=_read, args=(launcher, out), daemon=True)
    reader.start()
    seen: set[int] = set()
    others: set[int] = set()
    signalled: list[tuple[int, str, float]] = []
    deadline = time.monotonic() + scaled(RUN_S)
    try:
        while len(signalled) < 2 * len(INSTANTS_S) and time.monotonic() < deadline:
            assert launcher.poll() is None, f"the launcher ended: {launcher.returncode}"
            fresh = [pid for pid in _children(launcher.pid, others) if pid not in seen]
            if not fresh:
                time.sleep(0.001)  # poll fast: the earliest instant is the point
                continue
            pid = fresh[0]
            seen.add(pid)
            index = len(signalled)
            delay_s = INSTANTS_S[index % len(INSTANTS_S)]
            signum = SIGNALS[index % len(SIGNALS)]
            if delay_s:
                time.sleep(delay_s)  # an instant to signal at, not a wait for a condition
            try:
                psutil.Process(pid).send_signal(signum)
            except psutil.NoSuchProcess:
                continue
            signalled.append((pid, signal.Signals(signum).name, delay_s))
        assert len(signalled) == 2 * len(INSTANTS_S), f"too few restarts: {signalled}"
        # Let the last ones end and be reported before stopping the launcher.
        wait_until(lambda: len(_exits(out)) >= len(signalled), RUN_S, "every signalled child's end")
        launcher.send_signal(signal.SIGINT)
        code = launcher.wait(timeout=scaled(60.0))
    finally:
        if launcher.poll() is None:
            launcher.kill()
            launcher.wait()
    reader.join(timeout=scaled(30.0))
    text = "\n".join(out)
    exits = _exits(out)
    assert [line for line in exits if "exited with 0;" not in line] == [], (
        f"signalled {signalled}:\n{text}"
    )
    # Every signalled child's exit was reported (a restart line per exit).
    assert len(exits) >= len(signalled), f"signalled {signalled}:\n{text}"
    assert code == 0, text
