"""Reading a framegate MCAP recording back: its buffers, then their elements in time order."""

from __future__ import annotations

import struct
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import IO, Any

from mcap.exceptions import McapError
from mcap.reader import make_reader

from middleware import DataObject, Retention

from ._format import (
    ELEMENT_SCHEMA_NAME,
    FORMAT_VERSION,
    KEY_BUFFER,
    KEY_FORMAT,
    KEY_KIND,
    KEY_RETENTION,
    KEY_SERVICE,
    BagError,
    decode_element,
    retention_from_json,
)

_MAGIC = b"\x89MCAP0\r\n"


@dataclass(frozen=True, slots=True)
class RecordedBuffer:
    """One buffer as a recording holds it."""

    service: str
    buffer: str
    kind: str
    retention: Retention
    topic: str
    channel_id: int
    count: int

    @property
    def name(self) -> str:
        return f"{self.service}/{self.buffer}"


class Bag:
    """An open recording. Use as a context manager (``open_bag``)."""

    def __init__(self, path: Path) -> None:
        self.path = path
        try:
            self._stream: IO[bytes] = open(path, "rb")  # noqa: SIM115 - closed in close()
        except OSError as exc:
            raise BagError(f"cannot read {path}: {exc.strerror}") from exc
        try:
            if self._stream.read(len(_MAGIC)) != _MAGIC:
                raise BagError(f"{path} is not an MCAP file; record one with `framegate record`")
            self._stream.seek(0)
            self._reader = make_reader(self._stream)
            self.buffers = self._find_buffers()
        except BagError:
            self._stream.close()
            raise
        except (McapError, ValueError, struct.error, EOFError) as exc:
            self._stream.close()
            raise BagError(
                f"{path} is not a complete MCAP file ({exc}); "
                "was the recording killed before it could finish?"
            ) from exc

    def _find_buffers(self) -> tuple[RecordedBuffer, ...]:
        summary = self._reader.get_summary()
        if summary is None:
            raise BagError(f"{self.path} has no summary section; was the recording interrupted?")
        stats = summary.statistics
        counts: dict[int, int] = dict(stats.channel_message_counts) if stats else {}
        found = []
        for channel in summary.channels.values():
            schema = summary.schemas.get(channel.schema_id)
            if schema is None or schema.name != ELEMENT_SCHEMA_NAME:
                continue
            meta = channel.metadata
            where = f"{self.path} channel {channel.topic}"
            if meta.get(KEY_FORMAT) != FORMAT_VERSION:
                raise BagError(
                    f"{where}: framegate format {meta.get(KEY_FORMAT)!r} is not supported "
                    f"(this version reads {FORMAT_VERSION!r})"
                )
            try:
                service, buffer, kind = meta[KEY_SERVICE], meta[KEY_BUFFER], meta[KEY_KIND]
            except KeyError as exc:
                raise BagError(f"{where}: channel metadata lacks {exc.args[0]}") from exc
            found.append(
                RecordedBuffer(
                    service=service,
                    buffer=buffer,
                    kind=kind,
                    retention=retention_from_json(meta.get(KEY_RETENTION, "{}"), where),
                    topic=channel.topic,
                    channel_id=channel.id,
                    count=counts.get(channel.id, 0),
                )
            )
        if not found:
            raise BagError(
                f"{self.path} holds no framegate buffers (no {ELEMENT_SCHEMA_NAME} channels); "
                "was it written by `framegate record`?"
            )
        return tuple(sorted(found, key=lambda b: b.name))

    def elements(
        self, buffers: list[RecordedBuffer] | None = None
    ) -> Iterator[tuple[RecordedBuffer, DataObject]]:
        """Elements of ``buffers`` (default: all) in timestamp order across buffers."""
        chosen = {b.channel_id: b for b in (buffers if buffers is not None else self.buffers)}
        topics = [b.topic for b in chosen.values()]
        try:
            for _schema, channel, message in self._reader.iter_messages(
                topics=topics, log_time_order=True
            ):
                recorded = chosen.get(channel.id)
                if recorded is None:
                    continue
                yield recorded, decode_element(message.data, f"{self.path} {channel.topic}")
        except (McapError, ValueError, struct.error, EOFError) as exc:
            raise BagError(f"{self.path} is damaged: {exc}") from exc

    def close(self) -> None:
        self._stream.close()

    def __enter__(self) -> Bag:
        return self

    def __exit__(self, *_exc: Any) -> None:
        self.close()


def open_bag(path: Path) -> Bag:
    """Open a recording made by ``framegate record``; BagError says what is wrong."""
    return Bag(path)
