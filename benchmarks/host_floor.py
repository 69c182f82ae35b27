"""The host's own floor: how often the control loop overruns when its cycle is nothing but
a fixed amount of Python work, no CAN, no threads, no other process of ours.

    .venv/bin/python benchmarks/host_floor.py [--rates 1000,2000] [--work 0,100,200,300,400]
                                              [--footprints 0,4096] [--duration 8]
                                              [--repeat 2] [--quick]

The bare loop of ``rocoma_can/runtime/host_timing.py`` (what ``rocoma-can doctor --timing``
runs): ``ControlLoop`` as ``run`` and ``demo`` use it (its wait, its spin, its collector and
switch-interval settings) drives a stand-in hardware whose write does W µs of Python work
(sized at start as the loop runs it: ``WorkHardware.size``) and a stand-in manager that
always says OK. Whatever overruns it counts is the host's: the hypervisor's and kernel's
interruptions, other tenants, a CPU or a memory that is slow for a while. A loop whose
cycle does W µs of real work meets the same host, so the demo's and telemetry_run.py's counts
are read against this table at their own work (the demo's loop: ~390-440 µs a cycle at
1 kHz, its drives simulated on its thread).

The work reads small objects spread over a footprint, in an order unrelated to where they
lie (as a Python program's objects are). At footprint 0 it stays in the CPU's first-level
cache and sees only the scheduler and a slow CPU; at 4 MiB, past the core's second-level
cache, it also sees the memory other programs on the host share. On the 2-core VM these
benchmarks run on the two differ: 300-400 µs at 1 kHz overran 0-12 times in 8,000 cycles
at footprint 0, and 0-867 at 4 MiB, whose median differed by up to 1.5x from one run to
the next (benchmarks/HISTORY.md).

Per rate, footprint and work: cycles, overruns (the loop's own count,
rocoma_can/overrun.py) and their share, how many of them were on the CPU (the work itself
took longer than usual) or waiting off it (the loop was not scheduled), the work's median
and p99.9 thread CPU (the spread is the host: the work is the same every cycle), and the
mean period. The runs alternate ``--repeat`` times, so a noisy minute spreads over them.
"""
from __future__ import annotations

import argparse
from dataclasses import asdict
from typing import Any

from _report import report

from rocoma_can.runtime.host_timing import MEMORY_FOOTPRINT, bare_loop


def one(rate: float, work_us: float, footprint: int, duration: float,
        priority: int | None = None) -> dict[str, Any]:
    """One run of ``duration`` s at ``rate`` with ``work_us`` of work a cycle over
    ``footprint`` bytes (``priority``: SCHED_FIFO), as the JSON keeps it."""
    run = bare_loop(rate, work_us, footprint, duration, priority=priority)
    return {**asdict(run), "footprint_kib": footprint // 1024}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--rates", default="1000,2000", help="loop rates, Hz")
    parser.add_argument("--work", default="0,100,200,300,400",
                        help="µs of work a cycle (as the host runs it at start)")
    parser.add_argument("--footprints", default=f"0,{MEMORY_FOOTPRINT >> 10}",
                        help="KiB of objects the work reads, comma-separated")
    parser.add_argument("--duration", type=float, default=8.0, help="s per run")
    parser.add_argument("--repeat", type=int, default=2, help="rounds over every pair")
    parser.add_argument("--quick", action="store_true",
                        help="1 kHz, 300 µs, both footprints, 2 s")
    args = parser.parse_args()
    if args.quick:
        args.rates, args.work, args.duration, args.repeat = "1000", "300", 2.0, 1
    rates = [float(r) for r in args.rates.split(",")]
    works = [float(w) for w in args.work.split(",")]
    footprints = [int(f) * 1024 for f in args.footprints.split(",")]
    runs = [one(rate, work, footprint, args.duration)
            for _ in range(args.repeat) for rate in rates for work in works
            for footprint in footprints if work < 1e6 / rate]
    runs.sort(key=lambda r: (r["rate"], r["footprint_kib"], r["work_us"]))
    rows = [[f"{r['rate']:g}", r["footprint_kib"], f"{r['work_us']:g}", r["cycles"],
             r["overruns"],
             f"{100 * r['overruns'] / max(r['cycles'], 1):.2f}",
             r["overruns"] - r["waiting"], r["waiting"], f"{r['cpu_median_us']:.0f}",
             f"{r['cpu_p999_us']:.0f}", f"{r['period_mean_ms']:.3f}"] for r in runs]
    report("host_floor", "The host's floor: the loop with a fixed amount of work a cycle",
           ["rate Hz", "footprint KiB", "work µs", "cycles", "overruns", "%", "on the CPU",
            "waiting", "CPU median µs", "CPU p99.9 µs", "period mean ms"],
           rows, args=args, results={"runs": runs},
           notes=["work: Python reads of small objects spread over the footprint, sized "
                  "at start as the loop runs it; the CPU columns are what the same work "
                  "took, cycle by cycle. No CAN, no other thread: every overrun here is the "
                  "host's, and a loop with as much real work over as much memory meets "
                  "the same host."])


if __name__ == "__main__":
    main()
