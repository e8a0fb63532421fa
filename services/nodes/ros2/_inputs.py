"""The bridge's inputs: ROS 2 images and IMU samples into NAME/images and NAME/rates, with
the camera description (``_camera_info``), sequence gaps (``_sequence``) and stamp order
(``_stamps``) of each; the buffering rules and skip reasons are ``_bridge``'s docstring.
Beside those: ``future-stamp`` (beyond the producer's horizon), ``lost-in-transport`` and
``sequence-jump`` (``_sequence``), ``camera-info-mismatch``, ``bad-camera-info``, ``bad-tf``,
``tf-queue-full`` (``_camera_info``), and ``stopped`` for what was still queued when the
bridge stopped: every image received is stored, refused or counted under a reason.

Threads: Zenoh's callback thread only notes the sample's sequence number, appends to the
in-queue (``on_sample``) and, for the images, schedules a drain on the node's executor when
none is due (``attach``): the images are decoded and put there, a few per run, as the camera
service puts its frames, since their put never waits (a refused frame is dropped). The IMU
keeps a worker thread (``ros2-imu-in``): a refused batch waits up to ``--gyro-wait-ms`` for
credit (the mediator needs every sample), and that wait on the executor would hold every
output and the images with it. Each in-queue is guarded by its condition, ``_Skips`` by its
lock.
"""

from __future__ import annotations

import collections
import dataclasses
import logging
import threading
import time
from collections.abc import Callable

import numpy as np

from middleware import (
    ConfigError,
    FlowControlRefused,
    FramegateError,
    Node,
    Producer,
    Retention,
    now_ns,
    printable,
)
from services.lib.camera_model import CameraModel
from services.lib.messages import frame_metadata_of
from services.lib.quality import Exposure
from services.nodes.gyro import put_samples, sample_elements

from ._camera_info import CAMERA_INFO, TF_MESSAGE, TF_STATIC, CameraSource
from ._cdr import CdrError, Codec, StampError
from ._config import MAX_FRAME_ID_CHARS, Ros2Config
from ._link import RosLink
from ._rmw import Attachment, Durability, Qos, Reliability
from ._sequence import SequenceWatch
from ._stamps import StampGate

# How long an input worker waits for a sample before looking at ``stop``.
_POLL_S = 0.2
# Samples an input on the executor decodes and puts per run: an image costs milliseconds
# (decoding, its one copy), so a few, then the node's other handlers get their turn.
_PER_RUN = 4
# A partial IMU batch goes out after this long without a new sample.
_IMU_IDLE_S = 0.05
# The IMU in-queue's least depth, in samples. The mediator needs every sample (two lost in a
# row leave a hole no frame across it can be assessed through), and the IMU worker stalls
# for a whole ``--gyro-wait-ms`` while a batch waits for credit, or longer on a busy machine:
# 2 s at 1 kHz, about 0.7 MB of CDR at most (a loaded run lost samples from a 40-deep queue).
_IMU_QUEUE = 2048
# What each in-queue holds at most in bytes, whatever its depth in messages: a peer's IMU
# messages with a 2 MB frame_id held 2,048 times grew the bridge to 3.9 GB. 2,048 honest IMU
# messages are ~0.7 MB; five 1280x1024 images ~6.5 MB (a 4K RGB image is 25 MB).
_IMU_QUEUE_BYTES = 8 << 20
_IMAGE_QUEUE_BYTES = 256 << 20
# A skip's detail in the log at most this long: it quotes a peer's message (a frame id, an
# encoding), which may be megabytes of text with newlines and terminal escapes in it.
DETAIL_CHARS = 300


class _Skips:
    """Counted skips: into the producer's ``skipped`` when there is one, one warning each."""

    def __init__(self, log: logging.Logger) -> None:
        self._log = log
        self._lock = threading.Lock()
        self.counts: collections.Counter[str] = collections.Counter()

    def count(self, producer: Producer | None, reason: str, detail: str, n: int = 1) -> None:
        with self._lock:
            first = self.counts[reason] == 0
            self.counts[reason] += n
        if producer is not None:
            producer.count_skip(reason, n)
        if first:
            self._log.warning(
                "skipping (%s; counted, warned once): %s", reason, printable(detail, DETAIL_CHARS)
            )


