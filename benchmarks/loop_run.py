"""A steady run of the real control loop with simulated drives: missed cycles, period, jitter.

    .venv/bin/python benchmarks/loop_run.py [--drives 12] [--buses 4] [--rate 1000]
                                            [--duration 60] [--fd]
    tools/vcan-run .venv/bin/python benchmarks/loop_run.py --separate-process --rate 200

The loop is rocoma_can.runtime.ControlLoop (read -> manager.update -> write, sleep then spin
to an absolute deadline); the drives are brought up, a JointPD (CSP) holds them, then the
loop runs for --duration seconds. Default: the simulator runs in this process on an
in-process bus (``--interface inproc``), stepped on the loop's thread right after each write
(lockstep, as ``rocoma-can demo`` runs it); ``--sim-thread`` gives it a receive thread of
its own, which shares the GIL and the 2 cores with the loop; ``--interface virtual``
(python-can's bus, which copies every frame once per receiver) always has a thread. With
--separate-process the simulator is a ``rocoma-can sim`` subprocess on SocketCAN vcan0,
which this machine only has inside user-mode-linux (tools/vcan-run), where every syscall
is slow: use a rate the VM can sustain there. The JSON records which mode ran. ``--buses N``
spreads the drives over N buses (one simulated segment each; vcan0 and vcan1 with
--separate-process), one manager over all of them. ``--fd``: CAN FD buses whose drives map
PDOs of up to 64 bytes (one RPDO and one TPDO each a cycle, as ``rocoma-can demo --fd``);
the bus load they would have at 1 Mbit/s arbitration and ``--data-bitrate`` is printed.
"""
from __future__ import annotations

import argparse
import logging
import os
import subprocess
import sys
from collections.abc import Iterator
from contextlib import contextmanager

import numpy as np
from _report import report, stats
from _rig import Rig, Script, StartLog, missed_cycles, run_script

from rocoma_can import ManagerState
from rocoma_can.cli.demo.config import FD_BITRATE, FD_DATA_BITRATE
from rocoma_can.controllers.hold import Hold
from rocoma_can.controllers.pd import JointPD
from rocoma_can.drivers.plan.pdo_layout import DriveLayout
from rocoma_can.runtime.bus_load import BusLoad, bus_load


