"""One receive thread for several simulated segments (drivers/sim/group.py): serving the buses.

What must hold: the manager's hardware brings up and runs drives on every bus of the group
exactly as with a thread per segment; a heartbeat consumer on a bus with nothing else on
it still times out (the group vouches for idle buses, or a lost master would never be
seen); a bus that fails is recorded in its own segment and the others are still served;
buses one thread cannot wait on together (python-can's virtual) fall back to a thread per
segment. The waiting itself (frame_io.BusSelector) is tested in test_inproc.py; the
group's joined step in test_sim_group_joined_steps.py, lockstep in test_sim_group_lockstep.py.
"""
from __future__ import annotations

import struct
import threading
import time
import uuid

import can
import pytest
from fixtures.driver_rig import VCAN, VIRTUAL, Rig
from fixtures.rig_controllers import Brake, HoldPD
from fixtures.sim_group import NODES, sdo_write, send, wait_until

from rocoma_can import ManagerState, SwitchResult
from rocoma_can.drivers.protocol import cia301
from rocoma_can.drivers.protocol.cia402 import State402
from rocoma_can.drivers.sim.group import SegmentGroup
from rocoma_can.drivers.sim.segment import RX_BATCH, RX_IDLE, SimulatedSegment

COMMUNICATION_ERROR = 0x10  # error register 0x1001 bit 4


def _receive_threads() -> list[str]:
    return sorted(t.name for t in threading.enumerate()
                  if t.name in ("sim-group-rx", "sim-segment-rx"))


@pytest.mark.parametrize("interface,setup,shared", [
    ("inproc", VIRTUAL, True), ("virtual", VIRTUAL, False),
    pytest.param("socketcan", VCAN, True, marks=pytest.mark.vcan)])
def test_the_hardware_brings_up_and_runs_drives_on_every_bus_of_a_group(
        group_on, interface, setup, shared):
    before = _receive_threads()
    group, channels = group_on(interface, setup)
    assert group.shared_thread is shared
    started = _receive_threads()
    for name in before:
        started.remove(name)
    assert started == (["sim-group-rx"] if shared else ["sim-segment-rx"] * 2)
    buses = {f"bus{k}": can.Bus(interface=interface, channel=ch, ignore_config=True)
             for k, ch in enumerate(channels)}
    rig = Rig.for_setup(buses, {name: NODES for name in buses}, setup)
    try:
        assert rig.run_until(lambda: not rig.hw.starting,
                             setup.bring_up_budget(2 * len(NODES))), rig.hw.drive_status()
        assert rig.hw.all_ready, rig.hw.drive_status()
        rig.mgr.add_controller(HoldPD(), emergency=Brake())
        assert rig.switch("hold") == SwitchResult.SWITCHED
        assert rig.run_until(lambda: rig.hw.all_enabled, setup.enable_budget()), \
            rig.hw.drive_status()
        rig.run(20 * rig.dt)
        assert rig.mgr.state is ManagerState.OK, rig.hw.drive_status()
        for segment in group.segments:
            assert all(d.state402 is State402.OPERATION_ENABLED
                       for d in segment.drives.values())
            assert segment.sync_count >= 20
    finally:
        rig.close()
        for bus in buses.values():
            bus.shutdown()
    group.check()


def test_a_lost_master_heartbeat_is_seen_on_a_bus_that_is_otherwise_silent(group_on):
    """The consumer judges a loss only once every frame that arrived before its deadline
    was handled; on a silent bus only the group's idle wake-ups can say so."""
    group, channels = group_on("inproc")
    drive = group.segments[1].drives[1]
    master = can.Bus(interface="inproc", channel=channels[1], ignore_config=True)
    try:
        consumer_ms = 2 * VIRTUAL.heartbeat_ms
        sdo_write(master, 1, 0x1016, 1, struct.pack("<I", 100 << 16 | consumer_ms))
        send(master, cia301.HEARTBEAT + 100, bytes([cia301.NmtState.OPERATIONAL]))
        lost_by = time.monotonic() + consumer_ms / 1000 + VIRTUAL.detect_budget()
        while not drive.error_register & COMMUNICATION_ERROR and time.monotonic() < lost_by:
            time.sleep(RX_IDLE)
        assert drive.error_register & COMMUNICATION_ERROR, drive.status_line()
        # the drive on the other bus never saw the master: nothing to lose
        assert not group.segments[0].drives[1].error_register & COMMUNICATION_ERROR
    finally:
        master.shutdown()
    group.check()


def test_a_failed_bus_is_counted_in_its_segment_and_the_others_are_still_served(group_on):
    group, channels = group_on("inproc")
    failed, served = group.segments
    failed.bus.shutdown()  # its interface goes away under the running group
    master = can.Bus(interface="inproc", channel=channels[1], ignore_config=True)
    try:
        wait_until(lambda: failed.bus_errors, "the failure counted")
        assert isinstance(failed.bus_error, can.CanOperationError)
        before, start, sent = failed.bus_errors, time.monotonic(), 0
        while time.monotonic() - start < 10 * RX_IDLE:  # a flood on the served bus
            send(master, cia301.NMT, bytes([cia301.NmtCommand.STOP, 99]))  # no such node
            sent += 1
            time.sleep(0.001)
        sdo_write(master, 2, 0x6060, 0, bytes([8]))  # and it still answers
        assert served.drives[2].od_value(0x6060) == 8
        wait_until(lambda: served.nmt_count == sent, "the flood handled")
        wait_until(lambda: failed.bus_errors > before, "the failed bus read again")
        elapsed = time.monotonic() - start
        # read again every RX_IDLE, not once per frame on the other bus
        assert failed.bus_errors - before <= elapsed / RX_IDLE + 2, (sent, elapsed)
    finally:
        master.shutdown()
    group.stop()
    assert served.bus_errors == 0
    group.check()  # a bus that failed is not a failure of the simulation


def test_a_burst_longer_than_one_read_is_handled_without_more_traffic():
    """RX_BATCH frames per read: the rest of a burst must not wait for the next frame."""
    channel = f"group-{uuid.uuid4().hex[:8]}"
    segment = SimulatedSegment.open(channel, "inproc", NODES, sync_period=VIRTUAL.dt)
    sender = can.Bus(interface="inproc", channel=channel, ignore_config=True)
    group = SegmentGroup([segment])
    count = 3 * RX_BATCH + 5
    try:
        for _ in range(count):  # NMT to a node that is not there: counted, nothing else
            send(sender, cia301.NMT, bytes([cia301.NmtCommand.STOP, 99]))
        group.start()
        wait_until(lambda: segment.nmt_count == count, f"{count} NMT frames handled")
    finally:
        group.stop()
        sender.shutdown()
    group.check()


def test_an_empty_group_is_refused():
    with pytest.raises(ValueError, match="at least one segment"):
        SegmentGroup([])
