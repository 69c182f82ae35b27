"""One receive thread for several simulated segments (drivers/sim/group.py).

What must hold: the manager's hardware brings up and runs drives on every bus of the group
exactly as with a thread per segment; a heartbeat consumer on a bus with nothing else on
it still times out (the group vouches for idle buses, or a lost master would never be
seen); a bus that fails is recorded in its own segment and the others are still served;
buses one thread cannot wait on together (python-can's virtual) fall back to a thread per
segment. The waiting itself (frame_io.BusSelector) is tested in test_inproc_bus.py.
"""
from __future__ import annotations

import struct
import threading
import time
import uuid

import can
import pytest
from fixtures.bus import VCAN_CHANNELS, require_vcan
from fixtures.driver_rig import VCAN, VIRTUAL, Brake, Can, HoldPD, Rig

from rocoma_can import ManagerState, SwitchResult
from rocoma_can.drivers import cia301
from rocoma_can.drivers.cia402 import State402
from rocoma_can.drivers.sim.group import SegmentGroup
from rocoma_can.drivers.sim.segment import RX_BATCH, RX_IDLE, SimulatedSegment

NODES = (1, 2)
COMMUNICATION_ERROR = 0x10  # error register 0x1001 bit 4


def _receive_threads() -> list[str]:
    return sorted(t.name for t in threading.enumerate()
                  if t.name in ("sim-group-rx", "sim-segment-rx"))


@pytest.fixture
def group_on():
    """``group_on(interface, setup)``: a started group of two segments of NODES each."""

    def make(interface: str, setup: Can = VIRTUAL) -> tuple[SegmentGroup, list[str]]:
        if interface == "socketcan":
            require_vcan()
            channels = list(VCAN_CHANNELS)
        else:
            base = f"group-{uuid.uuid4().hex[:8]}"
            channels = [f"{base}-{k}" for k in range(2)]
        segments: list[SimulatedSegment] = []
        opened.append(segments)
        for ch in channels:
            segments.append(SimulatedSegment.open(ch, interface, NODES, sync_period=setup.dt,
                                                  params=setup.joints))
        group = SegmentGroup(segments)
        made.append(group)
        return group.start(), channels

    opened: list[list[SimulatedSegment]] = []
    made: list[SegmentGroup] = []
    yield make
    for group in made:
        group.stop()
    for segments in opened:  # a group that was never made: its segments (stop is idempotent)
        for segment in segments:
            segment.stop()


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


def _wait(predicate, what: str) -> None:
    deadline = time.monotonic() + VIRTUAL.detect_budget()
    while not predicate():
        assert time.monotonic() < deadline, what
        time.sleep(RX_IDLE)


def _send(bus: can.BusABC, cob_id: int, data: bytes) -> None:
    bus.send(can.Message(arbitration_id=cob_id, data=data, is_extended_id=False))


def _sdo_write(bus: can.BusABC, node: int, index: int, sub: int, data: bytes) -> None:
    """An expedited download of 1-4 bytes, answered (0x60) within the detection budget."""
    command = 0x23 | (4 - len(data)) << 2
    _send(bus, cia301.SDO_RX + node,
          struct.pack("<BHB", command, index, sub) + data.ljust(4, b"\0"))
    deadline = time.monotonic() + VIRTUAL.detect_budget()
    while time.monotonic() < deadline:
        msg = bus.recv(0.05)
        if msg is not None and msg.arbitration_id == cia301.SDO_TX + node:
            assert msg.data[0] == 0x60, f"SDO write 0x{index:04X} aborted: {bytes(msg.data)}"
            return
    raise AssertionError(f"no SDO answer from node {node} on {bus.channel_info}")


