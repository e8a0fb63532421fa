"""record → MCAP → play as real subprocesses on loopback."""

from __future__ import annotations

import base64
import json
import signal
import time
from pathlib import Path
from typing import Any

import msgpack
import numpy as np
import pytest
from mcap.reader import make_reader

from middleware import DataObject, NetworkConfig, Node, Retention, make_metadata
from services.lib.messages import DecisionRecord, detections_metadata, gyro_metadata
from services.lib.quality import GyroSamples
from services.tools.bag import BagWriter, open_bag
from tests.conftest import free_port, wait_until
from tests.helpers.timing import answered, scaled
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
            # `-o run`, as with `ros2 bag record -o run`: the file is run.mcap.
            "record", "cam/images", "cam/log", "-o", str(tmp_path / "run"), "--count", str(COUNT),
            "--queue", "1", "--json",
        )  # fmt: skip
        assert images.wait_for_subscribers(1, timeout_s=scaled(30))
        assert log.wait_for_subscribers(1, timeout_s=scaled(30))
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
    assert summary["file"] == str(bag) and not (tmp_path / "run").exists()

    _check_mcap(bag, base)

    # The original service is gone; play offers the same names again.
    play_endpoint = f"tcp/127.0.0.1:{free_port()}"
    # `play run` plays the run.mcap that `record -o run` wrote.
    player = cli.start("play", str(tmp_path / "run"), "--fast", "--json", "--listen", play_endpoint)
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
            replayed = answered(
                lambda b=buffer: client.query(f"cam/{b}", time_range=f"[{base}..]"),  # type: ignore[misc]
                buffer,
            )
            assert [(e.timestamp_ns, e.payload, e.metadata) for e in replayed] == expected
        info = answered(lambda: client.buffer_info("cam/images", timeout_s=scaled(10.0)), "info")
        assert info.retention == retention
    player.send_signal(signal.SIGTERM)  # Ctrl-C equivalent: closes cleanly
    # How promptly is test_clean_exit's; here the exit code (at load 36, 20 s was missed).
    assert player.wait(timeout=scaled(60)) == 0


def _elements(node: Node, target: str) -> list[tuple[int, bytes, bytes]]:
    found = answered(lambda: node.query(target), target)
    return [(e.timestamp_ns, e.payload, e.metadata) for e in found]


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
        played = answered(lambda: client.query("cam/images"), "cam/images")
    shift = played[0].timestamp_ns - recorded[0]
    assert abs(played[0].timestamp_ns - started) < 30 * 10**9  # now, not 1970
    assert [e.timestamp_ns - shift for e in played] == recorded
    assert [e.payload for e in played] == [frame_payload(i) for i in range(5)]
    # Metadata moved along: the envelope and the exposure start, not the exposure time.
    assert played[2].metadata == frame_metadata(recorded[2] + shift, 2)
    player.send_signal(signal.SIGTERM)
    assert player.wait(timeout=scaled(20)) == 0


def test_play_puts_a_newest_element_of_long_before_the_recording_at_once(
    cli: Cli, tmp_path: Path
) -> None:
    """record keeps each buffer's newest element at its start (a camera description put
    once, maybe an hour earlier). play paced from that stamp and idled the hour before the
    first frame (a 5 s `record --all` of a 25 min old pipeline took 25 min to play)."""
    bag = tmp_path / "latched.mcap"
    started = 10**13
    info_t = started - 3600 * 10**9  # an hour before the recording started
    frames = [started + i * 100 * MS for i in range(5)]
    with BagWriter(bag) as writer:
        writer.add_buffer("cam", "info", kind="generic", retention=Retention())
        writer.add_buffer("cam", "images", kind="frame", retention=Retention())
        writer.write(
            "cam/info", DataObject(info_t, b"description", make_metadata("generic", info_t))
        )
        for i, t in enumerate(frames):
            writer.write("cam/images", DataObject(t, frame_payload(i), frame_metadata(t, i)))
        writer.add_metadata("framegate.recording", {"started_ns": str(started)})
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    player = cli.start("play", str(bag), "--loop", "--json", "--listen", endpoint)
    events = LineReader(player)
    events.json_until(lambda e: e["event"] == "offered", TIMEOUT_S)
    with Node(network=NetworkConfig(connect=(endpoint,))) as client:
        wait_until(lambda: "cam" in client.live_services(), 10, "the played service")
        # Two passes of 0.5 s each, not an hour: both buffers get their elements again.
        wait_until(
            lambda: (
                len(client.query("cam/images")) >= 2 * len(frames)
                and len(client.query("cam/info")) >= 2
            ),
            scaled(30),
            "two passes of the recording",
        )
        played = client.query("cam/images")
    stamps = [e.timestamp_ns for e in played]
    assert stamps == sorted(stamps) and stamps[: len(frames)] == frames, stamps
    period = stamps[len(frames)] - frames[0]
    assert period < 10**9, period  # shifted by the frames' span, not by the hour
    player.send_signal(signal.SIGTERM)
    assert player.wait(timeout=scaled(20)) == 0


