"""E-stop latency on the bus, with the real loop, hardware layer and simulated drives.

    .venv/bin/python benchmarks/estop_latency.py [--drives 12] [--rate 500] [--repeat 30]

(a) failing advance -> first emergency frame: a JointPD (CSP) whose advance starts returning
    False; the emergency controller QuickStop takes over in that update call, so its first
    RPDO (controlword 0x0002 quick stop, or 0x0000 torque off if the manager fell to
    FAILPROOF) is sent in the same cycle. Measured from the failing advance call to the
    first such frame received by a listener on the bus, and to the last drive's one.
(b) e-stop CAN frame in -> torque-off frames out: an e-stop frame on the e-stop COB-ID
    (0x2130; drained by the hardware's read with the drives' frames, as Runtime wires it)
    while a controller with no emergency controller runs: the manager goes to FAILPROOF and
    every drive gets controlword 0x0000. Measured from the send of the e-stop frame, which
    the loop thread sends right after a cycle's write.
Cycles = loop cycle of the frame minus loop cycle of the failure (a) / of the cycle that sent
the e-stop frame (b): (a) 0 = same cycle; (b) 1 = the next cycle, the first whose read can
see the frame (the target: it acts in the cycle that reads it). Each repetition re-enables
the drives first (not timed).
"""
from __future__ import annotations

import argparse
import logging
import math
import threading
import time

import can
from _report import report, stats
from _rig import ESTOP_COB_ID, Rig, Script, run_script

from rocoma_can import ManagerState
from rocoma_can.controllers.pd import JointPD
from rocoma_can.controllers.quick_stop import QuickStop
from rocoma_can.drivers.link.bus import open_bus
from rocoma_can.drivers.protocol import cia301

STOP_CONTROLWORDS = (0x0000, 0x0002)  # torque off (disable voltage), quick stop
SETTLE_CYCLES = 20                    # OK and enabled this long before each trigger
WAIT_S = 1.0                          # a reaction not seen within this is counted as lost


class FailingPD(JointPD):
    """A PD that fails on request, stamping when and in which cycle its advance failed."""

    def __init__(self, name: str, cycle_of, **kwargs) -> None:
        super().__init__(name, **kwargs)
        self.fail = False
        self.failed_at = math.nan
        self.failed_cycle = -1
        self._cycle_of = cycle_of

    def advance(self, dt: float) -> bool:
        if self.fail:
            self.fail = False
            self.failed_at = time.monotonic()
            self.failed_cycle = self._cycle_of()
            return False
        return super().advance(dt)


class StopFrames(can.Listener):
    """First frame with a stop controlword per drive after ``arm`` (on the Notifier thread)."""

    def __init__(self, drives: int, cycle_of) -> None:
        self._node_of = {cia301.RPDO_BASE[0] + n: n for n in range(1, drives + 1)}
        self._cycle_of = cycle_of
        self.seen: dict[int, tuple[float, int]] = {}
        self.armed = False
        self.done = threading.Event()
        self._n = drives

    def arm(self) -> None:
        self.seen = {}
        self.done.clear()
        self.armed = True

    def on_message_received(self, msg: can.Message) -> None:
        node = self._node_of.get(msg.arbitration_id)
        if node is None or not self.armed or node in self.seen or msg.dlc < 2:
            return
        if (msg.data[0] | msg.data[1] << 8) in STOP_CONTROLWORDS:
            self.seen[node] = (time.monotonic(), self._cycle_of())
            if len(self.seen) == self._n:
                self.armed = False
                self.done.set()

    def on_error(self, exc: Exception) -> None:
        pass


