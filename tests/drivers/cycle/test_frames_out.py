"""drivers/cycle/frames_out.py, rocoma_can/stopper.py: the CAN driver's torque-off path: every drive
gets controlword 0, whatever else fails.

What must hold: a second fault under the emergency controller switches every drive off in
the same cycle and keeps them off; the torque-off frames are the hardware's own, whatever
the failproof controller commands; a hung controller's drives get them from the watchdog
while the update is stuck; a stopped loop goes silent and the drives switch off by
themselves within the consumer time after the last heartbeat.

The tests that take the segment, make_rig or recorder fixture run twice: on python-can's
virtual bus at 200 Hz with six drives (fast suite) and on SocketCAN vcan0 at 25 Hz with three
(vcan suite, through tools/vcan-run; see driver_rig.VCAN for why). Assertions are on states,
events and the frames seen on the bus, never on wall time, except where the safety model
itself is a time bound.
"""
from __future__ import annotations

import struct
import threading
import time

from fixtures.driver_rig import RPDO1, bring_up, enable_with, seconds_until_all_off, synced_mark
from fixtures.rig_controllers import Brake, HoldPD

from rocoma_can import ManagerState
from rocoma_can.drivers.protocol import cia301
from rocoma_can.drivers.protocol.cia402 import State402
from rocoma_can.drivers.protocol.joints import JointMode


def rpdo1_cycles(frames) -> list[dict[int, int]]:
    """RPDO1 controlwords per cycle (a cycle starts with drive 1's frame)."""
    cycles: list[dict[int, int]] = []
    for f in frames:
        node = RPDO1[f.cob_id]
        if node == 1 or not cycles:
            cycles.append({})
        cycles[-1][node] = struct.unpack_from("<H", f.data)[0]
    return cycles


def test_fault_emergency_second_fault_failproof_torque_off_in_the_same_cycle(
        segment, make_rig, recorder):
    rig = make_rig()
    bring_up(rig)
    enable_with(rig, HoldPD(), emergency=Brake())
    nodes = tuple(segment.drives)
    first_fault, second_fault = nodes[1], nodes[-1]
    healthy = [n for n in nodes if n not in (first_fault, second_fault)]
    segment.drives[first_fault].trip_fault(cia301.EMCY_OVERCURRENT)
    assert rig.run_until(lambda: rig.mgr.state == ManagerState.EMERGENCY,
                         rig.setup.detect_budget())
    latched = rig.hw.supervisor.latched[nodes.index(first_fault)]
    assert latched is not None and latched.node_id == first_fault and "0x2310" in latched.cause
    rig.run(0.2)
    assert rig.mgr.state == ManagerState.EMERGENCY  # one broken drive is one e-stop
    assert all(segment.drives[n].state402 == State402.OPERATION_ENABLED
               for n in nodes if n != first_fault)

    mark = synced_mark(recorder, rig)
    segment.drives[second_fault].trip_fault(cia301.EMCY_OVERTEMPERATURE)
    assert rig.run_until(lambda: rig.states[-1] == ManagerState.FAILPROOF,
                         rig.setup.detect_budget())
    assert rig.states[-2] == ManagerState.EMERGENCY
    rig.run(0.1)
    # Each cycle sends RPDO1 of every drive in order. The first cycle in which a healthy
    # drive (neither faulted one) got controlword 0 is the FAILPROOF cycle: every drive got 0.
    synced_mark(recorder, rig)
    cycles = rpdo1_cycles(recorder.frames(set(RPDO1), since=mark))
    first = next(c for c in cycles if any(c.get(n) == 0 for n in healthy))
    assert first == {n: 0 for n in nodes}, cycles
    assert rig.run_until(lambda: all(d.state402 in (State402.SWITCH_ON_DISABLED, State402.FAULT)
                                     for d in segment.drives.values()),
                         rig.setup.enable_budget())
    # and every following cycle keeps sending controlword 0 to every drive
    mark = synced_mark(recorder, rig)
    rig.run(0.1)
    # The recorder reads on a thread of its own: in the user-mode-linux guest a fixed 50 ms
    # was not always enough for it to see these cycles' frames. A marker sent after them
    # and seen by it bounds the wait by the configured stall budget instead.
    synced_mark(recorder, rig)
    words = [struct.unpack_from("<H", f.data)[0] for f in recorder.frames(set(RPDO1), since=mark)]
    assert words and set(words) == {0}


