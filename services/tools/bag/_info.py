"""``framegate info FILE.mcap``: what a recording holds, like ``ros2 bag info``."""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from ._format import BagError
from ._scan import scan


@dataclass(frozen=True, slots=True)
class ChannelInfo:
    topic: str
    schema: str
    kind: str | None  # the framegate metadata kind of an element channel
    messages: int


@dataclass(frozen=True, slots=True)
class BufferRecord:
    """What the recorder said of one buffer: kept, fetched late, and the two losses."""

    name: str
    recorded: int
    backfilled: int
    evicted: int  # gone from the buffer before it could be fetched
    dropped: int  # fetched, but the recorder's write queue was full

    def json(self) -> dict[str, Any]:
        return {
            "name": self.name,
            "recorded": self.recorded,
            "backfilled": self.backfilled,
            "evicted": self.evicted,
            "dropped": self.dropped,
        }


# A recording's own account is small; a larger one is not ours (a file can hold anything).
_MAX_ACCOUNT_BYTES = 1 << 20


def recorder_account(metadata: list[Any]) -> tuple[BufferRecord, ...]:
    """The per-buffer account ``framegate record`` left in the file's metadata (empty if
    none, or if it cannot be read: the data itself is what counts)."""
    text = _recording_fields(metadata).get("buffers")
    if text is None or len(text) > _MAX_ACCOUNT_BYTES:
        return ()
    try:
        rows = json.loads(text)
        return tuple(
            BufferRecord(
                name=str(row["name"]),
                recorded=int(row["recorded"]),
                backfilled=int(row.get("backfilled", 0)),
                # Files of before the split counted both losses as "lost".
                evicted=int(row.get("evicted", row.get("lost", 0))),
                dropped=int(row.get("dropped", 0)),
            )
            for row in rows
        )
    except (ValueError, TypeError, KeyError, AttributeError, RecursionError):
        return ()


def recording_started_ns(metadata: list[Any]) -> int | None:
    """The instant ``framegate record`` started (its ``started_ns``), or None (another
    writer's file, or no account). Elements stamped before it are the buffers' newest at
    the start (a camera description put once, long before)."""
    return _ns(_recording_fields(metadata).get("started_ns"))


def recording_window(metadata: list[Any]) -> tuple[int, int | None, str] | None:
    """When ``framegate record`` ran (``started_ns``, ``stopped_ns``) and on which host, or
    None (another writer's file). The stop is None when the recorder was killed before its
    end record: the start record, written first, still gives the start and the host."""
    fields = _recording_fields(metadata)
    start = _ns(fields.get("started_ns"))
    if start is None:
        return None
    return start, _ns(fields.get("stopped_ns")), fields.get("host", "")


# ``framegate record`` writes START_RECORD when it starts (host, start) and END_RECORD when
# it stops (the same again, the stop and the buffers' account); a recorder killed leaves
# only the first.
START_RECORD = "framegate.recording.start"
END_RECORD = "framegate.recording"


def _recording_fields(metadata: list[Any]) -> dict[str, str]:
    """The fields of ``framegate record``'s metadata records, the end record's overriding
    the start record's. Values that are not text are left out."""
    fields: dict[str, str] = {}
    for name in (START_RECORD, END_RECORD):
        for record in metadata:
            data = getattr(record, "metadata", None)
            if getattr(record, "name", None) == name and isinstance(data, dict):
                fields.update((k, v) for k, v in data.items() if isinstance(v, str))
    return fields


def _ns(text: str | None) -> int | None:
    """A recorded instant in ns, or None if absent or not a plain number."""
    if text is not None and text.isdigit() and len(text) < 25:
        return int(text)
    return None


@dataclass(frozen=True, slots=True)
class RecordingInfo:
    path: str
    size_bytes: int
    status: str  # complete | recovered
    integrity: str  # one line: what was read, what was lost
    messages: int
    start_ns: int | None
    end_ns: int | None
    chunks: int
    compressions: tuple[str, ...]
    channels: tuple[ChannelInfo, ...]
    buffers: tuple[BufferRecord, ...] = ()
    # When the recorder ran (its own clock) and where: the messages' span may start long
    # before, as a buffer's newest element at the start is recorded however old it is.
    # The stop is None for a recorder killed before it wrote its end record.
    recorded: tuple[int, int | None, str] | None = None

    @property
    def duration_s(self) -> float:
        if self.start_ns is None or self.end_ns is None:
            return 0.0
        return (self.end_ns - self.start_ns) / 1e9

    def json(self) -> dict[str, Any]:
        return {
            "path": self.path,
            "size_bytes": self.size_bytes,
            "status": self.status,
            "integrity": self.integrity,
            "messages": self.messages,
            "start_ns": self.start_ns,
            "end_ns": self.end_ns,
            "duration_s": self.duration_s,
            "chunks": self.chunks,
            "compressions": list(self.compressions),
            "channels": [
                {"topic": c.topic, "schema": c.schema, "kind": c.kind, "messages": c.messages}
                for c in self.channels
            ],
            "recorder": [b.json() for b in self.buffers],
            "recorded_start_ns": self.recorded[0] if self.recorded else None,
            "recorded_stop_ns": self.recorded[1] if self.recorded else None,
            "recorded_host": self.recorded[2] if self.recorded else None,
        }


def recording_info(path: Path) -> RecordingInfo:
    """Scan ``path`` (every checksum) and describe it; BagError if it holds nothing readable."""
    try:
        size = path.stat().st_size
        with path.open("rb") as stream:
            found = scan(stream, size, str(path))
    except OSError as exc:
        raise BagError(f"cannot read {path}: {exc.strerror or exc}") from exc
    summary, integrity = found.summary, found.integrity
    counts = summary.statistics.channel_message_counts if summary.statistics else {}
    channels = tuple(
        sorted(
            (
                ChannelInfo(
                    topic=channel.topic,
                    schema=summary.schemas[channel.schema_id].name
                    if channel.schema_id in summary.schemas
                    else "",
                    kind=channel.metadata.get("framegate.kind"),
                    messages=int(counts.get(channel_id, 0)),
                )
                for channel_id, channel in summary.channels.items()
            ),
            key=lambda c: c.topic,
        )
    )
    end = _rfc3339(integrity.end_ns) if integrity.end_ns is not None else "its start"
    return RecordingInfo(
        path=str(path),
        size_bytes=size,
        status=integrity.status,
        integrity=integrity.describe(end),
        messages=integrity.messages,
        start_ns=integrity.start_ns,
        end_ns=integrity.end_ns,
        chunks=found.chunks,
        compressions=tuple(sorted(found.compressions)),
        channels=channels,
        buffers=recorder_account(found.metadata),
        recorded=recording_window(found.metadata),
    )


def _rfc3339(timestamp_ns: int) -> str:
    from datetime import UTC, datetime

    stamp = datetime.fromtimestamp(timestamp_ns / 1e9, UTC).isoformat(timespec="microseconds")
    return stamp.replace("+00:00", "Z")
