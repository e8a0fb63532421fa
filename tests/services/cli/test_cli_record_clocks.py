"""``record`` whose clock is not its producers': behind them, and stepped while it records.

The recorder is a real process whose wall clock is shifted by the LD_PRELOAD shim
(``tests/helpers/clock_shim.py``); the producer is this test's node, on the real clock.
"""

from __future__ import annotations

import json
import signal
import subprocess
import sys
import time
from pathlib import Path
from typing import Any

import pytest
import zenoh

from middleware import NetworkConfig, Node, Producer, make_metadata
from tests.conftest import REPO, child_env
from tests.helpers.clock_shim import build_clock_shim, shifted_clock_env, step_clock
from tests.helpers.raw_zenoh import open_session
from tests.helpers.timing import scaled
from tests.services.cli.conftest import DISCOVERY_TIMEOUT_S, TIMEOUT_S

pytestmark = pytest.mark.integration

S = 1_000_000_000


def _record(endpoint: str, env: dict[str, str], *args: str) -> subprocess.Popen[str]:
    argv = ["record", *args, "--json", "--connect", endpoint]
    return subprocess.Popen(
        [sys.executable, "-m", "services.cli", *argv, "--timeout", str(DISCOVERY_TIMEOUT_S)],
        cwd=REPO,
        env=env,
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
    )


def _put_now(producer: Producer, count: int) -> None:
    for _ in range(count):
        t = time.time_ns()
        producer.put(t, b"x", make_metadata("generic", t))


def _record_five(endpoint: str, env: dict[str, str], producer: Producer, bag: Path) -> Any:
    """``record cam/a --count 5`` into ``bag`` while ``producer`` puts 5 elements stamped now,
    once it has subscribed; its JSON summary."""
    recorder = _record(
        endpoint, env, "cam/a", "-o", str(bag), "--count", "5", "--duration", str(scaled(30))
    )
    try:
        assert producer.wait_for_subscribers(1, timeout_s=scaled(60)), "record never subscribed"
        _put_now(producer, 5)
        out, err = recorder.communicate(timeout=scaled(TIMEOUT_S))
    finally:
        if recorder.poll() is None:
            recorder.kill()
            recorder.wait()
    assert recorder.returncode == 0, err
    return json.loads(out)


def test_record_behind_its_producers_clock_records_what_they_stamp(
    listen_net: NetworkConfig, endpoint: str, tmp_path: Path
) -> None:
    """A recorder whose host is 60 s behind the producer's (not yet synchronised): its
    ``--duration`` ended, in the producer's stamps, 60 s before the recording began, so
    every element was past the stop and the file held none, with no word."""
    offset = tmp_path / "offset"
    step_clock(offset, -60 * S)
    env = shifted_clock_env(child_env(), build_clock_shim(tmp_path), offset)
    with Node("cam", listen_net) as node:
        producer = node.offer("a")
        summary = _record_five(endpoint, env, producer, tmp_path / "behind.mcap")
    assert [b["recorded"] for b in summary["buffers"]] == [5], summary


def test_record_whose_clock_steps_back_keeps_a_positive_duration_and_its_elements(
    listen_net: NetworkConfig, endpoint: str, tmp_path: Path
) -> None:
    """NTP steps the recorder's clock back 60 s while it records, then Ctrl-C: the stop
    instant was read from the system clock, 60 s before the elements just stored (those not
    yet fetched were past the stop: dropped) and the summary said "in -55.0 s"."""
    offset = tmp_path / "offset"
    step_clock(offset, 0)
    env = shifted_clock_env(child_env(), build_clock_shim(tmp_path), offset)
    with Node("cam", listen_net) as node:
        producer = node.offer("a")
        bag = tmp_path / "stepped.mcap"
        recorder = _record(endpoint, env, "cam/a", "-o", str(bag))
        try:
            assert producer.wait_for_subscribers(1, timeout_s=scaled(60)), "record never subscribed"
            _put_now(producer, 3)
            step_clock(offset, -60 * S)
            _put_now(producer, 3)
            # The shim re-reads its offset file at most 10 ms after it changed: a fixed
            # period of the shim's, not a condition the recorder could report.
            time.sleep(0.05)
            recorder.send_signal(signal.SIGINT)
            out, err = recorder.communicate(timeout=scaled(TIMEOUT_S))
        finally:
            if recorder.poll() is None:
                recorder.kill()
                recorder.wait()
    assert recorder.returncode == 0, err
    summary = json.loads(out)
    assert [b["recorded"] for b in summary["buffers"]] == [6], summary
    assert summary["duration_s"] >= 0, summary


def test_record_does_not_take_a_peers_word_for_its_producers_clock(
    listen_net: NetworkConfig, endpoint: str, tmp_path: Path
) -> None:
    """A peer answers ``@info`` in the producer's name with its real description but a clock
    an hour behind: two sessions answer, so the recording's stop is not moved an hour early
    (it would have recorded nothing)."""
    with Node("cam", listen_net) as node, open_session(endpoint) as rogue:
        producer = node.offer("a")
        copy = json.loads(
            next(r.ok.payload.to_bytes() for r in rogue.get("framegate/@info/cam") if r.ok)
        )

        def answer(query: zenoh.Query) -> None:
            with query:
                forged = dict(copy, clock_ns=time.time_ns() - 3600 * S)
                query.reply(query.key_expr, json.dumps(forged).encode())

        queryable = rogue.declare_queryable("framegate/@info/cam", zenoh.handlers.Callback(answer))
        try:
            summary = _record_five(endpoint, child_env(), producer, tmp_path / "peer.mcap")
        finally:
            queryable.undeclare()
    assert [b["recorded"] for b in summary["buffers"]] == [5], summary
