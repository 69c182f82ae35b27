"""Several simulated segments (one per bus) served by ONE receive thread.

A bench of 12 drives on 4 buses at 1 kHz has four segments. Each with a receive thread of
its own, every cycle wakes four threads (more when the loop's RPDOs and SYNC arrive in
separate bursts), and each wake-up is a hand-over of the GIL that the control loop in the
same process waits behind. A group waits for frames on all its buses at once
(frame_io.BusSelector: one ``select`` on SocketCAN, one shared Event on in-process buses)
and hands each bus's frames to its own segment (``SimulatedSegment.pump``), so a cycle
wakes one thread. The drives cannot tell the difference: each segment keeps its lock, its
timers, its dynamics and its arrival-time rules (``received_until``: a bus the selector
found empty is vouched for with ``nothing_arrived``, so a lost heartbeat on a silent bus
is still seen).

The segments' joints are stepped together too: the group joins their dynamics into one set
of arrays (``JointDynamics.joined``: each segment's arrays become views of its slice) and,
after handing over a wake-up's frames, steps every segment whose SYNC came in one call. A
step is ~50 numpy calls whose cost hardly depends on the joint count, so four 3-joint
segments cost a quarter of what four steps would (the largest single part of the
simulator's CPU). A segment whose SYNC is left to the group takes its step alone the moment
another frame of its bus needs the drives after it (an SDO request, an NMT command; a
master's heartbeat does not) - so every drive still sees its frames in order, with its step
between. Three rules keep the steps joined when it matters most, under load:

- A segment stops reading after a SYNC it defers and keeps the rest (``pump``'s backlog):
  a group that lags finds several cycles queued and catches up one cycle of every bus per
  joined step, instead of each segment stepping alone at its next SYNC (four times the
  cost, which kept a lagging bench lagging); at most ``CATCH_UP_ROUNDS`` per pass. A bus
  with frames kept is not vouched for as silent (``nothing_arrived``) until they are
  handled.
- A SYNC that came without the other buses' waits up to ``JOIN_WAIT`` for them.
- A timer event of a segment whose step waits comes after the step (rescheduled); a change
  through a drive's API takes the step first.

The group holds the lock of every segment it reads from the first frame it hands over to the
last answer, so no timer of such a segment runs between a SYNC and its step (the others'
timers run on); and it holds its buses' wake-ups for the pass (inproc.py's
``hold_wakeups``), so the master's reader wakes once for all the answers. The joined step
writes every segment's arrays, so it also takes the other segments' locks if they are free
at once; if one is busy (its timer stepping its joints alone) the pass's segments step
alone instead. A drive that raises while answering is its
own segment's failure (``check``); the thread goes on reading every bus. Equal SYNC periods
(the loop sends one SYNC per bus per cycle) give exactly the steps of segments stepped
alone; periods that need different sub-step counts are integrated in the larger count
(shorter sub-steps).

Lockstep (``start(lockstep=True)``, what ``rocoma-can demo`` and benchmarks/loop_run.py
use): the control loop's own thread runs the pass right after its write
(``lockstep_pass``, via ``stepped_before(on_cycle)``), so the drives answer each SYNC
before the loop sleeps and no thread takes the GIL from the loop, or the loop from it, in
the middle of a cycle; the receive thread stands by, and reads the buses again when the
loop has not called for LOCKSTEP_GRACE. With 12 drives on 4 buses at 1 kHz the simulator
on its thread cost more CPU a cycle than stepped in lockstep (hand-overs of the GIL cost
more than the simulation), and tripped TPDO supervision where lockstep holds
(benchmarks/HISTORY.md; the figures: benchmarks/README.md).

Buses one thread cannot wait on together (python-can's ``virtual`` hands frames over a
queue per bus) get a receive thread per segment, as a lone segment has (no lockstep). A
bus whose interface fails is counted in its own segment's ``bus_errors`` and read again
every ``RX_IDLE`` seconds (BusSelector.failed) while the others are served.
"""
from __future__ import annotations

import math
import threading
from collections.abc import Callable, Iterable

import numpy as np

from ..link.frame_io import BusSelector, FrameReader
from .dynamics import JointDynamics
from .segment import JOIN_WAIT, SimulatedSegment
from .timers import RX_IDLE

#: Cycles of every bus one pass catches up at most: a pass holds its segments' locks and
#: their buses' wake-ups, so a long catch-up is cut into passes between which the timers
#: run (heartbeats) and the master's reader is woken for the answers so far.
CATCH_UP_ROUNDS = 8
#: A lockstep group's receive thread stands by while the loop called ``lockstep_pass``
#: within this long, and reads the buses itself again after (a loop stopped or stalled).
LOCKSTEP_GRACE = RX_IDLE


