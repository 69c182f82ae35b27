"""The writer process gives its CPU away every ``PIECE`` of its work, so a loop queued on its
CPU waits for one piece, not for a writing burst.

The writer works in bursts: every 50 ms (writer.POLL) it turns what the rings got into JSON,
MCAP and candump text (~15 ms of CPU for 12 drives on 4 buses at 1 kHz, every frame in the
trace), and on an e-stop it writes a flight record (1-1.6 s of CPU). Its niceness does not keep
such a burst from delaying the loop. Traced on a 2-core VM (kernel 6.18, HZ=250) at 1 kHz:
the loop, woken by its timer on the CPU the writer was running on, was left queued there
until the writer's slice or the next tick ended, 2.4-3.8 ms later, while the other CPU
idled: the scheduler did not preempt the writer on that wake-up (the trace shows no
need-resched set) whether the writer ran at nice 19, SCHED_IDLE or SCHED_BATCH. Those waits were
most of the loop's missed cycles with recording on. A loop with ``realtime.priority``
(SCHED_FIFO) preempts any such task at once; this is for the loop at normal priority, the
default.

A ``sched_yield`` ends the writer's turn: a task queued on its CPU runs next. Work is
counted in the thread's CPU time, so time the writer spent preempted or asleep is no reason
to yield again (under contention that would cut its share further, towards falling a ring
behind); the CPU clock (a system call) is read only once a piece of wall time has passed
(``perf_counter``, a tenth of its cost). With nothing queued a yield returns at once (a
few hundred a second while the writer works; the figures: benchmarks/README.md, "Figures
behind constants"). What stays whole is what happens in one
call: a numpy sort or copy of a flight record's 10 s, an MCAP chunk's compression.
"""
from __future__ import annotations

import os
import time
from collections.abc import Callable

#: the writer's work between two yields, s: well inside a 1 kHz cycle's slack
PIECE = 0.0002


class Pacer:
    """``pace()`` in the writer's loops: a yield once ``piece`` seconds of the thread's CPU
    time have passed since the last one (see module). ``yields`` counts them; the clocks
    are the wall's and the thread's work's."""

    def __init__(self, piece: float = PIECE, wall: Callable[[], float] = time.perf_counter,
                 work: Callable[[], float] = time.thread_time) -> None:
        self.piece = piece
        self.yields = 0
        self._wall, self._work = wall, work
        self._checked, self._worked = wall(), work()

    def __call__(self) -> None:
        now = self._wall()
        if now - self._checked < self.piece:
            return
        self._checked = now
        if self._work() - self._worked < self.piece:  # preempted or asleep meanwhile
            return
        os.sched_yield()
        self.yields += 1
        self._checked, self._worked = self._wall(), self._work()


def unpaced() -> None:
    """The pace of a writer alone on its thread and CPU (benchmarks, tools): none."""
