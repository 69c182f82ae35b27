"""drivers/hardware.py, drivers/link/bus_port.py (several buses): several CAN buses under one
manager: each bus its own SYNC, PDOs and manager heartbeat; one JointState over all joints; a failed
bus is a failproof stop with torque-off frames on every other bus; the e-stop frame works on any
bus, in the cycle that reads it; CAN FD.

Two buses ("left", "right"; python-can virtual, and in-process ones), each with its own
simulated segment of two drives with node ids 1 and 2 (node ids repeat across buses, as on
a real robot with one bus per limb), and a frame recorder per bus.
"""
from __future__ import annotations

import time

import can
import pytest
from fixtures.bus import record
from fixtures.driver_rig import VIRTUAL, Rig
from fixtures.rig_controllers import Brake, HoldPD

from rocoma_can import EventKind, ManagerState, SwitchResult
from rocoma_can.drivers.protocol import cia301
from rocoma_can.drivers.protocol.cia402 import State402
from rocoma_can.runtime.loop import run_cycle

NODES = (1, 2)
SIDES = ("left", "right")
ESTOP = 0x0A0


@pytest.fixture(params=["virtual", "inproc"])
def two_buses(request, virtual_channel, sim_segment_factory, bus_factory):
    """Segments, recorders and a started rig on two buses; ``fd``: CAN FD buses. On
    python-can's virtual buses the hardware reads each bus on a thread of its own; on
    in-process buses one thread reads both (bus.readers_for)."""
    interface = request.param
    made: list = []

    def make(fd: bool = False, **kw):
        protocol = {"protocol": can.CanProtocol.CAN_FD} if fd else {}
        channels = {side: f"{virtual_channel}-{side}" for side in SIDES}
        segments = {side: sim_segment_factory(NODES, channel=ch, interface=interface,
                                              sync_period=VIRTUAL.dt, fd=fd)
                    for side, ch in channels.items()}
        recorders = {side: record(ch, interface, **protocol) for side, ch in channels.items()}
        rig = Rig.for_setup({side: bus_factory(ch, interface, **protocol)
                             for side, ch in channels.items()},
                            {side: NODES for side in SIDES}, VIRTUAL, estop_cob_id=ESTOP, **kw)
        readers = {id(port.canopen.reader) for port in rig.hw.ports}
        assert len(readers) == (1 if interface == "inproc" else 2)
        rig.interface = interface
        made.append((rig, recorders))
        budget = VIRTUAL.bring_up_budget(len(NODES))
        assert rig.run_until(lambda: not rig.hw.starting, budget), rig.hw.drive_status()
        assert rig.hw.all_ready, rig.hw.drive_status()
        rig.channels = channels
        return rig, segments, recorders

    yield make
    for rig, recorders in made:
        rig.close()
        for r in recorders.values():
            r.stop()


def _rpdo(cob_id: int) -> bool:
    return 0x200 <= cob_id < 0x280 or 0x300 <= cob_id < 0x380


def _hold(rig: Rig) -> None:
    rig.mgr.add_controller(HoldPD(), emergency=Brake())
    assert rig.switch("hold") == SwitchResult.SWITCHED
    assert rig.run_until(lambda: rig.hw.all_enabled, VIRTUAL.enable_budget()), \
        rig.hw.drive_status()


def test_each_bus_gets_its_own_frames_and_the_manager_heartbeat(two_buses):
    rig, segments, recorders = two_buses()
    _hold(rig)
    assert [d.name for d in rig.hw.drives_config] == ["left1", "left2", "right1", "right2"]
    assert rig.hw.frames_per_cycle == 4 * 4 + 2  # 2 RPDOs + 2 TPDOs per drive, SYNC per bus
    marks = {side: r.mark() for side, r in recorders.items()}
    # longer than the drives' consumer of the manager heartbeat: each drive gets it on its bus
    consumer = rig.hw.consumer_ms / 1000
    cycles = max(1, int(round(2 * consumer / rig.dt)))
    rig.run(2 * consumer)
    assert rig.mgr.state is ManagerState.OK and rig.hw.all_enabled, rig.hw.drive_status()
    for side, r in recorders.items():
        # the recorder reads on a thread of its own and may trail: wait for the cycles' SYNCs
        r.wait_for_count(cycles, VIRTUAL.detect_budget(), cob_id=cia301.SYNC,
                         since=marks[side])
        frames = r.frames(since=marks[side])
        heartbeats = [f for f in frames if f.cob_id == cia301.HEARTBEAT + 100]
        assert heartbeats and all(f.data == bytes([cia301.NmtState.OPERATIONAL])
                                  for f in heartbeats)
        # between two SYNCs, one cycle: this bus's two drives' two RPDOs each, nothing more
        at = [k for k, f in enumerate(frames) if f.cob_id == cia301.SYNC]
        between = frames[at[0] + 1:at[-1]]
        rpdos = [f.cob_id for f in between if _rpdo(f.cob_id)]
        assert set(rpdos) == {0x201, 0x202, 0x301, 0x302}
        assert len(rpdos) == 4 * (len(at) - 1), (side, len(rpdos), len(at))
        assert all(d.state402 == State402.OPERATION_ENABLED
                   for d in segments[side].drives.values())
    # one JointState over all four joints, fed from both buses (each cycle whose TPDOs all
    # arrived before its read; on a loaded machine not every one does)
    assert rig.run_until(lambda: rig.hw.state.fresh.all(), VIRTUAL.detect_budget())


