"""What ``mgr.update()`` costs on top of the controller's own advance, and the e-stop path.

    .venv/bin/python benchmarks/manager_overhead.py [--joints 12] [--repeat 20000]
                                                     [--estops 300] [--quick]

Rows: a trivial controller (advance returns True) and a joint PD, each called directly and
through ``mgr.update()`` in OK (adapter, timing, lock, layer dispatch); then the update call
in which the controller fails (advance returns False: the emergency controller Damp runs
initialize_fast and its first advance in the same call) and the update call that handles an
``emergency_stop()`` request. The e-stop rows are measured over --estops repetitions, each
followed by a switch back to the controller (not timed). ns per call, median / p99 / max.
As in the control loop, ``post_cycle`` follows every update (not timed; its own row shows
what waking the stopper and the event thread costs once the cycle's frames are out): an
update() wakes no thread, so the e-stop's work on other threads cannot take the GIL inside
the timed call.
"""
from __future__ import annotations

import argparse
import gc
import logging
import time
from collections.abc import Callable

import numpy as np
from _report import report, stats

from rocoma_can import ControllerManager, ManagerState, SwitchResult
from rocoma_can.controllers.damp import Damp
from rocoma_can.controllers.pd import JointPD
from rocoma_can.controllers.torque_off import TorqueOff
from rocoma_can.drivers.protocol.joints import JointCommand, JointState
from rocoma_can.interfaces import Controller

DT = 0.001


class Trivial(Controller):
    """Does nothing, succeeds: what is left of an update is the manager's own cost."""

    def create(self, dt: float) -> bool:
        return True

    def initialize(self, dt: float) -> bool:
        return True

    def advance(self, dt: float) -> bool:
        return True


class Failing(Controller):
    """Succeeds until ``fail`` is set: the failure path under test."""

    fail = False

    def create(self, dt: float) -> bool:
        return True

    def initialize(self, dt: float) -> bool:
        self.fail = False
        return True

    def advance(self, dt: float) -> bool:
        return not self.fail


def random_joints(n: int) -> tuple[JointState, JointCommand]:
    """A reproducible joint state (positions and velocities in [-1, 1]) and a zero command."""
    rng = np.random.default_rng(0)
    state, command = JointState.zeros(n), JointCommand.zeros(n)
    state.position[:] = rng.uniform(-1, 1, n)
    state.velocity[:] = rng.uniform(-1, 1, n)
    return state, command


def timed_ns(fn: Callable[[], object], repeat: int) -> np.ndarray:
    samples = np.empty(repeat)
    clock = time.perf_counter_ns
    for i in range(repeat):
        t0 = clock()
        fn()
        samples[i] = clock() - t0
    return samples


def _switch(mgr: ControllerManager, name: str) -> None:
    result = mgr.switch_controller(name, timeout=5.0)
    if result != SwitchResult.SWITCHED or mgr.state != ManagerState.OK:
        raise RuntimeError(f"switch to {name!r} gave {result!r}, manager {mgr.state!r}")


def _wait_stopped(mgr: ControllerManager, timeout: float = 5.0) -> None:
    """Until no adapter is being stopped: an emergency controller still being stopped
    would send the next failure straight to FAILPROOF."""
    deadline = time.monotonic() + timeout
    adapters = mgr.adapters().values()
    while any(getattr(a, "being_stopped", False) for a in adapters):
        if time.monotonic() > deadline:
            raise RuntimeError("a controller is still being stopped after 5 s")
        time.sleep(0.0005)


