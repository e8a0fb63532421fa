"""An unmodified ROS 2 vision node as a flow-controlled consumer of a framegate buffer.

``--consumer-done /yolo/detections --consumer-queue N`` turns the ``--image-out`` mapping
of the node's input (``mediator/images=/camera/image_sharp``) from an observer into a loop:

- the *gate*, a flow-controlled subscription of the buffer with queue N (no payloads), is
  the ROS 2 node as framegate sees it. Its notifications are taken only when the node is
  done with an image: a result whose ``header.stamp`` equals the image's arrived, or
  ``--consumer-timeout-ms`` passed. So its queue holds exactly the node's outstanding
  images, the producer (the mediator) sees that fill as the consumer's load, and it cannot
  put more than N images the node has not answered (flow control, the paper's rule: the
  mediator leaves frames out, nothing here drops).
- the *feed*, an observing subscription of the same buffer (payloads pushed), brings each
  element, which is published to ROS 2 as a ``sensor_msgs/msg/Image`` and recorded in
  :class:`Outstanding`. Every element the feed gets is resolved exactly once (answered,
  timed out, or not publishable), and each resolution takes one notification off the gate.
- the result topic is subscribed from the start, before any image can reach the node, and
  takes messages of every type on it, read only as far as their leading
  ``std_msgs/Header``; the subscription's liveliness token follows once a publisher's
  token names the type (the graph then shows that one).

Counted, never silent (``framegate info NAME/results``, ``skipped``): ``consumer-timeout``
(an image never answered; its slot freed), ``late-result``, ``unmatched-result``,
``bad-result`` (no readable header), ``result-queue-full``, ``missed-image`` (the feed lost
a notification: its gate entry is freed), ``not-published``, ``unmatched-gate`` (a gate
entry no image of the feed accounts for, e.g. across a producer restart, freed after the
timeout), ``ungated-image`` (an image the gate never counted, e.g. at start: nothing
to free), ``not-recorded`` (an answer out of stamp order: its slot is freed, its element
not stored), ``internal-error``. Each answered image becomes one element of NAME/results
(key: the image's), with how long the node took and how long the loop took to free its
slot.

Threads: Zenoh's callback thread only enqueues results (a bounded ``queue.Queue``) and
reads tokens (``on_token``, under ``_lock``); the *feed* thread takes, encodes and publishes
images; the *resolver* thread declares the result subscription's token once its type is
known, matches results, expires slots and takes gate notifications. ``_lock`` guards the ledger,
the ``GateBook`` (resolutions not yet paid by a gate take) and the type discovery.

Why threads of its own rather than the node's executor (``Node.on``/``at``): on its one
executor thread a result waits behind the encoding and publishing of an image (a copy of
the frame, milliseconds on a loaded machine), so its slot is freed later and the mediator
sees the node busy longer. Measured on the same loaded 2-core machine (``framegate bench
ros2-loop``, runs alternated): with the executor (7 runs) the node in the loop gained -2 to
+13 % (median +6.5 %) and processed 3-15 % fewer images than the uncontrolled one; with these
two threads (9 runs) +5 to +26 % (median +14 %) and 0-10 % fewer. The ranges overlap at
that load; the medians decided.
"""

from __future__ import annotations

import contextlib
import logging
import queue
import threading
import time
from collections.abc import Callable
from typing import Any, Protocol

from middleware import (
    PUSH_ALL,
    FramegateError,
    Node,
    Producer,
    Retention,
    SubscriptionMode,
    make_metadata,
)

from ._config import Mapping, Ros2Config
from ._consumer import (
    HEADER_MAX_BYTES,
    ConsumerCounts,
    DoneTopic,
    GateBook,
    HeaderError,
    InputDepthCheck,
    Outstanding,
    Resolved,
    ResultType,
    decode_header,
)
from ._link import RosLink, RosPublisher
from ._rmw import ATTACHMENT_BYTES, Attachment, Qos

log = logging.getLogger("framegate.ros2")


class Skips(Protocol):
    """The bridge's counted skips (``_bridge._Skips``): into a producer's ``skipped``, with
    one warning per reason."""

    def count(self, producer: Producer | None, reason: str, detail: str) -> None: ...


