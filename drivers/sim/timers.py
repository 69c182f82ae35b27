"""The simulated segment's timers: monotonic one-shot events on one thread.

Heartbeats, consumer deadlines, late TPDOs and babbling are timer events of the segment
(segment.py), run with its lock held; a lockstep pass (group.py) may run them on its own
thread instead.
"""
from __future__ import annotations

import heapq
import itertools
import math
import threading
import time
from collections.abc import Callable
from typing import Any

#: Longest wait for a frame before the receive thread looks at ``_stopped`` again; also how
#: stale ``received_until`` may get on a silent bus (a heartbeat loss is seen this much late).
RX_IDLE = 0.02


class Timers:
    """Monotonic one-shot timers on one thread (a heap, no thread per timer), or on the
    thread of a lockstep pass (``run_due``): the timer thread then stands by until no pass
    has run them for RX_IDLE."""

    def __init__(self, run: Callable[[Callable[..., Any], tuple[Any, ...]], None]) -> None:
        self._run = run
        self._heap: list[tuple[float, int, Callable[..., Any], tuple[Any, ...]]] = []
        self._seq = itertools.count()
        self._cond = threading.Condition()
        self._stopped = False
        self._driven_at = -math.inf  # the latest run_due
        self._thread = threading.Thread(target=self._loop, name="sim-timers", daemon=True)

    def start(self) -> None:
        self._thread.start()

    def stop(self, timeout: float = 2.0) -> None:
        with self._cond:
            self._stopped = True
            self._cond.notify()
        if self._thread.is_alive():
            self._thread.join(timeout)

    def call_at(self, when: float, fn: Callable[..., Any], args: tuple[Any, ...]) -> None:
        with self._cond:
            heapq.heappush(self._heap, (when, next(self._seq), fn, args))
            if time.monotonic() - self._driven_at >= RX_IDLE:  # (standing by: no wake-up)
                self._cond.notify()

    def run_due(self, now: float) -> None:
        """Run the events due by ``now`` on the caller's thread, in order."""
        if now - self._driven_at >= RX_IDLE:  # the thread may be in a long wait: from
            with self._cond:  # now on it stands by in RX_IDLE turns, and resumes in time
                self._driven_at = now
                self._cond.notify()
        self._driven_at = now
        heap = self._heap
        while heap and heap[0][0] <= now:  # (a look without the lock: popped under it)
            with self._cond:
                if not heap or heap[0][0] > now:
                    return
                _, _, fn, args = heapq.heappop(heap)
            self._run(fn, args)

    def _loop(self) -> None:
        while True:
            with self._cond:
                while not self._stopped:
                    now = time.monotonic()
                    if now - self._driven_at < RX_IDLE:  # a lockstep pass runs them
                        self._cond.wait(RX_IDLE)
                        continue
                    if self._heap and self._heap[0][0] <= now:
                        break
                    wait = self._heap[0][0] - now if self._heap else 0.5
                    self._cond.wait(min(wait, 0.5))
                if self._stopped:
                    return
                _, _, fn, args = heapq.heappop(self._heap)
            self._run(fn, args)
