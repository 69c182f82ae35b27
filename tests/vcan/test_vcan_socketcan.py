"""drivers/link/bus.py, frame_io.py: real SocketCAN on vcan0/vcan1 (tests/vcan/ is marked `vcan`:
run through tools/vcan-run).

Inside user-mode-linux system calls are slow, so these tests use low cycle rates and assert
counts and orderings, never speed.
"""
from __future__ import annotations

import time

import can

from rocoma_can.drivers.link.bus import open_bus


def frame(cob_id: int, *data: int, extended: bool = False) -> can.Message:
    return can.Message(arbitration_id=cob_id, data=bytes(data), is_extended_id=extended)


def socketcan(bus_factory, channel: str = "vcan0") -> can.BusABC:
    return bus_factory(channel, "socketcan")


def test_two_sockets_exchange_frames_in_order(bus_factory, frame_recorder):
    recorder = frame_recorder(interface="socketcan")
    a, b = socketcan(bus_factory), socketcan(bus_factory)

    for i in range(30):
        a.send(frame(0x201, i, 0xAA))
    received = [b.recv(timeout=5) for _ in range(30)]
    for i in range(30):
        b.send(frame(0x181, i))
    replies = [a.recv(timeout=5) for _ in range(30)]

    assert [(m.arbitration_id, m.data[0]) for m in received] == [(0x201, i) for i in range(30)]
    assert [m.data[0] for m in replies] == list(range(30))
    assert all(m.channel == "vcan0" and not m.is_extended_id for m in received)
    recorder.wait_for_count(60, timeout=10)
    assert recorder.cob_ids() == [0x201] * 30 + [0x181] * 30


def test_frame_flags_survive_the_kernel(bus_factory):
    a, b = socketcan(bus_factory), socketcan(bus_factory)
    a.send(frame(0x1ABCDE01, 1, 2, 3, extended=True))
    a.send(can.Message(arbitration_id=0x601, is_remote_frame=True, dlc=8, is_extended_id=False))

    extended, remote = b.recv(timeout=5), b.recv(timeout=5)

    assert (extended.arbitration_id, extended.is_extended_id, bytes(extended.data)) == (
        0x1ABCDE01, True, b"\x01\x02\x03")
    assert (remote.arbitration_id, remote.is_remote_frame, remote.dlc) == (0x601, True, 8)


def test_can_fd_frames_with_bit_rate_switching_pass_vcan(bus_factory):
    """tools/vcan-run gives vcan0/vcan1 an MTU of 72, so FD sockets exchange FD frames: the
    frames an FD bus's manager and simulated drives send (FrameWriter) arrive as FD frames
    with BRS through the batched reader (FrameReader), and classic sockets still work."""
    from rocoma_can.drivers.link.frame_io import FrameReader, FrameWriter
    sender = bus_factory("vcan1", "socketcan", fd=True)
    receiver = bus_factory("vcan1", "socketcan", fd=True)
    FrameWriter(sender, fd=True).send(0x181, bytes(range(8)))
    FrameWriter(sender).send(0x701, b"\x05")  # a classic frame on the FD bus
    batch: list[can.Message] = []
    reader = FrameReader(receiver)
    deadline = time.monotonic() + 5
    while len(batch) < 2 and time.monotonic() < deadline:
        batch += reader.read(0.5)
    fd_frame, classic = batch
    assert (fd_frame.arbitration_id, fd_frame.is_fd, fd_frame.bitrate_switch) == (0x181, True,
                                                                                  True)
    assert bytes(fd_frame.data) == bytes(range(8))
    assert (classic.arbitration_id, classic.is_fd, bytes(classic.data)) == (0x701, False,
                                                                            b"\x05")


def test_a_long_fd_pdo_passes_vcan_whole(bus_factory):
    """A PDO over 8 bytes (pdo_bytes on an FD bus) goes out at its FD length and arrives
    with that length as its DLC, which is what the receive check compares with the
    mapping's padded size (pdo_layout: 13 bytes mapped, a 16-byte frame)."""
    from rocoma_can.drivers.link.frame_io import FrameReader, FrameWriter
    from rocoma_can.drivers.plan.config import DriveConfig
    from rocoma_can.drivers.plan.pdo_layout import layout_for
    (rpdo,) = layout_for(DriveConfig("j", 1, 4096, 1.0, modes=("csp", "csv", "cst"),
                                     pdo_bytes=64)).rpdos
    sender = bus_factory("vcan1", "socketcan", fd=True)
    receiver = bus_factory("vcan1", "socketcan", fd=True)
    data = rpdo.codec.pack(0x0F, 8, -5, 6, -7)
    FrameWriter(sender, fd=True).send(rpdo.cob_id, data)
    batch: list[can.Message] = []
    reader = FrameReader(receiver)
    deadline = time.monotonic() + 5
    while not batch and time.monotonic() < deadline:
        batch += reader.read(0.5)
    (got,) = batch
    assert (got.arbitration_id, got.is_fd, got.bitrate_switch, got.dlc) == (0x201, True, True,
                                                                            rpdo.size)
    assert rpdo.size == 16 and rpdo.codec.unpack(bytes(got.data)) == (0x0F, 8, -5, 6, -7)


