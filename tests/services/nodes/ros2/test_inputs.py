"""The bridge's inputs with real framegate buffers (no ROS 2 session): the camera description
built from CameraInfo and /tf_static, and stamps that cannot poison the time order."""

from __future__ import annotations

import dataclasses
import logging
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from middleware import NetworkConfig, Node
from services.lib.camera_model import CameraModel
from services.lib.messages import read_frame_metadata
from services.lib.quality import DEFAULT_B0_PX, BlurOptions, GyroSamples
from services.lib.sim import Scenario, ScenarioConfig
from services.nodes.mediator import blur_quality
from services.nodes.ros2._bridge import ImagesIn, ImuIn, _Skips
from services.nodes.ros2._camera_info import CameraSource, intrinsics
from services.nodes.ros2._cdr import IMU, Codec
from services.nodes.ros2._config import Ros2Config
from services.nodes.ros2._rmw import Attachment
from tests.helpers.timing import answered
from tests.services.nodes.ros2.ros_camera import IMAGE_FRAME, IMU_FRAME, camera_info, tf_static

HOUR_NS = 3600 * 10**9


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


def _image(
    codec: Codec, stamp_ns: int, width: int, height: int, pixels: bytes | None = None
) -> bytes:
    data = pixels if pixels is not None else bytes(width * height)
    return bytes(codec.encode_image(stamp_ns, IMAGE_FRAME, width, height, "mono8", data))


def _imu(codec: Codec, sec: int, nanosec: int, frame_id: str = IMU_FRAME) -> bytes:
    t = codec.store.types
    v, z = t["geometry_msgs/msg/Vector3"], np.zeros(9)
    message = t[IMU](
        t["std_msgs/msg/Header"](t["builtin_interfaces/msg/Time"](sec, nanosec), frame_id),
        t["geometry_msgs/msg/Quaternion"](0, 0, 0, 1),
        z,
        v(0.0, 0.0, 0.1),
        z,
        v(0, 0, 0),
        z,
    )
    return bytes(codec.store.serialize_cdr(message, IMU))


def _broadcast(source: CameraSource, messages: dict[str, bytes]) -> None:
    for i, raw in enumerate(messages.values()):
        source.on_tf(raw, Attachment(1, 0, bytes([i]) * 16).encode())


