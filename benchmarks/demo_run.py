"""The demo as a user runs it: overruns with recording on (its default) and off, alternated.

    .venv/bin/python benchmarks/demo_run.py [--drives 12] [--rate 1000] [--duration 16]
                                            [--repeat 3] [--priority N] [--quick]

``rocoma-can demo --drives 12 --rate 1000`` is the number issue 36 set a target for
(recording on: mean period <= 1.01 ms, overruns < 0.1 %). Each round runs the demo twice, in
fresh processes: as it comes (recording, flight records, plot) and with ``--no-record
--no-flight``; then, in this process, the bare loop (host_floor.py) for as many cycles,
each only as much Python work as the recorded run's median cycle took of the loop thread's
CPU, in the CPU's cache: what the host's scheduling and CPU allowed that much work in that
minute, to read the demo's counts against (not a bound: the host changes from one minute to
the next; ``bare`` says why not a memory-bound work). From the demo's summary:
cycles, overruns (on the CPU / waiting off it, the loop's own split:
rocoma_can/overrun.py), period mean and max. From a recorded run's trace:
the manager state each overrun happened in, since they differ in what they cost: in
FAILPROOF the drives are off (the bring-up, where the simulated drives answer the bring-up's
SDOs in the loop's pass, and after the walk-through's second fault); in OK and EMERGENCY a
controller commands them.

The simulated drives are stepped in the loop's pass (the demo's default), so the loop's
thread does their work too; the machine's other load is what it is: compare the columns of
one run, not runs of different days. ``--priority N``: every demo and bare loop of the
rounds with its loop at SCHED_FIFO N (``demo --priority``), as a robot's loop runs.
"""
from __future__ import annotations

import argparse
import re
import subprocess
import sys
import tempfile
from collections import Counter
from pathlib import Path
from typing import Any

import host_floor
import numpy as np
from _report import report

from rocoma_can.overrun import overran
from rocoma_can.record.trace import CYCLE_TOPIC, read_messages

#: the summary lines read (rocoma_can/cli/demo/report.py)
_CYCLES = re.compile(r"^\s+cycles\s+(\d+)$", re.M)
_OVERRUNS = re.compile(r"^\s+overruns \(past their period\)\s+(\d+)(?: \((\d+) on the CPU, "
                       r"(\d+) waiting off it\))?$", re.M)  # no split when there are none
_PERIOD = re.compile(r"^\s+period mean / max\s+([\d.]+) / ([\d.]+) ms$", re.M)
STATES = ("FAILPROOF", "EMERGENCY", "OK")


def _summary(out: str) -> dict[str, Any]:
    """The demo's summary numbers; ValueError naming the line that is missing."""
    found = {}
    for name, pattern in (("cycles", _CYCLES), ("overruns", _OVERRUNS), ("period", _PERIOD)):
        match = pattern.search(out)
        if match is None:
            raise ValueError(f"the demo's summary has no {name} line:\n{out[-1500:]}")
        found[name] = match.groups()
    overruns, on_cpu, waiting = (int(v or 0) for v in found["overruns"])
    return {"cycles": int(found["cycles"][0]), "overruns": overruns, "on_cpu": on_cpu,
            "waiting": waiting, "period_mean_ms": float(found["period"][0]),
            "period_max_ms": float(found["period"][1])}


def _states(trace: Path, rate: float) -> tuple[dict[str, int], float]:
    """How many of a trace's overruns happened in each manager state, and the median of
    its cycles' CPU time on the loop's thread (s)."""
    rows = [m for _, _, m in read_messages(str(trace), CYCLE_TOPIC)]
    work = np.array([r["work"] for r in rows])
    late = np.array([r["late"] for r in rows])
    where = Counter(rows[i]["state"] for i in np.flatnonzero(overran(work, late, 1.0 / rate)))
    return ({state: where.get(state, 0) for state in STATES},
            float(np.median([r["cpu"] for r in rows])))


