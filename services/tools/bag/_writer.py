"""Writing buffers to an MCAP file that ``play`` re-offers and Foxglove opens."""

from __future__ import annotations

import contextlib
import json
import os
import threading
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import IO, Any

from mcap.writer import CompressionType, Writer

from middleware import ConfigError, DataObject, Retention
from services.lib.files import create_file
from services.lib.frame_layout import frame_layout

from ._derived import DerivedMessage, Deriver
from ._format import (
    ELEMENT_MESSAGE_ENCODING,
    ELEMENT_SCHEMA_ENCODING,
    ELEMENT_SCHEMA_NAME,
    ELEMENT_SCHEMA_TEXT,
    IMAGE_MESSAGE_ENCODING,
    IMAGE_SCHEMA,
    IMAGE_SCHEMA_ENCODING,
    IMAGE_SCHEMA_NAME,
    KEY_ROLE,
    KEY_SOURCE,
    PROFILE,
    BagError,
    channel_metadata,
    element_topic,
    encode_element,
    encode_raw_image,
    image_topic,
)

COMPRESSIONS = {"zstd": CompressionType.ZSTD, "lz4": CompressionType.LZ4, "none": None}
# Where mcap's Writer keeps the compression of the chunks it closes (see ``catch_up``).
_COMPRESSION_ATTRIBUTE = "_Writer__compression"

# A chunk is closed, written and flushed to the OS once it holds this much, or once its
# first message is this old: a recording cut short (full disk, kill -9, power loss) loses
# at most the open chunk, which readers skip (``_scan``).
CHUNK_BYTES = 4 * 1024 * 1024
CHUNK_AGE_S = 1.0
# The file is fsync'ed at most this often (after a chunk), so a power loss loses about this
# much more than a kill does, and a high-rate recording does not wait on the disk per chunk.
FSYNC_PERIOD_S = 1.0


@dataclass
class _Channels:
    service: str
    element_id: int
    frame: bool = False
    image_id: int | None = None
    messages: int = 0
    images: int = 0
    deriver: Deriver | None = None
    derived_ids: dict[str, int] = field(default_factory=dict)
    derived: int = 0


