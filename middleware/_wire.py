"""Key expressions and message encodings: the protocol a client in any language speaks.

Keys (``ns`` is the namespace, ``framegate`` by default):

    ns/<service>/<buffer>                         queryable: the elements
    ns/@info/<service>                            queryable: JSON description of the service
    ns/@svc/<service>                             liveliness token of a live service
    ns/@sub/<service>/<buffer>/<id>/<mode>/<N>/<push>/<node>~<host>
                                                  liveliness token of a subscription
    ns/@notify/<service>/<buffer>/<id>            notifications to one subscription
    ns/@ack/<service>/<buffer>/<id>               the subscription's "taken" acknowledgements

``@`` chunks are verbatim in Zenoh: wildcards never match them, so ``ns/**`` sees data only.
Element replies carry the raw payload; the attachment is msgpack ``{"t": int, "m": str}``
(timestamp_ns, metadata XML). A notification's Zenoh payload is the element's payload when it
is pushed (else empty) and its attachment a msgpack array (the header, decoded once per
notification on the subscriber's hot path); acks are msgpack maps.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from typing import NamedTuple

import msgpack

from ._decode import is_text
from ._errors import QueryError
from ._records import DataObject, SubscriptionMode

# Error replies start with one of these codes, then ": " and the message.
ERR_BAD_QUERY = "bad-query"
ERR_NOT_FOUND = "not-found"


@dataclass(frozen=True, slots=True)
class Keys:
    """Builds the key expressions of one namespace."""

    namespace: str

    def data(self, service: str, buffer: str) -> str:
        return f"{self.namespace}/{service}/{buffer}"

    def service_data(self, service: str) -> str:
        return f"{self.namespace}/{service}/*"

    def info(self, service: str) -> str:
        return f"{self.namespace}/@info/{service}"

    def service_token(self, service: str) -> str:
        return f"{self.namespace}/@svc/{service}"

    def subscription_token(
        self,
        service: str,
        buffer: str,
        sub_id: str,
        mode: SubscriptionMode,
        queue_size: int,
        push_max_bytes: int,
        holder: str,
    ) -> str:
        descriptor = descriptor_of(mode, queue_size, push_max_bytes)
        return f"{self.namespace}/@sub/{service}/{buffer}/{sub_id}/{descriptor}/{holder}"

    def subscription_tokens(self, service: str, buffer: str) -> str:
        return f"{self.namespace}/@sub/{service}/{buffer}/**"

    def notify(self, service: str, buffer: str, sub_id: str) -> str:
        return f"{self.namespace}/@notify/{service}/{buffer}/{sub_id}"

    def ack(self, service: str, buffer: str, sub_id: str) -> str:
        return f"{self.namespace}/@ack/{service}/{buffer}/{sub_id}"

    def acks(self, service: str, buffer: str) -> str:
        return f"{self.namespace}/@ack/{service}/{buffer}/*"


# Largest queue size a token may ask for: bounds the subscriber's and producer's tables.
# (A producer holds flow-control queues within a smaller budget, see _protocol_producer.)
MAX_QUEUE_SIZE = 1 << 20


def descriptor_of(mode: SubscriptionMode, queue_size: int, push_max_bytes: int) -> str:
    """A registration's ``mode/N/push``, as its token says and its notifications carry it."""
    return f"{mode.value}/{queue_size}/{push_max_bytes}"


def holder_chunk(node: str | None, host: str) -> str:
    """The token's last chunk: ``<node>~<host>`` (node empty for an anonymous client)."""
    clean = "".join(c if c.isalnum() or c in "-._" else "_" for c in host) or "unknown"
    return f"{node or ''}~{clean}"


