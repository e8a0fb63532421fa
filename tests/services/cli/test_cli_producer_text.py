"""A producer's metadata text reaches a terminal only as one line of printable text: a newline
in a field (a forged ``error:`` line), an 8-bit escape sequence and a bidi override are
written as their escapes by ``echo`` and ``query`` (real processes, real Zenoh)."""

from __future__ import annotations

import subprocess
import sys

import pytest

from middleware import NetworkConfig, Node
from tests.conftest import REPO, child_env, run_framegate, wait_until
from tests.helpers.timing import scaled

pytestmark = pytest.mark.integration

# Valid metadata (the producer's checks pass it), its one field a hostile text.
EVIL = "fine\nerror: forged line\u009b2J\u202eevil"
META = (
    '<metadata xmlns="urn:framegate:1" kind="generic" timestamp_ns="{t}">'
    f"<note>{EVIL}</note></metadata>"
)


ECHO = ("echo", "evil/x")


def _assert_clean(out: str) -> None:
    assert "\u009b" not in out and "\u202e" not in out, repr(out)
    assert not any(line.startswith("error: forged") for line in out.splitlines()), repr(out)
    assert "fine\\nerror: forged" in out, repr(out)  # shown, as escapes


def test_echo_and_query_print_a_producers_text_as_one_printable_line(endpoint: str) -> None:
    with Node("evil", NetworkConfig(listen=(endpoint,))) as node:
        buffer = node.offer("x")
        echo = subprocess.Popen(
            [sys.executable, "-m", "services.cli", *ECHO, "--connect", endpoint, "--count", "1"],
            stdout=subprocess.PIPE,
            stderr=subprocess.PIPE,
            text=True,
            cwd=REPO,
            env=child_env(),
        )
        try:
            wait_until(lambda: buffer.info().subscriptions, 30, "echo's subscription")
            buffer.put(1, b"x", META.format(t=1), wait_s=scaled(10))
            out, err = echo.communicate(timeout=scaled(30))
        finally:
            echo.kill()
        assert echo.returncode == 0, err
        _assert_clean(out)
        assert "note: fine\\nerror: forged line\\x9b2J\\u202eevil" in out, repr(out)
        done = run_framegate("query", "evil/x", "--connect", endpoint)
    assert done.returncode == 0, done.stderr
    _assert_clean(done.stdout)