class _InQueue:
    """KEEP_LAST queue between Zenoh's callback and a worker: the oldest goes when full."""

    def __init__(self, depth: int, max_bytes: int, on_overflow: Callable[[], None]) -> None:
        self._items: collections.deque[tuple[bytes, bytes | None]] = collections.deque()
        self._depth = depth
        self._max_bytes = max_bytes
        self._bytes = 0
        self._cond = threading.Condition()
        self._on_overflow = on_overflow
        # Set by ``_Input.attach``: called (Zenoh's thread) when the queue gets work while
        # no drain is due, so one executor deadline is scheduled per burst, not per sample.
        self.on_ready: Callable[[], object] | None = None
        self._due = False

    def put(self, payload: bytes, attachment: bytes | None) -> None:
        size = len(payload) + len(attachment or b"")
        dropped = 0
        with self._cond:
            # The newest always stays (a message larger than the bound alone included).
            while self._items and (
                len(self._items) >= self._depth or self._bytes + size > self._max_bytes
            ):
                old, old_attachment = self._items.popleft()
                self._bytes -= len(old) + len(old_attachment or b"")
                dropped += 1
            self._items.append((payload, attachment))
            self._bytes += size
            self._cond.notify()
            ready = self.on_ready if not self._due else None
            self._due = ready is not None
        for _ in range(dropped):
            self._on_overflow()
        if ready is not None:
            ready()

    def drain(self, budget: int) -> tuple[list[tuple[bytes, bytes | None]], bool]:
        """(the executor) At most ``budget`` items, oldest first, and whether more wait (the
        caller then schedules the next drain itself; else the next ``put`` asks for one)."""
        with self._cond:
            items = [self._items.popleft() for _ in range(min(budget, len(self._items)))]
            self._bytes -= sum(len(p) + len(a or b"") for p, a in items)
            self._due = bool(self._items)
            return items, self._due

    def get(self, timeout_s: float) -> tuple[bytes, bytes | None] | None:
        with self._cond:
            if not self._items:
                self._cond.wait(timeout_s)
            if not self._items:
                return None
            item = self._items.popleft()
            self._bytes -= len(item[0]) + len(item[1] or b"")
            return item

    def clear(self) -> int:
        """Drop what waits (the bridge is stopping); how many there were."""
        with self._cond:
            count = len(self._items)
            self._items.clear()
            self._bytes = 0
            return count


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


def _count_lost(producer: Producer, watch: SequenceWatch, skips: _Skips) -> None:
    """Count in ``producer`` the samples ``watch`` found lost in transport."""
    losses = watch.take_lost()
    if losses.lost:
        skips.count(
            producer,
            "lost-in-transport",
            f"{losses.lost} samples of {watch.topic} never arrived (a gap in their publisher's "
            "sequence numbers)",
            losses.lost,
        )
    if losses.jumps:
        skips.count(
            producer,
            "sequence-jump",
            f"a publisher of {watch.topic} jumped in its sequence numbers",
            losses.jumps,
        )


class _Input:
    """What both inputs share: the in-queue Zenoh's callback fills, the sequence watch, the
    stamp gate, and the worker loop that takes each sample (``take``), finishes what is
    pending when the input goes quiet (``idle``) and counts what the stop left queued."""

    # In the log and the skip details: "image", "IMU".
    what = ""
    # How long the worker waits for a sample before ``idle`` and a look at ``stop``.
    idle_s = _POLL_S

    def __init__(
        self, producer: Producer, skips: _Skips, topic: str | None, depth: int, max_bytes: int
    ) -> None:  # fmt: skip
        self.producer = producer
        self._skips = skips
        self.queue = _InQueue(
            depth,
            max_bytes,
            lambda: skips.count(producer, "in-queue-full", f"the {self.what} in-queue was full"),
        )
        self.sequence = SequenceWatch(topic or "")
        # A stamp is remembered only once its sample can be stored (``StampGate.accept``).
        self.gate = StampGate(producer.horizon_ns, self.what)
        self.stored = self.dropped = 0
        self._count = 0  # samples taken: the sequence number of one without an attachment
        self._finished = False

    def on_sample(self, payload: bytes, attachment: bytes | None) -> None:
        """Zenoh's callback: note the sequence number, enqueue."""
        self.sequence.observe(attachment)
        self.queue.put(payload, attachment)

    def run(self, stop: threading.Event) -> None:
        """The input's worker thread (the IMU, see ``ImuIn``), until ``stop`` is set."""
        while not stop.is_set():
            item = self.queue.get(self.idle_s)
            _count_lost(self.producer, self.sequence, self._skips)
            if item is None:
                self.idle()
                continue
            self._count += 1
            self._take_one(item[0], _sequence(item[1], self._count))
        self.finish()

    def attach(self, node: Node) -> None:
        """Decode and put on ``node``'s executor instead of a worker thread (the images: their
        put never waits, see ``ImagesIn``): a deadline at once when samples arrive, at most
        ``_PER_RUN`` of them per run, and every ``idle_s`` what the sequence watch found lost
        meanwhile (a publisher's first samples are lost without any arriving)."""

        def drain(_now_ns: int) -> None:
            if self._finished:  # stopping: what is queued is counted by ``finish``
                return
            items, more = self.queue.drain(_PER_RUN)
            for raw, attachment in items:
                self._count += 1
                self._take_one(raw, _sequence(attachment, self._count))
            _count_lost(self.producer, self.sequence, self._skips)
            if more:  # behind the node's other work, as the executor's round robin
                node.at(time.monotonic_ns(), drain)

        self.queue.on_ready = lambda: node.at(time.monotonic_ns(), drain)
        node.every(
            self.idle_s, lambda _now_ns: _count_lost(self.producer, self.sequence, self._skips)
        )

    def finish(self) -> None:
        """The bridge stops: send what waits, count what was received and never put."""
        self._finished = True
        self.queue.on_ready = None
        self.idle()  # what was accepted goes out (or is counted as refused)
        if left := self.queue.clear():
            self._skips.count(
                self.producer, "stopped", f"{left} {self.what} samples at the stop", left
            )

    def _take_one(self, raw: bytes, sequence: int) -> None:
        try:
            self.take(raw, sequence)
        except Exception as exc:  # one message must never stop the bridge
            logging.getLogger("framegate.ros2").exception("%s: unexpected error", self.what)
            self._skips.count(self.producer, "internal-error", repr(exc))

    def take(self, raw: bytes, sequence: int) -> None:
        """One sample from the in-queue, with its publisher's sequence number."""
        raise NotImplementedError

    def idle(self) -> None:
        """The input is quiet (or stopping): send what waits."""