def test_torque_off_frames_do_not_depend_on_the_failproof_controller(segment, make_rig,
                                                                      recorder):
    """Even a failproof layer that commands motion cannot make FAILPROOF send anything but
    controlword 0: the frames are pre-encoded by the hardware layer."""
    from rocoma_can import ControllerManager, FailproofController

    class Reckless(FailproofController):
        def advance(self, dt):
            self.command.mode.fill(JointMode.CSP)
            self.command.position.fill(1.0)

    rig = make_rig()
    bring_up(rig)
    rig.mgr.shutdown()
    rig.mgr = ControllerManager(Reckless(), rig.dt, rig.hw.state, rig.hw.command)
    rig.run(5 * rig.dt)
    mark = synced_mark(recorder, rig)
    rig.run(10 * rig.dt)
    assert set(rig.states[-10:]) == {ManagerState.FAILPROOF}
    recorder.wait_for_count(len(segment.drives) * 10, rig.setup.stall, set(RPDO1), since=mark)
    frames = recorder.frames(set(RPDO1), since=mark)
    assert {struct.unpack_from("<Hbi", f.data) for f in frames} == {(0, 8, 0)}
    assert all(d.state402 == State402.SWITCH_ON_DISABLED for d in segment.drives.values())


class HangingHold(HoldPD):
    """A PD whose advance blocks, once told to, until released: a hung controller."""

    def __init__(self) -> None:
        super().__init__("hanging")
        self.hang = threading.Event()
        self.release = threading.Event()

    def advance(self, dt: float) -> bool:
        if self.hang.is_set():
            self.release.wait(60.0)  # the test releases it; the bound only ends a broken test
        return super().advance(dt)


def test_hung_advance_gets_torque_off_frames_while_update_is_stuck(
        segment, make_rig, can_setup, virtual_channel, frame_recorder):
    """Issue 8: the watchdog sends the failproof frames itself while the update thread is
    stuck; when the advance returns it has failed, and the manager is FAILPROOF: the drives
    are off already, there is nothing for the emergency controller to stop (one documented
    end state, instead of EMERGENCY and then FAILPROOF on the drives' "drop-outs").
    The recorder starts after enabling: only the frames after the mark matter, and in the
    guest its thread and socket slowed bring-up and enabling for nothing."""
    rig = make_rig()
    bring_up(rig)
    ctrl = HangingHold()
    enable_with(rig, ctrl, emergency=Brake())
    recorder = frame_recorder(can_setup.channel(virtual_channel), can_setup.interface)
    mark = synced_mark(recorder, rig)
    ctrl.hang.set()
    result: list[ManagerState] = []
    stuck = threading.Thread(target=lambda: result.append(rig.cycle()))
    stuck.start()
    try:
        # controlword 0 to every drive, twice over, while the cycle is still inside update()
        frames = recorder.wait_for_count(
            2 * len(segment.drives), rig.setup.hang_budget(), tuple(RPDO1),
            since=mark, where=lambda f: struct.unpack_from("<H", f.data)[0] == 0)
        assert {RPDO1[f.cob_id] for f in frames} == set(segment.drives)
        assert stuck.is_alive() and rig.mgr.hang_calls >= 2
    finally:
        ctrl.release.set()
        stuck.join(rig.setup.hang_budget())
    assert result == [ManagerState.FAILPROOF]
    assert "hung for" in rig.mgr.adapters()["hanging"].failure
    assert not any("dropped out" in e.cause for e in rig.hw.fault_events)
    calls = rig.mgr.hang_calls
    rig.run(0.2)
    assert rig.mgr.hang_calls == calls  # quiet again once update() returns


def test_a_stopped_loop_goes_silent_and_drives_switch_off_by_themselves(segment, make_rig,
                                                                      can_setup):
    """The hung-loop half of the safety model (the killed process is in tests/vcan): the
    drives' heartbeat consumer switches them off, not before its time (the last heartbeat
    came at most a period before the stop) and within it, plus one period, plus one stall of
    the process that simulates the drives and watches them (a loaded guest was seen 0.24 s
    late)."""
    rig = make_rig()
    bring_up(rig)
    enable_with(rig, HoldPD())
    stopped = time.monotonic()  # no more cycles: no RPDOs, no SYNC, no manager heartbeat
    period = rig.hw.manager_heartbeat_period
    consumer = rig.hw.consumer_ms / 1000
    bound = consumer + period + can_setup.stall
    elapsed = seconds_until_all_off(segment, stopped, bound + 1.0)
    assert consumer - period <= elapsed < bound, elapsed
