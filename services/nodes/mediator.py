"""The mediator (paper §4.3, Fig. 5): forwards a frame to the detector only if its
gyro-estimated quality beats the detector's load.

This module is the thin I/O around ``services.lib.decisions``: it takes camera frames and
gyro batches, turns each frame into a quality, feeds the pure :class:`Decider` with the
quality, the detector's queue and the clock, and carries out the verdicts (put the frame to
mediator/images, keep its bytes while held, record every decision). The policies (``paper``:
q > load; ``replace``: hold the sharpest frames, one per free slot) and the gyro-missing
rule live, and are tested, there.

Buffering rules chosen here:
- camera/images: flow-controlled with a deep queue (default 8), taken at once, so the
  mediator never is the reason a frame is dropped at the camera;
- gyro/rates: flow-controlled, taken at once by a thread of its own (a lossless consumer:
  the gyro waits briefly rather than lose samples the blur estimate needs);
- mediator/images: offered with the detector as a flow-controlled subscriber; its queue is
  the load indicator, and it is the mediator's one flow-controlled output. A frame is only
  put when the decider says so; a refusal all the same drops that frame (``refused``).
- mediator/decisions: bookkeeping. A record never waits and never raises out of the
  mediator: a record refused because a subscriber flow-controls the buffer (or rejected for
  any other reason) is counted (``decisions_dropped``, logged) and dropped. A slow watcher
  loses records; it never slows or stops the frames.

Failure behaviour (every input a peer can produce): metadata that passes its XSD is not
trusted. A frame is skipped, counted and recorded with a reason when its metadata cannot be
read (``bad-metadata``), its size or exposure is zero or negative (``bad-size``,
``bad-exposure``), its encoding is unknown (``bad-encoding``), its payload does not hold
width x height x channels bytes (``bad-payload-size``), or its blur is not a number
(``bad-blur``: NaN or INF in fx_px or gyro_to_camera are refused by the camera model; what
still slips through ends here). Anything else that goes wrong with one frame is logged with
its traceback and recorded as ``internal-error``; the mediator goes on with the next frame.
Gyro batches that cannot be decoded or hold NaN/INF are dropped; samples not newer than the
newest one kept (late, re-delivered or overlapping batches) are dropped; a batch far older
than everything kept is a restarted gyro and starts the cache over. Late or out-of-order
frames are the decider's (``out-of-order``).

Time and stalls: a frame stamped more than ``horizon_s`` ahead of our clock is skipped
(``future-stamp``) before it can become the time-order reference; a new epoch of the camera
stream (a restarted camera, our subscription registered again) restarts the time order, and
the frames the camera stored in the gap get ``mediator-lapsed`` records. A new stream that
starts before frames already forwarded (a camera restarted after its clock was stepped back,
after a rogue's future stamp) removes those from ``images`` (counted skipped ``rewound``) so
that its frames can follow at once; the detector does the same with its detections. Camera and gyro
clocks are compared every 2 s (``ClockOffsets``); beyond ``max_clock_offset`` of the exposure
frames are not paired (``clock-offset``). Once a flow-controlled consumer has been seen, its
lapsed subscription counts as a full queue (``consumer-lapsed``), never as load 0.

Gyro missing or late (no coverage ``gyro_wait_ms`` after the exposure ended): by default a
frame is forwarded only when the detector is idle (``--gyro-missing idle``); ``accept`` and
``reject`` are the alternatives. Outages and recovery are logged.

Threads: ``step`` runs on the caller's thread and owns the decider and the held frames'
bytes; the gyro cache's thread takes gyro notifications and shares only the batch list,
guarded by its condition. Zenoh's threads only feed the middleware's queues.
"""

from __future__ import annotations

import argparse
import collections
import threading
import time
from dataclasses import dataclass

import numpy as np

from middleware import (
    PUSH_ALL,
    FlowControlRefused,
    FramegateError,
    NetworkConfig,
    Node,
    Notification,
    Producer,
    Retention,
    now_ns,
    split_target,
)
from services.lib.decisions import (
    DEFAULT_POLICY,
    POLICIES,
    Action,
    Candidate,
    Decider,
    GyroMissing,
    Load,
    Rules,
    Verdict,
    make_policy,
)
from services.lib.messages import FRAME_CHANNELS, DecisionRecord, FrameMeta, read_frame_metadata
from services.lib.quality import (
    DEFAULT_B0_PX,
    BlurMode,
    BlurOptions,
    CoverageError,
    GyroSamples,
    estimate_blur,
    quality,
)
from services.nodes._contract import Service, ServiceEntry
from services.nodes._mediator_inputs import (
    ClockOffsets,
    GyroCache,
    _tightest,
    detector_load,
    merge_batch,
)
from services.nodes._runtime import Monotonic, setup_logging