class ImagesIn(_Input):
    """ROS 2 images → NAME/images (see the module docstring for the rules), on the node's
    executor once attached: ``put`` without ``wait_s`` refuses at once, never waits."""

    what = "image"

    def __init__(
        self,
        node: Node,
        codec: Codec,
        config: Ros2Config,
        skips: _Skips,
        cameras: CameraSource | None = None,
    ) -> None:
        producer = node.offer(
            "images",
            kind="frame",
            retention=Retention(max_count=config.retention_frames, max_bytes=512 * 2**20),
            horizon_s=config.max_ahead_ms / 1e3,
        )
        super().__init__(producer, skips, config.image_in, config.in_depth, _IMAGE_QUEUE_BYTES)
        self._codec, self._config = codec, config
        # The header.frame_id of the last image decoded: the outputs' frame (``frame_id``).
        self.last_frame_id: str | None = None
        self.camera = _camera(config)
        self.cameras = cameras or CameraSource(
            codec,
            logging.getLogger("framegate.ros2"),
            image_topic=config.image_in or "",
            info_topic=config.camera_info_topic,
            imu_topic=config.imu_in,
            override=self.camera,
            rotation=config.imu_to_camera,
        )

    def take(self, raw: bytes, sequence: int) -> None:
        # The frame's id is its publisher's sequence number, when it is one a frame id can be
        # (a peer's attachment may say anything; the image is not refused for it).
        self.handle(raw, sequence if 0 <= sequence < 2**63 else 0)

    def handle(self, raw: bytes, frame_id: int) -> None:
        """Decode, check and put one image; every failure is a counted skip."""
        skip = self._skips.count
        try:
            image = self._codec.decode_image(raw)
        except StampError as exc:
            skip(self.producer, "bad-stamp", str(exc))
            return
        except CdrError as exc:
            reason = "bad-cdr" if str(exc).startswith("not a CDR") else "bad-image"
            skip(self.producer, reason, str(exc))
            return
        if 0 < len(image.frame_id) <= MAX_FRAME_ID_CHARS:
            self.last_frame_id = image.frame_id
        camera = self.cameras.for_image(
            image.frame_id,
            image.width,
            image.height,
            lambda reason, detail, n: skip(self.producer, reason, detail, n),
        )
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
        refusal = self.gate.check(key, now_ns())  # key <= stamp: a bad stamp is a bad key
        if refusal is not None:
            skip(self.producer, refusal.reason, refusal.detail)
            return
        exposure = Exposure(key, self._config.exposure_ns)
        metadata = frame_metadata_of(
            frame_id, exposure, image.encoding, image.width, image.height, camera
        )
        try:
            # Decoding copied nothing; this is the frame's one copy, out of the message.
            self.producer.put(key, image.pixels(), metadata)
            self.stored += 1
        except FlowControlRefused:
            self.dropped += 1  # dropped at the bridge, counted in images.info().refused
        except FramegateError as exc:
            skip(None, "rejected", f"frame at {key} ns: {exc}")  # the producer counted it
            return  # not remembered: a rejected stamp must not hold back the next ones
        # Remembered only now, accepted (refused by flow control means a valid stamp).
        self.gate.accept(key)


