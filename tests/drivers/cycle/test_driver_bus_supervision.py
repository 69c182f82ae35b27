"""drivers/cycle/supervision.py, receive.py, drivers/link/bus_port.py: what the CAN driver takes as
a broken drive or bus, and what it does not.

What must hold: a lost heartbeat, missing TPDOs, a statusword that is no CiA 402 state, a
TPDO of the wrong length and a bus-off error frame are each a fault at once (one drive: an
e-stop; the bus: a failproof stop); heartbeats waiting behind a starved reader are not
called lost; frames that are not CANopen (29-bit, remote) are never feedback or SDO
answers, and canopen keeps no EMCY log of its own.

The tests that take the segment, make_rig or recorder fixture run twice: on python-can's
virtual bus at 200 Hz with six drives (fast suite) and on SocketCAN vcan0 at 25 Hz with three
(vcan suite, through tools/vcan-run; see driver_rig.VCAN for why). Assertions are on states,
events and the frames seen on the bus, never on wall time.
"""
from __future__ import annotations

import struct
import threading

import can
from fixtures.driver_rig import VIRTUAL, Rig, bring_up, enable_with, status_report
from fixtures.rig_controllers import Brake, HoldPD

from rocoma_can import ManagerState, SwitchResult
from rocoma_can.drivers.protocol import cia301
from rocoma_can.drivers.protocol.cia402 import State402

NODES = VIRTUAL.nodes


def test_heartbeat_loss_of_one_drive_is_an_estop(segment, make_rig):
    # TPDO supervision out of the way (a silent drive sends no TPDOs either), so the
    # heartbeat deadline is what trips
    rig = make_rig(tpdo_timeout_cycles=1_000_000)
    bring_up(rig)
    enable_with(rig, HoldPD(), emergency=Brake())
    nodes = tuple(segment.drives)
    silent = nodes[-1]
    segment.drives[silent].set_silent(True)
    assert rig.run_until(lambda: rig.mgr.state == ManagerState.EMERGENCY,
                         rig.setup.detect_budget())
    latched = rig.hw.supervisor.latched[nodes.index(silent)]
    assert latched.node_id == silent and "heartbeat lost" in latched.cause
    assert [s.fault is not None for s in rig.hw.drive_status()] == [n == silent for n in nodes]
    rig.run(0.2)
    assert rig.mgr.state == ManagerState.EMERGENCY


def test_missing_tpdos_are_an_estop(segment, make_rig):
    rig = make_rig()
    bring_up(rig)
    enable_with(rig, HoldPD(), emergency=Brake())
    segment.drives[1].set_sync_response(False)  # heartbeat goes on, TPDOs stop
    assert rig.run_until(lambda: rig.mgr.state == ManagerState.EMERGENCY,
                         rig.setup.detect_budget())
    latched = rig.hw.supervisor.latched[0]
    assert latched.node_id == 1 and "TPDOs missing" in latched.cause


def test_a_statusword_that_is_no_state_is_a_fault_at_once(segment, make_rig):
    """A garbled statusword in the first cycles of enabling used to be taken as one more
    enable step, reported only when the enable timed out; it is that drive's fault at once.

    The switch is committed before the statusword is garbled and before the next cycle (the
    switcher commits between cycles, so no enable frame has been sent yet). Garbled first,
    the switch raced the fault: a loaded switcher thread committed after the fault was
    latched, and the switch guard rightly refused it."""
    rig = make_rig()
    bring_up(rig)
    rig.mgr.add_controller(HoldPD(), emergency=Brake())
    garbled = tuple(segment.drives)[1]
    assert rig.mgr.switch_controller("hold", timeout=rig.setup.stall) == SwitchResult.SWITCHED
    segment.drives[garbled].garble_statusword(0x0008)  # not enabled yet: reads as no state
    enable_cycles = int(rig.setup.timeouts.enable / rig.dt)
    before = len(rig.states)
    assert rig.run_until(lambda: rig.hw.supervisor.latched[1] is not None,
                         rig.setup.detect_budget())
    latched = rig.hw.supervisor.latched[1]
    assert latched.node_id == garbled and "no CiA 402 state" in latched.cause
    assert len(rig.states) - before < enable_cycles  # before the enable timeout would say