def test_cameras_from_camera_info_and_tf_blur_as_the_equivalent_camera_xml(
    node: Node, consumer: Node, codec: Codec
) -> None:
    scenario = Scenario(ScenarioConfig(seed=3))
    # ROS 2 stamps share one clock: the equivalent XML has no camera-gyro offset.
    xml = CameraModel.from_xml(dataclasses.replace(scenario.camera, gyro_time_offset_ns=0).to_xml())
    skips = _Skips(logging.getLogger("test"))
    config = Ros2Config(image_in="/camera/image_raw", imu_in="/imu/data", exposure_ms=20)
    images = ImagesIn(node, codec, config, skips)
    imu = ImuIn(node, codec, config, skips, images.cameras)
    now = time.time_ns()
    # Binned 2x2: the sensor's CameraInfo, halved, describes the images.
    images.cameras.on_camera_info(camera_info(codec, xml, now, binning=2), None)
    _broadcast(images.cameras, tf_static(codec, xml.gyro_to_camera))
    imu.add(_imu(codec, now // 10**9 - 1, 0))
    images.handle(_image(codec, now, xml.width_px, xml.height_px), 1)
    [element] = answered(lambda: consumer.query("ros2/images"), "ros2/images")
    meta = read_frame_metadata(element.metadata)
    ros = meta.camera
    assert ros is not None
    for name in ("width_px", "height_px", "fx_px", "fy_px", "cx_px", "cy_px"):
        assert getattr(ros, name) == pytest.approx(getattr(xml, name), rel=1e-9)
    assert np.allclose(ros.gyro_to_camera, xml.gyro_to_camera, atol=1e-9)

    # The mediator's own estimate with either description, over the scenario's motion.
    gyro = scenario.gyro_samples()
    samples = GyroSamples(np.asarray(gyro.t_ns), np.asarray(gyro.rate_rad_s))
    blurs = []
    for i in range(1, 6):
        info = scenario.frame_info(i)
        frame = dataclasses.replace(
            meta,
            exposure=dataclasses.replace(
                meta.exposure, start_ns=info.exposure_start_ns, duration_ns=info.exposure_ns
            ),
        )
        pair = [
            blur_quality(
                dataclasses.replace(frame, camera=c), samples, BlurOptions(), DEFAULT_B0_PX
            )
            for c in (ros, xml)
        ]
        assert pair[0] == pytest.approx(pair[1], rel=1e-6)
        blurs.append(pair[0][0])
    assert max(blurs) > 0.1  # the motion blurs: the comparison is not of zeros


_IDENTITY = (1.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0)


def test_a_wrong_size_camera_info_is_a_counted_skip_and_what_is_missing_is_said_once(
    node: Node, codec: Codec, caplog: pytest.LogCaptureFixture
) -> None:
    skips = _Skips(logging.getLogger("test"))
    camera = CameraModel(64, 48, 50.0, 50.0, 32.0, 24.0)
    images = ImagesIn(node, codec, Ros2Config(image_in="/cam/image_raw", imu_in="/imu"), skips)
    now = time.time_ns()
    with caplog.at_level(logging.WARNING):
        images.cameras.on_camera_info(camera_info(codec, camera, now, size=(640, 480)), None)
        images.handle(_image(codec, now, 64, 48), 1)
        images.handle(_image(codec, now + 1000, 64, 48), 2)
        images.cameras.on_camera_info(camera_info(codec, camera, now, calibrated=False), None)
        images.handle(_image(codec, now + 2000, 64, 48), 3)
        images.handle(_image(codec, now + 3000, 64, 48), 4)
    assert skips.counts == {"camera-info-mismatch": 1}
    assert images.producer.info().skipped == {"camera-info-mismatch": 1}
    assert images.producer.info().puts == 4  # the frames go on, without a description
    waits = [r.getMessage() for r in caplog.records if "waiting for" in r.getMessage()]
    assert len(waits) == 2, waits
    assert "a CameraInfo on /cam/camera_info for 64x48 images (it says 640x480)" in waits[0]
    assert "an IMU message on /imu to name the IMU frame (or --imu-to-camera)" in waits[0]
    assert "K[0] is 0: the camera is uncalibrated" in waits[1]


def _described_inputs(node: Node, codec: Codec, imu_frame: str = IMU_FRAME) -> tuple[ImagesIn, int]:
    """The inputs of /cam/image_raw (64x48) and /imu/data, given a CameraInfo, an identity
    mount on /tf_static and one IMU message naming ``imu_frame``; (images in, now)."""
    camera = CameraModel(64, 48, 50.0, 50.0, 32.0, 24.0)
    skips = _Skips(logging.getLogger("test"))
    config = Ros2Config(image_in="/cam/image_raw", imu_in="/imu/data")
    images = ImagesIn(node, codec, config, skips)
    imu = ImuIn(node, codec, config, skips, images.cameras)
    now = time.time_ns()
    images.cameras.on_camera_info(camera_info(codec, camera, now), None)
    _broadcast(images.cameras, tf_static(codec, _IDENTITY))
    imu.add(_imu(codec, now // 10**9 - 1, 0, imu_frame))
    return images, now


@pytest.mark.parametrize("empty", ["imu", "image"])
def test_an_empty_frame_id_is_said_to_need_the_rotation_flag_not_an_imu_message(
    empty: str, node: Node, codec: Codec, caplog: pytest.LogCaptureFixture
) -> None:
    # tf2 has no frame "": an IMU or images without a header.frame_id never get a rotation
    # from /tf_static. The line said it waited for "an IMU message on /imu/data to name the
    # IMU frame" while they arrived.
    images, now = _described_inputs(node, codec, "" if empty == "imu" else IMU_FRAME)
    image = codec.encode_image(
        now, "" if empty == "image" else IMAGE_FRAME, 64, 48, "mono8", bytes(64 * 48)
    )
    with caplog.at_level(logging.WARNING):
        images.handle(bytes(image), 1)
    waits = [r.getMessage() for r in caplog.records if "waiting for" in r.getMessage()]
    topic = "/imu/data" if empty == "imu" else "/cam/image_raw"
    assert len(waits) == 1, waits
    assert f"--imu-to-camera (the messages on {topic} name no frame" in waits[0], waits
    assert "an IMU message" not in waits[0] and "the transform from" not in waits[0]


def test_with_camera_info_off_the_wait_names_the_flag_that_gives_it(
    node: Node, codec: Codec, caplog: pytest.LogCaptureFixture
) -> None:
    config = Ros2Config(image_in="/cam/image_raw", camera_info="", imu_to_camera=_IDENTITY)
    images = ImagesIn(node, codec, config, _Skips(logging.getLogger("test")))
    with caplog.at_level(logging.WARNING):
        images.handle(_image(codec, time.time_ns(), 64, 48), 1)
    waits = [r.getMessage() for r in caplog.records if "waiting for" in r.getMessage()]
    assert len(waits) == 1 and "--camera-xml (CameraInfo is not read" in waits[0], waits
    assert "None" not in waits[0]


def test_camera_xml_and_the_rotation_flag_override_ros2(
    node: Node, codec: Codec, tmp_path: Path
) -> None:
    xml = CameraModel(64, 48, 50.0, 50.0, 32.0, 24.0)
    path = tmp_path / "camera.xml"
    path.write_bytes(xml.to_xml())
    flip = (1.0, 0.0, 0.0, 0.0, -1.0, 0.0, 0.0, 0.0, -1.0)
    config = Ros2Config(image_in="/cam/image_raw", camera_xml=path, imu_to_camera=flip)
    images = ImagesIn(node, codec, config, _Skips(logging.getLogger("test")))
    assert not images.cameras.wants_camera_info and not images.cameras.wants_tf
    found = images.cameras.for_image(IMAGE_FRAME, 64, 48, lambda r, d, n: None)
    assert found is not None and found.gyro_to_camera == flip and found.fx_px == 50.0


def _info_with(codec: Codec, binning: int = 1, **fields: Any) -> bytes:
    """A CameraInfo of a 320x240 camera (fx 300, fy 310) with ``fields`` replaced."""
    camera = CameraModel(320, 240, 300.0, 310.0, 160.0, 120.0)
    message = codec.store.deserialize_cdr(
        camera_info(codec, camera, 1, binning=binning), "sensor_msgs/msg/CameraInfo"
    )
    return bytes(
        codec.store.serialize_cdr(
            dataclasses.replace(message, **fields), "sensor_msgs/msg/CameraInfo"
        )
    )


def test_rectified_topics_read_p_and_binning_divides(codec: Codec) -> None:
    # P, of the rectified image, differs from K: another focal length and centre.
    p = np.array([500.0, 0, 330, 0, 0, 520, 250, 0, 0, 0, 1, 0])
    raw = _info_with(codec, binning=2, p=p)
    raw_k = intrinsics(codec, raw, rectified=False)
    assert (raw_k.width_px, raw_k.height_px) == (320, 240)
    assert (raw_k.fx_px, raw_k.fy_px, raw_k.cx_px, raw_k.cy_px) == (300, 310, 160, 120)
    rect = intrinsics(codec, raw, rectified=True)
    assert (rect.fx_px, rect.fy_px, rect.cx_px, rect.cy_px) == (250, 260, 165, 125)


@pytest.mark.parametrize(
    "k",
    [
        (1e300, 0, 160, 0, 300, 120, 0, 0, 1),
        (1e-300, 0, 160, 0, 300, 120, 0, 0, 1),
        (300, 0, -1e300, 0, 300, 120, 0, 0, 1),
        (300, 0, 160, 0, float("nan"), 120, 0, 0, 1),
    ],
)
def test_a_camera_info_with_absurd_intrinsics_is_refused(
    codec: Codec, k: tuple[float, ...]
) -> None:
    from services.nodes.ros2._cdr import CdrError

    raw = _info_with(codec, k=np.array(k, dtype=np.float64))
    with pytest.raises(CdrError, match="focal lengths"):
        intrinsics(codec, raw, rectified=False)


def test_one_future_stamp_does_not_poison_later_images(node: Node, codec: Codec) -> None:
    skips = _Skips(logging.getLogger("test"))
    images = ImagesIn(node, codec, Ros2Config(image_in="/cam"), skips)
    now = time.time_ns()
    images.handle(_image(codec, now + HOUR_NS, 8, 4), 1)
    images.handle(_image(codec, (2**31 - 1) * 10**9, 8, 4), 2)
    # Inside the 10 s a producer takes by default, but beyond the bridge's --max-ahead-ms:
    # accepted, it would hold back every later image for 9 s.
    images.handle(_image(codec, now + 9 * 10**9, 8, 4), 3)
    images.handle(_image(codec, now, 8, 4), 4)
    images.handle(_image(codec, now + 1_000_000, 8, 4), 5)
    assert skips.counts == {"future-stamp": 3}
    assert images.producer.info().puts == 2


def test_an_image_is_not_refused_for_the_sequence_number_its_attachment_says(
    node: Node, codec: Codec
) -> None:
    skips = _Skips(logging.getLogger("test"))
    images = ImagesIn(node, codec, Ros2Config(image_in="/cam"), skips)
    now = time.time_ns()
    for i, sequence in enumerate((-5, 2**63, 7)):  # no frame id, no frame id, one
        images.take(_image(codec, now + i * 1_000_000, 8, 4), sequence)
    assert skips.counts == {} and images.producer.info().puts == 3
    assert images.producer.info().rejected == 0


def test_imu_stamps_are_checked_field_by_field_and_a_future_one_does_not_poison(
    node: Node, codec: Codec
) -> None:
    skips = _Skips(logging.getLogger("test"))
    imu = ImuIn(node, codec, Ros2Config(imu_in="/imu"), skips)
    sec = time.time_ns() // 10**9
    imu.add(_imu(codec, sec + 3600, 0))  # an hour ahead
    imu.add(_imu(codec, 2**31 - 1, 0))  # 2038
    imu.add(_imu(codec, sec + 9, 0))  # inside a producer's default 10 s, not the bridge's 1 s
    imu.add(_imu(codec, sec - 2, 4_000_000_000))  # nanosec = 4e9 is no time (not +4 s)
    imu.add(_imu(codec, sec - 1, 0))
    imu.add(_imu(codec, sec - 1, 5_000_000))
    imu.flush()
    assert skips.counts == {"future-stamp": 3, "bad-stamp": 1}
    assert imu.stored == 2


def test_an_image_with_nanosec_beyond_a_second_is_a_bad_stamp(node: Node, codec: Codec) -> None:
    t = codec.store.types
    header = t["std_msgs/msg/Header"](
        t["builtin_interfaces/msg/Time"](time.time_ns() // 10**9 - 5, 4_000_000_000), "c"
    )
    raw = codec.store.serialize_cdr(
        t["sensor_msgs/msg/Image"](header, 4, 8, "mono8", 0, 8, np.zeros(32, dtype=np.uint8)),
        "sensor_msgs/msg/Image",
    )
    skips = _Skips(logging.getLogger("test"))
    images = ImagesIn(node, codec, Ros2Config(image_in="/cam"), skips)
    images.handle(bytes(raw), 1)
    assert skips.counts == {"bad-stamp": 1}


def test_the_example_camera_xml_is_what_the_optical_frame_convention_gives() -> None:
    from services.nodes.ros2._tf import StaticTransforms, Transform, rotation_from_quaternion
    from tests.conftest import REPO

    example = CameraModel.from_xml((REPO / "examples" / "ros2_camera.xml").read_bytes())
    tree = StaticTransforms()
    optical = rotation_from_quaternion(-0.5, 0.5, -0.5, 0.5)  # REP 103's optical frame
    identity = rotation_from_quaternion(0.0, 0.0, 0.0, 1.0)
    tree.update(
        b"urdf",
        [
            Transform("camera_link", "camera_optical_frame", optical),
            Transform("camera_link", "imu_link", identity),
        ],
    )
    rotation = tree.rotation("camera_optical_frame", "imu_link")
    assert rotation is not None
    assert np.allclose(rotation, example.gyro_to_camera)


def test_the_camera_info_topic_is_beside_the_image_topic_unless_told() -> None:
    import argparse

    from middleware import ConfigError
    from services.nodes.ros2._config import add_arguments, config_from_args

    parser = argparse.ArgumentParser()
    add_arguments(parser)

    def parse(*argv: str) -> Ros2Config:
        return config_from_args(parser.parse_args(list(argv)))

    found = parse("--image-in", "/robot/cam/image_rect", "--imu-to-camera", *"100010001")
    assert found.camera_info_topic == "/robot/cam/camera_info"
    assert found.imu_to_camera == (1.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0)
    assert parse("--image-in", "/image_raw").camera_info_topic == "/camera_info"
    assert parse("--image-in", "/c/image_raw", "--camera-info", "").camera_info_topic is None
    told = parse("--ros-namespace", "/r", "--image-in", "img", "--camera-info", "info")
    assert told.camera_info_topic == "/r/info"
    with pytest.raises(ConfigError, match="--imu-to-camera needs 9 numbers"):
        Ros2Config(imu_to_camera=(1.0, 0.0))
    # Refused at start, naming the flag (not later, blamed on ROS 2's camera description).
    with pytest.raises(ConfigError, match="--imu-to-camera must be a rotation matrix"):
        Ros2Config(imu_to_camera=(1.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 2.0))
    # The loop's flags without the loop: said, not silently ignored.
    with pytest.raises(ConfigError, match="--consumer-queue, --consumer-timeout-ms without"):
        parse("--image-out", "mediator/images=/x", "--consumer-queue", "3",
              "--consumer-timeout-ms", "500")  # fmt: skip


def test_tf_static_holds_bounded_bytes_and_counts_every_message_it_drops(codec: Codec) -> None:
    from collections import Counter

    from services.nodes.ros2._camera_info import TF_MAX_BYTES, TF_QUEUE

    cameras = CameraSource(
        codec,
        logging.getLogger("test"),
        image_topic="/cam/image_raw",
        info_topic="/cam/camera_info",
        imu_topic="/imu",
    )
    for _ in range(3):  # a peer's garbage of Zenoh's largest sizes: never held
        cameras.on_tf(bytes(TF_MAX_BYTES + 1), None)
    for _ in range(TF_QUEUE + 10):  # more than the queue holds: the oldest 10 dropped
        cameras.on_tf(b"garbage", None)
    counted: Counter[str] = Counter()

    def skip(reason: str, _detail: str, n: int) -> None:
        counted[reason] += n

    cameras.for_image(IMAGE_FRAME, 64, 48, skip)
    assert counted["tf-queue-full"] == 10
    assert counted["bad-tf"] == 3 + TF_QUEUE  # the oversize and the garbage read


def test_an_in_queue_is_bounded_in_bytes_as_well_as_in_messages() -> None:
    """IMU messages with a 2 MB frame_id, 2,048 of them queued, held 3.9 GB: the queue
    keeps at most its bytes too, dropping (and counting) the oldest; the newest stays even
    when it alone is larger."""
    from services.nodes.ros2._inputs import _InQueue

    overflows: list[int] = []
    queue = _InQueue(2048, 10_000, lambda: overflows.append(1))
    for _ in range(20):
        queue.put(bytes(2_000), None)
    assert len(overflows) == 15  # 5 of 2,000 B fit in 10,000
    queue.put(bytes(50_000), b"x")
    assert len(overflows) == 20
    item = queue.get(0)
    assert item is not None and len(item[0]) == 50_000
    assert queue.get(0) is None
    queue.put(bytes(9_000), None)  # the bytes taken out were given back
    assert len(overflows) == 20


def test_a_region_of_interest_far_off_the_sensor_is_refused(codec: Codec) -> None:
    from services.nodes.ros2._cdr import CdrError

    roi = codec.store.types["sensor_msgs/msg/RegionOfInterest"](2**32 - 1, 0, 240, 320, False)
    raw = _info_with(codec, roi=roi)
    with pytest.raises(CdrError, match="region of interest"):
        intrinsics(codec, raw, rectified=False)


def test_k0_zero_is_uncalibrated_for_a_rectified_topic_too(codec: Codec) -> None:
    from services.nodes.ros2._camera_info import Uncalibrated

    # K zero (uncalibrated, as image_proc reads it), a P left over from elsewhere.
    raw = _info_with(codec, k=np.zeros(9))
    with pytest.raises(Uncalibrated, match=r"K\[0\] is 0"):
        intrinsics(codec, raw, rectified=True)


@pytest.mark.parametrize("frame", ["camera_link", IMAGE_FRAME])
def test_images_stamped_outside_an_optical_frame_are_said_once_to_turn_the_blur_axes(
    frame: str, node: Node, codec: Codec, caplog: pytest.LogCaptureFixture
) -> None:
    # A driver stamping its images in the camera's body frame (x forward) got the rotation
    # into that frame from /tf_static, and the blur about the wrong axes, without a word.
    images, now = _described_inputs(node, codec)
    with caplog.at_level(logging.WARNING):
        for i in range(3):
            image = codec.encode_image(now + i, frame, 64, 48, "mono8", bytes(64 * 48))
            images.handle(bytes(image), i + 1)
    said = [r.getMessage() for r in caplog.records if "optical frame" in r.getMessage()]
    if frame == IMAGE_FRAME:
        assert said == []
    else:
        assert len(said) == 1, said
        assert "stamped in frame 'camera_link'" in said[0] and "--imu-to-camera" in said[0]
    [element, *_] = answered(lambda: node.query("ros2/images"), "ros2/images")
    assert read_frame_metadata(element.metadata).camera is not None  # described either way


def test_images_of_a_new_size_with_a_stale_camera_info_go_on_without_a_description(
    node: Node, codec: Codec
) -> None:
    # The driver binned its images (64x48 -> 32x24) and still sends the old CameraInfo with
    # each. That CameraInfo is the counted skip; the images are fine and go on without a
    # description, as when no CameraInfo had ever matched. The 64x48 intrinsics taken
    # before stayed, and every image was dropped as ``camera-mismatch``.
    images, now = _described_inputs(node, codec)
    images.handle(_image(codec, now, 64, 48), 1)
    camera = CameraModel(64, 48, 50.0, 50.0, 32.0, 24.0)
    for i in range(1, 4):
        images.cameras.on_camera_info(camera_info(codec, camera, now + i * 1000), None)
        images.handle(_image(codec, now + i * 1000, 32, 24), i + 1)
    info = images.producer.info()
    assert info.puts == 4, info.skipped
    assert info.skipped == {"camera-info-mismatch": 3}


def test_a_rectified_topic_turns_the_tf_rotation_by_the_camera_infos_r(codec: Codec) -> None:
    """A stereo pair's rectified images are rotated by R from the camera frame their header
    names: the blur must be estimated about the rectified axes (v_rect = R R_tf v_imu)."""
    imu_to_camera = tuple(Rotation.from_euler("xyz", [0.3, -0.2, 0.1]).as_matrix().reshape(-1))
    r = Rotation.from_euler("y", 0.05).as_matrix()  # a typical small stereo rectification

    def described(topic: str, r_values: np.ndarray) -> CameraModel:
        raw = _info_with(codec, r=r_values.reshape(-1))
        cameras = CameraSource(
            codec, logging.getLogger("test"), image_topic=topic, info_topic="/i", imu_topic="/m"
        )
        for broadcast in tf_static(codec, imu_to_camera).values():
            cameras.on_tf(broadcast, None)
        cameras.on_camera_info(raw, None)
        cameras.set_imu_frame(IMU_FRAME)
        found = cameras.for_image(IMAGE_FRAME, 320, 240, lambda r, d, n: None)
        assert found is not None
        return found

    tf = np.asarray(imu_to_camera).reshape(3, 3)
    rect = described("/stereo/left/image_rect", r)
    assert np.allclose(np.asarray(rect.gyro_to_camera).reshape(3, 3), r @ tf, atol=1e-9)
    # A raw topic's images are not rectified, and a monocular R (identity, or left all
    # zeros by some drivers) turns nothing.
    for topic, r_values in (
        ("/stereo/left/image_raw", r),
        ("/cam/image_rect", np.eye(3)),
        ("/cam/image_rect", np.zeros((3, 3))),
    ):
        found = described(topic, r_values)
        assert np.allclose(np.asarray(found.gyro_to_camera).reshape(3, 3), tf, atol=1e-9), topic


def test_a_rectification_r_that_is_no_rotation_is_a_bad_camera_info(codec: Codec) -> None:
    from services.nodes.ros2._cdr import CdrError

    raw = _info_with(codec, r=np.full(9, float("nan")))
    with pytest.raises(CdrError, match="rectification"):
        intrinsics(codec, raw, rectified=True)
    assert intrinsics(codec, raw, rectified=False).rectification is None  # not used there
