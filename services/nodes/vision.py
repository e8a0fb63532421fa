"""Your own vision function behind the mediator, as its flow-controlled consumer: the
mediator forwards fewer, sharper frames the slower it is (docs/vision.md).

The handler (see ``services/lib/vision.py`` for what it receives and returns) runs as a
flow-controlled consumer of ``mediator/images``: the fill of this subscription's queue is
the load the mediator compares each frame's quality with, so the frames it forwards follow
the handler's real speed. Its results are offered as ``NAME/detections`` (boxes) or
``NAME/results`` (anything else), keyed by the frame's timestamp.

Buffering rule: flow-controlled subscriber with queue N (default 2), as in the paper. A
notification leaves the queue when taken, before processing, so up to N more frames may
wait while one is processed. The output never waits: a result refused because a subscriber
of the output flow-controls it is dropped (counted ``refused``), so a slow watcher of the
results never slows the vision code or, through it, the mediator.

Failures, each a counted skip of the output buffer (``framegate info NAME/detections``),
with one warning per kind, never a crash or a stalled queue: a frame whose metadata or
payload cannot be read (``bad-frame``), a handler that raises (``handler-error:TYPE``), a
result that does not fit the buffer (``bad-result``), no result (``no-result``), an input
element not after the last result (``out-of-order``); messages on the input subscription's
key that were no notification (``bad-notification``: garbage, oversize, pushed out by a
flood; no frame, but counted here so that a flood shows). A handler that cannot be imported,
or a name that is not callable, is refused before anything starts (one ``error:`` line,
exit 1; ``framegate launch --check`` reports it for a deploy file).

Rewinds: results are never removed because of one input element. Only a rewind the input's
producer recorded (``BufferInfo.rewinds``: the mediator's, after a camera restarted with its
clock behind) removes the results it explains (counted ``rewound``), mirroring what the
producer removed (``RewindFollower``). Any other stale element, forged or not, is
``out-of-order``, and nothing is removed.

Threads: the service's main thread runs the loop (take one notification, process, put); the
handler runs on one long-lived thread of its own (``CallThread``, ``vision-handler``), one
call at a time, so that a stop is honoured while it is inside native code; a handler class
is created on that thread too, so per-thread state carries from call to call. The loop is
deliberately not a handler on the node's executor: a vision function runs for a frame period
or more, and there it would hold up the node's other duties for that long -- among them a
delayed ack of the frame just taken, so the mediator would read the queue fuller than it is
while the handler runs, and acks and resends for watchers of the results. ``Runner.handle``
has an executor handler's shape (a batch of notifications) should that trade be wanted. The
executor's one duty of this service is a timer that counts the frames an ``--observe``
runner's queue dropped while the handler runs (``NotObserved``), and the messages on its
key that were no notification (``BadNotifications``; its one warning shares the step's set of
kinds warned, which the loop's thread also adds to). ``VisionStep``
(``_vision_step.py``) is the per-frame work with no I/O, called directly by tests.
"""

from __future__ import annotations

import argparse
import logging
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass

from middleware import (
    PUSH_ALL,
    BufferInfo,
    ConfigError,
    DataObject,
    FlowControlRefused,
    FramegateError,
    NetworkConfig,
    Node,
    NotFoundError,
    Notification,
    Producer,
    Retention,
    SubscriptionMode,
    now_ns,
)
from services.lib.argtypes import positive_int
from services.lib.rewind import RewindFollower
from services.lib.settings import add_flags, from_args, setting
from services.lib.vision import ResultKind
from services.nodes._contract import Service, ServiceEntry
from services.nodes._not_observed import BadNotifications, NotObserved
from services.nodes._runtime import CallThread, setup_logging
from services.nodes._vision_handler import (
    Handler,
    handler_argument,
    handler_name,
    load_handler,
    result_kind,
)
from services.nodes._vision_step import Skipped, VisionStep

