"""A ROS 2 vision node played with plain Zenoh, as rmw_zenoh's nodes speak (no ROS 2 needed).

``python -m services.evidence.bench._ros2_node PARAMS_JSON`` declares a node (liveliness
tokens, a subscription on ``image_topic`` with a KEEP_LAST queue of ``depth``, a publisher
on ``result_topic``) and, per image, holds the processor for ``service_time_s`` (or longer
if the work takes longer), then publishes one result carrying the image's ``header``, as
vision_msgs detectors do. With ``detect`` it runs framegate's own marker detector on the
image and the result is a ``vision_msgs/msg/Detection2DArray`` (one detection per marker,
class id = marker id); otherwise it is ``result_type`` (``pkg/msg/Name``, any name: its
CDR is the header followed by a uint32 count of images seen, and its type hash
``result_hash``), to show that the bridge needs nothing but the header. ``answer: false``
never answers.

It prints one JSON line per event on stdout: ``{"ready": true}``, then ``{"received":
stamp_ns}`` per image as it arrives and ``{"answered": stamp_ns, "markers": [...]}`` per
result, until stdin closes or SIGTERM. The bridge's loop benchmark and the bridge's tests use it.
"""

from __future__ import annotations

import _thread
import collections
import json
import signal
import struct
import sys
import threading
import time
from typing import Any

import zenoh

from services.nodes.ros2._cdr import DETECTIONS, IMAGE, Codec
from services.nodes.ros2._consumer import decode_header
from services.nodes.ros2._rmw import (
    Attachment,
    EntityKind,
    NodeIdentity,
    Qos,
    Reliability,
    data_key,
    gid,
    type_hash,
)

_lock = threading.Lock()


def _emit(**fields: Any) -> None:
    with _lock:
        print(json.dumps(fields), flush=True)


def _header_cdr(stamp_ns: int, frame_id: str, extra: int) -> bytes:
    """A little-endian CDR message: std_msgs/Header, then one uint32."""
    text = frame_id.encode() + b"\0"
    body = struct.pack("<iII", stamp_ns // 10**9, stamp_ns % 10**9, len(text)) + text
    body += b"\0" * (-len(body) % 4) + struct.pack("<I", extra)
    return b"\x00\x01\x00\x00" + body


def _config(params: dict[str, Any]) -> zenoh.Config:
    conf = zenoh.Config()
    for key, value in {
        "mode": "peer",
        "connect/endpoints": [params["connect"]],
        "listen/endpoints": ["tcp/127.0.0.1:0"],
        "scouting/multicast/enabled": False,
    }.items():
        conf.insert_json5(key, json.dumps(value))
    return conf


def main(params: dict[str, Any]) -> None:
    codec = Codec("jazzy")
    detect = bool(params.get("detect", False))
    answer = bool(params.get("answer", True))
    service_s = float(params.get("service_time_s", 0.0))
    depth = int(params.get("depth", 10))
    if detect:
        result_type, result_hash = DETECTIONS, codec.rihs01(DETECTIONS)
    else:
        result_type = str(params.get("result_type", "my_msgs/msg/Done"))
        result_hash = str(params.get("result_hash", "RIHS01_" + "ab" * 32))
    stop = threading.Event()
    # Set on a thread of its own: the handler may run inside ``stop.wait`` while this thread
    # holds the event's lock, where ``set`` would wait for that lock for ever.
    signal.signal(signal.SIGTERM, lambda *_: _thread.start_new_thread(stop.set, ()))
    images: collections.deque[bytes] = collections.deque(maxlen=depth)  # KEEP_LAST
    arrived = threading.Condition()

    def on_image(sample: zenoh.Sample) -> None:
        raw = sample.payload.to_bytes()
        _emit(received=decode_header(raw).stamp_ns)
        with arrived:
            images.append(raw)
            arrived.notify()

    with zenoh.open(_config(params)) as session:
        node = NodeIdentity(0, str(session.info.zid()), str(params.get("name", "vision")))
        in_topic, out_topic = str(params["image_topic"]), str(params["result_topic"])
        image_hash = type_hash(codec.rihs01(IMAGE), "jazzy")
        sub_qos = Qos(Reliability.RELIABLE, depth)
        declared: list[Any] = [session.liveliness().declare_token(node.node_token())]
        sub_token = node.endpoint_token(
            1, EntityKind.SUBSCRIPTION, in_topic, IMAGE, image_hash, sub_qos
        )
        pub_token = node.endpoint_token(
            2, EntityKind.PUBLISHER, out_topic, result_type, result_hash, Qos()
        )
        declared.append(
            session.declare_subscriber(
                data_key(0, in_topic, IMAGE, image_hash),
                zenoh.handlers.Callback(on_image, indirect=True),
            )
        )
        publisher = session.declare_publisher(data_key(0, out_topic, result_type, result_hash))
        declared += [
            session.liveliness().declare_token(sub_token),
            session.liveliness().declare_token(pub_token),
        ]
        source_gid = gid(pub_token)

        def until_stdin_closes() -> None:
            sys.stdin.read()
            stop.set()

        threading.Thread(target=until_stdin_closes, daemon=True).start()
        _emit(ready=True)
        seen = 0
        while not stop.is_set():
            with arrived:
                if not images:
                    arrived.wait(0.2)
                    continue
                raw = images.popleft()
            started = time.monotonic()
            image = codec.decode_image(raw)
            seen += 1
            markers: list[tuple[int, list[float]]] = []
            if detect:
                from services.lib.markers import detect_markers

                pixels = image.data.reshape(image.height, image.step)[:, : image.width]
                markers = [
                    (d.marker_id, [c for corner in d.corners_px for c in corner])
                    for d in detect_markers(pixels)
                ]
            if stop.wait(max(0.0, service_s - (time.monotonic() - started))) or not answer:
                continue
            if detect:
                cdr: bytes | bytearray = codec.encode_detections(
                    image.stamp_ns, image.frame_id, markers
                )
            else:
                cdr = _header_cdr(image.stamp_ns, image.frame_id, seen)
            attachment = Attachment(seen, time.time_ns(), source_gid).encode()
            publisher.put(cdr, attachment=attachment)
            _emit(answered=image.stamp_ns, markers=sorted({m for m, _ in markers}))
        publisher.undeclare()
        for entity in reversed(declared):
            entity.undeclare()


if __name__ == "__main__":
    main(json.loads(sys.argv[1]))
