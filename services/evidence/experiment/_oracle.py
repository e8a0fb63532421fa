"""The offline-optimal schedule: the most recognitions any frame selection could reach.

Theory of operation. Frames arrive at ``arrivals_ns`` (in order). The detector processes
one frame at a time for exactly ``service_ns``, takes frames in arrival order and starts
the next one the moment it is free (it never idles with a frame waiting). At most
``capacity`` chosen frames may have arrived and not yet started: the detector's queue N,
plus the frames a mediator may hold back (one for a mediator with a hold slot, as
``replace`` has; zero for one that only accepts or rejects at arrival, as the paper's).
A frame that would exceed that is lost, exactly as the camera's flow control or a full
mediator loses it. The oracle knows every frame's value in advance and picks the subset
to process that maximises the summed value.

Why a dynamic programme over server-free times is exact. Decide frames in arrival order
and let F be the time the detector finishes the last chosen frame. Every chosen frame
has arrived by the time the next one arrives (at ``a``), so a chosen frame that has not
started by ``a`` started later than its arrival, which means exactly when its predecessor
finished: the unstarted frames form one busy chain ending at F, starting at F - S,
F - 2S, ... Their number is ``ceil((F - a) / S) - 1`` (for F > a), a function of F and
``a`` alone. So F is the whole state: whether frame i can be taken and what taking it does
(F becomes max(F, a_i) + S) depend on nothing else. F only takes values a_j + kS, finitely
many, and a smaller F with at least the value dominates a larger one (fewer frames waiting
at every later arrival, earlier finish after every later choice), so keeping the Pareto
front of (F, value) after each frame loses no optimum. The result is the exact optimum;
``tests`` check it against brute force over every subset on small cases.
"""

from __future__ import annotations

import itertools
from collections.abc import Sequence
from dataclasses import dataclass

from ._config import ExperimentError

_IDLE = -(2**62)


@dataclass(frozen=True, slots=True)
class OracleSchedule:
    """The optimal selection: ``frames`` (indices into the arrivals, in order) and the
    summed ``value`` of their values."""

    frames: tuple[int, ...]
    value: int


def waiting_at(free_ns: int, arrival_ns: int, service_ns: int) -> int:
    """How many frames of a busy chain that ends at ``free_ns`` have not started by
    ``arrival_ns`` (the one in processing does not count)."""
    if free_ns <= arrival_ns:
        return 0
    return -(-(free_ns - arrival_ns) // service_ns) - 1


def feasible(
    arrivals_ns: Sequence[int], chosen: Sequence[int], *, service_ns: int, capacity: int
) -> bool:
    """Whether processing exactly ``chosen`` (indices, increasing) keeps at most
    ``capacity`` frames waiting at every arrival of a chosen frame."""
    free_ns = _IDLE
    for index in chosen:
        arrival = arrivals_ns[index]
        if free_ns > arrival and waiting_at(free_ns, arrival, service_ns) >= capacity:
            return False
        free_ns = max(free_ns, arrival) + service_ns
    return True


def optimal_schedule(
    arrivals_ns: Sequence[int], values: Sequence[int], *, service_ns: int, capacity: int
) -> OracleSchedule:
    """The subset of frames with the largest summed value that the queue can process (see
    the module docstring). Among equal values, the one that frees the detector earliest."""
    if len(arrivals_ns) != len(values):
        raise ExperimentError(f"{len(arrivals_ns)} arrivals but {len(values)} values")
    if service_ns <= 0:
        raise ExperimentError(f"service time must be > 0 ns, got {service_ns}")
    if capacity < 0:
        raise ExperimentError(f"capacity must be >= 0 frames, got {capacity}")
    if any(b < a for a, b in itertools.pairwise(arrivals_ns)):
        raise ExperimentError("arrivals must be in time order")
    # Pareto front: free time -> (value, back pointer). A back pointer is (frame, previous
    # node) kept as a linked list so that no schedule is copied per state.
    front: dict[int, tuple[int, tuple[int, object] | None]] = {_IDLE: (0, None)}
    for index, (arrival, value) in enumerate(zip(arrivals_ns, values, strict=True)):
        candidates = dict(front)
        if value > 0:
            for free_ns, (total, link) in front.items():
                if free_ns > arrival and waiting_at(free_ns, arrival, service_ns) >= capacity:
                    continue
                new_free = max(free_ns, arrival) + service_ns
                new_total = total + value
                kept = candidates.get(new_free)
                if kept is None or kept[0] < new_total:
                    candidates[new_free] = (new_total, (index, link))
        front = _pareto(candidates)
    best_free = min(front, key=lambda f: (-front[f][0], f))
    total, link = front[best_free]
    frames: list[int] = []
    while link is not None:
        index, rest = link
        frames.append(index)
        link = rest  # type: ignore[assignment]
    return OracleSchedule(tuple(reversed(frames)), total)


def _pareto(
    states: dict[int, tuple[int, tuple[int, object] | None]],
) -> dict[int, tuple[int, tuple[int, object] | None]]:
    """Only the states no earlier-free state matches in value."""
    kept: dict[int, tuple[int, tuple[int, object] | None]] = {}
    best = -1
    for free_ns in sorted(states):
        total, link = states[free_ns]
        if total > best:
            kept[free_ns] = (total, link)
            best = total
    return kept
