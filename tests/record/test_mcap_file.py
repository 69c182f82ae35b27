"""The bulk MCAP writer (record/mcap_file.py): read back by the ``mcap`` package's readers
(by the summary, and through with CRC checks), and its layout checked record by record by
a parser of the spec's own here, so a field no Python reader looks at (an index's offset or
length, the footer's) is checked too; a full disk said at the write."""
from __future__ import annotations

import errno
import io
import json
import struct
import zlib
from pathlib import Path
from typing import Any

import pytest

pytest.importorskip("mcap")  # the extra record: installed by the test command
import zstandard  # noqa: E402 - with mcap
from mcap.reader import make_reader  # noqa: E402
from mcap.stream_reader import StreamReader  # noqa: E402

from rocoma_can.record.mcap_file import MAGIC, McapFile  # noqa: E402
from rocoma_can.record.trace import McapWriter, read_messages  # noqa: E402

T0 = 1_700_000_000 * 10**9
Sent = list[tuple[int, int, bytes]]  # (channel, log time, data)


def _file(path: Path, chunk_size: int) -> Sent:
    """Two channels' messages over many chunks, a third channel registered mid-file."""
    with path.open("wb") as stream:
        f = McapFile(stream, chunk_size=chunk_size)
        schema = f.schema("s", "jsonschema", b'{"type":"object"}')
        a, b = f.channel("/a", "json", schema), f.channel("/b", "json", schema)
        sent = []
        for k in range(0, 3000, 10):
            times = [T0 + 1000 * (k + i) for i in range(10)]
            datas = [json.dumps({"k": k + i}).encode() for i in range(10)]
            f.add_many(a if k % 20 else b, times, datas)
            sent += [(a if k % 20 else b, t, d) for t, d in zip(times, datas)]
            if k == 1500:
                c = f.channel("/c", "json", schema, {"note": "late"})
                f.add(c, T0 + 1000 * k + 1, b'{"late":true}')
                sent.append((c, T0 + 1000 * k + 1, b'{"late":true}'))
        f.finish()
    return sent


def _records(raw: bytes) -> list[tuple[int, int, bytes]]:
    """(offset, opcode, body) of every record between the magics, read by the spec."""
    assert raw[:8] == MAGIC and raw[-8:] == MAGIC
    found, at = [], 8
    while at < len(raw) - 8:
        opcode, length = struct.unpack_from("<BQ", raw, at)
        found.append((at, opcode, raw[at + 9:at + 9 + length]))
        at += 9 + length
    assert at == len(raw) - 8  # every byte in a record
    return found


def _string(body: bytes, at: int) -> tuple[str, int]:
    (n,) = struct.unpack_from("<I", body, at)
    return body[at + 4:at + 4 + n].decode(), at + 4 + n


def _chunk_messages(body: bytes) -> tuple[tuple[int, int], dict[int, tuple[int, int, int]]]:
    """A chunk record's (start, end) times and its messages by offset in its records:
    (channel, sequence, log time), publish time checked equal to the log time."""
    start, end, size, crc = struct.unpack_from("<QQQI", body)
    compression, at = _string(body, 28)
    assert compression == "zstd"
    (length,) = struct.unpack_from("<Q", body, at)
    records = zstandard.ZstdDecompressor().decompress(body[at + 8:at + 8 + length],
                                                      max_output_size=size)
    assert len(records) == size and zlib.crc32(records) == crc
    messages, k = {}, 0
    while k < len(records):
        opcode, n = struct.unpack_from("<BQ", records, k)
        if opcode == 0x05:
            channel, sequence, log_time, publish = struct.unpack_from("<HIQQ", records, k + 9)
            assert publish == log_time
            messages[k] = (channel, sequence, log_time)
        k += 9 + n
    return (start, end), messages


def test_every_message_is_read_back_in_order_with_its_channel_and_time(tmp_path: Path) -> None:
    path = tmp_path / "m.mcap"
    sent = _file(path, chunk_size=4096)
    with path.open("rb") as stream:
        reader = make_reader(stream)
        summary = reader.get_summary()
        assert summary is not None
        topics = {c.id: c.topic for c in summary.channels.values()}
        got = [(topics[channel.id], message.log_time, message.publish_time, message.data)
               for _, channel, message in reader.iter_messages(log_time_order=True)]
    expected = sorted(((topics[c], t, t, d) for c, t, d in sent), key=lambda m: m[1])
    assert got == expected
    assert topics == {1: "/a", 2: "/b", 3: "/c"}  # numbered from 1, as mcap's writer does
    with path.open("rb") as stream:  # read through, not by the summary, CRCs checked
        through = [(r.log_time, r.data) for r in StreamReader(stream, validate_crcs=True).records
                   if type(r).__name__ == "Message"]
    assert sorted(through) == sorted((t, d) for _, t, d in sent)


