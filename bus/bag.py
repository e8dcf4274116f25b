"""MCAP bags: write them, read them back (also ones cut short by a crash). How a message is
stored is bus.bag_format's; recording the bus and replaying bags, bus.bag_record_play's.

Chunks are closed by age as well as size, and the file's header is on disk from the start, so
a recorder killed at any moment loses at most ``CHUNK_PERIOD_S`` and never leaves an empty
file. Images, point clouds and transforms are also written to a ``<topic>/foxglove`` channel in
Foxglove's well-known protobuf schemas, so Foxglove Studio shows them directly.

Reading trusts no bag: every record's length, every chunk's uncompressed size and what its
decompression actually yields are bounded (by the bus's largest message) before anything is
allocated, and a message that does not decode is a BagError, not a traceback. A bag cut
short by a crash still reads up to the cut.
"""

from __future__ import annotations

import dataclasses
import io
import os
import stat
import struct
import time
import typing
from array import array
from collections.abc import Collection, Iterator, Sequence
from pathlib import Path
from typing import Any, BinaryIO

import lz4.frame
import numpy as np
import zstandard
from mcap.exceptions import McapError, RecordLengthLimitExceeded
from mcap.reader import SeekingReader
from mcap.records import Channel, Chunk, Schema
from mcap.records import Message as McapMessage
from mcap.stream_reader import StreamReader, breakup_chunk
from mcap.writer import CompressionType, Writer

from bus.bag_format import (
    MESSAGE_ENCODING,
    SCHEMA_ENCODING,
    BagError,
    pack_frames,
    schema_description,
    unpack_frames,
)
from msgs.codec import DEFAULT_MAX_MESSAGE_BYTES, Envelope, MessageError, decode
from msgs.foxglove import FOXGLOVE_SUFFIX, foxglove_view

COMPRESSIONS = {"none": CompressionType.NONE, "lz4": CompressionType.LZ4, "zstd": CompressionType.ZSTD}
# No record, and no chunk once decompressed, may be larger than the largest message the bus
# carries plus its framing: a bag that claims more is refused before anything is allocated.
MAX_RECORD_BYTES = DEFAULT_MAX_MESSAGE_BYTES + (1 << 20)
# A chunk is closed at this age, or at chunk_size, whichever comes first: what a killed recorder
# can lose. Half the ~1 s promised, leaving the rest to a recorder that a busy machine delays.
CHUNK_PERIOD_S = 0.5


class BagWriteError(BagError):
    """The disk refused the bag's data (full, over a size limit, failing): recording stopped and
    the file was closed as it stood, readable up to its last complete chunk. ``errno`` says why."""

    def __init__(self, text: str, errno: int | None) -> None:
        super().__init__(text)
        self.errno = errno


