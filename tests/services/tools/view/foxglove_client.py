"""A minimal Foxglove WebSocket client, as the Foxglove app speaks to foxglove-sdk servers.

Subprotocol ``foxglove.sdk.v1``: the server sends ``serverInfo`` and ``advertise`` (JSON
text); the client sends ``subscribe``; the server sends binary *message data* frames:
opcode 1, subscription id (uint32 LE), log time (uint64 LE ns), then the message. Protobuf
messages are decoded with the FileDescriptorSet the channel advertised (base64), exactly as
a client that knows nothing else would.
"""

from __future__ import annotations

import base64
import json
import re
import struct
import time
from dataclasses import dataclass
from typing import Any

from google.protobuf import descriptor_pb2, descriptor_pool, message_factory
from websockets.sync.client import ClientConnection, connect
from websockets.typing import Subprotocol

from tests.helpers.timing import scaled

SUBPROTOCOL = Subprotocol("foxglove.sdk.v1")
MESSAGE_DATA = 1
# foxglove-sdk (0.30) sends a channel's advertisement to a client *before* it records the
# channel for that client (connected_client.rs, advertise_channels): a subscribe that arrives
# in between is refused with "Unknown channel ID: N". A client that subscribes the moment it
# sees a channel leaves the server this long first, and subscribes again if refused.
ADVERTISE_SETTLE_S = 0.2
_UNKNOWN = re.compile(r"Unknown channel ID: (\d+)")


@dataclass(frozen=True)
class Received:
    topic: str
    log_time_ns: int
    received_ns: int
    message: Any  # a protobuf message, or a dict for JSON channels


class FoxgloveClient:
    def __init__(self, url: str, *, max_queue: int | None = 64, keepalive: bool = True) -> None:
        # ``keepalive=False`` for a client meant to stall: with websockets' keepalive pings a
        # client that stops reading closes its own connection about 40 s later (ping every
        # 20 s, 20 s for the pong it never reads), turning "stalled" into "gone".
        opened = connect(
            url,
            subprotocols=[SUBPROTOCOL],
            max_size=None,
            max_queue=max_queue,
            compression=None,
            ping_interval=20 if keepalive else None,
        )
        self.ws: ClientConnection = opened.__enter__()  # closed by close()
        self.server_info: dict[str, Any] = {}
        self.channels: dict[str, dict[str, Any]] = {}  # topic → advertised channel
        self._subs: dict[int, dict[str, Any]] = {}
        self._classes: dict[int, Any] = {}

    def _handle_text(self, text: str) -> None:
        body = json.loads(text)
        if body["op"] == "serverInfo":
            self.server_info = body
        elif body["op"] == "advertise":
            for channel in body["channels"]:
                self.channels[channel["topic"]] = channel
        elif body["op"] == "status" and (refused := _UNKNOWN.search(body.get("message", ""))):
            again = [
                {"id": sub_id, "channelId": channel["id"]}
                for sub_id, channel in self._subs.items()
                if channel["id"] == int(refused.group(1))
            ]
            if again:
                time.sleep(ADVERTISE_SETTLE_S)
                self.ws.send(json.dumps({"op": "subscribe", "subscriptions": again}))

    def wait_for_topics(self, topics: set[str], timeout_s: float) -> None:
        deadline = time.monotonic() + scaled(timeout_s)
        while not topics <= set(self.channels):
            remaining = deadline - time.monotonic()
            if remaining <= 0:
                raise AssertionError(f"not advertised: {topics - set(self.channels)}")
            try:
                frame = self.ws.recv(timeout=remaining)
            except TimeoutError:
                continue
            if isinstance(frame, str):
                self._handle_text(frame)

    def subscribe(self, topics: list[str]) -> None:
        time.sleep(ADVERTISE_SETTLE_S)  # see ADVERTISE_SETTLE_S
        requests = []
        for topic in topics:
            channel = self.channels[topic]
            sub_id = len(self._subs) + 1
            self._subs[sub_id] = channel
            requests.append({"id": sub_id, "channelId": channel["id"]})
        self.ws.send(json.dumps({"op": "subscribe", "subscriptions": requests}))

    def _decode(self, channel: dict[str, Any], data: bytes) -> Any:
        if channel["encoding"] == "json":
            return json.loads(data)
        assert channel["encoding"] == "protobuf", channel
        cls = self._classes.get(channel["id"])
        if cls is None:
            files = descriptor_pb2.FileDescriptorSet.FromString(base64.b64decode(channel["schema"]))
            pool = descriptor_pool.DescriptorPool()
            for proto in files.file:
                pool.Add(proto)
            cls = message_factory.GetMessageClass(pool.FindMessageTypeByName(channel["schemaName"]))
            self._classes[channel["id"]] = cls
        return cls.FromString(data)

    def receive(self, timeout_s: float) -> Received | None:
        """The next message data frame (control messages are handled on the way)."""
        deadline = time.monotonic() + scaled(timeout_s)
        while (remaining := deadline - time.monotonic()) > 0:
            try:
                frame = self.ws.recv(timeout=remaining)
            except TimeoutError:
                return None
            if isinstance(frame, str):
                self._handle_text(frame)
                continue
            received_ns = time.time_ns()
            assert frame[0] == MESSAGE_DATA, frame[:1]
            sub_id, log_time = struct.unpack_from("<IQ", frame, 1)
            channel = self._subs[sub_id]
            message = self._decode(channel, bytes(frame[13:]))
            return Received(channel["topic"], log_time, received_ns, message)
        return None

    def close(self) -> None:
        self.ws.close()


def stamp_ns(message: Any) -> int:
    """A Foxglove message's ``timestamp`` field in ns."""
    return int(message.timestamp.seconds) * 1_000_000_000 + int(message.timestamp.nanos)