def _check_layout(raw: bytes) -> dict[str, Any]:
    """Every index and offset of the file checked against the records it points at; what
    the summary says, for the caller to compare with what was written."""
    records = _records(raw)
    at_offset = {offset: (opcode, body) for offset, opcode, body in records}
    # footer -> summary offsets -> groups of their opcode
    _, opcode, body = records[-1]
    assert opcode == 0x02
    summary_start, offsets_start, _ = struct.unpack_from("<QQI", body)
    assert at_offset[offsets_start][0] == 0x0E
    groups = {}
    for _, opcode, body in records:
        if opcode == 0x0E:
            group, start, length = struct.unpack_from("<BQQ", body)
            inside = [r for r in records if start <= r[0] < start + length]
            assert inside and {r[1] for r in inside} == {group}
            assert inside[-1][0] + 9 + len(inside[-1][2]) == start + length
            groups[group] = inside
    assert summary_start == min(r[0] for g in groups.values() for r in g)
    data_end = [r for r in records if r[1] == 0x0F]
    assert len(data_end) == 1 and data_end[0][0] + 9 + 4 == summary_start
    # each chunk index: its chunk (times, sizes, length), then exactly its message indexes,
    # each entry a message record of its channel at its time in that chunk
    entries = 0
    for _, _, body in groups.get(0x08, []):
        first, last, start, length, map_len = struct.unpack_from("<QQQQI", body)
        index_offsets = dict(struct.iter_unpack("<HQ", body[36:36 + map_len]))
        index_length, = struct.unpack_from("<Q", body, 36 + map_len)
        compression, at = _string(body, 44 + map_len)
        compressed, uncompressed = struct.unpack_from("<QQ", body, at)
        opcode, chunk = at_offset[start]
        assert opcode == 0x06 and 9 + len(chunk) == length and compression == "zstd"
        (times, messages) = _chunk_messages(chunk)
        assert times == (first, last)
        assert (first, last) == (min(m[2] for m in messages.values()),
                                 max(m[2] for m in messages.values()))
        assert struct.unpack_from("<Q", chunk, 16)[0] == uncompressed
        assert len(chunk) - 8 - (28 + 4 + len(compression)) == compressed
        following = [r for r in records if start + length <= r[0] < start + length
                     + index_length]
        assert {r[1] for r in following} == {0x07}
        assert following[-1][0] + 9 + len(following[-1][2]) == start + length + index_length
        assert {r[0] for r in following} == set(index_offsets.values())
        for offset, _, index in following:
            channel, n = struct.unpack_from("<HI", index)
            assert index_offsets[channel] == offset
            for log_time, at in struct.iter_unpack("<QQ", index[6:6 + n]):
                assert messages[at][0] == channel and messages[at][2] == log_time
                entries += 1
        assert entries and sum(1 for _ in messages) <= entries
    stats_body = groups[0x0B][0][2]
    count, schemas, channels, _, _, chunks, first, last, map_len = \
        struct.unpack_from("<QHIIIIQQI", stats_body)
    return {"count": count, "schemas": schemas, "channels": channels, "chunks": chunks,
            "chunk_indexes": len(groups.get(0x08, [])), "first": first, "last": last,
            "per_channel": dict(struct.iter_unpack("<HQ", stats_body[46:46 + map_len])),
            "entries": entries}


def test_every_index_and_offset_points_at_its_record(tmp_path: Path) -> None:
    path = tmp_path / "m.mcap"
    sent = _file(path, chunk_size=4096)
    said = _check_layout(path.read_bytes())
    assert said["count"] == said["entries"] == len(sent)
    assert said["chunks"] == said["chunk_indexes"] > 10
    assert (said["schemas"], said["channels"]) == (1, 3)
    assert said["per_channel"] == {c: sum(1 for s in sent if s[0] == c) for c in (1, 2, 3)}
    assert (said["first"], said["last"]) == (min(t for _, t, _ in sent),
                                             max(t for _, t, _ in sent))
    with path.open("rb") as stream:
        summary = make_reader(stream).get_summary()
    assert summary is not None and summary.channels[3].metadata == {"note": "late"}