def parse_subscription_token(
    key: str,
) -> tuple[str, SubscriptionMode, int, int, str | None, str | None]:
    """(id, mode, queue size, push limit, node, host) from a subscription token; ValueError
    if malformed. Node and host are None for a token without the holder chunk.

    The push limit is the largest payload the subscriber wants pushed with its notifications
    (-1: the producer's default).
    """
    parts = key.split("/")
    node: str | None = None
    host: str | None = None
    if len(parts) >= 9 and parts[-8] == "@sub":
        node, sep, host = parts[-1].partition("~")
        if not sep:
            raise ValueError(f"holder chunk {parts[-1]!r} is not <node>~<host>")
        parts = parts[:-1]
    if len(parts) < 8 or parts[-7] != "@sub":
        raise ValueError(f"not a subscription token: {key!r}")
    sub_id, mode, size, push = parts[-4], parts[-3], parts[-2], parts[-1]
    if not sub_id:
        raise ValueError("empty subscription id")
    # The id and holder reach every client in ``@info``, whose decoder refuses the whole
    # description for one unprintable or overlong name: refused here, one token at a time.
    if not all(is_text(text) for text in (sub_id, node or "", host or "")):
        raise ValueError("subscription id or holder is overlong or holds unprintable characters")
    if not (size.lstrip("-").isdigit() and push.lstrip("-").isdigit()):
        raise ValueError(f"queue size {size!r} and push limit {push!r} must be integers")
    queue_size, push_max_bytes = int(size), int(push)
    if queue_size > MAX_QUEUE_SIZE:
        raise ValueError(f"queue size {queue_size} > {MAX_QUEUE_SIZE}")
    if queue_size < 1:
        raise ValueError(f"queue size {queue_size} < 1")
    if push_max_bytes < -1:
        raise ValueError(f"push limit {push_max_bytes} < -1")
    return sub_id, SubscriptionMode(mode), queue_size, push_max_bytes, node, host


def encode_element_attachment(element: DataObject) -> bytes:
    return bytes(msgpack.packb({"t": element.timestamp_ns, "m": element.metadata.decode("utf-8")}))


def decode_element(payload: bytes, attachment: bytes | None) -> DataObject:
    """Rebuild a DataObject from a reply; QueryError if the attachment is not ours."""
    if attachment is None:
        raise QueryError("reply has no attachment: not a framegate element")
    try:
        head = msgpack.unpackb(attachment)
        stamp, metadata = head["t"], head["m"]
    except (ValueError, KeyError, TypeError, msgpack.UnpackException) as exc:
        raise QueryError(f"reply attachment is not a framegate element header: {exc}") from exc
    # A stamp is an int nanosecond count as every producer stores it; anything else (a
    # float, a bool, one outside 0 .. 2^63 - 1) is no element of ours.
    if type(stamp) is not int or not 0 <= stamp < 2**63 or type(metadata) is not str:
        raise QueryError(
            "reply attachment is not a framegate element header: timestamp "
            f"{type(stamp).__name__} {str(stamp)[:24]}, metadata {type(metadata).__name__}"
        )
    try:
        return DataObject(stamp, payload, metadata.encode("utf-8"))
    except UnicodeEncodeError as exc:
        raise QueryError(f"reply metadata is not UTF-8 text: {exc.reason}") from exc


class Header(NamedTuple):
    """A decoded single-element notification header (see ``encode_notification_header``)."""

    epoch: str
    seq: int
    timestamp_ns: int
    metadata: bytes | None
    pushed: bool
    acked: int | None
    descriptor: str | None
    base: int | None


class BatchHeader(NamedTuple):
    """A decoded batch notification header (see ``encode_batch_header``)."""

    epoch: str
    seq: int
    timestamps_ns: tuple[int, ...]
    metadata: tuple[bytes | None, ...]
    payload_sizes: tuple[int, ...] | None
    acked: int | None
    descriptor: str | None
    base: int | None


def encode_notification_header(
    epoch: str,
    seq: int,
    timestamp_ns: int,
    metadata: bytes | None,
    *,
    pushed: bool,
    acked: int | None = None,
    descriptor: str | None = None,
    base: int | None = None,
) -> bytes:
    """The attachment of a notification, a msgpack array of 8: ``[epoch (str), seq (int, 1,
    2, ... per registration), timestamp_ns (int), metadata (bin or nil), pushed (bool: the
    Zenoh payload is the element's payload; else it is empty), acked (the producer's ack
    count when sent, the window base; int or nil), descriptor (the registration's
    ``mode/N/push``; str or nil), base (int >= 0 or nil: how many elements the producer
    had stored when it made this registration, so that seq s is its element number
    base + s)]``. An array of 7 (no base) is still read.

    An array, not a map: the subscriber decodes it in a third of the time, without a dict.
    """
    return bytes(
        msgpack.packb(
            (epoch, seq, timestamp_ns, metadata, pushed, acked, descriptor, base),
            use_bin_type=True,
        )
    )