def test_a_lost_master_heartbeat_is_seen_on_a_bus_that_is_otherwise_silent(group_on):
    """The consumer judges a loss only once every frame that arrived before its deadline
    was handled; on a silent bus only the group's idle wake-ups can say so."""
    group, channels = group_on("inproc")
    drive = group.segments[1].drives[1]
    master = can.Bus(interface="inproc", channel=channels[1], ignore_config=True)
    try:
        consumer_ms = 2 * VIRTUAL.heartbeat_ms
        _sdo_write(master, 1, 0x1016, 1, struct.pack("<I", 100 << 16 | consumer_ms))
        _send(master, cia301.HEARTBEAT + 100, bytes([cia301.NmtState.OPERATIONAL]))
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
        _wait(lambda: failed.bus_errors, "the failure counted")
        assert isinstance(failed.bus_error, can.CanOperationError)
        before, start, sent = failed.bus_errors, time.monotonic(), 0
        while time.monotonic() - start < 10 * RX_IDLE:  # a flood on the served bus
            _send(master, cia301.NMT, bytes([cia301.NmtCommand.STOP, 99]))  # no such node
            sent += 1
            time.sleep(0.001)
        _sdo_write(master, 2, 0x6060, 0, bytes([8]))  # and it still answers
        assert served.drives[2].od_value(0x6060) == 8
        _wait(lambda: served.nmt_count == sent, "the flood handled")
        _wait(lambda: failed.bus_errors > before, "the failed bus read again")
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
            _send(sender, cia301.NMT, bytes([cia301.NmtCommand.STOP, 99]))
        group.start()
        _wait(lambda: segment.nmt_count == count, f"{count} NMT frames handled")
    finally:
        group.stop()
        sender.shutdown()
    group.check()


def test_an_empty_group_is_refused():
    with pytest.raises(ValueError, match="at least one segment"):
        SegmentGroup([])


RPDO1 = struct.Struct("<HBh")  # the simulated drive's default: controlword, mode, torque
RPDO2 = struct.Struct("<ii")  # target position, target velocity (increments)
CSP = 8


def test_a_group_steps_its_segments_joints_together_exactly_as_alone():
    """The group joins its segments' dynamics and steps every segment whose SYNC came in
    one call. The drives must not tell: two segments in a group and the same two alone,
    fed the same frames (CSP moves, fixed SYNC period), end bit for bit in the same
    place; and the group took one step per SYNC round, not one per segment. (Each round's
    frames are queued while the test holds the group's locks, so the group sees both
    buses' SYNCs in one pass whatever the machine's load.)"""
    base = f"joined-{uuid.uuid4().hex[:8]}"
    lone_channels = [f"{base}-lone-{k}" for k in range(2)]
    group_channels = [f"{base}-group-{k}" for k in range(2)]
    lone = [SimulatedSegment.open(ch, "inproc", NODES, sync_period=0.001, seed=k)
            for k, ch in enumerate(lone_channels)]
    grouped = [SimulatedSegment.open(ch, "inproc", NODES, sync_period=0.001, seed=k)
               for k, ch in enumerate(group_channels)]
    group = SegmentGroup(grouped)
    masters = [can.Bus(interface="inproc", channel=ch, ignore_config=True)
               for ch in lone_channels + group_channels]
    segments = lone + grouped
    try:
        for segment in lone:
            segment.start()
        group.start()
        assert all(s.deferred_dt is None for s in lone)
        syncs = 0

        def cycle(controlword: int, target: int) -> None:
            nonlocal syncs
            # the group's locks held: it handles both buses' frames in one pass after them
            with grouped[0].lock, grouped[1].lock:
                for bus in masters:
                    for n in NODES:
                        _send(bus, 0x200 + n, RPDO1.pack(controlword, CSP, 0))
                        _send(bus, 0x300 + n, RPDO2.pack(target * n, 0))
                for bus in masters:
                    _send(bus, cia301.SYNC, b"")
            syncs += 1
            deadline = time.monotonic() + VIRTUAL.detect_budget()
            while not all(s.sync_count >= syncs for s in segments):
                assert time.monotonic() < deadline, f"every segment handles SYNC {syncs}"
                time.sleep(0.001)

        for bus in masters:
            _send(bus, cia301.NMT, bytes((cia301.NmtCommand.START, 0)))
        for controlword in (0x06, 0x07, 0x0F):  # shutdown, switch on, enable operation
            cycle(controlword, 0)
        assert all(d.state402 is State402.OPERATION_ENABLED
                   for s in segments for d in s.drives.values())
        for k in range(200):
            cycle(0x0F, 300 * k)  # a ramp: the position loops work every step
        moved = [s.drives[n].position_rad for s in lone for n in NODES]
        assert min(abs(q) for q in moved) > 0.05
        assert [s.drives[n].position_rad for s in grouped for n in NODES] == moved
        assert [s.drives[n].torque_nm for s in grouped for n in NODES] == \
            [s.drives[n].torque_nm for s in lone for n in NODES]
        assert group.joined_steps == syncs  # both buses' SYNCs: one step each time
    finally:
        for bus in masters:
            bus.shutdown()
        group.stop()
        for segment in lone:
            segment.stop()
    group.check()


