"""The paper's policy (§4.3): forward a frame iff its quality beats the detector's load."""

from __future__ import annotations

from collections.abc import Sequence

from services.lib.quality import accept

from ._records import Action, Candidate, Verdict, View


class PaperPolicy:
    """``paper``: forward iff q > load; never holds a frame. Idle (load 0) takes anything."""

    name = "paper"

    def on_frame(self, frame: Candidate, view: View) -> Sequence[Verdict]:
        assert frame.q is not None  # the decider applies the gyro-missing rule first
        if accept(frame.q, view.load.fill):
            return [Verdict(frame, Action.FORWARD, "quality>load")]
        return [Verdict(frame, Action.DROP, "quality<=load")]

    def on_tick(self, view: View) -> Sequence[Verdict]:
        return ()

    def next_due_ns(self, view: View) -> int | None:
        return None  # holds nothing
