"""framegate middleware: named, timestamp-keyed buffers over Eclipse Zenoh.

A service offers named buffers (time series of payload + XML metadata keyed by int
nanoseconds); clients query them by time and subscribe to availability notifications with
a queue size of their choice. While a flow-controlled subscriber's queue is full the
producer is refused (paper §4.1). The bytes on the wire: docs/wire-format.md; the protocol:
docs/protocol.md.

Reading order, for whoever must change something:

1. ``_node`` — ``Node``: one Zenoh session, ``offer`` / ``subscribe``, and the executor API
   (``on`` / ``every`` / ``at`` / ``spin``); its parts ``_query`` (reading by time),
   ``_discovery`` (what is live, ``@info``; the bounded answers to ``@info/*`` in
   ``_info_intake``, liveliness queries no number of tokens can hang in ``_liveliness``)
   and ``_session`` (opening, Zenoh's errors).
2. ``_executor`` — the node's one thread: what waits, what runs per turn, and how a handler
   that blocks avoids waiting for itself. ``_inbox``: what runs on Zenoh's threads.
3. One side of the protocol at a time, each as one object: ``_protocol_producer`` (every
   decision a producer makes, as ``_protocol_events``; its fair shares per holder in
   ``_protocol_shares``) over the pure credit rules of ``_ledger_producer``; then
   ``_producer``, which only moves bytes and time between Zenoh and that object (what
   ``put`` checks of an element first: ``_element_check``; its put rate: ``_rate``). The same
   for the subscriber: ``_protocol_subscriber``, ``_ledger_subscriber``, ``_subscription``
   (whose log lines about registrations and lapses, which a peer can provoke, are rate-bounded
   by ``_news``).
4. ``_wire`` (the bytes on the wire), ``_service`` (queryables answering reads and
   ``@info``), ``_info_codec`` (the ``@info`` reply both ways, through the bounded gate of
   ``_decode``), ``_buffer`` (the time series), ``_records`` (the typed records and their one
   JSON form), then the rest (``_errors``, ``_xml``, ``_shapes``, ``_kinds``, ``_timerange``,
   ``_clock``, ``_config``, ``_rendezvous``).

docs/threads.md says which thread runs what and what each lock guards.
"""

from ._clock import ClockSample, ClockStatus, SteadyClock, now_ns
from ._config import (
    RENDEZVOUS_DELAY_MS,
    NetworkConfig,
    add_network_arguments,
    check_name,
    checked_endpoints,
    endpoint_parts,
    listening_endpoints,
    network_from_args,
)
from ._decode import listing, printable
from ._discovery import split_target
from ._errors import (
    EXIT_NAME_TAKEN,
    ClosedError,
    ConfigError,
    DuplicateTimestampError,
    FlowControlRefused,
    FramegateError,
    NameTakenError,
    NotFoundError,
    PayloadTooLargeError,
    QueryError,
    RegistrationRefused,
    SchemaError,
    TransportError,
)
from ._kinds import register_kind
from ._node import Node
from ._producer import Producer
from ._protocol_producer import FLOW_QUEUE_MAX, INLINE_METADATA_MAX, QUEUE_BUDGET
from ._protocol_subscriber import OBSERVE_QUEUE_MAX
from ._records import (
    BufferInfo,
    BufferLimits,
    DataObject,
    Notification,
    Retention,
    Rewind,
    ServiceInfo,
    SubscriptionInfo,
    SubscriptionMode,
    tightest_flow,
)
from ._subscription import PUSH_ALL, Subscription
from ._timerange import TimeRange, parse_duration_ns, parse_time_ns, parse_time_range
from ._xml import XmlLimits, field_text, make_metadata, parse_untrusted, validate_metadata

__all__ = [
    "EXIT_NAME_TAKEN",
    "FLOW_QUEUE_MAX",
    "INLINE_METADATA_MAX",
    "OBSERVE_QUEUE_MAX",
    "PUSH_ALL",
    "QUEUE_BUDGET",
    "RENDEZVOUS_DELAY_MS",
    "BufferInfo",
    "BufferLimits",
    "ClockSample",
    "ClockStatus",
    "ClosedError",
    "ConfigError",
    "DataObject",
    "DuplicateTimestampError",
    "FlowControlRefused",
    "FramegateError",
    "NameTakenError",
    "NetworkConfig",
    "Node",
    "NotFoundError",
    "Notification",
    "PayloadTooLargeError",
    "Producer",
    "QueryError",
    "RegistrationRefused",
    "Retention",
    "Rewind",
    "SchemaError",
    "ServiceInfo",
    "SteadyClock",
    "Subscription",
    "SubscriptionInfo",
    "SubscriptionMode",
    "TimeRange",
    "TransportError",
    "XmlLimits",
    "add_network_arguments",
    "check_name",
    "checked_endpoints",
    "endpoint_parts",
    "field_text",
    "listening_endpoints",
    "listing",
    "make_metadata",
    "network_from_args",
    "now_ns",
    "parse_duration_ns",
    "parse_time_ns",
    "parse_time_range",
    "parse_untrusted",
    "printable",
    "register_kind",
    "split_target",
    "tightest_flow",
    "validate_metadata",
]
