"""The mediator's pairing: each camera frame with the gyro samples of its exposure, to a
quality (see ``services.nodes.mediator``).

A frame waits for gyro coverage at most ``gyro_wait_ns`` after it arrived, but never holds
the frames behind it back: every frame waits on its own deadline, and the frames are handed
on in arrival order as soon as each is covered or due. While the gyro is known to be out
(a frame's wait ended without coverage and no sample arrived since), new frames wait for
nothing: the gyro-missing rule decides them at once. So a dead, stopped or late gyro never
slows the mediator below the camera's rate.

A frame is paired only while camera and gyro clocks are known to agree: after a camera or
gyro restart, frames wait (as for coverage) for their clocks to be measured again, and are
unpaired (``clock-unmeasured``) if that takes longer; beyond ``max_clock_offset`` of the
exposure they are unpaired (``clock-offset``); the gyro-missing rule decides both.

Nothing here waits or starts a thread: the caller feeds frames (``add``) and asks at its own
times, with its monotonic clock, what is ready (``ready``) and when to ask next
(``next_deadline_ns``).
"""

from __future__ import annotations

import collections
import logging
import time
from dataclasses import dataclass

from middleware import FramegateError
from services.lib.frame_layout import FrameError
from services.lib.messages import FrameMeta
from services.lib.quality import (
    BlurOptions,
    CoverageError,
    GyroSamples,
    frame_quality,
)
from services.nodes._mediator_inputs import ClockOffsets, GyroCache

# Frames waiting for coverage at once, at most: beyond, the oldest is decided without it
# (a camera that floods frames cannot make the mediator hold their bytes without bound).
MAX_WAITING = 64


# A frame the mediator skips; ``reason`` goes into its decision record. The frame checks
# are the one shared ``check_frame`` (services.lib.messages).
BadFrame = FrameError


def blur_quality(
    meta: FrameMeta, samples: GyroSamples, options: BlurOptions, b0_px: float
) -> tuple[float, float]:
    """Blur and quality of a frame with a camera model; BadFrame when they are not numbers.

    CoverageError when the samples do not cover the exposure (the gyro-missing rule).
    """
    assert meta.camera is not None
    try:
        return frame_quality(samples, meta.exposure, meta.camera, b0_px, options)
    except CoverageError:
        raise
    except (FramegateError, ValueError, ArithmeticError) as exc:
        raise BadFrame("bad-blur", str(exc)) from exc


@dataclass(frozen=True, slots=True)
class Waiting:
    """A frame read and checked, waiting for its quality; its bytes go with it."""

    meta: FrameMeta
    payload: bytes
    metadata: bytes
    arrived_ns: int


@dataclass(frozen=True, slots=True)
class Paired:
    """A frame's outcome: its blur and quality, or why it has none (``unpaired``: a clock
    reason; None with no quality: the gyro does not cover it). ``error``: a BadFrame."""

    frame: Waiting
    blur_px: float | None
    q: float | None
    unpaired: str | None = None
    error: BadFrame | None = None


# A gyro outage is warned about once it lasts this long (briefer ones are counted).
_OUTAGE_SAY_NS = 1_000_000_000