def test_play_skips_and_counts_an_element_its_buffer_refuses(cli: Cli, tmp_path: Path) -> None:
    """A damaged or hand-made file: one element's metadata is no XML, another's names
    another stamp. Each is skipped, counted and warned of once; every other one is played."""
    bag = tmp_path / "damaged.mcap"
    base = time.time_ns() - 10**9
    stamps = [base + i * MS for i in range(6)]
    with BagWriter(bag) as writer:
        writer.add_buffer("gen", "b", kind="generic", retention=Retention())
        for i, t in enumerate(stamps):
            metadata = make_metadata("generic", t)
            if i == 1:
                metadata = b"<not xml"
            elif i == 3:
                metadata = make_metadata("generic", t + 1)
            writer.write("gen/b", DataObject(t, b"x", metadata))
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    player = cli.start("play", str(bag), "--fast", "--json", "--listen", endpoint)
    events = LineReader(player)
    done = events.json_until(lambda e: e["event"] == "done", TIMEOUT_S)
    assert done["played"] == 4, done
    assert done["skipped"] == {"gen/b: SchemaError": 2}, done
    with Node(network=NetworkConfig(connect=(endpoint,))) as client:
        wait_until(lambda: "gen" in client.live_services(), 10, "the played service")
        played = answered(lambda: client.query("gen/b"), "gen/b")
    assert [e.timestamp_ns for e in played] == [stamps[i] for i in (0, 2, 4, 5)]
    player.send_signal(signal.SIGTERM)
    assert player.wait(timeout=scaled(20)) == 0
    assert player.stderr is not None
    warnings = [line for line in player.stderr.read().splitlines() if line.startswith("warning")]
    assert len(warnings) == 1 and "skipped the element stamped" in warnings[0], warnings


def test_record_writes_verdict_and_detection_annotations_with_foxglove_schemas(
    listen_net: NetworkConfig, cli: Cli, tmp_path: Path
) -> None:
    bag = tmp_path / "annotated.mcap"
    base = time.time_ns()
    frames = [base + i * 50 * MS for i in range(3)]
    with Node("rig", listen_net) as rig:
        images = rig.offer("images", kind="frame")
        decisions = rig.offer("decisions", kind="decision")
        detections = rig.offer("detections", kind="detections")
        rates = rig.offer("rates", kind="gyro")
        recorder = cli.start(
            "record", "rig/images", "rig/decisions", "rig/detections", "rig/rates",
            "-o", str(bag), "--count", "3", "--json",
        )  # fmt: skip
        for producer in (images, decisions, detections, rates):
            assert producer.wait_for_subscribers(1, timeout_s=scaled(30))
        for i, t in enumerate(frames):
            put_frame(images, t, i)
            # Verdict borders are drawn to the size of the frames recorded so far: let the
            # recorder take the frame before its verdict is put.
            wait_until(
                lambda: all(s.queued == 0 for s in images.subscriptions()), 30, "frame taken"
            )
            verdict = DecisionRecord(
                t, i, 1.5 * i, 0.9 - 0.3 * i, 0.5, i == 0, "q", "paper", 5.0, 0
            )
            decisions.put(t + MS, b"", verdict.metadata(t + MS))
            corners = [1.0, 1.0, 5.0, 1.0, 5.0, 4.0, 1.0, 4.0]
            detections.put(
                t, b"", detections_metadata(t, i, "rig/images", 1000, [(7 + i, corners)])
            )
            samples = GyroSamples(np.array([t - MS, t]), np.full((2, 3), 0.1 * i))
            rates.put(t, samples.to_bytes(), gyro_metadata(samples))
        out, err = recorder.communicate(timeout=TIMEOUT_S)
        assert recorder.returncode == 0, err
    derived = {b["name"]: b["derived_messages"] for b in json.loads(out)["buffers"]}
    # Per decision an annotation and a plot point; per detection one; per gyro sample one.
    assert derived == {"rig/images": 0, "rig/decisions": 6, "rig/detections": 3, "rig/rates": 6}
    with bag.open("rb") as stream:
        reader = make_reader(stream)
        summary = reader.get_summary()
        assert summary is not None
        channels = {c.topic: c for c in summary.channels.values()}
        schemas = {t: summary.schemas.get(c.schema_id) for t, c in channels.items()}
        for topic in ("/rig/decisions/annotations", "/rig/detections/annotations"):
            schema = schemas[topic]
            assert schema is not None and schema.name == "foxglove.ImageAnnotations"
            assert (schema.encoding, channels[topic].message_encoding) == ("protobuf", "protobuf")
        assert channels["/rig/decisions/verdict"].message_encoding == "json"
        assert channels["/rig/rates/rates"].message_encoding == "json"
        messages = {
            topic: [(m.log_time, m.data) for _s, _c, m in reader.iter_messages(topics=[topic])]
            for topic in channels
        }
        verdict_schema = schemas["/rig/decisions/annotations"]
        assert verdict_schema is not None
    annotations = _protobuf_class(verdict_schema.data, verdict_schema.name)
    drawn = [annotations.FromString(data) for _t, data in messages["/rig/decisions/annotations"]]
    # Each verdict is stamped with its frame's timestamp: Foxglove draws it on that frame.
    assert [a.timestamp.seconds * 10**9 + a.timestamp.nanos for a in drawn] == frames
    assert drawn[0].texts[0].text.startswith("ACCEPT") and drawn[1].texts[0].text.startswith(
        "REJECT"
    )
    assert [(p.x, p.y) for p in drawn[0].points[0].points][2] == (WIDTH - 4.0, HEIGHT - 4.0)
    markers = [annotations.FromString(d) for _t, d in messages["/rig/detections/annotations"]]
    assert [m.texts[0].text for m in markers] == ["id 7", "id 8", "id 9"]
    plot = [json.loads(d) for _t, d in messages["/rig/decisions/verdict"]]
    assert [p["accepted"] for p in plot] == [True, False, False] and plot[0]["q"] == 0.9
    assert len(messages["/rig/rates/rates"]) == 6
    with open_bag(bag) as recorded:  # play reads the buffers and leaves the derived channels be
        assert [b.name for b in recorded.buffers] == [
            "rig/decisions", "rig/detections", "rig/images", "rig/rates",
        ]  # fmt: skip


