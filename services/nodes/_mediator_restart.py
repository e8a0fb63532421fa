"""A camera stream that starts (over): the first frame, a restarted camera, or our
subscription registered again (see ``services.nodes.mediator``).

Its frames are judged afresh once the camera's clock has answered: the time order restarts,
and frames already forwarded after the new stream's start are removed only when the
camera's clock change explains the step back (``services.lib.rewind``). The frames the camera
stored while nothing took them get ``mediator-lapsed`` records. Both questions (the clock,
the frames missed) are asked without waiting; their answers are handlers on the executor,
so a camera that went away again holds up nothing.
"""

from __future__ import annotations

import functools
import logging
import time
from collections.abc import Callable
from dataclasses import dataclass

from middleware import DataObject, FramegateError, Node, split_target
from services.lib.decisions import Decider
from services.lib.messages import read_frame_metadata
from services.lib.rewind import SourceClock, rewind_after
from services.nodes._mediator_inputs import ClockOffsets
from services.nodes._mediator_output import Output

# Looks for the frames stored while our subscription had lapsed, 1 s apart (``missed``).
MISSED_TRIES = 5


@dataclass(slots=True)
class StreamStart:
    """A camera stream that started at ``first_ns``, until its clock has answered."""

    first_ns: int
    before: StreamStart | None  # the start of the stream that ended: its clock, once in
    restarted: bool  # there was a stream before: a rewind to check, an order to restart
    answered: bool = False
    clock: SourceClock | None = None  # sampled when it began, once answered

    @property
    def ready(self) -> bool:
        """Both clocks it is judged by have answered (each question times out)."""
        return self.answered and (self.before is None or self.before.answered)


class StreamStarts:
    """The starts of the camera's stream: each asks the camera's clock, and the stream's
    first frames wait for the answer (``holding``; one round trip, at most the question's
    timeout) so that a restart is judged against the right time order instead of its
    frames being dropped as late.

    Threads: ``begin``, ``resume`` and ``holding`` run where the mediator's handlers run;
    the answers come on the node's executor and only mark their start answered, then call
    ``wake`` (the mediator's, which carries the start out when it drives the executor)."""

    def __init__(
        self,
        node: Node,
        camera: str,
        offsets: ClockOffsets,
        out: Output,
        decider: Decider,
        log: logging.Logger,
        wake: Callable[[], object],
    ) -> None:
        self._node = node
        self._camera = camera
        self._camera_name = split_target(camera)[0]
        self._offsets = offsets
        self._out = out
        self._decider = decider
        self._log = log
        self._wake = wake
        self._pending: StreamStart | None = None  # not carried out yet
        self._current: StreamStart | None = None  # the current stream's

    @property
    def holding(self) -> bool:
        """Whether the frames of a stream that started wait for its clock's answer (also
        the first stream's: its clock is what a later restart is judged by, and a source
        that is gone by then cannot be asked)."""
        return self._pending is not None

    def clock(self) -> SourceClock | None:
        """The current stream's camera clock, sampled when it began (None: not answered)."""
        return self._current.clock if self._current is not None else None

    def begin(self, first_ns: int, restarted: bool) -> None:
        """A stream starts at ``first_ns`` (``restarted``: after another one)."""
        if self._pending is not None:  # started over again before the clocks answered
            self._carry_out(self._pending)  # no rewind: a clock it needed is unknown
        # The old stream's clock as sampled when it began (a sample taken now may already
        # be of the new process), and the new one's, asked now.
        start = StreamStart(first_ns, self._current, restarted)
        self._pending = self._current = start
        self._offsets.ask(self._camera_name, functools.partial(self._answered, start))

    def _answered(self, start: StreamStart, clock: SourceClock | None) -> None:
        """(the executor) A stream's clock answered (None: it did not)."""
        start.clock, start.answered = clock, True
        if self._pending is not None and self._pending.ready:
            self._wake()

    def resume(self) -> bool:
        """Whether frames may be decided: no start waits for its clock (one that has
        answered is carried out here)."""
        start = self._pending
        if start is not None and start.ready:
            self._carry_out(start)
        return not self.holding

    def _carry_out(self, start: StreamStart) -> None:
        self._pending = None
        before = start.before.clock if start.before is not None else None
        start.before = None  # carried out: a chain of starts is not kept
        if not start.restarted:
            return
        out = self._out
        floor = out.newest_put_ns
        if floor is not None and start.first_ns <= floor:
            check = rewind_after(floor, start.first_ns, before, start.clock, out.images.horizon_ns)
            if check.after_ns is not None:
                # The frames forwarded after the new stream's start were stamped by the
                # camera's old clock, now known to have been ahead: kept, they would hold
                # every later frame out of the detector's time-ordered buffer.
                out.images.discard_after(check.after_ns, "rewound")
                out.newest_put_ns = out.images.series.newest_ns
                floor = out.newest_put_ns or 0  # 0: nothing left below which to stay
            else:
                self._log.warning(
                    "camera stream starts %.3f s before the newest frame forwarded, and that "
                    "is not a step of the camera's clock (%s): nothing is removed; its frames "
                    "until then are dropped out-of-order",
                    (floor - start.first_ns) / 1e9,
                    check.why,
                )
        self._decider.restart_order(floor)

    def missed(self, since_ns: int, until_ns: int, tries: int = 0) -> None:
        """Record the frames the camera stored after ``since_ns`` (the last one taken) and
        before ``until_ns``: stored while our subscription had lapsed (stopped, cut off past
        the lease) or before it registered with a restarted camera, none will be notified;
        each gets a ``mediator-lapsed`` record. A look-up that is not answered is made
        again; frames the camera's retention evicted cannot be named."""
        if until_ns <= since_ns + 1:
            return

        def answered(found: list[DataObject] | FramegateError) -> None:
            if isinstance(found, FramegateError):
                self._log.warning("cannot look up the frames missed before %d: %s", until_ns, found)
                if tries + 1 < MISSED_TRIES:
                    again = time.monotonic_ns() + 1_000_000_000
                    self._node.at(again, lambda _: self.missed(since_ns, until_ns, tries + 1))
                return
            for element in found:
                try:
                    frame_id = read_frame_metadata(element.metadata).frame_id
                except (FramegateError, ValueError, TypeError):
                    frame_id = 0
                reason, detail = "mediator-lapsed", "stored while not taken"
                self._out.skip(element.timestamp_ns, frame_id, reason, detail)
            if found:
                what = "stored while our camera subscription had lapsed: recorded mediator-lapsed"
                self._log.warning("%d frames were %s", len(found), what)

        try:
            self._node.ask_query(
                self._camera,
                answered,
                time_range=f"[{since_ns + 1}..{until_ns - 1}]",
                timeout_s=5.0,
                # The camera's own answer only: a peer answering beside it would invent
                # a record per element it made up.
                session=self._offsets.session_of(self._camera_name),
            )
        except FramegateError as exc:
            answered(exc)
