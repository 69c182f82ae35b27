"""tests/fixtures/recorder.py: the frame recorder on python-can's virtual bus: it sees what every
other bus on the channel sends, in order, and its waits are bounded."""
from __future__ import annotations

import threading

import can
import pytest
from fixtures.recorder import FrameRecorder


def frame(cob_id: int, *data: int) -> can.Message:
    return can.Message(arbitration_id=cob_id, data=bytes(data), is_extended_id=False)


def test_records_every_frame_from_every_sender_in_order(bus_factory, frame_recorder):
    recorder = frame_recorder()
    first, second, receiver = bus_factory(), bus_factory(), bus_factory()
    for i in range(20):
        (first if i % 2 == 0 else second).send(frame(0x180 + i % 2, i))

    got = recorder.wait_for_count(20, timeout=5)

    assert [f.cob_id for f in got] == [0x180, 0x181] * 10
    assert [f.data for f in got] == [bytes([i]) for i in range(20)]
    times = [f.time for f in got]
    assert times == sorted(times)
    # The recorder listens on a bus of its own: other receivers still get every frame.
    assert [receiver.recv(timeout=5).data[0] for _ in range(20)] == list(range(20))


def test_filters_marks_and_counts(virtual_bus, frame_recorder):
    recorder = frame_recorder()
    virtual_bus.send(frame(0x701, 0x00))
    virtual_bus.send(frame(0x201, 1))
    recorder.wait_for_count(2, timeout=5)
    mark = recorder.mark()
    virtual_bus.send(frame(0x201, 2))
    virtual_bus.send(frame(0x081))
    recorder.wait_for(lambda f: f.cob_id == 0x081, timeout=5, since=mark)

    assert recorder.cob_ids() == [0x701, 0x201, 0x201, 0x081]
    assert recorder.cob_ids(since=mark) == [0x201, 0x081]
    assert recorder.count(0x201) == 2
    assert recorder.count(0x201, since=mark) == 1
    assert [f.data for f in recorder.frames(cob_id={0x701, 0x081})] == [b"\x00", b""]
    assert recorder.count(where=lambda f: f.data[:1] == b"\x02") == 1
    recorder.clear()
    assert recorder.frames() == []


def test_wait_for_returns_a_frame_that_arrives_later(virtual_bus, frame_recorder):
    recorder = frame_recorder()
    sender = threading.Timer(0.05, virtual_bus.send, args=(frame(0x581, 0x60),))
    sender.start()
    try:
        found = recorder.wait_for(lambda f: f.cob_id == 0x581, timeout=5)
    finally:
        sender.join(5)
    assert found.data == b"\x60"


def test_waits_are_bounded_and_say_what_arrived(virtual_bus, frame_recorder):
    recorder = frame_recorder()
    virtual_bus.send(frame(0x181, 7))
    recorder.wait_for_count(1, timeout=5)

    with pytest.raises(TimeoutError, match=r"recorded 1 frame.*id=0x181"):
        recorder.wait_for(lambda f: f.cob_id == 0x999, timeout=0.05)
    with pytest.raises(TimeoutError, match=r"1 of 3 frames"):
        recorder.wait_for_count(3, timeout=0.05, cob_id=0x181)


def test_stop_ends_recording_and_leaves_a_borrowed_bus_open(bus_factory):
    sender = bus_factory()
    recorder = FrameRecorder(bus_factory(), owns_bus=False).start()
    sender.send(frame(0x100))
    recorder.wait_for_count(1, timeout=5)
    recorder.stop()
    sender.send(frame(0x101))
    assert recorder.cob_ids() == [0x100]
    # The bus was not the recorder's to close: it still receives.
    assert recorder.bus.recv(timeout=5).arbitration_id == 0x101
