"""The CiA 402 enable sequence, stepped from the cyclic controlword, and the two faults only
it can see: a drive that does not reach operation enabled in time (STO input low?), and one
that drops out of operation enabled while commanded.

"In time" is per step: each of shutdown, switch on and enable operation gets the whole
``timeout`` from the moment the drive was seen reaching the state before it. A drive that
never leaves a state is found after ``timeout``, as before; a drive that answers every step,
each a round trip of the bus, is not declared stuck because the round trips added up (a
host or guest that delays every frame by a second made a 6 s deadline for the whole
sequence fail with the drive still stepping). Going back a step does not restart the clock.
The time that counts is time the drive was being asked: each cycle adds its period, but
at most ``timeout / min_cycles`` (the hardware passes its TPDO timeout as ``min_cycles``,
the cycles the drive's feedback may take). A process frozen for seconds sent the drive
nothing meanwhile; on wall time alone, the first cycle after it would find the step's time
up although the drive was never asked. While the loop runs, nothing changes.

Why from the cyclic RPDO and not by SDO or canopen's BaseNode402: one step per cycle
(shutdown, switch on, enable operation) never blocks the cycle, and while enabling the
targets hold the actual position, so enabling cannot make a joint jump. Called only for a
drive that is READY, not latched, and commanded a cyclic mode; every other drive is
``reset`` (the hardware layer sends it torque-off frames).
"""
from __future__ import annotations

import math
from collections.abc import Callable

from ..protocol import cia402
from ..protocol.cia402 import State402

CW_ENABLE = int(cia402.Controlword.ENABLE_OPERATION)
OP_ENABLED = int(State402.OPERATION_ENABLED)
#: cycles a drive must have been in operation enabled before leaving it counts as a drop-out
#: (not a fault of an enable step that a drive answers a cycle late)
DROP_AFTER_CYCLES = 4
# Next enable step (shutdown, switch on, enable operation) by State402 value + 1; every state
# the enable sequence cannot leave by itself gets disable voltage.
_ENABLE_STEP = {
    State402.SWITCH_ON_DISABLED: int(cia402.Controlword.SHUTDOWN),
    State402.READY_TO_SWITCH_ON: int(cia402.Controlword.SWITCH_ON),
    State402.SWITCHED_ON: CW_ENABLE,
    State402.OPERATION_ENABLED: CW_ENABLE,
}
ENABLE_STEP = tuple(_ENABLE_STEP.get(State402(s), int(cia402.Controlword.DISABLE_VOLTAGE))
                    for s in range(-1, 8))
# How far along the sequence each state is, by State402 value + 1 (-1: not on the way).
_PROGRESS = {State402.SWITCH_ON_DISABLED: 0, State402.READY_TO_SWITCH_ON: 1,
             State402.SWITCHED_ON: 2}
PROGRESS = tuple(_PROGRESS.get(State402(s), -1) for s in range(-1, 8))
#: the steps from switch on disabled to operation enabled, each with the whole timeout
ENABLE_STEPS = len(_PROGRESS)

Fault = Callable[[int, str, float], None]  # (drive index, cause, now): Supervisor.fault


class EnableSequence:
    """Per drive: cycles in operation enabled, since when the drive has been waited for at
    its furthest step, and which step that is."""

    def __init__(self, drives: int, timeout: float, fault: Fault, min_cycles: int = 0) -> None:
        self.timeout = timeout
        # the most one cycle may add to a step's time (a freeze adds no more than this)
        self.cap = timeout / min_cycles if min_cycles > 0 else math.inf
        self._fault = fault
        self._enabled_cycles = [0] * drives
        self._asked = [0.0] * drives  # how long the furthest step has been asked, capped
        self._last = [math.nan] * drives  # when it was last asked (NaN: not waiting)
        self._furthest = [-1] * drives

    def controlword(self, i: int, state: int, now: float) -> int:
        """This cycle's controlword for drive i, commanded a cyclic mode and in ``state``:
        CW_ENABLE once it is enabled (the caller sends the targets then), else the next
        enable step, or 0 after a drop-out (reported through ``fault``)."""
        if state == OP_ENABLED:
            self._enabled_cycles[i] += 1
            self._last[i] = math.nan
            return CW_ENABLE
        if self._enabled_cycles[i] >= DROP_AFTER_CYCLES:
            self._enabled_cycles[i] = 0
            self._fault(i, f"dropped out of operation enabled (now {State402(state).name})", now)
            return 0
        self._enabled_cycles[i] = 0
        last = self._last[i]
        progress = PROGRESS[state + 1]
        if last != last or progress > self._furthest[i]:  # NaN: just started wanting
            self._asked[i] = 0.0
            self._last[i] = now
            self._furthest[i] = max(progress, self._furthest[i])
        elif self._ask(i, now) > self.timeout:
            self._fault(i, f"not enabled: no enable step within {self.timeout} s (stuck in "
                           f"{State402(state).name}; STO input low?)", now)
        return ENABLE_STEP[state + 1]

    def _ask(self, i: int, now: float) -> float:
        """Add this cycle (at most ``cap``) to drive i's step time; the total."""
        self._asked[i] += min(max(now - self._last[i], 0.0), self.cap)
        self._last[i] = now
        return self._asked[i]

    def reset(self, i: int) -> None:
        """Drive i is not being enabled this cycle (torque-off, quick stop, not ready)."""
        self._enabled_cycles[i] = 0
        self._last[i] = math.nan
        self._furthest[i] = -1
