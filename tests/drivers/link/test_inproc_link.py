"""The link between two processes' in-process channels (drivers/link/inproc_link.py): what the
demo's simulator process and the loop's process rely on.

Both ends run in this process here, each joined to channels of its own name (the link
matches channels by position, not name), over a real socket pair; the demo's own test
(tests/cli/demo/test_demo_drives.py) runs the other end in a child process.
"""
from __future__ import annotations

import socket
import threading
import time
import uuid
from collections.abc import Iterator

import can
import pytest

from rocoma_can.drivers.link.inproc_link import FRAME, InProcessLink

WAIT = 2.0  # s for a frame to cross: a bound, never expected to be reached
TIMEOUT = 20.0  # s: a socket timeout a send would wait out if the link kept it


def _open(channel: str) -> can.BusABC:
    return can.Bus(interface="inproc", channel=channel, ignore_config=True)


@pytest.fixture
def pair() -> Iterator[tuple[list[str], list[str], InProcessLink, InProcessLink]]:
    """Channels a0, a1 here joined to b0, b1 'there'; both links with receive threads."""
    tag = uuid.uuid4().hex[:8]
    a_channels, b_channels = [f"a{k}-{tag}" for k in range(2)], [f"b{k}-{tag}" for k in range(2)]
    sa, sb = socket.socketpair(socket.AF_UNIX, socket.SOCK_SEQPACKET)
    la = InProcessLink(sa, a_channels).start()
    lb = InProcessLink(sb, b_channels).start()
    yield a_channels, b_channels, la, lb
    la.close()
    lb.close()
    sa.close()
    sb.close()


@pytest.fixture
def unstarted() -> Iterator[tuple[InProcessLink, InProcessLink, can.BusABC, can.BusABC]]:
    """(la, lb, a bus on la's channel, a bus on lb's): one channel each side, and neither
    link reads by itself (the caller's ``receive`` does)."""
    tag = uuid.uuid4().hex[:8]
    sa, sb = socket.socketpair(socket.AF_UNIX, socket.SOCK_SEQPACKET)
    la, lb = InProcessLink(sa, [f"a-{tag}"]), InProcessLink(sb, [f"b-{tag}"])
    tx, rx = _open(f"a-{tag}"), _open(f"b-{tag}")
    yield la, lb, tx, rx
    for bus in (tx, rx):
        bus.shutdown()
    la.close()
    lb.close()
    sa.close()
    sb.close()


def test_every_field_of_a_frame_crosses_to_the_channel_at_the_same_position(pair):
    a, b, _, lb = pair
    tx, rx0, rx1 = _open(a[1]), _open(b[0]), _open(b[1])
    try:
        sent = [
            can.Message(arbitration_id=0x181, data=b"\x01\x02", is_extended_id=False),
            can.Message(arbitration_id=0x1ABCDEF, is_remote_frame=True, dlc=6),
            can.Message(arbitration_id=0x201, data=bytes(range(64)), is_extended_id=False,
                        is_fd=True, bitrate_switch=True, error_state_indicator=True),
            can.Message(arbitration_id=0x20000040, is_error_frame=True, data=bytes(8)),
            can.Message(arbitration_id=0x000, data=b"", is_extended_id=False),
        ]
        for msg in sent:
            tx.send(msg)
        got = [rx1.recv(WAIT) for _ in sent]
        fields = [f for f in can.Message.__slots__ if f != "__weakref__"]
        for g, s in zip(got, sent):
            assert g is not None
            for field in fields:
                assert hasattr(g, field), field
            assert g.equals(s, timestamp_delta=None, check_channel=False,
                            check_direction=False), (g, s)
            assert g.is_rx and g.channel == b[1] and g.timestamp > 0
            assert isinstance(g.data, bytearray)
        assert rx0.recv(0.05) is None  # the other channel got nothing
        assert lb.rx_frames == len(sent) and lb.rx_bad == 0
    finally:
        for bus in (tx, rx0, rx1):
            bus.shutdown()


def test_both_directions_and_nothing_comes_back_to_its_sender(pair):
    a, b, _, _ = pair
    here, there = _open(a[0]), _open(b[0])
    try:
        here.send(can.Message(arbitration_id=0x80, data=b"", is_extended_id=False))
        assert there.recv(WAIT).arbitration_id == 0x80
        there.send(can.Message(arbitration_id=0x701, data=b"\x05", is_extended_id=False))
        assert here.recv(WAIT).arbitration_id == 0x701
        assert here.recv(0.1) is None and there.recv(0.1) is None  # no echo either way
    finally:
        here.shutdown()
        there.shutdown()


def test_a_held_burst_on_several_buses_crosses_as_one_datagram_in_order(pair):
    """The control loop's write: its buses' wake-ups held, frames on each, released: one
    datagram (one system call, one wake-up of the other process) for all of them."""
    a, b, la, _ = pair
    tx = [_open(c) for c in a]
    rx = [_open(c) for c in b]
    try:
        before = la.tx_datagrams
        for bus in tx:
            bus.hold_wakeups()
        for n in range(6):
            tx[n % 2].send(can.Message(arbitration_id=0x200 + n, data=bytes([n]),
                                       is_extended_id=False))
        assert la.tx_datagrams == before  # nothing written while held
        for bus in tx:
            bus.release_wakeups()
        assert la.tx_datagrams == before + 1
        for k in range(2):
            assert [rx[k].recv(WAIT).arbitration_id for _ in range(3)] == \
                [0x200 + n for n in range(k, 6, 2)]
    finally:
        for bus in (*tx, *rx):
            bus.shutdown()


