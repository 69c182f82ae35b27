"""Node guarding from the manager's side: remote requests from the cycle, answers judged.

A drive with no heartbeat producer (or none watching the manager) is guarded (drive_plan.py):
every ``heartbeat_ms`` the cycle sends a remote frame to 0x700 + node id and the drive
answers with its NMT state and a toggle bit that changes with every answer. Like the
manager's heartbeat, the requests come from the cycle only: a loop that stops or hangs
stops guarding, and each drive's life guarding (0x100C x 0x100D) switches it off (0x6007).
The answers arrive as heartbeats do (receive.py) and are supervised the same way.
"""
from __future__ import annotations

import math
from collections.abc import Sequence

import can

from . import cia301
from .bus_port import BusPort


class NodeGuarding:
    """The guard requests and answers of the guarded drives (one per node: its lead axis)."""

    def __init__(self, guarded: Sequence[bool], node_ids: Sequence[int],
                 periods: Sequence[float], port_of: Sequence[BusPort]) -> None:
        n = len(guarded)
        self.guarded = list(guarded)
        self._drives = [i for i in range(n) if guarded[i]]
        self._frames = {i: can.Message(arbitration_id=cia301.HEARTBEAT + node_ids[i],
                                       is_remote_frame=True, dlc=1, is_extended_id=False)
                        for i in self._drives}
        self._send = [port.send for port in port_of]
        self._period = list(periods)
        self._due = [math.inf] * n   # inf: not guarded (yet)
        self.next_due = math.inf     # the earliest of them
        self._toggle = [-1] * n      # the last answer's toggle bit; -1: none yet
        self._asked = [0] * n        # requests sent since the last answer taken
        self.repeats = 0             # answers whose toggle bit did not change

    def start(self, i: int) -> None:
        """Guard drive i from this cycle on: life guarding starts with the first request,
        so it is sent in the cycle the drive's configuration completes."""
        if self.guarded[i]:
            self._due[i] = self.next_due = -math.inf

    def send_due(self, now: float) -> None:
        """The requests that are due, on a grid like the heartbeat's."""
        due, period, asked = self._due, self._period, self._asked
        nearest = math.inf
        for i in self._drives:
            if due[i] <= now:
                self._send[i](self._frames[i])
                asked[i] += 1
                nxt = due[i] + period[i]
                due[i] = nxt if nxt > now else now + period[i]
            if due[i] < nearest:
                nearest = due[i]
        self.next_due = nearest

    def answer(self, i: int, byte: int) -> int | None:
        """The NMT state a guard answer of drive i reports, or None when it does not count:
        the answer taken last again (a stale or doubled frame; answers that never toggle
        run into the deadline, a guarding loss). After two requests or more the same bit is
        a new answer: the one between was lost, and one lost frame is not a lost drive."""
        toggle = byte & cia301.GUARD_TOGGLE
        state = byte & ~cia301.GUARD_TOGGLE
        if state == cia301.NmtState.BOOT_UP:  # a boot-up restarts the toggling
            self._toggle[i] = -1
        elif toggle == self._toggle[i] and self._asked[i] < 2:
            self.repeats += 1
            return None
        else:
            self._toggle[i] = toggle
            self._asked[i] = 0
        return state
