"""One frame through a vision handler, with no I/O: decode the frame, call the handler,
encode its result, or count why there is none (``VisionStep``; the runner around it is
``services/nodes/vision.py``, tests call it directly)."""

from __future__ import annotations

import collections
import logging
import re
import time
import traceback
from collections.abc import Callable
from dataclasses import dataclass

from middleware import FramegateError
from services.lib.messages import decode_image, read_frame_metadata
from services.lib.vision import Encoded, FrameMeta, ResultKind, encode_result, plain_result
from services.nodes._vision_handler import Handler, Image

# Distinct warning kinds remembered; past this, further kinds share one (a handler raising
# a new exception type per frame must not grow the log or this set without bound).
_MAX_WARNING_KINDS = 64
# The longest exception type name a skip reason keeps (``handler-error:NAME``).
_MAX_TYPE_NAME = 64

__all__ = ["Encoded", "Skipped", "VisionStep", "call_directly", "user_traceback"]


@dataclass(frozen=True, slots=True)
class Skipped:
    """A frame that produced no element: why (the skip reason ``info`` counts) and detail."""

    reason: str
    detail: str


def call_directly(work: Callable[[], object]) -> object:
    return work()


class _HandlerFailed(Exception):
    """The handler raised (any ``BaseException``: ``SystemExit``, ``KeyboardInterrupt`` from
    the user's code is not a stop of this service): one skipped frame. Its type name, text
    and traceback are made on the handler's thread, where a stop reaches them (an
    exception's ``__str__`` that blocks, or raises ``SystemExit``, ran on the runner's loop)."""

    def __init__(self, original: BaseException) -> None:
        self.name = _type_name(original)
        self.text = _text(original)
        try:
            self.trace = user_traceback(original)
        except BaseException:
            self.trace = f"(the traceback of {self.name} cannot be printed)"
        super().__init__(self.text)


def _guarded(handler: Handler, image: Image, frame: FrameMeta) -> object:
    """Call the handler; whatever it raises comes back as ``_HandlerFailed``, so that only a
    real stop (``_Stopped``, raised by the caller's side, not here) ends the runner."""
    try:
        return handler(image, frame)
    except BaseException as exc:
        raise _HandlerFailed(exc) from None


@dataclass(frozen=True, slots=True)
class _BadResult:
    """The handler returned, but its result cannot be converted (returned, not raised, so
    that it is not counted as the handler's error)."""

    error: FramegateError


def _plain(result: object, kind: ResultKind) -> object:
    """``plain_result`` on the handler's thread: the result's own code (a ``__float__``, a
    ``__str__``) runs where a stop reaches it and where what it raises is one skip."""
    try:
        return plain_result(result, kind)
    except FramegateError as exc:
        return _BadResult(exc)


def user_traceback(exc: BaseException) -> str:
    """``exc``'s traceback from the handler's own frame on (below ``_guarded``), the same for
    every exception type: the runner's frames before it are framegate's, not the user's."""
    tb, shown = exc.__traceback__, exc.__traceback__
    while tb is not None:
        if tb.tb_frame.f_code is _guarded.__code__ and tb.tb_next is not None:
            shown = tb.tb_next
        tb = tb.tb_next
    return "".join(traceback.format_exception(type(exc), exc, shown)).rstrip("\n")


def _type_name(exc: BaseException) -> str:
    """The name of ``exc``'s type as a skip reason can carry it: a type made at run time
    may be named anything, and a reason with a newline or past 1,024 characters made the
    output buffer's description unreadable (``framegate info`` refused it)."""
    name = re.sub(r"[^\w.]", "?", type(exc).__name__)
    return name[:_MAX_TYPE_NAME] or "?"


def _text(exc: BaseException) -> str:
    """``str(exc)``, or a placeholder when the handler's exception cannot even say what
    it is (its ``__str__`` raises)."""
    try:
        return str(exc)
    except BaseException:
        return f"<{_type_name(exc)} whose message cannot be printed>"


class VisionStep:
    """One frame in, one element (or a counted skip) out; no network, no threads.

    ``call`` runs the handler's invocation (the service wraps it to honour a stop); the time
    it takes is the element's ``processing_ns``.
    """

    def __init__(
        self,
        handler: Handler,
        kind: ResultKind,
        source: str,
        log: logging.Logger,
        call: Callable[[Callable[[], object]], object] = call_directly,
    ) -> None:
        self.handler = handler
        self.kind = kind
        self.source = source
        self.log = log
        self._call = call
        self.skipped = collections.Counter[str]()
        self.processed = 0
        self._warned: set[str] = set()

    def process(
        self, timestamp_ns: int, payload: bytes, metadata: bytes, taken_ns: int | None = None
    ) -> Encoded | Skipped:
        """Decode the frame, run the handler, encode its result (``taken_ns``: when the
        frame was taken up, written into a detections result)."""
        try:
            frame = read_frame_metadata(metadata)
            image = decode_image(payload, frame)
            if frame.timestamp_ns != timestamp_ns:
                raise FramegateError(
                    f"metadata says timestamp {frame.timestamp_ns}, element is {timestamp_ns}"
                )
        except (FramegateError, KeyError, ValueError) as exc:
            return self.skip("bad-frame", f"frame {timestamp_ns}: {exc}")
        started = time.monotonic_ns()
        try:
            result = self._call(lambda: _plain(_guarded(self.handler, image, frame), self.kind))
        except _HandlerFailed as failed:  # the user's code: anything it raises is one skip
            return self.skip(
                f"handler-error:{failed.name}",
                f"frame {frame.frame_id}: handler raised {failed.name}: {failed.text}",
                trace=failed.trace,
            )
        processing_ns = time.monotonic_ns() - started
        self.processed += 1
        if isinstance(result, _BadResult):
            return self.skip("bad-result", f"frame {frame.frame_id}: {result.error}")
        try:
            encoded = encode_result(result, self.kind, frame, self.source, processing_ns, taken_ns)
        except FramegateError as exc:
            return self.skip("bad-result", f"frame {frame.frame_id}: {exc}")
        if encoded is None:
            return self.skip("no-result", "", warn=False)
        return encoded

    def skip(
        self, reason: str, detail: str, *, warn: bool = True, trace: str | None = None
    ) -> Skipped:
        """Count ``reason``; the first time it is seen, log ``detail`` as a warning."""
        # A kind already counted keeps its own count; only new ones past the bound share one.
        if (
            reason.startswith("handler-error:")
            and reason not in self.skipped
            and len(self._warned) >= _MAX_WARNING_KINDS
        ):
            reason = "handler-error:other"
        self.skipped[reason] += 1
        if warn:
            text = f"{detail} (skipped; further '{reason}' skips are counted, not logged)"
            if trace is not None:
                text += "\n" + trace
            self.warn_once(reason, text)
        return Skipped(reason, detail)

    def warn_once(self, kind: str, text: str) -> None:
        """Log ``text`` as a warning the first time ``kind`` is seen."""
        if kind not in self._warned:
            self._warned.add(kind)
            self.log.warning("%s", text)
