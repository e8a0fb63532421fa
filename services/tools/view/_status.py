"""The viewer's counters and its one-line status: rates per channel, clients, drops.

Pure bookkeeping (no I/O, no clocks of its own): the streaming threads count, the status
loop takes a snapshot with the time it passes in.

Threads: ``Counters`` is updated from every buffer's streaming thread and from the
Foxglove server's callback thread, and read by the status loop; one lock guards it.
"""

from __future__ import annotations

import threading
from collections import Counter
from dataclasses import dataclass, field

# The status line fits a terminal of this width.
LINE_COLUMNS = 100
# Channels that carry frames (raw or JPEG).
IMAGE_SUFFIXES = ("/image", "/compressed")


@dataclass(frozen=True, slots=True)
class Status:
    """One status snapshot."""

    url: str
    clients: int
    rates_hz: dict[str, float]
    published: int
    missed: int
    lost: int
    slow_clients: dict[str, int]

    def line(self) -> str:
        """At most ``LINE_COLUMNS`` characters (the URL is printed once at start; ``--json``
        has every channel's rate): ``clients 1 | sent: 12 channels 160.2 msg/s, images
        15.0/s | missed 0 lost 0 | slow: 127.0.0.1:5000 (1x)``. The rates are what was sent
        to clients; ``missed`` counts the notifications passed over while a client watched
        their buffer (the viewer fell behind and showed a newer one), ``lost`` the elements
        it could not fetch for a client; a slow client has its oldest messages dropped."""
        total = sum(self.rates_hz.values())
        images = sum(hz for t, hz in self.rates_hz.items() if t.endswith(IMAGE_SUFFIXES))
        text = f"clients {self.clients} | "
        if self.clients == 0:
            # Nothing is sent, so there is nothing to rate: say what the viewer waits for.
            text += "waiting for a Foxglove client"
        elif self.rates_hz:
            text += f"sent: {len(self.rates_hz)} channels {total:.1f} msg/s, images {images:.1f}/s"
        else:
            text += f"{self.published} messages sent" if self.published else "nothing sent yet"
        text += f" | missed {self.missed} lost {self.lost}"
        if self.slow_clients:
            names = ", ".join(f"{a} ({n}x)" for a, n in sorted(self.slow_clients.items()))
            text += f" | slow: {names}"
        if len(text) > LINE_COLUMNS:
            text = text[: LINE_COLUMNS - 3] + "..."
        return text

    def json(self) -> dict[str, object]:
        return {
            "event": "status",
            "url": self.url,
            "clients": self.clients,
            "rates_hz": {t: round(hz, 2) for t, hz in sorted(self.rates_hz.items())},
            "published": self.published,
            "missed": self.missed,
            "lost": self.lost,
            "slow_clients": dict(sorted(self.slow_clients.items())),
        }


@dataclass
class Counters:
    """What the viewer did since it started."""

    published: Counter[str] = field(default_factory=Counter)
    # Per buffer: notifications the observer queue passed over while a client watched the
    # buffer (the viewer fell behind; unwatched, nothing is missed by anyone) and elements it
    # could not fetch for a client (evicted first).
    missed: dict[str, int] = field(default_factory=dict)
    lost: Counter[str] = field(default_factory=Counter)
    # Client id → channel ids it subscribes to.
    subscriptions: dict[int, set[int]] = field(default_factory=dict)
    # Client address → times the server reported its outbox full (it then drops the
    # client's oldest messages; the server reports at most once per 30 s).
    slow: Counter[str] = field(default_factory=Counter)
    _lock: threading.Lock = field(default_factory=threading.Lock)
    _last: tuple[float, Counter[str]] | None = None

    def count(self, topic: str, messages: int = 1) -> None:
        with self._lock:
            self.published[topic] += messages

    def set_missed(self, buffer: str, missed: int) -> None:
        with self._lock:
            self.missed[buffer] = missed

    def add_lost(self, buffer: str) -> None:
        with self._lock:
            self.lost[buffer] += 1

    def subscribed(self, client_id: int, channel_id: int) -> None:
        with self._lock:
            self.subscriptions.setdefault(client_id, set()).add(channel_id)

    def unsubscribed(self, client_id: int, channel_id: int) -> None:
        with self._lock:
            channels = self.subscriptions.get(client_id, set())
            channels.discard(channel_id)
            if not channels:
                self.subscriptions.pop(client_id, None)

    def slow_client(self, address: str) -> None:
        with self._lock:
            self.slow[address] += 1

    def client_gone(self, address: str) -> None:
        with self._lock:
            self.slow.pop(address, None)

    def snapshot(self, url: str, now_s: float) -> Status:
        """The status now; rates are over the time since the previous snapshot."""
        with self._lock:
            published = Counter(self.published)
            rates: dict[str, float] = {}
            if self._last is not None and now_s > self._last[0]:
                span = now_s - self._last[0]
                rates = {t: (n - self._last[1][t]) / span for t, n in published.items()}
            self._last = (now_s, published)
            return Status(
                url=url,
                clients=len(self.subscriptions),
                rates_hz=rates,
                published=sum(published.values()),
                missed=sum(self.missed.values()),
                lost=sum(self.lost.values()),
                slow_clients=dict(self.slow),
            )
