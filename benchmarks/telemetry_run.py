"""What telemetry costs the loop: the whole runtime (``rocoma-can run``'s Runtime: the
hardware, the manager and its CANopen node) with simulated drives on in-process buses,
held by a PD controller at a steady rate, once per set of telemetry.

    .venv/bin/python benchmarks/telemetry_run.py [--drives 12] [--rate 1000] [--duration 20]
                                                 [--sets off,flight,record,all] [--repeat 2]

Sets: ``off`` (nothing), ``flight`` (the flight recorder, ``run``'s default), ``record``
(``--record`` and the flight recorder: the demo's default), ``foxglove`` and ``zenoh``
(each alone on top of ``record``), ``ros2`` (the ROS 2 node, ``run --ros2``, on a Zenoh
router in this process, with a subscriber to everything it publishes), ``all`` (record, flight
recorder, Zenoh bridge on loopback, Foxglove live view on loopback with one viewer, a
process of its own, subscribed to everything; ``--viewer-nice 19`` runs it niced, as a
viewer on another machine would cost the robot's nothing), ``+fd`` in a set's name (``off+fd``,
``all+fd``) runs CAN FD buses (1/5 Mbit/s, the drives' PDOs up to 64 bytes: ``demo --fd``'s
set-up), ``+proc`` (``off+proc``, ``record+fd+proc``) runs the simulated drives in a
process of their own (``demo --sim process``: the loop's process pays only for their
frames, as with real drives). Each set
runs in a fresh process, the sets alternate ``--repeat`` times, and the machine's other
load is what it is: compare sets of one run, not runs of different days.

Without ``+proc`` the simulator is stepped on the loop's thread after each write
(lockstep, the demo's ``--sim loop``): the loop's process does the drives' work too, so
these numbers are a pessimistic bound for a loop whose drives are real; with it, the
drives' process is a third busy process on the machine. Reported per set: cycles in the
steady run, missed cycle slots, overruns (the loop's own count), period mean / p99 / max,
the CPU per cycle of the loop's process, of the writer process (recording off the loop's
interpreter: rings.py, writer.py) and of the drives' process (+proc).
"""
from __future__ import annotations

import argparse
import json
import os
import resource
import socket
import subprocess
import sys
import tempfile
import threading
import time
import uuid
from pathlib import Path
from typing import Any

import numpy as np
from _report import report, stats
from _rig import missed_cycles

