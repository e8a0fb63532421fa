"""``framegate view``: the running pipeline streamed live to Foxglove over its WebSocket protocol.

Frames become ``foxglove.RawImage`` (or JPEG ``CompressedImage``), the mediator's verdicts
and the detector's markers ``foxglove.ImageAnnotations`` on the frames they belong to, the
verdicts and gyro rates JSON channels for Plot, every buffer's metadata a JSON channel. The
topics are those ``framegate record`` writes (``services.tools.bag``), so one Foxglove layout
serves live and recorded data. The viewer observes and never slows a producer.
"""

from ._config import (
    DEFAULT_BACKLOG,
    DEFAULT_HOST,
    DEFAULT_PORT,
    DEFAULT_QUEUE,
    VIEW_PORT_ENV,
    ViewConfig,
    default_port,
)
from ._layout import foxglove_layout, installed_layout
from ._server import FoxgloveServer
from ._status import Counters, Status
from ._view import check_targets, parse_target, run_view

__all__ = [
    "DEFAULT_BACKLOG",
    "DEFAULT_HOST",
    "DEFAULT_PORT",
    "DEFAULT_QUEUE",
    "VIEW_PORT_ENV",
    "Counters",
    "FoxgloveServer",
    "Status",
    "ViewConfig",
    "check_targets",
    "default_port",
    "foxglove_layout",
    "installed_layout",
    "parse_target",
    "run_view",
]
