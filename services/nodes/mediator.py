"""The mediator (paper §4.3, Fig. 5): forwards a frame to the detector only if its
gyro-estimated quality beats the detector's load.

Buffering rules chosen here:
- camera/images: flow-controlled with a deep queue (default 8), taken at once, so the
  mediator never is the reason a frame is dropped at the camera;
- gyro/rates: flow-controlled, taken at once by a thread of its own (a lossless consumer:
  the gyro waits briefly rather than lose samples the blur estimate needs);
- mediator/images: offered with the detector as a flow-controlled subscriber; its fill is
  the load indicator. A frame is only put when the acceptance test says so, so the
  mediator itself is never refused in normal operation.

Policies: ``paper`` — accept iff q > load (and q >= q_min). ``replace`` (beyond the paper) —
while the detector has something queued, hold the sharpest frame so far and hand it over
the moment the queue empties; a sharper newer frame replaces the held one.
Gyro missing or late (no coverage ``gyro_wait_ms`` after the exposure ended): by default a
frame is accepted only when the detector is idle (``--gyro-missing idle``); ``accept`` and
``reject`` are the alternatives. Outages and recovery are logged.
"""

from __future__ import annotations

import argparse
import enum
import threading
import time
from dataclasses import dataclass

from middleware import (
    PUSH_ALL,
    FlowControlRefused,
    FramegateError,
    NetworkConfig,
    Node,
    Producer,
    Retention,
    Subscription,
)
from services.lib.camera_model import CameraModel
from services.lib.messages import DecisionRecord, FrameMeta, read_frame_metadata
from services.lib.quality import (
    DEFAULT_B0_PX,
    BlurMode,
    BlurOptions,
    CoverageError,
    GyroSamples,
    accept,
    estimate_blur,
    quality,
)
from services.nodes._runtime import Monotonic, setup_logging


class Policy(enum.Enum):
    """How frames are chosen for the detector."""

    PAPER = "paper"
    REPLACE = "replace"
    DEFAULT = PAPER


class GyroMissing(enum.Enum):
    """What to do with a frame whose exposure the gyro does not cover."""

    IDLE = "idle"
    ACCEPT = "accept"
    REJECT = "reject"
    DEFAULT = IDLE


@dataclass(frozen=True, slots=True)
class MediatorConfig:
    """Everything the mediator can be told."""

    name: str = "mediator"
    camera: str = "camera/images"
    gyro: str = "gyro/rates"
    camera_queue: int = 8
    b0_px: float = DEFAULT_B0_PX
    q_min: float = 0.0
    policy: Policy = Policy.DEFAULT
    gyro_missing: GyroMissing = GyroMissing.DEFAULT
    gyro_wait_ms: float = 150.0
    blur_mode: BlurMode = BlurMode.DEFAULT
    max_hold_ms: float = 250.0


@dataclass
class _Frame:
    meta: FrameMeta
    payload: bytes
    metadata: bytes
    blur_px: float | None
    q: float | None
    end_ns: int


class GyroCache:
    """Recent gyro batches, fed by a thread that takes gyro notifications at once."""

    def __init__(self, sub: Subscription, keep_ns: int = 10_000_000_000) -> None:
        self._sub = sub
        self._keep_ns = keep_ns
        self._batches: list[GyroSamples] = []
        self._cond = threading.Condition()
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, daemon=True, name="gyro-cache")
        self._thread.start()

    def _run(self) -> None:
        while not self._stop.is_set():
            note = self._sub.take(timeout_s=0.2)
            if note is None:
                continue
            try:
                element = self._sub.fetch(note)
                batch = GyroSamples.from_bytes(element.payload)
            except (FramegateError, ValueError):
                continue
            if len(batch) == 0:
                continue
            with self._cond:
                if self._batches and batch.t_ns[0] <= self._batches[-1].t_ns[-1]:
                    # Out of order or a restarted gyro: start over rather than mix clocks.
                    self._batches = [b for b in self._batches if b.t_ns[-1] < batch.t_ns[0]]
                self._batches.append(batch)
                horizon = int(batch.t_ns[-1]) - self._keep_ns
                while self._batches and self._batches[0].t_ns[-1] < horizon:
                    self._batches.pop(0)
                self._cond.notify_all()

    @property
    def newest_ns(self) -> int | None:
        with self._cond:
            return int(self._batches[-1].t_ns[-1]) if self._batches else None

    def wait_covering(self, end_ns: int, timeout_s: float) -> bool:
        """Wait until a sample at or after ``end_ns`` (gyro clock) has arrived."""
        deadline = time.monotonic() + timeout_s
        with self._cond:
            while not self._batches or self._batches[-1].t_ns[-1] < end_ns:
                remaining = deadline - time.monotonic()
                if remaining <= 0:
                    return False
                self._cond.wait(remaining)
            return True

    def window(self, start_ns: int, end_ns: int, margin_ns: int = 20_000_000) -> GyroSamples:
        """Samples from batches overlapping [start - margin, end + margin]."""
        with self._cond:
            chosen = [
                b
                for b in self._batches
                if b.t_ns[-1] >= start_ns - margin_ns and b.t_ns[0] <= end_ns + margin_ns
            ]
        return GyroSamples.concat(chosen) if chosen else GyroSamples.empty()

    def stop(self) -> None:
        self._stop.set()
        self._thread.join(timeout=2)


