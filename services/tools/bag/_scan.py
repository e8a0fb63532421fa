"""Checking a recording end to end, and recovering what a cut-short or damaged one holds.

A recording is written as small chunks, each with a CRC of its contents, followed at close
by the data section's CRC, a summary (channels, statistics, chunk index) with its own CRC
and a footer. A recording that was killed, ran out of disk or lost power has no summary:
its last chunk may be torn, but every chunk before it is whole.

The rule ``play`` and ``info`` follow:

* **complete**: every record parses, the file ends with its footer and closing magic, and
  every checksum the writer stored matches. It is read through its summary.
* **recovered**: otherwise the file is read up to the first byte that is missing or
  damaged. Every chunk before that byte whose own CRC matches is kept; everything from that
  byte on is lost. ``Integrity.describe`` says how many messages were recovered, up to what
  time, and where and why the rest was lost.
* **unreadable**: not an MCAP file, or no complete chunk before the damage. BagError.

Parsing is the ``mcap`` library's (its stream reader, told to emit chunks whole and to
check CRCs); this module only decides where the good part ends. Every error the library
or its decompressors raise on bad bytes is mapped to BagError (``READ_ERRORS``).
"""

from __future__ import annotations

import struct
import zlib
from dataclasses import dataclass, field
from typing import IO

import zstandard
from mcap.exceptions import EndOfFile, McapError
from mcap.records import (
    Channel,
    Chunk,
    ChunkIndex,
    DataEnd,
    Footer,
    Header,
    Message,
    Metadata,
    Schema,
    Statistics,
)
from mcap.stream_reader import MAGIC_SIZE, CRCValidationError, StreamReader, breakup_chunk
from mcap.summary import Summary

from ._format import BagError

MAGIC = b"\x89MCAP0\r\n"
# What the mcap library and the decompressors it calls raise on bytes that are not a valid
# MCAP: its own errors, CRC mismatches (ValueError), short reads (struct.error, EOFError),
# zstd and lz4 failures, bad UTF-8 (ValueError), ids that point nowhere (KeyError), and
# absurd lengths (OverflowError, MemoryError).
READ_ERRORS: tuple[type[BaseException], ...] = (
    McapError,
    ValueError,
    struct.error,
    EOFError,
    KeyError,
    IndexError,
    OverflowError,
    MemoryError,
    RuntimeError,
    zstandard.ZstdError,
)
# Bytes of the footer's fields a summary CRC covers: opcode, length, summary_start and
# summary_offset_start (the CRC itself and the closing magic follow).
_FOOTER_CRC_SPAN = 1 + 8 + 8 + 8


def reason(exc: BaseException) -> str:
    """A short, one-line account of a read error."""
    if isinstance(exc, EndOfFile | EOFError | struct.error):
        return "the file ends inside a record"
    if isinstance(exc, CRCValidationError):
        if isinstance(exc.record, DataEnd):
            return "the data section's checksum does not match: bytes before it were changed"
        return "its checksum does not match"
    text = " ".join(str(exc).split()) or type(exc).__name__
    return text[:160]


@dataclass(frozen=True, slots=True)
class Integrity:
    """How much of a recording could be read, and why not all of it."""

    complete: bool
    size_bytes: int
    messages: int  # messages the file yields (all channels, images and annotations too)
    start_ns: int | None
    end_ns: int | None
    data_end_byte: int | None = None  # where the data section ends, if that was reached
    lost_from_byte: int | None = None  # the first byte not read (None: complete)
    cut_short: bool = False  # the file has no end: killed, full disk or power loss
    problem: str | None = None  # why the rest was not read

    @property
    def status(self) -> str:
        return "complete" if self.complete else "recovered"

    def describe(self, end_text: str) -> str:
        """One line: ``recovered N messages up to <end_text>; the file was cut short ...``."""
        if self.complete:
            plural = "" if self.messages == 1 else "s"
            return f"complete: {self.messages} message{plural}, checksums verified"
        head = f"recovered {self.messages} messages up to {end_text}"
        at = self.lost_from_byte or 0
        if self.cut_short:
            tail = self.size_bytes - at
            lost = (
                f"the {tail} bytes after its last complete chunk and anything not yet written "
                "are lost"
                if tail
                else "anything not yet written is lost"
            )
            return f"{head}; the file was cut short at byte {self.size_bytes} (no summary): {lost}"
        if self.data_end_byte is not None and at > self.data_end_byte:
            return (
                f"{head}; the summary after the data is damaged at byte {at} ({self.problem}); "
                "every chunk's checksum matched, so no message is lost"
            )
        return (
            f"{head}; the file is damaged at byte {at} of {self.size_bytes} "
            f"({self.problem}) and what follows it is lost"
        )


