"""Quality from blur (paper eq. 3, with a scale) and the acceptance test (paper §4.3)."""

from __future__ import annotations

import math
import sys
from dataclasses import dataclass

DEFAULT_B0_PX = 5.0
"""Blur scale b0 of q = exp(-blur_px / b0_px), in pixels.

The paper's literal q = e^-b with b in pixels (b0 = 1) rejects so much at 1024x768,
f ~ 558 px, that the processor idles and recognition ends up worse than dropping frames at
random. A scale near the blur at which the target's recognition rate halves works; that is
about 4-6 px for ArUco markers at that size. ``derive_b0`` measures it from recorded frames.
"""

# q never reaches 0, so an idle consumer (load 0) still accepts any frame (paper §4.3).
_MIN_Q = sys.float_info.min


def _check_unit(name: str, value: float, *, open_low: bool = False) -> None:
    low_ok = value > 0.0 if open_low else value >= 0.0
    if not (low_ok and value <= 1.0):
        interval = "(0, 1]" if open_low else "[0, 1]"
        raise ValueError(f"{name} must be in {interval}, got {value!r}")


def quality(blur_px: float, b0_px: float = DEFAULT_B0_PX) -> float:
    """q = exp(-blur_px / b0_px) in (0, 1]; 1 is a still camera."""
    if not blur_px >= 0.0:
        raise ValueError(f"blur_px must be >= 0 (inf allowed), got {blur_px!r}")
    if not (b0_px > 0.0 and math.isfinite(b0_px)):
        raise ValueError(f"b0_px must be a positive finite number of pixels, got {b0_px!r}")
    return max(math.exp(-blur_px / b0_px), _MIN_Q)


def queue_load(pending: int, capacity: int) -> float:
    """System load in [0, 1]: pending notifications over the queue's capacity (paper §4.3)."""
    if capacity <= 0:
        raise ValueError(f"queue capacity must be positive, got {capacity}")
    if pending < 0:
        raise ValueError(f"pending count must be >= 0, got {pending}")
    return min(pending / capacity, 1.0)


def accept(q: float, load: float, q_min: float = 0.0) -> bool:
    """The acceptance test: a frame passes iff q > load and q >= q_min.

    An idle consumer (load 0) takes every frame; a full one (load 1) takes none.
    """
    _check_unit("q", q, open_low=True)
    _check_unit("load", load)
    _check_unit("q_min", q_min)
    return q > load and q >= q_min


@dataclass(frozen=True, slots=True)
class Decision:
    """What the mediator decided for one frame, and why."""

    timestamp_ns: int
    blur_px: float
    q: float
    load: float
    accepted: bool
    reason: str


def decide(
    timestamp_ns: int,
    blur_px: float,
    load: float,
    *,
    b0_px: float = DEFAULT_B0_PX,
    q_min: float = 0.0,
) -> Decision:
    """Quality of a frame from its blur, the acceptance test, and a one-line reason."""
    q = quality(blur_px, b0_px)
    accepted = accept(q, load, q_min)
    if accepted:
        reason = f"accepted: q {q:.3g} > load {load:.3g}"
    elif q < q_min:
        reason = f"rejected: q {q:.3g} below the minimum {q_min:.3g}"
    else:
        reason = f"rejected: q {q:.3g} <= load {load:.3g}"
    return Decision(timestamp_ns, blur_px, q, load, accepted, reason)