def test_a_failed_bus_is_a_failproof_stop_with_torque_off_on_every_bus(two_buses,
                                                                       bus_factory):
    """A bus-off on the right bus: every right drive is latched, and the manager goes to
    FAILPROOF even though the controller has an emergency controller: the left drives get
    controlword 0x0000 (disable voltage) frames at once. Recovery brings both back."""
    rig, segments, recorders = two_buses()
    _hold(rig)
    mark = recorders["left"].mark()
    bus_factory(rig.channels["right"], rig.interface).send(can.Message(
        arbitration_id=0x40, is_error_frame=True, is_extended_id=False, data=bytes(8)))
    assert rig.run_until(lambda: rig.mgr.state is ManagerState.FAILPROOF,
                         VIRTUAL.detect_budget())
    assert "bus-off on bus 'right'" in rig.hw.bus_fault
    latched = [event is not None for event in rig.hw.supervisor.latched]
    assert latched == [False, False, True, True]
    for node in NODES:
        recorders["left"].wait_for(lambda f, n=node: f.cob_id == 0x200 + n
                                   and f.data[:2] == b"\x00\x00",
                                   VIRTUAL.detect_budget(), since=mark)
    assert rig.run_until(lambda: all(d.state402 == State402.SWITCH_ON_DISABLED
                                     for s in segments.values() for d in s.drives.values()),
                         VIRTUAL.enable_budget())
    status = rig.hw.status_report()
    assert [(b.name, bool(b.fault)) for b in status.buses] == [("left", False),
                                                               ("right", True)]
    recovered = rig.hw.recover()
    assert rig.run_until(recovered.done, VIRTUAL.recovery_budget()) and recovered.result()
    assert rig.hw.bus_fault is None and rig.hw.all_ready
    assert rig.switch("hold") == SwitchResult.SWITCHED
    assert rig.run_until(lambda: rig.hw.all_enabled, VIRTUAL.enable_budget())


@pytest.mark.parametrize("side", SIDES)
def test_an_estop_frame_on_any_bus_acts_in_the_cycle_that_reads_it(two_buses, bus_factory,
                                                                   side):
    """The hardware drains e-stop frames with the drives' frames at the start of the cycle,
    so the update() right after that read already runs the emergency layer: 0 cycles."""
    rig, _, _ = two_buses()
    _hold(rig)
    events = []
    rig.mgr.subscribe(events.append)
    port = rig.hw.ports[SIDES.index(side)]
    bus_factory(rig.channels[side], rig.interface).send(
        can.Message(arbitration_id=ESTOP, data=b"", is_extended_id=False))
    deadline = time.monotonic() + VIRTUAL.stall
    while not any(m.arbitration_id == ESTOP for m in list(port.rx)):
        assert time.monotonic() < deadline, "the e-stop frame never reached the receiver"
        time.sleep(0.0005)
    assert rig.mgr.state is ManagerState.OK
    assert run_cycle(rig.hw, rig.mgr, time.monotonic()) is ManagerState.EMERGENCY  # that cycle
    assert rig.hw.estop_frames == 1
    deadline = time.monotonic() + VIRTUAL.stall  # events are delivered off the cycle
    while not any(e.kind is EventKind.EMERGENCY_STOP for e in events):
        assert time.monotonic() < deadline, events
        time.sleep(0.001)
    (estop,) = [e for e in events if e.kind is EventKind.EMERGENCY_STOP]
    assert estop.cause == f"CAN e-stop from 0x0A0 on bus {side!r}"


def test_the_estop_cob_id_can_be_changed_and_switched_off(two_buses, bus_factory):
    rig, _, _ = two_buses()
    _hold(rig)
    rig.hw.set_estop_cob_id(0)
    sender = bus_factory(rig.channels["left"], rig.interface)
    sender.send(can.Message(arbitration_id=ESTOP, data=b"\x01", is_extended_id=False))
    rig.run(20 * rig.dt)
    assert rig.mgr.state is ManagerState.OK and rig.hw.estop_frames == 0
    rig.hw.set_estop_cob_id(0x0A1)
    sender.send(can.Message(arbitration_id=0x0A1, is_remote_frame=True, is_extended_id=False))
    assert rig.run_until(lambda: rig.mgr.state is ManagerState.EMERGENCY,
                         VIRTUAL.detect_budget())
    with pytest.raises(ValueError, match="11-bit COB-ID"):
        rig.hw.set_estop_cob_id(0x800)
    with pytest.raises(ValueError, match="TPDO1 of node 2"):  # any bus's drive
        rig.hw.set_estop_cob_id(0x182)
    assert rig.hw.estop_cob_id == 0x0A1  # a refused id changes nothing


