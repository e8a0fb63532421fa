"""CDR round trips through rosbags: images, IMU samples, detections, verdicts."""

from __future__ import annotations

import json
import time
import tracemalloc

import numpy as np
import pytest

from middleware import ConfigError, DataObject
from services.lib.messages import frame_metadata_of
from services.lib.quality import Exposure
from services.nodes.ros2._bridge import Encoders
from services.nodes.ros2._cdr import BYTES_PER_PIXEL, DETECTIONS, IMAGE, STRING, CdrError, Codec
from services.nodes.ros2._config import Ros2Config


@pytest.fixture(params=["humble", "jazzy"])
def codec(request: pytest.FixtureRequest) -> Codec:
    return Codec(request.param)


def test_image_round_trip_keeps_pixels_and_stamp(codec: Codec) -> None:
    pixels = (np.arange(6 * 5 * 3) % 256).astype(np.uint8).tobytes()
    raw = codec.encode_image(1_700_000_000_987_654_321, "cam", 6, 5, "bgr8", pixels)
    image = codec.decode_image(bytes(raw))
    assert (image.stamp_ns, image.frame_id, image.width, image.height) == (
        1_700_000_000_987_654_321,
        "cam",
        6,
        5,
    )
    assert (image.encoding, image.step) == ("bgr8", 18)
    assert image.pixels() == pixels
    message = codec.decode(bytes(raw), IMAGE)  # rosbags reads what we wrote
    assert message.data.tobytes() == pixels


@pytest.mark.parametrize(
    ("encoding", "bytes_per_pixel"), [("bgra8", 4), ("rgba8", 4), ("mono16", 2)]
)
def test_a_new_encodings_image_round_trips_through_the_bridge_and_back(
    codec: Codec, encoding: str, bytes_per_pixel: int
) -> None:
    """In: a ROS 2 image with padded rows becomes the frame's unpadded pixels; out: the
    frame becomes an image of the same encoding whose step is width x bytes per pixel."""
    width, height, step = 5, 3, 5 * bytes_per_pixel + 4
    rows = (np.arange(height * step) % 251).astype(np.uint8).reshape(height, step)
    types = codec.store.types
    padded = types[IMAGE](
        header=types["std_msgs/msg/Header"](
            stamp=types["builtin_interfaces/msg/Time"](sec=1_700_000_000, nanosec=5),
            frame_id="zed_left",
        ),
        height=height,
        width=width,
        encoding=encoding,
        is_bigendian=0,
        step=step,
        data=rows.reshape(-1),
    )
    image = codec.decode_image(bytes(codec.store.serialize_cdr(padded, IMAGE)))
    pixels = image.pixels()
    assert pixels == rows[:, : width * bytes_per_pixel].tobytes()
    now = 1_700_000_000_000_000_005
    element = DataObject(
        now, pixels, frame_metadata_of(1, Exposure(now, 5), encoding, width, height, None)
    )
    out = codec.decode(bytes(Encoders(codec, Ros2Config()).image(element)), IMAGE)
    assert (out.encoding, out.width, out.height, out.step) == (
        encoding,
        width,
        height,
        width * bytes_per_pixel,
    )
    assert out.is_bigendian == 0 and out.data.tobytes() == pixels


def _mono16_message(codec: Codec, samples: np.ndarray, *, big_endian: bool) -> bytes:
    types = codec.store.types
    height, width = samples.shape
    message = types[IMAGE](
        header=types["std_msgs/msg/Header"](
            stamp=types["builtin_interfaces/msg/Time"](sec=1_700_000_000, nanosec=0),
            frame_id="ir",
        ),
        height=height,
        width=width,
        encoding="mono16",
        is_bigendian=int(big_endian),
        step=2 * width + 2,  # padded rows too
        data=np.pad(
            samples.astype(">u2" if big_endian else "<u2").view(np.uint8), ((0, 0), (0, 2))
        ).reshape(-1),
    )
    return bytes(codec.store.serialize_cdr(message, IMAGE))


@pytest.mark.parametrize("big_endian", [False, True])
def test_a_mono16_image_is_stored_little_endian_whichever_order_it_came_in(
    codec: Codec, big_endian: bool
) -> None:
    samples = np.array([[0x0102, 0x0FFF, 0], [0xFFFF, 0x1234, 7]], np.uint16)
    image = codec.decode_image(_mono16_message(codec, samples, big_endian=big_endian))
    assert image.swap is big_endian
    assert image.pixels() == samples.astype("<u2").tobytes()


def test_is_bigendian_is_ignored_for_eight_bit_samples(codec: Codec) -> None:
    types = codec.store.types
    header = types["std_msgs/msg/Header"](
        stamp=types["builtin_interfaces/msg/Time"](sec=1, nanosec=0), frame_id="c"
    )
    data = np.arange(2 * 2 * 4, dtype=np.uint8)
    message = types[IMAGE](header, 2, 2, "bgra8", 1, 8, data)
    image = codec.decode_image(bytes(codec.store.serialize_cdr(message, IMAGE)))
    assert not image.swap and image.pixels() == data.tobytes()


