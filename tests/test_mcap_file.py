"""The bulk MCAP writer (record/mcap_file.py), read back by the ``mcap`` package's readers:
every message where its indexes say, the summary's counts, CRCs that check, a full disk
said at the write."""
from __future__ import annotations

import errno
import io
import json
import struct
from pathlib import Path

import pytest

pytest.importorskip("mcap")  # the extra record: installed by the test command
import zstandard  # noqa: E402 - with mcap
from mcap.reader import make_reader  # noqa: E402
from mcap.records import Chunk, ChunkIndex, MessageIndex  # noqa: E402
from mcap.stream_reader import StreamReader  # noqa: E402

from rocoma_can.record.mcap_file import McapFile  # noqa: E402
from rocoma_can.record.trace import McapWriter, read_messages  # noqa: E402

T0 = 1_700_000_000 * 10**9


def _file(path: Path, chunk_size: int) -> tuple[list[tuple[int, int, bytes]], McapFile]:
    """Two channels' messages over many chunks, a third channel registered mid-file."""
    stream = path.open("wb")
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
    stream.close()
    return sent, f


def test_every_message_is_read_back_in_order_with_its_channel_and_time(tmp_path: Path) -> None:
    path = tmp_path / "m.mcap"
    sent, _ = _file(path, chunk_size=4096)
    with path.open("rb") as stream:
        reader = make_reader(stream)
        topics = {c.id: c.topic for c in reader.get_summary().channels.values()}
        got = [(topics[channel.id], message.log_time, message.data)
               for _, channel, message in reader.iter_messages(log_time_order=True)]
    expected = sorted(((["/a", "/b", "/c"][c], t, d) for c, t, d in sent),
                      key=lambda m: m[1])
    assert got == expected
    with path.open("rb") as stream:  # read through, not by the summary
        through = [(r.log_time, r.data) for r in StreamReader(stream, validate_crcs=True).records
                   if type(r).__name__ == "Message"]
    assert sorted(through) == sorted((t, d) for _, t, d in sent)


def test_the_summary_counts_and_the_indexes_point_at_their_records(tmp_path: Path) -> None:
    path = tmp_path / "m.mcap"
    sent, _ = _file(path, chunk_size=4096)
    raw = path.read_bytes()
    with path.open("rb") as stream:
        summary = make_reader(stream).get_summary()
    assert summary is not None and summary.statistics is not None
    stats = summary.statistics
    assert stats.message_count == len(sent)
    assert stats.channel_message_counts == {c: sum(1 for s in sent if s[0] == c)
                                            for c in (0, 1, 2)}
    assert (stats.message_start_time, stats.message_end_time) == \
        (min(t for _, t, _ in sent), max(t for _, t, _ in sent))
    assert stats.chunk_count == len(summary.chunk_indexes) > 10
    assert summary.channels[2].metadata == {"note": "late"}
    # each chunk index: the chunk record where it says, and each channel's message index
    # record; each index entry: a message record at that offset of the chunk, at that time
    records = list(StreamReader(io.BytesIO(raw), validate_crcs=True, emit_chunks=True).records)
    chunks = [r for r in records if isinstance(r, Chunk)]
    indexes = [r for r in records if isinstance(r, MessageIndex)]
    assert len(chunks) == len(summary.chunk_indexes)
    seen = 0
    for ci, chunk in zip(summary.chunk_indexes, chunks):
        assert isinstance(ci, ChunkIndex)
        assert raw[ci.chunk_start_offset] == 0x06
        for channel, offset in ci.message_index_offsets.items():
            assert raw[offset] == 0x07
            assert struct.unpack_from("<H", raw, offset + 9)[0] == channel
        data = zstandard.ZstdDecompressor().decompress(chunk.data,
                                                       max_output_size=chunk.uncompressed_size)
        for index in indexes:
            if index.channel_id not in ci.message_index_offsets:
                continue
            for log_time, offset in index.records:
                if offset >= len(data) or data[offset] != 0x05:
                    continue  # another chunk's index
                channel, _, at = struct.unpack_from("<HIQ", data, offset + 9)
                if channel == index.channel_id and at == log_time:
                    seen += 1
    assert seen == len(sent)


class _FullDisk(io.RawIOBase):
    """A stream that takes ``room`` bytes, then says ENOSPC."""

    def __init__(self, room: int) -> None:
        self.room = room

    def writable(self) -> bool:
        return True

    def write(self, data: object) -> int:
        size = len(data)  # type: ignore[arg-type]
        if size > self.room:
            raise OSError(errno.ENOSPC, "No space left on device")
        self.room -= size
        return size


def test_a_full_disk_is_said_at_the_write_that_does_not_fit() -> None:
    f = McapFile(_FullDisk(2000), chunk_size=1000)  # type: ignore[arg-type]
    channel = f.channel("/a", "json", 0)
    with pytest.raises(OSError) as raised:
        for k in range(1000):
            f.add(channel, T0 + k, b'{"k":1}')
    assert raised.value.errno == errno.ENOSPC
    assert k < 200  # at the chunk that did not fit, not at the end
    with pytest.raises(ValueError, match="earlier write .* failed"):
        f.finish()  # offsets after a cut write would point anywhere: no summary on them


def test_a_message_on_a_channel_never_registered_is_refused() -> None:
    f = McapFile(io.BytesIO())
    with pytest.raises(ValueError, match="channel 3 was never registered"):
        f.add(3, T0, b"{}")


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


def test_messages_after_the_footer_or_without_their_times_are_refused() -> None:
    f = McapFile(io.BytesIO())
    channel = f.channel("/a", "json", 0)
    with pytest.raises(ValueError, match="2 log times for 1 messages"):
        f.add_many(channel, [T0, T0 + 1], [b"{}"])
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
