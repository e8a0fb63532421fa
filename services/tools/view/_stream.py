"""One buffer streamed to Foxglove: observe, derive the wanted messages, publish.

Buffering rule: the viewer *observes* (``SubscriptionMode.OBSERVE``) with a small queue, so
it never holds a producer back; when it falls behind it misses notifications and counts
them (``missed`` in the status line) while a client watches the buffer: with nobody
watching, a notification passed over is missed by no one. It shows the newest data, so a
miss is never fetched back. A frame's payload is fetched only while some client subscribes
to its image channel.

Threads: each buffer has its own daemon thread that takes notifications, fetches, derives
and publishes. The shared ``FrameSizes`` (the newest frame's size, for verdict borders) is
a plain attribute written and read whole.
"""

from __future__ import annotations

import threading
import time

from middleware import (
    BufferInfo,
    DataObject,
    FramegateError,
    Node,
    Notification,
    Subscription,
    SubscriptionMode,
)
from services.tools.bag import Deriver, frame_layout

from ._config import ViewConfig
from ._server import FoxgloveServer
from ._status import Counters

TAKE_TIMEOUT_S = 0.2
LOOKUP_INTERVAL_S = 1.0
LOOKUP_TIMEOUT_S = 1.0


class FrameSizes:
    """The newest raw frame's (width, height) in pixels, whichever buffer it came from."""

    def __init__(self) -> None:
        self.size_px: tuple[int, int] | None = None
        self._next_lookup = 0.0

    def known(self, node: Node) -> tuple[int, int] | None:
        """The size, asking a live frame buffer for its newest frame while none has been
        seen: a verdict's notification can overtake its frame's (each buffer has its own
        thread), and the verdict border needs the size. At most one lookup per second."""
        if self.size_px is not None or time.monotonic() < self._next_lookup:
            return self.size_px
        self._next_lookup = time.monotonic() + LOOKUP_INTERVAL_S
        try:
            frames = [
                b.name
                for s in node.services(timeout_s=LOOKUP_TIMEOUT_S)
                for b in s.buffers
                if b.kind == "frame"
            ]
            for name in frames:
                for element in node.latest(name, 1, timeout_s=LOOKUP_TIMEOUT_S):
                    layout = frame_layout(element.metadata)
                    if layout is not None:
                        self.size_px = (layout.width_px, layout.height_px)
                        return self.size_px
        except FramegateError:
            pass  # no frame to ask: the verdict goes without its border, as before
        return self.size_px


class BufferStream:
    """Streams one buffer on its own thread until ``stop`` is set."""

    def __init__(
        self,
        node: Node,
        buffer: BufferInfo,
        config: ViewConfig,
        server: FoxgloveServer,
        counters: Counters,
        sizes: FrameSizes,
        stop: threading.Event,
    ) -> None:
        self.name = buffer.name
        self._node = node
        self._server = server
        self._counters = counters
        self._sizes = sizes
        self._stop = stop
        self._deriver = Deriver(
            buffer.service,
            buffer.buffer,
            buffer.kind,
            images=config.images,
            metadata=True,
            jpeg_quality=config.jpeg_quality or 80,
        )
        self._topics = {t.topic: t for t in self._deriver.topics}
        # Roles whose messages need the payload, not just the metadata.
        self._payload_topics = {
            t.topic for t in self._deriver.topics if t.role in ("image", "rates")
        }
        server.declare(self._deriver.topics)
        self._sub: Subscription = node.subscribe(
            buffer.name,
            queue_size=config.queue_for(buffer.kind),
            mode=SubscriptionMode.OBSERVE,
            wait_s=max(2.0, config.discovery_timeout_s),
        )
        self.error: BaseException | None = None
        # The subscription's missed total when last looked at, and the misses counted.
        self._missed_seen = 0
        self._missed = 0
        self.thread = threading.Thread(target=self._run, name=f"view-{self.name}", daemon=True)
        self.thread.start()

    def _run(self) -> None:
        try:
            while not self._stop.is_set():
                note = self._sub.take(timeout_s=TAKE_TIMEOUT_S)
                self._count_missed()
                if note is not None:
                    self._on_notification(note)
        except Exception as exc:  # the viewer says so and starts it again; the others go on
            self.error = exc

    def _count_missed(self) -> None:
        """Add the notifications passed over since the last look, if a client watches."""
        total = self._sub.missed_total
        passed, self._missed_seen = total - self._missed_seen, total
        if passed > 0 and self._server.wanted(self._deriver.topics):
            self._missed += passed
            self._counters.set_missed(self.name, self._missed)

    def _on_notification(self, note: Notification) -> None:
        if self._deriver.kind == "frame" and note.metadata is not None:
            layout = frame_layout(note.metadata)
            if layout is not None:
                self._sizes.size_px = (layout.width_px, layout.height_px)
        wanted = self._server.wanted(self._deriver.topics)
        if not wanted:
            return
        element = self._element(note, needs_payload=bool(wanted & self._payload_topics))
        if element is None:
            return
        size_px = self._sizes.known(self._node) if self._deriver.kind == "decision" else None
        messages = self._deriver.derive(element, frame_size_px=size_px, wanted=wanted)
        self._server.publish(self._topics, messages)

    def _element(self, note: Notification, *, needs_payload: bool) -> DataObject | None:
        if note.element is not None:
            return note.element
        if note.metadata is not None and not needs_payload:
            return DataObject(note.timestamp_ns, b"", note.metadata)
        try:
            return self._sub.fetch(note, timeout_s=2.0)
        except FramegateError:
            self._counters.add_lost(self.name)  # evicted, or its service went away
            return None

    def close(self) -> None:
        self.thread.join(timeout=2 * TAKE_TIMEOUT_S + 2.0)
        self._sub.close()