class Trials:
    """The repetition state machine, stepped from the loop's on_cycle."""

    def __init__(self, rig: Rig, cases: list[tuple[str, FailingPD]], repeat: int,
                 listener: StopFrames, injector: can.BusABC) -> None:
        self.rig, self.cases, self.repeat = rig, cases, repeat
        self.listener, self.injector = listener, injector
        self.results = {case: [] for case, _ in cases}
        self.lost = {case: 0 for case, _ in cases}
        self.case = 0
        self.step = "settle"
        self.count = 0
        self.t0 = math.nan
        self.c0 = -1
        self.pending = None

    def __call__(self, now: float) -> bool:
        hw, mgr = self.rig.hardware, self.rig.manager
        name, ctrl = self.cases[self.case]
        if self.step == "settle":
            on = (mgr.state == ManagerState.OK and mgr.active_controller_name == ctrl.name
                  and hw.all_enabled)
            self.count = self.count + 1 if on else 0
            if self.count < SETTLE_CYCLES:
                if not hw.all_ready and not hw.starting:
                    hw.recover()  # a supervision fault (e.g. late TPDOs under load)
                if not on and (self.pending is None or self.pending.done()) and \
                        (mgr.state != ManagerState.OK or mgr.active_controller_name != ctrl.name):
                    self.pending = mgr.request_switch(ctrl.name)
                return False
            self.listener.arm()
            if name.startswith("a"):
                ctrl.fail = True  # fails in the next cycle's update
            else:
                self.c0 = hw.cycles
                self.t0 = time.monotonic()
                self.injector.send(can.Message(arbitration_id=ESTOP_COB_ID, data=b"",
                                               is_extended_id=False), timeout=0.1)
            self.step, self.t_trigger = "wait", now
            return False
        # step == "wait"
        if not self.listener.done.is_set():
            if now - self.t_trigger > WAIT_S:
                self.listener.armed = False
                self.lost[name] += 1
                self._next()
            return False
        if name.startswith("a"):
            t0, c0 = ctrl.failed_at, ctrl.failed_cycle
        else:
            t0, c0 = self.t0, self.c0
        seen = sorted(self.listener.seen.values())
        self.results[name].append(((seen[0][0] - t0) * 1e6, (seen[-1][0] - t0) * 1e6,
                                   seen[0][1] - c0, seen[-1][1] - c0))
        return self._next()

    def _next(self) -> bool:
        name = self.cases[self.case][0]
        self.step, self.count = "settle", 0
        if len(self.results[name]) + self.lost[name] >= self.repeat:
            self.case += 1
            self.pending = None
        return self.case >= len(self.cases)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--drives", type=int, default=12)
    parser.add_argument("--rate", type=float, default=250.0, help="Hz")
    parser.add_argument("--repeat", type=int, default=30)
    parser.add_argument("--quick", action="store_true", help="4 drives, 5 repetitions")
    args = parser.parse_args()
    if args.quick:
        args.drives, args.repeat = 4, 5
    logging.basicConfig(level=logging.CRITICAL)

    with Rig(args.drives, args.rate) as rig:
        cycle_of = lambda: rig.hardware.cycles  # noqa: E731 - read on other threads
        pd_a = FailingPD("pd_quick_stop", cycle_of, mode="CSP")
        pd_b = FailingPD("pd_no_emergency", cycle_of, mode="CSP")
        rig.add(pd_a, emergency=QuickStop("quick_stop"))
        rig.add(pd_b)
        listen_bus = open_bus(rig.interface, rig.channel, receive_own_messages=False)
        injector = open_bus(rig.interface, rig.channel, receive_own_messages=False)
        listener = StopFrames(args.drives, cycle_of)
        notifier = can.Notifier(listen_bus, [listener], timeout=0.05)
        try:
            cases = [("a: failing advance -> first emergency frame", pd_a),
                     ("b: e-stop frame -> torque-off frames", pd_b)]
            trials = Trials(rig, cases, args.repeat, listener, injector)
            timeout = 10.0 + args.repeat * 2 * 0.5
            script = Script(rig, pd_a.name, trials, timeout=timeout)
            run_script(rig, script, int(args.rate * (timeout + 10)))
        finally:
            notifier.stop(2.0)
            listen_bus.shutdown()
            injector.shutdown()

    rows, data = [], {}
    for name, samples in trials.results.items():
        first = stats([s[0] for s in samples])
        last = stats([s[1] for s in samples])
        c_first = stats([s[2] for s in samples])
        c_last = stats([s[3] for s in samples])
        rows.append([name, len(samples), trials.lost[name], first["median"], first["p99"],
                     first["max"], last["median"], last["max"],
                     f"{c_first['median']:.0f} / {c_first['max']:.0f}",
                     f"{c_last['median']:.0f} / {c_last['max']:.0f}"])
        data[name] = {"first_frame_us": first, "all_drives_us": last,
                      "first_frame_cycles": c_first, "all_drives_cycles": c_last,
                      "lost": trials.lost[name]}
    notes = [f"{args.drives} simulated drives (in-process, {rig.interface} bus), loop at "
             f"{args.rate:g} Hz (period {1e6 / args.rate:.0f} us); cycles: median / max; "
             "lost = no reaction seen within 1 s.",
             "Times are when a listener thread in this process received the frame: they "
             "include its wake-up behind the GIL (the loop spins for the last 0.5 ms before "
             "each deadline), so they over-state the send time."]
    if script.timed_out:
        notes.append(f"TIMED OUT in phase {script.phase}: the numbers are partial.")
    report("estop_latency", "E-stop latency to the bus",
           ["path", "n", "lost", "first us p50", "p99", "max", "all drives us p50", "max",
            "cycles first", "cycles all"], rows, args=args, notes=notes,
           results={"mode": "in-process", "rate_hz": args.rate, "drives": args.drives,
                    "cases": data, "timed_out": script.timed_out})


if __name__ == "__main__":
    main()
