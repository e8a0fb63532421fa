"""One bad stamp cannot poison the bridge: a real ``framegate run ros2`` process and ROS 2
camera and IMU publishers played with plain Zenoh. An image and an IMU sample stamped an
hour ahead, one in 2038 (``sec = 2**31 - 1``) and one with ``nanosec = 4e9`` are counted
skips; every good message after them is stored."""

from __future__ import annotations

import subprocess
import sys
import time
from collections.abc import Iterator

import numpy as np
import pytest
import zenoh

from middleware import FramegateError, NetworkConfig, Node
from services.nodes.ros2._cdr import IMAGE, IMU, Codec
from tests.conftest import REPO, child_env, wait_until
from tests.services.nodes.ros2.ros_graph import TOPIC, Driver, ros_router

pytestmark = pytest.mark.integration

IMU_TOPIC = "/imu/data"


def _image(codec: Codec, sec: int, nanosec: int) -> bytes:
    t = codec.store.types
    header = t["std_msgs/msg/Header"](t["builtin_interfaces/msg/Time"](sec, nanosec), "camera")
    message = t[IMAGE](header, 4, 8, "mono8", 0, 8, np.zeros(32, dtype=np.uint8))
    return bytes(codec.store.serialize_cdr(message, IMAGE))


def _imu(codec: Codec, sec: int, nanosec: int) -> bytes:
    t = codec.store.types
    v, z = t["geometry_msgs/msg/Vector3"], np.zeros(9)
    message = t[IMU](
        t["std_msgs/msg/Header"](t["builtin_interfaces/msg/Time"](sec, nanosec), "imu"),
        t["geometry_msgs/msg/Quaternion"](0, 0, 0, 1),
        z,
        v(0.0, 0.0, 0.1),
        z,
        v(0, 0, 0),
        z,
    )
    return bytes(codec.store.serialize_cdr(message, IMU))


@pytest.fixture
def router() -> Iterator[tuple[zenoh.Session, str]]:
    with ros_router() as found:
        yield found


def test_a_future_or_impossible_stamp_does_not_poison_the_bridge(
    router: tuple[zenoh.Session, str], endpoint: str
) -> None:
    session, ros_endpoint = router
    codec = Codec("jazzy")
    camera = Driver(session, codec, "camera_driver")
    imu = Driver(session, codec, "imu_driver", IMU_TOPIC, IMU)
    proc = subprocess.Popen(
        [
            *(sys.executable, "-m", "services.cli", "run", "ros2", "--listen", endpoint),
            *("--ros-connect", ros_endpoint, "--image-in", TOPIC, "--imu-in", IMU_TOPIC),
            *("--camera-info", "", "--gyro-batch", "1", "--in-depth", "16"),
        ],
        cwd=REPO,
        env=child_env(),
        stdout=subprocess.DEVNULL,
        stderr=subprocess.DEVNULL,
    )
    try:
        with Node(network=NetworkConfig(connect=(endpoint,))) as client:

            def info(buffer: str) -> tuple[int, dict[str, int]]:
                try:
                    found = client.buffer_info(buffer, timeout_s=2.0)
                except FramegateError:
                    return 0, {}
                return found.puts, dict(found.skipped)

            def subscribed() -> bool:
                tokens = [
                    str(r.ok.key_expr)
                    for r in session.liveliness().get("@ros2_lv/0/**")
                    if r.ok is not None
                ]
                return sum("/MS/" in t and "framegate_bridge" in t for t in tokens) >= 2

            wait_until(lambda: subscribed() and info("ros2/images")[1] == {}, 60, "the bridge")
            sec = time.time_ns() // 10**9
            bad = ((sec + 3600, 0), (2**31 - 1, 0), (sec - 3, 4_000_000_000))
            good = [(sec - 2, i * 10_000_000) for i in range(5)]
            for when in (*bad, *good):
                camera.publish(cdr=_image(codec, *when))
                imu.publish(cdr=_imu(codec, *when))
                time.sleep(0.02)  # a driver's pace: nothing dropped for a full in-queue
            expected = {"future-stamp": 2, "bad-stamp": 1}
            for buffer in ("ros2/images", "ros2/rates"):
                puts, skipped = wait_until(
                    lambda b=buffer: (i := info(b))[0] + sum(i[1].values()) >= 8 and i,
                    30,
                    f"every {buffer} message stored or counted",
                )
                assert (puts, skipped) == (len(good), expected), buffer
    finally:
        proc.terminate()
        proc.wait(timeout=10)
        camera.close()
        imu.close()
