"""BusReader (drivers/link/bus.py): the one reader of a bus, or of several buses on one thread.

What must hold with several buses on one thread: each frame reaches the listeners of its
own bus, in order; a bus that fails is reported to its own listeners only, read again at
the ``retry`` pace (not in a busy loop), and the other buses are still served; a listener
that raises does not end reading. ``readers_for`` shares a thread only where one thread
can wait on all the buses (in-process or SocketCAN), and the hardware's buses get their
listeners attached before the first frame is read. ``drain_now`` (the control loop's read)
hands over what waits on the caller's thread, and the thread stands by while drains come.
"""
from __future__ import annotations

import inspect
import threading
import time
import uuid

import can
import pytest
from fixtures.driver_rig import VIRTUAL

from rocoma_can.drivers.link.bus import (
    DRAIN_STANDBY,
    BusReader,
    CanopenBus,
    readers_for,
    start_reading,
)

POLL = inspect.signature(BusReader).parameters["poll"].default
#: a frame handed from one thread to another on a loaded machine, plus one idle poll
WAIT = VIRTUAL.stall + POLL
RETRY = 0.02
BATCH = 256  # frames one read takes (frame_io.FrameReader.read's default limit)


class Seen(can.Listener):
    def __init__(self, fail_on: int | None = None) -> None:
        self.frames: list[int] = []
        self.errors: list[Exception] = []
        self._fail_on = fail_on
        self.got = threading.Event()

    def on_message_received(self, msg: can.Message) -> None:
        if msg.arbitration_id == self._fail_on:
            raise RuntimeError("listener bug")
        self.frames.append(msg.arbitration_id)
        self.got.set()

    def on_error(self, exc: Exception) -> None:
        self.errors.append(exc)


def _wait(predicate, what: str) -> None:
    deadline = time.monotonic() + WAIT
    while not predicate():
        assert time.monotonic() < deadline, what
        time.sleep(0.001)


def _threads(name: str) -> int:
    return sum(t.name == name for t in threading.enumerate())


@pytest.fixture
def inproc_buses():
    """``make(n, interface="inproc")`` -> (senders, receivers) on n fresh channels."""
    opened: list[can.BusABC] = []

    def make(n: int, interface: str = "inproc"):
        base = f"reader-{uuid.uuid4().hex[:8]}"
        pairs = [tuple(can.Bus(interface=interface, channel=f"{base}-{k}", ignore_config=True)
                       for _ in range(2)) for k in range(n)]
        opened.extend(b for pair in pairs for b in pair)
        return [p[0] for p in pairs], [p[1] for p in pairs]

    yield make
    for bus in opened:
        bus.shutdown()


def _frame(cob_id: int) -> can.Message:
    return can.Message(arbitration_id=cob_id, is_extended_id=False)


def test_one_thread_hands_each_bus_its_own_frames_in_order(inproc_buses):
    senders, receivers = inproc_buses(3)
    seen = [Seen() for _ in receivers]
    before = _threads("three buses")
    reader = BusReader(receivers[0], (seen[0],),
                       more=[(b, (s,)) for b, s in zip(receivers[1:], seen[1:])],
                       name="three buses")
    try:
        assert _threads("three buses") - before == 1
        for n in range(20):
            senders[n % 3].send(_frame(0x100 + n))
        _wait(lambda: sum(len(s.frames) for s in seen) == 20, "20 frames")
        for k, s in enumerate(seen):
            assert s.frames == [0x100 + n for n in range(k, 20, 3)]
    finally:
        reader.stop()
    assert not reader.alive


def test_a_failed_bus_is_reported_to_its_own_listeners_and_the_others_are_served(
        inproc_buses):
    senders, receivers = inproc_buses(2)
    seen = [Seen(), Seen()]
    reader = BusReader(receivers[0], (seen[0],), more=[(receivers[1], (seen[1],))],
                       retry=RETRY)
    try:
        receivers[0].shutdown()
        _wait(lambda: seen[0].errors, "the failure reported")
        assert isinstance(seen[0].errors[0], can.CanOperationError)
        before, start, sent = len(seen[0].errors), time.monotonic(), 0
        while time.monotonic() - start < 10 * RETRY:  # a flood on the other bus meanwhile
            senders[1].send(_frame(0x181))
            sent += 1
            time.sleep(0.001)
        _wait(lambda: len(seen[1].frames) == sent, "the other bus's frames")
        _wait(lambda: len(seen[0].errors) > before, "the failed bus read again")
        elapsed = time.monotonic() - start
        # read again every RETRY, not once per frame on the other bus
        assert len(seen[0].errors) - before <= elapsed / RETRY + 2, (sent, elapsed)
        assert seen[1].errors == [] and reader.alive
    finally:
        reader.stop()


