"""When a stage may remove what it produced because its input started over earlier in time.

A rewind (``Producer.discard_after``) destroys history, so it is never decided from one
element. The mediator rewinds mediator/images only when the camera itself is known to have
started over with another clock, and that clock change explains the whole step back
(``rewind_after``); the stages after it follow only a rewind their input producer recorded
(``RewindFollower``, reading the input's ``BufferInfo.rewinds``). A rogue single put, a stale
stamp, stamp 1 or 2^63-1 remove nothing: the element is dropped, counted, instead.
"""

from __future__ import annotations

import collections
import logging
import time
from dataclasses import dataclass

from middleware import FramegateError, Node, Producer, Rewind, ServiceInfo


@dataclass(frozen=True, slots=True)
class SourceClock:
    """One sample of a source's clock: its offset from ours (NTP-style, error at most half
    the round trip), and which clock it was (host, pid and the steps it absorbed)."""

    host: str
    pid: int
    steps: int | None
    offset_ns: int
    error_ns: int

    @property
    def identity(self) -> tuple[str, int, int | None]:
        return (self.host, self.pid, self.steps)

    @classmethod
    def of(cls, info: ServiceInfo) -> SourceClock | None:
        """The clock sample a service description carries (None from a peer without one)."""
        if info.clock_offset_ns is None:
            return None
        return cls(
            info.host,
            info.pid,
            info.clock_steps,
            info.clock_offset_ns,
            (info.round_trip_ns or 0) // 2,
        )


@dataclass(frozen=True, slots=True)
class RewindCheck:
    """Whether a stage may remove what it put after ``after_ns`` (None: it may not), why."""

    after_ns: int | None
    why: str


def rewind_after(
    newest_put_ns: int,
    first_ns: int,
    before: SourceClock | None,
    after: SourceClock | None,
    horizon_ns: int,
) -> RewindCheck:
    """May the elements put after ``first_ns - 1`` go, now that the source's new stream
    starts at ``first_ns``, at or before the newest element put (``newest_put_ns``)?

    Only if all hold: both the old stream's clock (``before``) and the new one's
    (``after``) were sampled; they are different clocks (another process, or the same one
    after a clock step); the old clock ran ahead of the new one by at least the step back,
    so the removed elements were stamped by the wrong one;
    the new clock is the nearer to ours; and the step back is within ``horizon_ns``.
    "By at least the step back" is proven: the lead less both samples' errors covers it.
    Otherwise nothing is removed and the new stream's early frames are dropped as late.
    """
    span = newest_put_ns - first_ns + 1
    if span <= 0:
        return RewindCheck(None, "in-order")
    if before is None or after is None:
        return RewindCheck(None, "clock-unknown")
    if before.identity == after.identity:
        return RewindCheck(None, "same-clock")
    # The lead must be proven, not merely possible: a peer that answers slowly makes its
    # sample's error as large as it likes (half the round trip), and "within the error" would
    # then explain any small step back.
    lead = before.offset_ns - after.offset_ns
    if lead - before.error_ns - after.error_ns < span:
        return RewindCheck(None, "not-a-clock-step")
    if abs(after.offset_ns) >= abs(before.offset_ns):
        return RewindCheck(None, "new-clock-further-off")
    if span > horizon_ns:
        return RewindCheck(None, "beyond-horizon")
    return RewindCheck(first_ns - 1, "source-clock-stepped-back")


# At most this many asks of the input's rewinds per second; past that, stale elements are
# skipped without asking: each ask is a round trip on the stage's thread, and a peer can send
# stale elements as fast as it likes. A genuine rewind is recorded before the input's first
# element that needs it, so it is found at once unless a burst of stale ones came just before.
ASKS_PER_S = 5


class RewindFollower:
    """For a stage whose output is keyed by its input's stamps (the detector): follow
    only the rewinds its input producer recorded.

    Call ``seen(producer)`` with the input subscription's ``producer_epoch`` before each
    input element, and ``follow(stamp)`` when an input
    element is stamped at or before the newest element of ``output``: it reads the input's
    ``info`` once, and for each rewind recorded there and not yet followed whose bound lies
    below ``stamp``, removes what ``output`` holds after that bound (``cause``: ``rewound``).
    True when ``stamp`` may now be put; False when no such rewind explains it, so the element
    is late and must be skipped (counted) while ``output`` keeps everything.

    A producer can only rewind what it delivered: when the input's producer changes (it
    restarted, or another process took its name: it greets the subscription under a new
    producer epoch), what ``output`` holds by then came from the one before, and no rewind
    of the new one removes it. Only a greeting moves this floor: a forged notification under
    a made-up epoch does not.
    """

    def __init__(
        self,
        node: Node,
        input_target: str,
        output: Producer,
        log: logging.Logger,
        timeout_s: float = 2.0,
    ) -> None:
        self._node = node
        self._input = input_target
        self._output = output
        self._log = log
        self._timeout_s = timeout_s
        self._followed: set[Rewind] = set()
        self._producer: str | None = None  # the input's producer epoch, as last seen
        self._session: str | None = None  # and the Zenoh session that greeted us for it
        # What ``output`` held when that producer's first notification came: older
        # results are not its to rewind (None: everything in ``output`` came from it).
        self._floor_ns: int | None = None
        self._warned = False
        self._asked: collections.deque[int] = collections.deque(maxlen=ASKS_PER_S)

    def seen(self, producer: str | None, session: str | None = None) -> None:
        """The input's producer as the subscription was last greeted by (before an input
        element is processed): its epoch, and the Zenoh session that greeted it (whose
        answer alone tells its rewinds); None while not registered changes nothing."""
        self._session = session
        if producer is not None and producer != self._producer:
            if self._producer is not None:
                self._floor_ns = self._output.series.newest_ns
            self._producer = producer

    def follow(self, stamp_ns: int) -> bool:
        floor = self._floor_ns
        if floor is not None and stamp_ns <= floor:
            return False  # before this producer's time: none of its rewinds explains it
        now = time.monotonic_ns()
        if len(self._asked) == ASKS_PER_S and now - self._asked[0] < 1_000_000_000:
            return False  # a burst of stale elements (a peer's, perhaps): asked enough
        self._asked.append(now)
        try:
            # Removing elements must not rest on a peer's word: only the session that greeted
            # the input subscription counts; without it, a second session answering as the
            # input's service (one that forges a rewind) makes the answer void.
            info = self._node.buffer_info(
                self._input, timeout_s=self._timeout_s, unambiguous=True, session=self._session
            )
            rewinds = info.rewinds
        except FramegateError as exc:
            if not self._warned:  # once: each stale element asks again
                self._warned = True
                self._log.warning(
                    "cannot read the rewinds of %s (%s): stale elements are skipped, "
                    "nothing is removed",
                    self._input,
                    exc,
                )
            return False
        self._followed &= set(rewinds)  # bounded by what the input's info lists
        for rewind in rewinds:
            newest = self._output.series.newest_ns
            if rewind in self._followed or newest is None:
                continue
            # Only a rewind of the very elements the output is keyed by: below ``stamp``,
            # and everything the output holds after its bound is within what it removed
            # (an older rewind, or one of elements this stage never had, explains nothing).
            if not rewind.after_ns < stamp_ns <= newest <= (rewind.last_ns or -1):
                continue
            self._followed.add(rewind)
            bound = rewind.after_ns if floor is None else max(rewind.after_ns, floor)
            self._output.discard_after(bound, "rewound")
        newest = self._output.series.newest_ns
        return newest is None or stamp_ns > newest