def test_each_threads_frames_arrive_in_the_order_it_sent_them(pair):
    a, b, _, _ = pair
    rx = _open(b[0])
    senders = [_open(a[0]) for _ in range(3)]
    per_thread = 200

    def send(k: int) -> None:
        for n in range(per_thread):
            senders[k].send(can.Message(arbitration_id=0x100 * (k + 1), data=n.to_bytes(2, "big"),
                                        is_extended_id=False))
    threads = [threading.Thread(target=send, args=(k,)) for k in range(3)]
    try:
        for t in threads:
            t.start()
        for t in threads:
            t.join(WAIT)
        got: dict[int, list[int]] = {}
        for _ in range(3 * per_thread):
            msg = rx.recv(WAIT)
            got.setdefault(msg.arbitration_id, []).append(int.from_bytes(msg.data, "big"))
        assert got == {0x100 * (k + 1): list(range(per_thread)) for k in range(3)}
    finally:
        for bus in (rx, *senders):
            bus.shutdown()


def test_a_full_socket_drops_and_counts_and_a_send_never_waits(unstarted):
    """The other side reads nothing (a stalled process): sends go on, each at once; what
    the socket cannot take is counted, and what it took arrives once it is read."""
    la, lb, tx, rx = unstarted
    frame = can.Message(arbitration_id=0x181, data=bytes(8), is_extended_id=False)
    sends = 0
    while la.tx_dropped == 0 and sends < 1_000_000:
        tx.send(frame)
        sends += 1
    assert la.tx_dropped == 1 and la.tx_datagrams == sends - 1
    for _ in range(10):
        tx.send(frame)
    assert la.tx_dropped == 11
    assert lb.receive(WAIT) == sends - 1  # what was taken is handed over
    assert rx.recv(0.0) is not None
    tx.send(frame)  # room again
    assert la.tx_dropped == 11 and lb.receive(WAIT) == 1


def test_the_other_end_closing_ends_the_link_and_says_so():
    tag = uuid.uuid4().hex[:8]
    sa, sb = socket.socketpair(socket.AF_UNIX, socket.SOCK_SEQPACKET)
    ended = threading.Event()
    la = InProcessLink(sa, [f"stays-{tag}"], on_close=ended.set).start()
    lb = InProcessLink(sb, [f"goes-{tag}"])
    try:
        lb.close()  # as a process that ends: its end shut down
        sb.close()
        assert ended.wait(WAIT) and la.closed.is_set()
        assert la.receive(0.0) == 0  # and a caller's receive says so at once
    finally:
        la.close()
        sa.close()


def test_a_socket_with_a_timeout_is_made_blocking_so_a_send_never_waits():
    """A default timeout set anywhere in the process would make CPython wait on a full
    socket despite MSG_DONTWAIT, and end a receive thread's read by raising."""
    tag = uuid.uuid4().hex[:8]
    previous = socket.getdefaulttimeout()
    socket.setdefaulttimeout(TIMEOUT)
    try:
        sa, sb = socket.socketpair(socket.AF_UNIX, socket.SOCK_SEQPACKET)
    finally:
        socket.setdefaulttimeout(previous)
    la = InProcessLink(sa, [f"t-{tag}"])
    tx = _open(f"t-{tag}")
    try:
        assert sa.gettimeout() is None
        frame = can.Message(arbitration_id=0x181, data=bytes(8), is_extended_id=False)
        while la.tx_dropped == 0:  # fills the socket; each send returns at once
            tx.send(frame)
        t0 = time.monotonic()
        tx.send(frame)
        assert la.tx_dropped == 2
        assert time.monotonic() - t0 < TIMEOUT / 2  # not the timeout's wait
    finally:
        tx.shutdown()
        la.close()
        sa.close()
        sb.close()


def test_receive_on_the_callers_thread_waits_at_most_its_timeout_then_takes_all_waiting(
        unstarted):
    _, lb, tx, rx = unstarted
    t0 = time.monotonic()
    assert lb.receive(0.05) == 0
    assert time.monotonic() - t0 >= 0.05
    for n in range(3):  # three sends, three datagrams
        tx.send(can.Message(arbitration_id=0x300 + n, data=b"", is_extended_id=False))
    assert lb.receive(WAIT) == 3
    assert [rx.recv(0.0).arbitration_id for _ in range(3)] == [0x300, 0x301, 0x302]


def test_a_datagram_that_is_not_one_is_counted_and_the_link_goes_on():
    tag = uuid.uuid4().hex[:8]
    sa, sb = socket.socketpair(socket.AF_UNIX, socket.SOCK_SEQPACKET)
    lb = InProcessLink(sb, [f"dst-{tag}"])
    rx = _open(f"dst-{tag}")
    try:
        good = FRAME.pack(0, 0x181, 0, 1, 1) + b"\x07"
        sa.send(good + FRAME.pack(5, 0x182, 0, 0, 0))  # a channel the link does not join
        sa.send(good + FRAME.pack(0, 0x183, 0, 8, 8) + b"\x00")  # data cut short
        sa.send(b"\x00\x01")  # not even a header
        sa.send(good)
        assert lb.receive(WAIT) == 4
        assert lb.rx_bad == 3
        assert [rx.recv(0.0).arbitration_id for _ in range(3)] == [0x181] * 3
        assert rx.recv(0.0) is None
    finally:
        rx.shutdown()
        lb.close()
        sa.close()
        sb.close()


def test_a_link_joins_one_to_256_channels_each_once():
    sa, sb = socket.socketpair(socket.AF_UNIX, socket.SOCK_SEQPACKET)
    try:
        with pytest.raises(ValueError, match="1 to 256 channels, got 0"):
            InProcessLink(sa, [])
        # twice: what one end hands over the other would send back across
        with pytest.raises(ValueError, match=r"each channel once, got \['x', 'y', 'x'\]"):
            InProcessLink(sa, ["x", "y", "x"])
    finally:
        sa.close()
        sb.close()
