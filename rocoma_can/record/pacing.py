"""The writer process gives its CPU away every ``PIECE`` of work, so the loop never waits
for a writing burst.

The writer works in bursts: every 50 ms (writer.POLL) it turns what the rings got into JSON,
MCAP and candump text (~10 ms of CPU for 12 drives on 4 buses at 1 kHz), and on an e-stop it
writes a flight record (~1 s). Its niceness does not stop such a burst from delaying the
loop: when the loop's timer fires on the CPU the writer runs on, a kernel without wake-up
preemption (PREEMPT_NONE, the common server build), or an EEVDF scheduler that lets the
running task finish its slice (RUN_TO_PARITY), leaves the loop waiting in that CPU's queue
until the writer's slice or the next tick ends (3-4 ms at HZ=250), even with the other CPU
idle. Traced on a 2-core VM at 1 kHz: most of the loop's missed cycles with recording on
were such waits behind the writer; the writer as SCHED_IDLE or SCHED_BATCH did not change
it.

A ``sched_yield`` every ``PIECE`` of the writer's work ends its slice there: a loop queued
on its CPU runs next, so it waits for at most one piece. With nothing queued the yield
returns at once (~1 µs: a few hundred per second while the writer works).
"""
from __future__ import annotations

import os
import time

#: the writer's work between two yields at most, s: well inside a 1 kHz cycle's slack
PIECE = 0.0002


class Pacer:
    """``pace()`` in the writer's loops: a yield when ``piece`` seconds of work have passed
    since the last one (see module). ``yields`` counts them."""

    def __init__(self, piece: float = PIECE) -> None:
        self.piece = piece
        self.yields = 0
        self._since = time.perf_counter()

    def __call__(self) -> None:
        now = time.perf_counter()
        if now - self._since >= self.piece:
            os.sched_yield()
            self.yields += 1
            self._since = time.perf_counter()


def unpaced() -> None:
    """The pace of a writer alone on its thread and CPU (benchmarks, tools): none."""
