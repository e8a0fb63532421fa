"""What ``framegate view`` streams, and where it listens."""

from __future__ import annotations

import ipaddress
import os
from collections.abc import Mapping
from dataclasses import dataclass

from middleware import OBSERVE_QUEUE_MAX, ConfigError

DEFAULT_PORT = 8765
# The variable that moves the WebSocket port (a flag still wins): two pipelines on one
# host, each with its own FRAMEGATE_LOCAL_PORT, then each get their own viewer port.
VIEW_PORT_ENV = "FRAMEGATE_VIEW_PORT"
DEFAULT_HOST = "127.0.0.1"
# Observer queue per frame buffer: a viewer that falls behind misses notifications (counted)
# rather than holding anything back. A few frames absorb a scheduling hiccup; more would
# only show older frames. Small, frequent elements (gyro batches, verdicts) get a longer
# queue (SMALL_QUEUE), so a busy machine does not punch holes into the plots.
DEFAULT_QUEUE = 4
SMALL_QUEUE = 32
# Messages the Foxglove server buffers per client before it drops that client's oldest
# ones. 64 is about a second of the demo's traffic, and at most ~80 MB of raw frames.
DEFAULT_BACKLOG = 64


def default_port(environ: Mapping[str, str] | None = None) -> int:
    """``$FRAMEGATE_VIEW_PORT`` if set (checked as a port), else 8765."""
    value = (os.environ if environ is None else environ).get(VIEW_PORT_ENV)
    if not value:
        return DEFAULT_PORT
    if not value.isdigit() or not 0 <= int(value) <= 65535:
        raise ConfigError(f"{VIEW_PORT_ENV}={value} is not a port number: use 0..65535 (0: any)")
    return int(value)


@dataclass(frozen=True, slots=True)
class ViewConfig:
    """``targets`` empty: every buffer of every live service, including ones that come later."""

    targets: tuple[str, ...] = ()
    host: str = DEFAULT_HOST
    port: int = DEFAULT_PORT
    jpeg_quality: int | None = None
    queue: int = DEFAULT_QUEUE
    backlog: int = DEFAULT_BACKLOG
    status_interval_s: float = 1.0
    discover_interval_s: float = 2.0
    duration_s: float | None = None
    discovery_timeout_s: float = 3.0

    def __post_init__(self) -> None:
        if not 0 <= self.port <= 65535:
            raise ConfigError(f"--port {self.port}: must be 0..65535 (0: any free port)")
        if self.jpeg_quality is not None and not 1 <= self.jpeg_quality <= 100:
            raise ConfigError(f"--jpeg {self.jpeg_quality}: JPEG quality must be 1..100")
        # Checked here, not by each subscription: a queue no producer registers made the
        # view warn "cannot stream ... trying again" every 2 s for good, streaming nothing.
        if not 1 <= self.queue <= OBSERVE_QUEUE_MAX:
            raise ConfigError(
                f"--queue {self.queue}: must be 1..{OBSERVE_QUEUE_MAX} (the observe limit)"
            )
        if self.backlog < 1:
            raise ConfigError(f"--backlog {self.backlog}: must be >= 1")
        if self.duration_s is not None and self.duration_s <= 0:
            raise ConfigError(f"--duration {self.duration_s}: must be > 0 seconds")

    def queue_for(self, kind: str) -> int:
        """The observer queue for a buffer of ``kind``."""
        return self.queue if kind == "frame" else max(self.queue, SMALL_QUEUE)

    @property
    def images(self) -> str:
        """How frames travel: ``raw`` (foxglove.RawImage) or ``jpeg`` (CompressedImage)."""
        return "raw" if self.jpeg_quality is None else "jpeg"

    @property
    def exposed(self) -> bool:
        """Whether the server listens beyond this machine (a warning-worthy choice)."""
        try:
            return not ipaddress.ip_address(self.host).is_loopback
        except ValueError:
            return self.host != "localhost"
