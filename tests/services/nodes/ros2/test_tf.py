"""Rotations between frames from /tf_static, as tf2 composes them."""

from __future__ import annotations

import logging
import math

import numpy as np
import pytest

from services.nodes.ros2._camera_info import (
    TF_BYTES_PER_IMAGE,
    TF_MAX_BYTES,
    TF_MESSAGE,
    TF_QUEUE,
    CameraSource,
)
from services.nodes.ros2._cdr import Codec
from services.nodes.ros2._rmw import Attachment
from services.nodes.ros2._tf import (
    MAX_BROADCASTERS,
    MAX_CHAIN,
    MAX_FRAMES,
    StaticTransforms,
    Transform,
    rotation_from_quaternion,
)
from tests.services.nodes.ros2.ros_graph import Lines


def _about(axis: str, angle: float) -> tuple[float, ...]:
    s = math.sin(angle / 2)
    x, y, z = (s if axis == a else 0.0 for a in "xyz")
    return rotation_from_quaternion(x, y, z, math.cos(angle / 2))


def _matrix(values: tuple[float, ...] | None) -> np.ndarray:
    assert values is not None
    return np.asarray(values).reshape(3, 3)


def test_a_quaternion_turns_child_vectors_into_the_parent_frame() -> None:
    # 90 degrees about z: the child's x axis is the parent's y axis.
    r = _matrix(_about("z", math.pi / 2))
    assert np.allclose(r @ [1, 0, 0], [0, 1, 0])
    with pytest.raises(ValueError, match="not a rotation"):
        rotation_from_quaternion(0.0, 0.0, 0.0, 0.0)
    with pytest.raises(ValueError, match="not a rotation"):
        rotation_from_quaternion(math.nan, 0.0, 0.0, 1.0)


def test_a_two_link_chain_composes_to_the_rotation_between_its_ends() -> None:
    tree = StaticTransforms()
    tree.update(
        b"robot",
        [
            Transform("base_link", "camera_link", _about("z", 0.3)),
            Transform("camera_link", "/camera_optical_frame", _about("x", -math.pi / 2)),
        ],
    )
    tree.update(b"imu", [Transform("base_link", "imu_link", _about("y", 0.2))])
    # v_camera = R v_imu = (R_base_cam)^T R_base_imu v_imu
    base_cam = _matrix(_about("z", 0.3)) @ _matrix(_about("x", -math.pi / 2))
    expected = base_cam.T @ _matrix(_about("y", 0.2))
    assert np.allclose(_matrix(tree.rotation("camera_optical_frame", "imu_link")), expected)
    assert np.allclose(_matrix(tree.rotation("imu_link", "/camera_optical_frame")), expected.T)
    assert tree.rotation("camera_optical_frame", "gps") is None


def test_a_broadcasters_later_message_replaces_its_transform_of_the_same_child() -> None:
    tree = StaticTransforms()
    tree.update(b"a", [Transform("base", "imu", _about("z", 0.1))])
    tree.update(b"b", [Transform("base", "cam", _about("z", 0.0))])
    tree.update(b"a", [Transform("base", "imu", _about("z", 0.5))])
    assert np.allclose(_matrix(tree.rotation("cam", "imu")), _matrix(_about("z", 0.5)))
    tree.update(b"a", [])  # says nothing about imu: tf2 forgets no static transform
    assert np.allclose(_matrix(tree.rotation("cam", "imu")), _matrix(_about("z", 0.5)))


def test_one_broadcasters_transforms_sent_in_separate_messages_all_count() -> None:
    # rclpy's StaticTransformBroadcaster publishes each sendTransform call alone: a Python
    # node sending the camera's link, then its IMU mount, gave a tree without the camera.
    tree = StaticTransforms()
    tree.update(b"py", [Transform("base_link", "camera_link", _about("z", 0.3))])
    tree.update(b"py", [Transform("camera_link", "camera_optical_frame", _about("x", -1.0))])
    tree.update(b"py", [Transform("base_link", "imu_link", _about("y", 0.2))])
    base_cam = _matrix(_about("z", 0.3)) @ _matrix(_about("x", -1.0))
    expected = base_cam.T @ _matrix(_about("y", 0.2))
    assert np.allclose(_matrix(tree.rotation("camera_optical_frame", "imu_link")), expected)


def test_the_transform_of_a_child_heard_last_wins_whoever_sent_it() -> None:
    tree = StaticTransforms()
    tree.update(b"a", [Transform("base", "imu", _about("z", 0.1))])
    tree.update(b"b", [Transform("base", "imu", _about("z", 0.5))])
    tree.update(b"a", [Transform("base", "cam", _about("z", 0.0))])  # a heard last, not of imu
    assert np.allclose(_matrix(tree.rotation("cam", "imu")), _matrix(_about("z", 0.5)))


def test_a_broadcaster_keeps_at_most_max_frames_transforms_its_newest() -> None:
    identity = (1.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0)
    tree = StaticTransforms()
    for i in range(MAX_FRAMES + 1):  # one message each: all merged, the first forgotten
        tree.update(b"a", [Transform("root", f"c{i}", identity)])
    assert tree.rotation("c0", "root") is None
    assert tree.rotation("c1", "root") == identity
    assert tree.rotation(f"c{MAX_FRAMES}", "root") == identity


def test_a_cycle_of_transforms_ends_the_walk() -> None:
    tree = StaticTransforms()
    tree.update(
        b"a",
        [Transform("a", "b", _about("z", 0.1)), Transform("b", "a", _about("z", 0.1))],
    )
    assert tree.rotation("a", "c") is None