_POLL_S = 0.2
# The resolver wakes at least this often while it owes the gate a take whose notification
# has not arrived yet (the gate's and the feed's notifications of one put race).
_RETRY_S = 0.02
# Results waiting for the resolver; a node answers at most one per image it was sent.
_RESULTS_DEPTH = 64


class ConsumerLoop:
    """One ROS 2 node in the loop (see the module docstring)."""

    def __init__(
        self,
        node: Node,
        link: RosLink,
        publisher: RosPublisher,
        mapping: Mapping,
        encode: Callable[[Any], bytes | bytearray | None],
        config: Ros2Config,
        skips: Skips,
        *,
        first_field: Callable[[str], str | None] | None = None,
    ) -> None:
        assert config.consumer_done is not None
        self.mapping = mapping
        self._node, self._link, self._publisher = node, link, publisher
        self._encode, self._config, self._skips = encode, config, skips
        depth = config.consumer_queue
        self.results = node.offer("results", kind="generic", retention=Retention(max_count=10_000))
        self._lock = threading.Lock()
        self._ledger = Outstanding(depth, int(config.consumer_timeout_ms * 1e6))
        self._book = GateBook(self._ledger.timeout_ns)
        # ``first_field``: a known result type's first field (Codec.first_field).
        self._done = DoneTopic(config.consumer_done, first_field)
        self._depth = InputDepthCheck(mapping.topic, depth)
        self._subscribed: set[ResultType] = set()  # the result types announced (tokens)
        # A full queue refuses the newest result, counted (see _on_result).
        self._answers: queue.Queue[tuple[bytes, bytes | None]] = queue.Queue(_RESULTS_DEPTH)
        self.published = 0
        # The node's results are listened to before any image can reach it: Zenoh routes
        # them by data subscribers, and one declared only once the graph named the result
        # type (the resolver's turn after the token arrived) could reach a node that
        # answered its first image sooner too late, losing that answer (consumer-timeout).
        # Every type on the topic: a peer's tokens of made-up types choose nothing
        # (``DoneTopic``). The subscription's token, which names a type, follows.
        link.listen_any_type(config.consumer_done, self._on_result)
        # The feed first: an element the gate holds but the feed missed would hold a slot
        # until the timeout; one the feed has and the gate missed costs nothing lasting.
        self._feed = node.subscribe(
            mapping.buffer,
            queue_size=max(8, 2 * depth),
            mode=SubscriptionMode.OBSERVE,
            wait_s=0,
            push_max_bytes=PUSH_ALL,
            await_service=True,
        )
        self._gate = node.subscribe(
            mapping.buffer,
            queue_size=depth,
            mode=SubscriptionMode.FLOW,
            wait_s=0,
            push_max_bytes=0,  # the feed brings the payloads
            await_service=True,
            # A take is the node done with an image: its slot is free now. Coalesced (N >= 4)
            # the mediator saw the node one image fuller until the next answer.
            ack_each_take=True,
        )

    # -- the ROS graph (Zenoh's thread) ------------------------------------------------------
    def on_token(self, token: str) -> None:
        with self._lock:
            remark = self._done.feed(token)
            shallow = self._depth.feed(token)
        if remark:
            log.warning("ros2: consumer result topic %s", remark)
        if shallow:
            log.warning("ros2: consumer input: %s", shallow)

    # -- feed: images out --------------------------------------------------------------------
    def run_feed(self, stop: threading.Event) -> None:
        while not stop.is_set():
            note = self._feed.take(timeout_s=_POLL_S)
            if note is None:
                continue
            try:
                self._publish(note)
            except Exception as exc:  # one element must never stop the bridge
                log.exception("consumer feed: unexpected error")
                self._skips.count(self.results, "internal-error", repr(exc))
                self._resolved_without_image(1)

    def _publish(self, note: Any) -> None:
        if note.missed:
            self._skips.count(
                self.results,
                "missed-image",
                f"{note.missed} notification(s) of {note.service}/{note.buffer}",
            )
            self._resolved_without_image(note.missed)
        try:
            element = self._feed.fetch(note)
            cdr = self._encode(element)
        except (FramegateError, ValueError, KeyError, TypeError) as exc:
            what = f"{self.mapping.buffer} at {note.timestamp_ns}: {exc}"
            self._skips.count(self.results, "not-published", what)
            self._resolved_without_image(1)
            return
        if cdr is None:
            self._resolved_without_image(1)
            return
        stamp = self._config.stamp_ns(element.timestamp_ns)
        # Recorded before publishing: the node may answer before publish() returns.
        with self._lock:
            added = self._ledger.add(stamp, time.monotonic_ns())
        if not added:
            self._skips.count(self.results, "not-published", f"no free slot for {stamp} ns")
            self._resolved_without_image(1)
            return
        try:
            self._publisher.publish(cdr)
            self.published += 1
        except FramegateError as exc:
            with self._lock:
                self._ledger.withdraw(stamp)
            self._skips.count(self.results, "not-published", str(exc))
            self._resolved_without_image(1)

    def _resolved_without_image(self, count: int) -> None:
        with self._lock:
            spared = self._book.owe(count, time.monotonic_ns())
        self._count_ungated(spared)

    def _count_ungated(self, count: int) -> None:
        for _ in range(count):
            self._skips.count(
                self.results,
                "ungated-image",
                f"an image of {self.mapping.buffer} the gate never counted (registration)",
            )

    # -- resolver: results in, slots freed ---------------------------------------------------
    def run_resolver(self, stop: threading.Event) -> None:
        waiting_said = False
        while not stop.is_set():
            if not self._subscribed:
                with self._lock:
                    first = self._done.found[:1]
                for found in first:
                    self._subscribe(found)
            if not self._subscribed and not waiting_said:
                waiting_said = True
                log.info(
                    "ros2: waiting for a publisher of %s (its type is read from its "
                    "liveliness token); until then images to %s free their slot after "
                    "%.0f ms",
                    self._done.topic,
                    self.mapping.topic,
                    self._config.consumer_timeout_ms,
                )
            try:
                self._turn()
            except Exception as exc:  # never stop resolving: the gate would stay full
                log.exception("consumer resolver: unexpected error")
                self._skips.count(self.results, "internal-error", repr(exc))

    def _subscribe(self, found: ResultType) -> None:
        topic = self._done.topic
        # The ROS graph's view of the subscriber listening since the start (``__init__``).
        self._link.subscription_token(topic, found.ros_type, found.type_hash, Qos())
        self._subscribed.add(found)
        log.info(
            "ros2: consumer results on %s, of every type (first announced: %s, %s)",
            topic,
            found.ros_type,
            found.type_hash,
        )

    def _on_result(self, raw: bytes, attachment: bytes | None) -> None:
        """(Zenoh's thread) Only enqueue, and only what is read: a full queue of a peer's
        large messages would hold ``_RESULTS_DEPTH`` times their size."""
        if attachment is not None and len(attachment) != ATTACHMENT_BYTES:
            attachment = None  # not rmw_zenoh's: read as none (see _answer)
        try:
            self._answers.put_nowait((raw[:HEADER_MAX_BYTES], attachment))
        except queue.Full:
            self._skips.count(self.results, "result-queue-full", "the result queue was full")

    def _next_result(self, wait_s: float) -> tuple[bytes, bytes | None] | None:
        try:
            if wait_s > 0:
                return self._answers.get(timeout=wait_s)
            return self._answers.get_nowait()
        except queue.Empty:
            return None

    def _turn(self) -> None:
        """Wait for a result or the next deadline, then free what is resolved."""
        with self._lock:
            deadline = self._ledger.next_deadline_ns()
            owing = self._book.debt > 0
        wait_s = _RETRY_S if owing or not self._subscribed else _POLL_S
        if deadline is not None:
            wait_s = min(wait_s, max(0.0, (deadline - time.monotonic_ns()) / 1e9))
        item = self._next_result(wait_s)
        answered: list[tuple[Resolved, int]] = []
        # A bounded batch: a peer that refills the queue as fast as it drains must not keep
        # the turn from expiring slots and paying the gate.
        taken = 0
        while item is not None:
            if (done := self._answer(*item)) is not None:
                answered.append(done)
            taken += 1
            item = self._next_result(0) if taken < _RESULTS_DEPTH else None
        now = time.monotonic_ns()
        with self._lock:
            expired = self._ledger.expire(now)
            spared = self._book.owe(len(answered) + len(expired), now)
        self._count_ungated(spared)
        for gone in expired:
            self._skips.count(
                self.results,
                "consumer-timeout",
                f"no result on {self._done.topic} within {self._config.consumer_timeout_ms:g} "
                f"ms of its turn for the image stamped {gone.stamp_ns} ns",
            )
        released_ns = self._pay(now)
        for resolved, sent_ns in answered:
            self._record(resolved, sent_ns, released_ns)

    def _answer(self, raw: bytes, attachment: bytes | None) -> tuple[Resolved, int] | None:
        """Match one result; (the image it answers, the result's source wall time)."""
        try:
            header = decode_header(raw)
        except HeaderError as exc:
            with self._lock:
                self._ledger.bad_result()
            self._skips.count(
                self.results,
                "bad-result",
                f"a result on {self._done.topic} that does not start with a std_msgs/Header "
                f"({exc}): its type must lead with the image's Header for the loop to match it",
            )
            return None
        with self._lock:
            resolved = self._ledger.answer(header.stamp_ns, time.monotonic_ns())
        if isinstance(resolved, str):
            detail = (
                f"result stamped {header.stamp_ns} ns ({header.frame_id[:40]}) came after its "
                f"image's slot timed out: the node took longer than --consumer-timeout-ms "
                f"({self._config.consumer_timeout_ms:g} ms) for one image; raise it"
            )
            if resolved == "unmatched":
                # Said once: a node stamping its results itself (now(), not its image's)
                # shows only as every image timing out, unless this line says why.
                with self._lock:
                    near = self._ledger.nearest(header.stamp_ns)
                waiting = "" if near is None else f" (nearest waiting: {near} ns)"
                detail = (
                    f"result stamped {header.stamp_ns} ns names no image sent to "
                    f"{self.mapping.topic}{waiting}: a second result for one image, or a node "
                    f"that does not copy its image's header.stamp into its result "
                    f"(frame {header.frame_id[:40]!r})"
                )
            self._skips.count(self.results, f"{resolved}-result", detail)
            return None
        sent_ns = time.time_ns()
        if attachment is not None:
            # A result without rmw_zenoh's attachment still frees its slot.
            with contextlib.suppress(ValueError):
                sent_ns = Attachment.decode(attachment).source_timestamp_ns
        return resolved, sent_ns

    def _pay(self, now_ns: int) -> int:
        """Take one gate notification per resolution owed, settle mismatches (see
        ``GateBook``); the wall time the takes were done."""
        with self._lock:
            owed = self._book.debt
        taken = self._gate.take_many(owed, timeout_s=0) if owed else []
        released_ns = time.time_ns()
        with self._lock:
            cancelled = self._book.taken(len(taken), now_ns)
            accounted = len(self._ledger) + self._feed.pending
            extra = self._book.surplus(self._gate.pending, accounted, now_ns)
        self._count_ungated(cancelled)
        for note in self._gate.take_many(extra, timeout_s=0) if extra else []:
            self._skips.count(
                self.results,
                "unmatched-gate",
                f"a gate notification of {self.mapping.buffer} at {note.timestamp_ns} ns "
                "without an image",
            )
        return released_ns

    def _record(self, resolved: Resolved, sent_ns: int, released_ns: int) -> None:
        key = self._config.start_ns(resolved.stamp_ns)
        fields = {
            "stamp_ns": resolved.stamp_ns,
            "answer_ns": resolved.resolved_ns - resolved.published_ns,
            "release_ns": max(0, released_ns - sent_ns),
        }
        try:
            self.results.put(key, b"", make_metadata("generic", key, fields))
        except FramegateError as exc:
            self._skips.count(self.results, "not-recorded", f"result of {key} ns: {exc}")

    def counts(self) -> ConsumerCounts:
        with self._lock:
            return self._ledger.counts()

    def close(self) -> None:
        for sub in (self._gate, self._feed):
            sub.close()
