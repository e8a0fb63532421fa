"""``replace`` (beyond the paper): hold the best frames, one for each free queue slot.

The detector's queue has ``free`` slots. Rather than commit a frame to a slot at once (a
committed frame cannot be taken back), the mediator holds a candidate for every free slot:
the sharpest frames seen, none held longer than ``max_hold_ns``. A new frame takes the place
of the worst held one if it is at least as sharp (``replaced``), else it is dropped
(``worse-than-held``). Held frames go to the detector oldest first:

- when the detector's queue is empty (``forwarded-held``): the detector must not idle;
- when a frame has been held ``max_hold_ns`` (``held-max``): it was the best of its window
  and a slot is free for it, so it fills that slot; with the detector slower than the hold
  time this fills every slot of the queue.

A frame that finds the queue empty and nothing held goes at once (``idle``); with every slot
taken nothing can be held (``queue-full``). If slots vanish (another flow-controlled
subscriber, a smaller queue after a restart), the worst held frames are let go (``no-slot``).
"""

from __future__ import annotations

from collections.abc import Sequence

from ._records import Action, Candidate, Verdict, View


def _sharpness(frame: Candidate) -> tuple[float, int]:
    # Worst first: lowest q, and among equals the oldest (a newer frame is fresher).
    assert frame.q is not None
    return (frame.q, frame.timestamp_ns)


class ReplacePolicy:
    """Hold the sharpest frames, one per free slot; forward them as the detector needs them."""

    name = "replace"

    def on_frame(self, frame: Candidate, view: View) -> Sequence[Verdict]:
        load = view.load
        if load.idle and not view.held:
            return [Verdict(frame, Action.FORWARD, "idle")]
        if load.free == 0:
            return [Verdict(frame, Action.DROP, "queue-full")]
        if len(view.held) < load.free:
            return [Verdict(frame, Action.HOLD, "held")]
        worst = min(view.held, key=_sharpness)
        assert frame.q is not None and worst.q is not None
        if frame.q >= worst.q:
            return [Verdict(worst, Action.DROP, "replaced"), Verdict(frame, Action.HOLD, "held")]
        return [Verdict(frame, Action.DROP, "worse-than-held")]

    def next_due_ns(self, view: View) -> int | None:
        return None  # a free slot (new input) or the maximum hold (the decider's) only

    def on_tick(self, view: View) -> Sequence[Verdict]:
        out: list[Verdict] = []
        held = list(view.held)
        free = view.load.free
        while len(held) > free:
            worst = min(held, key=_sharpness)
            held.remove(worst)
            out.append(Verdict(worst, Action.DROP, "no-slot"))
        queued = view.load.queued
        if held and queued == 0 and view.load.capacity > 0:
            out.append(Verdict(held.pop(0), Action.FORWARD, "forwarded-held"))
            queued += 1
        for frame in list(held):
            if view.held_for_ns(frame) >= view.max_hold_ns and queued < view.load.capacity:
                held.remove(frame)
                out.append(Verdict(frame, Action.FORWARD, "held-max"))
                queued += 1
        return out
