"""MCAP files written in bulk: a chunked, indexed MCAP writer whose cost per message is one
struct pack and two buffer appends.

Why not the ``mcap`` package's ``Writer`` (still the reader, ``trace.read_messages``): it
builds a record object, updates statistics and writes six pieces per message. A recording
with every frame writes tens of thousands of them a second for the demo's 12 drives, and a
flight record 10 s of them at once: here a frame's message costs the writer process a
fraction of what it cost there, and the writer's whole work at 1 kHz shrank by a third
(benchmarks/recording_cost.py; the figures: benchmarks/README.md, "Figures behind
constants").

What it writes (MCAP, https://mcap.dev/spec): the magic, a header, then chunks of
``chunk_size`` uncompressed bytes (zstd, with their CRC) each followed by its message
indexes; the schema and channel records go into the chunk in which they are registered,
before any message on them. ``finish`` writes the data end, a summary (schemas, channels,
statistics, chunk indexes, each group's offset) and the footer, as ``mcap``'s writer does,
so a reader may seek by time (Foxglove) or read through (``mcap``'s stream reader).

Errors: a write the stream refuses (a full disk) raises at that write, with its cause; the
file then takes nothing more (its offsets would be wrong after a cut write), and
``finish`` leaves it as it is, without a summary, which readers that read through still
read. Bad input (an id past 65,535, a time out of 0..2**64-1 ns, data that is not bytes)
raises ValueError or TypeError and writes nothing. Not thread-safe: one writer thread
uses it; the stream is a binary file (a short write is written on until done).
"""
from __future__ import annotations

import errno
import struct
import sys
import zlib
from array import array
from collections.abc import Mapping, Sequence
from typing import BinaryIO

MAGIC = b"\x89MCAP0\r\n"
HEADER, FOOTER, SCHEMA, CHANNEL, MESSAGE, CHUNK = 0x01, 0x02, 0x03, 0x04, 0x05, 0x06
MESSAGE_INDEX, CHUNK_INDEX, STATISTICS, SUMMARY_OFFSET, DATA_END = 0x07, 0x08, 0x0B, 0x0E, 0x0F

#: a message record's opcode, length and fixed fields: channel, sequence, log and publish time
_MESSAGE = struct.Struct("<BQHIQQ")
_MESSAGE_FIXED = 22  # the fixed fields' bytes (the record's length less its data)
_RECORD = struct.Struct("<BQ")
_U16, _U32, _U64 = struct.Struct("<H"), struct.Struct("<I"), struct.Struct("<Q")
_MAX_ID = 0xFFFF  # schema and channel ids are u16


def _string(text: str) -> bytes:
    """The spec's string: its UTF-8 length (u32), then the bytes."""
    raw = text.encode()
    return _U32.pack(len(raw)) + raw


def _record(opcode: int, body: bytes) -> bytes:
    """A record: its opcode (u8), its body's length (u64), the body."""
    return _RECORD.pack(opcode, len(body)) + body


def _pairs(values: array[int]) -> bytes:
    """(time, offset) pairs as the spec's little-endian u64s."""
    if sys.byteorder != "little":
        values = array("Q", values)
        values.byteswap()
    return values.tobytes()