def test_a_drive_that_raises_in_a_joined_step_fails_its_segment_only(group_on):
    """A bug in one drive's answer to a joined step is its segment's failure (check()
    says so); the one thread every bus of the group is read on goes on serving them."""
    group, channels = group_on("inproc")
    broken = group.segments[0].drives[NODES[0]]

    def finish_step(on_sync: bool, *joint_values: list[float]) -> None:
        raise RuntimeError("a bug in the drive's answer")
    broken.finish_step = finish_step  # type: ignore[method-assign]
    masters = [can.Bus(interface="inproc", channel=ch, ignore_config=True) for ch in channels]
    try:
        for k in range(1, 4):
            with group.segments[0].lock, group.segments[1].lock:  # one pass: a joined step
                for bus in masters:
                    _send(bus, cia301.SYNC, b"")
            _wait(lambda k=k: group.segments[1].sync_count >= k, f"bus 1 answers SYNC {k}")
        assert group.joined_steps == 3
        assert all(s.deferred_dt is None for s in group.segments)
        assert len(group.segments[0].errors) == 3
        with pytest.raises(RuntimeError, match="simulated segment failed"):
            group.check()
        assert group.segments[1].errors == []
    finally:
        for bus in masters:
            bus.shutdown()


def test_no_joined_step_while_a_segment_outside_the_pass_may_be_stepping_alone():
    """The joined step writes every joint's arrays, those of a segment that got no SYNC
    too. Such a segment can be stepping its own joints on its timer at that moment (it
    free-runs when its bus is silent), under its own lock only: the group must then step
    the segments of its pass alone, not join them over the other's half-done step. The
    test holds the third segment's lock as its timer would; two buses' SYNCs come in one
    pass. Held: they are answered, each stepped alone; released: one joined step."""
    base = f"outside-{uuid.uuid4().hex[:8]}"
    channels = [f"{base}-{k}" for k in range(3)]
    segments = [SimulatedSegment.open(ch, "inproc", NODES, sync_period=0.001)
                for ch in channels]
    group = SegmentGroup(segments)
    masters = [can.Bus(interface="inproc", channel=ch, ignore_config=True)
               for ch in channels[:2]]

    def one_pass_of_syncs(k: int) -> None:
        with segments[0].lock, segments[1].lock:  # both SYNCs wait for one pass
            for bus in masters:
                _send(bus, cia301.SYNC, b"")
        _wait(lambda: all(s.sync_count >= k for s in segments[:2]),
              f"both buses answer SYNC {k}")

    try:
        group.start()
        with segments[2].lock:  # the silent bus's segment, busy as on its own timer
            one_pass_of_syncs(1)
            assert group.joined_steps == 0  # stepped alone
        one_pass_of_syncs(2)
        assert group.joined_steps == 1
    finally:
        for bus in masters:
            bus.shutdown()
        group.stop()
    group.check()


def _two_groups_of(count: int, base: str, lockstep: bool = False
                   ) -> tuple[list[SimulatedSegment], SegmentGroup, list[can.BusABC],
                              list[can.BusABC]]:
    """``count`` lone segments and ``count`` grouped (their pass run by the test; with
    ``lockstep``, lockstep_pass, the group's thread standing by), each with a master bus;
    the drives started and enabled in CSP on every bus."""
    lone = [SimulatedSegment.open(f"{base}-lone-{k}", "inproc", NODES, sync_period=0.001,
                                  seed=k) for k in range(count)]
    grouped = [SimulatedSegment.open(f"{base}-group-{k}", "inproc", NODES, sync_period=0.001,
                                     seed=k) for k in range(count)]
    group = SegmentGroup(grouped)
    lone_masters = [can.Bus(interface="inproc", channel=f"{base}-lone-{k}", ignore_config=True)
                    for k in range(count)]
    masters = [can.Bus(interface="inproc", channel=f"{base}-group-{k}", ignore_config=True)
               for k in range(count)]
    for segment in lone:
        segment.start()
    group.start(thread=lockstep, lockstep=lockstep)
    for bus in lone_masters + masters:
        _send(bus, cia301.NMT, bytes((cia301.NmtCommand.START, 0)))
    for k, controlword in enumerate((0x06, 0x07, 0x0F), 1):
        for bus in lone_masters + masters:
            _cycle_frames(bus, controlword, 0)
        if lockstep:  # (the thread answers if it was in a pass: it stands by after)
            group.lockstep_pass()
        else:
            group.pass_once(0.0)
        _wait(lambda k=k: all(s.sync_count >= k for s in lone + grouped),
              f"all segments: SYNC {k}")
    assert all(d.state402 is State402.OPERATION_ENABLED
               for s in lone + grouped for d in s.drives.values())
    return lone, group, lone_masters, masters


