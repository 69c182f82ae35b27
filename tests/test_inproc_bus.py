"""The in-process bus (``interface: inproc``): what a CAN bus between threads must keep.

Every endpoint on a channel sees every other endpoint's frames, in send order, each frame
as it was when sent (the sender re-fills its pre-allocated frames at once); a reader nobody
serves drops its oldest frames and counts them; a send never blocks; a shut-down bus fails
loudly and wakes a reader waiting on it.
"""
from __future__ import annotations

import threading
import uuid

import can
import pytest

from rocoma_can.drivers.frame_io import FrameReader, FrameWriter
from rocoma_can.drivers.inproc import InProcessBus


@pytest.fixture
def channel() -> str:
    return f"inproc-{uuid.uuid4().hex[:8]}"


def _open(channel: str, **kwargs: object) -> can.BusABC:
    return can.Bus(interface="inproc", channel=channel, ignore_config=True, **kwargs)


def _frame(cob_id: int, data: bytes = b"") -> can.Message:
    return can.Message(arbitration_id=cob_id, data=data, is_extended_id=False)


def test_python_can_opens_it_by_name_and_every_other_endpoint_gets_each_frame(channel):
    a, b, c = (_open(channel) for _ in range(3))
    try:
        assert isinstance(a, InProcessBus)
        for n in range(5):
            a.send(_frame(0x181 + n, bytes([n])))
        for rx in (b, c):
            got = [rx.recv(1.0) for _ in range(5)]
            assert [(m.arbitration_id, bytes(m.data)) for m in got] == \
                [(0x181 + n, bytes([n])) for n in range(5)]
            assert all(m.is_rx and m.channel == channel for m in got)
        assert a.recv(0.0) is None  # not its own frames
    finally:
        for bus in (a, b, c):
            bus.shutdown()


def test_a_frame_refilled_after_send_arrives_as_it_was_sent(channel):
    tx, rx = _open(channel), _open(channel)
    try:
        frame = can.Message(arbitration_id=0x201, data=bytearray(8), is_extended_id=False)
        for n in range(3):
            frame.data[0] = n
            tx.send(frame)
        assert [rx.recv(1.0).data[0] for _ in range(3)] == [0, 1, 2]
    finally:
        tx.shutdown()
        rx.shutdown()


def test_own_frames_only_when_asked(channel):
    bus = _open(channel, receive_own_messages=True)
    try:
        bus.send(_frame(0x080))
        assert bus.recv(1.0).arbitration_id == 0x080
    finally:
        bus.shutdown()


def test_a_full_receive_queue_drops_the_oldest_and_counts_them(channel):
    tx, rx = _open(channel), InProcessBus(channel, rx_queue_size=4)
    try:
        for n in range(10):
            tx.send(_frame(0x100 + n))  # never blocks, whatever the reader does
        assert rx.rx_dropped == 6
        assert [rx.recv(0.0).arbitration_id for _ in range(4)] == [0x106, 0x107, 0x108, 0x109]
        assert rx.recv(0.0) is None
    finally:
        tx.shutdown()
        rx.shutdown()


def test_a_waiting_reader_wakes_for_a_frame_from_another_thread(channel):
    tx, rx = _open(channel), _open(channel)
    got: list[can.Message | None] = []
    try:
        reader = threading.Thread(target=lambda: got.append(rx.recv(10.0)))
        reader.start()
        tx.send(_frame(0x701, b"\x05"))
        reader.join(10.0)
        assert not reader.is_alive()
        assert got[0] is not None and got[0].arbitration_id == 0x701
    finally:
        tx.shutdown()
        rx.shutdown()


def test_frame_reader_takes_a_batch_and_keeps_filters(channel):
    tx, rx = _open(channel), _open(channel)
    try:
        rx.set_filters([{"can_id": 0x180, "can_mask": 0x780}])  # TPDO1 of any node
        for cob_id in (0x181, 0x201, 0x182, 0x701, 0x183):
            tx.send(_frame(cob_id))
        batch = FrameReader(rx).read(1.0, limit=10)
        assert [m.arbitration_id for m in batch] == [0x181, 0x182, 0x183]
        assert FrameReader(rx).read(0.01) == []
    finally:
        tx.shutdown()
        rx.shutdown()


def test_an_fd_bus_says_so_and_fd_frames_keep_their_flags(channel):
    tx, rx = _open(channel, fd=True), _open(channel, fd=True)
    try:
        assert tx.protocol == can.CanProtocol.CAN_FD
        FrameWriter(tx, fd=True).send(0x181, bytes(range(12)))
        msg = rx.recv(1.0)
        assert msg.is_fd and msg.bitrate_switch and bytes(msg.data) == bytes(range(12))
    finally:
        tx.shutdown()
        rx.shutdown()


def test_shutdown_fails_sends_wakes_a_reader_and_leaves_the_others_working(channel):
    a, b, c = (_open(channel) for _ in range(3))
    woke = threading.Event()

    def read() -> None:
        try:
            b.recv(10.0)
        except can.CanOperationError:
            pass
        woke.set()
    try:
        reader = threading.Thread(target=read)
        reader.start()
        b.shutdown()
        reader.join(10.0)
        assert woke.is_set()
        with pytest.raises(can.CanOperationError, match="shut down"):
            b.send(_frame(0x080))
        with pytest.raises(can.CanOperationError, match="shut down"):
            b.recv(0.0)
        a.send(_frame(0x080))
        assert c.recv(1.0).arbitration_id == 0x080
    finally:
        for bus in (a, b, c):
            bus.shutdown()


def test_bad_queue_size_is_refused(channel):
    with pytest.raises(ValueError, match="rx_queue_size"):
        InProcessBus(channel, rx_queue_size=0)