@dataclass
class Scan:
    """What one pass over a recording found."""

    integrity: Integrity
    summary: Summary  # the file's own summary when complete, else rebuilt from good chunks
    header: Header | None = None
    metadata: list[Metadata] = field(default_factory=list)
    compressions: set[str] = field(default_factory=set)
    chunks: int = 0


@dataclass
class _Pass:
    """Records of the sequential pass, before anything is decided."""

    header: Header | None = None
    chunks: list[tuple[int, Chunk]] = field(default_factory=list)  # (offset, chunk w/o data)
    metadata: list[Metadata] = field(default_factory=list)
    statistics: Statistics | None = None
    data_end: int | None = None  # offset of the DataEnd record
    footer: Footer | None = None
    footer_at: int | None = None
    failed_at: int | None = None
    error: BaseException | None = None
    summary: Summary = field(default_factory=Summary)


def scan(stream: IO[bytes], size: int, where: str) -> Scan:
    """Read the whole file once (checking every stored checksum) and decide what is good."""
    stream.seek(0)
    if stream.read(MAGIC_SIZE) != MAGIC:
        raise BagError(f"{where} is not an MCAP file; record one with `framegate record`")
    found = _first_pass(stream, size)
    ends_with_magic = _ends_with_magic(stream, size)
    problem_at, problem = found.failed_at, reason(found.error) if found.error else None
    if problem is None and found.footer is not None:
        problem_at, problem = _check_summary(stream, found)
    if problem is None and (found.footer is None or not ends_with_magic):
        problem_at, problem = size, "the file has no footer"
    compressions = {chunk.compression or "none" for _offset, chunk in found.chunks}
    if problem is None and found.footer is not None and found.footer.summary_start != 0:
        stats = found.statistics
        integrity = Integrity(
            complete=True,
            size_bytes=size,
            messages=stats.message_count if stats else 0,
            start_ns=stats.message_start_time if stats and stats.message_count else None,
            end_ns=stats.message_end_time if stats and stats.message_count else None,
            data_end_byte=found.data_end,
        )
        return Scan(
            integrity,
            found.summary,
            found.header,
            found.metadata,
            compressions,
            len(found.chunks),
        )
    assert problem_at is not None and problem is not None
    return _recover(
        stream,
        size,
        found,
        problem_at,
        problem,
        cut_short=not ends_with_magic,
        compressions=compressions,
        where=where,
    )


def _first_pass(stream: IO[bytes], size: int) -> _Pass:
    """Every record up to the first that does not parse; chunks are kept without data."""
    found = _Pass()
    stream.seek(0)
    # Chunks stay whole (their CRC is checked later, only if needed); the data section's
    # CRC is checked when DataEnd is read. No record may claim more bytes than the file has.
    records = StreamReader(
        stream, emit_chunks=True, validate_crcs=True, record_size_limit=size
    ).records
    at = 0
    while True:
        at = stream.tell()
        try:
            record = next(records)
        except StopIteration:
            return found
        except READ_ERRORS as exc:
            found.failed_at, found.error = max(at, MAGIC_SIZE), exc
            return found
        if isinstance(record, Chunk):
            found.chunks.append((at, _without_data(record)))
        elif isinstance(record, Header):
            found.header = record
        elif isinstance(record, Metadata):
            found.metadata.append(record)
        elif isinstance(record, DataEnd):
            found.data_end = at
        elif isinstance(record, Footer):
            found.footer, found.footer_at = record, at
        elif found.data_end is not None:
            _add_summary_record(found, record)


def _without_data(chunk: Chunk) -> Chunk:
    """The chunk's header fields only: the pass must not hold the whole file in memory."""
    return Chunk(
        compression=chunk.compression,
        data=b"",
        message_start_time=chunk.message_start_time,
        message_end_time=chunk.message_end_time,
        uncompressed_crc=chunk.uncompressed_crc,
        uncompressed_size=chunk.uncompressed_size,
    )


def _add_summary_record(found: _Pass, record: object) -> None:
    summary = found.summary
    if isinstance(record, Schema):
        summary.schemas[record.id] = record
    elif isinstance(record, Channel):
        summary.channels[record.id] = record
    elif isinstance(record, ChunkIndex):
        summary.chunk_indexes.append(record)
    elif isinstance(record, Statistics):
        found.statistics = summary.statistics = record


def _ends_with_magic(stream: IO[bytes], size: int) -> bool:
    if size < 2 * MAGIC_SIZE:
        return False
    stream.seek(size - MAGIC_SIZE)
    return stream.read(MAGIC_SIZE) == MAGIC


