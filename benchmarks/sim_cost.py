"""What the simulated drives cost per SYNC: can the simulator keep up with a 1 kHz bench?

    .venv/bin/python benchmarks/sim_cost.py [--drives 1,3,6,12] [--repeat 3000] [--quick]

One simulated segment (``drivers/sim/segment.py``) on an in-process bus with the drive's
default PDOs (the EDS's: RPDOs event-driven, applied on arrival; rocoma-can's bring-up makes
them synchronous, applied at the next SYNC, which costs the same), its drives started and
enabled in CSP by frames: NMT start, controlwords 6, 7, 15 in RPDO1. Then, ``--repeat``
times: every drive's RPDO1 (controlword, mode, torque) and RPDO2 (target position and
velocity), and a SYNC; the segment applies them, steps the joints once (a fixed 1 ms step)
and answers with two TPDOs per drive. Measured: the CPU time of the segment's receive
thread (its thread CPU clock, so another process on the machine does not count), per SYNC
and per drive. That thread shares the interpreter with the control loop when the simulator
runs in-process (``rocoma-can demo``, ``benchmarks/loop_run.py``), so the last column says
what share of one core a 1 kHz bench with that many segments of that size would spend on
simulation alone.
"""
from __future__ import annotations

import argparse
import struct
import threading
import time
import uuid

import can
from _report import report, stats

from rocoma_can.drivers.link.bus import open_bus
from rocoma_can.drivers.protocol import cia301
from rocoma_can.drivers.protocol.cia402 import State402
from rocoma_can.drivers.sim.segment import SimulatedSegment

#: the simulated drive's default RPDO1: controlword, modes of operation, target torque
RPDO1 = struct.Struct("<HBh")
RPDO2 = struct.Struct("<ii")  # target position, target velocity
CSP = 8
BENCH_DRIVES = 12  # the bench: 12 drives at 1 kHz


def _rx_thread_clock() -> int:
    """The CPU clock of the segment's receive thread (started last, named by the segment)."""
    threads = [t for t in threading.enumerate() if t.name == "sim-segment-rx"]
    if len(threads) != 1 or threads[0].ident is None:
        raise RuntimeError(f"expected one running sim-segment-rx thread, found {len(threads)}")
    return time.pthread_getcpuclockid(threads[0].ident)


def _wait_syncs(segment: SimulatedSegment, count: int, timeout: float = 5.0) -> None:
    deadline = time.monotonic() + timeout
    while segment.sync_count < count:
        if time.monotonic() > deadline:
            raise RuntimeError(f"the segment handled {segment.sync_count} of {count} SYNCs "
                               f"within {timeout} s")
        time.sleep(POLL)


#: how often the sender looks whether the segment is done: often enough to keep SYNCs coming,
#: rarely enough not to take the GIL from the thread being measured
POLL = 50e-6
BATCH = 50  # SYNCs per sample


def measure(drives: int, repeat: int) -> list[float]:
    """CPU µs of the segment's receive thread per SYNC, one sample per ``BATCH`` SYNCs."""
    channel = f"sim-cost-{uuid.uuid4().hex[:8]}"
    nodes = list(range(1, drives + 1))
    segment = SimulatedSegment.open(channel, "inproc", nodes, sync_period=0.001).start()
    master = open_bus("inproc", channel, receive_own_messages=False)
    try:
        def frame(cob_id: int, data: bytes) -> None:
            master.send(can.Message(arbitration_id=cob_id, data=data, is_extended_id=False))

        frame(cia301.NMT, bytes((cia301.NmtCommand.START, 0)))
        syncs = 0
        for cw in (0x06, 0x07, 0x0F):  # shutdown, switch on, enable operation
            for n in nodes:
                frame(0x200 + n, RPDO1.pack(cw, CSP, 0))
            frame(cia301.SYNC, b"")
            syncs += 1
            _wait_syncs(segment, syncs)
        states = {n: segment.drives[n].state402 for n in nodes}
        if any(s != State402.OPERATION_ENABLED for s in states.values()):
            raise RuntimeError(f"drives not enabled: {states}")
        rpdo1 = [can.Message(arbitration_id=0x200 + n, data=RPDO1.pack(0x0F, CSP, 0),
                             is_extended_id=False) for n in nodes]
        rpdo2 = [can.Message(arbitration_id=0x300 + n, data=bytes(8), is_extended_id=False)
                 for n in nodes]
        sync = can.Message(arbitration_id=cia301.SYNC, data=b"", is_extended_id=False)
        clock = _rx_thread_clock()
        samples = []
        batch = BATCH
        for b in range(max(1, round(repeat / batch))):
            t0 = time.clock_gettime(clock)
            for k in range(batch):
                target = 1000 * (b * batch + k)  # increments: a slow ramp
                for msg1, msg2 in zip(rpdo1, rpdo2):
                    RPDO2.pack_into(msg2.data, 0, target, 0)
                    master.send(msg1)
                    master.send(msg2)
                master.send(sync)
                syncs += 1
                _wait_syncs(segment, syncs)
            samples.append((time.clock_gettime(clock) - t0) / batch * 1e6)
        segment.check()
        return samples
    finally:
        master.shutdown()
        segment.stop()


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--drives", default="1,3,6,12",
                        help="drives per segment, comma-separated")
    parser.add_argument("--repeat", type=int, default=3000, help="SYNCs per segment size")
    parser.add_argument("--quick", action="store_true", help="--repeat 300")
    args = parser.parse_args()
    if args.quick:
        args.repeat = 300
    rows, results = [], []
    for n in (int(x) for x in args.drives.split(",")):
        s = stats(measure(n, args.repeat))
        segments = -(-BENCH_DRIVES // n)
        share = segments * s["median"] * 1e-6 * 1000.0  # of one core, at 1 kHz
        rows.append([n, s["median"], s["p99"], s["median"] / n,
                     f"{segments} x {n}: {100 * share:.0f} %"])
        results.append({"drives": n, "per_sync_us": s, "per_drive_us": s["median"] / n,
                        "bench_segments": segments, "bench_core_share": share})
    report("sim_cost", "Simulated segment, CPU per SYNC (its receive thread)",
           ["drives", "median us", "p99 us", "per drive us",
            f"{BENCH_DRIVES} drives at 1 kHz (segments x drives: core)"],
           rows, args=args, results=results,
           notes=[f"CPU time of the segment's receive thread per SYNC (batches of {BATCH} "
                  "SYNCs): every drive's two RPDOs, the SYNC, one dynamics step, two TPDOs "
                  "per drive sent on the in-process bus. CSP, drives enabled."])


if __name__ == "__main__":
    main()
