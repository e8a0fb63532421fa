"""The bridge's loops: ROS 2 camera and IMU in, framegate frames, detections and verdicts out.

In: each ``sensor_msgs/msg/Image`` becomes one ``frame`` element of NAME/images keyed by its
exposure start (``header.stamp`` moved by ``--stamp``), exactly as the camera service puts
them, so the mediator subscribes to NAME/images unchanged; each ``sensor_msgs/msg/Imu``
becomes a one-sample ``gyro`` element of NAME/rates, put in batches as the gyro service does.

Buffering rules chosen here. ROS 2 publishers cannot be refused, so framegate's flow
control ends at the bridge:
- images: when flow control refuses a frame it is dropped here and counted, like the
  camera's dropped-at-the-source frames (the producer's ``refused`` in ``framegate info``).
  Between Zenoh and the put, a KEEP_LAST queue of ``--in-depth`` images drops the oldest.
- IMU: a refused batch waits up to ``--gyro-wait-ms`` for credit (the mediator needs every
  sample), then is dropped and counted as the gyro service does.
- out: every framegate buffer carried to ROS 2 is *observed* (never flow-controlled), so a
  slow or absent ROS 2 subscriber never holds framegate back; a full queue misses
  notifications, counted by the producer.

Bad input never stops the bridge: a message that does not decode (``bad-cdr``), an image
whose width x height x step disagrees with its data or an encoding framegate cannot hold
(``bad-image``), a frame that does not fit the camera description (``camera-mismatch``), a
stamp that is not newer than the last one (``out-of-order``, ``duplicate-stamp``) or is
zero (``bad-stamp``), an element the producer rejects (``rejected``), a full in-queue
(``in-queue-full``): each is a counted skip (``Producer.count_skip``, ``skipped`` in
``framegate info``) with one warning per reason. Out, an element that cannot be read
(``bad-element``) or a publish Zenoh refuses (``publish-failed``) is skipped the same way,
and anything unforeseen with one message is logged with its traceback (``internal-error``)
while the bridge goes on.

Threads: Zenoh's callback thread only appends to the in-queues (see ``_link``); one thread
per input decodes and puts; one thread per output takes, encodes and publishes; one watches
for the ROS 2 router (``_link.watch_router``); the caller's thread waits for ``stop``. Each
in-queue is guarded by its condition; ``_Skips`` by its lock.
"""

from __future__ import annotations

import collections
import logging
import threading
import time
from collections.abc import Callable
from typing import Any

import numpy as np

from middleware import (
    PUSH_ALL,
    ConfigError,
    FlowControlRefused,
    FramegateError,
    NetworkConfig,
    Node,
    Producer,
    Retention,
    SubscriptionMode,
    field_text,
    make_metadata,
    parse_untrusted,
    validate_metadata,
)
from services.lib.camera_model import CameraModel
from services.lib.messages import DecisionRecord
from services.nodes._runtime import setup_logging
from services.nodes.gyro import sample_elements

from ._cdr import CHANNELS, DETECTIONS, IMAGE, IMU, STRING, CdrError, Codec
from ._config import Mapping, Ros2Config
from ._link import RosLink, RosPublisher, watch_router
from ._rmw import Attachment, TopicCheck, dds_type_name, type_hash

_NS = "{urn:framegate:1}"
# How long an output thread waits for a notification before looking at ``stop``.
_POLL_S = 0.2
# A partial IMU batch goes out after this long without a new sample.
_IMU_IDLE_S = 0.05


class _Skips:
    """Counted skips: into the producer's ``skipped`` when there is one, one warning each."""

    def __init__(self, log: logging.Logger) -> None:
        self._log = log
        self._lock = threading.Lock()
        self.counts: collections.Counter[str] = collections.Counter()

    def count(self, producer: Producer | None, reason: str, detail: str) -> None:
        with self._lock:
            self.counts[reason] += 1
            first = self.counts[reason] == 1
        if producer is not None:
            producer.count_skip(reason)
        if first:
            self._log.warning("skipping (%s; counted, warned once): %s", reason, detail)