def _cycle_frames(bus: can.BusABC, controlword: int, target: int) -> None:
    for n in NODES:
        _send(bus, 0x200 + n, RPDO1.pack(controlword, CSP, 0))
        _send(bus, 0x300 + n, RPDO2.pack(target * n, 0))
    _send(bus, cia301.SYNC, b"")
    _send(bus, cia301.HEARTBEAT + 127, bytes([cia301.NmtState.OPERATIONAL]))


def _close(lone: list[SimulatedSegment], group: SegmentGroup, buses: list[can.BusABC]) -> None:
    for bus in buses:
        bus.shutdown()
    group.stop()
    for segment in lone:
        segment.stop()


def test_a_group_that_lags_catches_up_with_one_joined_step_per_cycle():
    """A group that fell behind (a stalled thread, a loaded machine) finds several cycles
    of every bus queued. It must take them one cycle at a time, each with one joined step,
    and answer every SYNC in order, exactly as lone segments fed the same frames; not let
    each segment step alone at its next SYNC (four times the cost, which kept a lagging
    1 kHz bench lagging). A master's heartbeat right after each SYNC does not break the
    join. Here 30 cycles are queued on four buses before the passes."""
    lone, group, lone_masters, masters = _two_groups_of(4, f"lag-{uuid.uuid4().hex[:8]}")
    try:
        steps_before = group.joined_steps
        cycles = 30
        for k in range(cycles):
            for bus in lone_masters + masters:
                _cycle_frames(bus, 0x0F, 400 * k)
            _wait(lambda k=k: all(s.sync_count >= 4 + k for s in lone),
                  f"lone segments: SYNC {4 + k}")
        passes = 0
        while any(s.sync_count < 3 + cycles for s in group.segments):
            assert passes < cycles, [s.sync_count for s in group.segments]
            group.pass_once(0.0)  # as the receive thread's loop: passes of bounded reads
            passes += 1
        assert [s.sync_count for s in group.segments] == [3 + cycles] * 4
        assert group.joined_steps - steps_before == cycles
        moved = [s.drives[n].position_rad for s in lone for n in NODES]
        assert min(abs(q) for q in moved) > 0.001  # the joints moved: the test compares motion
        assert [s.drives[n].position_rad for s in group.segments for n in NODES] == moved
        assert [s.drives[n].torque_nm for s in group.segments for n in NODES] == \
            [s.drives[n].torque_nm for s in lone for n in NODES]
    finally:
        _close(lone, group, lone_masters + masters)
    group.check()


def test_a_sync_waits_for_the_other_buses_syncs_then_steps_without_them():
    """A cycle's SYNCs reach the group's buses one after another (another process sends
    them, the sender loses the GIL mid-burst). A SYNC that came alone is not answered in
    that pass: the group waits up to JOIN_WAIT for the others', then one joined step
    answers all. A SYNC whose companions never come is answered after JOIN_WAIT: a pass
    then waits no longer than that, however long its timeout."""
    lone, group, lone_masters, masters = _two_groups_of(2, f"wait-{uuid.uuid4().hex[:8]}")
    try:
        first, second = group.segments
        steps = group.joined_steps
        _cycle_frames(masters[0], 0x0F, 100)
        group.pass_once(0.0)
        assert (first.sync_count, second.sync_count) == (3, 3)  # waiting: not answered yet
        _cycle_frames(masters[1], 0x0F, 100)
        group.pass_once(0.0)
        assert (first.sync_count, second.sync_count) == (4, 4)
        assert group.joined_steps == steps + 1  # one step for both
        _cycle_frames(masters[0], 0x0F, 200)  # the other bus's master is gone
        group.pass_once(0.0)
        assert first.sync_count == 4
        for _ in range(3):  # a pass waits no longer than JOIN_WAIT (a wake-up may end it
            group.pass_once(10 * RX_IDLE)  # sooner: frames already handled)
            if first.sync_count == 5:
                break
        assert (first.sync_count, second.sync_count) == (5, 4)
        assert group.joined_steps == steps + 1  # alone
    finally:
        _close(lone, group, lone_masters + masters)
    group.check()


