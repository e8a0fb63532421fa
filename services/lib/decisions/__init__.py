"""The mediator's decisions as a pure object: frame quality, detector load and clock in,
verdicts out (forward now, hold for later, drop, each with a reason). No I/O, no threads:
``services.nodes.mediator`` only feeds it and carries out what it says, and a replay or an
experiment can run the very same code on recorded times.

Feeding it::

    decider = Decider(make_policy("replace"), Rules(max_hold_ns=250_000_000))
    verdicts = decider.frame(Candidate(ts, frame_id, q, arrived_ns=now), Load(queued, n), now)
    verdicts += decider.tick(Load(queued, n), now)      # while decider.held is not empty
    # a FORWARD whose put was refused: decider.refused(frame) gives the DROP to record

The rules every policy shares (late frames, the gyro-missing rule, q_min, time order, the
maximum hold time, repair of a misbehaving policy) live in ``_decider.py``; its docstring
lists them in the order they apply.

Writing a policy (the contract): a module ``_<name>.py`` with a class that has

- ``name``: what ``--policy`` selects and every decision record carries;
- ``on_frame(frame, view) -> Sequence[Verdict]``: exactly one verdict for ``frame`` (a
  :class:`Candidate` with a quality, q >= q_min, newer than every frame before), plus any
  verdicts on frames in ``view.held`` (e.g. one the new frame replaces);
- ``on_tick(view) -> Sequence[Verdict]``: verdicts on held frames only; called before and
  after every frame and on every tick while frames are held;

and one line in ``_registry.py``'s ``POLICIES`` (and this ``__all__`` if it is public). A
policy is causal: it sees only the :class:`View`, which is everything the mediator knows —
``now_ns``; ``load`` (the detector's queue: ``queued``, ``capacity`` N, ``fill`` = the
paper's load, ``free`` slots, ``idle``); ``held`` (frames held, oldest first, with their
``arrived_ns``); ``recent_q`` (the last qualities, the recent distribution); ``detector``
(when it last took a frame and its estimated service time: the processing clock); and
``max_hold_ns``. A policy never stores frames (the decider holds them, so none is lost) but
may keep statistics of its own; it must not read a clock or do I/O. FORWARDs go out in time
order; the decider drops what breaks a rule and counts contract faults in
``policy_faults``. Reasons are short kebab-case words; ``held`` marks a frame still waiting.

Policies: ``paper`` (forward iff q > load: the paper's rule), ``replace`` (hold the
sharpest frames, one for each free queue slot; see ``_replace.py``), ``deadline`` (hold the
best frame and forward it just before the detector needs one) and ``adaptive`` (quantile
thresholds of the recent qualities on the detector's processing clock; tuned on
calibration seeds; see ``_adaptive.py``).
"""

from ._adaptive import AdaptivePolicy
from ._deadline import DeadlinePolicy
from ._decider import DEFAULT_MAX_HOLD_NS, Decider, GyroMissing, Rules
from ._paper import PaperPolicy
from ._policy import Policy
from ._records import (
    Action,
    Candidate,
    DetectorClock,
    Load,
    Verdict,
    View,
    queue_load,
    tightest_load,
)
from ._registry import DEFAULT_POLICY, POLICIES, make_policy
from ._replace import ReplacePolicy

__all__ = [
    "DEFAULT_MAX_HOLD_NS",
    "DEFAULT_POLICY",
    "POLICIES",
    "Action",
    "AdaptivePolicy",
    "Candidate",
    "DeadlinePolicy",
    "Decider",
    "DetectorClock",
    "GyroMissing",
    "Load",
    "PaperPolicy",
    "Policy",
    "ReplacePolicy",
    "Rules",
    "Verdict",
    "View",
    "make_policy",
    "queue_load",
    "tightest_load",
]