def estop_samples(mgr: ControllerManager, ctrl: Failing, repeat: int,
                  how: str) -> tuple[np.ndarray, np.ndarray]:
    """The update call that handles a failure (``how`` = "advance" or "request"), and the
    post_cycle call after it."""
    samples = np.empty(repeat)
    wakes = np.empty(repeat)
    clock = time.perf_counter_ns
    for i in range(repeat):
        _switch(mgr, ctrl.name)
        _wait_stopped(mgr)
        for _ in range(5):       # a few ordinary cycles first, as in a running loop
            mgr.update()
            mgr.post_cycle()
        if how == "advance":
            ctrl.fail = True
            t0 = clock()
            state = mgr.update()
        else:
            mgr.emergency_stop("benchmark")
            t0 = clock()
            state = mgr.update()
        samples[i] = clock() - t0
        t0 = clock()
        mgr.post_cycle()
        wakes[i] = clock() - t0
        if state != ManagerState.EMERGENCY:
            raise RuntimeError(f"e-stop ({how}) ended in {state!r}, expected EMERGENCY")
    return samples, wakes


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--joints", type=int, default=12)
    parser.add_argument("--repeat", type=int, default=20000)
    parser.add_argument("--estops", type=int, default=300)
    parser.add_argument("--quick", action="store_true", help="2000 calls, 30 e-stops")
    args = parser.parse_args()
    if args.quick:
        args.repeat, args.estops = 2000, 30
    logging.getLogger("rocoma_can").setLevel(logging.CRITICAL)  # one warning per e-stop
    state, command = random_joints(args.joints)

    rows, data = [], {}

    def row(label: str, samples: np.ndarray, direct: float | None = None) -> None:
        s = stats(samples)
        overhead = s["median"] - direct if direct is not None else float("nan")
        rows.append([label, s["median"], s["p99"], s["max"], overhead])
        data[label] = {**s, "overhead_median_ns": overhead}

    with ControllerManager(TorqueOff(), DT, state, command) as mgr:
        trivial = Trivial("trivial")
        pd = JointPD("pd", kp=100.0, kd=4.0, target=0.3, torque_limit=20.0, velocity_limit=2.0)
        failing = Failing("failing")
        damp = Damp("damp", damping=2.0, torque_limit=20.0)  # one instance, shared
        for ctrl in (trivial, pd, failing):
            if not mgr.add_controller(ctrl, emergency=damp):
                raise RuntimeError(f"could not add {ctrl.name}")
        gc.disable()  # measure the code, not the collector
        try:
            medians = {}
            for ctrl in (trivial, pd):
                direct = timed_ns(lambda c=ctrl: c.advance(DT), args.repeat)
                row(f"{ctrl.name}: advance() direct", direct)
                _switch(mgr, ctrl.name)
                updates = timed_ns(mgr.update, args.repeat)
                row(f"{ctrl.name}: mgr.update()", updates, float(np.median(direct)))
                medians[ctrl.name] = float(np.median(updates))
            base = medians["trivial"]  # Failing's own advance is as trivial
            mgr.post_cycle()  # from here on update() leaves every wake-up to post_cycle
            failed, wake_a = estop_samples(mgr, failing, args.estops, "advance")
            row("e-stop: advance fails -> damp", failed, base)
            requested, wake_b = estop_samples(mgr, failing, args.estops, "request")
            row("e-stop: emergency_stop() request", requested, base)
            row("post_cycle after an e-stop (wakes 2 threads)", np.concatenate((wake_a, wake_b)))
            steady = timed_ns(mgr.update, args.repeat)  # EMERGENCY: damp advancing
            row("damp: mgr.update() in EMERGENCY", steady)
            ratio = float(np.median(failed)) / float(np.median(steady))
        finally:
            gc.enable()

    report("manager_overhead",
           f"Manager update overhead, {args.joints} joints (ns per call)",
           ["call", "median ns", "p99 ns", "max ns", "overhead ns"], rows, args=args,
           notes=["overhead = median minus the direct advance median (e-stop rows: minus "
                  "the median of a trivial controller's update: what the e-stop adds); "
                  "gc disabled while timing.",
                  f"e-stop update / a steady update of the emergency layer (damp): "
                  f"{ratio:.1f}x (target <= 5x)."],
           results={**data, "estop_over_steady_emergency": ratio})


if __name__ == "__main__":
    main()
