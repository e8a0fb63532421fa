"""Decision sequences as small tables, and a discrete-event detector to drive a decider.

A sequence is one event per line, times in milliseconds, the frame key = its number::

    frame t=0  f=1 q=0.30 queue=0/2  -> 1 forward quality>load
    tick  t=40      queue=0/2        -> 2 forward forwarded-held ; 3 drop superseded
    frame t=50 f=4 q=-    queue=1/2  -> 4 drop gyro-missing-idle

``q=-`` is a frame the gyro did not cover; ``-> -`` expects no verdict.
"""

from __future__ import annotations

import heapq
from dataclasses import dataclass, field

from services.lib.decisions import Action, Candidate, Decider, Load, Verdict

MS = 1_000_000


def _fields(text: str) -> dict[str, str]:
    return dict(part.split("=", 1) for part in text.split())


def _load(text: str) -> Load:
    queued, capacity = text.split("/")
    return Load(int(queued), int(capacity))


def _expected(text: str) -> list[tuple[int, Action, str]]:
    text = text.strip()
    if text == "-":
        return []
    out = []
    for part in text.split(";"):
        key, action, reason = part.split()
        out.append((int(key), Action(action), reason))
    return out


def play(decider: Decider, table: str) -> list[list[Verdict]]:
    """Feed every line to ``decider`` and check its verdicts; returns them per line."""
    seen: list[list[Verdict]] = []
    for number, line in enumerate(table.strip().splitlines(), 1):
        line = line.split("#", 1)[0].strip()
        if not line:
            continue
        event, rest = line.split(None, 1)
        given, _, want = rest.partition("->")
        f = _fields(given)
        now_ns = int(float(f["t"]) * MS)
        load = _load(f["queue"])
        if event == "frame":
            q = None if f["q"] == "-" else float(f["q"])
            frame = Candidate(int(f["f"]), int(f["f"]), q, arrived_ns=now_ns)
            verdicts = decider.frame(frame, load, now_ns)
        elif event == "tick":
            verdicts = decider.tick(load, now_ns)
        else:
            raise AssertionError(f"line {number}: unknown event {event!r}")
        got = [(v.frame.timestamp_ns, v.action, v.reason) for v in verdicts]
        assert got == _expected(want), f"line {number}: {line}"
        seen.append(verdicts)
    assert decider.policy_faults == 0
    return seen


@dataclass
class QueueRun:
    """What a simulated run saw: the most frames waiting at once, and what was processed."""

    max_queued: int = 0
    max_waiting: int = 0
    processed: list[int] = field(default_factory=list)
    verdicts: list[Verdict] = field(default_factory=list)
    refused: int = 0
    idle_ns: int = 0


def run_detector(
    decider: Decider,
    qualities: list[float],
    *,
    frame_period_ns: int,
    service_ns: int,
    capacity: int,
    tick_ns: int = MS,
    latencies_ns: list[int] | None = None,
    ack_delays_ns: tuple[int, ...] = (),
    service_steps_ns: tuple[int, ...] = (),
) -> QueueRun:
    """Frames every ``frame_period_ns`` into ``decider``; a FIFO detector with ``capacity``
    waiting slots takes one frame at a time for ``service_ns``. Ticks every ``tick_ns``.

    Frame i (numbered from 1, its ``frame_id``) is exposed at (i - 1) periods (its
    ``timestamp_ns``, the camera's clock) and decided ``latencies_ns[i - 1]`` later (0 by
    default); ``processed`` holds frame ids. ``ack_delays_ns``: the producer's count sees
    the n-th take ``ack_delays_ns[n % len]`` after it happened (its ack in flight; the take
    is dated when seen), and refuses a forward while that count is full (``refused``);
    ``idle_ns`` is how long the detector had nothing to do between its first take and its
    last. ``service_steps_ns``: the n-th frame takes ``service_ns + service_steps_ns[n %
    len]`` (a detector whose speed varies)."""
    run = QueueRun()
    queue: list[int] = []
    busy_until: int | None = None
    takes: list[tuple[int, int]] = []  # (taken, seen)

    def count(now: int) -> Load:
        if not ack_delays_ns:
            return Load(len(queue), capacity)  # every take seen, at once, undated
        unseen = sum(1 for _t, seen in takes[-capacity - 1 :] if seen > now)
        dated = [seen for _t, seen in takes if seen <= now]
        return Load(len(queue) + unseen, capacity, max(dated) if dated else None)

    def take(now: int) -> int:
        if takes:  # the detector was free since idle_since
            run.idle_ns += now - idle_since[0]
        run.processed.append(queue.pop(0))
        delay = ack_delays_ns[len(takes) % len(ack_delays_ns)] if ack_delays_ns else 0
        takes.append((now, now + delay))
        step = service_steps_ns[len(takes) % len(service_steps_ns)] if service_steps_ns else 0
        return now + service_ns + step

    idle_since = [0]
    events: list[tuple[int, int, str]] = []
    for i in range(len(qualities)):
        late = latencies_ns[i] if latencies_ns is not None else 0
        heapq.heappush(events, (i * frame_period_ns + late, 1, "frame"))
    end_ns = len(qualities) * frame_period_ns + (capacity + 2) * service_ns + 10 * tick_ns
    t = 0
    while t <= end_ns:
        heapq.heappush(events, (t, 2, "tick"))
        t += tick_ns
    index = 0
    while events:
        now, _, kind = heapq.heappop(events)
        # The detector finishes and takes the next frame before anything else happens now.
        if busy_until is not None and busy_until <= now:
            idle_since[0], busy_until = busy_until, None
        if busy_until is None and queue:
            busy_until = take(max(now, idle_since[0]))
        load = count(now)
        if kind == "frame":
            q = qualities[index]
            index += 1
            frame = Candidate((index - 1) * frame_period_ns, index, q, arrived_ns=now)
            verdicts = decider.frame(frame, load, now)
        else:
            verdicts = decider.tick(load, now)
        for verdict in verdicts:
            run.verdicts.append(verdict)
            if verdict.action is Action.FORWARD:
                if count(now).queued >= capacity:
                    assert ack_delays_ns, "forwarded into a full queue"
                    run.refused += 1
                    decider.refused(verdict.frame)
                    continue
                queue.append(verdict.frame.frame_id)
        if busy_until is None and queue:
            busy_until = take(now)
        run.max_queued = max(run.max_queued, len(queue))
        run.max_waiting = max(run.max_waiting, len(queue) + len(decider.held))
    return run
