"""One Ctrl-C or SIGTERM ends a camera with exit 0, even while it renders a frame.

The simulated camera renders on a worker thread inside OpenCV; a stop that left that thread
running while the interpreter finalised aborted the process (exit 134, "terminate called
without an active exception"). Each process is signalled the moment it starts rendering
frames (once it has stored one: a camera that cannot keep its rate renders all the time).
"""

from __future__ import annotations

import signal
import subprocess
import threading
import time
from pathlib import Path

import pytest

from middleware import FramegateError, NetworkConfig, Node
from tests.conftest import free_port, start_framegate, wait_until
from tests.helpers.timing import scaled

# Stops that must reach a camera while it renders.
pytestmark = [pytest.mark.integration, pytest.mark.usefixtures("live_render")]


def _stored(node: Node, target: str) -> bool:
    try:
        info = node.buffer_info(target, timeout_s=scaled(2.0))
    except FramegateError:
        return False
    return info.puts > 0


class _Watched:
    """A process whose merged output is collected by a thread."""

    def __init__(self, proc: subprocess.Popen[str]) -> None:
        self.proc = proc
        self.lines: list[str] = []
        self.pump = threading.Thread(target=self._pump, daemon=True)
        self.pump.start()

    def _pump(self) -> None:
        assert self.proc.stdout is not None
        for line in self.proc.stdout:
            self.lines.append(line.rstrip())

    def stop(self, signum: int) -> tuple[int, float]:
        """Signal once; the exit code and how long the process took to end."""
        sent = time.monotonic()
        self.proc.send_signal(signum)
        try:
            code = self.proc.wait(timeout=scaled(20))
        except subprocess.TimeoutExpired as exc:
            self.proc.kill()
            self.proc.wait()
            raise AssertionError(f"pid {self.proc.pid} still running 20 s after {signum}") from exc
        return code, time.monotonic() - sent


def _stop_batch(
    node: Node, start: list[_Watched], names: list[str], signum: int
) -> list[tuple[int, float, str]]:
    """Signal each camera once it stored a frame; exit codes, stop times, output."""
    results: list[tuple[int, float, str]] = [(0, 0.0, "")] * len(start)

    def one(i: int) -> None:
        watched = start[i]
        target = f"{names[i]}/images"
        wait_until(lambda: _stored(node, target) or watched.proc.poll() is not None, 90, target)
        code, took = watched.stop(signum)
        watched.pump.join(timeout=scaled(10))  # the last lines: read up to end of output
        results[i] = (code, took, "\n".join(watched.lines[-20:]))

    threads = [threading.Thread(target=one, args=(i,)) for i in range(len(start))]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    return results


def _check(results: list[tuple[int, float, str]], what: str) -> None:
    failed = [(code, took, out) for code, took, out in results if code != 0]
    assert not failed, f"{len(failed)}/{len(results)} {what} did not exit 0: {failed[0]}"
    for _code, _took, out in results:
        assert "terminate called" not in out, out
    # "~2 s" is the contract; the generous bound only catches a stop that hangs.
    slowest = max(took for _code, took, _out in results)
    assert slowest < scaled(20), f"slowest stop took {slowest:.1f} s"


@pytest.mark.slow
def test_twenty_signals_stop_rendering_cameras_with_exit_0() -> None:
    results: list[tuple[int, float, str]] = []
    port = free_port()
    # Five at a time: ten rendering cameras at once starved the suite's other processes
    # (run-queue waits past their sessions' lease) and proved nothing more.
    for signum in (signal.SIGINT, signal.SIGTERM) * 2:
        names = [f"cam{i}" for i in range(5)]
        argv = ["run", "camera", "--source", "sim", "--loop", "--name"]
        batch = [_Watched(start_framegate([*argv, name], local_port=port)) for name in names]
        try:
            with Node(network=NetworkConfig(local_port=port)) as node:
                results += _stop_batch(node, batch, names, signum)
        finally:
            for watched in batch:
                if watched.proc.poll() is None:
                    watched.proc.kill()
                    watched.proc.wait()
    _check(results, "camera stops")


@pytest.mark.parametrize(
    ("service", "signum"), [("camera", signal.SIGTERM), ("gyro", signal.SIGINT)]
)
def test_a_signal_during_the_first_render_of_a_prerendered_approach_exits_0(
    tmp_path: Path, service: str, signum: int
) -> None:
    """A prerendered source renders its approach before the service starts (minutes on 2
    cores): the stop reaches the render, which ends after the frames in progress, removes
    its partial directory, and the service exits 0 without having started."""
    cache = tmp_path / "approaches"
    argv = ["run", service, "--source", "prerendered", "--path", str(cache), "--seed", "4242"]
    watched = _Watched(start_framegate(argv, local_port=free_port()))
    try:
        wait_until(
            lambda: any(cache.glob("*.partial-*")) or watched.proc.poll() is not None,
            60,
            "the render's partial directory",
        )
        assert watched.proc.poll() is None, "\n".join(watched.lines)
        code, took = watched.stop(signum)
    finally:
        if watched.proc.poll() is None:
            watched.proc.kill()
            watched.proc.wait()
    watched.pump.join(timeout=scaled(10))
    out = "\n".join(watched.lines)
    assert code == 0, f"{service} exited {code} after {signum!r}\n{out}"
    assert "Traceback" not in out, out
    # A stop waits for at most the frames being rendered; the bound only catches a render
    # that ignored the stop (a whole approach takes minutes).
    assert took < scaled(20), f"{service} took {took:.1f} s to stop\n{out}"
    assert not list(cache.glob("*.partial-*")), "a stopped render left its partial directory"
    assert not [p for p in cache.iterdir() if p.is_dir()], "a stopped render was kept"