class BagWriter:
    """Writes envelopes (with their raw frames) to an MCAP file, chunked and compressed."""

    def __init__(
        self,
        path: str | Path,
        compression: str = "lz4",
        foxglove: bool = True,
        chunk_size: int = 4 * 1024 * 1024,
        chunk_period_s: float = CHUNK_PERIOD_S,
    ) -> None:
        if compression not in COMPRESSIONS:
            raise BagError(f"compression {compression!r} unknown; allowed: {sorted(COMPRESSIONS)}")
        self.path = Path(path)
        self._abandoned = False
        try:
            self.path.parent.mkdir(parents=True, exist_ok=True)
            self._file: BinaryIO = open(self.path, "wb")
        except OSError as error:
            raise BagWriteError(f"bag {self.path} cannot be created: {error.strerror or error}", error.errno) from error
        try:
            self._writer = Writer(self._file, chunk_size=chunk_size, compression=COMPRESSIONS[compression])
            self._writer.start(profile="dtx", library="dtx")
            self._file.flush()  # a recorder killed at once still leaves a bag that opens, never 0 bytes
        except OSError as error:
            raise self._write_failed(error) from error
        self.chunk_period_s = chunk_period_s
        self._chunk_opened: float | None = None  # time.monotonic() of the open chunk's first message
        self.foxglove = foxglove
        self._schemas: dict[str, int] = {}
        self._channels: dict[str, int] = {}
        self.counts: dict[str, int] = {}

    def _channel(self, topic: str, schema_name: str, encoding: str, schema_data: bytes, message_encoding: str) -> int:
        if topic not in self._channels:
            if schema_name not in self._schemas:
                self._schemas[schema_name] = self._writer.register_schema(schema_name, encoding, schema_data)
            self._channels[topic] = self._writer.register_channel(topic, message_encoding, self._schemas[schema_name])
        return self._channels[topic]

    def write(self, envelope: Envelope, frames: list[Any], log_time_ns: int | None = None) -> None:
        """Add one message; BagWriteError (the file closed as it stands) when the disk refuses it."""
        try:
            self._write(envelope, frames, log_time_ns)
        except OSError as error:
            raise self._write_failed(error) from error

    def _write(self, envelope: Envelope, frames: list[Any], log_time_ns: int | None) -> None:
        message = envelope.message
        log_time = log_time_ns if log_time_ns is not None else time.time_ns()
        channel = self._channel(
            envelope.topic, message.SCHEMA, SCHEMA_ENCODING, schema_description(type(message)), MESSAGE_ENCODING
        )
        self._writer.add_message(
            channel, log_time, pack_frames(frames[1:]), message.header.stamp_ns, message.header.seq
        )
        self.counts[envelope.topic] = self.counts.get(envelope.topic, 0) + 1
        if self._chunk_opened is None:
            self._chunk_opened = time.monotonic()
        if self.foxglove:
            view = foxglove_view(message)
            if view is not None:
                schema = view.get_schema()
                fox_channel = self._channel(
                    envelope.topic + FOXGLOVE_SUFFIX, schema.name, schema.encoding, schema.data, "protobuf"
                )
                self._writer.add_message(
                    fox_channel, log_time, view.encode(), message.header.stamp_ns, message.header.seq
                )

        self.flush_if_due()

    def flush_if_due(self) -> None:
        """Close the open chunk and hand it to the OS once it is ``chunk_period_s`` old, so a
        recorder killed at any moment loses at most that much (a chunk is only readable once
        closed); called after each message and by the recorder's loop when none come."""
        if self._chunk_opened is not None and time.monotonic() - self._chunk_opened >= self.chunk_period_s:
            try:
                self._writer.flush()
            except OSError as error:
                raise self._write_failed(error) from error
            self._chunk_opened = None

    def close(self) -> None:
        """Write the summary and close; nothing more after a write failed (the file is closed)."""
        if self._abandoned:
            return
        try:
            self._writer.finish()
            self._file.close()
        except OSError as error:
            raise self._write_failed(error) from error

    def _write_failed(self, error: OSError) -> BagWriteError:
        """Close the file as it stands (no summary: the disk refuses more) and say so. A file
        that holds nothing is removed, so a full disk leaves no empty bags behind."""
        self._abandoned = True
        try:
            self._file.close()  # its unwritten buffer is lost; the raw file is closed regardless
        except OSError:
            pass
        kept = self.path.stat().st_size if self.path.exists() else 0
        if kept == 0:
            self.path.unlink(missing_ok=True)
        return BagWriteError(
            f"bag {self.path}: the disk refused the data ({error.strerror or error}); recording "
            f"stopped, {kept} bytes kept, readable up to the last complete chunk"
            if kept
            else f"bag {self.path}: the disk refused the data ({error.strerror or error}); "
            "nothing could be written, the file is removed",
            error.errno,
        )


@dataclasses.dataclass
class BagInfo:
    path: str
    truncated: bool
    message_count: int
    start_ns: int
    end_ns: int
    topics: dict[str, dict[str, Any]]
    compression: str

    @property
    def duration_s(self) -> float:
        return max(0, self.end_ns - self.start_ns) / 1e9


@dataclasses.dataclass
class BagRecord:
    topic: str
    schema: str
    message_encoding: str
    log_time_ns: int
    data: bytes
    publish_time_ns: int = 0


class _BoundedFile:
    """A bag file whose reads are bounded: none past its end (a length read from a damaged bag
    would otherwise allocate what it claims first) and none over ``MAX_RECORD_BYTES``."""

    def __init__(self, stream: BinaryIO, path: str | Path) -> None:
        self._stream, self._path = stream, path
        self._size = os.fstat(stream.fileno()).st_size

    def seek(self, offset: int, whence: int = io.SEEK_SET) -> int:
        return self._stream.seek(offset, whence)

    def tell(self) -> int:
        return self._stream.tell()

    def read(self, size: int | None = -1) -> bytes:
        left = max(0, self._size - self._stream.tell())
        if size is None or size < 0:
            size = left
        if size > MAX_RECORD_BYTES:
            raise BagError(f"bag {self._path}: a record claims {size} bytes, over the limit of {MAX_RECORD_BYTES}")
        return self._stream.read(min(size, left))  # a short read is a bag cut short