def test_vcan1_is_a_separate_bus(bus_factory, frame_recorder):
    recorder0 = frame_recorder("vcan0", "socketcan")
    recorder1 = frame_recorder("vcan1", "socketcan")
    on0, on1 = socketcan(bus_factory, "vcan0"), socketcan(bus_factory, "vcan1")

    on1.send(frame(0x111))
    on0.send(frame(0x100))
    recorder0.wait_for(lambda f: f.cob_id == 0x100, timeout=5)
    recorder1.wait_for(lambda f: f.cob_id == 0x111, timeout=5)

    # vcan0's recorder had the vcan1 frame queued first if the two were one bus.
    assert recorder0.cob_ids() == [0x100]
    assert recorder1.cob_ids() == [0x111]


def test_kernel_bcm_sends_periodically_and_in_sequence(bus_factory, frame_recorder):
    recorder = frame_recorder(interface="socketcan")
    sender, marker = socketcan(bus_factory), socketcan(bus_factory)

    task = sender.send_periodic([frame(0x280, n) for n in range(3)], period=0.02)  # 50 Hz
    try:
        recorder.wait_for_count(9, timeout=10, cob_id=0x280)
        task.modify_data([frame(0x280, 0x10 + n) for n in range(3)])
        recorder.wait_for_count(6, timeout=10, cob_id=0x280, where=lambda f: f.data[0] >= 0x10)
    finally:
        task.stop()
    # The recorder reads on a thread of its own and may not have read a frame the kernel
    # sent just before the stop (one was taken for "after the stop" once in the guest): the
    # mark comes after a marker frame sent now, which the kernel queues behind them.
    marker.send(frame(0x7FE))
    recorder.wait_for(lambda f: f.cob_id == 0x7FE, timeout=5)
    stopped = recorder.mark()
    time.sleep(0.1)  # five periods: room for a frame the kernel should no longer send
    marker.send(frame(0x7FF))
    recorder.wait_for(lambda f: f.cob_id == 0x7FF, timeout=5, since=stopped)

    data = [f.data[0] for f in recorder.frames(0x280)]
    old = [d for d in data if d < 0x10]
    new = [d for d in data if d >= 0x10]
    assert data == old + new, "a frame with the old data came after the modification"
    # The kernel cycles through the frames in the order given, before and after modify_data.
    assert old[:9] == [0, 1, 2] * 3
    assert [d - 0x10 for d in new[:6]] in ([0, 1, 2] * 2, [1, 2, 0] * 2, [2, 0, 1] * 2)
    assert recorder.cob_ids(since=stopped) == [0x7FF], "BCM frames after task.stop()"


def test_kernel_bcm_with_duration_sends_an_exact_count(bus_factory, frame_recorder):
    recorder = frame_recorder(interface="socketcan")
    sender, marker = socketcan(bus_factory), socketcan(bus_factory)

    task = sender.send_periodic(frame(0x380, 1), period=0.02, duration=0.2)  # 10 frames
    try:
        recorder.wait_for_count(10, timeout=10, cob_id=0x380)
        time.sleep(0.1)  # five periods in which an eleventh frame would show
        marker.send(frame(0x7FF))
        recorder.wait_for(lambda f: f.cob_id == 0x7FF, timeout=5)
    finally:
        task.stop()

    assert recorder.count(0x380) == 10


def test_a_reader_that_lags_loses_no_frames(bus_factory):
    """Every socket rocoma-can opens (drivers.link.bus.open_bus: the node's, the CLI's, the
    simulator's, recorders) holds thousands of frames unread. The kernel's default buffer
    holds a few hundred (~200 KiB at ~1 KiB a frame), under a second of a busy bus for a
    reader the guest or a loaded host stalls; a frame that meets a full socket is dropped,
    and for SDO one lost segment is a transfer never answered."""
    reader = open_bus("socketcan", "vcan0", receive_own_messages=False)
    try:
        sender = socketcan(bus_factory)
        count, deadline = 2000, time.monotonic() + 120  # ~1.5 ms per system call in the guest
        sent = 0
        while sent < count:
            try:
                sender.send(frame(0x181, sent & 0xFF, sent >> 8))
                sent += 1
            except can.CanOperationError:  # the sender's own queue is full: let it drain
                assert time.monotonic() < deadline, f"only {sent} frames sent"
                time.sleep(0.001)
        received = []
        while (msg := reader.recv(timeout=2.0)) is not None:
            received.append(msg.data[0] | msg.data[1] << 8)
        assert received == list(range(count))
    finally:
        reader.shutdown()
