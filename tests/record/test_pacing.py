"""The writer process gives way to the loop (record/pacing.py): it yields its CPU every
piece of work, through a recording's poll and a flight record's ~1 s dump alike, so a loop
woken on its CPU waits for one piece, not for the writer's slice."""
from __future__ import annotations

import io
import os
import time

import can

from rocoma_can import ManagerState
from rocoma_can.drivers.protocol.joints import JointCommand, JointState
from rocoma_can.record.pacing import Pacer
from rocoma_can.record.rings import CHUNK, FrameRing, SharedFile, layout
from rocoma_can.record.trace import PACED_FRAMES, RowLayout, SignalTrace, read_messages
from rocoma_can.record.writer import Spec, Writer

ROWS, FRAMES = 300, 3000


class _Manager:
    active_controller_name = "pd"


class _Clock:
    """A clock the test moves: the wall's, or the thread's work's."""

    def __init__(self) -> None:
        self.now = 0.0

    def __call__(self) -> float:
        return self.now


def test_a_pacer_yields_once_a_piece_of_work_has_passed():
    every_call, never = Pacer(piece=0.0), Pacer(piece=3600.0)
    for _ in range(5):
        every_call()
        never()
    assert (every_call.yields, never.yields) == (5, 0)
    wall, work = _Clock(), _Clock()
    pacer = Pacer(0.001, wall, work)
    wall.now = work.now = 0.0009
    pacer()
    assert pacer.yields == 0  # less than a piece of work
    wall.now = work.now = 0.001
    pacer()
    assert pacer.yields == 1
    wall.now = 0.003  # preempted or asleep for 2 ms, 0.1 ms of work: no reason to yield
    work.now = 0.0011
    pacer()
    assert pacer.yields == 1
    wall.now, work.now = 0.004, 0.002  # a piece of wall time on, the work reaches a piece
    pacer()
    assert pacer.yields == 2


def test_a_recordings_poll_and_a_flight_record_give_way_throughout(tmp_path):
    """Every chunk of frames and every message of a poll, and every message and few dozen
    frames of a flight record, passes a yield point: with a piece of 0 each is a yield."""
    state, command = JointState.zeros(2), JointCommand.zeros(2)
    specs = layout([("rows", 2 * ROWS, RowLayout(state.names).width, False),
                    ("bus received", 2 * FRAMES, 0, False), ("bus sent", 2 * FRAMES, 0, False)])
    shared = SharedFile(specs[-1].offset + specs[-1].size)
    trace = SignalTrace(state, command, _Manager(), specs[0].capacity,
                        rows=shared.array(specs[0]),
                        publish=lambda n: shared.publish(specs[0], n), known=["pd"])
    received = FrameRing(shared, specs[1], sent=False)
    sent = FrameRing(shared, specs[2], sent=True)
    now, wall = time.monotonic(), time.time()
    for k in range(FRAMES):  # 1 s old: past the hold a poll leaves frames in
        ring, cob_id = (sent, 0x201) if k % 2 else (received, 0x181)
        ring.put(can.Message(arbitration_id=cob_id, data=bytes(8), is_extended_id=False),
                 wall - 1.0 + k * 1e-5)
    spec = Spec(os.dup(shared.fd), shared.size, specs[0], {"bus": ("vcan0", specs[1:])},
                list(state.names), {"pd": 0}, record=str(tmp_path / "rec"),
                flight=str(tmp_path / "flight"), rate=1000.0)
    writer = Writer(spec, io.StringIO())
    try:
        writer.pace.piece = 0.0
        writer.write()  # a poll of frames only: the candump file's chunks
        assert writer.pace.yields >= FRAMES // CHUNK
        for k in range(ROWS):  # 0.3 s at 1 kHz, 1 s old: past the hold a poll leaves rows
            trace.record(now - 1.0 - (ROWS - k) * 1e-3, 1e-4, 0.0, ManagerState.OK, 1e-4)
        polled = writer.pace.yields
        writer.write()  # a poll of rows only: each row's /rocoma/cycle and joint states
        assert writer.pace.yields - polled >= 2 * ROWS
        assert not list((tmp_path / "flight").glob("*.mcap"))  # none asked for
        assert writer.flight is not None
        writer.flight.request("test")
        polled = writer.pace.yields
        writer.write()
        [record] = (tmp_path / "flight").glob("*.mcap")
        assert writer.pace.yields - polled >= 2 * ROWS + FRAMES // PACED_FRAMES
    finally:
        writer.close()
        shared.close()
    logged = list(can.LogReader(str(tmp_path / "rec" / "bus.log")))
    recorded = [(m["id"], m["sent"]) for topic, _, m in read_messages(str(record))
                if topic == "/can/bus"]
    expected = [(0x201, True) if k % 2 else (0x181, False) for k in range(FRAMES)]
    assert [(m.arbitration_id, not m.is_rx) for m in logged] == expected  # paced, and whole
    assert recorded == expected