def test_a_burst_longer_than_one_read_is_handed_over_without_more_traffic(inproc_buses):
    senders, receivers = inproc_buses(2)
    seen = [Seen(), Seen()]
    count = 3 * BATCH + 5
    for n in range(count):  # queued before the reader exists
        senders[0].send(_frame(0x100 + n % 0x80))
    reader = BusReader(receivers[0], (seen[0],), more=[(receivers[1], (seen[1],))])
    try:
        _wait(lambda: len(seen[0].frames) == count, f"{count} frames")
    finally:
        reader.stop()


def test_a_listener_that_raises_is_told_and_reading_goes_on(inproc_buses):
    senders, receivers = inproc_buses(2)
    bad, good = Seen(fail_on=0x181), Seen()
    reader = BusReader(receivers[0], (bad, good), more=[(receivers[1], ())])
    try:
        senders[0].send(_frame(0x181))
        senders[0].send(_frame(0x182))
        _wait(lambda: good.frames == [0x181, 0x182], "both frames to the good listener")
        assert bad.frames == [0x182] and len(bad.errors) == 1
        assert reader.listener_errors == 1 and reader.alive
    finally:
        reader.stop()


def test_readers_for_shares_a_thread_only_where_it_can(inproc_buses):
    _, inproc = inproc_buses(3)
    _, virtual = inproc_buses(2, "virtual")
    for buses, expected in ((inproc, 1), (virtual, 2), (inproc[:1], 1)):
        readers = readers_for([(bus, ()) for bus in buses])
        try:
            assert len(readers) == expected
            assert [b for r in readers for b in r.buses] == list(buses)
        finally:
            for r in readers:
                r.stop()
    with pytest.raises(ValueError, match="SocketCAN or all in-process"):
        BusReader(virtual[0], (), more=[(virtual[1], ())])


def test_the_hardware_buses_read_nothing_until_every_listener_is_attached(inproc_buses):
    senders, receivers = inproc_buses(2)
    buses = [CanopenBus(bus, read=False) for bus in receivers]
    seen = [Seen(), Seen()]
    try:
        senders[0].send(_frame(0x701))  # queued before anyone reads
        for cb, s in zip(buses, seen):
            cb.add_listener(s)
        start_reading(buses)
        assert buses[0].reader is buses[1].reader is not None
        senders[1].send(_frame(0x702))
        _wait(lambda: seen[0].frames == [0x701] and seen[1].frames == [0x702], "both frames")
    finally:
        for cb in buses:
            cb.close()


class Threads(can.Listener):
    """Which thread handed over each frame."""

    def __init__(self) -> None:
        self.by: list[tuple[int, str]] = []

    def on_message_received(self, msg: can.Message) -> None:
        self.by.append((msg.arbitration_id, threading.current_thread().name))


class LockFreeThreads(Threads):
    lock_free = True  # as the hardware's receiver: drain_now may call it