# How often the frames an --observe runner lost are counted while its handler runs.
_MISSED_PERIOD_S = 0.5
# How long reading the input producer's recorded rewinds waits for its answer.
_INPUT_INFO_TIMEOUT_S = 1.0


@dataclass(frozen=True, slots=True)
class RunnerConfig:
    """What every vision runner is told (``framegate run vision`` and ``detector``)."""

    name: str = setting("vision", "service name")
    input: str = setting(
        "mediator/images", "frames to process: mediator/images (filtered) or camera/images"
    )
    queue: int = setting(2, "notification queue size N", parse=positive_int)
    # Observe instead of taking part in flow control: while the queue is full its oldest
    # frames are missed by this runner only (as a camera dropping at the source would for it
    # alone), so a second, uncontrolled runner never holds the camera back for the others.
    observe: bool = setting(
        False, "never hold the input's producer back: a full queue drops its oldest frame instead"
    )

    def spec(self, output: str, kind: ResultKind, processing_floor_s: float = 0.0) -> RunnerSpec:
        """What the runner needs, with what this service adds."""
        return RunnerSpec(
            self.name, self.input, self.queue, output, kind, self.observe, processing_floor_s
        )


@dataclass(frozen=True, slots=True)
class VisionConfig(RunnerConfig):
    """Everything ``framegate run vision`` can be told."""

    handler: str | None = setting(
        None,
        "your vision code, called once per frame as handler(image, frame) with the image "
        "as a NumPy array; it returns a list of Box (services.lib.vision; stored in "
        "NAME/detections), an "
        "Output or bytes (NAME/results; annotate it '-> Output'), or None (no result). "
        "Named package.module:function, module:Class.method or module:Class (created "
        "once with no arguments), or path/to/file.py:function; the current directory is "
        "importable (docs/vision.md)",
        parse=handler_argument,
        metavar="MODULE:FUNCTION",
        required=True,
    )
    output: str | None = setting(
        None, "the results buffer (default: detections for boxes, results otherwise)"
    )
    kind: str = setting(
        "auto",
        "the results buffer's kind; auto: from the handler's return annotation",
        choices=("auto", *(k.value for k in ResultKind)),
    )


@dataclass(frozen=True, slots=True)
class RunnerSpec:
    """What the runner needs, whichever service (vision, detector) configured it."""

    name: str
    input: str
    queue: int
    output: str
    kind: ResultKind
    observe: bool = False
    # Emulated load (the detector's --service-factor): each frame takes at least this long.
    processing_floor_s: float = 0.0


class _Stopped(BaseException):
    """The service was stopped while the handler ran (not a handler error)."""