class McapFile:
    """One MCAP file on ``stream`` (opened for binary writing; written from its start)."""

    def __init__(self, stream: BinaryIO, *, library: str = "rocoma-can",
                 chunk_size: int = 1024 * 1024, profile: str = "") -> None:
        import zstandard  # optional (extra record): only where a file is written
        self._compress = zstandard.ZstdCompressor().compress
        self._stream = stream
        self._chunk_size = chunk_size
        self._written = 0
        self._schemas: list[bytes] = []
        self._channels: list[bytes] = []
        self._chunk_indexes: list[bytes] = []
        self._counts: dict[int, int] = {}
        self._count = 0
        self._first = self._last = 0
        self._chunk = bytearray()
        self._index: dict[int, array[int]] = {}  # per channel: time, offset, time, ...
        self._chunk_first = self._chunk_last = -1
        self._finished = False
        self._failed: BaseException | None = None  # a write that failed: no more writes
        self._write(MAGIC + _record(HEADER, _string(profile) + _string(library)))

    def schema(self, name: str, encoding: str, data: bytes) -> int:
        """A new schema's id (1, 2, ...; 0 is "no schema")."""
        self._check_open()
        number = len(self._schemas) + 1
        if number > _MAX_ID:
            raise ValueError(f"an MCAP file has at most {_MAX_ID} schemas")
        record = _record(SCHEMA, _U16.pack(number) + _string(name) + _string(encoding)
                         + _U32.pack(len(data)) + data)
        self._schemas.append(record)
        self._chunk += record
        return number

    def channel(self, topic: str, message_encoding: str, schema: int,
                metadata: Mapping[str, str] | None = None) -> int:
        """A new channel's id (1, 2, ..., as the ``mcap`` package's writer numbers them)
        for messages under ``schema`` (0: none)."""
        self._check_open()
        number = len(self._channels) + 1
        if number > _MAX_ID or not 0 <= schema <= len(self._schemas):
            raise ValueError(f"MCAP channel {topic}: {number} channels (at most {_MAX_ID}), "
                             f"schema {schema} of {len(self._schemas)}")
        pairs = b"".join(_string(k) + _string(v) for k, v in (metadata or {}).items())
        record = _record(CHANNEL, _U16.pack(number) + _U16.pack(schema) + _string(topic)
                         + _string(message_encoding) + _U32.pack(len(pairs)) + pairs)
        self._channels.append(record)
        self._counts[number] = 0
        self._chunk += record
        return number

    def add(self, channel: int, log_time: int, data: bytes) -> None:
        """One message (its publish time: ``log_time``)."""
        self.add_many(channel, (log_time,), (data,))

    def add_many(self, channel: int, log_times: Sequence[int],
                 datas: Sequence[bytes]) -> None:
        """Messages on one channel, each at its log time (nanoseconds; its publish time
        too), each ``bytes``; the chunk is finished (compressed, written) once it holds
        ``chunk_size`` bytes. A call refused (a time out of range, data that is not bytes)
        adds none of its messages; a chunk that cannot be written raises the stream's
        error after they went in (the file takes nothing more)."""
        if not log_times:
            return
        self._check_open()
        if channel not in self._counts:
            raise ValueError(f"MCAP channel {channel} was never registered")
        if len(datas) != len(log_times):
            raise ValueError(f"{len(log_times)} log times for {len(datas)} messages")
        first, last = min(log_times), max(log_times)
        if first < 0 or last >= 1 << 64:
            raise ValueError(f"MCAP log times are 0..2**64-1 ns, got {first}..{last}")
        chunk, pack = self._chunk, _MESSAGE.pack
        index = self._index.get(channel)
        created = index is None
        if index is None:
            index = self._index[channel] = array("Q")
        size, entries, sequence = len(chunk), len(index), self._counts[channel]
        try:
            for log_time, data in zip(log_times, datas):
                index.append(log_time)
                index.append(len(chunk))
                chunk += pack(MESSAGE, _MESSAGE_FIXED + len(data), channel,
                              sequence & 0xFFFFFFFF, log_time, log_time)
                chunk += data
                sequence += 1
        except BaseException:  # (TypeError: data that is not bytes) the chunk as it was
            del chunk[size:]
            del index[entries:]
            if created:
                del self._index[channel]
            raise
        if self._chunk_first < 0:
            self._chunk_first, self._chunk_last = first, last
        else:
            self._chunk_first = min(self._chunk_first, first)
            self._chunk_last = max(self._chunk_last, last)
        if not self._count:
            self._first, self._last = first, last
        else:
            self._first, self._last = min(self._first, first), max(self._last, last)
        self._count += len(log_times)
        self._counts[channel] = sequence
        if len(chunk) >= self._chunk_size:
            self._finish_chunk()

    def _check_open(self) -> None:
        """ValueError if the file takes nothing more: finished, or a write failed."""
        if self._failed is not None:
            raise ValueError(f"an earlier write of this MCAP file failed "
                             f"({self._failed}): nothing more can be written to it")
        if self._finished:
            raise ValueError("the MCAP file is finished: no message can follow its footer")

    def _write(self, data: bytes) -> None:
        """Bytes to the stream; offsets are counted here (the stream is written from its
        start), so after a write that failed (and may have written part) the file takes
        no more."""
        try:
            view = memoryview(data)
            while view:  # (a buffered file writes all at once; a raw one may not)
                written = self._stream.write(view)
                if written is None:  # a non-blocking raw stream that is full
                    raise BlockingIOError(errno.EAGAIN, "the MCAP file's stream would block")
                view = view[written:]
        except BaseException as exc:
            self._failed = exc
            raise
        self._written += len(data)

    def _finish_chunk(self) -> None:
        """The chunk so far, compressed, and its message indexes. Schema and channel
        records with no message after them go into the data section as they are: a chunk
        without messages would have an index of times 0-0, which a viewer takes for the
        recording's start (1970)."""
        records = bytes(self._chunk)
        if not records:
            return
        if self._chunk_first < 0:
            self._write(records)
            self._chunk = bytearray()
            return
        first, last = self._chunk_first, self._chunk_last
        compressed = self._compress(records)
        body = (_U64.pack(first) + _U64.pack(last) + _U64.pack(len(records))
                + _U32.pack(zlib.crc32(records)) + _string("zstd")
                + _U64.pack(len(compressed)) + compressed)
        start = self._written
        chunk = _record(CHUNK, body)
        indexes, offsets = [], []
        position = start + len(chunk)
        for channel, pairs in self._index.items():
            raw = _pairs(pairs)
            record = _record(MESSAGE_INDEX, _U16.pack(channel) + _U32.pack(len(raw)) + raw)
            offsets.append(_U16.pack(channel) + _U64.pack(position))
            position += len(record)
            indexes.append(record)
        index_bytes = b"".join(indexes)
        self._write(chunk + index_bytes)
        offset_map = b"".join(offsets)
        self._chunk_indexes.append(_record(CHUNK_INDEX, (
            _U64.pack(first) + _U64.pack(last) + _U64.pack(start) + _U64.pack(len(chunk))
            + _U32.pack(len(offset_map)) + offset_map + _U64.pack(len(index_bytes))
            + _string("zstd") + _U64.pack(len(compressed)) + _U64.pack(len(records)))))
        self._chunk = bytearray()
        self._index = {}
        self._chunk_first = self._chunk_last = -1

    def finish(self) -> None:
        """The last chunk, the summary and the footer; the stream is left open (its
        owner flushes and closes it). Once only; after a write that failed, nothing (that
        failure was raised where it happened, and a summary needs right offsets)."""
        if self._finished or self._failed is not None:
            return
        self._finish_chunk()
        self._write(_record(DATA_END, _U32.pack(0)))
        summary_start = self._written
        groups = []
        counts = b"".join(_U16.pack(c) + _U64.pack(n) for c, n in self._counts.items())
        statistics = [_record(STATISTICS, (
            _U64.pack(self._count) + _U16.pack(len(self._schemas))
            + _U32.pack(len(self._channels)) + _U32.pack(0) + _U32.pack(0)
            + _U32.pack(len(self._chunk_indexes)) + _U64.pack(self._first)
            + _U64.pack(self._last) + _U32.pack(len(counts)) + counts))]
        for opcode, records in ((SCHEMA, self._schemas), (CHANNEL, self._channels),
                                (STATISTICS, statistics), (CHUNK_INDEX, self._chunk_indexes)):
            if records:
                data = b"".join(records)
                groups.append(struct.pack("<BQ", opcode, self._written) + _U64.pack(len(data)))
                self._write(data)
        offsets_start = self._written
        self._write(b"".join(_record(SUMMARY_OFFSET, group) for group in groups))
        self._write(_record(FOOTER, _U64.pack(summary_start) + _U64.pack(offsets_start)
                            + _U32.pack(0)) + MAGIC)
        self._finished = True