class Pairing:
    """Frames waiting for gyro coverage, handed on in arrival order (module docstring)."""

    def __init__(
        self,
        gyro: GyroCache,
        offsets: ClockOffsets,
        *,
        gyro_wait_ns: int,
        b0_px: float,
        options: BlurOptions,
        max_clock_offset: float,
        log: logging.Logger,
        gyro_missing: str,
    ) -> None:
        self.gyro = gyro
        self.offsets = offsets
        self._wait_ns = gyro_wait_ns
        self._b0_px = b0_px
        self._options = options
        self._max_offset = max_clock_offset
        self._log = log
        self._policy = gyro_missing
        self._waiting: collections.deque[Waiting] = collections.deque()
        # The newest gyro sample when the gyro was found out; None while it is not.
        self._out_at: int | None = None
        self._gyro_ok = True
        # A gyro outage is warned about once it has lasted ``_OUTAGE_SAY_NS``: a loaded
        # machine makes many brief ones (a late batch), counted and said with the next.
        self._out_since_ns = 0
        self._outage_said = False
        self._brief_outages = 0
        self._offset_ok = True
        self._unmeasured_logged = False

    @property
    def waiting(self) -> int:
        return len(self._waiting)

    def add(self, frame: Waiting) -> None:
        self._waiting.append(frame)

    def next_deadline_ns(self) -> int | None:
        """When the oldest waiting frame is due without coverage (None: nothing waits)."""
        return self._waiting[0].arrived_ns + self._wait_ns if self._waiting else None

    def ready(self, now_ns: int) -> list[Paired]:
        """The waiting frames that are covered or due, oldest first; later ones stay."""
        out: list[Paired] = []
        if self._out_at is not None and self.gyro.newest_ns != self._out_at:
            self._out_at = None  # samples again: frames wait for coverage again
        while self._waiting:
            frame = self._waiting[0]
            overflow = len(self._waiting) > MAX_WAITING
            due = overflow or self._out_at is not None or now_ns >= frame.arrived_ns + self._wait_ns
            paired = self._pair(frame, due)
            if paired is None:
                break
            self._waiting.popleft()
            out.append(paired)
        return out

    def drain(self) -> list[Paired]:
        """Every waiting frame, decided as it stands now (the mediator stops)."""
        out = [self._pair(f, True) for f in self._waiting]
        self._waiting.clear()
        return [p for p in out if p is not None]

    def _pair(self, frame: Waiting, due: bool) -> Paired | None:
        meta = frame.meta
        camera = meta.camera
        if camera is None:
            return Paired(frame, None, None)
        clock = self._clocks(meta, due)
        if clock == "wait":
            return None  # the clocks are being measured: wait for that as for coverage
        if clock is not None:
            return Paired(frame, None, None, clock)
        start = meta.exposure.start_ns + camera.gyro_time_offset_ns
        end = meta.exposure.end_ns + camera.gyro_time_offset_ns
        end += camera.height_px * camera.line_readout_ns
        newest = self.gyro.newest_ns
        if newest is None or newest < end:
            if not due:
                return None
            self._missing(meta, newest)
            return Paired(frame, None, None)
        try:
            blur, q = blur_quality(meta, self.gyro.window(start, end), self._options, self._b0_px)
        except CoverageError as exc:
            self._log.debug("frame %d: %s", meta.frame_id, exc)
            self._missing(meta, newest)
            return Paired(frame, None, None)
        except BadFrame as exc:
            return Paired(frame, None, None, error=exc)
        if not self._gyro_ok:
            if self._outage_said:
                self._log.warning("gyro covers frames again from frame %d", meta.frame_id)
            else:
                self._brief_outages += 1
            self._gyro_ok = True
        return Paired(frame, blur, q)

    def _missing(self, meta: FrameMeta, newest: int | None) -> None:
        """The gyro does not cover this frame: out until a new sample arrives."""
        self._out_at = newest
        now = time.monotonic_ns()
        if self._gyro_ok:
            self._gyro_ok, self._out_since_ns, self._outage_said = False, now, False
        if self._outage_said or now - self._out_since_ns < _OUTAGE_SAY_NS:
            return
        self._outage_said = True
        brief, self._brief_outages = self._brief_outages, 0
        self._log.warning(
            "gyro does not cover frame %d (newest gyro sample %s); policy: %s, decided at "
            "once until gyro samples arrive again%s",
            meta.frame_id,
            "none yet" if newest is None else newest,
            self._policy,
            f" ({brief} briefer outages before, not logged)" if brief else "",
        )

    def _clocks(self, meta: FrameMeta, due: bool) -> str | None:
        """Why camera and gyro stamps cannot be paired now, or None when they can.

        Pairing looks up the gyro samples stamped during the frame's exposure; if the two
        clocks disagree by more than ``max_clock_offset`` of the exposure, those samples
        are of another moment (``clock-offset``); until both clocks have been measured
        (at start, after either restarted) that is not known: the frame waits for the
        measurement as for coverage (``wait``), and when due is ``clock-unmeasured`` (with no
        gyro sample at all, the frame is simply not covered). Warned once per episode.
        """
        measured = self.offsets.current()
        if measured is None and self.gyro.newest_ns is None:
            return None  # no gyro sample at all: nothing to pair with (gyro missing)
        if measured is None:
            if not due:
                return "wait"
            if not self._unmeasured_logged:
                self._unmeasured_logged = True
                self._log.warning(
                    "camera and gyro clocks not measured yet (a source started or started "
                    "over): frames are not paired (clock-unmeasured) until they are"
                )
            return "clock-unmeasured"
        if self._unmeasured_logged:
            self._unmeasured_logged = False
            self._log.warning("camera and gyro clocks measured: %+.1f ms", measured[0] / 1e6)
        limit_ns = self._max_offset * meta.exposure.duration_ns
        agree = abs(measured[0]) - measured[1] <= limit_ns
        if agree != self._offset_ok:
            self._offset_ok = agree
            if agree:
                self._log.warning(
                    "camera and gyro clocks agree again (%+.1f ms)", measured[0] / 1e6
                )
            else:
                self._log.warning(
                    "camera clock is %+.3f s (+-%.3f) off the gyro's, more than %g of the "
                    "%.0f ms exposure: frames are not paired with gyro samples (clock-offset) "
                    "until they agree; synchronise the clocks (chrony)",
                    measured[0] / 1e9,
                    measured[1] / 1e9,
                    self._max_offset,
                    meta.exposure.duration_ns / 1e6,
                )
        return None if agree else "clock-offset"
