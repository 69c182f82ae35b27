"""A segment group in lockstep (drivers/sim/group.py; the demo's simulator): the control
loop's thread steps it right after its write, no thread hand-over in the cycle.

What must hold: each cycle is answered on the caller's thread, the joints moving as lone
segments' do; a loop that stops stepping the group leaves it to its own thread (within
LOCKSTEP_GRACE) instead of deaf drives; a pass never waits for a segment another thread
holds; the drives' timers run in the passes and go back to their threads when left.
"""
from __future__ import annotations

import struct
import threading
import time
import uuid

import can
from fixtures.sim_group import (
    NODES,
    close_groups,
    cycle_frames,
    sdo_write,
    two_groups_of,
    wait_until,
)

from rocoma_can.drivers.protocol import cia301


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
    lone, group, lone_masters, masters = two_groups_of(
        4, f"lockstep-{uuid.uuid4().hex[:8]}", lockstep=True)
    try:
        for bus in masters:
            _answers(bus)  # the bring-up's
        cycles, answered, passes = 60, 0, group.lockstep_passes
        steps = group.joined_steps
        for k in range(cycles):
            for bus in lone_masters + masters:
                cycle_frames(bus, 0x0F, 400 * k)
            syncs = [s.sync_count for s in group.segments]
            if group.lockstep_pass():
                for segment, bus, before in zip(group.segments, masters, syncs):
                    if segment.sync_count > before:  # answered within the call
                        assert TPDOS <= _answers(bus)  # (+ heartbeats)
                        answered += 1
            wait_until(lambda k=k: all(s.sync_count >= 4 + k for s in group.segments),
                       f"SYNC {4 + k} answered")
            for bus in masters:
                _answers(bus)
        assert answered >= 0.75 * 4 * cycles, answered
        assert group.lockstep_passes - passes >= 0.75 * cycles
        assert group.joined_steps - steps >= 0.75 * cycles
        wait_until(lambda: all(s.sync_count >= 3 + cycles for s in lone), "lone segments")
        moved = [s.drives[n].position_rad for s in lone for n in NODES]
        assert min(abs(q) for q in moved) > 0.001
        assert [s.drives[n].position_rad for s in group.segments for n in NODES] == moved
    finally:
        close_groups(lone, group, lone_masters + masters)
    group.check()


def test_a_lockstep_group_is_read_by_its_thread_once_the_loop_stops_stepping_it():
    """A loop that stops calling ``lockstep_pass`` (it ended, or stalls) must not leave
    the drives deaf: within LOCKSTEP_GRACE the group's thread reads the buses again, so
    SYNCs and SDOs are answered and a lost master heartbeat is judged."""
    lone, group, lone_masters, masters = two_groups_of(
        2, f"standby-{uuid.uuid4().hex[:8]}", lockstep=True)
    try:
        for k in range(5):
            for bus in masters:
                cycle_frames(bus, 0x0F, 100 * k)
            group.lockstep_pass()
            wait_until(lambda k=k: all(s.sync_count >= 4 + k for s in group.segments),
                       f"SYNC {4 + k}")
        syncs = [s.sync_count for s in group.segments]
        for bus in masters:  # no lockstep_pass from here on
            cycle_frames(bus, 0x0F, 600)
        wait_until(lambda: [s.sync_count for s in group.segments] == [n + 1 for n in syncs],
                   "the group's thread answers the SYNCs")
    finally:
        close_groups(lone, group, lone_masters + masters)
    group.check()


def test_a_lockstep_pass_never_waits_for_a_segment_another_thread_holds():
    """The control loop's thread must never block on a lock a slower thread holds: a
    segment whose lock is taken (a fault injected through a drive's API) is left for a
    later pass, its bus is not vouched for as silent, and the other buses are answered.
    The group's own thread, should it take over (a caller stalled for LOCKSTEP_GRACE on a
    loaded machine), does not wait for that lock either, so lockstep passes resume."""
    lone, group, lone_masters, masters = two_groups_of(
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
            cycle_frames(bus, 0x0F, 100)
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
        wait_until(lambda: group.lockstep_pass() and first.sync_count == before[0] + 1,
                   "the first segment answered once its lock is free")
        assert second.sync_count == before[1] + 1
    finally:
        release.set()
        close_groups(lone, group, lone_masters + masters)
    group.check()


def test_a_lockstep_group_runs_the_drives_timers_and_hands_them_back_when_left():
    """In lockstep the drives' timer events (here the heartbeat producer) run in the pass,
    their threads standing by: the heartbeats appear while ``lockstep_pass`` runs, not in
    the pauses between calls. A loop that stops stepping the group leaves them to the
    timer threads again, and the heartbeats go on at their period."""
    lone, group, lone_masters, masters = two_groups_of(
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
            sdo_write(first_bus, NODES[0], cia301.PRODUCER_HEARTBEAT_TIME, 0,
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
        close_groups(lone, group, lone_masters + masters)
    group.check()