def test_a_flight_records_channels_one_after_the_other_keep_their_times(
        tmp_path: Path) -> None:
    """A flight record writes each channel's whole window in turn (the rows, then each
    bus's frames): times go back between calls, and each chunk's times and the file's
    are still the least and greatest of what they hold."""
    path = tmp_path / "f.mcap"
    sent: Sent = []
    with path.open("wb") as stream:
        f = McapFile(stream, chunk_size=2048)
        channels = [f.channel(f"/{name}", "json", 0) for name in ("rows", "bus0", "bus1")]
        for k, channel in enumerate(channels):
            times = [T0 + 10_000 * i + 2 - k for i in range(500)]  # the last one first
            for first in range(0, 500, 32):
                part = times[first:first + 32]
                f.add_many(channel, part, [b"{}"] * len(part))
                sent += [(channel, t, b"{}") for t in part]
        f.finish()
    said = _check_layout(path.read_bytes())
    assert said["count"] == said["entries"] == len(sent) == 1500
    assert (said["first"], said["last"]) == (T0, T0 + 10_000 * 499 + 2)


class _FullDisk(io.RawIOBase):
    """A stream that takes ``room`` bytes, then says ENOSPC."""

    def __init__(self, room: int) -> None:
        self.room = room
        self.taken = 0

    def writable(self) -> bool:
        return True

    def write(self, data: object) -> int:
        size = len(memoryview(data))  # type: ignore[arg-type]
        if size > self.room:
            raise OSError(errno.ENOSPC, "No space left on device")
        self.room -= size
        self.taken += size
        return size


def test_a_full_disk_is_said_at_the_write_that_does_not_fit() -> None:
    disk = _FullDisk(2000)
    f = McapFile(disk, chunk_size=1000)  # type: ignore[arg-type]
    channel = f.channel("/a", "json", 0)
    with pytest.raises(OSError) as raised:
        for k in range(1000):
            f.add(channel, T0 + k, b'{"k":1}')
    assert raised.value.errno == errno.ENOSPC
    assert k < 200  # at the chunk that did not fit, not at the end
    taken = disk.taken
    f.finish()  # said already; a summary on offsets after a cut write would point anywhere
    with pytest.raises(ValueError, match="earlier write .* failed"):
        f.add(channel, T0, b"{}")
    assert disk.taken == taken


def test_a_summary_that_does_not_fit_is_said_once() -> None:
    probe = io.BytesIO()
    f = McapFile(probe)
    f.add(f.channel("/a", "json", 0), T0, b"{}")
    f.finish()
    disk = _FullDisk(len(probe.getvalue()) - 20)  # room for all but the footer
    f = McapFile(disk)  # type: ignore[arg-type]
    f.add(f.channel("/a", "json", 0), T0, b"{}")
    with pytest.raises(OSError):
        f.finish()
    f.finish()  # the failure was raised; nothing more is written
    assert disk.taken == len(probe.getvalue()) - 8 - 29  # all but the footer and magic


class _Trickle(io.RawIOBase):
    """A raw stream that takes at most 7 bytes a call (as a pipe or socket may)."""

    def __init__(self) -> None:
        self.data = bytearray()

    def writable(self) -> bool:
        return True

    def write(self, data: object) -> int:
        part = bytes(memoryview(data)[:7])  # type: ignore[arg-type]
        self.data += part
        return len(part)


def test_a_stream_that_takes_part_of_a_write_gets_the_rest() -> None:
    whole, trickle = io.BytesIO(), _Trickle()
    for stream in (whole, trickle):
        f = McapFile(stream, chunk_size=100)  # type: ignore[arg-type]
        channel = f.channel("/a", "json", 0)
        for k in range(50):
            f.add(channel, T0 + k, b'{"k":%d}' % k)
        f.finish()
    assert bytes(trickle.data) == whole.getvalue()


class _WouldBlock(_Trickle):
    """A non-blocking raw stream that is full after its first write."""

    def write(self, data: object) -> int | None:  # type: ignore[override]
        if self.data:
            return None
        return super().write(data)


def test_a_stream_that_would_block_is_an_error_not_a_loop() -> None:
    with pytest.raises(BlockingIOError):
        McapFile(_WouldBlock()).finish()  # type: ignore[arg-type]