# -- the service ---------------------------------------------------------------------------
class Runner:
    """The I/O around a :class:`VisionStep`: take a frame, fetch it, process, offer."""

    def __init__(
        self, spec: RunnerSpec, step: VisionStep, node: Node, output: Producer,
        stop: threading.Event,
    ) -> None:  # fmt: skip
        self.spec = spec
        self.step = step
        self.node = node
        self.output = output
        self.rewinds = RewindFollower(
            node, spec.input, output, step.log, timeout_s=_INPUT_INFO_TIMEOUT_S
        )
        self.stop = stop
        self.not_observed = NotObserved(output)

    def handle(
        self,
        notes: list[Notification],
        fetch: Callable[[Notification], DataObject],
        producer_epoch: str | None = None,
        producer_session: str | None = None,
    ) -> None:
        """Process a batch of notifications (one per turn today; an executor handler later);
        ``producer_epoch``, ``producer_session``: the input subscription's (rewinds are
        followed only as far as the producer that greeted it delivered, and as it tells)."""
        for note in notes:
            if self.stop.is_set():
                return
            taken_ns = now_ns()  # the frames' clock: what the runner did when, beside them
            self.rewinds.seen(producer_epoch, producer_session)
            if note.missed:  # an observer's full queue (keep-last), or a lapse: never seen
                self.not_observed.carried(note.missed)
            if not self._in_order(note.timestamp_ns):
                continue
            try:
                element = fetch(note)
            except FramegateError as exc:
                detail = f"frame stamped {note.timestamp_ns}: {exc}"
                self._count(self.step.skip("bad-frame", detail))
                continue
            outcome = self.step.process(
                element.timestamp_ns, element.payload, element.metadata, taken_ns
            )
            if isinstance(outcome, Skipped):
                self._count(outcome)
                continue
            try:
                self.output.put(note.timestamp_ns, outcome.payload, outcome.metadata)
            except FramegateError as exc:
                # Refused (a full flow-controlled watcher) or rejected (too large, ...):
                # counted so by the producer; the frame's result is lost, said once per kind.
                counter = "refused" if isinstance(exc, FlowControlRefused) else "rejected"
                self.step.warn_once(
                    f"put-{type(exc).__name__}",
                    f"cannot store the result of the frame stamped {note.timestamp_ns}: {exc} "
                    f"(counted as {counter} in 'framegate info {self.output.name}'; further "
                    "ones are not logged)",
                )

    def _count(self, skipped: Skipped) -> None:
        self.output.count_skip(skipped.reason)

    def _in_order(self, timestamp_ns: int) -> bool:
        """Whether a result for ``timestamp_ns`` can follow ours; removes our later results
        only as a rewind the input's producer recorded says (see the module docstring)."""
        newest = self.output.series.newest_ns
        if newest is None or timestamp_ns > newest:
            return True
        if self.rewinds.follow(timestamp_ns):
            return True
        self._count(
            self.step.skip(
                "out-of-order",
                f"frame {timestamp_ns} is not after the last result ({newest}), and no "
                f"rewind that {self.spec.input} recorded explains it; skipped, nothing removed",
            )
        )
        return False


# The thread every call of a runner's handler runs on (and its class is created on).
HANDLER_THREAD = "vision-handler"


def serve(
    spec: RunnerSpec,
    handler: Handler,
    network: NetworkConfig,
    stop: threading.Event,
    thread: CallThread | None = None,
) -> int:
    """Run ``handler`` behind ``spec.input`` until ``stop`` is set (or KeyboardInterrupt),
    each call on ``thread`` (the one its class was created on; by default a new one)."""
    if thread is not None:
        return _serve(spec, handler, network, stop, thread)
    calls = CallThread(HANDLER_THREAD)
    try:
        return _serve(spec, handler, network, stop, calls)
    finally:
        calls.close()


