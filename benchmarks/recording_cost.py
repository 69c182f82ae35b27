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
  both; a flight record the MCAP ones);
* flight record: the writer's CPU time for one record (``FlightRecords.dump``, the live
  view's channels included) of 10 s of the demo's traffic at 1 kHz: that many joints'
  rows, and 13 frames a cycle on each of one bus per 3 joints (each drive's 2 RPDOs and 2
  TPDOs, a SYNC), the traffic of ``rocoma-can demo --drives N --rate 1000``. The demo's
  e-stops each ask for one while the loop runs.
"""
from __future__ import annotations

import argparse
import io
import tempfile
import time
from pathlib import Path

import can
import numpy as np
from _report import report, stats

from rocoma_can import ManagerState
from rocoma_can.drivers.protocol.joints import JointCommand, JointState
from rocoma_can.record.can_log import candump_line
from rocoma_can.record.flight import FlightRecords
from rocoma_can.record.live_channels import Facts, LiveChannels
from rocoma_can.record.pacing import unpaced
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


#: the flight record's window, s, and the rate its rows and frames come at, Hz
FLIGHT_SECONDS, FLIGHT_RATE = 10.0, 1000.0
SENT, RECEIVED = 7, 6  # a bus's frames a cycle, 3 drives: 6 RPDOs and a SYNC; 6 TPDOs
FILL_MARGIN = 600.0  # s


def time_flight(joints: int, seconds: float = FLIGHT_SECONDS) -> float:
    """s of the writer's CPU for one flight record of ``seconds`` (see module)."""
    cycles = int(seconds * FLIGHT_RATE)
    trace, rows = _shared_trace(joints, cycles + 1)
    now, wall = time.monotonic(), time.time()
    for k in range(cycles):
        trace.record(now - seconds + k / FLIGHT_RATE, 1e-4, 0.0, ManagerState.OK, 1e-4)
    buses = {}
    msg = can.Message(arbitration_id=0x181, data=bytes(range(8)), is_extended_id=False)
    for b in range(max(1, -(-joints // 3))):
        readers = []
        for per_cycle in (RECEIVED, SENT):
            ring, reader = _frames(cycles * per_cycle + 1)
            for k in range(cycles * per_cycle):
                ring.put(msg, wall - seconds + k / (FLIGHT_RATE * per_cycle))
            readers.append(reader)
        buses[f"bus{b}"] = readers
    layout_ = trace.layout
    with tempfile.TemporaryDirectory(prefix="rocoma-flight-cost-") as tmp:
        # a window longer than what the rings hold: the record is all of it, however long
        # filling them took (its stamps were taken before)
        flight = FlightRecords(Path(tmp), seconds + FILL_MARGIN, layout_, rows, buses,
                               lambda w: LiveChannels(w, layout_, 1.0 / FLIGHT_RATE, None,
                                                      Facts(window=seconds)),
                               unpaced)
        flight.request("benchmark")
        t0 = time.process_time()
        done = flight.dump({0: "pd"})
        spent = time.process_time() - t0
    if isinstance(done, str):
        raise SystemExit(f"the flight record failed: {done}")
    return spent


def _ints(text: str) -> list[int]:
    return [int(v) for v in text.split(",")]


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--joints", type=_ints, default=[3, 6, 12, 24])
    parser.add_argument("--repeat", type=int, default=20000, help="calls per measurement")
    parser.add_argument("--quick", action="store_true",
                        help="2000 calls per measurement, a flight record of 1 s")
    args = parser.parse_args()
    repeat = 2000 if args.quick else args.repeat
    frame = time_frame(repeat * 5)
    rows, results = [], []
    for n in args.joints:
        loop = stats(time_record(n, repeat))
        per_cycle, per_line, per_message = time_writer(n, max(200, repeat // 10))
        flight = time_flight(n, 1.0 if args.quick else FLIGHT_SECONDS)
        rows.append([n, loop["median"], loop["p99"], frame, per_cycle, per_line, per_message,
                     flight])
        results.append({"joints": n, "loop_record_us": loop, "loop_frame_us": frame,
                        "writer_row_us": per_cycle, "writer_candump_us": per_line,
                        "writer_mcap_frame_us": per_message, "writer_flight_record_s": flight})
    report("recording_cost", "Recording cost (µs)",
           ["joints", "loop: row median", "loop: row p99", "loop: per frame",
            "writer: per cycle (MCAP row)", "writer: per frame (candump)",
            "writer: per frame (MCAP)", "writer: flight record (s)"], rows, args=args,
           results=results,
           notes=["loop: what the loop's process does (SignalTrace.record into shared "
                  "memory, FrameRing.put per frame received or sent), no allocation. writer: "
                  "the writer process, on its own interpreter (--record writes rows, candump "
                  "lines and MCAP frame messages; a flight record rows and MCAP frame "
                  "messages). flight record: the writer's CPU time for one record of "
                  f"{1 if args.quick else FLIGHT_SECONDS:g} s at 1 kHz, 13 frames a cycle on "
                  "each bus of 3 joints."])
    assert np.isfinite(rows[0][1])


if __name__ == "__main__":
    main()