def _check_summary(stream: IO[bytes], found: _Pass) -> tuple[int | None, str | None]:
    """Where and why the summary cannot be trusted, or (None, None)."""
    footer, footer_at = found.footer, found.footer_at
    assert footer is not None and footer_at is not None
    if footer.summary_start == 0:
        return None, None
    if found.data_end is None or not found.data_end < footer.summary_start <= footer_at:
        return footer_at, "the footer points outside the file"
    if footer.summary_crc != 0:
        stream.seek(footer.summary_start)
        remaining = footer_at + _FOOTER_CRC_SPAN - footer.summary_start
        crc = 0
        while remaining > 0:
            block = stream.read(min(remaining, 1 << 20))
            if not block:
                return footer.summary_start, "the summary is cut short"
            crc = zlib.crc32(block, crc)
            remaining -= len(block)
        if crc != footer.summary_crc:
            return footer.summary_start, "the summary's checksum does not match"
    stats = found.statistics
    if stats is None or stats.chunk_count != len(found.chunks):
        return footer.summary_start, "the summary does not match the chunks found"
    return None, None


def _recover(
    stream: IO[bytes],
    size: int,
    found: _Pass,
    problem_at: int,
    problem: str,
    *,
    cut_short: bool,
    compressions: set[str],
    where: str,
) -> Scan:
    """Keep every chunk before the first problem whose own CRC matches; stop at a bad one."""
    summary = Summary()
    counts: dict[int, int] = {}
    start_ns: int | None = None
    end_ns: int | None = None
    kept = 0
    for offset, header in found.chunks:
        if offset >= problem_at:
            break
        try:
            records = _read_chunk(stream, offset, size)
            messages = [r for r in records if isinstance(r, Message)]
            for record in records:
                if isinstance(record, Schema):
                    summary.schemas[record.id] = record
                elif isinstance(record, Channel):
                    summary.channels[record.id] = record
            unknown = {m.channel_id for m in messages} - set(summary.channels)
            if unknown:
                raise ValueError(f"messages of undeclared channel {min(unknown)}")
        except READ_ERRORS as exc:
            problem_at, problem, cut_short = offset, f"a chunk: {reason(exc)}", False
            break
        kept += 1
        for message in messages:
            counts[message.channel_id] = counts.get(message.channel_id, 0) + 1
            start_ns = message.log_time if start_ns is None else min(start_ns, message.log_time)
            end_ns = message.log_time if end_ns is None else max(end_ns, message.log_time)
        if messages:
            summary.chunk_indexes.append(_index(offset, header))
    total = sum(counts.values())
    if total == 0:
        lost = "cut short" if cut_short else f"damaged at byte {problem_at} ({problem})"
        raise BagError(
            f"{where} is {lost} before its first complete chunk: nothing can be recovered"
        )
    summary.statistics = Statistics(
        message_count=total,
        schema_count=len(summary.schemas),
        channel_count=len(summary.channels),
        attachment_count=0,
        metadata_count=len(found.metadata),
        chunk_count=kept,
        message_start_time=start_ns or 0,
        message_end_time=end_ns or 0,
        channel_message_counts=counts,
    )
    integrity = Integrity(
        complete=False,
        size_bytes=size,
        messages=total,
        start_ns=start_ns,
        end_ns=end_ns,
        data_end_byte=found.data_end,
        lost_from_byte=problem_at,
        cut_short=cut_short,
        problem=problem,
    )
    return Scan(integrity, summary, found.header, found.metadata, compressions, kept)


def _read_chunk(stream: IO[bytes], offset: int, size: int) -> list[object]:
    """The records of the chunk at ``offset``, its CRC checked."""
    stream.seek(offset)
    record = next(
        StreamReader(stream, skip_magic=True, emit_chunks=True, record_size_limit=size).records
    )
    if not isinstance(record, Chunk):
        raise ValueError(f"no chunk at byte {offset}")
    return list(breakup_chunk(record, validate_crc=True))


def _index(offset: int, chunk: Chunk) -> ChunkIndex:
    """A chunk index entry for a chunk found by the pass (what a seeking reader needs)."""
    return ChunkIndex(
        message_start_time=chunk.message_start_time,
        message_end_time=chunk.message_end_time,
        chunk_start_offset=offset,
        chunk_length=0,  # not used for reading
        message_index_offsets={},  # unknown: every chunk is scanned for the topics asked
        message_index_length=0,
        compression=chunk.compression,
        compressed_size=0,
        uncompressed_size=chunk.uncompressed_size,
    )
