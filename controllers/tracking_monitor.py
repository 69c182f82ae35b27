"""Worker example (entry point ``worker_example``): a PD that reports its tracking error.

Shows rocoma's worker pattern: ``initialize`` starts a 30 Hz worker, ``pre_stop`` cancels it.
The worker samples the reference and the measured position (the cycle keeps running and is
never blocked by it) and publishes running statistics as an immutable TrackingStats: one
reference assignment, so readers on any thread get a consistent snapshot without a lock the
cycle could ever wait on.
"""
from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import numpy as np

from rocoma_can.workers import WorkerEvent, WorkerHandle, WorkerOptions

from .params import number
from .pd import JointPD

WORKER_NAME = "tracking_stats"


@dataclass(frozen=True)
class TrackingStats:
    """Tracking error (reference - measured) over the samples since initialize."""
    names: tuple[str, ...]
    samples: int
    rms: tuple[float, ...]        # rad, per joint
    max_abs: tuple[float, ...]    # rad, per joint
    last: tuple[float, ...]       # rad, per joint, latest sample
    time: float                   # monotonic time of the latest sample


class TrackingMonitor(JointPD):
    """The ``pd`` controller (same parameters) plus:
      monitor_frequency   Hz at which the worker samples the tracking error, > 0 (default 30)
    """

    def __init__(self, name: str = "worker_example", *, monitor_frequency: object = 30.0,
                 **pd_params: Any) -> None:
        super().__init__(name, **pd_params)
        self.monitor_frequency = number(self, "monitor_frequency", monitor_frequency,
                                        positive=True)
        self._worker: WorkerHandle | None = None
        self._stats: TrackingStats | None = None

    def create(self, dt: float) -> bool:
        if not super().create(dt):
            return False
        n = self.group.n
        self._sum_sq = np.zeros(n)   # touched by the worker thread only
        self._max_abs = np.zeros(n)
        self._error = np.zeros(n)
        self._samples = 0
        return True

    def initialize(self, dt: float) -> bool:
        if not super().initialize(dt):
            return False
        if self._worker is not None and self._worker.is_running:
            self.cancel_worker(self._worker, wait=True)
        self._sum_sq.fill(0.0)
        self._max_abs.fill(0.0)
        self._samples = 0
        self._stats = None
        self._worker = self.add_worker(WorkerOptions(
            name=WORKER_NAME, callback=self._sample, frequency=self.monitor_frequency))
        return self.start_worker(self._worker)

    def pre_stop(self) -> bool:
        if self._worker is None:
            return True
        return self.cancel_worker(self._worker, wait=True)

    def cleanup(self) -> bool:
        return self.pre_stop()

    def snapshot(self) -> TrackingStats | None:
        """The latest statistics (None before the first sample); safe from any thread."""
        return self._stats

    @property
    def worker(self) -> WorkerHandle | None:
        return self._worker

    def _sample(self, event: WorkerEvent) -> bool:
        # Copies of shared arrays the cycle writes in place: each element is consistent, the
        # set may straddle a cycle, which is fine for statistics.
        index = self.group.index
        error = self._error
        np.subtract(self.reference, self.state.position[index], out=error)
        self._samples += 1
        np.add(self._sum_sq, error * error, out=self._sum_sq)
        np.maximum(self._max_abs, np.abs(error), out=self._max_abs)
        self._stats = TrackingStats(
            names=self.group.names, samples=self._samples,
            rms=tuple(math.sqrt(x / self._samples) for x in self._sum_sq),
            max_abs=tuple(float(x) for x in self._max_abs),
            last=tuple(float(x) for x in error), time=event.time)
        return True
