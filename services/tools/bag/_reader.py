"""Reading a framegate MCAP recording back: its buffers, then their elements in time order."""

from __future__ import annotations

import os
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import IO, Any

from mcap.reader import SeekingReader
from mcap.summary import Summary

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
from ._scan import READ_ERRORS, Integrity, reason, scan


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


class _RecoveredReader(SeekingReader):
    """The library's seeking reader over a summary rebuilt from the chunks that were whole."""

    def __init__(self, stream: IO[bytes], summary: Summary, size: int) -> None:
        super().__init__(stream, validate_crcs=True, record_size_limit=size)
        self._recovered = summary

    def get_summary(self) -> Summary:
        return self._recovered


class Bag:
    """An open recording. Use as a context manager (``open_bag``).

    Opening reads the whole file once to check it (``_scan``): ``integrity`` says whether it
    is complete or how much of a cut-short or damaged file was recovered; ``buffers`` and
    ``elements`` then give only what was recovered.
    """

    def __init__(self, path: Path) -> None:
        self.path = path
        try:
            self._stream: IO[bytes] = open(path, "rb")  # noqa: SIM115 - closed in close()
            self.size_bytes = os.fstat(self._stream.fileno()).st_size
        except OSError as exc:
            raise BagError(f"cannot read {path}: {exc.strerror}") from exc
        try:
            found = scan(self._stream, self.size_bytes, str(path))
            self.integrity: Integrity = found.integrity
            self.header = found.header
            self.metadata = found.metadata
            self.compressions = found.compressions
            self.chunks = found.chunks
            self.summary = found.summary
            self._stream.seek(0)
            if found.integrity.complete:
                self._reader: SeekingReader = SeekingReader(
                    self._stream, validate_crcs=True, record_size_limit=self.size_bytes
                )
            else:
                self._reader = _RecoveredReader(self._stream, found.summary, self.size_bytes)
            self.buffers = self._find_buffers()
        except BagError:
            self._stream.close()
            raise
        except READ_ERRORS as exc:
            self._stream.close()
            raise BagError(f"{path} is damaged: {reason(exc)}") from exc

    def _find_buffers(self) -> tuple[RecordedBuffer, ...]:
        summary = self.summary
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
        self,
        buffers: list[RecordedBuffer] | None = None,
        on_bad: Callable[[RecordedBuffer, BagError], object] | None = None,
    ) -> Iterator[tuple[RecordedBuffer, DataObject]]:
        """Elements of ``buffers`` (default: all) in timestamp order across buffers. A
        message that is no framegate element raises BagError, or with ``on_bad`` is passed
        to it and skipped (the rest is read)."""
        chosen = {b.channel_id: b for b in (buffers if buffers is not None else self.buffers)}
        topics = [b.topic for b in chosen.values()]
        try:
            for _schema, channel, message in self._reader.iter_messages(
                topics=topics, log_time_order=True
            ):
                recorded = chosen.get(channel.id)
                if recorded is None:
                    continue
                try:
                    element = decode_element(message.data, f"{self.path} {channel.topic}")
                except BagError as exc:
                    if on_bad is None:
                        raise
                    on_bad(recorded, exc)
                    continue
                yield recorded, element
        except READ_ERRORS as exc:
            raise BagError(f"{self.path} is damaged: {reason(exc)}") from exc

    def close(self) -> None:
        self._stream.close()

    def __enter__(self) -> Bag:
        return self

    def __exit__(self, *_exc: Any) -> None:
        self.close()


def open_bag(path: Path) -> Bag:
    """Open a recording made by ``framegate record``; BagError says what is wrong."""
    return Bag(path)