# While frames are held, poll this often so they go out when the detector's queue drains.
_HOLD_POLL_S = 0.005


@dataclass(frozen=True, slots=True)
class MediatorConfig:
    """Everything the mediator can be told (one flag per field)."""

    name: str = "mediator"
    camera: str = "camera/images"
    gyro: str = "gyro/rates"
    camera_queue: int = 8
    b0_px: float = DEFAULT_B0_PX
    q_min: float = 0.0
    policy: str = DEFAULT_POLICY
    gyro_missing: GyroMissing = GyroMissing.DEFAULT
    gyro_wait_ms: float = 150.0
    blur_mode: BlurMode = BlurMode.DEFAULT
    max_hold_ms: float = 250.0
    horizon_s: float = 10.0
    max_clock_offset: float = 0.5


@dataclass(frozen=True, slots=True)
class _Frame:
    meta: FrameMeta
    payload: bytes
    metadata: bytes
    candidate: Candidate


class BadFrame(Exception):
    """A frame the mediator skips; ``reason`` goes into its decision record."""

    def __init__(self, reason: str, detail: str) -> None:
        super().__init__(detail)
        self.reason = reason


def check_frame(meta: FrameMeta, payload_bytes: int) -> None:
    """Raise BadFrame for a frame no detector could use, whatever its XSD allowed."""
    if meta.width_px <= 0 or meta.height_px <= 0:
        raise BadFrame("bad-size", f"size {meta.width_px}x{meta.height_px}")
    if meta.exposure.duration_ns <= 0:
        raise BadFrame("bad-exposure", f"exposure of {meta.exposure.duration_ns} ns")
    channels = FRAME_CHANNELS.get(meta.encoding)
    if channels is None:
        raise BadFrame("bad-encoding", f"encoding {meta.encoding!r}")
    expected = meta.width_px * meta.height_px * channels
    if payload_bytes != expected:
        raise BadFrame(
            "bad-payload-size",
            f"payload of {payload_bytes} bytes, {meta.width_px}x{meta.height_px} "
            f"{meta.encoding} needs {expected}",
        )


def blur_quality(
    meta: FrameMeta, samples: GyroSamples, options: BlurOptions, b0_px: float
) -> tuple[float, float]:
    """Blur and quality of a frame with a camera model; BadFrame when they are not numbers.

    CoverageError when the samples do not cover the exposure (the gyro-missing rule).
    """
    assert meta.camera is not None
    try:
        with np.errstate(all="ignore"):  # a NaN result is checked below, not warned about
            blur = float(estimate_blur(samples, meta.exposure, meta.camera, options).blur_px)
    except CoverageError:
        raise
    except (FramegateError, ValueError, ArithmeticError) as exc:
        raise BadFrame("bad-blur", str(exc)) from exc
    if not blur >= 0.0:  # NaN (INF or NaN in the camera model) is not a quality
        raise BadFrame("bad-blur", f"blur of {blur} px")
    return blur, quality(blur, b0_px)