def _serve(
    spec: RunnerSpec,
    handler: Handler,
    network: NetworkConfig,
    stop: threading.Event,
    calls: CallThread,
) -> int:
    log = setup_logging(spec.name)

    def call(work: Callable[[], object]) -> object:
        # On the handler's thread, so a stop is honoured while it is in native code.
        started = time.monotonic()
        result = calls.call(lambda: (True, work()), stop)
        if result is None:
            raise _Stopped
        # Emulated load: the frame occupies the runner at least this long, and its
        # processing_ns says so.
        remaining = spec.processing_floor_s - (time.monotonic() - started)
        if remaining > 0 and stop.wait(remaining):
            raise _Stopped
        return result[1]

    with Node(spec.name, network) as node:
        output = node.offer(
            spec.output, kind=spec.kind.value, retention=Retention(max_count=100_000)
        )
        # Every frame given to the handler is processed: have it pushed, not fetched.
        frames = node.subscribe(
            spec.input,
            queue_size=spec.queue,
            mode=SubscriptionMode.OBSERVE if spec.observe else SubscriptionMode.FLOW,
            wait_s=0,
            push_max_bytes=PUSH_ALL,
            await_service=True,  # a pipeline starts every service at once
            # The mediator's load is the frames waiting: each take acked at once, or with a
            # queue of 4 and more the frame in the handler counted as waiting until the next.
            ack_each_take=True,
        )
        step = VisionStep(handler, spec.kind, spec.input, log, call)
        runner = Runner(spec, step, node, output, stop)
        # While the handler runs (for minutes, if it hangs), frames its full queue drops are
        # counted from the subscription, not only when the next frame is taken.
        bad = BadNotifications(output, step.warn_once)

        def count_losses(_now_ns: int) -> None:
            runner.not_observed.total_is(frames.missed_total)
            bad.total_is(frames.garbage + frames.dropped)

        node.every(_MISSED_PERIOD_S, count_losses)
        log.info(
            "%s: %s -> %s/%s (%s, queue %d%s)",
            spec.name,
            spec.input,
            spec.name,
            spec.output,
            handler_name(handler),
            spec.queue,
            f", processing >= {spec.processing_floor_s * 1e3:.0f} ms"
            if spec.processing_floor_s
            else "",
        )
        say_at: float | None = time.monotonic() + _SAY_AFTER_S  # None: looked once already
        try:
            while not stop.is_set():
                notes = frames.take_many(1, timeout_s=0.5)
                runner.handle(notes, frames.fetch, frames.producer_epoch, frames.producer_session)
                if say_at is not None and time.monotonic() > say_at:
                    say_at = None
                    if not frames.wait_registered(0):
                        _say_why_unregistered(node, spec.input, log)
        except (KeyboardInterrupt, _Stopped):
            pass
        log.info("%s", _summary(spec, output.info()))
    return 0


def _summary(spec: RunnerSpec, results: BufferInfo) -> str:
    """The stop line, as the other services give one: what was stored, what skipped."""
    skipped = ", ".join(f"{reason} {n}" for reason, n in sorted(results.skipped.items()))
    return (
        f"{spec.name}: {results.puts} results stored in {spec.name}/{spec.output}, "
        f"skipped: {skipped or 'none'}"
    )


# A runner whose input has not registered it this long says why, once.
_SAY_AFTER_S = 5.0


def _say_why_unregistered(node: Node, target: str, log: logging.Logger) -> None:
    """One warning when the input cannot be had as named (a misspelt service or buffer:
    otherwise the runner would wait in silence); nothing while it is merely starting."""
    try:
        node.buffer_info(target, timeout_s=1.0)
    except NotFoundError as exc:
        log.warning("still waiting for %s: %s", target, exc)
    except FramegateError:
        pass  # not answering now: starting, or busy; the subscription registers when it can


def run(config: VisionConfig, network: NetworkConfig, stop: threading.Event | None = None) -> int:
    """Load the handler and serve until ``stop`` is set."""
    spec = config.handler
    if spec is None:
        raise ConfigError("framegate run vision needs --handler package.module:function")
    stop = stop or threading.Event()
    # A handler class is created on the thread its calls run on (a model or connection its
    # __init__ makes may be bound to that thread).
    thread = CallThread(HANDLER_THREAD)
    try:
        try:
            loaded = thread.call(lambda: load_handler(spec), stop)
        except ConfigError as exc:  # its class failed as it was created: worded as the flag check
            raise ConfigError(f"framegate run vision: argument --handler: {exc}") from exc
        if loaded is None:  # stopped while the class was created
            return 0
        kind = result_kind(loaded, config.kind)
        output = config.output or ("detections" if kind is ResultKind.DETECTIONS else "results")
        return serve(config.spec(output, kind), loaded, network, stop, thread)
    finally:
        thread.close()


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """The runner's flags (``framegate run vision --help``): one per config field."""
    add_flags(parser, VisionConfig)


def config_from_args(args: argparse.Namespace) -> VisionConfig:
    config: VisionConfig = from_args(VisionConfig, args)
    return config


SERVICE: Service[VisionConfig] = ServiceEntry(
    "vision", VisionConfig, add_arguments, config_from_args, run
)
