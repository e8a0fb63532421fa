"""``record --all`` (every buffer, also those that appear later) and ``info FILE.mcap``."""

from __future__ import annotations

import json
import time
from pathlib import Path

import pytest

from middleware import NetworkConfig, Node, make_metadata
from tests.conftest import wait_until
from tests.helpers.timing import scaled
from tests.services.cli.conftest import Cli

pytestmark = pytest.mark.integration


def _put(producer, t: int) -> None:  # type: ignore[no-untyped-def]
    producer.put(t, b"x%d" % t, make_metadata("generic", t))


def test_record_all_takes_every_buffer_including_a_late_one_and_info_describes_the_file(
    listen_net: NetworkConfig, cli: Cli, tmp_path: Path
) -> None:
    bag = tmp_path / "all.mcap"
    with Node("cam", listen_net) as service:
        first = service.offer("a")
        # --count, not a short --duration: on a busy machine the puts below may come later
        # than any duration chosen here; the duration only bounds a broken run.
        argv = ("--all", "-o", str(bag), "--count", "5", "--duration", "300", "--json")
        recorder = cli.start("record", *argv)
        assert first.wait_for_subscribers(1, timeout_s=scaled(30))
        late = service.offer("b")  # appears after the recording started
        assert late.wait_for_subscribers(1, timeout_s=scaled(30)), "--all never picked up cam/b"
        base = time.time_ns()
        for i in range(5):
            _put(first, base + i)
            _put(late, base + i)
        wait_until(lambda: first.info().puts == 5, 30, "puts")
        out, err = recorder.communicate(timeout=scaled(60))
        assert recorder.returncode == 0, err
    summary = json.loads(out)
    recorded = {b["name"]: b["recorded"] for b in summary["buffers"]}
    assert recorded == {"cam/a": 5, "cam/b": 5}

    info = cli.run("info", str(bag), "--json")
    assert info.returncode == 0, info.describe()
    described = info.json()
    assert described["status"] == "complete"
    counts = {c["topic"]: c["messages"] for c in described["channels"]}
    kinds = {c["topic"]: c["kind"] for c in described["channels"]}
    assert kinds["/cam/a"] == "generic"
    assert [counts[t] for t in sorted(counts) if t.endswith(("cam/a", "cam/b"))] == [5, 5]
    text = cli.run("info", str(bag))
    assert "complete: " in text.stdout and "cam/a" in text.stdout


def test_info_of_a_file_that_is_no_recording_is_one_line(cli: Cli, tmp_path: Path) -> None:
    junk = tmp_path / "junk.mcap"
    junk.write_bytes(b"not an mcap file at all")
    result = cli.run("info", str(junk))
    assert result.returncode == 1
    assert result.stderr.strip().startswith("error: ") and "not an MCAP file" in result.stderr
    assert len(result.stderr.strip().splitlines()) == 1


def test_record_needs_buffers_or_all(cli: Cli, tmp_path: Path) -> None:
    result = cli.run("record", "-o", str(tmp_path / "x.mcap"))
    assert result.returncode == 1
    assert "--all" in result.stderr


def test_record_all_leaves_out_a_service_that_only_answers_info(
    listen_net: NetworkConfig, endpoint: str, cli: Cli, tmp_path: Path
) -> None:
    """A peer answering ``@info`` for a service that holds no liveliness token (any peer
    can): ``record --all`` tried to record its buffer and failed the whole recording, after
    a clock question and a data query per made-up service (20 of them: 126 s)."""
    import zenoh

    bag = tmp_path / "all.mcap"
    with Node("cam", listen_net) as service:
        real = service.offer("a")
        conf = zenoh.Config()
        for key, value in {
            "mode": "peer",
            "connect/endpoints": [endpoint],
            "scouting/multicast/enabled": False,
        }.items():
            conf.insert_json5(key, json.dumps(value))
        with zenoh.open(conf) as peer:
            replies = list(peer.get("framegate/@info/cam", timeout=scaled(10)))
            described = next(r.ok for r in replies if r.ok is not None).payload.to_bytes()
            ghost = described.replace(b'"cam"', b'"ghost"')
            queryable = peer.declare_queryable(
                "framegate/@info/ghost",
                lambda query: query.reply("framegate/@info/ghost", ghost),
            )
            argv = ("--all", "-o", str(bag), "--count", "3", "--duration", "300", "--json")
            recorder = cli.start("record", *argv)
            assert real.wait_for_subscribers(1, timeout_s=scaled(60)), recorder
            base = time.time_ns()
            for i in range(3):
                _put(real, base + i)
            out, err = recorder.communicate(timeout=scaled(60))
            queryable.undeclare()
    assert recorder.returncode == 0, err
    recorded = {b["name"]: b["recorded"] for b in json.loads(out)["buffers"]}
    assert recorded == {"cam/a": 3}, err
