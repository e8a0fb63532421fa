"""Driving a ``Mediator`` without its node's executor (tests that step it by hand): what
the executor does for it, one step at a time, on the test's thread."""

from __future__ import annotations

import time
import weakref

from services.nodes.mediator import GYRO_TAKE_MAX, OFFSET_PERIOD_S, Mediator

# How often a step looks for gyro samples while a frame waits for them (on the executor,
# gyro notifications run their handler at once).
GYRO_LOOK_S = 0.005
# Gyro batches taken per step at most.
GYRO_ROUNDS = 8
# When each stepped mediator measures its clocks next (``Node.every`` does it on the executor).
_MEASURE_AT: weakref.WeakKeyDictionary[Mediator, int] = weakref.WeakKeyDictionary()


def next_measure_ns(mediator: Mediator) -> int:
    """When ``step`` measures ``mediator``'s clocks next (0: at its first step)."""
    return _MEASURE_AT.get(mediator, 0)


def step(mediator: Mediator, timeout_s: float = 0.5) -> None:
    """Measure clocks when due, take what the gyro has, then one camera notification or,
    until something is due, nothing. Never raises for input."""
    now = time.monotonic_ns()
    if mediator._offsets.asked.is_set() or now >= next_measure_ns(mediator):
        mediator._measure(now)
        _MEASURE_AT[mediator] = now + int(OFFSET_PERIOD_S * 1e9)
    for _ in range(GYRO_ROUNDS):  # what the gyro sent since the last step
        notes = mediator._gyro_sub.take_many(GYRO_TAKE_MAX, timeout_s=0)
        if not notes:
            break
        mediator.on_gyro(notes)
    wait = timeout_s
    due = mediator.next_deadline_ns()
    if due is not None:
        wait = min(wait, max(0.0, (due - time.monotonic_ns()) / 1e9))
    if mediator.pairing.waiting:
        wait = min(wait, GYRO_LOOK_S)  # gyro samples are only seen at the next step
    note = mediator._camera.take(timeout_s=wait)
    if note is None:
        mediator.on_time(time.monotonic_ns())
    else:
        mediator.on_camera(note)
