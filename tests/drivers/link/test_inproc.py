"""drivers/link/inproc.py, frame_io.py: the in-process bus (``interface: inproc``): what a CAN bus
between threads must keep.

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
from fixtures.driver_rig import VIRTUAL

from rocoma_can.drivers.link.frame_io import BusSelector, FrameReader, FrameWriter
from rocoma_can.drivers.link.inproc import InProcessBus


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


def test_exact_cob_id_filters_take_only_their_standard_frames(channel):
    """A CANopen master's filters (one COB-ID each, mask 0x7FF, standard) are checked as
    a set: the same frames pass as python-can's own check would let through, an extended
    frame with the same number does not, and other filters still work as python-can's."""
    tx, rx = _open(channel), _open(channel)
    try:
        rx.set_filters([{"can_id": c, "can_mask": 0x7FF, "extended": False}
                        for c in (0x181, 0x281, 0x701)])
        for cob_id in (0x181, 0x201, 0x281, 0x182, 0x701):
            tx.send(_frame(cob_id))
        tx.send(can.Message(arbitration_id=0x181, data=b"", is_extended_id=True))
        assert [m.arbitration_id for m in FrameReader(rx).read(1.0, limit=10)] == \
            [0x181, 0x281, 0x701]
        rx.set_filters([{"can_id": 0x180, "can_mask": 0x780}])  # not one COB-ID: as python-can
        for cob_id in (0x181, 0x201, 0x182):
            tx.send(_frame(cob_id))
        assert [m.arbitration_id for m in FrameReader(rx).read(1.0, limit=10)] == [0x181, 0x182]
    finally:
        tx.shutdown()
        rx.shutdown()


class _CountingEvent(threading.Event):
    def __init__(self) -> None:
        super().__init__()
        self.sets = 0

    def set(self) -> None:
        self.sets += 1
        super().set()


def test_held_wakeups_queue_a_burst_and_wake_its_reader_once_at_the_release(channel):
    """hold_wakeups: the frames of a burst are queued (in order, at once) but their reader
    is woken at the release, once; a frame another thread sends meanwhile wakes it at
    once; holds nest; a release without a hold is a bug and says so."""
    tx, rx = _open(channel), _open(channel)
    woken = _CountingEvent()
    try:
        rx.add_wakeup(woken)
        tx.hold_wakeups()
        tx.hold_wakeups()
        for cob_id in (0x201, 0x301, 0x080):
            tx.send(_frame(cob_id))
        assert rx.pending and woken.sets == 0
        tx.release_wakeups()
        assert woken.sets == 0  # still held once
        other = threading.Thread(target=lambda: tx.send(_frame(0x701, b"\x05")))
        other.start()
        other.join(10.0)
        assert woken.sets == 1  # another thread's frame: at once
        woken.clear()
        tx.release_wakeups()
        assert woken.sets == 2
        assert [m.arbitration_id for m in FrameReader(rx).read(0.0, limit=10)] == \
            [0x201, 0x301, 0x080, 0x701]
        with pytest.raises(RuntimeError, match="without hold_wakeups"):
            tx.release_wakeups()
        woken.clear()  # as a selector does before it waits again
        tx.send(_frame(0x202))  # not held: at once
        assert woken.sets == 3
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


def test_one_thread_waits_on_several_buses_and_reads_the_one_with_frames(channel):
    """frame_io.BusSelector: what a simulated segment group and a BusReader of several
    buses wait with."""
    budget = VIRTUAL.stall  # a thread handing a frame to another on a loaded machine
    retry = budget  # no stall between two calls of this test outlasts it
    tx = [_open(f"{channel}-{k}") for k in range(3)]
    rx = [_open(f"{channel}-{k}") for k in range(3)]
    selector = BusSelector(rx, retry=retry)
    try:
        assert selector.wait(0.01) == []
        woke: list[list[int]] = []
        waiter = threading.Thread(target=lambda: woke.append(selector.wait(budget)))
        waiter.start()
        tx[1].send(_frame(0x181, b"\x01"))
        waiter.join(budget)
        assert woke == [[1]]  # the bus with a frame waiting, not the others
        assert [m.arbitration_id for m in FrameReader(rx[1]).read(0.0)] == [0x181]
        assert selector.wait(0.01) == []  # handled: nothing new
        for n in range(5):  # more than one read takes: the rest is still found
            tx[0].send(_frame(0x200 + n))
        assert selector.wait(0.0) == [0]
        assert len(FrameReader(rx[0]).read(0.0, limit=3)) == 3
        assert selector.wait(0.0) == [0]
        assert len(FrameReader(rx[0]).read(0.0)) == 2
        rx[2].shutdown()  # a bus going away wakes the waiter: its read reports it
        assert selector.wait(budget) == [2]
        with pytest.raises(can.CanOperationError, match="shut down"):
            FrameReader(rx[2]).read(0.0)
        selector.failed(2)  # left out for ``retry``, then offered once more
        assert selector.failing(2) and selector.wait(0.0) == []
        assert selector.wait(retry + budget) == [2] and not selector.failing(2)
        selector.close()
        tx[0].send(_frame(0x182))
        # still found by looking, without a wake-up (and the shut bus, until failed again)
        assert selector.wait(0.01) == [0, 2]
    finally:
        for bus in (*tx, *rx):
            bus.shutdown()


def test_buses_one_thread_cannot_wait_on_together_are_refused(channel):
    buses = [can.Bus(interface="virtual", channel=channel, ignore_config=True),
             _open(channel)]
    try:
        assert not BusSelector.supports(buses)
        assert not BusSelector.supports([])
        with pytest.raises(ValueError, match="all of them are SocketCAN or all in-process"):
            BusSelector(buses, retry=0.05)
    finally:
        for bus in buses:
            bus.shutdown()


def test_bad_queue_size_is_refused(channel):
    with pytest.raises(ValueError, match="rx_queue_size"):
        InProcessBus(channel, rx_queue_size=0)


def test_a_copy_carries_every_field_python_can_has(channel):
    """The copy is made field by field, without Message.__init__ (it costs ~4x as much): a
    field a newer python-can adds would otherwise be missing from every received frame."""
    tx, rx = _open(channel), _open(channel, fd=True)
    try:
        sent = can.Message(arbitration_id=0x1ABCDE, data=bytes(range(12)), is_extended_id=True,
                           is_fd=True, bitrate_switch=True, error_state_indicator=True)
        tx.send(sent)
        got = rx.recv(1.0)
        fields = [f for f in can.Message.__slots__ if f != "__weakref__"]
        assert {"timestamp", "channel", "is_rx"} < set(fields)
        for field in fields:
            assert hasattr(got, field), field
        for field in set(fields) - {"timestamp", "channel", "is_rx"}:
            assert getattr(got, field) == getattr(sent, field), field
        assert got.is_rx and got.channel == channel and got.timestamp > 0
        assert got.equals(sent, timestamp_delta=None, check_channel=False,
                          check_direction=False)
        assert got.data is not sent.data
    finally:
        tx.shutdown()
        rx.shutdown()