class Mediator:
    """The acceptance loop; ``step`` handles one camera notification or a timeout."""

    def __init__(self, node: Node, config: MediatorConfig, log_name: str = "mediator") -> None:
        self.config = config
        self.log = setup_logging(log_name)
        self._node = node
        self.images: Producer = node.offer(
            "images", kind="frame", retention=Retention(max_count=64, max_bytes=256 * 2**20)
        )
        self.decisions: Producer = node.offer(
            "decisions", kind="decision", retention=Retention(max_count=100_000)
        )
        # Every frame is taken and assessed, so frames come pushed with their notification.
        self._camera = node.subscribe(
            config.camera, queue_size=config.camera_queue, wait_s=0, push_max_bytes=PUSH_ALL
        )
        self._gyro = GyroCache(node.subscribe(config.gyro, queue_size=256, wait_s=0))
        self._options = BlurOptions(mode=config.blur_mode)
        self._keys = Monotonic()
        self._held: _Frame | None = None
        self._gyro_ok = True
        self._camera_cache: tuple[bytes, CameraModel] | None = None

    # -- one frame --------------------------------------------------------------------------
    def step(self, timeout_s: float = 0.5) -> None:
        """Take one camera notification (or time out) and decide."""
        wait = 0.005 if self._held is not None else timeout_s
        note = self._camera.take(timeout_s=wait)
        if self._held is not None:
            self._forward_held_if_idle()
        if note is None:
            return
        try:
            element = self._camera.fetch(note)
            meta = read_frame_metadata(element.metadata)
        except FramegateError as exc:
            self.log.warning("skipping frame %d: %s", note.timestamp_ns, exc)
            return
        frame = self._assess(meta, element.payload, element.metadata)
        if self.config.policy is Policy.REPLACE and frame.q is not None:
            self._replace(frame)
        else:
            self._paper(frame)

    def _assess(self, meta: FrameMeta, payload: bytes, metadata: bytes) -> _Frame:
        camera = meta.camera
        end_ns = meta.exposure.end_ns
        if camera is None:
            return _Frame(meta, payload, metadata, None, None, end_ns)
        gyro_end = end_ns + camera.gyro_time_offset_ns + camera.height_px * camera.line_readout_ns
        covered = self._gyro.wait_covering(gyro_end, self.config.gyro_wait_ms / 1e3)
        if covered:
            start = meta.exposure.start_ns + camera.gyro_time_offset_ns
            samples = self._gyro.window(start, gyro_end)
            try:
                blur = estimate_blur(samples, meta.exposure, camera, self._options).blur_px
            except CoverageError as exc:
                covered = False
                self.log.debug("frame %d: %s", meta.frame_id, exc)
        if not covered:
            if self._gyro_ok:
                self.log.warning(
                    "gyro does not cover frame %d (newest gyro sample %s); policy: %s",
                    meta.frame_id,
                    self._gyro.newest_ns,
                    self.config.gyro_missing.value,
                )
            self._gyro_ok = False
            return _Frame(meta, payload, metadata, None, None, end_ns)
        if not self._gyro_ok:
            self.log.warning("gyro covers frames again from frame %d", meta.frame_id)
            self._gyro_ok = True
        return _Frame(meta, payload, metadata, blur, quality(blur, self.config.b0_px), end_ns)

    def _paper(self, frame: _Frame) -> None:
        load = self.images.fill()
        if frame.q is None:
            policy = self.config.gyro_missing
            ok = policy is GyroMissing.ACCEPT or (policy is GyroMissing.IDLE and load == 0.0)
            reason = f"gyro-missing-{policy.value}"
        else:
            ok = accept(frame.q, load, self.config.q_min)
            if ok:
                reason = "quality>load"
            elif frame.q < self.config.q_min:
                reason = "below-minimum"
            else:
                reason = "quality<=load"
        if ok and not self._put(frame):
            ok, reason = False, "refused"
        self._decide(frame, load, ok, reason)

    def _replace(self, frame: _Frame) -> None:
        assert frame.q is not None
        load = self.images.fill()
        if frame.q < self.config.q_min:
            self._decide(frame, load, False, "below-minimum")
            return
        if load == 0.0:
            # Idle: hand over the better of the held frame and this one, in time order.
            held, self._held = self._held, None
            best = frame if held is None or held.q is None or frame.q >= held.q else held
            if held is not None and best is frame:
                self._decide(held, load, False, "replaced")
            ok = self._put(best)
            self._decide(best, load, ok, "idle" if ok else "refused")
            if best is held:
                self._decide(frame, load, False, "worse-than-held")
            return
        held = self._held
        stale = held is not None and (frame.end_ns - held.end_ns) > self.config.max_hold_ms * 1e6
        if held is None or held.q is None or frame.q >= held.q or stale:
            if held is not None:
                self._decide(held, load, False, "stale" if stale else "replaced")
            self._held = frame
            self._decide(frame, load, False, "held")
        else:
            self._decide(frame, load, False, "worse-than-held")

    def _forward_held_if_idle(self) -> None:
        held = self._held
        if held is None or self.images.fill() > 0.0:
            return
        self._held = None
        ok = self._put(held)
        self._decide(held, 0.0, ok, "forwarded-held" if ok else "refused")

    def _put(self, frame: _Frame) -> bool:
        try:
            self.images.put(frame.meta.timestamp_ns, frame.payload, frame.metadata)
            return True
        except FlowControlRefused:
            return False
        except FramegateError as exc:
            self.log.warning("cannot forward frame %d: %s", frame.meta.frame_id, exc)
            return False

    def _decide(self, frame: _Frame, load: float, accepted: bool, reason: str) -> None:
        record = DecisionRecord(
            frame_timestamp_ns=frame.meta.timestamp_ns,
            frame_id=frame.meta.frame_id,
            blur_px=frame.blur_px,
            quality=frame.q,
            load=load,
            accepted=accepted,
            reason=reason,
            policy=self.config.policy.value,
            b0_px=self.config.b0_px,
            latency_ns=time.time_ns() - frame.end_ns,
        )
        key = self._keys.next()
        self.decisions.put(key, b"", record.metadata(key))

    def close(self) -> None:
        self._gyro.stop()


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """The mediator's flags (``framegate run mediator --help``)."""
    d = MediatorConfig()
    parser.add_argument("--name", default=d.name, help="service name (default %(default)s)")
    parser.add_argument("--camera", default=d.camera, help="frames to filter (SERVICE/BUFFER)")
    parser.add_argument("--gyro", default=d.gyro, help="gyro batches (SERVICE/BUFFER)")
    parser.add_argument(
        "--camera-queue",
        type=int,
        default=d.camera_queue,
        help="notification queue on the camera (deep: never stall it)",
    )
    parser.add_argument(
        "--b0",
        type=float,
        default=d.b0_px,
        dest="b0_px",
        help="blur scale b0 in pixels: q = exp(-blur/b0) (default %(default)s)",
    )
    parser.add_argument("--q-min", type=float, default=d.q_min, help="minimum quality")
    parser.add_argument(
        "--policy",
        choices=[p.value for p in Policy],
        default=d.policy.value,
        help="paper: q > load; replace: hold the sharpest frame while busy",
    )
    parser.add_argument(
        "--gyro-missing",
        choices=[g.value for g in GyroMissing],
        default=d.gyro_missing.value,
        help="frames without gyro coverage: idle = accept only when idle",
    )
    parser.add_argument(
        "--gyro-wait-ms",
        type=float,
        default=d.gyro_wait_ms,
        help="how long to wait for gyro coverage after exposure end",
    )
    parser.add_argument(
        "--blur-mode",
        choices=["center", "mean", "max"],
        default="center",
        help="where blur is measured (paper: center)",
    )


def config_from_args(args: argparse.Namespace) -> MediatorConfig:
    return MediatorConfig(
        name=args.name,
        camera=args.camera,
        gyro=args.gyro,
        camera_queue=args.camera_queue,
        b0_px=args.b0_px,
        q_min=args.q_min,
        policy=Policy(args.policy),
        gyro_missing=GyroMissing(args.gyro_missing),
        gyro_wait_ms=args.gyro_wait_ms,
        blur_mode=BlurMode(args.blur_mode),
    )


def run(config: MediatorConfig, network: NetworkConfig, stop: threading.Event | None = None) -> int:
    """Run until ``stop`` is set or KeyboardInterrupt."""
    stop = stop or threading.Event()
    with Node(config.name, network) as node:
        mediator = Mediator(node, config, config.name)
        mediator.log.info(
            "mediator: %s + %s -> %s/images (policy %s, b0 %.1f px)",
            config.camera,
            config.gyro,
            config.name,
            config.policy.value,
            config.b0_px,
        )
        try:
            while not stop.is_set():
                mediator.step()
        except KeyboardInterrupt:
            pass
        finally:
            mediator.close()
    return 0