@pytest.mark.parametrize("buses", [1, 2])
def test_drain_now_hands_over_on_the_callers_thread_and_the_thread_stands_by(
        inproc_buses, buses):
    """The control loop reads its buses itself at the start of each cycle: what waits is
    handed, in order, to the listeners that take no lock, on its thread, before drain_now
    returns; the other listeners (canopen's, which notify Conditions: the loop must not
    wait for a lock) get the same frames, in order, on the reader's thread. While drains
    come the reader thread reads nothing itself (no frame is handed over twice); once they
    stop, it reads again within DRAIN_STANDBY."""
    senders, receivers = inproc_buses(buses)
    quick = [LockFreeThreads() for _ in receivers]
    other = [Threads() for _ in receivers]
    reader = BusReader(receivers[0], (quick[0], other[0]),
                       more=[(b, (q, o)) for b, q, o in zip(receivers[1:], quick[1:],
                                                              other[1:])],
                       name="drained")
    try:
        _wait(reader.drain_now, "a drain (not while the thread hands over)")
        for n in range(10):
            for k, sender in enumerate(senders):
                sender.send(_frame(0x100 * (k + 1) + n))
            sent = time.monotonic()
            if reader.drain_now():  # (the thread's meanwhile only after a long stall here)
                assert all(q.by[-1][0] == 0x100 * (k + 1) + n for k, q in enumerate(quick))
                assert reader.received_until(receivers[-1]) >= sent
            time.sleep(DRAIN_STANDBY / 10)
        sent_ids = [[0x100 * (k + 1) + n for n in range(10)] for k in range(buses)]
        _wait(lambda: [[cob for cob, _ in o.by] for o in other] == sent_ids,
              "the locking listeners get every frame, in order")
        for q, o in zip(quick, other):
            assert [cob for cob, _ in q.by] == [cob for cob, _ in o.by]
            assert sum(name == "MainThread" for _, name in q.by) >= 5
            assert all(name == "drained" for _, name in o.by)
        for sender in senders:  # no more drains: the thread reads them
            sender.send(_frame(0x7FF))
        _wait(lambda: all(q.by and q.by[-1] == (0x7FF, "drained") for q in quick),
              "the thread reads again")
    finally:
        reader.stop()


def test_drain_now_leaves_an_interface_it_cannot_read_apart_to_the_thread(inproc_buses):
    """python-can's virtual bus has nothing to wait on apart from its read: drain_now
    reads nothing (False) and the thread goes on handing frames over."""
    senders, receivers = inproc_buses(1, "virtual")
    seen = Threads()
    reader = BusReader(receivers[0], (seen,), name="virtual reader")
    try:
        assert not reader.drain_now()
        senders[0].send(_frame(0x123))
        _wait(lambda: seen.by == [(0x123, "virtual reader")], "the thread hands it over")
    finally:
        reader.stop()


def test_drained_frames_reach_the_other_listeners_in_order_at_any_drain_pace(inproc_buses):
    """A loop slower than DRAIN_STANDBY drains between the thread's own reads: frames the
    drain queued for the listeners that take locks come to them before any frame the
    thread reads later (canopen's SDO client must see its answers in order)."""
    senders, receivers = inproc_buses(1)
    quick, other = LockFreeThreads(), Threads()
    reader = BusReader(receivers[0], (quick, other), name="slow loop")
    try:
        for n in range(40):
            senders[0].send(_frame(0x100 + n))
            if n % 3 == 0:
                reader.drain_now()
                time.sleep(1.5 * DRAIN_STANDBY)  # the thread reads again meanwhile
            else:
                time.sleep(0.001)
        _wait(lambda: len(other.by) == 40, "every frame to the other listener")
        assert [cob for cob, _ in other.by] == [0x100 + n for n in range(40)]
        assert [cob for cob, _ in quick.by] == [0x100 + n for n in range(40)]
    finally:
        reader.stop()


def test_a_bus_that_fails_while_the_loop_drains_is_reported_and_the_others_served(
        inproc_buses):
    """Draining must not hide a failed bus: the thread stops standing by, reads it, tells
    its listeners (on_error, bus_errors) and moves its received_until on, so the
    hardware's heartbeat deadlines on it still pass; the other bus is still drained."""
    senders, receivers = inproc_buses(2)
    seen = [Seen(), LockFreeThreads()]
    seen[0].lock_free = True  # type: ignore[attr-defined]  # drained on this thread
    reader = BusReader(receivers[0], (seen[0],), more=[(receivers[1], (seen[1],))],
                       retry=RETRY, name="one fails")
    try:
        _wait(reader.drain_now, "a first drain")
        receivers[0].shutdown()  # its interface is gone: reads raise
        failed_at = time.monotonic()
        end = failed_at + WAIT
        n = 0
        while time.monotonic() < end and not (seen[0].errors and reader.bus_errors and
                                               reader.received_until(receivers[0])
                                               > failed_at):
            senders[1].send(_frame(0x200 + n % 100))
            n += 1
            reader.drain_now()
            time.sleep(0.001)
        assert seen[0].errors and reader.bus_errors > 0
        assert reader.received_until(receivers[0]) > failed_at
        before = len(seen[1].by)
        senders[1].send(_frame(0x7FF))
        _wait(lambda: reader.drain_now() and len(seen[1].by) > before, "bus 1 served")
    finally:
        reader.stop()
