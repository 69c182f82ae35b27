"""drivers/cycle/supervision.py, drivers/sim/faults.py: every fault a simulated drive can have,
injected into one drive of a holding manager whose controller has a braking emergency controller.
Documented end state (docs/safety.md): the drive's fault is latched with its cause, the drive gets
nothing but torque-off frames from then on, the manager is in EMERGENCY and the others are braked
(enabled, CSV); the operator's second e-stop then gives torque-off frames for every drive."""
from __future__ import annotations

import can
import pytest
from fixtures.driver_rig import synced_mark
from fixtures.rig_controllers import Brake, HoldPD
from safety_rig import CW_DISABLE_VOLTAGE, NODES, SAFETY, Served

from rocoma_can import ManagerState, SwitchResult
from rocoma_can.drivers.protocol import cia301
from rocoma_can.drivers.protocol.cia402 import Mode, State402

FAULTY = NODES[1]
NMT_STOP, NMT_PRE_OP, NMT_RESET_NODE = 0x02, 0x80, 0x81
OFF = (State402.SWITCH_ON_DISABLED, State402.FAULT, State402.NOT_READY_TO_SWITCH_ON)


def _nmt_from_another_node(command: int):
    def send(served: Served, bus: can.BusABC) -> None:
        bus.send(can.Message(arbitration_id=0x000, data=bytes((command, FAULTY)),
                             is_extended_id=False))
    return send


FAULTS = {
    "emcy-overcurrent": lambda s, bus: s.segment.drives[FAULTY].trip_fault(
        cia301.EMCY_OVERCURRENT),
    "garbled-statusword": lambda s, bus: s.segment.drives[FAULTY].garble_statusword(),
    "silent": lambda s, bus: s.segment.drives[FAULTY].set_silent(),
    "ignores-sync": lambda s, bus: s.segment.drives[FAULTY].set_sync_response(False),
    "late-tpdos": lambda s, bus: s.segment.drives[FAULTY].set_tpdo_delay(
        3 * s.rig.hw.supervisor.tpdo_timeout_cycles * s.rig.dt),
    "sto-low": lambda s, bus: s.segment.drives[FAULTY].set_sto(True),
    "nmt-stop": _nmt_from_another_node(NMT_STOP),
    "nmt-pre-operational": _nmt_from_another_node(NMT_PRE_OP),
    "nmt-reset-node": _nmt_from_another_node(NMT_RESET_NODE),
}


@pytest.mark.parametrize("fault", list(FAULTS.values()), ids=list(FAULTS))
def test_a_drive_fault_is_isolated_and_braked_then_torque_off(served, bus_factory, fault):
    rig, segment, recorder = served.rig, served.segment, served.recorder
    i = NODES.index(FAULTY)
    rig.mgr.add_controller(HoldPD("braked"), emergency=Brake())
    assert rig.switch("braked") == SwitchResult.SWITCHED
    assert rig.run_until(lambda: rig.hw.all_enabled, SAFETY.enable_budget())

    fault(served, bus_factory())
    assert rig.run_until(lambda: rig.hw.supervisor.latched[i] is not None,
                         SAFETY.detect_budget()), rig.hw.drive_status()
    since = synced_mark(recorder, rig)  # every frame sent before the latch is behind us
    rig.run(10 * rig.dt)
    assert rig.mgr.state is ManagerState.EMERGENCY, rig.hw.fault_events
    # isolated: nothing but controlword 0 to the faulted drive ...
    recorder.wait_for(lambda f: f.cob_id == 0x200 + FAULTY, SAFETY.detect_budget(), since=since)
    assert {f.data[:2] for f in recorder.frames(0x200 + FAULTY, since=since)} \
        == {CW_DISABLE_VOLTAGE}
    # ... while the others are braked, enabled in CSV (as soon as the simulator, a thread
    # that a loaded machine may hold back, has applied the braking RPDOs)
    assert rig.run_until(lambda: all(
        segment.drives[n].state402 == State402.OPERATION_ENABLED
        and segment.drives[n].mode_display == Mode.CSV for n in NODES if n != FAULTY),
        SAFETY.detect_budget()), segment.status_lines()
    assert rig.mgr.state is ManagerState.EMERGENCY

    mark = recorder.mark()
    rig.mgr.emergency_stop()
    assert rig.cycle() is ManagerState.FAILPROOF
    for n in NODES:
        recorder.wait_for(lambda f, n=n: f.cob_id == 0x200 + n
                          and f.data[:2] == CW_DISABLE_VOLTAGE, SAFETY.detect_budget(),
                          since=mark)
    assert rig.run_until(lambda: all(segment.drives[n].state402 == State402.SWITCH_ON_DISABLED
                                     for n in NODES if n != FAULTY), SAFETY.enable_budget())
    # the faulted drive is off too, even one that no longer applies RPDOs (pre-operational,
    # ignoring SYNC): it got controlword 0 by SDO as well
    assert rig.run_until(lambda: segment.drives[FAULTY].state402 in OFF,
                         SAFETY.enable_budget() + SAFETY.sdo_timeout), segment.status_lines()
    assert rig.mgr.internal_errors == 0
    assert rig.cycle() is ManagerState.FAILPROOF  # the loop lives