class _InQueue:
    """KEEP_LAST queue between Zenoh's callback and a worker: the oldest goes when full."""

    def __init__(self, depth: int, on_overflow: Callable[[], None]) -> None:
        self._items: collections.deque[tuple[bytes, bytes | None]] = collections.deque()
        self._depth = depth
        self._cond = threading.Condition()
        self._on_overflow = on_overflow

    def put(self, payload: bytes, attachment: bytes | None) -> None:
        with self._cond:
            overflow = len(self._items) >= self._depth
            if overflow:
                self._items.popleft()
            self._items.append((payload, attachment))
            self._cond.notify()
        if overflow:
            self._on_overflow()

    def get(self, timeout_s: float) -> tuple[bytes, bytes | None] | None:
        with self._cond:
            if not self._items:
                self._cond.wait(timeout_s)
            return self._items.popleft() if self._items else None


def frame_metadata(
    frame_id: int,
    start_ns: int,
    exposure_ns: int,
    encoding: str,
    width: int,
    height: int,
    camera: CameraModel | None,
) -> bytes:
    """``frame`` metadata, field for field as the camera service writes it."""
    fields: dict[str, Any] = {
        "frame_id": frame_id,
        "exposure_start_ns": start_ns,
        "exposure_ns": exposure_ns,
        "encoding": encoding,
        "width_px": width,
        "height_px": height,
    }
    if camera is not None:
        fields["camera"] = camera.camera_fields()
    return make_metadata("frame", start_ns, fields)


def _camera(config: Ros2Config) -> CameraModel | None:
    """The ``--camera-xml`` description; ConfigError naming the file when it is unusable."""
    if config.camera_xml is None:
        return None
    try:
        return CameraModel.from_xml(config.camera_xml.read_bytes())
    except OSError as exc:
        raise ConfigError(f"cannot read --camera-xml {config.camera_xml}: {exc.strerror}") from exc
    except FramegateError as exc:
        raise ConfigError(f"--camera-xml {config.camera_xml}: {exc}") from exc


def _sequence(attachment: bytes | None, fallback: int) -> int:
    if attachment is None:
        return fallback
    try:
        return Attachment.decode(attachment).sequence_number
    except ValueError:
        return fallback


class ImagesIn:
    """ROS 2 images → NAME/images (see the module docstring for the rules)."""

    def __init__(self, node: Node, codec: Codec, config: Ros2Config, skips: _Skips) -> None:
        self.producer = node.offer(
            "images",
            kind="frame",
            retention=Retention(max_count=config.retention_frames, max_bytes=512 * 2**20),
        )
        self._codec, self._config, self._skips = codec, config, skips
        self.camera = _camera(config)
        self.queue = _InQueue(
            config.in_depth,
            lambda: skips.count(self.producer, "in-queue-full", "the in-queue was full"),
        )
        self._last_key = 0
        self.stored = self.dropped = 0

    def run(self, stop: threading.Event) -> None:
        count = 0
        while not stop.is_set():
            item = self.queue.get(_POLL_S)
            if item is not None:
                count += 1
                try:
                    self.handle(item[0], _sequence(item[1], count))
                except Exception as exc:  # one message must never stop the bridge
                    logging.getLogger("framegate.ros2").exception("image: unexpected error")
                    self._skips.count(self.producer, "internal-error", repr(exc))

    def handle(self, raw: bytes, frame_id: int) -> None:
        """Decode, check and put one image; every failure is a counted skip."""
        skip = self._skips.count
        try:
            image = self._codec.decode_image(raw)
        except CdrError as exc:
            reason = "bad-cdr" if str(exc).startswith("not a CDR") else "bad-image"
            skip(self.producer, reason, str(exc))
            return
        camera = self.camera
        if camera is not None and (camera.width_px, camera.height_px) != (
            image.width,
            image.height,
        ):
            skip(
                self.producer,
                "camera-mismatch",
                f"image {image.width}x{image.height}, camera {camera.width_px}x{camera.height_px}",
            )
            return
        key = self._config.start_ns(image.stamp_ns)
        if image.stamp_ns <= 0 or key <= 0:
            skip(self.producer, "bad-stamp", f"header.stamp {image.stamp_ns} ns")
            return
        if key <= self._last_key:
            reason = "duplicate-stamp" if key == self._last_key else "out-of-order"
            skip(self.producer, reason, f"stamp {image.stamp_ns} ns after {self._last_key} ns")
            return
        metadata = frame_metadata(
            frame_id,
            key,
            self._config.exposure_ns,
            image.encoding,
            image.width,
            image.height,
            camera,
        )
        try:
            # Decoding copied nothing; this is the frame's one copy, out of the message.
            self.producer.put(key, image.pixels(), metadata)
            self.stored += 1
        except FlowControlRefused:
            self.dropped += 1  # dropped at the bridge, counted in images.info().refused
        except FramegateError as exc:
            skip(None, "rejected", f"frame at {key} ns: {exc}")  # the producer counted it
        self._last_key = key