def _open_bag(path: str | Path) -> BinaryIO:
    """The bag file, opened only if it is a regular file (a named pipe would block, a device
    never end)."""
    try:
        fd = os.open(path, os.O_RDONLY | os.O_NONBLOCK | os.O_CLOEXEC)  # opening a pipe must not wait
    except OSError as exc:
        raise BagError(f"bag {path} cannot be read: {exc}") from exc
    if not stat.S_ISREG(os.fstat(fd).st_mode):
        os.close(fd)
        raise BagError(f"bag {path} is not a regular file")
    os.set_blocking(fd, True)
    return os.fdopen(fd, "rb")


def _decompressed(chunk: Chunk, path: str | Path) -> bytes:
    """A chunk's records, decompressed no further than the size the chunk declares (itself
    bounded): a small chunk that inflates to gigabytes is refused after that many bytes."""
    size = chunk.uncompressed_size
    if size > MAX_RECORD_BYTES:
        raise BagError(f"bag {path}: a chunk claims {size} bytes uncompressed, over the limit of {MAX_RECORD_BYTES}")
    try:
        if chunk.compression == "":
            data = chunk.data
        elif chunk.compression == "zstd":
            reader = zstandard.ZstdDecompressor().stream_reader(chunk.data)
            parts, got = [], 0
            while got <= size and (part := reader.read(size + 1 - got)):
                parts.append(part)
                got += len(part)
            data = b"".join(parts)
        elif chunk.compression == "lz4":
            data = lz4.frame.LZ4FrameDecompressor().decompress(chunk.data, max_length=size + 1)
        else:
            raise BagError(f"bag {path}: chunk compression {chunk.compression!r} unknown")
    except (zstandard.ZstdError, RuntimeError) as exc:
        raise BagError(f"bag {path}: a chunk does not decompress ({exc})") from exc
    if len(data) != size:
        raise BagError(
            f"bag {path}: a chunk declares {size} bytes uncompressed but holds "
            f"{'more' if len(data) > size else len(data)}"
        )
    return data


@dataclasses.dataclass
class BagReading:
    """What reading a bag found besides its records; final once the records are exhausted."""

    truncated: bool = False
    compression: str = "unknown"


def read_records(path: str | Path) -> tuple[Iterator[BagRecord], BagReading]:
    """Iterate every message of a bag in file order; the BagReading says, once the iterator
    is exhausted, whether the file was cut short and how its chunks were compressed. The
    seeking reader needs the summary a crash never wrote, so a bag is read as a stream
    instead: that works for both. BagError for a bag that is not to be read (a record or
    chunk over the limits, not a regular file)."""
    reading = BagReading()

    def records() -> Iterator[BagRecord]:
        schemas: dict[int, Schema] = {}
        channels: dict[int, Channel] = {}
        with _open_bag(path) as raw:
            try:
                stream = _BoundedFile(raw, path)
                for record in StreamReader(
                    typing.cast(BinaryIO, stream),
                    skip_magic=False,
                    emit_chunks=True,
                    record_size_limit=MAX_RECORD_BYTES,
                ).records:
                    if isinstance(record, Chunk):
                        if reading.compression == "unknown":
                            reading.compression = record.compression or "none"
                        inner = breakup_chunk(
                            dataclasses.replace(record, compression="", data=_decompressed(record, path))
                        )
                    else:
                        inner = [record]
                    for item in inner:
                        if isinstance(item, Schema):
                            schemas[item.id] = item
                        elif isinstance(item, Channel):
                            channels[item.id] = item
                        elif isinstance(item, McapMessage):
                            channel = channels[item.channel_id]
                            schema = schemas.get(channel.schema_id)
                            yield BagRecord(
                                channel.topic,
                                schema.name if schema else "",
                                channel.message_encoding,
                                item.log_time,
                                item.data,
                                item.publish_time,
                            )
            except BagError:
                raise
            except RecordLengthLimitExceeded as exc:
                raise BagError(f"bag {path}: {exc}") from exc
            except OSError as exc:
                raise BagError(f"bag {path} cannot be read: {exc}") from exc
            except (McapError, EOFError, struct.error, ValueError, KeyError):
                reading.truncated = True  # everything before the cut has been yielded

    return records(), reading


