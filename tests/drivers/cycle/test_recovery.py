"""drivers/cycle/recovery.py: the CAN driver's recovery of faulted drives, and when a drive back is
commanded again.

What must hold: a recovered fault clears the latched e-stop and the next switch enables
every drive; a drive that is ready again under the emergency controller, or after the
switch of the controller running (degraded running), stays torque-off until the next
switch arms it: no controller commands a drive it did not initialize with.

The tests that take the segment, make_rig or recorder fixture run twice: on python-can's
virtual bus at 200 Hz with six drives (fast suite) and on SocketCAN vcan0 at 25 Hz with three
(vcan suite, through tools/vcan-run; see driver_rig.VCAN for why). Assertions are on states,
events and the frames seen on the bus, never on wall time.
"""
from __future__ import annotations

import time

from fixtures.driver_rig import VIRTUAL, Rig, bring_up, enable_with
from fixtures.rig_controllers import Brake, HoldPD

from rocoma_can import ManagerState, SwitchResult
from rocoma_can.drivers.protocol import cia301
from rocoma_can.drivers.protocol.cia402 import State402


def test_recovery_after_a_fault_returns_to_ok(segment, make_rig):
    rig = make_rig(estop_must_be_cleared=True)
    bring_up(rig)
    rig.mgr.clear_emergency_stop()
    enable_with(rig, HoldPD(), emergency=Brake())
    faulty = tuple(segment.drives)[-1]
    segment.drives[faulty].trip_fault(cia301.EMCY_FOLLOWING_ERROR)
    assert rig.run_until(lambda: rig.mgr.state == ManagerState.EMERGENCY,
                         rig.setup.detect_budget())
    assert rig.switch("hold") == SwitchResult.ERROR  # latched until recovered
    future = rig.hw.recover()
    assert rig.run_until(future.done, rig.setup.recovery_budget())
    assert future.result() is True, rig.hw.drive_status()
    assert not rig.mgr.estop_latched
    assert rig.switch("hold") == SwitchResult.SWITCHED
    assert rig.run_until(lambda: rig.hw.all_enabled, rig.setup.enable_budget()), \
        rig.hw.drive_status()
    assert rig.mgr.state == ManagerState.OK
    assert segment.drives[faulty].state402 == State402.OPERATION_ENABLED


def test_a_drive_recovered_under_the_emergency_layer_stays_off_until_the_next_switch(
        segment, make_rig):
    """A recovery asked while the emergency controller still commands the others brings the
    faulted drive back READY, but not under command: it had been torque-off since its
    fault, and the emergency controller's command (a pose or speed from before it sagged)
    must not be taken up by a drive nobody switched to. The next switch arms it."""
    rig = make_rig()
    bring_up(rig)
    enable_with(rig, HoldPD(), emergency=Brake())
    faulty = tuple(segment.drives)[-1]
    segment.drives[faulty].trip_fault(cia301.EMCY_FOLLOWING_ERROR)
    assert rig.run_until(lambda: rig.mgr.state == ManagerState.EMERGENCY,
                         rig.setup.detect_budget())
    future = rig.hw.recover()
    assert rig.run_until(future.done, rig.setup.recovery_budget())
    assert future.result() is True, rig.hw.drive_status()
    rig.run(rig.setup.enable_budget())  # time enough to have been enabled
    assert rig.mgr.state == ManagerState.EMERGENCY
    others = [n for n in segment.drives if n != faulty]
    assert all(segment.drives[n].state402 == State402.OPERATION_ENABLED for n in others)
    assert segment.drives[faulty].state402 != State402.OPERATION_ENABLED, \
        segment.drives[faulty].status_line()
    assert segment.drives[faulty].controlword == 0  # torque-off frames, still
    rig.mgr.add_controller(HoldPD("again"))
    assert rig.switch("again") == SwitchResult.SWITCHED
    assert rig.run_until(lambda: rig.hw.all_enabled, rig.setup.enable_budget()), \
        rig.hw.drive_status()


def test_a_drive_ready_after_the_switch_stays_off_until_the_next(virtual_channel,
                                                                sim_segment_factory,
                                                                bus_factory):
    """Degraded running: a drive that becomes ready after the switch (here: its STO input
    goes high again and it is recovered) is never commanded by the controller running
    since before, which initialized without it (its pose, its targets): it stays
    torque-off until the next switch arms it."""
    nodes = (1, 2, 3)
    segment = sim_segment_factory(nodes, channel=virtual_channel)
    segment.drives[3].set_sto(True)
    rig = Rig.for_setup(bus_factory(virtual_channel), nodes, VIRTUAL, required=(0, 1))
    try:
        bring_up(rig)
        rig.mgr.add_controller(HoldPD())
        rig.mgr.add_controller(HoldPD(name="other"))
        assert rig.switch("other") == SwitchResult.SWITCHED
        assert rig.run_until(lambda: rig.hw.enabled[:2].all(), VIRTUAL.enable_budget())
        segment.drives[3].set_sto(False)
        recovered = rig.hw.recover(VIRTUAL.recovery_budget())
        assert rig.run_until(recovered.done, VIRTUAL.recovery_budget())
        assert recovered.result() and rig.hw.all_ready, rig.hw.drive_status()
        rig.run(20 * rig.dt)
        assert rig.mgr.state == ManagerState.OK
        assert segment.drives[3].state402 == State402.SWITCH_ON_DISABLED  # not armed
        assert rig.switch("hold") == SwitchResult.SWITCHED  # the next switch arms it
        assert rig.run_until(lambda: rig.hw.all_enabled, VIRTUAL.enable_budget()), \
            rig.hw.drive_status()
    finally:
        rig.close()


def test_a_recovery_ends_when_the_hardware_is_cycled_without_a_manager(segment, make_rig):
    """The loop applies read()'s findings to the manager; a hardware cycled without one
    (read and write alone) still sees its recovery end, one cycle later, never hanging."""
    rig = make_rig()
    bring_up(rig)
    rig.mgr.shutdown()
    hw = rig.hw
    hw.supervisor.fault(0, "test", time.monotonic())
    budget = rig.setup.recovery_budget()
    future = hw.recover(budget)
    deadline = time.monotonic() + budget + rig.setup.stall  # it ends by its own timeout
    while not future.done() and time.monotonic() < deadline:
        hw.read(time.monotonic())  # the findings are not applied: there is no manager
        hw.write(ManagerState.FAILPROOF)
        time.sleep(rig.dt)
    assert future.done() and future.result() is True, hw.drive_status()
    assert hw.not_ready() is None
