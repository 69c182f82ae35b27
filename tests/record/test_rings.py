"""The rings in shared memory (record/rings.py) read while the producer writes: a reader
never gets a record the producer is overwriting, and never a record under another number."""
from __future__ import annotations

import io
import json
import os
import queue
import time
from typing import Any

import can
import pytest

from rocoma_can import ManagerState
from rocoma_can.drivers.protocol.joints import JointCommand, JointState
from rocoma_can.record.can_log import RecordingError, candump_line
from rocoma_can.record.rings import (
    MEMORY_SHARE,
    FrameRing,
    RingReader,
    SharedFile,
    frame_fields,
    layout,
    memory_available,
)
from rocoma_can.record.trace import RowLayout, SignalTrace
from rocoma_can.record.writer import Spec, Writer, _read_commands

CAPACITY = 4


class _Manager:
    active_controller_name = "pd"


def test_a_row_being_written_is_not_read_under_the_number_it_overwrites():
    """The producer writes a row into its slot, then stores the count: a reader between the
    two sees the old count, and the slot of the oldest row it counts holds the new row."""
    state, command = JointState.zeros(2), JointCommand.zeros(2)
    [rows] = layout([("rows", CAPACITY, RowLayout(state.names).width, False)])
    shared = SharedFile(rows.size)
    reader = RingReader(shared, rows)
    seen: list[tuple[int, list[float]]] = []

    def publish(count: int) -> None:  # the row is written, its count not yet stored
        start, got = reader.read(0)
        seen.append((start, got[:, 0].tolist()))
        shared.publish(rows, count)
    trace = SignalTrace(state, command, _Manager(), CAPACITY, rows=shared.array(rows),
                        publish=publish, known=["pd"])
    for number in range(3 * CAPACITY):
        trace.record(float(number), 1e-3, 0.0, ManagerState.OK, 1e-3)
    for start, stamps in seen:  # row number n was recorded at t = n
        assert stamps == [float(n) for n in range(start, start + len(stamps))], (start, stamps)


def test_a_frame_being_written_is_not_read_under_the_number_it_overwrites():
    [spec] = layout([("bus received", CAPACITY, 0, False)])
    shared = SharedFile(spec.size)
    ring, reader = FrameRing(shared, spec, sent=False), RingReader(shared, spec)
    records = shared.array(spec)
    for number in range(CAPACITY):
        ring.put(can.Message(arbitration_id=number, is_extended_id=False), float(number))
    # the producer's next record is in its slot, its count not yet stored: what a reader
    # in the writer process can find at any moment of a busy bus
    records["t"][0], records["id"][0] = float(CAPACITY), CAPACITY
    start, got = reader.read(0)
    assert got["id"].tolist() == list(range(start, start + len(got)))


def test_a_bus_log_is_in_time_order_when_a_frame_reaches_its_ring_late(tmp_path):
    """A frame can reach its ring after a later one was written: a received one the bus's
    reader hands over late, one another thread sent (SDO, NMT) that the cycle moves in at
    its end. The writer's poll in between must not put it after the later one in the
    candump file (canplayer replays in file order)."""
    state = JointState.zeros(1)
    specs = layout([("rows", 16, RowLayout(state.names).width, False),
                    ("bus received", 16, 0, False), ("bus sent", 16, 0, False)])
    shared = SharedFile(specs[-1].offset + specs[-1].size)
    received, sent = FrameRing(shared, specs[1], sent=False), FrameRing(shared, specs[2], sent=True)
    spec = Spec(os.dup(shared.fd), shared.size, specs[0], {"bus": ("vcan0", specs[1:])},
                list(state.names), {}, record=str(tmp_path / "rec"), rate=100.0)
    writer = Writer(spec, io.StringIO())
    now = time.time()
    sent.put(can.Message(arbitration_id=0x080, is_extended_id=False), now)  # a SYNC
    writer.write()  # a poll
    # an SDO answer that came before the SYNC, handed over by the bus's reader after it
    received.put(can.Message(arbitration_id=0x581, data=bytes(8), is_extended_id=False),
                 now - 0.005)
    writer.write(closing=True)
    writer.close()
    shared.close()
    frames = list(can.LogReader(str(tmp_path / "rec" / "bus.log")))
    assert [(m.arbitration_id, m.is_rx) for m in frames] == [(0x581, True), (0x080, False)]


