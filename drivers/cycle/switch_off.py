"""Controlword 0x0000 by SDO to a latched drive, from a thread of its own.

Why: a latched drive is sent torque-off RPDOs every cycle, but a drive that no longer
applies RPDOs (put into pre-operational by another node's NMT command, or ignoring SYNC)
keeps its last enabled set-point while it still answers SDO and still sees the manager's
heartbeat. An SDO write of the controlword reaches it.

Why a thread of its own, fed by a queue the cycle only appends to: the cycle never waits
for it, never starts a thread for it, never takes a lock a slow thread holds; and a drive's
configuration that takes seconds on the configuration workers cannot delay another drive's
switch-off. A job re-checks that it is still wanted (the same fault still latched) just
before it writes, so a switch-off queued before a recovery cannot disable the recovered drive.
"""
from __future__ import annotations

import logging
import queue
import threading
from collections.abc import Callable
from typing import Protocol

log = logging.getLogger(__name__)


class SdoControlword(Protocol):
    """The drive side (drive_bringup.DriveBringup): writes the controlword by SDO, or returns
    False without writing when the drive's SDO client is busy (its configuration runs)."""
    @property
    def name(self) -> str: ...

    def write_controlword_by_sdo(self, value: int) -> bool: ...


class SdoSwitchOff:
    def __init__(self, name: str = "canopen-switch-off") -> None:
        self._jobs: queue.SimpleQueue[tuple[SdoControlword, Callable[[], bool]] | None] = \
            queue.SimpleQueue()
        self._thread = threading.Thread(target=self._run, name=name, daemon=True)
        self.sent = 0     # controlwords written
        self.skipped = 0  # no longer wanted, or the drive was being configured (torque off)
        self.failed = 0   # the drive did not answer or refused

    def start(self) -> None:
        self._thread.start()

    def request(self, drive: SdoControlword, still_wanted: Callable[[], bool]) -> None:
        """From the cycle: a queue append, never blocking."""
        self._jobs.put_nowait((drive, still_wanted))

    def close(self, timeout: float = 5.0) -> None:
        self._jobs.put_nowait(None)
        if self._thread.is_alive():
            self._thread.join(timeout)
            if self._thread.is_alive():
                log.error("SDO switch-off thread did not stop within %.1f s", timeout)

    def _run(self) -> None:
        while (job := self._jobs.get()) is not None:
            drive, still_wanted = job
            try:
                if still_wanted() and drive.write_controlword_by_sdo(0x0000):
                    self.sent += 1
                else:
                    self.skipped += 1
            except Exception as exc:  # noqa: BLE001 - beside the RPDOs and the consumer
                self.failed += 1
                log.warning("drive %r: switching off by SDO failed: %s", drive.name, exc)
