"""The paper's policy (§4.3): forward iff q > load, recorded sequences in, verdicts out."""

from __future__ import annotations

from services.lib.decisions import Decider, Rules, make_policy

from .sequences import play


def test_paper_forwards_iff_quality_beats_the_queue_fill() -> None:
    play(
        Decider(make_policy("paper")),
        """
        frame t=0   f=1 q=0.10 queue=0/2  -> 1 forward quality>load   # idle takes anything
        frame t=33  f=2 q=0.40 queue=1/2  -> 2 drop quality<=load
        frame t=66  f=3 q=0.50 queue=1/2  -> 3 drop quality<=load     # equal is not better
        frame t=99  f=4 q=0.90 queue=1/2  -> 4 forward quality>load
        frame t=132 f=5 q=1.00 queue=2/2  -> 5 drop quality<=load     # full takes nothing
        tick  t=150         queue=0/2     -> -                        # paper never holds
        """,
    )


def test_paper_fills_every_slot_with_sharp_frames() -> None:
    play(
        Decider(make_policy("paper")),
        """
        frame t=0  f=1 q=0.9 queue=0/3 -> 1 forward quality>load
        frame t=10 f=2 q=0.9 queue=1/3 -> 2 forward quality>load
        frame t=20 f=3 q=0.9 queue=2/3 -> 3 forward quality>load
        frame t=30 f=4 q=0.9 queue=3/3 -> 4 drop quality<=load
        """,
    )


def test_paper_below_the_minimum_is_dropped_even_when_idle() -> None:
    play(
        Decider(make_policy("paper"), Rules(q_min=0.5)),
        """
        frame t=0  f=1 q=0.49 queue=0/2 -> 1 drop below-minimum
        frame t=10 f=2 q=0.50 queue=0/2 -> 2 forward quality>load
        """,
    )
