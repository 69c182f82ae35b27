"""rocoma_can/adapters.py, manager.py, drivers/hardware.py: every fault of the callbacks that run
inside the cycle, on the bus against simulated drives: the controller's advance and the emergency
controller's initialize_fast and advance, each raising, returning False, None or a numpy array,
writing NaN or inf into the command, or hanging. (The other callbacks run off the cycle; their
matrix is in test_every_layer_result_is_judged.py.)

Documented end states (docs/safety.md):
- the controller fails: EMERGENCY in the same update(), the emergency controller brakes the
  drives in CSV (they stay enabled: a smart stop);
- the emergency controller fails too: FAILPROOF in the same update(), controlword 0x0000 to
  every drive in that cycle's frames;
- either hangs inside update(): the watchdog sends torque-off frames to every drive while it
  is stuck, and the manager is FAILPROOF when it returns.
Every case ends with torque-off frames for every drive seen on the bus, the drives switched
off, the loop still cycling and no thread left (the served fixture checks that last).
"""
from __future__ import annotations

import math
import struct
import threading

import numpy as np
import pytest
from fixtures.rig_controllers import Brake, HoldPD
from safety_rig import CW_DISABLE_VOLTAGE, NODES, SAFETY, Served

from rocoma_can import ManagerState, SwitchResult
from rocoma_can.drivers.protocol.cia402 import Mode, State402

FAULTS = ("raise", "false", "none", "numpy-array", "nan", "inf", "hang")
CALLS = (("controller", "advance"), ("emergency", "initialize_fast"), ("emergency", "advance"))
RPDO1 = {0x200 + n: n for n in NODES}


class Fault:
    """One fault, armed by the test: what the faulty call does instead of its job."""

    def __init__(self, kind: str) -> None:
        self.kind = kind
        self.armed = threading.Event()
        self.release = threading.Event()

    def apply(self, real: object, command) -> object:
        """What the call returns: its real result until armed, then the fault's."""
        if not self.armed.is_set():
            return real
        kind = self.kind
        if kind == "raise":
            raise RuntimeError("fault injected")
        if kind == "hang":  # then returns as if all was well: having hung is the failure
            self.release.wait(10 * SAFETY.hang_budget())
            return real
        if kind in ("nan", "inf"):  # a command that looks fine to the controller
            command.position[0] = math.nan if kind == "nan" else math.inf
            command.torque[0] = math.nan if kind == "nan" else math.inf
            command.velocity[-1] = -math.inf if kind == "inf" else math.nan
            return real
        return {"false": False, "none": None, "numpy-array": np.array([True, True])}[kind]


class FaultyHold(HoldPD):
    def __init__(self, fault: Fault) -> None:
        super().__init__("faulty")
        self.fault = fault

    def advance(self, dt: float):
        return self.fault.apply(super().advance(dt), self.command)


class FaultyBrake(Brake):
    def __init__(self, faults: dict[str, Fault]) -> None:
        super().__init__("faulty_brake")
        self.faults = faults

    def initialize_fast(self, dt: float):
        real = super().initialize_fast(dt)
        fault = self.faults.get("initialize_fast")
        return real if fault is None else fault.apply(real, self.command)

    def advance(self, dt: float):
        real = super().advance(dt)
        fault = self.faults.get("advance")
        return real if fault is None else fault.apply(real, self.command)


def _controlwords_zero_for_every_drive(served: Served, since: int, timeout: float) -> None:
    for n in NODES:
        served.recorder.wait_for(lambda f, n=n: f.cob_id == 0x200 + n
                                 and f.data[:2] == CW_DISABLE_VOLTAGE, timeout, since=since)


def _cycle_stuck(served: Served, fault: Fault) -> ManagerState:
    """One cycle on a thread of its own while the fault hangs it; the watchdog must send
    torque-off frames (controlword 0) to every drive, twice over, before it is released."""
    rig = served.rig
    mark = served.recorder.mark()
    result: list[ManagerState] = []
    stuck = threading.Thread(target=lambda: result.append(rig.cycle()))
    stuck.start()
    try:
        frames = served.recorder.wait_for_count(
            2 * len(NODES), SAFETY.hang_budget(), tuple(RPDO1), since=mark,
            where=lambda f: struct.unpack_from("<H", f.data)[0] == 0)
        assert {RPDO1[f.cob_id] for f in frames} == set(NODES)
        assert stuck.is_alive() and rig.mgr.hang_calls >= 2
    finally:
        fault.release.set()
        stuck.join(SAFETY.hang_budget())
    assert not stuck.is_alive()
    return result[0]


@pytest.mark.parametrize("kind", FAULTS)
@pytest.mark.parametrize("layer,method", CALLS, ids=[f"{a}.{b}" for a, b in CALLS])
def test_a_faulty_cycle_callback_ends_in_its_documented_state(served, layer, method, kind):
    rig, segment = served.rig, served.segment
    fault = Fault(kind)
    controller_fault = fault if layer == "controller" else Fault("false")
    emergency = FaultyBrake({method: fault} if layer == "emergency" else {})
    rig.mgr.add_controller(FaultyHold(controller_fault), emergency=emergency)
    assert rig.switch("faulty") == SwitchResult.SWITCHED
    assert rig.run_until(lambda: rig.hw.all_enabled, SAFETY.enable_budget())
    mark = served.recorder.mark()

    fault.armed.set()
    controller_fault.armed.set()
    if kind == "hang":
        assert _cycle_stuck(served, fault) is ManagerState.FAILPROOF
        hung = "faulty" if layer == "controller" else "faulty_brake"
        assert f"{hung}.{method}" in rig.mgr.adapters()[hung].failure  # hung, or over budget
    elif layer == "controller":
        assert rig.cycle() is ManagerState.EMERGENCY  # in the same update()
        rig.run(20 * rig.dt)
        assert rig.mgr.state is ManagerState.EMERGENCY
        assert all(d.state402 == State402.OPERATION_ENABLED and d.mode_display == Mode.CSV
                   for d in segment.drives.values()), segment.status_lines()
    else:
        assert rig.cycle() is ManagerState.FAILPROOF  # EMERGENCY and FAILPROOF in one update()
        _controlwords_zero_for_every_drive(served, mark, SAFETY.detect_budget())

    # whatever happened, the operator's e-stops end in torque-off for every drive
    rig.mgr.emergency_stop()
    rig.cycle()
    rig.mgr.emergency_stop()
    assert rig.cycle() is ManagerState.FAILPROOF
    _controlwords_zero_for_every_drive(served, mark, SAFETY.detect_budget())
    assert rig.run_until(lambda: all(d.state402 == State402.SWITCH_ON_DISABLED
                                     for d in segment.drives.values()), SAFETY.enable_budget())
    assert rig.mgr.internal_errors == 0
    assert [rig.cycle() for _ in range(3)] == [ManagerState.FAILPROOF] * 3  # the loop lives
