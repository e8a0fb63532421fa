"""The one exception tree of framegate.

    FramegateError                 base: catch this to catch everything of ours
    ├── ConfigError                a configuration or deploy file is wrong
    ├── SchemaError                metadata is not well-formed, hostile, or fails its XSD
    ├── QueryError                 a query is malformed or the service answered with an error
    │   └── NotFoundError          no such service, buffer or element
    ├── FlowControlRefused         a subscriber's notification queue is full; nothing was stored
    ├── DuplicateTimestampError    a put's timestamp is not newer than the newest element
    ├── PayloadTooLargeError       a payload exceeds the buffer's configured limit
    ├── CoverageError              gyro samples do not cover a frame's exposure
    ├── CalibrationError           (services.lib.quality) recorded data cannot determine b0/offset
    └── TransportError             Zenoh failed underneath us (every zenoh.ZError maps here)

Messages name the bad value and say what to do.
"""

from __future__ import annotations


class FramegateError(Exception):
    """Base class of every error framegate raises on purpose."""


class ConfigError(FramegateError):
    """A configuration value, deploy file or endpoint is wrong."""


class SchemaError(FramegateError):
    """Metadata is malformed, hostile (DTD, entities, too big or deep) or fails its XSD."""


class QueryError(FramegateError):
    """A query is malformed, or the service answered a query with an error."""


class NotFoundError(QueryError):
    """No live service, buffer or element matches what was asked for."""


class FlowControlRefused(FramegateError):
    """A flow-controlled subscriber's notification queue is full; the element was not stored.

    The paper's rule: the source is prevented from producing. A camera drops the frame and
    counts it; a lossless source waits (``put(..., wait_s=...)``).
    """


class DuplicateTimestampError(FramegateError):
    """A put's timestamp is equal to or older than the buffer's newest element."""


class PayloadTooLargeError(FramegateError):
    """A payload exceeds the buffer's configured ``max_payload_bytes``."""


class CoverageError(FramegateError):
    """Gyro samples do not cover a frame's exposure (no data, or a gap longer than allowed)."""


class TransportError(FramegateError):
    """Zenoh failed underneath framegate (session, network or endpoint problem)."""