def _protobuf_class(file_descriptor_set: bytes, name: str) -> Any:
    from google.protobuf import descriptor_pb2, descriptor_pool, message_factory

    pool = descriptor_pool.DescriptorPool()
    for proto in descriptor_pb2.FileDescriptorSet.FromString(file_descriptor_set).file:
        pool.Add(proto)
    return message_factory.GetMessageClass(pool.FindMessageTypeByName(name))


def test_record_counts_garbage_on_its_notify_key_and_loses_nothing(
    listen_net: NetworkConfig, cli: Cli, tmp_path: Path, endpoint: str
) -> None:
    """A peer's garbage on the key the recorder's notifications come on: said in the summary
    (it was counted inside the subscription only), and every element is still recorded."""
    from middleware._wire import Keys
    from tests.helpers.raw_zenoh import open_session, reaching

    with Node("cam", listen_net) as service, open_session(endpoint) as rogue:
        log = service.offer("log", retention=Retention(max_count=500))
        recorder = cli.start(
            "record", "cam/log", "-o", str(tmp_path / "run.mcap"), "--count", str(COUNT),
            "--json",
        )  # fmt: skip
        assert log.wait_for_subscribers(1, timeout_s=scaled(30))
        (sub,) = log.subscriptions()
        key = Keys("framegate").notify("cam", "log", sub.subscription_id)
        garbage = reaching(rogue, key, "the recorder's notify key, from the rogue")
        base = time.time_ns()
        for i in range(COUNT):
            if i == COUNT - 1:
                # The rogue's garbage reaches the recorder through the service's session, so
                # it can lag behind the service's own puts (a recorder that stops at its
                # count then never sees it: CI under load). A query of the service after it
                # is answered only once that session has passed on every earlier message of
                # the rogue's link; the last element goes out after that.
                for _reply in rogue.get(Keys("framegate").info("cam"), timeout=scaled(30)):
                    break
            garbage.put(b"\xff" * 32, attachment=b"not a notification")
            t = base + i * MS
            log.put(t, b"line %d" % i, make_metadata("generic", t, {"n": i}))
        out, err = recorder.communicate(timeout=TIMEOUT_S)
        assert recorder.returncode == 0, err
    (row,) = json.loads(out)["buffers"]
    assert row["recorded"] == COUNT and row["lost"] == 0, row
    assert row["bad_notifications"] > 0, row