def encode_batch_header(
    epoch: str,
    seq: int,
    timestamps_ns: Sequence[int],
    metadata: Sequence[bytes | None],
    payload_sizes: Sequence[int] | None,
    *,
    acked: int | None = None,
    descriptor: str | None = None,
    base: int | None = None,
) -> bytes:
    """The attachment of a batch notification, n elements of seqs ``seq .. seq + n - 1``: like
    a single one, an array of 8, but ``[epoch, seq, [timestamp_ns] * n, [metadata or nil] *
    n, [payload size] * n or nil, acked, descriptor, base]``. The third item being an array is what
    makes it a batch. With payload sizes (pushed) the Zenoh payload is the elements'
    payloads one after another; without (nil) it is empty."""
    return bytes(
        msgpack.packb(
            (epoch, seq, timestamps_ns, metadata, payload_sizes, acked, descriptor, base),
            use_bin_type=True,
        )
    )


_INT = {int}
_BIN_OR_NIL = {bytes, type(None)}


def _check_batch(head: BatchHeader) -> BatchHeader:
    # The types of a batch's items are checked as sets (``type(x) is int`` refuses bools,
    # and so does this): one pass in C per list instead of a Python loop per element.
    n = len(head.timestamps_ns)
    if n < 1 or set(map(type, head.timestamps_ns)) != _INT:
        raise ValueError("batch notification needs integer timestamps, at least one")
    metas = head.metadata
    if type(metas) is not tuple or len(metas) != n:
        raise ValueError("batch notification needs n metadata entries")
    if not set(map(type, metas)) <= _BIN_OR_NIL:
        raise ValueError("batch notification metadata must be bin or nil")
    sizes = head.payload_sizes
    if sizes is not None and (
        type(sizes) is not tuple
        or len(sizes) != n
        or set(map(type, sizes)) != _INT
        or min(sizes) < 0
    ):
        raise ValueError("pushed batch notification needs n payload sizes >= 0")
    return head


# The largest seq (and base) a notification may carry: an int64, as msgpack packs it.
MAX_SEQ = 2**63 - 1


def decode_notification_header(raw: bytes) -> Header | BatchHeader | Control:
    """Decode and type-check a notification header (single or batch, see
    ``encode_notification_header`` and ``encode_batch_header``); ValueError if it is garbage.

    Only the types are checked here (``type(x) is int`` also refuses bools); what the values
    mean for the protocol (epochs, seqs, descriptors) is the ledger's to judge.
    """
    body = msgpack.unpackb(raw, use_list=False)
    if type(body) is tuple and len(body) in (3, 4, 5):
        kind, descriptor, text, base, since = (*body, None, None)[:5]
        if kind not in CONTROL_KINDS or type(descriptor) is not str or type(text) is not str:
            raise ValueError("control message is not [kind, descriptor, text]")
        for number in (base, since):
            if number is not None and (type(number) is not int or not 0 <= number <= MAX_SEQ):
                raise ValueError("control message base or since is not an int in 0..2^63-1")
        return Control(kind, descriptor, text, base, since)
    if type(body) is not tuple or len(body) not in (7, 8):
        raise ValueError("notification header is not an array of 8 (or 7)")
    if len(body) == 7:
        body = (*body, None)
    epoch, seq, stamp, metadata, pushed, acked, descriptor, base = body
    if base is not None and (type(base) is not int or not 0 <= base <= MAX_SEQ):
        raise ValueError("notification base is not an int in 0..2^63-1")
    if type(epoch) is not str or type(seq) is not int:
        raise ValueError("notification lacks epoch or seq")
    # Seqs and the acks that repeat them stay int64 (an ack of 2^64 could not be encoded);
    # seq < 1 is the ledger's to count.
    if seq + (len(stamp) - 1 if type(stamp) is tuple else 0) > MAX_SEQ:
        raise ValueError("notification seq beyond 2^63-1")
    if acked is not None and type(acked) is not int:
        raise ValueError("notification window base is not an int")
    if descriptor is not None and type(descriptor) is not str:
        raise ValueError("notification registration descriptor is not a str")
    if type(stamp) is int:
        if type(pushed) is not bool:
            raise ValueError("notification lacks push flag")
        if metadata is not None and type(metadata) is not bytes:
            raise ValueError("notification metadata is not bin")
        return tuple.__new__(Header, body)
    if type(stamp) is tuple:
        return _check_batch(tuple.__new__(BatchHeader, body))
    raise ValueError("notification timestamp is neither an int nor an array")


