"""Run every benchmark one after the other with short settings (a few minutes in all).

    .venv/bin/python benchmarks/run_all.py [--quick]

Each benchmark runs as its own process (so one's threads and GC state cannot colour the
next), prints its table and writes benchmarks/results/<name>.json. --quick runs each in its
quickest mode (what tests/tools/test_benchmarks_smoke.py does). Exit status: the number of
benchmarks that failed.
"""
from __future__ import annotations

import argparse
import subprocess
import sys
import time
from pathlib import Path

HERE = Path(__file__).resolve().parent

#: name -> arguments for the short run (the defaults of each script are longer)
SHORT = {
    "bus_load": [],
    "manager_overhead": [],
    "controllers": ["--repeat", "5000"],
    "cycle_cost": [],
    "loop_run": ["--duration", "10"],
    "estop_latency": [],
    "switch_missed_cycles": [],
    "cli_start": [],
    "recording_cost": [],
    "telemetry_run": ["--duration", "10"],
    "demo_run": ["--repeat", "1"],
    "ros2_run": ["--repeat", "1", "--duration", "10"],
    "host_floor": ["--work", "300,400", "--duration", "4", "--repeat", "1"],
    "sim_cost": [],
    "urdf_read": [],
}


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--quick", action="store_true")
    parser.add_argument("--only", default="", help="comma-separated names")
    args = parser.parse_args()
    names = [n for n in SHORT if not args.only or n in args.only.split(",")]
    failed = []
    for name in names:
        script = HERE / f"{name}.py"
        extra = ["--quick"] if args.quick else SHORT[name]
        t0 = time.monotonic()
        rc = subprocess.call([sys.executable, str(script), *extra], cwd=HERE.parent)
        print(f"\n({name}: exit {rc}, {time.monotonic() - t0:.1f} s)", flush=True)
        if rc:
            failed.append(name)
    if failed:
        print(f"\nfailed: {', '.join(failed)}")
    return len(failed)


if __name__ == "__main__":
    sys.exit(main())
