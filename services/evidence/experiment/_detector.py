"""The real detector's timeline, for the replay: when it took each frame and for how long.

The replay of a mediator run (``seed_replay``) must give its detector the speed the real one
had *when* it had it: on a loaded machine a frame's processing varies (105-150 ms and spikes
of 400 ms against 107 ms emulated, measured), and a slow spell costs the frames decided
during it. So each step of ``QueueModel.service_steps`` is dated by the real take:

- the detector writes when it took each frame up (``FrameDetections.taken_ns``, on the
  frames' clock); mapped onto the replay's time base, those are the steps' times, and a
  frame the next one was already waiting for occupied it until that next take;
- records without it (an older detector) are reconstructed: a frame was taken at the later
  of its forward (its arrival plus the latency of the mediator's forwarding record) and
  the end of the frame before.

Dated by the frame's arrival instead, as the replay did before, every slow spell was charged
to the frames taken about a service time earlier, and the replay's detector filled the time
the real one lost in it with fast steps: 6 frames and 5 large-marker recognitions more than
the real run, at N = 1 on a 2-core machine at load 12-24, where the same replay with the
traced real takes processed exactly the real run's 172 frames (measured).

The hand-over and the acks are read the same way: how long after its forward an idle
detector took a frame (``handover_steps``), and how long after each take the mediator learnt
of it (``ack_steps``, from the decision records' ``take_seen_ns``), so that the replay's
mediator knows no more of the detector than the real one did.
"""

from __future__ import annotations

import bisect
import statistics
from collections.abc import Iterable, Mapping, Sequence

from services.lib.messages import DecisionRecord

from ._records import FrameDetections

# How much later than its ack the detector may stamp a take (``taken_ns``): the ack leaves
# when the frame is taken, the stamp is written when the runner turns to the frame (the
# mediator saw acks up to 4.8 ms before the stamp on a loaded 2-core machine, measured).
_STAMP_LAG_NS = 5_000_000


def detector_overhead_ns(uncontrolled: Sequence[FrameDetections], arrival: dict[int, int]) -> int:
    """What a frame costs the detector besides its processing time (taking, fetching,
    putting the result: 3-6 ms a frame on a loaded 2-core machine, measured), from the
    seed's uncontrolled run, where the camera keeps its queue full so the detector never
    idles: the time between the first and the last frame it took, per frame, less the
    mean processing time (``uncontrolled``: that run's detections; ``arrival``: frame id ->
    its arrival). 0 without that run; ``seed_replay`` uses it only if that run's camera
    skipped few frames late (a gap idles the detector, and the idle time would count as
    overhead: 18 ms a frame measured with 55 frames late), and only for records that do
    not say when the detector took each frame."""
    known = [d for d in uncontrolled if d.frame_id in arrival]
    if len(known) < 2:
        return 0
    taken = [arrival[d.frame_id] for d in known]
    cycle = (max(taken) - min(taken)) / (len(taken) - 1)
    processing = statistics.fmean(d.processing_ns for d in known)
    return max(0, round(cycle - processing))


def clock_offset_ns(decisions: Sequence[DecisionRecord], starts: Mapping[int, int]) -> int | None:
    """The camera's clock less the replay's time base: each frame's key (its exposure start
    as the camera stamped it) less its exposure start in the dataset (``starts``: frame id
    -> that), the median over a run's decision records; None without one."""
    offsets = [d.frame_timestamp_ns - starts[d.frame_id] for d in decisions if d.frame_id in starts]
    return int(statistics.median(offsets)) if offsets else None