@pytest.mark.parametrize(
    "q",
    [(1e-6, 0.0, 0.0, 0.0), (0.0, 0.0, 0.0, 0.0), (2.0, 0.0, 0.0, 0.0), (math.nan, 0.0, 0.0, 1.0)],
)
def test_a_quaternion_that_is_not_of_unit_length_is_no_rotation(
    q: tuple[float, float, float, float],
) -> None:
    with pytest.raises(ValueError, match="not a rotation"):
        rotation_from_quaternion(*q)
    # Rounding in a message is normalized away, as tf2 does.
    assert _matrix(rotation_from_quaternion(0.0, 0.0, 0.0, 1.004)) == pytest.approx(np.eye(3))


def test_a_frame_named_with_megabytes_and_control_characters_is_one_short_log_line() -> None:
    log = logging.getLogger("test.camera_source")
    lines = Lines()
    log.addHandler(lines)
    try:
        cameras = CameraSource(
            Codec("jazzy"), log, image_topic="/camera/image_raw", info_topic=None, imu_topic="/imu"
        )
        cameras.set_imu_frame("imu\nWARNING forged line")
        skipped: list[str] = []
        name = "camera\n\x1b[31m" + "x" * 1_000_000
        assert cameras.for_image(name, 8, 4, lambda r, d, n: skipped.append(r)) is None
    finally:
        log.removeHandler(lines)
    assert len(lines.lines) == 1
    assert "\n" not in lines.lines[0] and "\x1b" not in lines.lines[0]
    assert len(lines.lines[0]) < 2_000


def test_a_tf_static_flood_costs_each_image_a_bounded_decode() -> None:
    codec = Codec("jazzy")
    t = codec.store.types

    def stamped(parent: str, child: str) -> object:
        return t["geometry_msgs/msg/TransformStamped"](
            header=t["std_msgs/msg/Header"](t["builtin_interfaces/msg/Time"](0, 0), parent),
            child_frame_id=child,
            transform=t["geometry_msgs/msg/Transform"](
                translation=t["geometry_msgs/msg/Vector3"](0.0, 0.0, 0.0),
                rotation=t["geometry_msgs/msg/Quaternion"](0.0, 0.0, 0.0, 1.0),
            ),
        )

    chain = [stamped(f"f{i}", f"f{i + 1}") for i in range(2000)]
    raw = bytes(codec.store.serialize_cdr(t[TF_MESSAGE](transforms=chain), TF_MESSAGE))
    assert TF_BYTES_PER_IMAGE < 2 * len(raw) <= 2 * TF_MAX_BYTES
    cameras = CameraSource(
        codec, logging.getLogger("test.tf_flood"), image_topic="/i", info_topic=None, imu_topic="/m"
    )
    for broadcaster in range(TF_QUEUE):
        cameras.on_tf(raw, Attachment(1, 1, bytes([broadcaster]) * 16).encode())
    images = 0
    while cameras._tf_raw:
        before = len(cameras._tf_raw)
        cameras.for_image("camera", 8, 4, lambda r, d, n: None)
        images += 1
        assert before - len(cameras._tf_raw) == 1  # one such message per image, not all
    assert images == TF_QUEUE


def test_a_chain_longer_than_any_robots_connects_nothing() -> None:
    identity = (1.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0)
    tree = StaticTransforms()
    # A peer's 262,144-link chain, spread over every broadcaster slot.
    for b in range(MAX_BROADCASTERS):
        links = range(b * MAX_FRAMES, (b + 1) * MAX_FRAMES)
        tree.update(
            b.to_bytes(16, "little"), [Transform(f"n{i}", f"n{i + 1}", identity) for i in links]
        )
    assert tree.rotation(f"n{MAX_BROADCASTERS * MAX_FRAMES}", "n0") is None
    assert tree.rotation(f"n{MAX_CHAIN}", "n0") == identity  # a chain within the bound


def test_a_transform_that_is_no_rotation_leaves_out_itself_not_its_messages_others() -> None:
    # tf2 refuses a denormalized quaternion per transform; the bridge refused the whole
    # message, so one bad mount in robot_state_publisher's message hid the camera's chain.
    codec = Codec("jazzy")
    t = codec.store.types

    def stamped(parent: str, child: str, q: tuple[float, float, float, float]) -> object:
        return t["geometry_msgs/msg/TransformStamped"](
            header=t["std_msgs/msg/Header"](t["builtin_interfaces/msg/Time"](0, 0), parent),
            child_frame_id=child,
            transform=t["geometry_msgs/msg/Transform"](
                translation=t["geometry_msgs/msg/Vector3"](0.0, 0.0, 0.0),
                rotation=t["geometry_msgs/msg/Quaternion"](*q),
            ),
        )

    half = math.sqrt(0.5)
    message = t[TF_MESSAGE](
        transforms=[
            stamped("base_link", "imu_link", (0.0, 0.0, 0.0, 1.0)),
            stamped("base_link", "lidar", (0.0, 0.0, 0.0, 0.0)),  # no rotation
            stamped("base_link", "camera_optical_frame", (0.0, 0.0, half, half)),
        ]
    )
    cameras = CameraSource(
        codec, logging.getLogger("test.tf_bad"), image_topic="/i", info_topic=None, imu_topic="/m"
    )
    cameras.on_tf(bytes(codec.store.serialize_cdr(message, TF_MESSAGE)), None)
    cameras.set_imu_frame("imu_link")
    skipped: list[tuple[str, int]] = []
    cameras.for_image("camera_optical_frame", 8, 4, lambda r, d, n: skipped.append((r, n)))
    assert skipped == [("bad-tf", 1)]
    expected = _matrix(_about("z", math.pi / 2)).T  # v_camera = R_base_cam^T v_base
    assert np.allclose(_matrix(cameras._tf.rotation("camera_optical_frame", "imu_link")), expected)
