"""The paper's policy (§4.3): forward a frame iff its quality beats the detector's load."""

from __future__ import annotations

from collections.abc import Sequence

from services.lib.quality import QualityInputError

from ._records import Action, Candidate, Verdict, View


def _check_unit(name: str, value: float, *, open_low: bool = False) -> None:
    low_ok = value > 0.0 if open_low else value >= 0.0
    if not (low_ok and value <= 1.0):
        interval = "(0, 1]" if open_low else "[0, 1]"
        raise QualityInputError(f"{name} must be in {interval}, got {value!r}")


def accept(q: float, load: float, q_min: float = 0.0) -> bool:
    """The acceptance test: a frame passes iff q > load and q >= q_min.

    An idle consumer (load 0) takes every frame (q is never 0); a full one (load 1) none.
    """
    _check_unit("q", q, open_low=True)
    _check_unit("load", load)
    _check_unit("q_min", q_min)
    return q > load and q >= q_min


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
