"""``framegate bench``: the quick run as a subprocess, and argument errors.

The quick run asserts only that every scenario produced numbers and that the JSON has the
documented keys (``quick_run``) — never a speed: this machine is shared and its speed is not
ours to test.
"""

from __future__ import annotations

import signal
import subprocess
from pathlib import Path

import psutil
import pytest

from services.cli import main
from tests.conftest import REPO, child_env, wait_until
from tests.helpers.timing import scaled
from tests.services.evidence.bench.quick_run import TRANSPORT, bench_command, quick_run


@pytest.mark.integration
@pytest.mark.slow
@pytest.mark.timeout(960)
def test_quick_run_gives_numbers_for_the_transport_scenarios(tmp_path: Path) -> None:
    quick_run(tmp_path, list(TRANSPORT))


def test_unknown_scenario_is_an_error_naming_it(capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["bench", "framez"]) == 1
    assert "unknown scenario(s) framez" in capsys.readouterr().err


def test_too_few_pairs_without_quick_is_refused(capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["bench", "--pairs", "1", "small"]) == 1
    assert "use --pairs 3 or more, or --quick" in capsys.readouterr().err


def test_json_into_a_missing_directory_is_refused(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    assert main(["bench", "--quick", "--json", str(tmp_path / "no" / "b.json"), "small"]) == 1
    assert "directory" in capsys.readouterr().err


@pytest.mark.integration
@pytest.mark.parametrize("signum", [signal.SIGINT, signal.SIGTERM])
def test_one_signal_stops_the_bench_and_its_workers_with_exit_0(signum: int) -> None:
    proc = subprocess.Popen(
        [*bench_command(), "--quick", "idle"],
        cwd=REPO,
        env=child_env(),
        stdout=subprocess.DEVNULL,
        stderr=subprocess.DEVNULL,
    )
    try:
        me = psutil.Process(proc.pid)
        workers = wait_until(
            lambda: (
                [c for c in me.children(recursive=True) if "_worker" in " ".join(c.cmdline())]
                if len(me.children(recursive=True)) >= 4
                else None
            ),
            60.0,
            "the bench's idle workers to start",
        )
        proc.send_signal(signum)
        assert proc.wait(timeout=scaled(15.0)) == 0
        _gone, alive = psutil.wait_procs(workers, timeout=scaled(10.0))
        assert not alive, alive
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()
