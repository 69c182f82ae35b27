"""benchmarks/*.py: every benchmark runs in its quickest mode and writes the JSON it promises.

Timing is never asserted here (a shared 2-core machine): only that each script exits 0 and
its result file has the keys the README and later comparisons read.
"""
from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import pytest
from fixtures.paths import ROOT

BENCHMARKS = ROOT / "benchmarks"
COMMON = {"benchmark", "title", "machine", "args", "headers", "rows", "results"}

CASES = {
    "bus_load": lambda r: {"frames_per_cycle", "fits_500k", "fits_1000k"} <= set(r[0]),
    "manager_overhead": lambda r: {"trivial: mgr.update()", "pd: mgr.update()",
                                   "e-stop: advance fails -> damp",
                                   "damp: mgr.update() in EMERGENCY",
                                   "estop_over_steady_emergency"} <= set(r),
    "loop_run": lambda r: {"mode", "missed_cycles", "period_us", "jitter_us", "estops",
                           "final_state", "buses"} <= set(r) and r["mode"] == "in-process",
    "estop_latency": lambda r: len(r["cases"]) == 2 and all(
        {"first_frame_us", "all_drives_us", "first_frame_cycles", "lost"} <= set(c)
        for c in r["cases"].values()),
    "controllers": lambda r: {"damp", "hold", "pd", "torque_off"} <= set(r) and all(
        {"initialize_fast_us", "advance_us"} <= set(c) for c in r.values()),
    "cycle_cost": lambda r: [row["drives"] for row in r] == [1, 6, 12, 24] and all(
        {"frames_per_cycle", "ours_us", "canopen_us", "speedup_median", "ns_per_frame",
         "core_share_at_30k_frames_s"} <= set(row) for row in r),
    "recording_cost": lambda r: [row["joints"] for row in r] == [3, 6, 12, 24] and all(
        {"loop_record_us", "loop_frame_us", "writer_row_us", "writer_candump_us",
         "writer_mcap_frame_us"} <= set(row) and row["writer_flight_record_s"] > 0
        for row in r),
    "telemetry_run": lambda r: [run["set"] for run in r["runs"]] == ["off", "all"] and all(
        {"cycles", "missed", "period_us", "loop_process_cpu_us", "writer_cpu_us",
         "errors"} <= set(run) and not run["errors"] and run["cycles"] > 0
        for run in r["runs"]),
    "demo_run": lambda r: [run["recording"] for run in r["runs"]] == [True, False, None]
    and all(
        {"cycles", "overruns", "on_cpu", "waiting", "period_mean_ms"} <= set(run)
        and run["cycles"] > 0 and run["on_cpu"] + run["waiting"] == run["overruns"]
        for run in r["runs"]) and sum(r["runs"][0]["by_state"].values())
    == r["runs"][0]["overruns"] and r["runs"][2]["work_us"] > 0
    and r["runs"][2]["work_us"] == 1e6 * r["runs"][0]["cpu_median_s"],
    "ros2_run": lambda r: [run["set"] for run in r["runs"]] == ["off", "ros2", "bare"]
    and all({"cycles", "overruns", "work_median_us"} <= set(run) and run["cycles"] > 0
            for run in r["runs"]) and r["runs"][2]["work_us"] == r["runs"][0]["work_median_us"]
    and r["runs"][1]["threads_cpu_us"].get("ros2-node", 0) > 0,
    "host_floor": lambda r: [(run["rate"], run["footprint_kib"], run["work_us"])
                             for run in r["runs"]] == [(1000.0, 0, 300.0), (1000.0, 4096, 300.0)]
    and all(
        {"cycles", "overruns", "waiting", "cpu_median_us", "period_mean_ms"} <= set(run)
        and run["cycles"] > 0 and run["waiting"] <= run["overruns"] for run in r["runs"]),
    "sim_cost": lambda r: [row["drives"] for row in r] == [1, 3, 6, 12] and all(
        {"per_sync_us", "per_drive_us", "bench_core_share"} <= set(row) for row in r),
    "urdf_read": lambda r: [row["links"] for row in r] == [1000, 4000] and all(
        {"mbytes", "median_ms", "per_link_us"} <= set(row) for row in r),
    "cli_start": lambda r: all({"seconds", "modules", "numpy", "exit_code"} <= set(c)
                               for c in r.values())
    and not r["rocoma-can status --help"]["numpy"],
    "switch_missed_cycles": lambda r: {"plain", "drives"} <= set(r) and all(
        {"missed_during", "max_period_ms_during", "missed_baseline", "results"} <= set(s)
        for s in r.values()),
}


@pytest.mark.parametrize("name", sorted(CASES))
def test_benchmark_runs_quick_and_writes_json(name: str, tmp_path: Path) -> None:
    env = {**os.environ, "ROCOMA_BENCH_RESULTS": str(tmp_path)}
    proc = subprocess.run([sys.executable, str(BENCHMARKS / f"{name}.py"), "--quick"],
                          cwd=BENCHMARKS.parent, env=env, capture_output=True, text=True,
                          timeout=120)
    assert proc.returncode == 0, proc.stdout[-2000:] + proc.stderr[-4000:]
    data = json.loads((tmp_path / f"{name}.json").read_text())
    assert COMMON <= set(data), sorted(COMMON - set(data))
    assert data["benchmark"] == name and data["rows"]
    assert CASES[name](data["results"]), data["results"]


def test_loop_run_on_can_fd_buses_says_their_load(tmp_path: Path) -> None:
    """--fd: the drives map one RPDO and one TPDO each on CAN FD buses; the JSON says the
    busiest bus's load as a 1/5 Mbit/s FD bus would carry it."""
    env = {**os.environ, "ROCOMA_BENCH_RESULTS": str(tmp_path)}
    proc = subprocess.run([sys.executable, str(BENCHMARKS / "loop_run.py"), "--quick", "--fd",
                           "--drives", "6", "--buses", "2", "--rate", "500"],
                          cwd=BENCHMARKS.parent, env=env, capture_output=True, text=True,
                          timeout=120)
    assert proc.returncode == 0, proc.stdout[-2000:] + proc.stderr[-4000:]
    results = json.loads((tmp_path / "loop_run.json").read_text())["results"]
    assert results["fd"] and results["data_bitrate"] == 5_000_000
    assert results["frames_per_cycle"] == 3 * 2 + 1 and 0 < results["bus_load"] < 1
    assert results["simulator"].endswith(", CAN FD") and results["phase"] == "done"