def test_a_frame_longer_than_its_rings_records_keeps_to_its_record():
    """An in-process bus hands a classic bus's reader what any sender sent, CAN FD frames
    too: a classic ring keeps 8 bytes of such a frame, and its payload must not run into the
    next record's."""
    [spec] = layout([("bus received", CAPACITY, 0, False)])
    shared = SharedFile(spec.size)
    ring = FrameRing(shared, spec, sent=False)
    ring.put(can.Message(arbitration_id=0x181, data=b"\x11" * 12, is_fd=True,
                         is_extended_id=False), 1.0)
    ring.put(can.Message(arbitration_id=0x182, data=b"\x22" * 8, is_extended_id=False), 2.0)
    _, records = RingReader(shared, spec).read(0)
    assert [data for _, _, _, data in frame_fields(records)] == ["11" * 8, "22" * 8]


def test_a_frames_flags_survive_the_ring_and_its_candump_line(tmp_path):
    """The ring encodes a frame's flags inline, the candump line reads them by
    drivers/protocol/wire.py's names: python-can's own log reader must get every flag back."""
    [spec] = layout([("bus sent", CAPACITY, 0, True)])
    shared = SharedFile(spec.size)
    ring = FrameRing(shared, spec, sent=True)
    sent = [
        can.Message(arbitration_id=0x201, data=bytes(range(12)), is_extended_id=False,
                    is_fd=True, bitrate_switch=True, error_state_indicator=True),
        can.Message(arbitration_id=0x1ABCDEF, is_remote_frame=True, dlc=0),
        can.Message(arbitration_id=0x181, data=b"\x01\x02", is_extended_id=False,
                    is_fd=True),
    ]
    for k, msg in enumerate(sent):
        ring.put(msg, 1.0 + k)
    _, records = RingReader(shared, spec).read(0)
    log = tmp_path / "bus.log"
    log.write_text("".join(candump_line(t, "can0", cob, flags, data)
                           for t, cob, flags, data in frame_fields(records)))
    got = list(can.LogReader(str(log)))
    for g, s in zip(got, sent, strict=True):
        assert (g.arbitration_id, g.is_extended_id, g.is_remote_frame, g.is_fd,
                g.bitrate_switch, g.error_state_indicator, bytes(g.data), g.is_rx) == (
            s.arbitration_id, s.is_extended_id, s.is_remote_frame, s.is_fd,
            s.bitrate_switch, s.error_state_indicator, bytes(s.data), False)


def _resident_kb(name: str) -> int:
    """Resident kB of this process's mappings of the memfd ``name`` (/proc/self/smaps)."""
    resident, inside = 0, False
    for line in open("/proc/self/smaps"):
        if line[0] in "0123456789abcdef" and "-" in line.split()[0]:
            inside = f"/memfd:{name}" in line
        elif inside and line.startswith("Rss:"):
            resident += int(line.split()[1])
    return resident


def test_the_rings_memory_is_all_taken_at_start():
    """Every page is present from the start: the loop never takes a page fault on a ring's
    first lap, nor dies of a page the machine can no longer give."""
    before = _resident_kb("rocoma-can-record")
    shared = SharedFile(8 << 20)
    try:
        assert _resident_kb("rocoma-can-record") - before >= 8 << 10
    finally:
        shared.close()