def test_frames_kept_after_a_waiting_sync_are_not_vouched_for_and_come_before_a_fault():
    """A SYNC that waits for the other buses' keeps the frames after it unhandled (the
    segment's backlog). While they wait, the group must not vouch for the bus as silent
    (``received_until`` past them would let a heartbeat consumer judge a heartbeat that
    came in time as lost); and a fault injected through a drive's API meanwhile comes
    after that SYNC's step and answer, not between its RPDOs and its step."""
    lone, group, lone_masters, masters = _two_groups_of(2, f"kept-{uuid.uuid4().hex[:8]}")
    try:
        first = group.segments[0]
        _cycle_frames(masters[0], 0x0F, 100)  # RPDOs, SYNC, then a master heartbeat
        sent = time.monotonic()
        group.pass_once(0.0)
        assert first.deferred_dt is not None and first.backlog  # waiting; heartbeat kept
        group.pass_once(0.0)  # nothing new on either bus (the wait may end here)
        assert first.backlog and first.received_until < sent
        for _ in range(10):  # the wait ends (JOIN_WAIT), the SYNC is answered, then the
            group.pass_once(RX_IDLE)  # kept heartbeat is handled at once
            if not first.backlog:
                break
        assert not first.backlog and first.sync_count == 4
        _cycle_frames(masters[0], 0x0F, 200)
        group.pass_once(0.0)
        assert first.deferred_dt is not None and first.sync_count == 4
        first.drives[NODES[0]].set_sto(True)
        assert first.deferred_dt is None and first.sync_count == 5  # the SYNC first
        assert first.drives[NODES[0]].sto_low
    finally:
        _close(lone, group, lone_masters + masters)
    group.check()


def _answers(bus: can.BusABC) -> set[int]:
    """The COB-IDs of the frames waiting on ``bus`` (read without waiting)."""
    got = set()
    while (msg := bus.recv(0.0)) is not None:
        got.add(msg.arbitration_id)
    return got


TPDOS = {base + n for base in (0x180, 0x280) for n in NODES}  # the drives' default TPDOs


def test_a_lockstep_group_answers_each_cycle_on_the_callers_thread():
    """In lockstep the control loop's thread steps the simulator right after its write:
    a segment's SYNC that ``lockstep_pass`` handled has been answered with every drive's
    TPDOs before the call returned (no thread hand-over), and the joints move exactly as
    lone segments fed the same frames. Left for later, and so not counted here: a segment
    whose lock a timer held (its heartbeat), and a cycle the group's thread took (it reads
    the buses itself once a caller stalled for LOCKSTEP_GRACE: the call returns False)."""
    lone, group, lone_masters, masters = _two_groups_of(
        4, f"lockstep-{uuid.uuid4().hex[:8]}", lockstep=True)
    try:
        for bus in masters:
            _answers(bus)  # the bring-up's
        cycles, answered, passes = 60, 0, group.lockstep_passes
        steps = group.joined_steps
        for k in range(cycles):
            for bus in lone_masters + masters:
                _cycle_frames(bus, 0x0F, 400 * k)
            syncs = [s.sync_count for s in group.segments]
            if group.lockstep_pass():
                for segment, bus, before in zip(group.segments, masters, syncs):
                    if segment.sync_count > before:  # answered within the call
                        assert TPDOS <= _answers(bus)  # (+ heartbeats)
                        answered += 1
            _wait(lambda k=k: all(s.sync_count >= 4 + k for s in group.segments),
                  f"SYNC {4 + k} answered")
            for bus in masters:
                _answers(bus)
        assert answered >= 0.75 * 4 * cycles, answered
        assert group.lockstep_passes - passes >= 0.75 * cycles
        assert group.joined_steps - steps >= 0.75 * cycles
        _wait(lambda: all(s.sync_count >= 3 + cycles for s in lone), "lone segments")
        moved = [s.drives[n].position_rad for s in lone for n in NODES]
        assert min(abs(q) for q in moved) > 0.001
        assert [s.drives[n].position_rad for s in group.segments for n in NODES] == moved
    finally:
        _close(lone, group, lone_masters + masters)
    group.check()


def test_a_lockstep_group_is_read_by_its_thread_once_the_loop_stops_stepping_it():
    """A loop that stops calling ``lockstep_pass`` (it ended, or stalls) must not leave
    the drives deaf: within LOCKSTEP_GRACE the group's thread reads the buses again, so
    SYNCs and SDOs are answered and a lost master heartbeat is judged."""
    lone, group, lone_masters, masters = _two_groups_of(
        2, f"standby-{uuid.uuid4().hex[:8]}", lockstep=True)
    try:
        for k in range(5):
            for bus in masters:
                _cycle_frames(bus, 0x0F, 100 * k)
            group.lockstep_pass()
            _wait(lambda k=k: all(s.sync_count >= 4 + k for s in group.segments),
                  f"SYNC {4 + k}")
        syncs = [s.sync_count for s in group.segments]
        for bus in masters:  # no lockstep_pass from here on
            _cycle_frames(bus, 0x0F, 600)
        _wait(lambda: [s.sync_count for s in group.segments] == [n + 1 for n in syncs],
              "the group's thread answers the SYNCs")
    finally:
        _close(lone, group, lone_masters + masters)
    group.check()


