"""Drive supervision: every way a drive can go wrong becomes one FaultEvent.

Causes: heartbeat deadline missed (monotonic clock, not canopen's wall-clock timestamps),
heartbeat reporting a state other than operational (the drive rebooted or was stopped), the
same for a node-guarded drive's answers (hardware.py sends the requests; answers whose
toggle bit did not change are no sign of life, node_guarding.py), an
EMCY with a non-zero code, the statusword fault bit or a statusword that is no CiA 402 state,
TPDOs missing for k cycles, a TPDO
whose length is not its mapping's, a drive
that does not reach operation enabled when commanded, or the bus going bus-off (an error
frame: python-can's ``bus.state`` does not say so on SocketCAN). ros2_canopen logs these and carries
on; here each one is an e-stop.

The first cause per drive latches the drive's fault and yields an event; later causes for
the same drive are kept for the status report but raise no new event, so one broken drive
is one e-stop (OK -> EMERGENCY), and a second drive failing is the second one (-> FAILPROOF).
The latch is cleared by recovery only.
"""
from __future__ import annotations

import collections
import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass

import numpy as np

from ..plan.config import DriveConfig
from ..plan.modes import DriveMode
from ..protocol import cia301, cia402

EMCY_NAMES = {
    cia301.EMCY_GENERIC: "generic error",
    cia301.EMCY_OVERCURRENT: "overcurrent",
    cia301.EMCY_OVERVOLTAGE: "overvoltage",
    cia301.EMCY_OVERTEMPERATURE: "overtemperature",
    cia301.EMCY_HEARTBEAT: "heartbeat error",
    cia301.EMCY_POSITION_SENSOR: "position sensor",
    cia301.EMCY_FOLLOWING_ERROR: "following error",
    cia301.EMCY_STO: "STO input active",
}

#: the lower of the two faulted CiA 402 states, as a plain int (numpy compares it cheaper)
_FAULTED = int(cia402.State402.FAULT_REACTION_ACTIVE)


def emcy_text(code: int) -> str:
    return f"EMCY 0x{code:04X} ({EMCY_NAMES.get(code, 'error')})"


@dataclass(frozen=True)
class FaultEvent:
    """One supervision finding, with enough to act on it and to tell a human."""
    node_id: int
    drive: str
    cause: str
    code: int = 0      # EMCY / 0x603F error code when known
    time: float = 0.0  # time.monotonic()
    index: int = -1    # the drive's index in the hardware (-1: a bus, not one drive)

    def __str__(self) -> str:
        if self.index < 0:  # a bus event: the cause names the bus
            return self.cause
        return f"drive {self.drive!r} (node {self.node_id}): {self.cause}"


