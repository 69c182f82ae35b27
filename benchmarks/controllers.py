"""Per-cycle cost of the controllers library: initialize_fast and advance, 12 joints.

    .venv/bin/python benchmarks/controllers.py [--joints 12] [--repeat 20000] [--quick]

Prints median and 99th percentile in µs per call and writes results/controllers.json. An
emergency controller's initialize_fast
runs in the failure's cycle, so it must stay far below the cycle time (1000 µs at 1 kHz).
Numbers are from this process on a shared machine: compare them, do not treat them as bounds.
"""
from __future__ import annotations

import argparse
import gc

from _report import report, stats  # benchmarks/ is on sys.path when run as a script
from manager_overhead import random_joints, timed_ns

from rocoma_can.controllers.damp import Damp
from rocoma_can.controllers.float import Float
from rocoma_can.controllers.hold import Hold
from rocoma_can.controllers.pd import JointPD
from rocoma_can.controllers.quick_stop import QuickStop
from rocoma_can.controllers.torque_off import TorqueOff
from rocoma_can.controllers.trajectory import Trajectory
from rocoma_can.interfaces import EmergencyController

DT = 0.001


def controllers() -> list:
    return [
        TorqueOff(),
        Damp("damp", damping=2.0, torque_limit=20.0),
        Hold("hold", kp=200.0, kd=5.0, torque_limit=20.0),
        Hold("hold_csp", mode="CSP"),
        QuickStop("quick_stop"),
        JointPD("pd", kp=100.0, kd=4.0, target=0.3, torque_limit=20.0, velocity_limit=2.0),
        JointPD("pd_csp", target=0.3, mode="CSP"),
        Trajectory("sine_csp", amplitude=0.2, frequency=1.0),
        Trajectory("sine_cst", amplitude=0.2, frequency=1.0, mode="CST", kp=100.0, kd=4.0),
        Trajectory("min_jerk", kind="min_jerk", target=0.5, duration=2.0),
        Float("float"),
    ]


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--joints", type=int, default=12)
    parser.add_argument("--repeat", type=int, default=20000)
    parser.add_argument("--quick", action="store_true", help="1000 calls each")
    args = parser.parse_args()
    repeat = 1000 if args.quick else args.repeat
    state, command = random_joints(args.joints)

    rows, results = [], {}
    gc.disable()  # measure the code, not the collector
    try:
        for ctrl in controllers():
            ctrl.dt, ctrl.state, ctrl.command = DT, state, command
            assert ctrl.create(DT) is not False, ctrl
            init = {"median": float("nan"), "p99": float("nan")}
            if isinstance(ctrl, EmergencyController):
                init = stats(timed_ns(lambda c=ctrl: c.initialize_fast(DT), repeat) / 1000.0)
            elif hasattr(ctrl, "initialize"):
                assert ctrl.initialize(DT)
            adv = stats(timed_ns(lambda c=ctrl: c.advance(DT), repeat) / 1000.0)
            rows.append([ctrl.name, init["median"], init["p99"], adv["median"], adv["p99"]])
            results[ctrl.name] = {"initialize_fast_us": init, "advance_us": adv}
    finally:
        gc.enable()
    report("controllers", f"Controllers library, {args.joints} joints (µs per call)",
           ["controller", "initialize_fast median", "initialize_fast p99", "advance median",
            "advance p99"], rows, args=args, results=results,
           notes=[f"{repeat} calls each. An emergency controller's initialize_fast runs in "
                  "the failure's cycle: it must stay far below dt (1000 µs at 1 kHz)."])


if __name__ == "__main__":
    main()