class Mediator:
    """The acceptance loop; ``step`` handles one camera notification or a timeout."""

    def __init__(self, node: Node, config: MediatorConfig, log_name: str = "mediator") -> None:
        self.config = config
        self.log = setup_logging(log_name)
        self.images: Producer = node.offer(
            "images", kind="frame", retention=Retention(max_count=64, max_bytes=256 * 2**20)
        )
        self.decisions: Producer = node.offer(
            "decisions", kind="decision", retention=Retention(max_count=100_000)
        )
        # Every frame is taken and assessed, so frames come pushed with their notification.
        self._camera = node.subscribe(
            config.camera,
            queue_size=config.camera_queue,
            wait_s=0,
            push_max_bytes=PUSH_ALL,
            await_service=True,  # a pipeline starts every service at once
        )
        self._gyro = GyroCache(
            node.subscribe(config.gyro, queue_size=256, wait_s=0, await_service=True)
        )
        self._offsets = ClockOffsets(
            node, split_target(config.camera)[0], split_target(config.gyro)[0]
        )
        self._offset_ok = True
        self._horizon_ns = int(config.horizon_s * 1e9)
        self._node = node
        self._camera_seq: int | None = None
        self._newest_camera_ns: int | None = None
        self._newest_put_ns: int | None = None
        # The flow-controlled consumer (the detector): whether one was ever seen, whether
        # its subscription has lapsed, and the frames last seen waiting in its queue.
        self._consumer_capacity: int | None = None
        self.lapsed = False
        self._queued_frames: collections.deque[_Frame] = collections.deque()
        self._last_load = Load(0, 0)
        self._options = BlurOptions(mode=config.blur_mode)
        self._keys = Monotonic()
        self.decider = Decider(
            make_policy(config.policy),
            Rules(
                q_min=config.q_min,
                gyro_missing=config.gyro_missing,
                max_hold_ns=int(config.max_hold_ms * 1e6),
            ),
        )
        self._pending: dict[int, _Frame] = {}  # frames the decider holds, by key
        self._gyro_ok = True
        self.skipped = collections.Counter[str]()
        self.decisions_dropped = 0
        self._policy_faults_logged = 0

    # -- one frame --------------------------------------------------------------------------
    def step(self, timeout_s: float = 0.5) -> None:
        """Take one camera notification (or time out) and decide. Never raises for input."""
        wait = _HOLD_POLL_S if self.decider.held else timeout_s
        note = self._camera.take(timeout_s=wait)
        if note is None:
            load = self._load()
            self._carry_out(self.decider.tick(load, time.monotonic_ns()), load)
            return
        if self._camera_seq is not None and note.seq <= self._camera_seq:
            # A new epoch of the camera's stream (it restarted, or our subscription was
            # registered again): its frames are judged afresh, not against the old ones.
            self.log.info("camera stream started over (seq %d): time order restarts", note.seq)
            floor = self._newest_put_ns
            if floor is not None and note.timestamp_ns <= floor:
                # It starts before frames we forwarded: those were stamped by a clock now
                # known to be wrong (a camera restarted after its clock was stepped back, a
                # rogue's future stamp). Kept, they would hold every later frame out of the
                # detector's time-ordered buffer for as long as the error.
                self.images.discard_after(note.timestamp_ns - 1, "rewound")
                floor = self.images.series.newest_ns or 0
                self._newest_put_ns = floor or None
            self.decider.restart_order(floor)
            self._offsets.forget()  # maybe another process, another clock
            self._record_missed(note.timestamp_ns)
        self._camera_seq = note.seq
        if note.timestamp_ns > now_ns() + self._horizon_ns:
            ahead_s = (note.timestamp_ns - now_ns()) / 1e9
            self._skip(
                note.timestamp_ns,
                0,
                "future-stamp",
                f"stamped {ahead_s:.1f} s ahead of our clock (horizon {self.config.horizon_s:g} s)",
            )
            return
        self._newest_camera_ns = note.timestamp_ns
        try:
            frame = self._assess(note)
        except BadFrame as exc:
            self._skip(note.timestamp_ns, 0, exc.reason, str(exc))
            return
        except Exception as exc:  # one frame must never take the mediator down
            self.log.exception("frame %d: unexpected error; skipped", note.timestamp_ns)
            self._skip(note.timestamp_ns, 0, "internal-error", repr(exc))
            return
        load = self._load()
        if self.lapsed:
            self._record(frame, Verdict(frame.candidate, Action.DROP, "consumer-lapsed"), load)
            return
        self._pending[frame.candidate.timestamp_ns] = frame
        self._carry_out(self.decider.frame(frame.candidate, load, time.monotonic_ns()), load)

    def _record_missed(self, until_ns: int) -> None:
        """Record the frames the camera stored between the last one we took and ``until_ns``.

        They were stored while our subscription had lapsed (this process was stopped or
        cut off past the lease) or before it registered with a restarted camera; none will
        ever be notified, and each gets a ``mediator-lapsed`` record. Frames the camera's
        retention has already evicted cannot be named; their count is not known here.
        """
        last = self._newest_camera_ns
        if last is None or until_ns <= last + 1:
            return
        try:
            missed = self._node.query(
                self.config.camera, time_range=f"[{last + 1}..{until_ns - 1}]", timeout_s=5.0
            )
        except FramegateError as exc:
            self.log.warning("cannot look up the frames missed before %d: %s", until_ns, exc)
            return
        for element in missed:
            try:
                frame_id = read_frame_metadata(element.metadata).frame_id
            except (FramegateError, ValueError, TypeError):
                frame_id = 0
            self._skip(element.timestamp_ns, frame_id, "mediator-lapsed", "stored while not taken")
        if missed:
            self.log.warning(
                "%d frames were stored while our camera subscription had lapsed: "
                "recorded mediator-lapsed",
                len(missed),
            )

    def _load(self) -> Load:
        """The detector's load; full while the subscription of a consumer we had lapsed.

        A flow-controlled consumer that stops answering (stopped, frozen, partitioned)
        loses its subscription after the lease; to the producer that looks like no
        consumer at all (load 0), and frames forwarded then are lost without a trace.
        So once a flow-controlled consumer has been seen, its absence means full: frames
        are recorded ``consumer-lapsed`` (not forwarded) until a consumer is back, and the
        frames that were waiting in its queue when it lapsed get a ``consumer-lapsed``
        record too. A mediator that never had one (uncontrolled wiring) forwards as before.
        """
        load, tightest = _tightest(self.images.subscriptions())
        if tightest is not None:
            if self.lapsed:
                self.lapsed = False
                self.log.warning("the detector's subscription is back: forwarding again")
            self._consumer_capacity = tightest.queue_size
            self._last_load = load
            return load
        if self._consumer_capacity is None:
            return load
        full = Load(self._consumer_capacity, self._consumer_capacity)
        if not self.lapsed:
            self.lapsed = True
            queued = self._last_load.queued
            waiting = list(self._queued_frames)[-queued:] if queued else []
            self.log.warning(
                "the detector's subscription lapsed (a stopped or unreachable consumer); "
                "frames are recorded consumer-lapsed, not forwarded, until it is back "
                "(%d forwarded frames were waiting in its queue)",
                len(waiting),
            )
            for frame in waiting:
                self._record(frame, Verdict(frame.candidate, Action.DROP, "consumer-lapsed"), full)
            self._queued_frames.clear()
        self._last_load = full
        return full

    def _assess(self, note: Notification) -> _Frame:
        try:
            element = self._camera.fetch(note)
        except FramegateError as exc:
            raise BadFrame("unavailable", str(exc)) from exc
        try:
            meta = read_frame_metadata(element.metadata)
        except (FramegateError, ValueError, TypeError) as exc:
            raise BadFrame("bad-metadata", str(exc)) from exc
        check_frame(meta, len(element.payload))
        blur, q = self._quality(meta)
        arrived = time.monotonic_ns()
        unpaired = None if self._offset_ok else "clock-offset"
        if unpaired:
            self.skipped[unpaired] += 1
            self.images.count_skip(unpaired)
        candidate = Candidate(meta.timestamp_ns, meta.frame_id, q, arrived, blur, unpaired)
        return _Frame(meta, element.payload, element.metadata, candidate)

    def _quality(self, meta: FrameMeta) -> tuple[float | None, float | None]:
        """Blur and quality of a frame, or (None, None) when the gyro does not cover it."""
        camera = meta.camera
        if camera is None:
            return None, None
        if not self._clocks_agree(meta):
            return None, None
        end_ns = meta.exposure.end_ns
        gyro_end = end_ns + camera.gyro_time_offset_ns + camera.height_px * camera.line_readout_ns
        covered = self._gyro.wait_covering(gyro_end, self.config.gyro_wait_ms / 1e3)
        result: tuple[float, float] | None = None
        if covered:
            start = meta.exposure.start_ns + camera.gyro_time_offset_ns
            samples = self._gyro.window(start, gyro_end)
            try:
                result = blur_quality(meta, samples, self._options, self.config.b0_px)
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
            return None, None
        if not self._gyro_ok:
            self.log.warning("gyro covers frames again from frame %d", meta.frame_id)
            self._gyro_ok = True
        assert result is not None
        return result

    def _clocks_agree(self, meta: FrameMeta) -> bool:
        """False when camera and gyro clocks are too far apart to pair their stamps.

        Pairing looks up the gyro samples stamped during the frame's exposure; if the two
        clocks disagree by more than ``max_clock_offset`` of the exposure (beyond what the
        measurement can tell), those samples are of another moment. Warned once per
        episode; such frames are ``clock-offset`` (the gyro-missing rule decides).
        """
        measured = self._offsets.current()
        limit_ns = self.config.max_clock_offset * meta.exposure.duration_ns
        agree = measured is None or abs(measured[0]) - measured[1] <= limit_ns
        if agree != self._offset_ok:
            self._offset_ok = agree
            if agree and measured is None:  # a source restarted: its clock not measured yet
                self.log.warning("camera or gyro started over: paired again until measured")
            elif agree and measured is not None:
                self.log.warning("camera and gyro clocks agree again (%+.1f ms)", measured[0] / 1e6)
            elif measured is not None:
                self.log.warning(
                    "camera clock is %+.3f s (+-%.3f) off the gyro's, more than %g of the "
                    "%.0f ms exposure: frames are not paired with gyro samples (clock-offset) "
                    "until they agree; synchronise the clocks (chrony)",
                    measured[0] / 1e9,
                    measured[1] / 1e9,
                    self.config.max_clock_offset,
                    meta.exposure.duration_ns / 1e6,
                )
        return agree

    # -- carrying out -------------------------------------------------------------------------
    def _carry_out(self, verdicts: list[Verdict], load: Load) -> None:
        """Put forwarded frames, record every verdict with the load the decider saw."""
        for verdict in verdicts:
            key = verdict.frame.timestamp_ns
            frame = self._pending.get(key)
            if verdict.action is not Action.HOLD:
                self._pending.pop(key, None)
            if frame is None:
                continue
            if verdict.action is Action.FORWARD and (why := self._put(frame)) is not None:
                verdict = self.decider.refused(verdict.frame)
                if why == "consumer-lapsed":
                    verdict = Verdict(verdict.frame, Action.DROP, why)
            self._record(frame, verdict, load)
        if self.decider.policy_faults > self._policy_faults_logged:
            self._policy_faults_logged = self.decider.policy_faults
            self.log.warning(
                "policy %s broke its contract (%d times so far)",
                self.config.policy,
                self.decider.policy_faults,
            )

    def _put(self, frame: _Frame) -> str | None:
        """Forward a frame: None once a consumer is told of it, else why not (``refused``;
        ``consumer-lapsed``: stored, but the consumer we had was not registered at that
        moment, a lapse between two looks at the load, so no notification will reach it)."""
        try:
            notified = self.images.put(frame.meta.timestamp_ns, frame.payload, frame.metadata)
        except FlowControlRefused:
            return "refused"
        except FramegateError as exc:
            self.log.warning("cannot forward frame %d: %s", frame.meta.frame_id, exc)
            return "refused"
        self._newest_put_ns = frame.meta.timestamp_ns
        if notified == 0 and self._consumer_capacity is not None:
            return "consumer-lapsed"
        self._queued_frames.append(frame)
        while len(self._queued_frames) > max(1, self._consumer_capacity or 1):
            self._queued_frames.popleft()
        return None

    def _record(self, frame: _Frame, verdict: Verdict, load: Load) -> None:
        candidate = frame.candidate
        self._write(
            DecisionRecord(
                frame_timestamp_ns=candidate.timestamp_ns,
                frame_id=candidate.frame_id,
                blur_px=candidate.blur_px,
                quality=candidate.q,
                load=load.fill,
                accepted=verdict.action is Action.FORWARD,
                reason=verdict.reason,
                policy=self.config.policy,
                b0_px=self.config.b0_px,
                latency_ns=now_ns() - frame.meta.exposure.end_ns,
            )
        )

    def _skip(self, key_ns: int, frame_id: int, reason: str, detail: str) -> None:
        self.skipped[reason] += 1
        self.images.count_skip(reason)
        count = self.skipped[reason]
        if count & (count - 1) == 0:  # 1, 2, 4, 8...: visible, never a flood
            self.log.warning("skipping frame %d (%s, %d so far): %s", key_ns, reason, count, detail)
        self._write(
            DecisionRecord(
                frame_timestamp_ns=key_ns,
                frame_id=frame_id,
                blur_px=None,
                quality=None,
                load=self._last_load.fill,
                accepted=False,
                reason=reason,
                policy=self.config.policy,
                b0_px=self.config.b0_px,
                latency_ns=0,
            )
        )

    def _write(self, record: DecisionRecord) -> None:
        """Put a decision record; a refusal or rejection is counted, never raised."""
        key = self._keys.next()
        try:
            self.decisions.put(key, b"", record.metadata(key))
        except FramegateError as exc:
            self.decisions_dropped += 1
            n = self.decisions_dropped
            if n & (n - 1) == 0:
                self.log.warning("decision record dropped (%d so far): %s", n, exc)

    def close(self) -> None:
        self._gyro.stop()
        self._offsets.stop()


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """The mediator's flags (``framegate run mediator --help``): one per config field."""
    from services.lib.argtypes import non_negative_float, positive_float, positive_int, unit_float

    d = MediatorConfig()
    parser.add_argument("--name", default=d.name, help="service name (default %(default)s)")
    parser.add_argument("--camera", default=d.camera, help="frames to filter (SERVICE/BUFFER)")
    parser.add_argument("--gyro", default=d.gyro, help="gyro batches (SERVICE/BUFFER)")
    parser.add_argument(
        "--camera-queue",
        type=positive_int,
        default=d.camera_queue,
        help="notification queue on the camera (deep: never stall it)",
    )
    parser.add_argument(
        "--b0",
        type=positive_float,
        default=d.b0_px,
        dest="b0_px",
        help="blur scale b0 in pixels: q = exp(-blur/b0) (default %(default)s)",
    )
    parser.add_argument("--q-min", type=unit_float, default=d.q_min, help="minimum quality")
    parser.add_argument(
        "--policy",
        choices=sorted(POLICIES),
        default=d.policy,
        help="paper: q > load; replace: hold the sharpest frames, one per free slot",
    )
    parser.add_argument(
        "--gyro-missing",
        choices=[g.value for g in GyroMissing],
        default=d.gyro_missing.value,
        help="frames without gyro coverage: idle = accept only when idle",
    )
    parser.add_argument(
        "--gyro-wait-ms",
        type=non_negative_float,
        default=d.gyro_wait_ms,
        help="how long to wait for gyro coverage after exposure end",
    )
    parser.add_argument(
        "--blur-mode",
        choices=[m.value for m in BlurMode if m is not BlurMode.POINT],
        default=d.blur_mode.value,
        help="where blur is measured (paper: center)",
    )
    parser.add_argument(
        "--max-hold-ms",
        type=non_negative_float,
        default=d.max_hold_ms,
        help="longest a frame may be held for the detector (default %(default)s)",
    )
    parser.add_argument(
        "--horizon-s",
        type=positive_float,
        default=d.horizon_s,
        help="frames stamped further ahead of our clock are skipped (default %(default)s)",
    )
    parser.add_argument(
        "--max-clock-offset",
        type=positive_float,
        default=d.max_clock_offset,
        help="camera-gyro clock offset allowed, as a fraction of the exposure (default "
        "%(default)s)",
    )


def config_from_args(args: argparse.Namespace) -> MediatorConfig:
    """The config the parsed flags describe."""
    return MediatorConfig(
        name=args.name,
        camera=args.camera,
        gyro=args.gyro,
        camera_queue=args.camera_queue,
        b0_px=args.b0_px,
        q_min=args.q_min,
        policy=args.policy,
        gyro_missing=GyroMissing(args.gyro_missing),
        gyro_wait_ms=args.gyro_wait_ms,
        blur_mode=BlurMode(args.blur_mode),
        max_hold_ms=args.max_hold_ms,
        horizon_s=args.horizon_s,
        max_clock_offset=args.max_clock_offset,
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
            config.policy,
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


# Re-exported: the inputs are part of what the mediator module offers.
__all__ = [
    "SERVICE",
    "BadFrame",
    "ClockOffsets",
    "GyroCache",
    "Mediator",
    "MediatorConfig",
    "add_arguments",
    "blur_quality",
    "check_frame",
    "config_from_args",
    "detector_load",
    "merge_batch",
    "run",
]

SERVICE: Service[MediatorConfig] = ServiceEntry(
    "mediator", MediatorConfig, add_arguments, config_from_args, run
)