class _StallingListener(can.Listener):
    """Once armed, holds the bus's reader thread on its next frame until released: a
    reader the scheduler starved (a frozen process), with frames waiting in the socket."""

    def __init__(self, bound: float) -> None:
        self.armed = threading.Event()
        self.holding = threading.Event()
        self.release = threading.Event()
        self._bound = bound

    def on_message_received(self, msg: can.Message) -> None:
        if self.armed.is_set() and not self.release.is_set():
            self.holding.set()
            self.release.wait(self._bound)


def test_heartbeats_waiting_behind_a_starved_reader_are_not_called_lost(
        virtual_channel, sim_segment_factory, bus_factory):
    """The cycle judges a heartbeat deadline only against what the bus's reader has
    handed over (BusReader.received_until): a reader stalled past a deadline, with the
    drives' heartbeats waiting in the bus, is not a heartbeat loss. A drive that really
    goes silent still is one once the reader has caught up."""
    setup = VIRTUAL
    segment = sim_segment_factory(setup.nodes[:2], channel=virtual_channel,
                                  sync_period=setup.dt)
    # TPDO supervision out of the way (the stalled reader delivers no TPDOs either)
    rig = Rig.for_setup(bus_factory(virtual_channel), setup.nodes[:2], setup,
                        tpdo_timeout_cycles=1_000_000)
    timeout = float(rig.hw.supervisor.heartbeat_timeout.max())
    stall = _StallingListener(bound=2 * timeout + setup.stall)
    try:
        bring_up(rig)
        enable_with(rig, HoldPD(), emergency=Brake())
        rig.hw.ports[0].canopen.add_listener(stall)
        stall.armed.set()
        assert stall.holding.wait(setup.detect_budget()), "the reader never got a frame"
        rig.run(2 * timeout)  # past every heartbeat deadline while the reader is held
        assert rig.mgr.state == ManagerState.OK, status_report(rig)
        stall.release.set()
        rig.run(timeout / 2)  # the reader catches up: the waiting heartbeats were in time
        assert rig.mgr.state == ManagerState.OK, status_report(rig)
        silent = setup.nodes[1]
        segment.drives[silent].set_silent(True)
        assert rig.run_until(lambda: rig.mgr.state == ManagerState.EMERGENCY,
                             setup.detect_budget()), status_report(rig)
        latched = rig.hw.supervisor.latched[1]
        assert latched.node_id == silent and "heartbeat lost" in latched.cause
    finally:
        stall.release.set()
        rig.close()


def test_only_exact_frames_are_drive_feedback(segment, make_rig, bus_factory, can_setup,
                                              virtual_channel):
    """A 29-bit or a remote frame on a TPDO's identifier is not CANopen and never feedback
    (a 29-bit 0x181 used to be decoded as drive 1's TPDO); an 11-bit TPDO whose length is not
    its mapping's is never decoded, and it is that drive's fault (the e-stop path)."""
    rig = make_rig()
    bring_up(rig)
    enable_with(rig, HoldPD(), emergency=Brake())
    intruder = bus_factory(can_setup.channel(virtual_channel), can_setup.interface)
    tpdo1 = cia301.TPDO_BASE[0] + 1
    four_turns = struct.pack("<Hih", 0x0027, 4 << 20, 0)  # operation enabled at 25 rad
    for _ in range(5):
        intruder.send(can.Message(arbitration_id=tpdo1, is_extended_id=True, data=four_turns))
        intruder.send(can.Message(arbitration_id=tpdo1, is_extended_id=False,
                                  is_remote_frame=True, dlc=8))
        rig.run(2 * rig.dt)
        assert abs(rig.hw.state.position[0]) < 1.0, rig.hw.state.position
    assert rig.mgr.state == ManagerState.OK and rig.hw.rx_bad == 0
    intruder.send(can.Message(arbitration_id=tpdo1, is_extended_id=False, data=bytes(3)))
    assert rig.run_until(lambda: rig.mgr.state == ManagerState.EMERGENCY,
                         rig.setup.detect_budget())
    assert rig.hw.rx_bad >= 1
    assert "TPDO 0x181 with 3 bytes" in rig.hw.supervisor.latched[0].cause
    assert abs(rig.hw.state.position[0]) < 1.0