def one(recording: bool, args: argparse.Namespace) -> dict[str, Any]:
    with tempfile.TemporaryDirectory(prefix="rocoma-demo-run-") as tmp:
        cmd = [sys.executable, "-m", "rocoma_can", "demo", "--drives", str(args.drives),
               "--rate", str(args.rate), "--duration", str(args.duration)]
        cmd += ["--record", tmp] if recording else ["--no-record", "--no-flight"]
        if args.priority is not None:
            cmd += ["--priority", str(args.priority)]
        done = subprocess.run(cmd, capture_output=True, text=True,
                              timeout=args.duration + 300)
        if done.returncode != 0:
            raise SystemExit(f"the demo failed (exit {done.returncode}):\n"
                             f"{done.stdout[-2000:]}{done.stderr[-2000:]}")
        result = {"recording": recording, **_summary(done.stdout)}
        if recording:
            result["by_state"], result["cpu_median_s"] = _states(Path(tmp) / "trace.mcap",
                                                                 args.rate)
        return result


def bare(cpu: float, cycles: int, args: argparse.Namespace) -> dict[str, Any]:
    """The host beside the round (host_floor.py): the same loop, as many cycles, each
    nothing but as much Python work as the recorded run's median cycle took of the loop
    thread's CPU, in the CPU's first-level cache (footprint 0): what the host's scheduling
    and CPU allowed that much work in that minute. Work over a few MiB, host_floor.py's
    other footprint, overran far more often than the demo in the same minutes (4.0, 0.6 and
    21 % against 0.3-0.4 % in one hour's three rounds): too memory-bound to stand for it."""
    r = host_floor.one(args.rate, cpu * 1e6, 0, cycles / args.rate, args.priority)
    return {"recording": None, "cycles": r["cycles"], "overruns": r["overruns"],
            "on_cpu": r["overruns"] - r["waiting"], "waiting": r["waiting"],
            "period_mean_ms": r["period_mean_ms"], "period_max_ms": r["period_max_ms"],
            "work_us": r["work_us"], "cpu_median_us": r["cpu_median_us"],
            "visits": r["visits"]}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--drives", type=int, default=12)
    parser.add_argument("--rate", type=float, default=1000.0)
    parser.add_argument("--duration", type=float, default=16.0, help="the walk-through, s")
    parser.add_argument("--repeat", type=int, default=3, help="rounds (each: on, then off)")
    parser.add_argument("--priority", type=int, default=None, metavar="1..99",
                        help="the demo's --priority: its loop SCHED_FIFO (default: normal)")
    parser.add_argument("--quick", action="store_true", help="6 drives, 200 Hz, 6 s, 1 round")
    args = parser.parse_args()
    if args.quick:
        args.drives, args.rate, args.duration, args.repeat = 6, 200.0, 6.0, 1
    runs, rows = [], []
    for _ in range(args.repeat):
        on, off = one(True, args), one(False, args)
        floor = bare(on["cpu_median_s"], on["cycles"], args)
        for label, r in (("on", on), ("off", off),
                         (f"bare loop, {floor['work_us']:.0f} µs CPU", floor)):
            runs.append(r)
            states = r.get("by_state")
            rows.append([label, r["cycles"], r["overruns"],
                         f"{100 * r['overruns'] / max(r['cycles'], 1):.2f}", r["on_cpu"],
                         r["waiting"],
                         " / ".join(str(states[s]) for s in STATES) if states else "-",
                         f"{r['period_mean_ms']:.2f}",
                         f"{r['period_max_ms']:.2f}"])
    report("demo_run", f"rocoma-can demo --drives {args.drives} --rate {args.rate:g}, "
           "recording on and off" + (f", loop SCHED_FIFO {args.priority}"
                                      if args.priority is not None else ""),
           ["run", "cycles", "overruns", "%", "on the CPU", "waiting",
            "in FAILPROOF / EMERGENCY / OK", "period mean ms", "period max ms"],
           rows, args=args, results={"runs": runs},
           notes=["overruns: cycles that ended after the next one's deadline; on the CPU / "
                  "waiting: the loop's split (rocoma_can/overrun.py). In FAILPROOF the "
                  "drives are off (bring-up; after the second fault). bare loop: the same "
                  "loop for as many cycles, each only the recorded run's median CPU time of "
                  "work, in the CPU's cache (host_floor.py): what this host's scheduling "
                  "and CPU allowed that much work in that minute."])


if __name__ == "__main__":
    main()
