"""drivers/link/bus.py: a SocketCAN link that goes down and comes back: the errors python-can
raises, and that the same Bus objects work again afterwards (what a driver's bus-failure handling
relies on)."""
from __future__ import annotations

import errno
import time

import can
import pytest


def frame(cob_id: int, *data: int) -> can.Message:
    return can.Message(arbitration_id=cob_id, data=bytes(data), is_extended_id=False)


def test_link_down_raises_and_link_up_recovers_the_same_buses(bus_factory, frame_recorder,
                                                              vcan_link):
    recorder = frame_recorder(interface="socketcan")
    a, b = bus_factory("vcan0", "socketcan"), bus_factory("vcan0", "socketcan")
    a.send(frame(0x201, 1))
    assert b.recv(timeout=5).data[0] == 1

    vcan_link("vcan0", "down")
    with pytest.raises(can.CanOperationError) as sending:
        a.send(frame(0x201, 2))
    with pytest.raises(can.CanOperationError) as receiving:
        b.recv(timeout=5)
    assert sending.value.error_code == errno.ENETDOWN
    assert receiving.value.error_code == errno.ENETDOWN

    vcan_link("vcan0", "up")
    a.send(frame(0x201, 3))
    assert b.recv(timeout=5).data[0] == 3
    b.send(frame(0x181, 4))
    assert a.recv(timeout=5).data[0] == 4

    # The recorder saw the failure as an error and kept recording across it.
    recorder.wait_for(lambda f: f.cob_id == 0x181, timeout=5)
    assert [f.data[0] for f in recorder.frames()] == [1, 3, 4]
    deadline = time.monotonic() + 5
    while not recorder.errors and time.monotonic() < deadline:
        time.sleep(0.02)
    assert [e.error_code for _, e in recorder.errors] == [errno.ENETDOWN]