def bag_info(path: str | Path) -> BagInfo:
    """Per channel: schema, encoding, messages, bytes, and how far behind the recorder was
    (:func:`recording_lag`)."""
    records, reading = read_records(path)
    topics: dict[str, dict[str, Any]] = {}
    times: dict[str, tuple[array[int], array[int]]] = {}  # topic -> (log times, publish times), in file order
    start = end = 0
    count = 0
    for record in records:
        entry = topics.setdefault(
            record.topic, {"schema": record.schema, "encoding": record.message_encoding, "count": 0, "bytes": 0}
        )
        entry["count"] += 1
        entry["bytes"] += len(record.data)
        if record.publish_time_ns:
            log_times, publish_times = times.setdefault(record.topic, (array("q"), array("q")))
            log_times.append(record.log_time_ns)
            publish_times.append(record.publish_time_ns)
        start = record.log_time_ns if count == 0 else min(start, record.log_time_ns)
        end = max(end, record.log_time_ns)
        count += 1
    for topic, entry in topics.items():
        if topic in times:
            entry.update(recording_lag(*times[topic]))
        else:
            reason = "no message of this channel carries a publish time"
            entry.update(lag_ms=None, lag_ms_undefined=reason, backlog_max=None, backlog_max_undefined=reason)
    return BagInfo(str(path), reading.truncated, count, start, end, topics, reading.compression)


def recording_lag(log_times: Sequence[int], publish_times: Sequence[int]) -> dict[str, Any]:
    """How far behind its recorder one channel was, from the records alone, in file (= write)
    order (docs/bag-format.md): each message's lag is its log time minus its publish time (the
    header stamp), in ms; the backlog when a message was written is the count of the channel's
    messages published by then but written after it."""
    logged = np.asarray(log_times, np.int64)
    published = np.asarray(publish_times, np.int64)
    lag_ms = (logged - published) / 1e6
    p50, p99 = np.percentile(lag_ms, [50, 99])
    published_by = np.searchsorted(np.sort(published), logged, side="right")
    backlog = published_by - np.arange(1, len(logged) + 1)
    return {
        "lag_ms": {"p50": round(float(p50), 3), "p99": round(float(p99), 3), "max": round(float(lag_ms.max()), 3)},
        "backlog_max": max(0, int(backlog.max())),
    }


def bag_channels(path: str | Path) -> dict[str, tuple[str, str]]:
    """Topic -> (schema name, message encoding); from the summary when the bag has one
    (instant), else by reading the whole stream."""
    with _open_bag(path) as raw:
        try:
            summary = SeekingReader(
                typing.cast(BinaryIO, _BoundedFile(raw, path)), record_size_limit=MAX_RECORD_BYTES
            ).get_summary()
        except (McapError, EOFError, struct.error, ValueError):
            summary = None
        except OSError as exc:
            raise BagError(f"bag {path} cannot be read: {exc}") from exc
    if summary is not None:
        return {
            c.topic: (summary.schemas[c.schema_id].name if c.schema_id in summary.schemas else "", c.message_encoding)
            for c in summary.channels.values()
        }
    return {topic: (entry["schema"], entry["encoding"]) for topic, entry in bag_info(path).topics.items()}


def iter_envelopes(path: str | Path, topics: Collection[str] | None = None) -> Iterator[tuple[int, Envelope]]:
    """(log time ns, decoded dtx message) for every dtx message of the bag, in file order; of
    ``topics`` only, where given (the others are not decoded: a bag recorded by an older build
    still gives the topics whose messages this one reads)."""
    records, _ = read_records(path)
    for number, record in enumerate(records, start=1):
        if record.message_encoding == MESSAGE_ENCODING and (topics is None or record.topic in topics):
            try:
                envelope = decode(unpack_frames(record.topic, record.data))
            except MessageError as exc:
                raise BagError(
                    f"bag {path}: message {number} ({record.topic}) is not a valid dtx message: {exc}"
                ) from exc
            yield record.log_time_ns, envelope
