"""Nothing missed without a count: a running bridge (real Zenoh sessions) and ROS 2 camera
publishers played with plain Zenoh as rmw_zenoh makes them. Every sequence number of a
publisher that starts after the bridge is either stored or counted as lost in transport; a
publisher that was there before the bridge is counted from its first sample seen."""

from __future__ import annotations

import json
import logging
import threading
import time
from collections.abc import Iterator
from typing import Any

import pytest
import zenoh

from middleware import FramegateError, NetworkConfig, Node
from services.nodes.ros2._bridge import run
from services.nodes.ros2._cdr import IMAGE, Codec
from services.nodes.ros2._config import Ros2Config
from services.nodes.ros2._rmw import (
    Attachment,
    EntityKind,
    NodeIdentity,
    Qos,
    data_key,
    gid,
    type_hash,
)
from tests.conftest import free_port, wait_until

pytestmark = pytest.mark.integration

TOPIC = "/camera/image_raw"


class _Lines(logging.Handler):
    def __init__(self) -> None:
        super().__init__()
        self.lines: list[str] = []

    def emit(self, record: logging.LogRecord) -> None:
        self.lines.append(record.getMessage())


def _config(mode: str, endpoint: str, *, listen: bool) -> zenoh.Config:
    conf = zenoh.Config()
    values: dict[str, Any] = {"mode": mode, "scouting/multicast/enabled": False}
    values["listen/endpoints" if listen else "connect/endpoints"] = [endpoint]
    if not listen:
        values["listen/endpoints"] = ["tcp/127.0.0.1:0"]
    for key, value in values.items():
        conf.insert_json5(key, json.dumps(value))
    return conf


class Driver:
    """One camera driver node with one image publisher (its token, its numbers)."""

    def __init__(self, session: zenoh.Session, codec: Codec, name: str) -> None:
        hash_chunk = type_hash(codec.rihs01(IMAGE), "jazzy")
        node = NodeIdentity(0, str(session.info.zid()), name)
        token = node.endpoint_token(
            1, EntityKind.PUBLISHER, TOPIC, IMAGE, hash_chunk, Qos.sensor_data()
        )
        self._token = session.liveliness().declare_token(token)
        self._publisher = session.declare_publisher(data_key(0, TOPIC, IMAGE, hash_chunk))
        self._gid, self._codec = gid(token), codec

    def publish(self, sequence: int) -> None:
        cdr = self._codec.encode_image(time.time_ns(), "camera", 8, 4, "mono8", bytes(32))
        attachment = Attachment(sequence, time.time_ns(), self._gid).encode()
        self._publisher.put(cdr, attachment=attachment)

    def close(self) -> None:
        self._token.undeclare()
        self._publisher.undeclare()


@pytest.fixture
def router() -> Iterator[tuple[zenoh.Session, str]]:
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    with zenoh.open(_config("router", endpoint, listen=True)) as session:
        yield session, endpoint


def test_a_publisher_started_after_the_bridge_has_every_number_stored_or_counted(
    router: tuple[zenoh.Session, str], endpoint: str
) -> None:
    session, ros_endpoint = router
    codec = Codec("jazzy")
    before = Driver(session, codec, "old_driver")  # there before the bridge
    lines = _Lines()
    logging.getLogger("framegate.ros2").addHandler(lines)
    stop = threading.Event()
    config = Ros2Config(ros_connect=(ros_endpoint,), image_in=TOPIC, camera_info="", in_depth=16)
    bridge = threading.Thread(target=run, args=(config, NetworkConfig(listen=(endpoint,)), stop))
    bridge.start()
    try:
        with Node(network=NetworkConfig(connect=(endpoint,))) as client:

            def counted() -> tuple[int, int]:
                try:
                    info = client.buffer_info("ros2/images", timeout_s=2.0)
                except FramegateError:
                    return (0, 0)
                return info.puts, info.skipped.get("lost-in-transport", 0)

            wait_until(lambda: any("ROS graph taken" in m for m in lines.lines), 60, "the graph")
            before.publish(1000)  # its first sample seen: counting starts, nothing lost
            wait_until(lambda: counted()[0] >= 1, 30, "the old driver's image")
            with zenoh.open(_config("peer", ros_endpoint, listen=False)) as late:
                driver = Driver(late, codec, "new_driver")
                # Its first two samples never left (as when a new session does not know the
                # bridge's subscription yet); the next are sent at once, as a driver does.
                for sequence in range(3, 7):
                    driver.publish(sequence)
                puts, lost = wait_until(
                    lambda: (c := counted())[0] + c[1] >= 1 + 6 and c, 30, "every number"
                )
                driver.close()
        assert lost >= 2
        assert puts + lost == 1 + 6  # numbers 1..6 of the new driver, stored or counted
    finally:
        stop.set()
        bridge.join(10)
        logging.getLogger("framegate.ros2").removeHandler(lines)
        before.close()
    assert not bridge.is_alive()
