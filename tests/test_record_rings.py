"""The rings in shared memory (record/rings.py) read while the producer writes: a reader
never gets a record the producer is overwriting, and never a record under another number."""
from __future__ import annotations

import can

from rocoma_can import ManagerState
from rocoma_can.drivers.joints import JointCommand, JointState
from rocoma_can.record.rings import FrameRing, RingReader, SharedFile, layout
from rocoma_can.record.trace import RowLayout, SignalTrace

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
        trace.record(float(number), 1e-3, 0.0, ManagerState.OK)
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
