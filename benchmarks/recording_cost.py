"""What recording costs: the loop's part per cycle, and the work it moves to other threads.

    .venv/bin/python benchmarks/recording_cost.py [--joints 3,6,12,24] [--repeat 20000] [--quick]

Recording is on by default (the flight recorder of ``rocoma-can run``), so its cost in the
cycle matters. Three costs per joint count:

* loop: ``SignalTrace.record``, the only recording work the control loop does (one ring row:
  timing, state, controller, every joint's feedback and command), µs per cycle;
* tap: ``FrameTap.on_message_received``, what the flight recorder does per received frame on
  its own passive bus reader thread (not the loop's, but it shares the interpreter);
* writer: JSON-encoding one cycle into MCAP (``McapWriter.cycles``), on the writer thread for
  ``--record`` and at a flight-record dump, µs per cycle.
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
from rocoma_can.record.flight import FrameTap
from rocoma_can.record.trace import McapWriter, SignalTrace


class _Manager:
    active_controller_name = "pd"


def time_record(joints: int, repeat: int) -> list[float]:
    state, command = JointState.zeros(joints), JointCommand.zeros(joints)
    trace = SignalTrace(state, command, _Manager(), capacity=max(2, repeat // 4))
    samples = []
    clock = time.perf_counter_ns
    for k in range(repeat):
        state.position[:] = k
        t0 = clock()
        trace.record(k * 0.001, 1e-4, 0.0, ManagerState.OK)
        samples.append((clock() - t0) / 1000.0)
    return samples


def time_tap(repeat: int) -> list[float]:
    tap = FrameTap("bus", seconds=10.0)
    msg = can.Message(arbitration_id=0x181, data=bytes(8), is_extended_id=False, timestamp=1.0)
    samples = []
    clock = time.perf_counter_ns
    for _ in range(repeat):
        t0 = clock()
        tap.on_message_received(msg)
        samples.append((clock() - t0) / 1000.0)
    return samples


def time_writer(joints: int, cycles: int) -> float:
    state, command = JointState.zeros(joints), JointCommand.zeros(joints)
    trace = SignalTrace(state, command, _Manager(), capacity=cycles + 1)
    for k in range(cycles):
        trace.record(k * 0.001, 1e-4, 0.0, ManagerState.OK)
    _, rows = trace.rows(0)
    writer = McapWriter(io.BytesIO(), state.names)
    t0 = time.perf_counter_ns()
    writer.cycles(trace, rows, 0.0)
    writer.finish()
    return (time.perf_counter_ns() - t0) / 1000.0 / cycles


def _ints(text: str) -> list[int]:
    return [int(v) for v in text.split(",")]


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--joints", type=_ints, default=[3, 6, 12, 24])
    parser.add_argument("--repeat", type=int, default=20000, help="calls per measurement")
    parser.add_argument("--quick", action="store_true", help="2000 calls per measurement")
    args = parser.parse_args()
    repeat = 2000 if args.quick else args.repeat
    tap = stats(time_tap(repeat))
    rows, results = [], []
    for n in args.joints:
        loop = stats(time_record(n, repeat))
        writer = time_writer(n, max(200, repeat // 10))
        rows.append([n, loop["median"], loop["p99"], tap["median"], writer])
        results.append({"joints": n, "loop_record_us": loop, "tap_us_per_frame": tap,
                        "writer_us_per_cycle": writer})
    report("recording_cost", "Recording cost (µs)",
           ["joints", "loop: record median", "loop: record p99", "tap per frame median",
            "writer per cycle (off the loop)"], rows, args=args, results=results,
           notes=["loop: SignalTrace.record, the control loop's whole part in recording "
                  "(flight recorder and --record alike), no allocation. tap: per frame on "
                  "the flight recorder's bus reader thread. writer: JSON + MCAP per cycle on "
                  "the writer thread (--record) or at a dump (flight recorder)."])
    assert np.isfinite(rows[0][1])


if __name__ == "__main__":
    main()