def _spin_us(text: str) -> float:
    value = float(text)
    if value < 0:
        raise argparse.ArgumentTypeError(f"expected µs >= 0, got {text}")
    return value


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--drives", type=int, default=12)
    parser.add_argument("--buses", type=int, default=1, help="buses the drives are spread over")
    parser.add_argument("--rate", type=float, default=1000.0, help="Hz")
    parser.add_argument("--duration", type=float, default=60.0, help="seconds of steady run")
    parser.add_argument("--separate-process", action="store_true",
                        help="simulator as a subprocess on socketcan vcan0 (tools/vcan-run)")
    parser.add_argument("--interface", choices=("inproc", "virtual"), default="inproc",
                        help="in-process bus of the default mode")
    parser.add_argument("--spin-us", type=_spin_us, default=None,
                        help="the loop's busy-wait before each deadline, µs (default: the "
                             "loop's, 500 or half a period; 0 sleeps to the deadline)")
    parser.add_argument("--nice-hogs", type=int, default=0, metavar="N",
                        help="N CPU hogs at nice 19 beside the run (background work the "
                             "loop should not notice)")
    parser.add_argument("--sim-thread", action="store_true",
                        help="in-process simulator on a thread of its own instead of stepped "
                             "on the loop's thread after each write (lockstep)")
    parser.add_argument("--fd", action="store_true",
                        help="CAN FD buses, the drives' PDOs up to 64 bytes")
    parser.add_argument("--data-bitrate", type=int, default=FD_DATA_BITRATE,
                        help="the FD data phase the printed bus load assumes, bit/s")
    parser.add_argument("--quick", action="store_true", help="--duration 2")
    args = parser.parse_args()
    if args.spin_us is not None and not args.spin_us * 1e-6 < 1.0 / args.rate:
        parser.error(f"--spin-us {args.spin_us:g} is not shorter than one period "
                     f"({1e6 / args.rate:.1f} µs at --rate {args.rate:g})")
    if args.quick:
        args.duration = 2.0
    logging.basicConfig(level=logging.ERROR)
    lockstep = not (args.separate_process or args.sim_thread or args.interface == "virtual")
    mode = ("separate process, socketcan" if args.separate_process
            else f"in-process {'lockstep' if lockstep else 'thread'}, {args.interface} bus")
    if args.buses > 1:
        mode += f" x{args.buses}"
    if args.fd:
        mode += ", CAN FD"
    if args.nice_hogs:
        mode += f", {args.nice_hogs} nice-19 hogs"

    estops: list[str] = []
    with _nice_hogs(args.nice_hogs), Rig(args.drives, args.rate,
                                         separate_process=args.separate_process,
             buses=args.buses, interface=args.interface, sim_thread=args.sim_thread,
             fd=args.fd) as rig:
        rig.add(JointPD("pd", mode="CSP"), emergency=Hold("hold", mode="CSP"))
        busiest = _busiest_bus(rig, args.rate, args.data_bitrate if args.fd else None)
        rig.manager.subscribe(lambda e: estops.append(e.cause) if e.kind.name ==
                              "EMERGENCY_STOP" else None)
        run_from = []

        def body(now: float) -> bool:
            if not run_from:
                run_from.append(now)
            return now - run_from[0] >= args.duration

        cycles = int(args.rate * (args.duration + 20)) + 100
        log = StartLog(cycles)
        script = Script(rig, "pd", body, timeout=args.duration + 15.0)
        summary = run_script(rig, script, cycles, log,
                             None if args.spin_us is None else args.spin_us * 1e-6)
        spin_us = script.loop.spin * 1e6
        final_state = ManagerState(int(script.loop.last_state)).name
        enabled_at_end = int(rig.hardware.enabled.sum())
        tx_errors = rig.hardware.tx_errors
        cycles_total = rig.hardware.cycles

    dt = 1.0 / args.rate
    starts = log.window(script.ready_at)
    periods_us = np.diff(starts) * 1e6
    p = stats(periods_us)
    jitter_us = np.abs(periods_us - dt * 1e6)
    j = stats(jitter_us)
    missed = missed_cycles(starts, dt)
    steady_s = float(starts[-1] - starts[0]) if len(starts) > 1 else 0.0
    rows = [[mode, args.drives, args.buses, f"{args.rate:g}", f"{busiest.load:.0%}",
             f"{spin_us:.0f}", f"{steady_s:.1f}", len(starts),
             missed, p["median"], p["p99"], p["max"], j["p99"], len(estops), final_state]]
    notes = [f"period and jitter (|period - {dt * 1e6:.0f} us|) over the steady run after "
             "bring-up and enable; missed = cycle slots with no cycle start (a gap of k "
             "periods misses k - 1).",
             f"ControlLoop summary over its ring: {summary.line()}",
             f"bus load: the busiest bus as a real one, worst case: {busiest.explain()} "
             f"({busiest.frames_per_cycle} frames a cycle)"]
    if script.timed_out:
        notes.append(f"TIMED OUT in phase {script.phase}: the numbers are partial.")
    report("loop_run", f"Control loop at {args.rate:g} Hz with {args.drives} simulated drives",
           ["simulator", "drives", "buses", "Hz", "bus load", "spin us", "run s", "cycles",
            "missed",
            "period p50 us",
            "p99 us", "max us", "jitter p99 us", "e-stops", "end state"],
           rows, args=args, notes=notes,
           results={"mode": "separate-process" if args.separate_process else "in-process",
                    "simulator": mode, "interface": None if args.separate_process
                    else args.interface, "drives": args.drives, "buses": args.buses,
                    "rate_hz": args.rate, "spin_us": spin_us, "fd": args.fd,
                    "data_bitrate": args.data_bitrate if args.fd else None,
                    "bus_load": busiest.load, "frames_per_cycle": busiest.frames_per_cycle,
                    "steady_seconds": steady_s, "cycles": len(starts),
                    "missed_cycles": missed, "period_us": p, "jitter_us": j,
                    "estops": len(estops), "estop_causes": estops[:10],
                    "final_state": final_state, "enabled_drives_at_end": enabled_at_end,
                    "tx_errors": tx_errors, "hardware_cycles": cycles_total,
                    "timed_out": script.timed_out, "phase": script.phase,
                    "loop_summary": summary.__dict__})


@contextmanager
def _nice_hogs(n: int) -> Iterator[None]:
    """``n`` processes spinning at nice 19 for the run, then killed."""
    hogs = [subprocess.Popen([sys.executable, "-c", "while 1: pass"],
                             preexec_fn=lambda: os.nice(19)) for _ in range(n)]
    try:
        yield
    finally:
        for hog in hogs:
            hog.kill()
            hog.wait()


def _busiest_bus(rig: Rig, rate: float, data_bitrate: int | None) -> BusLoad:
    """The load of the bus with the most drives, as a 1 Mbit/s bus (CAN FD: with this data
    phase) would carry it: the in-process buses carry anything."""
    hw = rig.hardware
    on: dict[str, list[DriveLayout]] = {}
    for d, layout in zip(hw.drives_config, hw.layouts):
        on.setdefault(d.bus, []).append(layout)
    return bus_load(max(on.values(), key=len), rate, FD_BITRATE, data_bitrate)


if __name__ == "__main__":
    main()