class ImuIn(_Input):
    """ROS 2 IMU samples → one-sample ``gyro`` elements of NAME/rates, in batches, on a
    worker thread of its own (``run``): its put may wait for credit (see the module)."""

    what = "IMU"
    idle_s = _IMU_IDLE_S  # a partial batch goes out when the IMU is this long quiet

    def __init__(
        self,
        node: Node,
        codec: Codec,
        config: Ros2Config,
        skips: _Skips,
        cameras: CameraSource | None = None,
    ) -> None:
        producer = node.offer(
            "rates",
            kind="gyro",
            retention=Retention(max_count=None, max_age_ns=30_000_000_000),
            horizon_s=config.max_ahead_ms / 1e3,
        )
        # Room for seconds of samples: those that arrive while the worker waits are kept.
        super().__init__(
            producer,
            skips,
            config.imu_in,
            max(config.in_depth, 4 * config.gyro_batch, _IMU_QUEUE),
            _IMU_QUEUE_BYTES,
        )
        self._codec, self._config = codec, config
        self._cameras = cameras  # told the IMU's frame, for the rotation to the camera
        self._frame: str | None = None  # the IMU frame told to the cameras ("" is one too)
        self._pending: list[tuple[int, tuple[float, float, float]]] = []
        self._period_ns = 0

    def take(self, raw: bytes, sequence: int) -> None:
        self.add(raw)
        if len(self._pending) >= self._config.gyro_batch:
            self.flush()

    def idle(self) -> None:
        self.flush()

    def add(self, raw: bytes) -> None:
        try:
            t_ns, rates, frame_id = self._codec.decode_imu_frame(raw)
        except StampError as exc:
            self._skips.count(self.producer, "bad-stamp", str(exc))
            return
        except CdrError as exc:
            self._skips.count(self.producer, "bad-cdr", str(exc))
            return
        refusal = self.gate.check(t_ns, now_ns())
        if refusal is not None:
            self._skips.count(self.producer, refusal.reason, refusal.detail)
            return
        if frame_id != self._frame and self._cameras is not None:
            self._frame = frame_id
            self._cameras.set_imu_frame(frame_id)
        last = self.gate.last_ns
        if last:
            step = t_ns - last
            self._period_ns = step if not self._period_ns else (3 * self._period_ns + step) // 4
        self.gate.accept(t_ns)
        self._pending.append((t_ns, rates))

    def flush(self) -> None:
        if not self._pending:
            return
        t = np.asarray([s[0] for s in self._pending], dtype=np.int64)
        w = np.asarray([s[1] for s in self._pending], dtype=np.float64)
        self._pending = []
        elements = sample_elements(t, w, period_ns=self._period_ns)
        stored, dropped = put_samples(
            self.producer,
            elements,
            batch=len(elements),
            wait_s=self._config.gyro_wait_ms / 1e3,
            rejected=lambda exc: self._skips.count(None, "rejected", f"IMU batch: {exc}"),
        )
        self.stored += stored
        self.dropped += dropped


# /tf_static as tf2_ros' static listener subscribes to it: reliable, transient local.
_TF_STATIC_QOS = Qos(Reliability.RELIABLE, 100, durability=Durability.TRANSIENT_LOCAL)


def _subscribe_camera(
    link: RosLink, cameras: CameraSource, config: Ros2Config, hashed: Callable[[str], str]
) -> None:
    """Subscribe to what the camera description is built from (nothing with --camera-xml)."""
    topic = config.camera_info_topic
    if cameras.wants_camera_info and topic:
        # Transient local, depth 1: a driver that publishes CameraInfo once, latched (as
        # many do for a fixed calibration), is read from its publisher's cache however late
        # the bridge starts; one that publishes it beside every image is heard as before.
        info_qos = dataclasses.replace(
            config.in_qos, depth=1, durability=Durability.TRANSIENT_LOCAL
        )
        link.subscribe(topic, CAMERA_INFO, hashed(CAMERA_INFO), info_qos, cameras.on_camera_info)
    if cameras.wants_tf:
        link.subscribe(TF_STATIC, TF_MESSAGE, hashed(TF_MESSAGE), _TF_STATIC_QOS, cameras.on_tf)
