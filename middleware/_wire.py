"""Key expressions and message encodings: the protocol a client in any language speaks.

Keys (``ns`` is the namespace, ``framegate`` by default):

    ns/<service>/<buffer>                         queryable: the elements
    ns/@info/<service>                            queryable: JSON description of the service
    ns/@svc/<service>                             liveliness token of a live service
    ns/@sub/<service>/<buffer>/<id>/<mode>/<N>/<push>   liveliness token of a subscription
    ns/@notify/<service>/<buffer>/<id>            notifications to one subscription
    ns/@ack/<service>/<buffer>/<id>               the subscription's "taken" acknowledgements

``@`` chunks are verbatim in Zenoh: wildcards never match them, so ``ns/**`` sees data only.
Element replies carry the raw payload; the attachment is msgpack ``{"t": int, "m": str}``
(timestamp_ns, metadata XML). A notification's Zenoh payload is the element's payload when it
is pushed (else empty) and its attachment a msgpack header; acks are msgpack maps.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import msgpack

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
    ) -> str:
        return (
            f"{self.namespace}/@sub/{service}/{buffer}/{sub_id}/{mode.value}/{queue_size}"
            f"/{push_max_bytes}"
        )

    def subscription_tokens(self, service: str, buffer: str) -> str:
        return f"{self.namespace}/@sub/{service}/{buffer}/*/*/*/*"

    def notify(self, service: str, buffer: str, sub_id: str) -> str:
        return f"{self.namespace}/@notify/{service}/{buffer}/{sub_id}"

    def ack(self, service: str, buffer: str, sub_id: str) -> str:
        return f"{self.namespace}/@ack/{service}/{buffer}/{sub_id}"

    def acks(self, service: str, buffer: str) -> str:
        return f"{self.namespace}/@ack/{service}/{buffer}/*"


# Largest queue size a token may ask for: bounds the subscriber's and producer's tables.
MAX_QUEUE_SIZE = 1 << 20


def parse_subscription_token(key: str) -> tuple[str, SubscriptionMode, int, int]:
    """(id, mode, queue size, push limit) from a subscription token; ValueError if malformed.

    The push limit is the largest payload the subscriber wants pushed with its notifications
    (-1: the producer's default).
    """
    parts = key.split("/")
    if len(parts) < 8 or parts[-7] != "@sub":
        raise ValueError(f"not a subscription token: {key!r}")
    sub_id, mode, size, push = parts[-4], parts[-3], parts[-2], parts[-1]
    if not sub_id:
        raise ValueError("empty subscription id")
    if not (size.lstrip("-").isdigit() and push.lstrip("-").isdigit()):
        raise ValueError(f"queue size {size!r} and push limit {push!r} must be integers")
    queue_size, push_max_bytes = int(size), int(push)
    if queue_size > MAX_QUEUE_SIZE:
        raise ValueError(f"queue size {queue_size} > {MAX_QUEUE_SIZE}")
    if queue_size < 1:
        raise ValueError(f"queue size {queue_size} < 1")
    if push_max_bytes < -1:
        raise ValueError(f"push limit {push_max_bytes} < -1")
    return sub_id, SubscriptionMode(mode), queue_size, push_max_bytes


def encode_element_attachment(element: DataObject) -> bytes:
    return bytes(msgpack.packb({"t": element.timestamp_ns, "m": element.metadata.decode("utf-8")}))


def decode_element(payload: bytes, attachment: bytes | None) -> DataObject:
    """Rebuild a DataObject from a reply; QueryError if the attachment is not ours."""
    if attachment is None:
        raise QueryError("reply has no attachment: not a framegate element")
    try:
        head = msgpack.unpackb(attachment)
        return DataObject(int(head["t"]), payload, str(head["m"]).encode("utf-8"))
    except (ValueError, KeyError, TypeError, msgpack.UnpackException) as exc:
        raise QueryError(f"reply attachment is not a framegate element header: {exc}") from exc


def encode_notification_header(
    epoch: str,
    seq: int,
    timestamp_ns: int,
    metadata: bytes | None,
    *,
    pushed: bool,
    acked: int | None = None,
    descriptor: str | None = None,
) -> bytes:
    """The attachment of a notification: {"e": registration epoch, "s": seq (1, 2, ... per
    registration), "t": timestamp_ns, "m": metadata (bytes, optional), "p": true when the
    Zenoh payload is the element's payload (pushed), false when it is empty, "a": the
    producer's ack count when sent (the window base), "k": the registration's
    ``mode/N/push`` (both optional for older peers)}."""
    body: dict[str, Any] = {"e": epoch, "s": seq, "t": timestamp_ns, "p": pushed}
    if metadata is not None:
        body["m"] = metadata
    if acked is not None:
        body["a"] = acked
    if descriptor is not None:
        body["k"] = descriptor
    return bytes(msgpack.packb(body, use_bin_type=True))


def encode_batch_header(
    epoch: str,
    seq: int,
    timestamps_ns: list[int],
    metadata: list[bytes | None],
    payload_sizes: list[int] | None,
    *,
    acked: int | None = None,
    descriptor: str | None = None,
) -> bytes:
    """The attachment of a batch notification, n elements of seqs ``seq .. seq + n - 1``:
    like a single one, but with {"n": n, "t": [timestamp_ns, ...], "m": [metadata or nil,
    ...]} and, when pushed ("p" true), "l": [payload size, ...]: the Zenoh payload is then
    the elements' payloads one after another."""
    body: dict[str, Any] = {
        "e": epoch,
        "s": seq,
        "n": len(timestamps_ns),
        "t": timestamps_ns,
        "m": metadata,
        "p": payload_sizes is not None,
    }
    if payload_sizes is not None:
        body["l"] = payload_sizes
    if acked is not None:
        body["a"] = acked
    if descriptor is not None:
        body["k"] = descriptor
    return bytes(msgpack.packb(body, use_bin_type=True))


def _is_int(value: object) -> bool:
    return isinstance(value, int) and not isinstance(value, bool)


def _check_batch(body: dict[str, Any]) -> None:
    n, times, metas = body["n"], body.get("t"), body.get("m")
    if not _is_int(n) or n < 1:
        raise ValueError("batch notification count must be an int >= 1")
    if not isinstance(times, list) or len(times) != n or not all(map(_is_int, times)):
        raise ValueError("batch notification needs n integer timestamps")
    if not isinstance(metas, list) or len(metas) != n:
        raise ValueError("batch notification needs n metadata entries")
    if not all(m is None or isinstance(m, bytes) for m in metas):
        raise ValueError("batch notification metadata must be bytes or nil")
    if not isinstance(body.get("p"), bool):
        raise ValueError("notification lacks push flag")
    sizes = body.get("l")
    if body["p"] and (
        not isinstance(sizes, list)
        or len(sizes) != n
        or not all(_is_int(x) and x >= 0 for x in sizes)
    ):
        raise ValueError("pushed batch notification needs n payload sizes")


def decode_notification_header(raw: bytes) -> dict[str, Any]:
    """Decode and type-check a notification header (single or batch, see
    ``encode_batch_header``); ValueError if it is garbage."""
    body = msgpack.unpackb(raw, raw=False)
    if not isinstance(body, dict):
        raise ValueError("notification header is not a map")
    if "n" in body:
        if not isinstance(body.get("e"), str) or not _is_int(body.get("s")):
            raise ValueError("notification lacks epoch or seq")
        _check_batch(body)
        if "a" in body and not _is_int(body["a"]):
            raise ValueError("notification window base is not an int")
        if "k" in body and not isinstance(body["k"], str):
            raise ValueError("notification registration descriptor is not a str")
        return body
    if not isinstance(body.get("e"), str) or not isinstance(body.get("s"), int):
        raise ValueError("notification lacks epoch or seq")
    if not isinstance(body.get("t"), int) or not isinstance(body.get("p"), bool):
        raise ValueError("notification lacks timestamp or push flag")
    if "m" in body and not isinstance(body["m"], bytes):
        raise ValueError("notification metadata is not bytes")
    if "a" in body and (not isinstance(body["a"], int) or isinstance(body["a"], bool)):
        raise ValueError("notification window base is not an int")
    if "k" in body and not isinstance(body["k"], str):
        raise ValueError("notification registration descriptor is not a str")
    if isinstance(body["s"], bool) or isinstance(body["t"], bool):
        raise ValueError("notification seq and timestamp must be ints")
    return body


def encode_ack(epoch: str, seq: int) -> bytes:
    """Ack: {"e": producer epoch, "s": highest seq taken} (cumulative, so a lost ack heals)."""
    return bytes(msgpack.packb({"e": epoch, "s": seq}))


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