def _rosbags_image(
    codec: Codec, t_ns: int, frame_id: str, width: int, height: int, encoding: str, pixels: bytes
) -> bytes:
    """The same image serialized by rosbags as a whole message: the reference."""
    types = codec.store.types
    stamp = types["builtin_interfaces/msg/Time"](sec=t_ns // 10**9, nanosec=t_ns % 10**9)
    message = types[IMAGE](
        header=types["std_msgs/msg/Header"](stamp=stamp, frame_id=frame_id),
        height=height,
        width=width,
        encoding=encoding,
        is_bigendian=0,
        step=width * BYTES_PER_PIXEL[encoding],
        data=np.frombuffer(pixels, dtype=np.uint8),
    )
    return bytes(codec.store.serialize_cdr(message, IMAGE))


@pytest.mark.parametrize(
    ("width", "encoding"),
    [(64, "mono8"), (5, "rgb8"), (3, "bgr8"), (5, "bgra8"), (3, "rgba8"), (5, "mono16")],
)
def test_image_encoding_is_byte_for_byte_rosbags_own(
    codec: Codec, width: int, encoding: str
) -> None:
    channels = BYTES_PER_PIXEL[encoding]
    pixels = (np.arange(width * 7 * channels) % 253).astype(np.uint8).tobytes()
    for frame_id in ("", "cam", "camera_optical_frame"):  # every alignment of the tail
        ours = codec.encode_image(1_234_567_890_123, frame_id, width, 7, encoding, pixels)
        reference = _rosbags_image(codec, 1_234_567_890_123, frame_id, width, 7, encoding, pixels)
        assert ours == bytes(reference)
        assert len(ours) < len(pixels) + 100  # the pixels once, plus the head


def test_an_image_array_encodes_like_its_bytes(codec: Codec) -> None:
    array = np.arange(12, dtype=np.uint8).reshape(3, 4)
    assert codec.encode_image(1, "c", 4, 3, "mono8", array) == codec.encode_image(  # type: ignore[arg-type]
        1, "c", 4, 3, "mono8", array.tobytes()
    )


def test_decoding_does_not_copy_the_pixels(codec: Codec) -> None:
    raw = bytes(codec.encode_image(1, "cam", 4, 4, "mono8", bytes(16)))
    image = codec.decode_image(raw)
    assert np.shares_memory(image.data, np.frombuffer(raw, dtype=np.uint8))


def test_truncated_messages_are_cdr_errors(codec: Codec) -> None:
    raw = bytes(codec.encode_image(1, "cam", 4, 4, "mono8", bytes(16)))
    with pytest.raises(CdrError, match="not a CDR sensor_msgs/msg/Image"):
        codec.decode_image(raw[:30])
    with pytest.raises(CdrError, match="not a CDR sensor_msgs/msg/Imu"):
        codec.decode_imu_frame(raw[:10])


def test_detections_and_verdicts_round_trip(codec: Codec) -> None:
    raw = codec.encode_detections(42, "cam", [(7, [10, 20, 30, 20, 30, 40, 10, 40])])
    message = codec.decode(bytes(raw), DETECTIONS)
    assert message.header.stamp.nanosec == 42
    [detection] = message.detections
    assert detection.id == "7" and detection.results[0].hypothesis.class_id == "7"
    box = detection.bbox
    assert (box.center.position.x, box.center.position.y, box.size_x, box.size_y) == (
        20,
        30,
        20,
        20,
    )
    text = codec.decode(bytes(codec.encode_string({"accepted": True, "stamp_ns": 5})), STRING)
    assert json.loads(text.data) == {"accepted": True, "stamp_ns": 5}


def test_vision_msgs_are_registered_once_per_store() -> None:
    first, second = Codec("jazzy"), Codec("jazzy")
    assert first.rihs01(DETECTIONS) == second.rihs01(DETECTIONS)
    assert first.rihs01(DETECTIONS).startswith("RIHS01_")


def test_unknown_distro_is_a_config_error() -> None:
    with pytest.raises(ConfigError, match="unknown ROS 2 distro 'foxy'"):
        Codec("foxy")


def test_encoding_a_full_frame_allocates_the_frame_once() -> None:
    width, height = 1280, 1024
    now = time.time_ns()
    element = DataObject(
        now,
        bytes(width * height),
        frame_metadata_of(1, Exposure(now, 5), "mono8", width, height, None),
    )
    encode = Encoders(Codec("jazzy"), Ros2Config()).image
    encode(element)  # warm up rosbags' generated serializers
    tracemalloc.start()
    try:
        before = tracemalloc.get_traced_memory()[0]
        message = encode(element)
        peak = tracemalloc.get_traced_memory()[1] - before
    finally:
        tracemalloc.stop()
    # The message is the one frame-sized buffer the out path makes (no second one on the way).
    assert len(message) > width * height
    assert peak < width * height + 64 * 1024, peak