class ImuIn:
    """ROS 2 IMU samples → one-sample ``gyro`` elements of NAME/rates, in batches."""

    def __init__(self, node: Node, codec: Codec, config: Ros2Config, skips: _Skips) -> None:
        self.producer = node.offer(
            "rates", kind="gyro", retention=Retention(max_count=None, max_age_ns=30_000_000_000)
        )
        self._codec, self._config, self._skips = codec, config, skips
        self.queue = _InQueue(
            max(config.in_depth, 4 * config.gyro_batch),
            lambda: skips.count(self.producer, "in-queue-full", "the IMU in-queue was full"),
        )
        self._pending: list[tuple[int, tuple[float, float, float]]] = []
        self._last_ns = 0
        self._period_ns = 0
        self.stored = self.dropped = 0

    def run(self, stop: threading.Event) -> None:
        while not stop.is_set():
            item = self.queue.get(_IMU_IDLE_S)
            if item is None:
                self.flush()
                continue
            try:
                self.add(item[0])
                if len(self._pending) >= self._config.gyro_batch:
                    self.flush()
            except Exception as exc:  # one message must never stop the bridge
                logging.getLogger("framegate.ros2").exception("IMU: unexpected error")
                self._skips.count(self.producer, "internal-error", repr(exc))

    def add(self, raw: bytes) -> None:
        try:
            t_ns, rates = self._codec.decode_imu(raw)
        except CdrError as exc:
            self._skips.count(self.producer, "bad-cdr", str(exc))
            return
        if t_ns <= 0:
            self._skips.count(self.producer, "bad-stamp", f"header.stamp {t_ns} ns")
            return
        if t_ns <= self._last_ns:
            reason = "duplicate-stamp" if t_ns == self._last_ns else "out-of-order"
            self._skips.count(self.producer, reason, f"IMU stamp {t_ns} ns after {self._last_ns}")
            return
        if self._last_ns:
            step = t_ns - self._last_ns
            self._period_ns = step if not self._period_ns else (3 * self._period_ns + step) // 4
        self._last_ns = t_ns
        self._pending.append((t_ns, rates))

    def flush(self) -> None:
        if not self._pending:
            return
        t = np.asarray([s[0] for s in self._pending], dtype=np.int64)
        w = np.asarray([s[1] for s in self._pending], dtype=np.float64)
        self._pending = []
        elements = sample_elements(t, w, period_ns=self._period_ns)
        # A batch never exceeds the smallest flow-controlled queue (it could never fit).
        queues = [
            s.queue_size for s in self.producer.subscriptions() if s.mode is SubscriptionMode.FLOW
        ]
        size = max(1, min([len(elements), *queues]))
        for i in range(0, len(elements), size):
            batch = elements[i : i + size]
            try:
                self.producer.put_many(batch, wait_s=self._config.gyro_wait_ms / 1e3)
                self.stored += len(batch)
            except FlowControlRefused:
                self.dropped += len(batch)
            except FramegateError as exc:
                self._skips.count(None, "rejected", f"IMU batch: {exc}")


