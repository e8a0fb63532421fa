"""The policy contract: a causal rule that decides which frames reach the detector."""

from __future__ import annotations

from collections.abc import Sequence
from typing import Protocol

from ._records import Candidate, Verdict, View


class Policy(Protocol):
    """A causal rule: it sees the past and the present (a :class:`View`), never the future.

    ``on_frame`` must return exactly one verdict for ``frame`` and may add verdicts for
    held frames (``view.held``); ``on_tick`` is called while frames are held and returns
    verdicts for held frames only. Verdicts are applied in the order returned; FORWARDs
    must go out in time order (an older frame after a newer one is dropped). A policy keeps
    no frames itself: the decider holds them, so a policy may keep statistics but never
    loses a frame.
    """

    @property
    def name(self) -> str:
        """The name ``--policy`` selects and the decision records carry."""
        ...

    def on_frame(self, frame: Candidate, view: View) -> Sequence[Verdict]:
        """Decide on a frame with a quality (q >= q_min, in time order)."""
        ...

    def on_tick(self, view: View) -> Sequence[Verdict]:
        """Decide on held frames as time passes or the detector's queue drains."""
        ...

    def next_due_ns(self, view: View) -> int | None:
        """The next time after ``view.now_ns`` at which ``on_tick`` may decide otherwise
        with no new input (no frame, no change of the detector's queue); None if only new
        input can change it. The mediator asks ``on_tick`` at these times, never on a poll
        (the decider adds each held frame's maximum hold itself)."""
        ...
