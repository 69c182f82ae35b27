"""Recovery: fault reset or restart of every latched or failed drive, over the cycles.

``request`` comes from any thread and returns a future; ``step`` runs in the cycle's read.
A fault of the very cycle a recovery would start in is delivered first, never erased. Then
the bus latches are cleared, and per drive: a READY drive whose heartbeat says operational
gets the fault-reset edge, any other drive a restart of its bring-up (a node configured again
is NMT-reset, so its other axes restart too; one under command is faulted first, so the
manager hears it drop out). The recovery succeeds when every drive is READY without a latch
and every bus has sent as many cycles in a row without a refused frame as TPDOs may be
missing; ``step`` then returns the future, for the loop to clear the manager's e-stop latch
before it says True (RecoveryDone); a hardware cycled without a manager
resolves it True in the next cycle. It fails at its timeout, or when every
drive has settled and some did not come back.
"""
from __future__ import annotations

import math
import threading
from collections.abc import Sequence
from concurrent.futures import Future, InvalidStateError
from dataclasses import dataclass
from typing import Protocol

import numpy as np

from ..bringup.drive_bringup import BringupPhase, DriveBringup
from ..link.bus_port import BusPort
from ..protocol import cia301
from .drive_table import DriveTable
from .supervision import Supervisor


class LatchClearer(Protocol):
    """The manager as a finished recovery sees it (rocoma_can's ControllerManager)."""
    def clear_emergency_stop(self) -> bool: ...


@dataclass(frozen=True, slots=True)
class RecoveryDone:
    """Every drive came back (``Recovery.step``): the e-stop latch is cleared, then the recovery's
    future says True, so its caller may switch at once. A clear that raises leaves the latch
    and ends the recovery as failed."""
    future: Future[bool]

    def apply(self, manager: LatchClearer) -> None:
        if self.future.done():  # the hardware closed meanwhile: it said False
            return
        try:
            manager.clear_emergency_stop()
            ok = True
        except Exception:
            ok = False
        try:
            self.future.set_result(ok)
        except InvalidStateError:  # closed in between, from another thread
            pass


class Recovery:
    """At most one recovery at a time; the bring-ups are attached when the hardware starts."""

    def __init__(self, table: DriveTable, *, ports: Sequence[BusPort],
                 supervisor: Supervisor, hb_state: list[int], hb_time: np.ndarray,
                 error_code: np.ndarray) -> None:
        """``hb_state``/``hb_time``: each drive's last heartbeat (receive.py), which says
        whether a fault reset can do; ``error_code``: JointState's, cleared on a restart."""
        self._table, self._ports, self._sup = table, ports, supervisor
        self._hb_state, self._hb_time, self._error_code = hb_state, hb_time, error_code
        self._bringups: Sequence[DriveBringup] = ()
        self.future: Future[bool] | None = None
        self._request_lock = threading.Lock()
        self._started = False
        self._reported = False  # step returned the future for the loop to resolve
        self._timeout = 5.0
        self._deadline = math.inf

    def attach_bringups(self, bringups: Sequence[DriveBringup]) -> None:
        """The drives' bring-ups, once the hardware has started them."""
        self._bringups = bringups

    @property
    def running(self) -> bool:
        return self.future is not None and not self.future.done()

    def request(self, timeout: float) -> Future[bool]:
        """A new recovery, or the one already running. From any thread: the lock orders
        callers among themselves (two at once must get the same future, never one the cycle
        does not step); the cycle never takes it."""
        with self._request_lock:
            if self.future is not None and not self.future.done():
                return self.future
            future: Future[bool] = Future()
            future.set_running_or_notify_cancel()  # a caller's cancel() cannot end it early
            self._timeout = timeout
            self._started = self._reported = False
            self.future = future
            return future

    def step(self, now: float) -> Future[bool] | None:
        """One cycle of the running recovery: its future once the drives are back (the
        caller clears the e-stop latch, then resolves it), else None."""
        future = self.future
        if future is None or future.done():
            return None
        if self._reported:  # handed over last cycle and nobody applied it: no manager
            self._finish(future, True)
            return None
        sup = self._sup
        if not self._started:
            if not sup.pending:
                self._begin(now)
            return None
        drives_ready = (all(b.phase == BringupPhase.READY for b in self._bringups)
                        and not any(sup.latched) and sup.bus_latched is None)
        if drives_ready and min(p.clean_cycles for p in self._ports) >= sup.tpdo_timeout_cycles:
            self._reported = True
            return future
        if now > self._deadline or (not drives_ready and all(
                b.phase in (BringupPhase.READY, BringupPhase.FAILED) for b in self._bringups)):
            self._finish(future, False)
        return None

    def close(self) -> None:
        """The hardware closes: a recovery still running did not bring the drives back."""
        future = self.future
        if future is not None and not future.done():
            future.set_result(False)

    @staticmethod
    def _finish(future: Future[bool], result: bool) -> None:
        """Resolve ``future`` unless another thread has (the hardware's close)."""
        try:
            future.set_result(result)
        except InvalidStateError:
            pass

    def _begin(self, now: float) -> None:
        sup, bringup = self._sup, self._bringups
        self._started = True
        self._deadline = now + self._timeout
        sup.bus_latched = None
        for port in self._ports:
            port.latched = None
        restarted: set[int] = set()
        for i, b in enumerate(bringup):
            if b.phase == BringupPhase.READY and sup.latched[i] is None:
                continue
            sup.disarm(i)
            sup.clear(i)
            self._error_code[i] = 0
            hb_ok = (self._hb_state[i] == cia301.NmtState.OPERATIONAL
                     and now - self._hb_time[i] < sup.heartbeat_timeout[i])
            if b.phase == BringupPhase.READY and hb_ok:
                b.reset_fault(now)
            elif b.phase != BringupPhase.CONFIGURING:
                b.restart(now, probe_at_once=True)
                restarted.add(i)
        for i in restarted:  # a node configured again is NMT-reset: all its axes restart
            if not self._table[i].leads_node:
                continue
            for k in self._table[i].node[1:]:
                if k in restarted or bringup[k].phase == BringupPhase.CONFIGURING:
                    continue
                if bringup[k].phase == BringupPhase.READY and sup.latched[k] is None:
                    # it may be under command: the manager hears it drop out (an e-stop,
                    # delivered this cycle); its configuration switched it off by SDO
                    # before the node's NMT pre-operational
                    sup.fault(k, "its node is configured again (recovery of drive "
                                 f"{self._table[i].config.name!r})", now)
                sup.disarm(k)
                sup.clear(k)
                bringup[k].restart(now, probe_at_once=True)