def test_bad_input_is_refused_before_anything_is_written() -> None:
    f = McapFile(io.BytesIO())
    with pytest.raises(ValueError, match="channel 3 was never registered"):
        f.add(3, T0, b"{}")
    channel = f.channel("/a", "json", 0)
    with pytest.raises(ValueError, match="2 log times for 1 messages"):
        f.add_many(channel, [T0, T0 + 1], [b"{}"])
    with pytest.raises(ValueError, match="schema 2 of 0"):
        f.channel("/b", "json", 2)
    for _ in range(0xFFFF - 1):
        f.channel("/many", "json", 0)
    with pytest.raises(ValueError, match="at most 65535"):
        f.channel("/one too many", "json", 0)
    f.finish()
    with pytest.raises(ValueError, match="finished"):
        f.add(channel, T0, b"{}")


def test_a_call_that_raises_adds_none_of_its_messages(tmp_path: Path) -> None:
    path = tmp_path / "m.mcap"
    with path.open("wb") as stream:
        f = McapFile(stream)
        channel = f.channel("/a", "json", 0)
        f.add_many(channel, [T0, T0 + 1], [b"1", b"2"])
        with pytest.raises(TypeError):
            f.add_many(channel, [T0 + 2, T0 + 3], [b"3", "not bytes"])  # type: ignore[list-item]
        with pytest.raises(ValueError, match="0..2"):
            f.add_many(channel, [T0 + 4, -1], [b"5", b"6"])
        f.add(channel, T0 + 7, b"8")
        f.finish()
    with path.open("rb") as stream:
        reader = make_reader(stream)
        got = [(m.log_time - T0, m.sequence, m.data)
               for _, _, m in reader.iter_messages(log_time_order=True)]
        stats = reader.get_summary().statistics
    assert got == [(0, 0, b"1"), (1, 1, b"2"), (7, 2, b"8")]  # numbered per channel
    assert stats is not None and stats.message_count == 3
    assert (stats.message_start_time, stats.message_end_time) == (T0, T0 + 7)


def test_channels_without_messages_make_no_chunk_of_time_zero(tmp_path: Path) -> None:
    """A viewer's timeline spans every chunk index's times: one of 0-0 would start it in
    1970. Channels registered after the last message (a bus with no frame yet) and a file
    with no message at all are still read, their channels in the summary."""
    path = tmp_path / "m.mcap"
    with path.open("wb") as stream:
        f = McapFile(stream, chunk_size=64)
        a = f.channel("/a", "json", 0)
        f.add(a, T0, b"{}")
        f.channel("/late", "json", 0)
        f.finish()
    empty = tmp_path / "empty.mcap"
    with empty.open("wb") as stream:
        McapWriter(stream, ["j1"]).finish()
    for file, count in ((path, 1), (empty, 0)):
        with file.open("rb") as stream:
            reader = make_reader(stream)
            summary = reader.get_summary()
            assert summary is not None
            assert all(ci.message_start_time >= T0 for ci in summary.chunk_indexes)
            assert sum(1 for _ in reader.iter_messages()) == count
        with file.open("rb") as stream:
            topics = {r.topic for r in StreamReader(stream, validate_crcs=True).records
                      if type(r).__name__ == "Channel"}
        assert ("/late" in topics) == (file == path)
    assert "/rocoma/cycle" in {c.topic for c in summary.channels.values()}  # (the empty one)


def test_the_trace_writer_keeps_every_frame_with_its_fields(tmp_path: Path) -> None:
    path = tmp_path / "t.mcap"
    frames = [(1.7e9 + k * 1e-4, 0x181 + k % 12, 64 * (k % 2), f"{k:016X}") for k in range(500)]
    with path.open("wb") as stream:
        writer = McapWriter(stream, ["j1"])
        writer.frames("arm", frames)
        writer.finish()
    got = [(t, m) for topic, t, m in read_messages(str(path)) if topic == "/can/arm"]
    assert [t for t, _ in got] == [int(f[0] * 1e9) for f in frames]
    assert [m["id"] for _, m in got] == [f[1] for f in frames]
    assert [m["data"] for _, m in got] == [f[3].lower() for f in frames]
    assert [m["sent"] for _, m in got] == [bool(f[2] & 64) for f in frames]
    assert all(m["dlc"] == 8 for _, m in got)
