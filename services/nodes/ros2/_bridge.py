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
  slow or absent ROS 2 subscriber never holds framegate back; a full queue drops its oldest
  notification for the newest (keep-last), counted ``not-observed``.

Bad input never stops the bridge: a message that does not decode (``bad-cdr``), an image
whose width x height x step disagrees with its data or an encoding framegate cannot hold
(``bad-image``), a frame that does not fit the camera description (``camera-mismatch``), a
stamp that is not newer than the last one (``out-of-order``, ``duplicate-stamp``) or is
zero (``bad-stamp``), an element the producer rejects (``rejected``), a full in-queue
(``in-queue-full``): each is a counted skip (``Producer.count_skip``, ``skipped`` in
``framegate info``) with one warning per reason. Out, an element that cannot be read
(``bad-element``), a publish Zenoh refuses (``publish-failed``), elements the observer was
never notified of (``not-observed``: its queue was full, or its subscription had lapsed) or
messages on its notify key that were no notification (``bad-notification``) are
skipped the same way, and anything unforeseen with one message is logged with its traceback
(``internal-error``) while the bridge goes on.

Threads: Zenoh's callback thread only appends to the in-queues (see ``_link``). On the
node's executor: the images in (decoded and put a few per run, ``_inputs``), the outputs
(``Output.on_notes``), and the watch for the ROS 2 router and the first look at the graph,
a timer and deadlines (``_graph``). On threads of their own: the IMU in (``ros2-imu-in``: its
put waits for credit, which on the executor would hold all the rest, ``_inputs``) and the
``--consumer-done`` loop (``_consumer_loop`` says why). The caller's thread spins the node
until ``stop``. Each in-queue is guarded by its condition; ``_Skips`` by its lock.
"""

from __future__ import annotations

import logging
import threading
import time
from collections.abc import Callable
from typing import Any

from middleware import (
    PUSH_ALL,
    FramegateError,
    NetworkConfig,
    Node,
    Notification,
    SubscriptionMode,
    validate_metadata,
)
from services.lib.frame_layout import read_frame_layout
from services.lib.messages import DecisionRecord
from services.nodes._not_observed import BAD_NOTIFICATION
from services.nodes._runtime import setup_logging

from ._camera_info import CAMERA_INFO, TF_MESSAGE, TF_STATIC, CameraSource
from ._cdr import DETECTIONS, IMAGE, IMU, STRING, Codec
from ._config import DEFAULT_FRAME_ID, Mapping, Ros2Config
from ._graph import StartWatch
from ._inputs import (
    ImagesIn,
    ImuIn,
    _camera,
    _subscribe_camera,
)
from ._inputs import _InQueue as _InQueue  # re-exported: other loops queue the same way
from ._inputs import _Skips as _Skips
from ._link import RosLink, RosPublisher
from ._rmw import TopicCheck, dds_type_name, type_hash
from ._sequence import SequenceWatch

__all__ = ["Encoders", "ImagesIn", "ImuIn", "Output", "run"]

_NS = "{urn:framegate:1}"
_log = logging.getLogger("framegate.ros2")
# How often an output counts the garbage on its notify key (a count, not a hot path).
BAD_NOTIFICATION_PERIOD_S = 2.0


class Output:
    """One framegate buffer → one ROS 2 topic, observed (never holding framegate back).

    A handler on the node's executor (``attach``): each notification is fetched (its element
    came along: ``PUSH_ALL``), encoded and published. Publishing only hands the message to
    Zenoh, which drops it rather than wait, except for a reliable keep-all topic
    (``--out-depth 0``), which may lose nothing: its publish waits for room, and the node's
    other handlers with it, as a ROS 2 keep-all publisher's caller does.
    """

    def __init__(
        self,
        node: Node,
        publisher: RosPublisher,
        mapping: Mapping,
        encode: Callable[[Any], bytes | bytearray | None],
        config: Ros2Config,
        skips: _Skips,
    ) -> None:
        self.mapping = mapping
        self._node = node
        self._publisher = publisher
        self._encode = encode
        self._skips = skips
        self._sub = node.subscribe(
            mapping.buffer,
            queue_size=config.out_queue,
            mode=SubscriptionMode.OBSERVE,
            wait_s=0,
            push_max_bytes=PUSH_ALL,
            await_service=True,  # the services it carries may start after it
        )
        self.published = 0
        self._bad = 0  # messages on the notify key that were no notification, counted

    def attach(self) -> None:
        """Run ``on_notes`` on the node's executor for what the subscription queues, and
        count what came on its key that was no notification (``_count_bad``)."""
        self._node.on(self._sub, self.on_notes)
        self._node.every(BAD_NOTIFICATION_PERIOD_S, self._count_bad)

    def _count_bad(self, _now_ns: int) -> None:
        """(the executor) A peer's garbage on the subscription's notify key, oversize
        messages, or those a flood pushed out of its inbox: counted ``bad-notification``
        (the subscription counted them, nothing showed them)."""
        total = self._sub.garbage + self._sub.dropped
        if total > self._bad:
            self._skips.count(
                None,
                BAD_NOTIFICATION,
                f"{total - self._bad} messages on the notification key of "
                f"{self.mapping.buffer} were no notification (garbage, oversize, or a flood)",
                total - self._bad,
            )
            self._bad = total

    def on_notes(self, notes: list[Notification]) -> None:
        """(the executor) Carry each notification to ROS 2; every failure is a counted skip."""
        for note in notes:
            try:
                self._carry(note)
            except Exception as exc:  # one element must never stop the bridge's executor
                _log.exception("output to %s: unexpected error", self.mapping.topic)
                self._skips.count(None, "internal-error", repr(exc))

    def _carry(self, note: Notification) -> None:
        skips = self._skips
        if note.missed:  # never notified (a full queue, or a lapse): never published
            skips.count(
                None,
                "not-observed",
                f"{note.missed} element(s) of {self.mapping.buffer} before {note.timestamp_ns}",
                note.missed,
            )
        try:
            element = self._sub.fetch(note)
            cdr = self._encode(element)
        except (FramegateError, ValueError, KeyError, TypeError) as exc:
            skips.count(None, "bad-element", f"{self.mapping.buffer} at {note.timestamp_ns}: {exc}")
            return
        if cdr is None:
            return
        try:
            self._publisher.publish(cdr)
            self.published += 1
        except FramegateError as exc:
            skips.count(None, "publish-failed", str(exc))


class Encoders:
    """framegate elements → CDR messages (``None``: nothing to publish for this one)."""

    def __init__(
        self,
        codec: Codec,
        config: Ros2Config,
        images_frame: Callable[[], str | None] = lambda: None,
    ) -> None:
        self._codec, self._config = codec, config
        self._images_frame = images_frame

    def frame_id(self) -> str:
        """The outputs' header.frame_id: ``--frame-id`` if given, else that of the images
        coming in (the same camera: a node that copies the header into its results then
        names a frame that exists in TF), else ``DEFAULT_FRAME_ID``."""
        return self._config.frame_id or self._images_frame() or DEFAULT_FRAME_ID

    def image(self, element: Any) -> bytes:
        # Only size and encoding are needed, and the producer validated the metadata against
        # its schema when it was put: the layout's three fields, checked against the payload.
        layout = read_frame_layout(element.metadata, len(element.payload))
        width, height, encoding = layout.width_px, layout.height_px, layout.encoding
        # The frame's one copy: after the CDR head, into the message that goes to Zenoh.
        return self._codec.encode_image(
            self._config.stamp_ns(element.timestamp_ns),
            self.frame_id(),
            width,
            height,
            encoding,
            element.payload,
        )

    def detections(self, element: Any) -> bytearray:
        root = validate_metadata(element.metadata, "detections")
        markers = []
        scores: list[float | None] = []  # a vision handler's confidences, carried across
        for marker in root.iter(_NS + "marker"):
            corners = [float(v) for v in (marker.findtext(_NS + "corners_px") or "").split()]
            if len(corners) != 8:
                raise ValueError(f"marker with {len(corners)} corner numbers, expected 8")
            markers.append((int(marker.findtext(_NS + "id") or 0), corners))
            score = marker.findtext(_NS + "score")
            scores.append(None if score is None else float(score))
        return self._codec.encode_detections(
            self._config.stamp_ns(element.timestamp_ns), self.frame_id(), markers, scores
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
        cameras = CameraSource(
            codec,
            log,
            image_topic=config.image_in or "",
            info_topic=config.camera_info_topic,
            imu_topic=config.imu_in,
            override=_camera(config),
            rotation=config.imu_to_camera,
        )
        watches: list[SequenceWatch] = []
        if config.image_in:
            images = ImagesIn(node, codec, config, skips, cameras)
            images.attach(node)  # decoded and put on the node's executor
            link.subscribe(config.image_in, IMAGE, hashed(IMAGE), config.in_qos, images.on_sample)
            watches.append(images.sequence)
            _subscribe_camera(link, cameras, config, hashed)
        if config.imu_in:
            imu = ImuIn(node, codec, config, skips, cameras)
            link.subscribe(config.imu_in, IMU, hashed(IMU), config.in_qos, imu.on_sample)
            watches.append(imu.sequence)
            start("ros2-imu-in", lambda: imu.run(stop))  # type: ignore[union-attr]
        # The input topics and their types (the graph check warns about other types).
        inputs = (
            (config.image_in, IMAGE),
            (config.imu_in, IMU),
            (
                config.image_in and cameras.wants_camera_info and config.camera_info_topic,
                CAMERA_INFO,
            ),
            (config.image_in and cameras.wants_tf and TF_STATIC, TF_MESSAGE),
        )
        encoders = Encoders(codec, config, lambda: images.last_frame_id if images else None)
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
                        node, link, publisher, encode, config, skips, start, stop, codec
                    )
                    continue
                output = Output(node, publisher, mapping, encode, config, skips)
                output.attach()
                outputs.append(output)
        log.info(
            "%s: node %s in domain %d via %s (%s); in: %s; out: %s",
            config.name,
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
            ", ".join(
                f"{m.buffer} -> {m.topic}"
                + (
                    f" (its results on {config.consumer_done})"
                    if m == config.consumer_mapping
                    else ""
                )
                for m in config.outputs
            )
            or "-",
        )
        if consumer is not None:
            link.watch_graph(consumer.on_token)
        expected = {
            topic: (dds_type_name(ros_type), hashed(ros_type))
            for topic, ros_type in (
                *((t, r) for t, r in inputs if t),
                *((m.topic, IMAGE) for m in config.image_out),
                *((m.topic, DETECTIONS) for m in config.detections_out),
                *((m.topic, STRING) for m in config.verdicts_out),
            )
        }
        check = TopicCheck(link.identity.session_id, expected)

        def on_token(token: str) -> None:
            for watch in watches:
                watch.announce(token)
            if said := check.check(token):
                log.warning("ros2: %s", said)

        link.watch_graph(on_token)
        where = ", ".join(config.ros_connect) or "the --ros-config endpoints"
        start_watch = StartWatch(node, link, watches, where, log)
        try:
            node.spin(stop)
        except KeyboardInterrupt:
            stop.set()
        finally:
            stop.set()
            start_watch.close()
        if images is not None:
            images.finish()
        deadline = time.monotonic() + 1.0
        for thread in threads:
            thread.join(max(0.0, deadline - time.monotonic()))
        skipped = ", ".join(f"{reason} {n}" for reason, n in sorted(skips.counts.items()))
        counts = consumer.counts() if consumer is not None else None
        log.info(
            "%s",
            stop_summary(
                config.name,
                frames=(images.stored, images.dropped) if images else (0, 0),
                imu=(imu.stored, imu.dropped) if imu else (0, 0),
                outputs_published=sum(o.published for o in outputs),
                loop_published=counts.published if counts is not None else None,
                skipped=skipped,
            ),
        )
        if consumer is not None and counts is not None:  # the loop's own line
            log.info("%s: consumer loop: %s", config.name, counts.text())
            consumer.close()
    return 0


def stop_summary(
    name: str,
    *,
    frames: tuple[int, int],
    imu: tuple[int, int],
    outputs_published: int,
    loop_published: int | None,
    skipped: str,
) -> str:
    """The bridge's line when it stops. ``loop_published``: the ``--consumer-done`` loop's
    images (None without it), said beside the outputs' messages: the line said "0 messages
    handed to ROS 2" while the loop had published 93 images (its own line follows)."""
    handed = f"{outputs_published} messages handed to ROS 2 by the outputs"
    if loop_published is not None:
        handed += f" and {loop_published} images by the consumer loop (next line)"
    return (
        f"{name}: {frames[0]} frames stored, {frames[1]} dropped at the bridge (flow control); "
        f"{imu[0]} IMU samples stored, {imu[1]} dropped; {handed} (whether a ROS 2 node "
        f"received them is ROS 2's to say); skipped: {skipped or 'none'}"
    )


def _start_consumer(
    node: Node,
    link: RosLink,
    publisher: RosPublisher,
    encode: Callable[[Any], bytes | bytearray | None],
    config: Ros2Config,
    skips: _Skips,
    start: Callable[[str, Callable[[], None]], None],
    stop: threading.Event,
    codec: Codec,
) -> Any:
    """The ``--consumer-done`` loop on the node's input mapping, its two threads started."""
    from ._consumer_loop import ConsumerLoop  # only a bridge with --consumer-done needs it

    mapping = config.consumer_mapping
    assert mapping is not None
    consumer = ConsumerLoop(
        node, link, publisher, mapping, encode, config, skips, first_field=codec.first_field
    )
    start(f"ros2-feed-{mapping.topic}", lambda: consumer.run_feed(stop))
    start("ros2-consumer-results", lambda: consumer.run_resolver(stop))
    return consumer
