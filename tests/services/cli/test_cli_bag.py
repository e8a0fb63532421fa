"""record → MCAP → play as real subprocesses on loopback."""

from __future__ import annotations

import base64
import json
import signal
import time
from pathlib import Path

import msgpack
import pytest
from mcap.reader import make_reader

from middleware import DataObject, NetworkConfig, Node, Retention, make_metadata
from services.tools.bag import BagWriter
from tests.conftest import free_port, wait_until
from tests.services.cli.conftest import (
    HEIGHT,
    MS,
    TIMEOUT_S,
    WIDTH,
    Cli,
    LineReader,
    frame_metadata,
    frame_payload,
    put_frame,
)

pytestmark = pytest.mark.integration

COUNT = 30


def test_record_then_play_gives_back_identical_buffers(
    listen_net: NetworkConfig, cli: Cli, tmp_path: Path
) -> None:
    bag = tmp_path / "run.mcap"
    retention = Retention(max_count=500)
    with Node("cam", listen_net) as service:
        # Never inline: the recorder must query every element, so a burst makes it miss.
        images = service.offer("images", kind="frame", retention=retention, inline_max_bytes=0)
        log = service.offer("log")
        recorder = cli.start(
            "record", "cam/images", "cam/log", "-o", str(bag), "--count", str(COUNT),
            "--queue", "1", "--json",
        )  # fmt: skip
        assert images.wait_for_subscribers(1, 30) and log.wait_for_subscribers(1, 30)
        base = time.time_ns()
        for i in range(COUNT):  # a burst, as fast as the producer can go
            t = base + i * MS
            put_frame(images, t, i)
            log.put(t, b"line %d" % i, make_metadata("generic", t, {"n": i}))
        out, err = recorder.communicate(timeout=TIMEOUT_S)
        assert recorder.returncode == 0, err
        originals = {
            "images": _elements(service, images.name),
            "log": _elements(service, log.name),
        }
    summary = json.loads(out)
    by_name = {b["name"]: b for b in summary["buffers"]}
    for name in ("cam/images", "cam/log"):
        assert by_name[name]["recorded"] == COUNT and by_name[name]["lost"] == 0
    assert by_name["cam/images"]["kind"] == "frame"
    # It could not keep up with the burst, and fetched what it missed from the buffer.
    assert by_name["cam/images"]["missed"] > 0 and by_name["cam/images"]["backfilled"] > 0
    assert summary["messages"] == 3 * COUNT

    _check_mcap(bag, base)

    # The original service is gone; play offers the same names again.
    play_endpoint = f"tcp/127.0.0.1:{free_port()}"
    player = cli.start("play", str(bag), "--fast", "--json", "--listen", play_endpoint)
    events = LineReader(player)
    offered = events.json_until(lambda e: e["event"] == "offered", TIMEOUT_S)
    assert {(b["name"], b["kind"], b["elements"]) for b in offered["buffers"]} == {
        ("cam/images", "frame", COUNT),
        ("cam/log", "generic", COUNT),
    }
    done = events.json_until(lambda e: e["event"] == "done", TIMEOUT_S)
    assert done["played"] == 2 * COUNT and done["serving"]
    with Node(network=NetworkConfig(connect=(play_endpoint,))) as client:
        wait_until(lambda: "cam" in client.live_services(), 10, "the played service")
        for buffer, expected in originals.items():
            replayed = client.query(f"cam/{buffer}", time_range=f"[{base}..]")
            assert [(e.timestamp_ns, e.payload, e.metadata) for e in replayed] == expected
        assert client.buffer_info("cam/images").retention == retention
    player.send_signal(signal.SIGTERM)  # Ctrl-C equivalent: closes cleanly
    assert player.wait(timeout=20) == 0


def _elements(node: Node, target: str) -> list[tuple[int, bytes, bytes]]:
    return [(e.timestamp_ns, e.payload, e.metadata) for e in node.query(target)]


def _check_mcap(path: Path, base: int) -> None:
    """What Foxglove and any MCAP reader see."""
    with path.open("rb") as stream:
        reader = make_reader(stream)
        summary = reader.get_summary()
        assert summary is not None and summary.statistics is not None
        channels = {c.topic: c for c in summary.channels.values()}
        assert set(channels) == {"/cam/images", "/cam/images/image", "/cam/log"}
        schemas = {t: summary.schemas[c.schema_id] for t, c in channels.items()}
        assert schemas["/cam/images"].name == "framegate.Element"
        assert channels["/cam/images"].message_encoding == "msgpack"
        assert channels["/cam/images"].metadata["framegate.kind"] == "frame"
        assert channels["/cam/log"].metadata["framegate.kind"] == "generic"
        assert schemas["/cam/images/image"].name == "foxglove.RawImage"
        assert schemas["/cam/images/image"].encoding == "jsonschema"
        assert channels["/cam/images/image"].message_encoding == "json"
        assert summary.statistics.message_count == 3 * COUNT
        images = list(reader.iter_messages(topics=["/cam/images/image"]))
        elements = list(reader.iter_messages(topics=["/cam/images"]))
    assert [m.log_time for _s, _c, m in images] == [base + i * MS for i in range(COUNT)]
    raw = json.loads(images[3][2].data)
    assert raw["timestamp"] == {"sec": (base + 3 * MS) // 10**9, "nsec": (base + 3 * MS) % 10**9}
    assert (raw["width"], raw["height"], raw["encoding"], raw["step"]) == (
        WIDTH,
        HEIGHT,
        "mono8",
        WIDTH,
    )
    assert base64.b64decode(raw["data"]) == frame_payload(3)
    element = msgpack.unpackb(elements[3][2].data)
    assert element == {
        "t": base + 3 * MS,
        "p": frame_payload(3),
        "m": frame_metadata(base + 3 * MS, 3),
    }


def test_play_paces_and_rebases_onto_the_wall_clock(cli: Cli, tmp_path: Path) -> None:
    bag = tmp_path / "old.mcap"
    recorded = [10**9 + i * 100 * MS for i in range(5)]  # 1970, 100 ms apart
    with BagWriter(bag) as writer:
        writer.add_buffer("cam", "images", kind="frame", retention=Retention())
        for i, t in enumerate(recorded):
            writer.write("cam/images", DataObject(t, frame_payload(i), frame_metadata(t, i)))
    play_endpoint = f"tcp/127.0.0.1:{free_port()}"
    player = cli.start(
        "play", str(bag), "--rebase", "--rate", "2", "--json", "--listen", play_endpoint
    )
    events = LineReader(player)
    events.json_until(lambda e: e["event"] == "offered", TIMEOUT_S)
    started = time.time_ns()
    done = events.json_until(lambda e: e["event"] == "done", TIMEOUT_S)
    assert done["elapsed_s"] >= 0.2  # 400 ms recorded, at twice the speed
    with Node(network=NetworkConfig(connect=(play_endpoint,))) as client:
        wait_until(lambda: "cam" in client.live_services(), 10, "the played service")
        played = client.query("cam/images")
    shift = played[0].timestamp_ns - recorded[0]
    assert abs(played[0].timestamp_ns - started) < 30 * 10**9  # now, not 1970
    assert [e.timestamp_ns - shift for e in played] == recorded
    assert [e.payload for e in played] == [frame_payload(i) for i in range(5)]
    # Metadata moved along: the envelope and the exposure start, not the exposure time.
    assert played[2].metadata == frame_metadata(recorded[2] + shift, 2)
    player.send_signal(signal.SIGTERM)
    assert player.wait(timeout=20) == 0
