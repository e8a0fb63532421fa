"""The bridge's in-direction boundary with real framegate buffers (no ROS 2 session):
flow control ends at the bridge, and every bad message is a counted skip, never a crash."""

from __future__ import annotations

import json
import logging
import signal
import subprocess
import sys
import threading
import time
from collections.abc import Iterator

import numpy as np
import pytest
import zenoh

from middleware import DataObject, NetworkConfig, Node, Producer
from services.lib.frame_layout import FrameError, read_frame_layout
from services.nodes.ros2._bridge import ImagesIn, ImuIn, _Skips, stop_summary
from services.nodes.ros2._cdr import BYTES_PER_PIXEL, IMAGE, IMU, Codec
from services.nodes.ros2._config import Ros2Config
from services.nodes.ros2._rmw import HUMBLE_TYPE_HASH, EntityKind, NodeIdentity, Qos
from tests.conftest import REPO, child_env, free_port, wait_until
from tests.helpers.timing import answered, scaled

W, H = 8, 4


@pytest.fixture
def codec() -> Codec:
    return Codec("jazzy")


@pytest.fixture
def node(listen_net: NetworkConfig) -> Iterator[Node]:
    with Node("ros2", listen_net) as n:
        yield n


@pytest.fixture
def consumer(connect_net: NetworkConfig) -> Iterator[Node]:
    with Node(network=connect_net) as n:
        yield n


def _image(codec: Codec, stamp_ns: int, encoding: str = "mono8") -> bytes:
    channels = BYTES_PER_PIXEL[encoding]
    pixels = (np.arange(W * H * channels) % 251).astype(np.uint8).tobytes()
    return bytes(codec.encode_image(stamp_ns, "cam", W, H, encoding, pixels))


def _query(consumer: Node, target: str) -> list[DataObject]:
    """The whole buffer, once the consumer has met its service (a query does not wait for
    discovery, which a loaded machine can take seconds over)."""
    service = target.split("/", 1)[0]
    wait_until(lambda: service in consumer.live_services(), 30, f"the {service} service")
    return answered(lambda: consumer.query(target), target)


def _skipped(producer: Producer) -> dict[str, int]:
    return dict(producer.info().skipped)


def test_a_refused_image_is_dropped_at_the_bridge_and_counted(
    node: Node, consumer: Node, codec: Codec
) -> None:
    images = ImagesIn(node, codec, Ros2Config(image_in="/cam"), _Skips(logging.getLogger()))
    # A flow-controlled subscriber with a queue of one that never takes.
    sub = consumer.subscribe("ros2/images", queue_size=1, wait_s=5)
    wait_until(lambda: images.producer.subscriptions(), 30, "the subscription")
    now = time.time_ns()
    images.handle(_image(codec, now), 1)
    images.handle(_image(codec, now + 1_000_000), 2)
    info = images.producer.info()
    assert (info.puts, info.refused) == (1, 1)
    assert (images.stored, images.dropped) == (1, 1)
    note = sub.take(timeout_s=scaled(30))
    assert note is not None and note.timestamp_ns == now


@pytest.mark.parametrize(
    ("raw", "reason"),
    [
        (b"\x00\x01\x00\x00garbage", "bad-cdr"),
        (b"", "bad-cdr"),
    ],
)
def test_malformed_cdr_is_a_counted_skip(node: Node, codec: Codec, raw: bytes, reason: str) -> None:
    skips = _Skips(logging.getLogger())
    images = ImagesIn(node, codec, Ros2Config(image_in="/cam"), skips)
    images.handle(raw, 1)
    assert skips.counts == {reason: 1}
    assert images.producer.info().puts == 0