class Output:
    """One framegate buffer → one ROS 2 topic, observed (never holding framegate back)."""

    def __init__(
        self,
        node: Node,
        publisher: RosPublisher,
        mapping: Mapping,
        encode: Callable[[Any], bytes | bytearray | None],
        config: Ros2Config,
    ) -> None:
        self.mapping = mapping
        self._publisher = publisher
        self._encode = encode
        self._sub = node.subscribe(
            mapping.buffer,
            queue_size=config.out_queue,
            mode=SubscriptionMode.OBSERVE,
            wait_s=0,
            push_max_bytes=PUSH_ALL,
            await_service=True,  # the services it carries may start after it
        )
        self.published = 0

    def run(self, stop: threading.Event, skips: _Skips) -> None:
        while not stop.is_set():
            note = self._sub.take(timeout_s=_POLL_S)
            if note is None:
                continue
            try:
                element = self._sub.fetch(note)
                cdr = self._encode(element)
            except (FramegateError, ValueError, KeyError, TypeError) as exc:
                skips.count(
                    None, "bad-element", f"{self.mapping.buffer} at {note.timestamp_ns}: {exc}"
                )
                continue
            if cdr is None:
                continue
            try:
                self._publisher.publish(cdr)
                self.published += 1
            except FramegateError as exc:
                skips.count(None, "publish-failed", str(exc))


class Encoders:
    """framegate elements → CDR messages (``None``: nothing to publish for this one)."""

    def __init__(self, codec: Codec, config: Ros2Config) -> None:
        self._codec, self._config = codec, config

    def image(self, element: Any) -> bytes:
        # Only size and encoding are needed, and the producer validated the metadata against
        # its schema when it was put: a hardened parse and three fields (about a tenth of a
        # full read), then the same consistency checks as the mediator's.
        root = parse_untrusted(element.metadata)
        if root.get("kind") != "frame":
            raise ValueError(f"metadata of kind {root.get('kind')!r}, expected frame")
        width = int(field_text(root, "width_px") or 0)
        height = int(field_text(root, "height_px") or 0)
        encoding = str(field_text(root, "encoding"))
        if encoding not in CHANNELS:
            raise ValueError(f"encoding {encoding!r}")
        expected = width * height * CHANNELS[encoding]
        if width <= 0 or height <= 0 or len(element.payload) != expected:
            raise ValueError(
                f"payload of {len(element.payload)} bytes for {width}x{height} {encoding}"
            )
        # The frame's one copy: after the CDR head, into the message that goes to Zenoh.
        return self._codec.encode_image(
            self._config.stamp_ns(element.timestamp_ns),
            self._config.frame_id,
            width,
            height,
            encoding,
            element.payload,
        )

    def detections(self, element: Any) -> bytearray:
        root = validate_metadata(element.metadata, "detections")
        markers = []
        for marker in root.iter(_NS + "marker"):
            corners = [float(v) for v in (marker.findtext(_NS + "corners_px") or "").split()]
            if len(corners) != 8:
                raise ValueError(f"marker with {len(corners)} corner numbers, expected 8")
            markers.append((int(marker.findtext(_NS + "id") or 0), corners))
        return self._codec.encode_detections(
            self._config.stamp_ns(element.timestamp_ns), self._config.frame_id, markers
        )

    def verdict(self, element: Any) -> bytearray:
        record = DecisionRecord.from_metadata(element.metadata)
        fields = {
            "stamp_ns": self._config.stamp_ns(record.frame_timestamp_ns),
            "frame_timestamp_ns": record.frame_timestamp_ns,
            "frame_id": record.frame_id,
            "accepted": record.accepted,
            "reason": record.reason,
            "quality": record.quality,
            "blur_px": record.blur_px,
            "load": record.load,
            "policy": record.policy,
        }
        return self._codec.encode_string(fields)


