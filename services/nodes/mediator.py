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
- gyro/rates: flow-controlled, taken at once by a handler on the executor (a lossless
  consumer: the gyro waits briefly rather than lose samples the blur estimate needs);
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
width x height x bytes per pixel (``bad-payload-size``), or its blur is not a number
(``bad-blur``: NaN or INF in fx_px or gyro_to_camera are refused by the camera model; what
still slips through ends here). Anything else that goes wrong with one frame is logged with
its traceback and recorded as ``internal-error``; the mediator goes on with the next frame.
Gyro batches that cannot be decoded or hold NaN/INF are dropped; samples not newer than the
newest one kept (late, re-delivered or overlapping batches) are dropped; a batch far older
than everything kept is a restarted gyro and starts the cache over. Late or out-of-order
frames are the decider's (``out-of-order``). Messages on the camera's or gyro's
notification key that were no notification (a peer's garbage, oversize, a flood that pushed
them out of the inbox) are counted on ``images`` as ``bad-notification``, with one warning.

Time and stalls: a frame stamped more than ``horizon_s`` ahead of our clock is skipped
(``future-stamp``) before it can become the time-order reference, and so is one stamped more
than 1 s ahead of the camera's own clock (as last measured, within that sample's error; a
camera whose clock stepped forward is measured again at once, and decided from then on). A
new epoch of the camera stream (a restarted camera, our subscription registered again: the
epoch the camera greeted us with; a notification of another epoch, a peer's made-up one, is
decided as a frame but starts nothing over) restarts the time order, and the frames the
camera stored in the gap get ``mediator-lapsed`` records. A new stream that starts before
frames already forwarded removes those from ``images`` only when the camera itself is known
to have started over with a clock that explains the step back (the old clock's sample ran
ahead of the new one's by at least the step, the new one is nearer ours, within the
producer's horizon: ``services.lib.rewind``); the removed frames are counted (skipped
``rewound``) and recorded (``info``'s rewinds), and the detector follows that record.
Anything else (a rogue's single put, a stale stamp) removes nothing: the frames before the
newest forwarded one are dropped ``out-of-order``. Camera and gyro clocks are compared every
2 s and at once after either started over (``ClockOffsets``); until measured, frames are not
paired (``clock-unmeasured``), beyond ``max_clock_offset`` of the exposure neither
(``clock-offset``). Once a flow-controlled consumer has been seen, its lapsed subscription
counts as a full queue (``consumer-lapsed``), never as load 0.

Gyro missing or late (no coverage ``gyro_wait_ms`` after the frame arrived): by default a
frame is forwarded only when the detector is idle (``--gyro-missing idle``); ``accept`` and
``reject`` are the alternatives. Frames wait for coverage side by side, each on its own
deadline, and not at all while the gyro is known to be out, so a dead, stopped or late gyro
never slows the mediator below the camera's rate (``_mediator_pairing``). Outages and
recovery are logged.

Modules: ``_mediator_config`` (settings and flags), ``_mediator_inputs`` (gyro cache, clock
offsets), ``_mediator_pairing`` (frame + gyro -> quality), ``_mediator_output`` (verdicts
carried out and recorded), ``_mediator_restart`` (a camera stream that starts over); this
one routes between them.

Threads: none of its own. The handlers (``on_camera``, ``on_gyro``, ``on_time``, the clock
measurements) run on the node's executor (``attach``): camera and gyro notifications as
they come, the detector's takes (``Producer.on_change``), one deadline at a time for what is
due next (a frame's gyro wait ends, a policy's hold: ``Decider.next_due_ns``), the clocks
every 2 s (asked without waiting: the answers run as handlers when they come). Tests may
drive the same handlers on their own thread instead (tests/services/nodes/mediator_driver.py).
Zenoh's threads only feed the middleware's inboxes.
"""

from __future__ import annotations

import threading
import time
from typing import Protocol

from middleware import (
    PUSH_ALL,
    FramegateError,
    NetworkConfig,
    Node,
    Notification,
    now_ns,
    split_target,
)
from services.lib.decisions import Action, Candidate, Decider, Rules, Verdict, make_policy
from services.lib.messages import check_frame, read_frame_metadata
from services.lib.quality import BlurOptions
from services.nodes._contract import Service, ServiceEntry
from services.nodes._mediator_config import MediatorConfig, add_arguments, config_from_args
from services.nodes._mediator_inputs import (
    GYRO_TAKE_MAX,
    OFFSET_PERIOD_S,
    ClockOffsets,
    GyroCache,
    merge_batch,
)
from services.nodes._mediator_output import Frame, Output
from services.nodes._mediator_pairing import (
    BadFrame,
    Paired,
    Pairing,
    Waiting,
    blur_quality,
)
from services.nodes._mediator_restart import StreamStarts
from services.nodes._not_observed import BadNotifications
from services.nodes._runtime import setup_logging


class _Deadline(Protocol):
    """What ``Node.at`` returns."""

    def cancel(self) -> None: ...


# Gyro notifications queued (deep: a busy mediator never stalls the gyro; see AckPolicy).
GYRO_QUEUE = 256
# Clock measurements asked for at once (frames wait for them) begin at most this often.
_SOON_GAP_NS = 250_000_000
# A frame stamped further ahead of its camera's own clock (beyond that clock's error) is
# skipped ``future-stamp``: a camera stamps its frames when it makes them.
_MAX_AHEAD_NS = 1_000_000_000


class Mediator:
    """The acceptance loop as handlers: camera frames, gyro batches, time (module doc)."""

    def __init__(self, node: Node, config: MediatorConfig, log_name: str = "mediator") -> None:
        self.config = config
        self.log = setup_logging(log_name)
        self.out = Output(
            node,
            policy=config.policy,
            b0_px=config.b0_px,
            horizon_s=config.horizon_s,
            log=self.log,
        )
        self.images = self.out.images
        self.decisions = self.out.decisions
        # Every frame is taken and assessed, so frames come pushed with their notification.
        self._camera = node.subscribe(
            config.camera,
            queue_size=config.camera_queue,
            wait_s=0,
            push_max_bytes=PUSH_ALL,
            await_service=True,  # a pipeline starts every service at once
        )
        gyro, queue = config.gyro, GYRO_QUEUE
        self._gyro_sub = node.subscribe(gyro, queue_size=queue, wait_s=0, await_service=True)
        self.gyro = GyroCache()
        self._camera_name = split_target(config.camera)[0]
        self._gyro_name = split_target(config.gyro)[0]
        self._offsets = ClockOffsets(
            node,
            self._camera_name,
            self._gyro_name,
            lambda service: (
                (self._camera if service == self._camera_name else self._gyro_sub).producer_session
            ),
        )
        self.pairing = Pairing(
            self.gyro,
            self._offsets,
            gyro_wait_ns=int(config.gyro_wait_ms * 1e6),
            b0_px=config.b0_px,
            options=BlurOptions(mode=config.blur_mode),
            max_clock_offset=config.max_clock_offset,
            log=self.log,
            gyro_missing=config.gyro_missing.value,
        )
        self._horizon_ns = int(config.horizon_s * 1e9)
        self._node = node
        # The epoch of the camera stream being decided (None: no frame yet).
        self._camera_epoch: str | None = None
        self._newest_camera_ns: int | None = None
        self.decider = Decider(
            make_policy(config.policy),
            Rules(
                q_min=config.q_min,
                gyro_missing=config.gyro_missing,
                max_hold_ns=int(config.max_hold_ms * 1e6),
            ),
        )
        self.starts = StreamStarts(
            node, config.camera, self._offsets, self.out, self.decider, self.log, self._clock_came
        )
        self._attached = False
        self._timer: _Deadline | None = None
        self._timer_at: int | None = None
        # Camera notifications taken and the newest gyro sample, at the last measurement.
        self._camera_notes = 0
        self._seen: tuple[int | None, int | None] = (0, None)

    @property
    def skipped(self) -> dict[str, int]:
        return self.out.skipped

    @property
    def lapsed(self) -> bool:
        return self.out.lapsed

    @property
    def decisions_dropped(self) -> int:
        return self.out.decisions_dropped

    # -- handlers ---------------------------------------------------------------------------
    def on_camera(self, note: Notification) -> None:
        """One camera notification. Never raises for input."""
        self._camera_notes += 1
        if note.epoch != self._camera_epoch:
            greeted = self._camera.registered_epoch
            if self._camera_epoch is None or greeted is None or note.epoch == greeted:
                self._started_over(note)
                self._camera_epoch = note.epoch
            # Otherwise an epoch the camera did not greet us with (a peer's made-up one, an
            # old registration's straggler): decided as any frame is, but it starts nothing
            # over (the clock samples stay, the time order stands). Not skipped: a forged
            # greeting would then make every real frame "foreign".
        ahead = self._too_far_ahead(note.timestamp_ns)
        if ahead is not None:
            self.out.skip(note.timestamp_ns, 0, "future-stamp", ahead)
            return
        self._newest_camera_ns = note.timestamp_ns
        try:
            frame = self._read(note)
        except BadFrame as exc:
            self.out.skip(note.timestamp_ns, 0, exc.reason, str(exc))
            return
        except Exception as exc:  # one frame must never take the mediator down
            self.log.exception("frame %d: unexpected error; skipped", note.timestamp_ns)
            self.out.skip(note.timestamp_ns, 0, "internal-error", repr(exc))
            return
        self.pairing.add(frame)
        self.on_time(time.monotonic_ns())

    def _too_far_ahead(self, timestamp_ns: int) -> str | None:
        """Why a frame stamped ``timestamp_ns`` is too far ahead to be decided (None: it is
        not): beyond the horizon of our clock, or well ahead of the camera's own clock as
        last measured (inside the horizon such a stamp would hold every later frame out of
        the time order for that long). The camera's clock may have stepped forward since:
        then it is measured again at once, and its frames are decided once it has been."""
        now = now_ns()
        if timestamp_ns > now + self._horizon_ns:
            ahead_s = (timestamp_ns - now) / 1e9
            return (
                f"stamped {ahead_s:.1f} s ahead of our clock (horizon {self.config.horizon_s:g} s)"
            )
        clock = self._offsets.camera_clock or self.starts.clock()
        if clock is not None:
            ahead_ns = timestamp_ns - (now + clock.offset_ns)
            if ahead_ns > _MAX_AHEAD_NS + clock.error_ns:
                self._measure_soon(time.monotonic_ns())
                return (
                    f"stamped {ahead_ns / 1e9:.1f} s ahead of the camera's clock as last "
                    "measured (measured again now)"
                )
        return None

    def on_gyro(self, notes: list[Notification]) -> None:
        """Gyro notifications taken together: frames they cover may be decided now."""
        if self.gyro.feed(self._gyro_sub, notes):  # a restarted gyro: its clock unmeasured
            self._offsets.forget()
        now = time.monotonic_ns()
        if self.pairing.waiting and self._offsets.current() is None:
            self._measure_soon(now)  # frames wait for the clocks, which can be asked now
        self.on_time(now)

    def _measure_soon(self, now: int) -> None:
        """Measure the clocks at once: once, and not while a measurement is out (its end
        starts the next, ``_measured``), nor sooner than ``_SOON_GAP_NS`` after the last
        one began. Asked for on every gyro batch while frames wait for the clocks, it
        asked both services 80 times a second when answers came slowly, and the camera's
        bounded inbox of info queries dropped them: the clocks stayed unknown."""
        if self._offsets.asked.is_set():
            return
        self._offsets.asked.set()
        if self._attached and not self._offsets.measuring:
            self._node.at(max(now, self._offsets.began_ns + _SOON_GAP_NS), self._measure)

    def on_time(self, now: int) -> None:
        """Frames paired or due are decided, held frames may go out or go stale."""
        if not self.starts.resume():
            return
        ready = self.pairing.ready(now)
        for paired in ready:
            self._decide(paired, now)
        if not ready:
            load = self.out.load()
            self.out.carry_out(self.decider, self.decider.tick(load, now), load)

    def next_deadline_ns(self) -> int | None:
        """When ``on_time`` has work next without any input (None: only on input): a
        frame's gyro wait ends, or the decider may decide on held frames."""
        if self.starts.holding:
            return None  # until the camera's clock answers (``_clock_came``)
        due = (self.pairing.next_deadline_ns(), self.decider.next_due_ns(time.monotonic_ns()))
        return min((d for d in due if d is not None), default=None)

    # -- one frame --------------------------------------------------------------------------
    def _read(self, note: Notification) -> Waiting:
        try:
            element = self._camera.fetch(note)
        except FramegateError as exc:
            raise BadFrame("unavailable", str(exc)) from exc
        try:
            meta = read_frame_metadata(element.metadata)
        except (FramegateError, ValueError, TypeError) as exc:
            raise BadFrame("bad-metadata", str(exc)) from exc
        check_frame(meta, len(element.payload))
        return Waiting(meta, element.payload, element.metadata, time.monotonic_ns())

    def _decide(self, paired: Paired, now: int) -> None:
        waiting = paired.frame
        meta = waiting.meta
        if paired.error is not None:
            self.out.skip(meta.timestamp_ns, meta.frame_id, paired.error.reason, str(paired.error))
            return
        if paired.unpaired is not None:
            self.out.count(paired.unpaired)
        candidate = Candidate(
            meta.timestamp_ns,
            meta.frame_id,
            paired.q,
            waiting.arrived_ns,
            paired.blur_px,
            paired.unpaired,
        )
        frame = Frame(meta, waiting.payload, waiting.metadata, candidate)
        load = self.out.load()
        if self.out.lapsed:
            self.out.record(frame, Verdict(candidate, Action.DROP, "consumer-lapsed"), load)
            return
        self.out.pending[candidate.timestamp_ns] = frame
        self.out.carry_out(self.decider, self.decider.frame(candidate, load, now), load)

    # -- a camera stream that starts (over) -------------------------------------------------
    def _started_over(self, note: Notification) -> None:
        """The first frame, or a new epoch of the camera's stream (it restarted, or our
        subscription was registered again): the old stream's frames are decided, and the
        new one's are judged afresh once its clock has answered (``StreamStarts``)."""
        restarted = self._camera_epoch is not None
        if restarted:
            self.log.info("camera stream started over (seq %d): time order restarts", note.seq)
            now = time.monotonic_ns()
            for paired in self.pairing.drain():  # the old stream's frames, still in order
                self._decide(paired, now)
            # Another producer instance may have another clock: measured afresh. The same one
            # registering us again (we lapsed) has the same clock: forgotten, its frames went
            # clock-unmeasured for a round trip (a step shows in the next sample's identity).
            if note.epoch.partition(".")[0] != str(self._camera_epoch).partition(".")[0]:
                self._offsets.forget()
            self._measure_soon(now)
            if self._newest_camera_ns is not None:
                self.starts.missed(self._newest_camera_ns, note.timestamp_ns)
        self.starts.begin(note.timestamp_ns, restarted)

    def _clock_came(self) -> None:
        """(the executor) A new stream's clock answered: its frames may be decided now."""
        if self._attached:
            self.on_time(time.monotonic_ns())
            self._schedule()

    # -- driving it ---------------------------------------------------------------------
    def attach(self) -> None:
        """Register the handlers on the node's executor (``run``): camera and gyro
        notifications, the detector's takes (``Producer.on_change``), the clock
        measurements every ``OFFSET_PERIOD_S``, and one deadline at a time for what is due
        next (a frame's gyro wait, a hold). Nothing polls."""
        self._attached = True

        def camera(notes: list[Notification]) -> None:
            for note in notes:
                self.on_camera(note)
            self._schedule()

        def gyro(notes: list[Notification]) -> None:
            self.on_gyro(notes)
            self._schedule()

        def taken() -> None:
            if self.decider.held:
                self.on_time(time.monotonic_ns())
                self._schedule()

        self._node.on(self._camera, camera)
        self._node.on(self._gyro_sub, gyro, max_batch=GYRO_TAKE_MAX)
        self.images.on_change(taken)
        self._node.every(OFFSET_PERIOD_S, self._measure)
        self._node.at(time.monotonic_ns(), self._measure)
        bad = BadNotifications(self.images, lambda _kind, text: self.log.warning("%s", text))
        inputs = (self._camera, self._gyro_sub)
        self._node.every(
            OFFSET_PERIOD_S, lambda _now: bad.total_is(sum(s.garbage + s.dropped for s in inputs))
        )

    def _measure(self, now: int) -> None:
        if self._offsets.measuring:
            return  # one at a time: its end measures again if that was asked meanwhile
        # A source is asked when its data came since the last measurement, or it answered
        # the last ask, or its back-off after a miss passed (``ClockOffsets.due``): a
        # stopped one holds the executor for the whole timeout only once per back-off. Not
        # on data alone: a camera that sent one frame before the gyro was up (or whose one
        # ask was missed under load) would never be asked again, its offset never measured.
        seen = (self._camera_notes, self.gyro.newest_ns)
        names = (self._camera_name, self._gyro_name)
        alive = [
            new != old or self._offsets.asked.is_set() or self._offsets.due(name, now)
            for new, old, name in zip(seen, self._seen, names, strict=True)
        ]
        self._seen = seen
        # The answers come later, on the executor: a round trip here would hold up every
        # frame and every hold for that long (100-250 ms under load, every period).
        self._offsets.measure(camera_alive=alive[0], gyro_alive=alive[1], then=self._measured)

    def _measured(self) -> None:
        """(the executor) A clock measurement is in: frames may have waited for it."""
        if self._attached and self._offsets.asked.is_set():  # asked while it was out
            at = max(time.monotonic_ns(), self._offsets.began_ns + _SOON_GAP_NS)
            self._node.at(at, self._measure)
        if self._attached and self.pairing.waiting:
            self.on_time(time.monotonic_ns())
            self._schedule()

    def _schedule(self) -> None:
        """Keep one deadline on the executor, at ``next_deadline_ns``."""
        due = self.next_deadline_ns()
        if self._timer is not None and self._timer_at == due:
            return
        if self._timer is not None:
            self._timer.cancel()
            self._timer = None
        if due is not None:
            self._timer, self._timer_at = self._node.at(due, self._on_timer), due

    def _on_timer(self, now: int) -> None:
        self._timer = None
        self.on_time(now)
        self._schedule()

    def close(self) -> None:
        """Stop the deadlines and the load callback (the node closes the subscriptions)."""
        self.images.on_change(None)
        if self._timer is not None:
            self._timer.cancel()


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
        mediator.attach()
        try:
            node.spin(stop)
        except KeyboardInterrupt:
            pass
        finally:
            mediator.close()
            mediator.log.info("%s: %s", config.name, mediator.out.summary())
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
    "merge_batch",
    "run",
]

SERVICE: Service[MediatorConfig] = ServiceEntry(
    "mediator", MediatorConfig, add_arguments, config_from_args, run
)
