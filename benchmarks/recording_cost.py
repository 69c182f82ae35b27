"""What recording costs: the loop's part per cycle and per frame, and the writer process's.

    .venv/bin/python benchmarks/recording_cost.py [--joints 3,6,12,24] [--repeat 20000] [--quick]

Recording is on by default (the flight recorder of ``rocoma-can run``), so its cost in the
loop's process matters. The loop's process only copies into rings in shared memory
(rocoma_can/record/rings.py); the writer process (writer.py) does the rest. Measured:

* row: ``SignalTrace.record`` into the shared ring, the loop's per-cycle part (timing,
  state, controller, every joint's feedback and command), µs per cycle;
* frame: ``FrameRing.put``, per frame the hardware received or sent (on the loop's thread
  or its bus reader's), µs per frame;
* writer: per cycle, the rows' JSON into MCAP (``McapWriter.cycles``), and per frame, the
  candump line and the MCAP frame message, in the writer process (``--record`` writes
  both; a flight record the MCAP ones).
"""
from __future__ import annotations

import argparse
import io
import time

import can
import numpy as np
from _report import report, stats

from rocoma_can import ManagerState
from rocoma_can.drivers.joints import JointCommand, JointState
from rocoma_can.record.can_log import candump_line
from rocoma_can.record.rings import FrameRing, RingReader, SharedFile, frame_fields, layout
from rocoma_can.record.trace import McapWriter, RowLayout, SignalTrace


class _Manager:
    active_controller_name = "pd"


def _shared_trace(joints: int, capacity: int) -> tuple[SignalTrace, RingReader]:
    state, command = JointState.zeros(joints), JointCommand.zeros(joints)
    [spec] = layout([("rows", capacity, RowLayout(state.names).width, False)])
    shared = SharedFile(spec.size)
    trace = SignalTrace(state, command, _Manager(), capacity, rows=shared.array(spec),
                        publish=lambda n: shared.publish(spec, n), known=["pd"])
    return trace, RingReader(shared, spec)


def time_record(joints: int, repeat: int) -> list[float]:
    trace, _ = _shared_trace(joints, max(2, repeat // 4))
    samples = []
    clock = time.perf_counter_ns
    for k in range(repeat):
        t0 = clock()
        trace.record(k * 0.001, 1e-4, 0.0, ManagerState.OK, 1e-4)
        samples.append((clock() - t0) / 1000.0)
    return samples


def _frames(repeat: int) -> tuple[FrameRing, RingReader]:
    [spec] = layout([("bus sent", repeat, 0, False)])
    shared = SharedFile(spec.size)
    return FrameRing(shared, spec, sent=True), RingReader(shared, spec)


def time_frame(repeat: int) -> float:
    ring, _ = _frames(repeat)
    msg = can.Message(arbitration_id=0x181, data=bytes(8), is_extended_id=False)
    put, stamp = ring.put, time.time()
    t0 = time.perf_counter_ns()
    for _ in range(repeat):
        put(msg, stamp)
    return (time.perf_counter_ns() - t0) / 1000.0 / repeat


def time_writer(joints: int, cycles: int) -> tuple[float, float, float]:
    """µs per cycle (rows to MCAP), per frame (candump line), per frame (MCAP message)."""
    trace, rows = _shared_trace(joints, cycles + 1)
    for k in range(cycles):
        trace.record(k * 0.001, 1e-4, 0.0, ManagerState.OK, 1e-4)
    writer = McapWriter(io.BytesIO(), trace.names)
    t0 = time.perf_counter_ns()
    writer.cycles(trace.layout, {0: "pd"}, rows.read(0)[1], 0.0)
    per_cycle = (time.perf_counter_ns() - t0) / 1000.0 / cycles
    frames = cycles * 10
    ring, reader = _frames(frames)
    msg = can.Message(arbitration_id=0x181, data=bytes(range(8)), is_extended_id=False)
    for k in range(frames):
        ring.put(msg, k * 1e-4)
    t0 = time.perf_counter_ns()
    lines = [candump_line(t, "can0", cob, flags, data)
             for t, cob, flags, data in frame_fields(reader.read(0)[1])]
    per_line = (time.perf_counter_ns() - t0) / 1000.0 / len(lines)
    t0 = time.perf_counter_ns()
    writer.frames("can0", frame_fields(reader.read(0)[1]))
    per_message = (time.perf_counter_ns() - t0) / 1000.0 / len(lines)
    writer.finish()
    return per_cycle, per_line, per_message


def _ints(text: str) -> list[int]:
    return [int(v) for v in text.split(",")]


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--joints", type=_ints, default=[3, 6, 12, 24])
    parser.add_argument("--repeat", type=int, default=20000, help="calls per measurement")
    parser.add_argument("--quick", action="store_true", help="2000 calls per measurement")
    args = parser.parse_args()
    repeat = 2000 if args.quick else args.repeat
    frame = time_frame(repeat * 5)
    rows, results = [], []
    for n in args.joints:
        loop = stats(time_record(n, repeat))
        per_cycle, per_line, per_message = time_writer(n, max(200, repeat // 10))
        rows.append([n, loop["median"], loop["p99"], frame, per_cycle, per_line, per_message])
        results.append({"joints": n, "loop_record_us": loop, "loop_frame_us": frame,
                        "writer_row_us": per_cycle, "writer_candump_us": per_line,
                        "writer_mcap_frame_us": per_message})
    report("recording_cost", "Recording cost (µs)",
           ["joints", "loop: row median", "loop: row p99", "loop: per frame",
            "writer: per cycle (MCAP row)", "writer: per frame (candump)",
            "writer: per frame (MCAP)"], rows, args=args, results=results,
           notes=["loop: what the loop's process does (SignalTrace.record into shared "
                  "memory, FrameRing.put per frame received or sent), no allocation. writer: "
                  "the writer process, on its own interpreter (--record writes rows, candump "
                  "lines and MCAP frame messages; a flight record rows and MCAP frame "
                  "messages)."])
    assert np.isfinite(rows[0][1])


if __name__ == "__main__":
    main()