def detector_steps(
    detections: Sequence[FrameDetections],
    decisions: Sequence[DecisionRecord],
    arrival: Mapping[int, int],
    nominal_ns: int,
    overhead_ns: int,
    offset_ns: int | None,
) -> tuple[tuple[tuple[int, int], ...], int]:
    """The real detector of a run as ``QueueModel.service_steps`` (see the module
    docstring), and the overhead per frame they include.

    ``detections`` and ``decisions`` (the final ones) are the run's records; ``arrival``:
    frame id -> its arrival in the replay's time base; ``nominal_ns``: the emulated
    processing time (no frame took less); ``overhead_ns``: the cost per frame besides
    processing for records that do not say when frames were taken; ``offset_ns``:
    ``clock_offset_ns`` of the run (None: the take times cannot be placed)."""
    done = sorted((d for d in detections if d.frame_id in arrival), key=lambda d: d.frame_id)
    forwarded = {
        d.frame_id: arrival[d.frame_id] + max(0, d.latency_ns)
        for d in decisions
        if d.accepted and d.frame_id in arrival
    }
    sent = [forwarded.get(d.frame_id, arrival[d.frame_id]) for d in done]
    busy = [max(nominal_ns, d.processing_ns) for d in done]
    if done and offset_ns is not None and all(d.taken_ns is not None for d in done):
        took = [d.taken_ns - offset_ns for d in done if d.taken_ns is not None]
        # Back to back: the next frame was there before this one's processing ended, so
        # this one occupied the detector until the next take.
        after = [k for k in range(len(done) - 1) if sent[k + 1] <= took[k] + busy[k]]
        cycles = {k: took[k + 1] - took[k] for k in after}
        if cycles:
            overhead_ns = max(0, int(statistics.median(cycles[k] - busy[k] for k in after)))
        steps = [(took[k], max(1, cycles.get(k, busy[k] + overhead_ns))) for k in range(len(done))]
        return tuple(steps), overhead_ns
    steps = []
    free_ns: int | None = None
    for k in range(len(done)):
        at = sent[k] if free_ns is None else max(sent[k], free_ns)
        steps.append((at, busy[k] + overhead_ns))
        free_ns = at + busy[k] + overhead_ns
    return tuple(steps), overhead_ns


def ack_steps(
    detections: Sequence[FrameDetections],
    decisions: Iterable[DecisionRecord],
    offset_ns: int | None,
) -> tuple[tuple[int, int], ...]:
    """How late the mediator of a run learnt of each take, for ``QueueModel.ack_steps``:
    (the take in the replay's time base, the delay until the mediator saw it).

    A take is seen when its ack reaches the mediator's producer; until then the producer
    counts the frame as queued, and the decider can neither date the take nor use the slot.
    The replay's mediator must know what the real one knew, no more: its detector's takes
    reach it as late as the real ones did. Each decision record says when the mediator last
    saw a take (``take_seen_ns``); the first such time at or after a take (the detector's
    ``taken_ns``, less ``_STAMP_LAG_NS``: the detector stamps a take just after its ack has
    left) is when that take was seen. A take whose ack was seen only after the next take was
    made cannot be told from that one's, and gives no step (the one before holds). () for
    records that do not say (an older mediator or detector): acks then arrive at once."""
    seen = sorted({d.take_seen_ns for d in decisions if d.take_seen_ns is not None})
    taken = sorted(d.taken_ns for d in detections if d.taken_ns is not None)
    if not seen or not taken or offset_ns is None:
        return ()
    steps: list[tuple[int, int]] = []
    for k, at in enumerate(taken):
        i = bisect.bisect_left(seen, at - _STAMP_LAG_NS)
        if i == len(seen):
            break
        if k + 1 < len(taken) and seen[i] >= taken[k + 1] - _STAMP_LAG_NS:
            continue
        steps.append((at - offset_ns, max(0, seen[i] - at)))
    return tuple(steps)


def handover_steps(
    detections: Sequence[FrameDetections],
    decisions: Sequence[DecisionRecord],
    arrival: Mapping[int, int],
    nominal_ns: int,
    offset_ns: int | None,
) -> tuple[tuple[int, int], ...]:
    """How long an idle detector of a run took to take a frame put to it, for
    ``QueueModel.handover_steps``: (the put in the replay's time base, until the take).

    The frame's forward (its arrival plus the latency of its forwarding record, which counts
    to the decision, before the put) to the detector's ``taken_ns``, for each frame that
    reached a detector done with the frame before it. The replay's detector took such a
    frame at once: at a run's first frame, 10 ms early (measured), and at N = 1, where the
    detector then takes back to back, the whole run stayed that far ahead of the real
    one, each take a frame early for the decisions in between. () for records that do not
    say when frames were taken."""
    if offset_ns is None:
        return ()
    done = sorted((d for d in detections if d.frame_id in arrival), key=lambda d: d.frame_id)
    forwarded = {
        d.frame_id: arrival[d.frame_id] + max(0, d.latency_ns)
        for d in decisions
        if d.accepted and d.frame_id in arrival
    }
    steps: list[tuple[int, int]] = []
    free_ns: int | None = None
    for detection in done:
        if detection.taken_ns is None:
            return ()
        took = detection.taken_ns - offset_ns
        sent = forwarded.get(detection.frame_id)
        if sent is not None and (free_ns is None or sent >= free_ns):
            steps.append((sent, max(0, took - sent)))
        free_ns = took + max(nominal_ns, detection.processing_ns)
    return tuple(steps)
