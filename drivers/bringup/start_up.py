"""Every drive's start-up as the hardware runs it: the configuration workers, each drive's
bring-up stepped once per cycle, and the report of how it ended.

The cycle submits configurations (SDO jobs) and the report's lines to the workers, and a
submit that finds no idle worker would start a thread on the cycle: ``open_workers`` starts
every one of them first. What a drive's bring-up means for the rest of the hardware is
handed back by two calls: ``on_ready`` (supervise it from now) and ``on_configured`` (its
heartbeat consumer or life guarding was just set up: the manager's heartbeat or guard
request must go out this cycle).
"""
from __future__ import annotations

import logging
import threading
from collections.abc import Callable, Sequence
from concurrent.futures import ThreadPoolExecutor

import numpy as np

from .drive_bringup import BringupPhase, DriveBringup
from .report import BringupReport

# The hardware's logger: start-up is the hardware's work, and its records are found there
# (a log filter on it, the demo's among them, keeps working).
log = logging.getLogger("rocoma_can.drivers.hardware")

#: how long ``open_workers`` waits for the configuration workers' threads to run (s)
WORKER_START = 5.0


class StartUp:
    """The bring-ups of N drives and the workers their configurations run on.

    ``node_ids``, ``bus_of``, ``channel``: the report's (report.py); ``on_ready(i, now)``:
    drive i became READY; ``on_configured(i)``: drive i's configuration completed."""

    def __init__(self, node_ids: Sequence[int], bus_of: Sequence[int],
                 channel: Callable[[int], str], *,
                 on_ready: Callable[[int, float], None],
                 on_configured: Callable[[int], None]) -> None:
        self.report = BringupReport(node_ids, bus_of, channel, self._submit)
        self.executor: ThreadPoolExecutor | None = None
        self.bringups: Sequence[DriveBringup] = ()
        self._on_ready, self._on_configured = on_ready, on_configured

    def open_workers(self, count: int) -> None:
        """Start ``count`` configuration workers, every thread of them now: the executor
        starts one on a submit that finds none idle, and bring-up submits from the cycle,
        which must not start a thread. Each waits at the barrier, so each submit finds
        none idle and starts one."""
        self.executor = ThreadPoolExecutor(max_workers=count,
                                           thread_name_prefix="canopen-config")
        started = threading.Barrier(count + 1)
        for _ in range(count):
            self.executor.submit(started.wait, WORKER_START)
        try:
            started.wait(WORKER_START)
        except threading.BrokenBarrierError:  # a machine that slow starts the rest later
            log.warning("configuration workers not all started within %.0f s", WORKER_START)

    def begin(self, bringups: Sequence[DriveBringup], now: float) -> None:
        """Every drive's bring-up from its beginning, from ``now``."""
        for b in bringups:
            b.restart(now)
        self.report.started_at = now
        self.bringups = bringups

    def step(self, now: float, fresh: np.ndarray, states: np.ndarray,
             codes: np.ndarray) -> None:
        """One cycle of every bring-up still running (``fresh``: whose TPDOs all came;
        ``states``, ``codes``: JointState's CiA 402 states and error codes)."""
        executor = self.executor
        if executor is None:
            return
        bringups = self.bringups
        for i, b in enumerate(bringups):
            phase = b.phase
            if phase == BringupPhase.READY or phase == BringupPhase.FAILED:
                continue
            if b.step(now, executor, bool(fresh[i]), int(states[i]), int(codes[i])):
                self._on_ready(i, now)
                self.report.ended(i, bringups, now)
            elif b.phase == BringupPhase.FAILED:
                # said once (status has it too), by a worker: the cycle does no I/O
                self.report.ended(i, bringups, now)
            elif phase == BringupPhase.CONFIGURING and b.phase == BringupPhase.STARTING:
                self._on_configured(i)

    @property
    def starting(self) -> bool:
        """Some drive is still in bring-up (neither READY nor FAILED)."""
        return any(b.phase not in (BringupPhase.READY, BringupPhase.FAILED) for b in self.bringups)

    def _submit(self, call: Callable[..., object], *args: object) -> None:
        """``call(*args)`` on a configuration worker (the report's lines)."""
        if self.executor is not None:
            self.executor.submit(call, *args)

    def close(self) -> None:
        """Cancel every configuration and join the workers."""
        for b in self.bringups:
            b.cancel()
        if self.executor is not None:
            self.executor.shutdown(wait=True, cancel_futures=True)
            self.executor = None