SETS = ("off", "flight", "record", "all")


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def _cpu_seconds(pid: int | str) -> float:
    try:
        fields = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
    except OSError:
        return float("nan")
    return (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")


def _thread_cpu() -> dict[str, float]:
    """CPU seconds so far of each Python thread of this process, by name."""
    found: dict[str, float] = {}
    for thread in threading.enumerate():
        if thread.native_id is not None:
            seconds = _cpu_seconds(f"{os.getpid()}/task/{thread.native_id}")
            found[thread.name] = found.get(thread.name, 0.0) + seconds
    return found


def one(name: str, drives: int, buses: int | None, rate: float, duration: float,
        viewer_nice: int = 0) -> dict[str, Any]:
    """Run one set in this process; its row as a dict."""
    import logging
    logging.basicConfig(level=logging.ERROR)
    from rocoma_can.cli.demo.config import default_buses, demo_config
    from rocoma_can.cli.demo.drives import InProcessSim, SimProcess
    from rocoma_can.runtime.config import validate
    from rocoma_can.runtime.system import Runtime
    parts = set(name.split("+"))
    if "all" in parts:
        parts |= {"foxglove", "zenoh"}
    if parts & {"foxglove", "zenoh"}:  # each on top of what the demo records
        parts.add("record")
    buses = default_buses(drives) if buses is None else buses
    fd = {"data_bitrate": 5_000_000} if "fd" in parts else {}
    raw = demo_config(f"bench-{uuid.uuid4().hex[:8]}", drives, rate, buses, "inproc", **fd)
    raw["manager"]["estop_must_be_cleared"] = False
    if "zenoh" in parts:
        raw["zenoh"] = {"prefix": "bench", "listen": [f"tcp/127.0.0.1:{_free_port()}"],
                        "multicast": False}
    router = _ros2_router(raw) if "ros2" in parts else None
    config = validate(raw, source="benchmark")
    sim_buses = [(b.channel, [d.node_id for d in config.drives_on(b)]) for b in config.buses]
    starts = np.zeros(int(rate * (duration + 60)) + 1000)
    count = [0]

    def on_cycle(now: float) -> None:
        k = count[0]
        if k < len(starts):
            starts[k] = now
            count[0] = k + 1

    foxglove = None
    if "foxglove" in parts:
        from rocoma_can.live.foxglove import FoxgloveConfig
        foxglove = FoxgloveConfig("127.0.0.1", _free_port())
    window: dict[str, Any] = {}
    with tempfile.TemporaryDirectory() as tmp:
        record = str(Path(tmp) / "rec") if "record" in parts else None
        flight = str(Path(tmp) / "flight") if parts & {"flight", "record"} else None
        simulator: InProcessSim | SimProcess = (
            SimProcess(sim_buses, None, drives, "fd" in parts) if "proc" in parts
            else InProcessSim(sim_buses, "inproc", None, "fd" in parts))
        try:
            with Runtime(config, record=record, on_cycle=(
                    simulator.on_cycle(on_cycle) if isinstance(simulator, InProcessSim)
                    else on_cycle),
                         flight=flight, foxglove=foxglove) as rt:
                viewer = (_viewer(foxglove.port, viewer_nice) if foxglove is not None
                          else None)

                def operate() -> None:
                    deadline = time.monotonic() + 60
                    while not rt.hardware.all_ready and time.monotonic() < deadline:
                        time.sleep(0.05)
                    rt.manager.switch_controller("pd", timeout=10.0)
                    time.sleep(1.0)  # settled
                    # (getattr: the script also measures commits from before the writer
                    # process, whose recording ran in the loop's process)
                    recorder = getattr(rt, "recorder", None)
                    writer = recorder.pid if recorder is not None else None
                    window.update(threads=_thread_cpu(), first=count[0], cpu=resource.getrusage(
                        resource.RUSAGE_SELF), writer=writer,
                        writer_cpu=_cpu_seconds(writer) if writer else 0.0,
                        state=rt.manager.state.name, overruns=rt.loop.stats.overruns,
                        sim_cpu=_cpu_seconds(simulator.pid) if simulator.pid else 0.0)
                    time.sleep(duration)
                    window.update(threads_end=_thread_cpu(), last=count[0],
                                  cpu_end=resource.getrusage(
                        resource.RUSAGE_SELF), writer_cpu_end=_cpu_seconds(writer)
                        if writer else 0.0, state_end=rt.manager.state.name,
                        overruns_end=rt.loop.stats.overruns,
                        # the work of the ring's cycles (start to end; the last 4096)
                        work_median_us=float(np.median(rt.loop.stats._work[
                            :min(rt.loop.stats.cycles, len(rt.loop.stats._work))])) * 1e6,
                        sim_cpu_end=_cpu_seconds(simulator.pid) if simulator.pid else 0.0)
                    rt.loop.stop("benchmark done")

                worker = threading.Thread(target=operate)
                worker.start()
                rt.run(duration=duration + 70, signals=False)
                worker.join(10.0)
                if viewer is not None:
                    viewer.kill()
                    viewer.wait()
                errors = (rt.recording.errors if rt.recording is not None else []) + \
                    (rt.flight.errors if rt.flight is not None else [])
        finally:
            simulator.stop()
            if router is not None:
                for session in router:
                    session.close()
    first, last = window["first"], window["last"]
    period = np.diff(starts[first:last]) * 1e6
    cycles = last - first
    cpu = (window["cpu_end"].ru_utime + window["cpu_end"].ru_stime
           - window["cpu"].ru_utime - window["cpu"].ru_stime)
    writer = window["writer_cpu_end"] - window["writer_cpu"]
    threads = {t: round((window["threads_end"][t] - window["threads"].get(t, 0.0))
                        / cycles * 1e6, 1) for t in window["threads_end"]}
    return {"set": name, "cycles": cycles, "threads_cpu_us": threads,
            "missed": missed_cycles(starts[first:last], 1.0 / rate),
            "overruns": window["overruns_end"] - window["overruns"],
            "period_us": stats(period), "loop_process_cpu_us": cpu / cycles * 1e6,
            "writer_cpu_us": writer / cycles * 1e6,
            "sim_process_cpu_us": (window["sim_cpu_end"] - window["sim_cpu"]) / cycles * 1e6,
            "state": window["state_end"], "work_median_us": window["work_median_us"],
            "errors": errors}


def _ros2_router(raw: dict[str, Any]) -> list[Any]:
    """A Zenoh router on loopback (rmw_zenoh's rmw_zenohd stands there on a robot), the
    config's ros2: section connected to it, and a peer subscribed to every topic it
    publishes (as ros2 topic echo would be): the sessions, to close."""
    import zenoh
    endpoint = f"tcp/127.0.0.1:{_free_port()}"
    sessions = []
    for mode, key in (("router", "listen"), ("client", "connect")):
        conf = zenoh.Config()
        conf.insert_json5("mode", json.dumps(mode))
        conf.insert_json5(f"{key}/endpoints", json.dumps([endpoint]))
        conf.insert_json5("scouting/multicast/enabled", "false")
        sessions.append(zenoh.open(conf))
    sessions[1].declare_subscriber("0/**", lambda sample: None)
    raw["ros2"] = {"connect": [endpoint]}
    return sessions


def run_set(name: str, args: argparse.Namespace) -> dict[str, Any]:
    """One set in a fresh process (``--one``); its row as a dict, or {"error": why}."""
    cmd = [sys.executable, __file__, "--one", name, "--drives", str(args.drives),
           "--rate", str(args.rate), "--duration", str(args.duration),
           "--viewer-nice", str(getattr(args, "viewer_nice", 0))]
    if getattr(args, "buses", None) is not None:
        cmd += ["--buses", str(args.buses)]
    done = subprocess.run(cmd, capture_output=True, text=True, timeout=args.duration + 180)
    if done.returncode != 0:
        return {"set": name, "error": (done.stderr.strip().splitlines() or ["?"])[-1]}
    result: dict[str, Any] = json.loads(done.stdout.strip().splitlines()[-1])
    return result


_VIEWER = """
import json, sys
from websockets.sync.client import connect
with connect(f"ws://127.0.0.1:{sys.argv[1]}", subprotocols=["foxglove.sdk.v1"]) as ws:
    subscriptions = 0
    for message in ws:
        if isinstance(message, str):
            msg = json.loads(message)
            if msg.get("op") == "advertise":
                channels = msg["channels"]
                ws.send(json.dumps({"op": "subscribe", "subscriptions": [
                    {"id": subscriptions + k, "channelId": c["id"]}
                    for k, c in enumerate(channels)]}))
                subscriptions += len(channels)
"""


def _viewer(port: int, nice: int) -> subprocess.Popen[bytes]:
    """A Foxglove viewer in a process of its own (its reading takes none of the loop's
    interpreter, only the machine's CPU: at ``nice``) that subscribes to every channel and
    reads on."""
    return subprocess.Popen([sys.executable, "-c", _VIEWER, str(port)],
                            stderr=subprocess.DEVNULL, preexec_fn=lambda: os.nice(nice))


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--drives", type=int, default=12)
    parser.add_argument("--buses", type=int, default=None, help="default: as the demo")
    parser.add_argument("--rate", type=float, default=1000.0)
    parser.add_argument("--duration", type=float, default=20.0, help="s of steady run")
    parser.add_argument("--sets", default=",".join(SETS))
    parser.add_argument("--repeat", type=int, default=1)
    parser.add_argument("--viewer-nice", type=int, default=0, metavar="N",
                        help="the viewer process's niceness (19: as if it ran elsewhere, "
                             "taking only what the robot's machine does not need)")
    parser.add_argument("--quick", action="store_true",
                        help="sets off,all; 6 drives at 200 Hz for 3 s")
    parser.add_argument("--one", help=argparse.SUPPRESS)
    args = parser.parse_args()
    if args.quick:
        args.duration, args.rate, args.drives, args.sets = 3.0, 200.0, 6, "off,all"
    if args.one:
        print(json.dumps(one(args.one, args.drives, args.buses, args.rate, args.duration,
                             args.viewer_nice)))
        return
    rows, results, notes = [], [], []
    for _ in range(args.repeat):
        for name in args.sets.split(","):
            r = run_set(name, args)
            if "error" in r:
                rows.append([name, "failed", "", "", "", "", "", "", "", "", r["error"]])
                continue
            results.append(r)
            p = r["period_us"]
            busiest = sorted(r["threads_cpu_us"].items(), key=lambda kv: -kv[1])[:4]
            notes.append(f"{name}: CPU µs per cycle of its busiest threads: " + ", ".join(
                f"{t} {us:g}" for t, us in busiest))
            rows.append([name, r["cycles"], r["missed"], r["overruns"], f"{p['mean']:.1f}",
                         f"{p['p99']:.0f}", f"{p['max']:.0f}",
                         f"{r['loop_process_cpu_us']:.0f}", f"{r['writer_cpu_us']:.0f}",
                         f"{r['sim_process_cpu_us']:.0f}" if "proc" in name else "-",
                         r["state"] + (f"; {r['errors'][0]}" if r["errors"] else "")])
    report("telemetry_run", f"The loop at {args.rate:g} Hz, {args.drives} drives, with and "
           "without telemetry",
           ["set", "cycles", "missed", "overruns", "period mean us", "p99 us", "max us",
            "loop process CPU us/cycle", "writer CPU us/cycle", "drives' process CPU us/cycle",
            "end state"],
           rows, args=args, results={"runs": results},
           notes=["missed: cycle slots with no cycle start (a gap of k periods misses k - 1); "
                  "overruns: cycles that ended after the next one's deadline (the loop's "
                  "own count, rocoma_can/overrun.py).",
                  "loop process CPU includes the simulated drives (stepped on the loop's "
                  "thread) unless the set has +proc (their own process); the writer process "
                  "records (rings.py, writer.py).", *notes])


if __name__ == "__main__":
    main()