def test_a_lockstep_pass_never_waits_for_a_segment_another_thread_holds():
    """The control loop's thread must never block on a lock a slower thread holds: a
    segment whose lock is taken (a fault injected through a drive's API) is left for a
    later pass, its bus is not vouched for as silent, and the other buses are answered.
    The group's own thread, should it take over (a caller stalled for LOCKSTEP_GRACE on a
    loaded machine), does not wait for that lock either, so lockstep passes resume."""
    lone, group, lone_masters, masters = _two_groups_of(
        2, f"busy-{uuid.uuid4().hex[:8]}", lockstep=True)
    taken, release = threading.Event(), threading.Event()

    def holder_() -> None:  # as a drive API call on the first segment, holding its lock
        with group.segments[0].lock:
            taken.set()
            release.wait(30.0)

    holder = threading.Thread(target=holder_)
    first, second = group.segments
    try:
        group.lockstep_pass()
        before = (first.sync_count, second.sync_count)
        holder.start()
        assert taken.wait(5.0)
        for bus in masters:
            _cycle_frames(bus, 0x0F, 100)
        sent = time.monotonic()
        returned: list[bool] = []
        for _ in range(20):  # True once the pass was ours (the thread may have had it)
            call = threading.Thread(target=lambda: returned.append(group.lockstep_pass()))
            call.start()
            call.join(5.0)  # it would hang on the lock for as long as the holder keeps it
            assert not call.is_alive(), "lockstep_pass waited for a segment's lock"
            if second.sync_count > before[1]:
                break
            time.sleep(0.001)
        assert (first.sync_count, second.sync_count) == (before[0], before[1] + 1)
        assert first.received_until < sent  # its frames were not read
        release.set()
        holder.join(5.0)
        _wait(lambda: group.lockstep_pass() and first.sync_count == before[0] + 1,
              "the first segment answered once its lock is free")
        assert second.sync_count == before[1] + 1
    finally:
        release.set()
        _close(lone, group, lone_masters + masters)
    group.check()


def test_a_lockstep_group_runs_the_drives_timers_and_hands_them_back_when_left():
    """In lockstep the drives' timer events (here the heartbeat producer) run in the pass,
    their threads standing by: the heartbeats appear while ``lockstep_pass`` runs, not in
    the pauses between calls. A loop that stops stepping the group leaves them to the
    timer threads again, and the heartbeats go on at their period."""
    lone, group, lone_masters, masters = _two_groups_of(
        2, f"timers-{uuid.uuid4().hex[:8]}", lockstep=True)
    period = 0.01
    first_bus = masters[0]
    beat = cia301.HEARTBEAT + NODES[0]

    def count(bus: can.BusABC) -> int:
        return sum(msg.arbitration_id == beat for msg in iter(lambda: bus.recv(0.0), None))

    try:
        done = threading.Event()

        def steps() -> None:  # the SDO answer below comes from a pass
            while not done.is_set():
                group.lockstep_pass()
                time.sleep(0.001)
        stepper = threading.Thread(target=steps)
        stepper.start()
        try:
            _sdo_write(first_bus, NODES[0], cia301.PRODUCER_HEARTBEAT_TIME, 0,
                       struct.pack("<H", round(period * 1000)))
        finally:
            done.set()
            stepper.join(5.0)
        in_passes = between = 0
        end = time.monotonic() + 0.3
        while time.monotonic() < end:
            between += count(first_bus)  # sent while no pass ran
            group.lockstep_pass()
            in_passes += count(first_bus)
            time.sleep(0.004)  # well inside LOCKSTEP_GRACE: the timer thread stands by
        expected = 0.3 / period
        assert in_passes >= expected / 2, (in_passes, between)
        assert between <= in_passes / 4, (in_passes, between)  # (a stalled caller: some)
        time.sleep(0.05)  # no more passes: the timer thread takes over
        count(first_bus)
        time.sleep(0.2)
        assert count(first_bus) >= 0.2 / period / 2
    finally:
        _close(lone, group, lone_masters + masters)
    group.check()
