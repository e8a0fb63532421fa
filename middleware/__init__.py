"""framegate middleware: named, timestamp-keyed buffers over Eclipse Zenoh.

(Temporary front door while the core lands; grows with the transport layer.)
"""

from ._errors import (
    ConfigError,
    CoverageError,
    DuplicateTimestampError,
    FlowControlRefused,
    FramegateError,
    NotFoundError,
    PayloadTooLargeError,
    QueryError,
    SchemaError,
    TransportError,
)
from ._xml import XmlLimits, field_text, make_metadata, parse_untrusted, validate_metadata

__all__ = [
    "ConfigError",
    "CoverageError",
    "DuplicateTimestampError",
    "FlowControlRefused",
    "FramegateError",
    "NotFoundError",
    "PayloadTooLargeError",
    "QueryError",
    "SchemaError",
    "TransportError",
    "XmlLimits",
    "field_text",
    "make_metadata",
    "parse_untrusted",
    "validate_metadata",
]