# Control messages travel on a subscription's notification key with an empty payload; their
# attachment is a msgpack array: ["hello", descriptor, epoch, base] when the producer
# registered the subscription (base: the elements it had stored then, as its notifications
# carry it; an array of 3 without it is still read), ["refused", descriptor, reason] when
# it refused it. The producer names its Zenoh session as the sample's source (a subscriber
# trusts a refusal only from the session that answers as the service).
CONTROL_KINDS = ("hello", "refused")


class Control(NamedTuple):
    kind: str
    descriptor: str
    text: str
    base: int | None = None
    # A greeting of a key registered before: how far its last registration was acked.
    since: int | None = None


def encode_control(
    kind: str, descriptor: str, text: str, base: int | None = None, since: int | None = None
) -> bytes:
    body: tuple[object, ...] = (kind, descriptor, text)
    if base is not None:
        body = (*body, base) if since is None else (*body, base, since)
    return bytes(msgpack.packb(body))


def encode_ack(epoch: str, seq: int) -> bytes:
    """Ack: {"e": producer epoch, "s": highest seq taken} (cumulative, so a lost ack heals)."""
    return bytes(msgpack.packb({"e": epoch, "s": seq}))


# Every ack starts with this byte: a msgpack map of two (``encode_ack``).
ACK_FIRST_BYTE = b"\x82"
# Ack keys whose last ack an ``AckFilter`` remembers (a flood of keys clears it: it is only
# a shortcut, the ledger decides).
ACK_KEYS_REMEMBERED = 1024


class AckFilter:
    """What an ack flood is made of, recognised before an ack is decoded: a payload whose
    first byte is not an ack's (garbage), and the same payload on the same key as the last
    one remembered for it within ``repeat_window_ns`` (acks are cumulative: a repeat changes
    nothing but making resends due, at most that often). Used on Zenoh's thread before an
    ack is buffered (``AckInbox``), and by the producer's protocol, which the model checker
    drives without an inbox."""

    def __init__(self, repeat_window_ns: int) -> None:
        self._window_ns = repeat_window_ns
        self._last: dict[str, tuple[bytes, int]] = {}

    @staticmethod
    def malformed(payload: bytes) -> bool:
        """Garbage: not even an ack's first byte (looked at before the key is read)."""
        return payload[:1] != ACK_FIRST_BYTE

    def repeat(self, key: str, payload: bytes, now_ns: int) -> bool:
        """The last ack remembered for ``key``, again within the window."""
        last = self._last.get(key)
        return last is not None and last[0] == payload and now_ns - last[1] < self._window_ns

    def remember(self, key: str, payload: bytes, now_ns: int) -> None:
        """``payload`` is now the last ack of ``key``."""
        if len(self._last) >= ACK_KEYS_REMEMBERED:
            self._last.clear()
        self._last[key] = (payload, now_ns)


def decode_ack(raw: bytes) -> tuple[str, int]:
    body = msgpack.unpackb(raw, raw=False)
    if not isinstance(body, dict):
        raise ValueError("ack is not a map")
    epoch, seq = body.get("e"), body.get("s")
    if not isinstance(epoch, str) or not isinstance(seq, int) or isinstance(seq, bool):
        raise ValueError("ack lacks epoch or integer seq")
    return epoch, seq


def error_text(code: str, message: str) -> str:
    return f"{code}: {message}"
