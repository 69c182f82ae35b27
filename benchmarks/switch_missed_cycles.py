"""Missed cycles while the manager switches to a controller whose initialize takes 500 ms.

    .venv/bin/python benchmarks/switch_missed_cycles.py [--rate 1000] [--repeat 3]
                                                         [--init 0.5] [--drives 12]

The switch runs on the manager's switcher thread; the loop (rocoma_can.runtime.ControlLoop)
must keep its rate meanwhile. Two set-ups: "plain" = the manager over a plain JointState /
JointCommand of 12 joints (no bus), and "drives" = the hardware layer with simulated drives
on the in-process bus (inproc; simulator on a thread in this process). For each switch:
cycles missed and the longest period between the switch request and its result, next to the
same numbers for a window of equal length just before it (baseline), so the switch's own
cost shows.
"""
from __future__ import annotations

import argparse
import logging
import math
import time
from typing import Any

from _report import report, stats
from _rig import Rig, Script, StartLog, missed_cycles, run_script

from rocoma_can import ControllerManager, SwitchResult
from rocoma_can.controllers.pd import JointPD
from rocoma_can.controllers.torque_off import TorqueOff
from rocoma_can.drivers.protocol.joints import JointCommand, JointState
from rocoma_can.runtime import ControlLoop

BASELINE_S = 0.6  # settle time before each switch (also the longest baseline window)


class SlowInit(JointPD):
    """A PD whose initialize blocks for ``seconds`` (loading a model, planning, ...)."""

    def __init__(self, name: str, seconds: float, **kwargs: Any) -> None:
        super().__init__(name, **kwargs)
        self.seconds = seconds

    def initialize(self, dt: float) -> bool:
        time.sleep(self.seconds)
        return super().initialize(dt)


class Switches:
    """on_cycle body: settle, switch to the other controller, wait for the result; repeat."""

    def __init__(self, manager: ControllerManager, names: tuple[str, str], repeat: int) -> None:
        self.manager = manager
        self.names = names
        self.repeat = repeat
        self.windows: list[tuple[float, float, int]] = []  # (requested, finished, result)
        self._since = math.nan
        self._future: Any = None

    def __call__(self, now: float) -> bool:
        if self._future is None:
            if self._since != self._since:
                self._since = now
            if now - self._since >= BASELINE_S:
                target = self.names[len(self.windows) % 2]
                self._requested = now
                self._future = self.manager.request_switch(target)
            return False
        if self._future.done():
            self.windows.append((self._requested, now, int(self._future.result())))
            self._future, self._since = None, math.nan
        return len(self.windows) >= self.repeat


class NoHardware:
    """The plain set-up: ControlLoop's read and write with nothing behind them."""

    def read(self, now: float) -> tuple[()]:
        return ()

    def write(self, state: Any, switch_count: int | None = None) -> None:
        pass


def measure(log: StartLog, windows: list[tuple[float, float, int]], dt: float) -> dict:
    during_missed, during_max, base_missed, base_max, results = [], [], [], [], []
    for t0, t1, result in windows:
        span = min(t1 - t0, BASELINE_S - 2 * dt)
        during = log.window(t0, t1)
        before = log.window(t0 - span, t0)
        during_missed.append(missed_cycles(during, dt))
        base_missed.append(missed_cycles(before, dt))
        during_max.append(float(max(during[1:] - during[:-1], default=0.0)) * 1e3
                          if len(during) > 1 else math.nan)
        base_max.append(float(max(before[1:] - before[:-1], default=0.0)) * 1e3
                        if len(before) > 1 else math.nan)
        results.append(SwitchResult(result).name)
    return {"switch_s": stats([w[1] - w[0] for w in windows]), "results": results,
            "missed_during": during_missed, "max_period_ms_during": during_max,
            "missed_baseline": base_missed, "max_period_ms_baseline": base_max}


def run_plain(args: argparse.Namespace) -> tuple[dict, bool]:
    state, command = JointState.zeros(args.joints), JointCommand.zeros(args.joints)
    dt = 1.0 / args.rate
    with ControllerManager(TorqueOff(), dt, state, command) as mgr:
        for ctrl in (JointPD("pd", kp=100.0, kd=4.0), SlowInit("slow", args.init)):
            if not mgr.add_controller(ctrl):
                raise RuntimeError(f"could not add {ctrl.name}")
        if mgr.switch_controller("pd", timeout=5.0) != SwitchResult.SWITCHED:
            raise RuntimeError("could not switch to pd")
        body = Switches(mgr, ("slow", "pd"), args.repeat)
        timeout = args.repeat * (BASELINE_S + args.init + 1.0) + 5.0
        log = StartLog(int(args.rate * (timeout + 5)))
        loop = ControlLoop(NoHardware(), mgr, args.rate,
                           on_cycle=lambda now: (log.add(now), body(now) and
                                                 loop.stop("done")),
                           stats_size=len(log.starts))
        loop.run(timeout)
    return measure(log, body.windows, dt), len(body.windows) < args.repeat


def run_drives(args: argparse.Namespace) -> tuple[dict, bool]:
    with Rig(args.drives, args.rate) as rig:
        rig.add(JointPD("pd", mode="CSP"))
        rig.add(SlowInit("slow", args.init, mode="CSP"))
        body = Switches(rig.manager, ("slow", "pd"), args.repeat)
        timeout = 10.0 + args.repeat * (BASELINE_S + args.init + 1.0)
        log = StartLog(int(args.rate * (timeout + 10)))
        script = Script(rig, "pd", body, timeout=timeout)
        run_script(rig, script, len(log.starts), log)
    return measure(log, body.windows, 1.0 / args.rate), script.timed_out


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--rate", type=float, default=1000.0, help="Hz")
    parser.add_argument("--init", type=float, default=0.5, help="seconds initialize blocks")
    parser.add_argument("--repeat", type=int, default=3, help="switches per set-up")
    parser.add_argument("--joints", type=int, default=12, help="plain set-up")
    parser.add_argument("--drives", type=int, default=12, help="drives set-up")
    parser.add_argument("--setups", default="plain,drives")
    parser.add_argument("--quick", action="store_true", help="1 switch of 0.2 s, 4 drives")
    args = parser.parse_args()
    if args.quick:
        args.repeat, args.init, args.drives = 1, 0.2, 4
    logging.basicConfig(level=logging.CRITICAL)

    rows, data, notes = [], {}, []
    for setup in args.setups.split(","):
        result, timed_out = {"plain": run_plain, "drives": run_drives}[setup](args)
        if timed_out:
            notes.append(f"{setup}: TIMED OUT, partial numbers.")
        label = (f"plain, {args.joints} joints" if setup == "plain"
                 else f"drives, {args.drives} simulated")
        for k, res in enumerate(result["results"]):
            rows.append([label, k + 1, res, result["missed_during"][k],
                         result["max_period_ms_during"][k], result["missed_baseline"][k],
                         result["max_period_ms_baseline"][k]])
        data[setup] = result
    notes.insert(0, f"loop at {args.rate:g} Hz; initialize blocks {args.init:g} s; baseline = "
                    "a window of the same length (at most "
                    f"{BASELINE_S:g} s) right before the switch request.")
    report("switch_missed_cycles", "Missed cycles during a slow switch",
           ["set-up", "switch", "result", "missed during", "max period ms",
            "missed baseline", "baseline max ms"], rows, args=args, notes=notes,
           results=data)


if __name__ == "__main__":
    main()