def test_canopen_keeps_no_emcy_log_and_takes_no_extended_frames(segment, make_rig, can_setup,
                                                                 virtual_channel, bus_factory):
    """The cycle decodes heartbeats and EMCYs itself; canopen's consumers of them kept an EMCY
    log that grew for the whole run (a drive repeating a warning) and its listener passed
    29-bit frames on as 11-bit ones. Now a storm of EMCYs leaves no log, an extended frame
    on a drive's SDO answer id is no answer, and the cycle still sees every EMCY."""
    rig = make_rig()
    bring_up(rig)
    node_id = can_setup.nodes[0]
    raw = bus_factory(can_setup.channel(virtual_channel), can_setup.interface)
    for _ in range(100):  # a vendor's code, repeated
        raw.send(can.Message(arbitration_id=cia301.EMCY + node_id, is_extended_id=False,
                             data=bytes([0x01, 0xFF, 0x80, 0, 0, 0, 0, 0])))
    raw.send(can.Message(arbitration_id=0x580 + node_id, is_extended_id=True,
                         data=bytes([0x43, 0x00, 0x10, 0x00, 1, 2, 3, 4])))
    # the cycle's own decoding sees them
    assert rig.run_until(lambda: rig.hw.state.error_code[0] == 0xFF01,
                         rig.setup.cycles_budget(10))
    rig.run(10 * rig.dt)  # and the frames after them
    node = rig.hw.ports[0].canopen.network[node_id]
    assert node.emcy.log == [] and node.emcy.active == []
    assert not node.sdo.responses.qsize(), "an extended frame was taken as an SDO answer"


def test_bus_off_error_frame_is_a_failproof_stop(virtual_channel, sim_segment_factory,
                                                  bus_factory):
    """SocketCAN reports bus-off only as an error frame (bus.state stays ACTIVE); here one
    is injected on the virtual bus (a real vcan never goes bus-off). A failed bus is a fault
    of every drive on it and a failproof stop, even with an emergency controller: once the
    bus is back the drives get torque-off frames, not the emergency layer's commands."""
    segment = sim_segment_factory(NODES, channel=virtual_channel)
    rig = Rig.for_setup(bus_factory(virtual_channel), NODES, VIRTUAL)
    try:
        bring_up(rig)
        enable_with(rig, HoldPD(), emergency=Brake())
        bus_factory(virtual_channel).send(can.Message(
            arbitration_id=0x40, is_error_frame=True, is_extended_id=False, data=bytes(8)))
        assert rig.run_until(lambda: rig.mgr.state == ManagerState.FAILPROOF,
                             rig.setup.detect_budget())
        assert rig.hw.bus_fault is not None and "bus-off" in rig.hw.bus_fault
        assert all(rig.hw.supervisor.latched)  # every drive on the bus
        assert rig.run_until(lambda: all(d.state402 == State402.SWITCH_ON_DISABLED
                                         for d in segment.drives.values()),
                             rig.setup.enable_budget())
        future = rig.hw.recover()
        assert rig.run_until(future.done, rig.setup.recovery_budget()) and future.result() is True
        assert rig.hw.bus_fault is None and rig.hw.all_ready
        assert rig.switch("hold") == SwitchResult.SWITCHED
        assert rig.run_until(lambda: rig.hw.all_enabled, rig.setup.enable_budget())
    finally:
        rig.close()