def test_inconsistent_sizes_unknown_encodings_and_stamps_are_counted_skips(
    node: Node, codec: Codec, caplog: pytest.LogCaptureFixture
) -> None:
    skips = _Skips(logging.getLogger("test"))
    images = ImagesIn(node, codec, Ros2Config(image_in="/cam"), skips)
    store = codec.store
    t = store.types
    now = time.time_ns()

    def message(width: int, height: int, step: int, encoding: str, data: int) -> bytes:
        header = t["std_msgs/msg/Header"](t["builtin_interfaces/msg/Time"](now // 10**9, 0), "c")
        image = t["sensor_msgs/msg/Image"](
            header, height, width, encoding, 0, step, np.zeros(data, dtype=np.uint8)
        )
        return bytes(store.serialize_cdr(image, "sensor_msgs/msg/Image"))

    with caplog.at_level(logging.WARNING):
        images.handle(message(W, H, W, "mono8", W * H - 1), 1)  # data too short
        images.handle(message(W, H, W - 1, "mono8", (W - 1) * H), 2)  # step < width
        images.handle(message(2**20, 2**20, 2**20, "mono8", 16), 3)  # absurd size
        images.handle(message(W, H, 2 * W, "yuv422", 2 * W * H), 4)  # unknown encoding
        images.handle(message(W, H, W, "mono8", W * H), 5)  # fine
        images.handle(message(W, H, W, "mono8", W * H), 6)  # same stamp again
        images.handle(_image(codec, now - 10**9), 7)  # older
        images.handle(_image(codec, 0), 8)  # no stamp
    assert skips.counts == {
        "bad-image": 4,
        "duplicate-stamp": 1,
        "out-of-order": 1,
        "bad-stamp": 1,
    }
    assert images.producer.info().puts == 1
    # One warning per reason, however many skips.
    warned = [r for r in caplog.records if "skipping (bad-image" in r.getMessage()]
    assert len(warned) == 1


@pytest.mark.parametrize("encoding", ["yuv422", "bayer_rggb8", "16UC1", "rgb16"])
def test_an_encoding_a_frame_cannot_hold_is_a_bad_image_naming_the_accepted_ones(
    node: Node, codec: Codec, caplog: pytest.LogCaptureFixture, encoding: str
) -> None:
    skips = _Skips(logging.getLogger("test"))
    images = ImagesIn(node, codec, Ros2Config(image_in="/cam"), skips)
    pixels = bytes(W * H * 2)
    raw = bytes(codec.store.serialize_cdr(
        codec.store.types[IMAGE](
            codec.store.types["std_msgs/msg/Header"](
                codec.store.types["builtin_interfaces/msg/Time"](time.time_ns() // 10**9, 0), "c"
            ),
            H, W, encoding, 0, 2 * W, np.frombuffer(pixels, np.uint8),
        ),
        IMAGE,
    ))  # fmt: skip
    with caplog.at_level(logging.WARNING):
        images.handle(raw, 1)
    assert skips.counts == {"bad-image": 1} and images.producer.info().puts == 0
    [warning] = [r.getMessage() for r in caplog.records if "bad-image" in r.getMessage()]
    assert f"encoding '{encoding}' (framegate takes mono8, mono16, bgr8, rgb8, bgra8, rgba8)" in (
        warning
    )


def test_padded_rows_are_stored_without_padding(node: Node, consumer: Node, codec: Codec) -> None:
    images = ImagesIn(node, codec, Ros2Config(image_in="/cam"), _Skips(logging.getLogger()))
    t, store = codec.store.types, codec.store
    rows = np.arange(H * (W + 4), dtype=np.uint8).reshape(H, W + 4)
    now = time.time_ns()
    header = t["std_msgs/msg/Header"](
        t["builtin_interfaces/msg/Time"](now // 10**9, now % 10**9), "c"
    )
    image = t["sensor_msgs/msg/Image"](header, H, W, "mono8", 0, W + 4, rows.reshape(-1))
    images.handle(bytes(store.serialize_cdr(image, "sensor_msgs/msg/Image")), 1)
    [element] = _query(consumer, "ros2/images")
    assert element.timestamp_ns == now
    assert element.payload == rows[:, :W].tobytes()


@pytest.mark.parametrize("encoding", ["bgra8", "rgba8", "mono16"])
def test_a_new_encodings_image_is_stored_as_a_frame_of_its_encoding(
    node: Node, consumer: Node, codec: Codec, encoding: str
) -> None:
    skips = _Skips(logging.getLogger())
    images = ImagesIn(node, codec, Ros2Config(image_in="/zed/left"), skips)
    now = time.time_ns()
    raw = _image(codec, now, encoding)
    images.handle(raw, 1)
    assert skips.counts == {}
    [element] = _query(consumer, "ros2/images")
    assert element.payload == codec.decode_image(raw).pixels()
    assert len(element.payload) == W * H * BYTES_PER_PIXEL[encoding]
    assert read_frame_layout(element.metadata, len(element.payload)).encoding == encoding


def test_stamp_at_exposure_end_keys_by_exposure_start(
    node: Node, consumer: Node, codec: Codec
) -> None:
    config = Ros2Config(image_in="/cam", stamp="end", exposure_ms=20)
    images = ImagesIn(node, codec, config, _Skips(logging.getLogger()))
    now = time.time_ns()
    images.handle(_image(codec, now), 1)
    [element] = _query(consumer, "ros2/images")
    assert element.timestamp_ns == now - 20_000_000
    assert config.stamp_ns(element.timestamp_ns) == now
    assert b"<exposure_ns>20000000</exposure_ns>" in element.metadata


def test_imu_samples_become_gyro_elements_in_batches(
    node: Node, consumer: Node, codec: Codec
) -> None:
    skips = _Skips(logging.getLogger())
    imu = ImuIn(node, codec, Ros2Config(imu_in="/imu", gyro_batch=4), skips)
    t, store = codec.store.types, codec.store
    start = time.time_ns() - 10**9

    def sample(t_ns: int, wz: float) -> bytes:
        header = t["std_msgs/msg/Header"](
            t["builtin_interfaces/msg/Time"](t_ns // 10**9, t_ns % 10**9), "i"
        )
        v = t["geometry_msgs/msg/Vector3"]
        z = np.zeros(9)
        message = t[IMU](
            header,
            t["geometry_msgs/msg/Quaternion"](0, 0, 0, 1),
            z,
            v(0.0, 0.0, wz),
            z,
            v(0, 0, 0),
            z,
        )
        return bytes(store.serialize_cdr(message, IMU))

    for i in range(4):
        imu.add(sample(start + i * 5_000_000, 0.1 * i))
    imu.add(sample(start + 2 * 5_000_000, 9.0))  # out of order
    imu.add(b"nonsense")
    imu.flush()
    elements = _query(consumer, "ros2/rates")
    assert [e.timestamp_ns for e in elements] == [start + i * 5_000_000 for i in range(4)]
    assert skips.counts == {"out-of-order": 1, "bad-cdr": 1}
    assert imu.stored == 4


def _lines_within(proc: subprocess.Popen[str], limit_s: float) -> Iterator[str]:
    """The process's output lines; it is killed if they have not stopped coming by then."""
    assert proc.stdout is not None
    killer = threading.Timer(scaled(limit_s), proc.kill)
    killer.start()
    try:
        yield from proc.stdout
    finally:
        killer.cancel()


@pytest.mark.integration
def test_sigterm_stops_the_bridge_within_two_seconds_with_exit_0(endpoint: str) -> None:
    proc = subprocess.Popen(
        [
            sys.executable,
            "-m",
            "services.cli",
            "run",
            "ros2",
            "--listen",
            endpoint,
            "--ros-connect",
            "tcp/127.0.0.1:1",
            "--image-in",
            "/camera/image_raw",
            "--image-out",
            "ros2/images=/echo",
        ],
        cwd=REPO,
        env=child_env(),
        stdout=subprocess.PIPE,
        stderr=subprocess.STDOUT,
        text=True,
    )
    try:
        assert proc.stdout is not None
        seen = []
        for line in _lines_within(proc, 30):
            seen.append(line)
            # Nothing listens on port 1: the bridge starts, then says no router answers.
            if "no ROS 2 router at tcp/127.0.0.1:1" in line:
                break
        else:
            raise AssertionError(f"bridge exited with {proc.wait()}: {''.join(seen)}")
        assert any("ros2: node framegate_bridge" in line for line in seen), seen
        proc.send_signal(signal.SIGTERM)
        started = time.monotonic()
        # "Within ~2 s" is the contract (by design: no wait of the bridge outlasts it); the
        # scaled deadline only catches a stop that hangs, as tests/services/nodes/
        # test_clean_exit.py does for every service.
        assert proc.wait(timeout=scaled(20)) == 0
        print(f"the bridge stopped {time.monotonic() - started:.2f} s after SIGTERM")
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()


def test_skips_show_in_the_buffers_skipped_counter(node: Node, codec: Codec) -> None:
    images = ImagesIn(node, codec, Ros2Config(image_in="/cam"), _Skips(logging.getLogger()))
    images.handle(b"garbage", 1)
    images.handle(_image(codec, 0), 2)
    assert _skipped(images.producer) == {"bad-cdr": 1, "bad-stamp": 1}


def test_outputs_name_the_frame_of_the_images_in_unless_told(node: Node, codec: Codec) -> None:
    from services.nodes.ros2._bridge import Encoders

    images = ImagesIn(node, codec, Ros2Config(image_in="/cam"), _Skips(logging.getLogger()))
    frame = lambda: images.last_frame_id  # noqa: E731
    assert Encoders(codec, Ros2Config(), frame).frame_id() == "camera"  # no image yet
    images.handle(_image(codec, time.time_ns()), 1)  # header.frame_id "cam"
    assert Encoders(codec, Ros2Config(), frame).frame_id() == "cam"
    assert Encoders(codec, Ros2Config(frame_id="optical"), frame).frame_id() == "optical"


def test_out_images_keep_pixels_and_refuse_inconsistent_elements(codec: Codec) -> None:
    from middleware import DataObject, make_metadata
    from services.lib.messages import frame_metadata_of
    from services.lib.quality import Exposure
    from services.nodes.ros2._bridge import Encoders

    encoders = Encoders(codec, Ros2Config(image_out=(), frame_id="cam"))
    now = time.time_ns()
    pixels = bytes(range(W * H))
    good = DataObject(now, pixels, frame_metadata_of(1, Exposure(now, 5), "mono8", W, H, None))
    message = codec.decode(encoders.image(good), "sensor_msgs/msg/Image")
    assert message.data.tobytes() == pixels
    assert (message.header.stamp.sec, message.header.stamp.nanosec) == divmod(now, 10**9)
    for bad, match in (
        (DataObject(now, pixels[:-1], good.metadata), "payload is 31 bytes"),
        (
            DataObject(now, pixels, frame_metadata_of(1, Exposure(now, 5), "yuv422", W, H, None)),
            "encoding",
        ),
        (DataObject(now, b"", make_metadata("generic", now, {})), "kind"),
    ):
        with pytest.raises(FrameError, match=match):
            encoders.image(bad)


@pytest.mark.integration
def test_a_driver_on_another_distro_is_named_with_the_flag_to_change(endpoint: str) -> None:
    # A ROS 2 router with a Humble camera driver's publisher token on /camera/image_raw; the
    # bridge, on its default distro (jazzy), would never meet its samples.
    router_at = f"tcp/127.0.0.1:{free_port()}"
    conf = zenoh.Config()
    conf.insert_json5("mode", '"router"')
    conf.insert_json5("listen/endpoints", json.dumps([router_at]))
    conf.insert_json5("scouting/multicast/enabled", "false")
    with zenoh.open(conf) as router:
        driver = NodeIdentity(0, str(router.info.zid()), "camera_driver")
        token = router.liveliness().declare_token(
            driver.endpoint_token(
                1,
                EntityKind.PUBLISHER,
                "/camera/image_raw",
                IMAGE,
                HUMBLE_TYPE_HASH,
                Qos.sensor_data(),
            )
        )
        proc = subprocess.Popen(
            [
                *(sys.executable, "-m", "services.cli", "run", "ros2", "--listen", endpoint),
                *("--ros-connect", router_at, "--image-in", "/camera/image_raw"),
            ],
            cwd=REPO,
            env=child_env(),
            stdout=subprocess.PIPE,
            stderr=subprocess.STDOUT,
            text=True,
        )
        try:
            seen = []
            for line in _lines_within(proc, 30):
                seen.append(line)
                if "--ros-distro humble" in line:
                    break
            else:
                raise AssertionError(f"bridge exited with {proc.wait()}: {''.join(seen)}")
            assert "/camera/image_raw is published as sensor_msgs::msg::dds_::Image_" in line
        finally:
            proc.terminate()
            proc.wait(timeout=scaled(10))
            token.undeclare()


def test_the_stop_line_counts_the_consumer_loops_images_beside_the_outputs() -> None:
    """With ``--consumer-done`` it said "0 messages handed to ROS 2 by the outputs" while
    the loop's own line below said "published 93"."""
    common = {"frames": (120, 3), "imu": (0, 0), "outputs_published": 0, "skipped": ""}
    with_loop = stop_summary("ros2", loop_published=93, **common)  # type: ignore[arg-type]
    assert "0 messages handed to ROS 2 by the outputs and 93 images by the consumer loop" in (
        with_loop
    ), with_loop
    alone = stop_summary("ros2", loop_published=None, **common)  # type: ignore[arg-type]
    assert "by the outputs (whether" in alone and "consumer loop" not in alone, alone
    assert alone.startswith("ros2: 120 frames stored, 3 dropped") and alone.endswith("none")


def test_detections_out_carry_a_vision_handlers_scores(codec: Codec) -> None:
    from services.lib.messages import detections_metadata
    from services.nodes.ros2._bridge import Encoders
    from services.nodes.ros2._cdr import DETECTIONS

    now = time.time_ns()
    corners = [10.0, 20.0, 30.0, 20.0, 30.0, 40.0, 10.0, 40.0]
    # A handler's boxes: one with its confidence, one without (a marker: certain).
    metadata = detections_metadata(
        now, 1, "in/put", 5, [(3, corners), (7, corners)], scores=[0.25, None]
    )
    raw = Encoders(codec, Ros2Config(frame_id="cam")).detections(DataObject(now, b"", metadata))
    message = codec.decode(bytes(raw), DETECTIONS)
    scores = [d.results[0].hypothesis.score for d in message.detections]
    assert [d.results[0].hypothesis.class_id for d in message.detections] == ["3", "7"]
    assert scores == [0.25, 1.0]