class SegmentGroup:
    """``SegmentGroup(segments).start()``; the group starts and stops its segments."""

    def __init__(self, segments: Iterable[SimulatedSegment]) -> None:
        self.segments = tuple(segments)
        if not self.segments:
            raise ValueError("a segment group needs at least one segment")
        # one receive thread serves every segment (False: one thread each)
        self.shared_thread = BusSelector.supports([s.bus for s in self.segments])
        self._selector: BusSelector | None = None  # made by start: it hooks into the buses
        self._dynamics: JointDynamics | None = None  # the joined joints (start), if shared
        self._dt = np.zeros(0)  # a joined step's length per joint
        self._slices: list[slice] = []
        self.joined_steps = 0  # dynamics steps taken for two segments or more at once
        self._join_by: float | None = None  # a SYNC waits for the others' until then
        self._locks: list[threading.RLock] = []  # the segments' (start)
        self._readers: list[FrameReader] = []
        # the buses' hold_wakeups and release_wakeups (inproc.py), where they have them
        self._holds: list[tuple[Callable[[], None], Callable[[], None]]] = []
        self.lockstep = False  # start(lockstep=True): see lockstep_pass
        self.lockstep_passes = 0
        self._lockstep_at = -math.inf  # the loop's latest lockstep_pass call
        self._pass_lock = threading.Lock()  # one pass at a time: the loop's or the thread's
        self._stopped = threading.Event()
        self._thread = threading.Thread(target=self._receive_loop, name="sim-group-rx",
                                        daemon=True)
        self._started = False

    def start(self, thread: bool = True, lockstep: bool = False) -> SegmentGroup:
        """Start every segment, and the one receive thread unless ``thread`` is False
        (then the caller runs ``pass_once``). ``lockstep``: the control loop's thread steps
        the simulator after each write (``lockstep_pass``); the receive thread stands by."""
        if self._started:
            raise RuntimeError("segment group already started")
        self._started = True
        self.lockstep = lockstep and self.shared_thread
        try:
            if self.shared_thread:
                self._selector = BusSelector([s.bus for s in self.segments], retry=RX_IDLE)
                if len(self.segments) > 1:
                    self._join_dynamics()
            for segment in self.segments:
                segment.start(receive=not self.shared_thread)
            if self._selector is not None:
                self._locks = [s.lock for s in self.segments]
                self._readers = [FrameReader(s.bus) for s in self.segments]
                holds = [(getattr(s.bus, "hold_wakeups", None),
                          getattr(s.bus, "release_wakeups", None)) for s in self.segments]
                self._holds = [(h, r) for h, r in holds if h is not None and r is not None]
                if thread:
                    self._thread.start()
        except BaseException:
            self.stop()
            raise
        return self

    def stop(self) -> None:
        """Stop the receive thread (joined), then every segment; idempotent."""
        self._stopped.set()
        if self._thread.is_alive():
            self._thread.join(2.0)
        for segment in self.segments:
            segment.stop()
        if self._selector is not None:
            self._selector.close()

    def check(self) -> None:
        """Re-raise the first exception a segment's threads caught, if any."""
        for segment in self.segments:
            segment.check()

    def __enter__(self) -> SegmentGroup:
        return self.start()

    def __exit__(self, *exc: object) -> None:
        self.stop()

    def _join_dynamics(self) -> None:
        """One set of arrays for every segment's joints (before the segments start)."""
        self._dynamics = JointDynamics.joined([s.dynamics for s in self.segments])
        self._dt = np.zeros(self._dynamics.n)
        first = 0
        for segment in self.segments:
            self._slices.append(slice(first, first + segment.dynamics.n))
            first += segment.dynamics.n
            segment.defer_steps()

    def _receive_loop(self) -> None:
        try:
            while not self._stopped.is_set():
                if self.lockstep and \
                        SimulatedSegment.clock() - self._lockstep_at < LOCKSTEP_GRACE:
                    self._stopped.wait(LOCKSTEP_GRACE)  # the loop steps us: stand by
                    continue
                with self._pass_lock:  # (a lockstep group's pass never waits for a lock)
                    whole = self.pass_once(RX_IDLE, wait_locks=not self.lockstep)
                if not whole:  # a segment's lock was taken: its frames wait a little
                    self._stopped.wait(JOIN_WAIT)
        except Exception as exc:  # noqa: BLE001 - a bug here: every segment's check says so
            self._record(exc)
            raise

    def lockstep_pass(self) -> bool:
        """Step the simulator on the caller's thread: the frames waiting on every bus,
        each segment's SYNC, one joined dynamics step, the answers; for the control loop's
        thread, right after its write (``start(lockstep=True)``). False when it did nothing:
        not a lockstep group, or the receive thread is in a pass (it has the frames).

        Why: a simulator thread in the loop's process takes the GIL in turns with the loop
        and its reader, and every turn costs more than the simulation (12 drives, 4 buses
        at 1 kHz cost about twice the CPU on a thread of their own as stepped here). In
        lockstep the drives answer each SYNC before the loop sleeps, as drives on a bus do
        well within a cycle; the loop's measured work includes the simulator's.

        The segments' timer events (heartbeats, consumer deadlines) run here too, after
        the frames, and their timer threads stand by: a timer thread the scheduler starves
        while it holds a segment's lock would keep that segment from this pass.

        Never waits: a segment whose lock another thread holds (a fault injected through a
        drive's API) is read in the next pass, and a SYNC does not wait for other buses'
        (the write sent them all). A loop that stops calling (stopped, or stalled for
        LOCKSTEP_GRACE) hands the buses back to the receive thread and the timers to
        theirs, so heartbeats are still sent and judged and SDOs still answered."""
        if not self.lockstep:
            return False
        self._lockstep_at = SimulatedSegment.clock()
        if not self._pass_lock.acquire(blocking=False):
            return False
        try:
            self.pass_once(0.0, wait_locks=False, join_wait=0.0)
            now = SimulatedSegment.clock()
            for segment in self.segments:  # their timer threads stand by meanwhile
                segment.run_due_timers(now)
        except Exception as exc:  # noqa: BLE001 - a simulator bug must not stop the loop:
            self._record(exc)  # check() says so, and the receive thread takes over
            self.lockstep = False
            return False
        finally:
            self._pass_lock.release()
        self.lockstep_passes += 1
        return True

    def stepped_before(self, on_cycle: Callable[[float], None]) -> Callable[[float], None]:
        """An ``on_cycle`` for the control loop (it runs after each write) that steps this
        group (``lockstep_pass``) and then calls ``on_cycle``."""
        step = self.lockstep_pass

        def stepped(now: float) -> None:
            step()
            on_cycle(now)
        return stepped

    def _record(self, exc: BaseException) -> None:
        for segment in self.segments:
            segment.errors.append(exc)

    def pass_once(self, timeout: float, *, wait_locks: bool = True,
                  join_wait: float = JOIN_WAIT) -> bool:
        """One pass of the receive thread: wait up to ``timeout`` s (less while a SYNC waits
        for the others') for frames on any bus, hand them to their segments, step the
        joints of those whose SYNC came. Public for tests and benchmarks that run passes on
        their own thread (``start(thread=False)``). ``wait_locks`` False: a segment whose
        lock is taken is left for the next pass (then False); ``join_wait``: how long a
        SYNC waits for the other buses' (JOIN_WAIT)."""
        selector = self._selector
        assert selector is not None  # started only with a selector
        segments, locks, readers = self.segments, self._locks, self._readers
        clock = SimulatedSegment.clock
        since = clock()
        ready = self._ready_after(selector, timeout, since)
        held, busy = self._take_locks(ready, wait_locks)
        for hold, _ in self._holds:  # the answers wake their readers once, after the pass
            hold()
        try:
            if len(ready) < len(segments):
                for i in selector.wait(0.0):
                    if i not in ready and locks[i].acquire(blocking=False):
                        held.append(locks[i])
                        ready.append(i)
            for i, segment in enumerate(segments):
                if i in ready:
                    if not segment.pump(readers[i], 0.0):
                        selector.failed(i)
                elif i not in busy and not selector.failing(i) and not segment.backlog:
                    segment.nothing_arrived(since)  # (a backlog: not everything handled)
            self._step_deferred(held, clock(), join_wait, wait_locks)
            self._catch_up(selector, ready, held, join_wait, wait_locks)
        finally:
            for _, release in self._holds:
                release()
            for lock in reversed(held):
                lock.release()
        return not busy

    def _ready_after(self, selector: BusSelector, timeout: float, since: float) -> list[int]:
        """The segments with frames to handle, in order, after waiting up to ``timeout``
        s (not at all while frames kept from an earlier pass wait; no longer than a SYNC
        waits for the others')."""
        segments = self.segments
        if any(s.backlog and s.deferred_dt is None for s in segments):
            timeout = 0.0
        elif self._join_by is not None:
            timeout = min(timeout, max(self._join_by - since, 0.0))
        ready = selector.wait(timeout)
        for i, segment in enumerate(segments):  # frames kept after a SYNC (pump)
            if segment.backlog and segment.deferred_dt is None and i not in ready:
                ready.append(i)
        ready.sort()
        return ready

    def _take_locks(self, ready: list[int],
                    wait_locks: bool) -> tuple[list[threading.RLock], set[int]]:
        """The locks of the segments to read, in order, held from the first frame to the
        joined step (no timer of theirs runs between a SYNC and its step); a bus whose
        frames came meanwhile joins the pass if its lock is free. No other holder takes
        two locks, so nobody waits in a cycle. Returns the locks held and the segments
        left out of ``ready`` (``wait_locks`` False: another thread holds its lock)."""
        locks = self._locks
        held = []
        busy = set()
        for i in list(ready):
            if wait_locks:
                locks[i].acquire()
            elif not locks[i].acquire(blocking=False):
                busy.add(i)
                ready.remove(i)
                continue
            held.append(locks[i])
        return held, busy

    def _catch_up(self, selector: BusSelector, ready: list[int],
                  held: list[threading.RLock], join_wait: float, wait_locks: bool) -> None:
        """Behind by more than a cycle: the next cycle of every bus read, one joined step
        again, until the backlogs are gone, the SYNCs part, or CATCH_UP_ROUNDS (then the
        next pass, at once, after the locks and wake-ups were given back)."""
        segments, readers = self.segments, self._readers
        rounds = 1
        while rounds < CATCH_UP_ROUNDS and self._join_by is None \
                and any(segments[i].backlog for i in ready):
            rounds += 1
            for i in ready:
                if not segments[i].pump(readers[i], 0.0):
                    selector.failed(i)
            self._step_deferred(held, SimulatedSegment.clock(), join_wait, wait_locks)

    def _step_deferred(self, held: list[threading.RLock], now: float,
                       join_wait: float, wait_locks: bool = True) -> None:
        """Step the joints of every segment whose SYNC came, in one call; each then samples
        and answers its SYNC (the locks of the segments read in this pass ``held``).

        A SYNC that came without the others' (their bus's frames not here yet: another
        process sending, a sender that lost the GIL mid-burst) waits up to ``join_wait``
        for them, so the cycle still costs one step; the segment's lock is free meanwhile, and
        anything else for it (a frame, a timer) takes its step first, as ever.

        The joined step writes every joint's arrays, a segment given no step included, so
        it needs every segment's lock: a segment outside this pass may be stepping its own
        joints on its timer (free-running, no SYNC for a while) in the same arrays. A lock
        that is not free at once is not waited for: the pending segments step alone."""
        if self._dynamics is None:
            return
        pending = [s for s in self.segments if s.deferred_dt is not None]
        if not pending:
            self._join_by = None
            return
        if len(pending) < len(self.segments):
            if self._join_by is None:
                self._join_by = now + join_wait
            if now < self._join_by:
                return  # the others' SYNCs may be on their way
        self._join_by = None
        if len(pending) >= 2:
            others = self._take_other_locks(held)
            if others is not None:
                try:
                    self._step_joined(
                        [s for s in self.segments if s.deferred_dt is not None])
                finally:
                    for lock in reversed(others):
                        lock.release()
                return
        for segment in pending:  # alone: the same cost
            lock = segment.lock  # one read in an earlier pass is not held now
            if segment.lock in held or wait_locks:
                with lock:
                    self._finish(segment, segment.finish_deferred)
            elif lock.acquire(blocking=False):  # (taken: its next frame or timer steps it)
                try:
                    self._finish(segment, segment.finish_deferred)
                finally:
                    lock.release()

    def _take_other_locks(self, held: list[threading.RLock]) -> list[threading.RLock] | None:
        """The locks of the segments not ``held``, taken if every one is free now; None
        (none taken) if one is not."""
        taken: list[threading.RLock] = []
        for segment in self.segments:
            if segment.lock in held:
                continue
            if not segment.lock.acquire(blocking=False):
                for lock in reversed(taken):
                    lock.release()
                return None
            taken.append(segment.lock)
        return taken

    def _step_joined(self, pending: list[SimulatedSegment]) -> None:
        """One dynamics step for every joint (every segment's lock held), then answers."""
        dynamics, dt = self._dynamics, self._dt
        assert dynamics is not None  # only with joined dynamics
        for segment, joints in zip(self.segments, self._slices):
            step = segment.deferred_dt
            dt[joints] = 0.0 if step is None else step
        try:
            dynamics.step(dt)
        except Exception as exc:  # noqa: BLE001 - a bug: every stepped segment says so
            for segment in pending:
                segment.deferred_dt = None
                segment.record(exc)
            return
        self.joined_steps += 1
        for segment in pending:
            self._finish(segment, segment.finish_joined)

    @staticmethod
    def _finish(segment: SimulatedSegment, finish: Callable[[], None]) -> None:
        """One segment's answer; a drive that raises is that segment's failure (check()),
        never the end of the thread every other bus is read on."""
        try:
            finish()
        except Exception as exc:  # noqa: BLE001 - recorded, receiving goes on
            segment.deferred_dt = None
            segment.record(exc)
