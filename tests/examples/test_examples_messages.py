"""The examples at human speed, and their mistakes as one line, never a traceback."""

from __future__ import annotations

import queue
import signal
import subprocess
import sys
import threading

import pytest

from tests.conftest import REPO, child_env, free_port
from tests.helpers.timing import scaled

pytestmark = pytest.mark.integration


def _start(script: str, *args: str) -> subprocess.Popen[str]:
    return subprocess.Popen(
        [sys.executable, str(REPO / "examples" / script), *args],
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
        env=child_env(),
    )


def _lines(proc: subprocess.Popen[str]) -> queue.Queue[str]:
    lines: queue.Queue[str] = queue.Queue()

    def pump() -> None:
        assert proc.stdout is not None
        for line in proc.stdout:
            lines.put(line)

    threading.Thread(target=pump, daemon=True).start()
    return lines


def test_offer_runs_until_ctrl_c_and_then_exits_0() -> None:
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    offer = _start("offer.py", "--listen", endpoint, "--period-s", "0.05")
    try:
        lines = _lines(offer)
        # Well past the old fixed count of 10: it keeps going until told to stop.
        puts = [lines.get(timeout=scaled(60)) for _ in range(15)]
        assert all(p.startswith("put ") for p in puts), puts
        assert offer.poll() is None
        offer.send_signal(signal.SIGINT)
        assert offer.wait(timeout=scaled(30)) == 0
        assert offer.stderr is not None and "Traceback" not in offer.stderr.read()
    finally:
        if offer.poll() is None:
            offer.kill()
            offer.wait()


def _one_line_error(proc: subprocess.Popen[str]) -> str:
    _out, err = proc.communicate(timeout=scaled(60))
    assert proc.returncode == 1, err
    assert "Traceback" not in err and len(err.splitlines()) == 1, err
    assert err.startswith("error: "), err
    return err


def _error_without_the_example(script: str, *args: str) -> str:
    """The one-line error of ``script`` run against a router where no example service is."""
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    with subprocess.Popen(  # something to connect to, but no example service
        [sys.executable, "-m", "services.cli", "router", "--listen", endpoint],
        env=child_env(),
        cwd=REPO,
        stdout=subprocess.DEVNULL,
        stderr=subprocess.DEVNULL,
    ) as router:
        try:
            return _one_line_error(_start(script, "--connect", endpoint, *args))
        finally:
            router.send_signal(signal.SIGINT)
            router.wait(timeout=scaled(30))


def test_query_of_a_stopped_example_is_one_line() -> None:
    assert "example" in _error_without_the_example("query.py")


def test_query_with_a_bad_range_is_one_line() -> None:
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    offer = _start("offer.py", "--listen", endpoint, "--period-s", "0.05")
    try:
        lines = _lines(offer)
        lines.get(timeout=scaled(60))  # it is up and has put something
        _one_line_error(_start("query.py", "--connect", endpoint, "--range", "[now(-1x)..]"))
    finally:
        offer.kill()
        offer.wait()


@pytest.mark.parametrize(
    ("script", "args", "expected"),
    [
        ("offer.py", ("--period-s", "nan"), "argument --period-s: must be a number of seconds >= 0"),  # noqa: E501
        ("offer.py", ("--period-s", "-1"), "argument --period-s: must be a number of seconds >= 0"),
        ("offer.py", ("--wait-s", "inf"), "argument --wait-s: must be a number of seconds >= 0"),
        ("offer.py", ("--count", "-3"), "argument --count: must be an integer >= 0"),
        ("subscribe.py", ("--delay-s", "nan"), "argument --delay-s: must be a number of seconds >= 0"),  # noqa: E501
        ("subscribe.py", ("--count", "-1"), "argument --count: must be an integer >= 1"),
        ("subscribe.py", ("--queue", "0"), "argument --queue: must be an integer >= 1"),
    ],
)  # fmt: skip
def test_flag_values_that_would_crash_or_do_nothing_are_refused_as_parsed(
    script: str, args: tuple[str, ...], expected: str
) -> None:
    proc = _start(script, "--connect", f"tcp/127.0.0.1:{free_port()}", *args)
    _out, err = proc.communicate(timeout=scaled(60))
    assert proc.returncode == 2, err  # argparse's own usage error
    assert "Traceback" not in err and expected in err, err


def test_subscribe_to_an_example_that_is_not_running_says_so() -> None:
    err = _error_without_the_example("subscribe.py", "--count", "1")
    assert "service 'example' is not live" in err and "offer.py" in err, err


def test_subscribe_and_query_show_a_binary_payload_by_its_size() -> None:
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    sub = _start("subscribe.py", "t/img", "--connect", endpoint, "--count", "2")
    pub = subprocess.Popen(  # 64x48 mono8 test frames: no text to print
        [sys.executable, "-m", "services.cli", "pub", "t/img", "--kind", "frame", "--count", "3",
         "--rate", "5", "--wait-subscribers", "1", "--timeout", "60", "--linger", "30",
         "--listen", endpoint],
        env=child_env(), cwd=REPO, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True,
    )  # fmt: skip
    try:
        out, err = sub.communicate(timeout=scaled(90))
        assert sub.returncode == 0 and "Traceback" not in err, err
        assert out.count(": 3072 bytes") == 2, out
        query = _start("query.py", "t/img", "--connect", endpoint, "--range", "[now(-60s)..]")
        out, err = query.communicate(timeout=scaled(60))
        assert query.returncode == 0 and "Traceback" not in err, err
        assert out.count(": 3072 bytes") >= 2 and "\\x" not in out, out
    finally:
        pub.kill()
        pub.wait()


@pytest.mark.parametrize("script", sorted(p.name for p in (REPO / "examples").glob("*.py")))
def test_an_examples_help_shows_no_markup(script: str) -> None:
    # The description is the docstring's first line: `--help` printed its reST literals
    # (``python examples/offer.py``), as `framegate run camera --help` once did.
    proc = _start(script, "--help")
    out, err = proc.communicate(timeout=scaled(60))
    assert proc.returncode == 0, err
    assert "``" not in out, out