class BagWriter:
    """Records elements of several buffers into one MCAP file. Thread-safe.

    Use as a context manager, or call ``close``: only a closed file has the summary
    section readers use to find channels and messages quickly. With ``annotations`` (the
    default) it also writes the derived Foxglove channels of ``_derived`` (verdict and
    detection annotations, the verdict and gyro-rate plots).
    """

    def __init__(
        self,
        path: Path,
        *,
        images: bool = True,
        annotations: bool = True,
        compression: str = "zstd",
        overwrite: bool = False,
        library: str = "framegate",
    ) -> None:
        if compression not in COMPRESSIONS:
            raise BagError(f"unknown compression {compression!r}; use zstd, lz4 or none")
        self.path = path
        self._images = images
        self._annotations = annotations
        # The newest raw frame's (width, height): verdict borders are drawn to that size.
        self._frame_size_px: tuple[int, int] | None = None
        self._schema_ids: dict[str, int] = {}
        try:  # exclusively, and never through a link another user planted
            self._stream: IO[bytes] = create_file(
                path, overwrite=overwrite, overwrite_flag="--overwrite"
            )
        except ConfigError as exc:
            raise BagError(str(exc)) from exc
        chosen = COMPRESSIONS[compression]
        self._compression = chosen if chosen is not None else CompressionType.NONE
        self._writer = Writer(
            self._stream,
            chunk_size=CHUNK_BYTES,
            compression=self._compression,
            use_chunking=True,
            # Chunks carry a CRC of their contents; the data section's CRC also covers chunk
            # headers and indexes, so readers tell a damaged file from a complete one.
            enable_crcs=True,
            enable_data_crcs=True,
        )
        self._writer.start(profile=PROFILE, library=library)
        self._lock = threading.Lock()
        self._element_schema = self._writer.register_schema(
            ELEMENT_SCHEMA_NAME, ELEMENT_SCHEMA_ENCODING, ELEMENT_SCHEMA_TEXT.encode("utf-8")
        )
        self._image_schema: int | None = None
        self._channels: dict[str, _Channels] = {}
        self._closed = False
        self._failed: str | None = None  # why the file cannot be written any more
        self._chunk_bytes = 0
        self._chunk_started = 0.0
        self._synced = time.monotonic()

    def add_buffer(self, service: str, buffer: str, *, kind: str, retention: Retention) -> None:
        """Declare a buffer before writing its elements (its kind is what ``play`` offers)."""
        with self._lock:
            self._check_writable()
            try:
                self._add_buffer(service, buffer, kind, retention)
            except OSError as exc:
                raise self._fail("write", exc) from exc

    def _add_buffer(self, service: str, buffer: str, kind: str, retention: Retention) -> None:
        """Register the buffer's channels (called under the lock)."""
        name = f"{service}/{buffer}"
        if name in self._channels:
            return
        element_id = self._writer.register_channel(
            element_topic(service, buffer),
            ELEMENT_MESSAGE_ENCODING,
            self._element_schema,
            channel_metadata(service, buffer, kind, retention),
        )
        channels = _Channels(service, element_id, frame=kind == "frame")
        if self._images and kind == "frame":
            if self._image_schema is None:
                self._image_schema = self._writer.register_schema(
                    IMAGE_SCHEMA_NAME,
                    IMAGE_SCHEMA_ENCODING,
                    json.dumps(IMAGE_SCHEMA).encode("utf-8"),
                )
            channels.image_id = self._writer.register_channel(
                image_topic(service, buffer),
                IMAGE_MESSAGE_ENCODING,
                self._image_schema,
                {KEY_ROLE: "image", KEY_SOURCE: element_topic(service, buffer)},
            )
        if self._annotations:
            self._add_derived(channels, service, buffer, kind)
        self._channels[name] = channels

    def _add_derived(self, channels: _Channels, service: str, buffer: str, kind: str) -> None:
        """Register the buffer's derived channels (called under the lock)."""
        deriver = Deriver(service, buffer, kind)
        for topic in deriver.topics:
            schema_id = 0  # schemaless JSON
            if topic.schema_name is not None:
                if topic.schema_name not in self._schema_ids:
                    self._schema_ids[topic.schema_name] = self._writer.register_schema(
                        topic.schema_name, topic.schema_encoding, topic.schema_data
                    )
                schema_id = self._schema_ids[topic.schema_name]
            channels.derived_ids[topic.topic] = self._writer.register_channel(
                topic.topic,
                topic.message_encoding,
                schema_id,
                {KEY_ROLE: topic.role, KEY_SOURCE: element_topic(service, buffer)},
            )
        if deriver.topics:
            channels.deriver = deriver

    def write(self, name: str, element: DataObject) -> None:
        """Append one element of ``service/buffer`` (declared with ``add_buffer``)."""
        # Encoding outside the lock: base64 of a large frame takes a while.
        data = encode_element(element)
        channels = self._channels.get(name)
        if channels is None:
            raise BagError(f"buffer {name!r} was not declared with add_buffer")
        image: bytes | None = None
        if channels.frame and (channels.image_id is not None or self._annotations):
            layout = frame_layout(element.metadata, len(element.payload))
            if layout is not None:
                self._frame_size_px = (layout.width_px, layout.height_px)
                if channels.image_id is not None:
                    image = encode_raw_image(element, layout, frame_id=channels.service)
        derived: list[DerivedMessage] = []
        if channels.deriver is not None:
            derived = channels.deriver.derive(element, frame_size_px=self._frame_size_px)
        t = element.timestamp_ns
        sync = False
        with self._lock:
            self._check_writable()
            channels.messages += 1
            try:
                if self._chunk_bytes == 0:
                    self._chunk_started = time.monotonic()
                self._add(channels, t, data, image)
                self._chunk_bytes += len(data) + (len(image) if image is not None else 0)
                for message in derived:
                    channels.derived += 1
                    self._chunk_bytes += len(message.data)
                    self._writer.add_message(
                        channels.derived_ids[message.topic],
                        log_time=message.log_time_ns,
                        data=message.data,
                        publish_time=message.log_time_ns,
                        sequence=channels.derived & 0xFFFFFFFF,
                    )
                if self._chunk_bytes >= CHUNK_BYTES:
                    sync = self._end_chunk()
            except OSError as exc:
                raise self._fail("write", exc) from exc
        if sync:
            self._sync()

    def catch_up(self, behind: bool) -> None:
        """While ``behind``, chunks are stored uncompressed: a writer that cannot keep up
        with the buffers (a busy machine, a slow compressor) catches up at the cost of file
        size instead of dropping elements or making the stop wait. MCAP compresses each
        chunk on its own, so readers take a file of mixed chunks as any other."""
        wanted = CompressionType.NONE if behind else self._compression
        with self._lock:
            # mcap's Writer takes the compression only at construction and reads it when it
            # closes a chunk; its attribute is private, so switch it only where it exists.
            if hasattr(self._writer, _COMPRESSION_ATTRIBUTE):
                setattr(self._writer, _COMPRESSION_ATTRIBUTE, wanted)

    def flush_if_due(self) -> None:
        """Close the open chunk if it is older than ``CHUNK_AGE_S`` (call this periodically:
        a quiet buffer must not keep its last elements only in memory)."""
        sync = False
        with self._lock:
            if self._closed or self._failed is not None or self._chunk_bytes == 0:
                return
            if time.monotonic() - self._chunk_started < CHUNK_AGE_S:
                return
            try:
                sync = self._end_chunk()
            except OSError as exc:
                raise self._fail("write", exc) from exc
        if sync:
            self._sync()

    def _end_chunk(self) -> bool:
        """Write the open chunk and hand it to the OS (under the lock); whether to fsync."""
        self._writer.flush()
        self._chunk_bytes = 0
        now = time.monotonic()
        if now - self._synced < FSYNC_PERIOD_S:
            return False
        self._synced = now
        return True

    def _sync(self) -> None:
        """fsync outside the lock, so writers do not wait on the disk."""
        try:
            os.fsync(self._stream.fileno())
        except (OSError, ValueError) as exc:  # ValueError: closed meanwhile, nothing to sync
            if isinstance(exc, OSError):
                with self._lock:
                    raise self._fail("write", exc) from exc

    def _check_writable(self) -> None:
        if self._failed is not None:
            raise BagError(self._failed)
        if self._closed:
            raise BagError(f"{self.path} is closed")

    def _fail(self, verb: str, exc: OSError) -> BagError:
        """Remember that the file cannot be written (under the lock): close() then leaves it as
        it is, cut short after its last complete chunk, instead of appending a summary to a
        file whose last chunk may be torn."""
        if self._failed is None:
            self._failed = f"cannot {verb} {self.path}: {exc.strerror or exc}"
        return BagError(self._failed)

    def _add(self, channels: _Channels, t: int, data: bytes, image: bytes | None) -> None:
        """Write the element message and its image message (called under the lock)."""
        self._writer.add_message(
            channels.element_id,
            log_time=t,
            data=data,
            publish_time=t,
            sequence=channels.messages & 0xFFFFFFFF,
        )
        if image is not None and channels.image_id is not None:
            channels.images += 1
            self._writer.add_message(
                channels.image_id,
                log_time=t,
                data=image,
                publish_time=t,
                sequence=channels.images & 0xFFFFFFFF,
            )

    def add_metadata(self, name: str, data: dict[str, str]) -> None:
        """A named MCAP metadata record (e.g. where and when the recording was made), handed
        to the OS at once: MCAP allows one anywhere in the data section, so one written at
        the start survives a recorder killed before its end."""
        with self._lock:
            self._check_writable()
            try:
                self._writer.add_metadata(name, data)
                self._stream.flush()
            except OSError as exc:
                raise self._fail("write", exc) from exc

    def counts(self) -> dict[str, tuple[int, int]]:
        """``service/buffer`` → (element messages, image messages) written so far."""
        with self._lock:
            return {name: (c.messages, c.images) for name, c in self._channels.items()}

    def derived_counts(self) -> dict[str, int]:
        """``service/buffer`` → derived messages (annotations, plots) written so far."""
        with self._lock:
            return {name: c.derived for name, c in self._channels.items()}

    def close(self) -> None:
        """Write the summary and close the file."""
        with self._lock:
            if self._closed:
                return
            self._closed = True
            if self._failed is not None:
                with contextlib.suppress(OSError):  # the write that failed already said why
                    self._stream.close()
                return
            try:
                try:
                    self._writer.finish()
                    self._stream.flush()
                    os.fsync(self._stream.fileno())
                finally:
                    self._stream.close()
            except OSError as exc:
                # A full disk (ENOSPC) or a vanished mount: say so, naming the file.
                raise self._fail("finish", exc) from exc

    def __enter__(self) -> BagWriter:
        return self

    def __exit__(self, *_exc: Any) -> None:
        self.close()