class Supervisor:
    """Deadlines and fault latches for N drives; all methods run on the cycle thread."""

    def __init__(self, drives: Sequence[DriveConfig], tpdo_timeout_cycles: int,
                 heartbeat_timeout_factor: float, history: int = 64,
                 guarded: Sequence[bool] = (),
                 why_lost: Callable[[int], str] = lambda i: "") -> None:
        """``why_lost``: what a life signal's loss adds to its cause, per drive (the
        hardware's: the guard answers that came and did not count); called only when one
        is lost."""
        if tpdo_timeout_cycles < 1:
            raise ValueError(f"tpdo_timeout_cycles must be >= 1, got {tpdo_timeout_cycles}")
        if heartbeat_timeout_factor <= 1.0:
            raise ValueError("heartbeat_timeout_factor must be > 1 (a deadline shorter than "
                             f"the heartbeat period always trips), got {heartbeat_timeout_factor}")
        n = len(drives)
        self.drives = list(drives)
        self.tpdo_timeout_cycles = tpdo_timeout_cycles
        self.heartbeat_timeout = np.array([d.heartbeat_ms * heartbeat_timeout_factor / 1000.0
                                           for d in drives])
        self.heartbeat_deadline = np.full(n, math.inf)
        self.active = np.zeros(n, dtype=bool)      # supervised: brought up and not failed
        self.watch = np.zeros(n, dtype=bool)       # active and not latched: what tick checks
        self.missing = np.zeros(n, dtype=np.int64)  # consecutive cycles without all TPDOs
        self.latched: list[FaultEvent | None] = [None] * n
        self.bus_latched: FaultEvent | None = None  # bus-off: not one drive's fault
        self.history: collections.deque[FaultEvent] = collections.deque(maxlen=history)
        self.pending: list[FaultEvent] = []
        # what a drive's life signal is (a node-guarded drive answers requests instead)
        self._signal = ["node guarding answer" if i < len(guarded) and guarded[i]
                        else "heartbeat" for i in range(n)]
        self._why_lost = why_lost

    def arm(self, i: int, now: float) -> None:
        """Start supervising drive i (brought up); heartbeat deadline from now."""
        self.active[i] = True
        self.watch[i] = self.latched[i] is None
        self.missing[i] = 0
        self.heartbeat_deadline[i] = now + self.heartbeat_timeout[i]

    def disarm(self, i: int) -> None:
        self.active[i] = False
        self.watch[i] = False
        self.heartbeat_deadline[i] = math.inf

    def clear(self, i: int) -> None:
        self.latched[i] = None
        self.watch[i] = self.active[i]

    def fault(self, i: int, cause: str, now: float, code: int = 0) -> None:
        event = FaultEvent(self.drives[i].node_id, self.drives[i].name, cause, code, now, i)
        self.history.append(event)
        if self.latched[i] is None:
            self.latched[i] = event
            self.watch[i] = False
            self.pending.append(event)

    def bus_fault(self, cause: str, now: float, drives: Sequence[int] = (),
                  bus: str = "bus") -> FaultEvent:
        """A bus itself failed (bus-off, frames refused): one event, node id 0, latched on
        ``drives`` (those on that bus: nothing reaches them, they must be brought back) and
        as the bus latch until recovery. One event, not one per drive: the hardware makes
        it one failproof stop (a smart stop needs every joint), and a later fault of another
        bus is an event of its own."""
        event = FaultEvent(0, bus, cause, 0, now)
        self.history.append(event)
        fresh = False
        for i in drives:
            if self.latched[i] is None:
                self.latched[i] = event
                self.watch[i] = False
                fresh = True
        if self.bus_latched is None:
            self.bus_latched = event
            fresh = True
        if fresh:
            self.pending.append(event)
        return event

    def on_heartbeat(self, i: int, state: int, now: float) -> None:
        if not self.active[i]:
            return
        self.heartbeat_deadline[i] = now + self.heartbeat_timeout[i]
        if state != cia301.NmtState.OPERATIONAL:
            self.fault(i, f"NMT state {cia301.nmt_name(state)} reported in {self._signal[i]}",
                       now)

    def on_bad_tpdo(self, i: int, cob_id: int, dlc: int, size: int, now: float) -> None:
        """A TPDO whose length is not its mapping's: garbled or remapped, never feedback."""
        if self.active[i]:
            self.fault(i, f"TPDO 0x{cob_id:03X} with {dlc} bytes, its mapping has {size}", now)

    def on_emcy(self, i: int, code: int, now: float) -> None:
        if code != cia301.EMCY_NO_ERROR and self.active[i]:
            self.fault(i, emcy_text(code), now, code)

    def tick(self, now: float, tpdos_complete: np.ndarray, states: np.ndarray,
             error_codes: np.ndarray, heard_until: np.ndarray | None = None) -> None:
        """Once per cycle after draining: deadlines, missing TPDOs, statusword fault bit.

        ``heard_until`` (per drive, default ``now``): every frame of the drive's bus that
        arrived before it has been drained. A heartbeat deadline counts as passed only
        before that: a reader thread the scheduler starved has heartbeats that came in
        time still unread, and calling them lost would stop the robot for nothing (the
        simulated drives' consumers keep the same rule).

        Drives already latched are not checked again (one event per drive). The common case,
        nothing wrong, costs a few reductions (Python's on ``tolist()``: for a dozen drives
        cheaper than numpy's, whose scalar compared with an IntEnum alone costs more);
        the per-drive loops run only when one of them says something is."""
        watch = self.watch
        if True not in watch.tolist():
            return
        missing = self.missing
        np.add(missing, 1, out=missing)
        np.copyto(missing, 0, where=tpdos_complete)
        if min(self.heartbeat_deadline.tolist()) < now:
            heard = now if heard_until is None else heard_until
            for i in np.flatnonzero(watch & (self.heartbeat_deadline < heard)):
                self.fault(int(i), f"{self._signal[i]} lost (none for "
                                   f"{self.heartbeat_timeout[i]:.3f} s)"
                                   + self._why_lost(int(i)), now)
                self.heartbeat_deadline[i] = math.inf  # one event per loss
        if max(missing.tolist()) >= self.tpdo_timeout_cycles:
            for i in np.flatnonzero(watch & (missing >= self.tpdo_timeout_cycles)):
                self.fault(int(i), f"TPDOs missing for {self.tpdo_timeout_cycles} cycles", now)
        seen = states.tolist()
        # FAULT_REACTION_ACTIVE (6) and FAULT (7) are the two highest State402 values
        if max(seen) >= _FAULTED:
            for i in np.flatnonzero(watch & (states >= _FAULTED)):
                code = int(error_codes[i])
                self.fault(int(i), "statusword fault bit"
                           + (f", {emcy_text(code)}" if code else ""), now, code)
        # UNKNOWN (-1): a statusword that is no CiA 402 state is garbled or broken firmware;
        # taken as an enable step it would only be reported when the enable timed out
        if min(seen) < 0:
            for i in np.flatnonzero(watch & (states < 0)):
                self.fault(int(i), "statusword matches no CiA 402 state (garbled?)", now)

    def take_pending(self) -> list[FaultEvent]:
        events, self.pending = self.pending, []
        return events