def run(config: Ros2Config, network: NetworkConfig, stop: threading.Event | None = None) -> int:
    """Bridge until ``stop`` is set or KeyboardInterrupt."""
    stop = stop or threading.Event()
    log = setup_logging(config.name)
    config.check_has_work()
    codec = Codec(config.ros_distro)
    skips = _Skips(log)
    threads: list[threading.Thread] = []

    def start(name: str, target: Callable[[], None]) -> None:
        thread = threading.Thread(target=target, name=name, daemon=True)
        thread.start()
        threads.append(thread)

    def hashed(ros_type: str) -> str:
        return type_hash(codec.rihs01(ros_type), config.ros_distro)

    with (
        Node(config.name, network) as node,
        RosLink(
            config.ros_network(),
            domain_id=config.domain_id,
            node_name=config.node_name,
            namespace=config.ros_namespace,
        ) as link,
    ):
        images = imu = None
        if config.image_in:
            images = ImagesIn(node, codec, config, skips)
            link.subscribe(config.image_in, IMAGE, hashed(IMAGE), config.in_qos, images.queue.put)
            start("ros2-images-in", lambda: images.run(stop))  # type: ignore[union-attr]
        if config.imu_in:
            imu = ImuIn(node, codec, config, skips)
            link.subscribe(config.imu_in, IMU, hashed(IMU), config.in_qos, imu.queue.put)
            start("ros2-imu-in", lambda: imu.run(stop))  # type: ignore[union-attr]
        encoders = Encoders(codec, config)
        outputs: list[Output] = []
        consumer = None
        for mappings, ros_type, encode in (
            (config.image_out, IMAGE, encoders.image),
            (config.detections_out, DETECTIONS, encoders.detections),
            (config.verdicts_out, STRING, encoders.verdict),
        ):
            for mapping in mappings:
                publisher = link.publisher(
                    mapping.topic, ros_type, hashed(ros_type), config.out_qos
                )
                if mapping == config.consumer_mapping:
                    consumer = _start_consumer(
                        node, link, publisher, encode, config, skips, start, stop
                    )
                    continue
                output = Output(node, publisher, mapping, encode, config)
                outputs.append(output)
                start(f"ros2-out-{mapping.topic}", lambda o=output: o.run(stop, skips))  # type: ignore[misc]
        log.info(
            "ros2: node %s in domain %d via %s (%s); in: %s; out: %s",
            config.node_name,
            config.domain_id,
            ", ".join(config.ros_connect),
            config.ros_distro,
            ", ".join(
                f"{t} -> {config.name}/{b}"
                for t, b in ((config.image_in, "images"), (config.imu_in, "rates"))
                if t
            )
            or "-",
            ", ".join(f"{o.mapping.buffer} -> {o.mapping.topic}" for o in outputs) or "-",
        )
        if consumer is not None:
            link.watch_graph(consumer.on_token)
        expected = {
            topic: (dds_type_name(ros_type), hashed(ros_type))
            for topic, ros_type in (
                *((t, r) for t, r in ((config.image_in, IMAGE), (config.imu_in, IMU)) if t),
                *((m.topic, IMAGE) for m in config.image_out),
                *((m.topic, DETECTIONS) for m in config.detections_out),
                *((m.topic, STRING) for m in config.verdicts_out),
            )
        }
        check = TopicCheck(link.identity.session_id, expected)

        def on_token(token: str) -> None:
            if said := check.check(token):
                log.warning("ros2: %s", said)

        link.watch_graph(on_token)
        where = ", ".join(config.ros_connect) or "the --ros-config endpoints"
        start("ros2-router", lambda: watch_router(link.routers, where, stop, log))
        try:
            while not stop.wait(0.5):
                pass
        except KeyboardInterrupt:
            stop.set()
        stop.set()
        deadline = time.monotonic() + 1.0
        for thread in threads:
            thread.join(max(0.0, deadline - time.monotonic()))
        log.info(
            "ros2: %d frames stored, %d dropped at the bridge (flow control); %d IMU samples "
            "stored, %d dropped; %s published; skipped: %s",
            images.stored if images else 0,
            images.dropped if images else 0,
            imu.stored if imu else 0,
            imu.dropped if imu else 0,
            sum(o.published for o in outputs),
            dict(skips.counts) or "none",
        )
        if consumer is not None:
            log.info("ros2: consumer loop: %s", consumer.counts())
            consumer.close()
    return 0


def _start_consumer(
    node: Node,
    link: RosLink,
    publisher: RosPublisher,
    encode: Callable[[Any], bytes | bytearray | None],
    config: Ros2Config,
    skips: _Skips,
    start: Callable[[str, Callable[[], None]], None],
    stop: threading.Event,
) -> Any:
    """The ``--consumer-done`` loop on the node's input mapping, its two threads started."""
    from ._consumer_loop import ConsumerLoop  # only a bridge with --consumer-done needs it

    mapping = config.consumer_mapping
    assert mapping is not None
    consumer = ConsumerLoop(node, link, publisher, mapping, encode, config, skips)
    start(f"ros2-feed-{mapping.topic}", lambda: consumer.run_feed(stop))
    start("ros2-consumer-results", lambda: consumer.run_resolver(stop))
    return consumer
