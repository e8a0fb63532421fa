"""The one exception tree of framegate.

The middleware defines the base and the transport-level errors; each domain library or
tool defines its own errors next to its code, always below ``FramegateError``::

    FramegateError                 base: catch this to catch everything of ours
    ├── ConfigError                a configuration, deploy file or endpoint is wrong
    │   └── NameTakenError         another live instance already offers this service name
    ├── SchemaError                metadata is not well-formed, hostile, or fails its XSD
    │   └── FrameError             (services.lib.frame_layout) a frame no consumer could use
    ├── QueryError                 a query is malformed or the service answered with an error
    │   └── NotFoundError          no such service, buffer or element
    ├── FlowControlRefused         a subscriber's notification queue is full; nothing was stored
    ├── RegistrationRefused        a producer refused a subscription (a limit it names)
    ├── DuplicateTimestampError    a put's timestamp is not newer than the newest element
    ├── PayloadTooLargeError       a payload exceeds the buffer's configured limit
    ├── ClosedError                a put on a closed buffer: the process is stopping
    ├── TransportError             Zenoh failed underneath us (every zenoh.ZError maps here)
    ├── CoverageError              (services.lib.quality) gyro samples do not cover an exposure
    ├── CalibrationError           (services.lib.quality) data cannot determine b0 or an offset
    ├── QualityInputError          (services.lib.quality) an invalid frame, gyro batch or option
    ├── DatasetError               (services.lib.sim) a dataset directory is missing or damaged
    ├── RenderStopped              (services.lib.sim) a stop came while an approach rendered
    ├── OutputError                (services.lib.files) an output file cannot be written
    ├── BagError                   (services.tools.bag) an MCAP recording cannot be read/written
    ├── ExperimentError            (services.evidence.experiment) an experiment cannot run as asked
    └── BenchError                 (services.evidence.bench) a benchmark worker failed

Messages name the bad value and say what to do. ``tests/middleware/test_errors.py`` checks
that this drawing names every subclass there is.
"""

from __future__ import annotations


class FramegateError(Exception):
    """Base class of every error framegate raises on purpose."""


class ConfigError(FramegateError):
    """A configuration value, deploy file or endpoint is wrong."""


class NameTakenError(ConfigError):
    """Another live process already offers this service name (it names that process's pid
    and host). Restarting will not help while that one lives: ``framegate run`` exits with
    ``EXIT_NAME_TAKEN`` so that ``launch`` does not restart it."""


# ``framegate run``'s exit code for a NameTakenError: a supervisor must not restart it.
EXIT_NAME_TAKEN = 4


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


class RegistrationRefused(FramegateError):
    """A producer refused a subscription: too many subscriptions, or a queue beyond what it
    can hold for flow control. The message names the limit."""


class DuplicateTimestampError(FramegateError):
    """A put's timestamp is equal to or older than the buffer's newest element."""


class PayloadTooLargeError(FramegateError):
    """A payload exceeds the buffer's configured ``max_payload_bytes``."""


class ClosedError(FramegateError):
    """The buffer (its node) is closed: the process is stopping. A service that puts from a
    timer or handler meets it in the moment between a stop and its own end; not a failure."""


class TransportError(FramegateError):
    """Zenoh failed underneath framegate (session, network or endpoint problem)."""