class FollowingErrorWatch:
    """The manager's following error check of the drives it runs in CSP with a
    ``limits.following_error`` window: the position target sent last cycle against the
    actual position read this cycle, beyond the window for ``following_error_cycles``
    consecutive cycles -> the drive's fault (an e-stop), EMCY code 0x8611 as a drive's own.

    The drive itself (0x6065/0x6066, written at bring-up) faults after twice as long: the
    manager, which knows the target it meant, reports first, the drive backs it up. The
    window must hold the drive's lag at full speed (its position loop's, plus a cycle or two
    of the bus). On the cycle, numpy on preallocated arrays only.
    """

    def __init__(self, drives: Sequence[DriveConfig], position_fed: np.ndarray) -> None:
        n = len(drives)
        self.window = np.array([d.limits.following_error if d.limits.following_error
                                is not None and DriveMode.CSP in d.modes and position_fed[i]
                                else math.inf for i, d in enumerate(drives)])
        self.active = bool(np.isfinite(self.window).any())
        self.cycles = np.array([d.limits.following_error_cycles for d in drives], dtype=np.int64)
        self.target = np.zeros(n)                 # rad, the CSP targets sent last cycle
        self.tracking = np.zeros(n, dtype=bool)   # a CSP target went out last cycle
        self.over = np.zeros(n, dtype=np.int64)   # consecutive cycles beyond the window
        self._error = np.zeros(n)
        self._beyond = np.zeros(n, dtype=bool)

    def check(self, actual: np.ndarray, sup: Supervisor, now: float) -> None:
        """This cycle's actual positions against last cycle's targets; then forget which
        drives were tracking (``sent`` marks this cycle's)."""
        if not self.active:
            return
        error, beyond, over = self._error, self._beyond, self.over
        np.subtract(self.target, actual, out=error)
        np.abs(error, out=error)
        np.greater(error, self.window, out=beyond)
        np.logical_and(beyond, self.tracking, out=beyond)
        np.multiply(over, beyond, out=over)  # back to 0 within the window
        np.add(over, beyond, out=over)
        np.greater_equal(over, self.cycles, out=beyond)
        if beyond.any():  # rare: a fault, allocation is fine here
            for i in np.flatnonzero(beyond).tolist():
                over[i] = 0
                if sup.latched[i] is None:
                    sup.fault(i, f"following error {error[i]:.4g} rad beyond the window "
                                 f"{self.window[i]:g} rad for {self.cycles[i]} cycles (CSP "
                                 f"target {self.target[i]:.4g} rad, actual {actual[i]:.4g} "
                                 "rad)", now, cia301.EMCY_FOLLOWING_ERROR)
        self.tracking.fill(False)

    def sent(self, targets: np.ndarray) -> None:
        """This cycle's targets (rad; those of the drives marked in ``tracking``)."""
        if self.active:
            np.copyto(self.target, targets)
