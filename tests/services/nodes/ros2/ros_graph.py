"""ROS 2 drivers and a ROS 2 router (``rmw_zenohd``) played with plain Zenoh, as rmw_zenoh
makes them, for tests of a running bridge."""

from __future__ import annotations

import contextlib
import json
import logging
import time
from collections.abc import Iterator
from typing import Any

import zenoh

from services.nodes.ros2._cdr import IMAGE, Codec
from services.nodes.ros2._rmw import (
    Attachment,
    EntityKind,
    NodeIdentity,
    Qos,
    data_key,
    gid,
    type_hash,
)
from tests.conftest import free_port

TOPIC = "/camera/image_raw"


class Lines(logging.Handler):
    def __init__(self) -> None:
        super().__init__()
        self.lines: list[str] = []

    def emit(self, record: logging.LogRecord) -> None:
        self.lines.append(record.getMessage())


def zenoh_config(mode: str, endpoint: str, *, listen: bool) -> zenoh.Config:
    conf = zenoh.Config()
    values: dict[str, Any] = {"mode": mode, "scouting/multicast/enabled": False}
    values["listen/endpoints" if listen else "connect/endpoints"] = [endpoint]
    if not listen:
        values["listen/endpoints"] = ["tcp/127.0.0.1:0"]
    for key, value in values.items():
        conf.insert_json5(key, json.dumps(value))
    return conf


class Driver:
    """One driver node with one publisher (its token, its numbers)."""

    def __init__(
        self,
        session: zenoh.Session,
        codec: Codec,
        name: str,
        topic: str = TOPIC,
        ros_type: str = IMAGE,
    ) -> None:
        hash_chunk = type_hash(codec.rihs01(ros_type), "jazzy")
        node = NodeIdentity(0, str(session.info.zid()), name)
        token = node.endpoint_token(
            1, EntityKind.PUBLISHER, topic, ros_type, hash_chunk, Qos.sensor_data()
        )
        self._token = session.liveliness().declare_token(token)
        self._publisher = session.declare_publisher(data_key(0, topic, ros_type, hash_chunk))
        self._gid, self._codec = gid(token), codec
        self.sequence = 0  # the last number published

    def publish(self, sequence: int | None = None, cdr: bytes | None = None) -> None:
        """One sample (an 8x4 image stamped now unless ``cdr``), numbered ``sequence`` or
        the next number."""
        self.sequence = sequence if sequence is not None else self.sequence + 1
        if cdr is None:
            cdr = self._codec.encode_image(time.time_ns(), "camera", 8, 4, "mono8", bytes(32))
        attachment = Attachment(self.sequence, time.time_ns(), self._gid).encode()
        self._publisher.put(cdr, attachment=attachment)

    def close(self) -> None:
        self._token.undeclare()
        self._publisher.undeclare()


@contextlib.contextmanager
def ros_router() -> Iterator[tuple[zenoh.Session, str]]:
    """A Zenoh router standing in for rmw_zenohd, and its endpoint."""
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    with zenoh.open(zenoh_config("router", endpoint, listen=True)) as session:
        yield session, endpoint