def test_rings_larger_than_the_memory_allows_are_refused_at_once():
    """Twice what the share allows: the memory available moves between this read and the
    check's (other work ends: a megabyte past the share was allowed once in CI)."""
    available = memory_available()
    assert available is not None  # Linux says it
    with pytest.raises(RecordingError, match=r"the recording's rings need \d+ MB of "
                                             r"memory, and \d+ MB are available"):
        SharedFile(int(available * MEMORY_SHARE * 2))


def test_a_late_answer_to_a_call_that_timed_out_is_dropped_and_the_writer_hears_on():
    """The live view's call that nobody answered in time is cancelled; its answer, coming
    late, finds nobody. A command the writer cannot take is skipped, and the ones after it
    are heard (its commands' end would leave it deaf to the close and to every later
    e-stop). Once the loop's process answers no more, a call is answered at once."""
    state = JointState.zeros(2)
    [rows] = layout([("rows", 16, RowLayout(state.names).width, False)])
    shared = SharedFile(rows.size)
    said = io.StringIO()
    writer = Writer(Spec(os.dup(shared.fd), shared.size, rows, {}, list(state.names), {},
                         rate=100.0), said)
    try:
        late = writer.call("estop", b"{}")
        assert json.loads(said.getvalue().splitlines()[-1]) == {
            "call": 1, "service": "estop", "payload": b"{}".hex()}
        late.cancel()  # the SDK's handler gave up waiting
        assert writer.take({"answer": 1, "reply": {"ok": True}}) is True
        answered = writer.call("estop", b"")
        commands: queue.Queue[dict[str, Any] | None] = queue.Queue()
        _read_commands(io.StringIO('{"answer": "not a number"}\n'
                                   '{"answer": 2, "reply": {"ok": true, "state": "FAILPROOF"}}\n'
                                   '{"latched": true}\n'), writer, commands)
        assert answered.result(0) == {"ok": True, "state": "FAILPROOF"}
        assert [commands.get_nowait(), commands.get_nowait()] == [{"latched": True}, None]
        # the commands' end above said the loop's process answers no more
        assert writer.call("estop", b"").result(0)["ok"] is False  # at once, nobody asked
        assert len(said.getvalue().splitlines()) == 2
    finally:
        writer.close()
        shared.close()


def test_what_the_writer_heard_goes_into_a_file_once_in_the_order_heard(tmp_path):
    """Status reports and service-call lines (Facts) reach a file each once, whatever their
    stamps' order (the recorder's own report can be stamped after a viewer's that it is
    sent before) and however the file's writes fall between them; a flight record takes
    those of its window."""
    from rocoma_can.record.live_channels import Facts, LiveChannels
    from rocoma_can.record.trace import McapWriter, RowLayout, read_messages
    facts = Facts(window=1.0)
    path = tmp_path / "heard.mcap"
    with open(path, "wb") as stream:
        writer = McapWriter(stream, ["j"])
        live = LiveChannels(writer, RowLayout(["j"]), 0.001, None, facts)
        facts.statuses.add(2.0, {"report": "later stamp, heard first"})
        facts.statuses.add(1.0, {"report": "earlier stamp, heard second"})
        facts.logs.add(1.5, ("switch from Foxglove: done", 2))
        live.heard(offset=0.0)
        facts.statuses.add(3.0, {"report": "third"})
        live.heard(offset=0.0)
        live.heard(offset=0.0)  # nothing new
        facts.statuses.add(4.0, {"report": "before the window"})
        facts.statuses.add(9.0, {"report": "in the window"})
        live.heard(offset=0.0, since=5.0)
        writer.finish()
    messages = list(read_messages(str(path)))
    reports = [m["report"] for topic, _, m in messages if topic == "/rocoma/status"]
    assert sorted(reports) == sorted(["later stamp, heard first",
                                      "earlier stamp, heard second", "third",
                                      "in the window"])
    assert [m["message"] for topic, _, m in messages if topic == "/rocoma/log"] == [
        "switch from Foxglove: done"]
