"""What the ROS 2 node costs the loop: the whole runtime (as ``run``) with ``--ros2`` off
and on, alternated, and the bare loop beside each round.

    .venv/bin/python benchmarks/ros2_run.py [--drives 12] [--rate 1000] [--duration 20]
                                            [--repeat 2] [--quick]

Each round runs telemetry_run.py's set ``off`` and then ``ros2`` (the node on a Zenoh
router on loopback, its joint states at 100 Hz, diagnostics, a subscriber to everything it
publishes), each in a fresh process, then in this process the bare loop (host_floor.py)
for as many cycles, each as much Python work as the ``off`` run's median cycle took (start to
end): what the host allowed that much work in that minute. The simulated drives are
stepped on the loop's thread (the demo's default). Compare the rows of one round: the
machine's other load is what it is.
"""
from __future__ import annotations

import argparse
from typing import Any

import host_floor
import telemetry_run
from _report import report


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--drives", type=int, default=12)
    parser.add_argument("--rate", type=float, default=1000.0)
    parser.add_argument("--duration", type=float, default=20.0, help="s of steady run")
    parser.add_argument("--repeat", type=int, default=2, help="rounds (each: off, ros2)")
    parser.add_argument("--quick", action="store_true", help="6 drives, 200 Hz, 3 s, 1 round")
    args = parser.parse_args()
    if args.quick:
        args.drives, args.rate, args.duration, args.repeat = 6, 200.0, 3.0, 1
    rows, runs = [], []
    for _ in range(args.repeat):
        off, on = telemetry_run.run_set("off", args), telemetry_run.run_set("ros2", args)
        for r in (off, on):
            runs.append(r)
            if "error" in r:
                rows.append([r["set"], "failed", "", "", "", "", "", r["error"]])
                continue
            p = r["period_us"]
            node = r["threads_cpu_us"].get("ros2-node", 0.0)
            rows.append([r["set"], r["cycles"], r["overruns"],
                         f"{100 * r['overruns'] / max(r['cycles'], 1):.2f}",
                         f"{p['mean']:.1f}", f"{p['max']:.0f}", f"{r['work_median_us']:.0f}",
                         f"{node:.1f}" if r["set"] == "ros2" else "-"])
        if "error" not in off:
            work = off["work_median_us"]
            floor: dict[str, Any] = host_floor.one(args.rate, work, 0,
                                                   off["cycles"] / args.rate)
            floor["work_median_us"] = floor["work_us"]
            runs.append({"set": "bare", **floor})
            rows.append([f"bare loop, {work:.0f} µs", floor["cycles"], floor["overruns"],
                         f"{100 * floor['overruns'] / max(floor['cycles'], 1):.2f}",
                         f"{floor['period_mean_ms'] * 1e3:.1f}",
                         f"{floor['period_max_ms'] * 1e3:.0f}", f"{work:.0f}", "-"])
    report("ros2_run", f"The loop at {args.rate:g} Hz, {args.drives} drives, with and without "
           "the ROS 2 node", ["set", "cycles", "overruns", "%", "period mean us",
                               "max us", "work median us/cycle",
                               "node thread CPU us/cycle"],
           rows, args=args, results={"runs": runs},
           notes=["overruns: cycles that ended after the next one's deadline (the loop's own "
                  "count, rocoma_can/overrun.py). work: a cycle's start to end, the "
                  "simulated drives included (stepped on the loop's thread). node thread: "
                  "the ROS 2 node's publisher thread (joint states at 100 Hz, diagnostics "
                  "at 1 Hz); Zenoh's own threads are in the process's CPU, not in these "
                  "columns."])


if __name__ == "__main__":
    main()