def test_can_fd_buses_carry_fd_frames_both_ways(two_buses):
    """On FD buses the manager's cycle frames and the drives' answers are CAN FD frames with
    bit rate switching (PDO payloads stay <= 8 bytes); bring-up and enabling work as on
    classic buses."""
    rig, _, recorders = two_buses(fd=True)
    _hold(rig)
    mark = {side: r.mark() for side, r in recorders.items()}
    rig.run(10 * rig.dt)
    for side, r in recorders.items():
        for first in (lambda f: f.cob_id == cia301.SYNC, lambda f: 0x180 <= f.cob_id < 0x200):
            r.wait_for(first, VIRTUAL.detect_budget(), since=mark[side])  # the recorder trails
        frames = r.frames(since=mark[side])
        ours = [f for f in frames if f.cob_id == cia301.SYNC or _rpdo(f.cob_id)]
        theirs = [f for f in frames if 0x180 <= f.cob_id < 0x200 or 0x280 <= f.cob_id < 0x300]
        assert ours and theirs
        assert all(f.message.is_fd and f.message.bitrate_switch for f in ours + theirs)
        assert all(len(f.data) <= 8 for f in ours + theirs)


def test_drives_that_map_longer_pdos_send_one_rpdo_and_one_tpdo_a_cycle(two_buses):
    """pdo_bytes 64 on CAN FD buses (the simulated drives on an FD bus map PDOs as CANopen
    FD does): each drive's targets in one RPDO (13 bytes, a 16-byte FD frame) and its
    feedback in one TPDO (12 bytes); bring-up maps them, the drives enable and follow."""
    rig, segments, recorders = two_buses(fd=True, drive={"pdo_bytes": 64})
    assert rig.hw.frames_per_cycle == 4 * 2 + 2
    _hold(rig)
    mark = {side: r.mark() for side, r in recorders.items()}
    rig.run(10 * rig.dt)
    for side, r in recorders.items():
        r.wait_for(lambda f: f.cob_id == 0x181, VIRTUAL.detect_budget(), since=mark[side])
        frames = r.frames(since=mark[side])
        rpdos = [f for f in frames if _rpdo(f.cob_id)]
        tpdos = [f for f in frames if 0x180 <= f.cob_id < 0x200 or 0x280 <= f.cob_id < 0x300]
        assert {f.cob_id for f in rpdos} == {0x201, 0x202}  # RPDO2 unused
        assert {f.cob_id for f in tpdos} == {0x181, 0x182}
        assert {len(f.data) for f in rpdos} == {16} and {len(f.data) for f in tpdos} == {12}
        assert all(f.message.is_fd and f.message.bitrate_switch for f in rpdos + tpdos)
    # enabled: the controlwords went in the long RPDOs, the statuswords came in the TPDOs
    assert rig.hw.all_enabled and rig.mgr.state is ManagerState.OK
    for segment in segments.values():  # as bring-up mapped them (sub-index 0: entries)
        for n in NODES:
            values = segment.drives[n].objects.values
            assert (values[(0x1600, 0)], values[(0x1A00, 0)]) == (5, 4)


def test_pdos_over_8_bytes_need_a_can_fd_bus(bus_factory, virtual_channel):
    from rocoma_can.drivers.hardware import CanopenHardware
    from rocoma_can.drivers.plan.config import DriveConfig
    with pytest.raises(ValueError, match="drive 'j1': pdo_bytes: 64 bytes a PDO need a CAN "
                                         "FD bus .*bus 'bus' is classic CAN"):
        CanopenHardware(bus_factory(virtual_channel), [DriveConfig("j1", 1, 4096, 1.0,
                                                                   pdo_bytes=64)], 100, 0.01)


def test_a_bus_without_drives_still_gets_sync_and_the_manager_heartbeat(virtual_channel,
                                                                        bus_factory):
    """SYNC and the manager heartbeat go out on every configured bus, one without drives
    too (a bus for a later limb, or for the integrator's e-stop box that watches the
    manager's heartbeat), in FAILPROOF and under the hang watchdog alike."""
    from rocoma_can.drivers.hardware import CanopenHardware
    from rocoma_can.drivers.plan.config import DriveConfig

    channels = {side: f"{virtual_channel}-{side}" for side in SIDES}
    empty = record(channels["left"])
    hw = CanopenHardware({side: bus_factory(ch) for side, ch in channels.items()},
                         [DriveConfig("j1", 1, 4096, 1.0, bus="right")], 100, VIRTUAL.dt)
    try:
        hw.start()
        hw.read(time.monotonic())
        hw.write(ManagerState.FAILPROOF)
        hw.send_torque_off()
        empty.wait_for_count(2, VIRTUAL.stall, cia301.SYNC)
        empty.wait_for_count(1, VIRTUAL.stall, cia301.HEARTBEAT + 100)
    finally:
        hw.close()
        empty.stop()
