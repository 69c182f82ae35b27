"""The group's joined step (drivers/sim/group.py): every segment whose SYNC came in one
pass is stepped in one call, and the drives must not tell.

What must hold: segments in a group end bit for bit where the same segments alone do; a
drive that raises in a joined step fails its own segment only; no joined step while a
segment outside the pass may be stepping alone on its timer; a group that lags catches up
one joined step per cycle; a SYNC waits (JOIN_WAIT at most) for the other buses' SYNCs;
the frames kept behind a waiting SYNC are not vouched for and come before a fault.
"""
from __future__ import annotations

import time
import uuid

import can
import pytest
from fixtures.driver_rig import VIRTUAL
from fixtures.sim_group import (
    CSP,
    NODES,
    RPDO1,
    RPDO2,
    close_groups,
    cycle_frames,
    send,
    two_groups_of,
    wait_until,
)

from rocoma_can.drivers.protocol import cia301
from rocoma_can.drivers.protocol.cia402 import State402
from rocoma_can.drivers.sim.group import SegmentGroup
from rocoma_can.drivers.sim.segment import RX_IDLE, SimulatedSegment


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
                        send(bus, 0x200 + n, RPDO1.pack(controlword, CSP, 0))
                        send(bus, 0x300 + n, RPDO2.pack(target * n, 0))
                for bus in masters:
                    send(bus, cia301.SYNC, b"")
            syncs += 1
            deadline = time.monotonic() + VIRTUAL.detect_budget()
            while not all(s.sync_count >= syncs for s in segments):
                assert time.monotonic() < deadline, f"every segment handles SYNC {syncs}"
                time.sleep(0.001)

        for bus in masters:
            send(bus, cia301.NMT, bytes((cia301.NmtCommand.START, 0)))
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
                    send(bus, cia301.SYNC, b"")
            wait_until(lambda k=k: group.segments[1].sync_count >= k, f"bus 1 answers SYNC {k}")
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
                send(bus, cia301.SYNC, b"")
        wait_until(lambda: all(s.sync_count >= k for s in segments[:2]),
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


def test_a_group_that_lags_catches_up_with_one_joined_step_per_cycle():
    """A group that fell behind (a stalled thread, a loaded machine) finds several cycles
    of every bus queued. It must take them one cycle at a time, each with one joined step,
    and answer every SYNC in order, exactly as lone segments fed the same frames; not let
    each segment step alone at its next SYNC (four times the cost, which kept a lagging
    1 kHz bench lagging). A master's heartbeat right after each SYNC does not break the
    join. Here 30 cycles are queued on four buses before the passes."""
    lone, group, lone_masters, masters = two_groups_of(4, f"lag-{uuid.uuid4().hex[:8]}")
    try:
        steps_before = group.joined_steps
        cycles = 30
        for k in range(cycles):
            for bus in lone_masters + masters:
                cycle_frames(bus, 0x0F, 400 * k)
            wait_until(lambda k=k: all(s.sync_count >= 4 + k for s in lone),
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
        close_groups(lone, group, lone_masters + masters)
    group.check()


def test_a_sync_waits_for_the_other_buses_syncs_then_steps_without_them():
    """A cycle's SYNCs reach the group's buses one after another (another process sends
    them, the sender loses the GIL mid-burst). A SYNC that came alone is not answered in
    that pass: the group waits up to JOIN_WAIT for the others', then one joined step
    answers all. A SYNC whose companions never come is answered after JOIN_WAIT: a pass
    then waits no longer than that, however long its timeout."""
    lone, group, lone_masters, masters = two_groups_of(2, f"wait-{uuid.uuid4().hex[:8]}")
    try:
        first, second = group.segments
        steps = group.joined_steps
        cycle_frames(masters[0], 0x0F, 100)
        group.pass_once(0.0)
        assert (first.sync_count, second.sync_count) == (3, 3)  # waiting: not answered yet
        cycle_frames(masters[1], 0x0F, 100)
        group.pass_once(0.0)
        assert (first.sync_count, second.sync_count) == (4, 4)
        assert group.joined_steps == steps + 1  # one step for both
        cycle_frames(masters[0], 0x0F, 200)  # the other bus's master is gone
        group.pass_once(0.0)
        assert first.sync_count == 4
        for _ in range(3):  # a pass waits no longer than JOIN_WAIT (a wake-up may end it
            group.pass_once(10 * RX_IDLE)  # sooner: frames already handled)
            if first.sync_count == 5:
                break
        assert (first.sync_count, second.sync_count) == (5, 4)
        assert group.joined_steps == steps + 1  # alone
    finally:
        close_groups(lone, group, lone_masters + masters)
    group.check()


def test_frames_kept_after_a_waiting_sync_are_not_vouched_for_and_come_before_a_fault():
    """A SYNC that waits for the other buses' keeps the frames after it unhandled (the
    segment's backlog). While they wait, the group must not vouch for the bus as silent
    (``received_until`` past them would let a heartbeat consumer judge a heartbeat that
    came in time as lost); and a fault injected through a drive's API meanwhile comes
    after that SYNC's step and answer, not between its RPDOs and its step."""
    lone, group, lone_masters, masters = two_groups_of(2, f"kept-{uuid.uuid4().hex[:8]}")
    try:
        first = group.segments[0]
        cycle_frames(masters[0], 0x0F, 100)  # RPDOs, SYNC, then a master heartbeat
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
        cycle_frames(masters[0], 0x0F, 200)
        group.pass_once(0.0)
        assert first.deferred_dt is not None and first.sync_count == 4
        first.drives[NODES[0]].set_sto(True)
        assert first.deferred_dt is None and first.sync_count == 5  # the SYNC first
        assert first.drives[NODES[0]].sto_low
    finally:
        close_groups(lone, group, lone_masters + masters)
    group.check()
