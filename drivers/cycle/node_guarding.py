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

from ..link.bus_port import BusPort
from ..protocol import cia301


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
        self._asked = [0] * n        # requests sent since the last answer heard (any)
        self._excused = [False] * n  # the last answer taken was a lost one's excused repeat
        self.stale = [0] * n         # answers not taken since the last one taken
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
        its toggle bit is the last taken answer's (a stale or doubled frame, or a hung
        node's CAN controller answering each request by itself with the frame last loaded
        into its mailbox). Such answers are no sign of life, however many come: the
        deadline runs out as for a silent drive (``why_lost`` says why).

        One excuse: the drive toggles with every answer it sends, so after one answer was
        lost on the bus the next carries the bit of the one taken before it. A repeat is
        taken when a request went unanswered right before it (two requests since the last
        answer heard, of any kind), once: the answer after it must toggle. A mailbox
        answers every request, so it never earns the excuse; one lost frame is not a lost
        drive."""
        toggle = byte & cia301.GUARD_TOGGLE
        state = byte & ~cia301.GUARD_TOGGLE
        asked, self._asked[i] = self._asked[i], 0
        if state == cia301.NmtState.BOOT_UP:  # a boot-up restarts the toggling
            self._toggle[i] = -1
            self._excused[i] = False
        elif toggle != self._toggle[i]:
            self._toggle[i] = toggle
            self._excused[i] = False
        elif asked >= 2 and not self._excused[i]:
            self._excused[i] = True
        else:
            self.repeats += 1
            self.stale[i] += 1
            return None
        self.stale[i] = 0
        return state

    def why_lost(self, i: int) -> str:
        """What to add to drive i's guarding loss: the answers that came and were not taken
        since the last one that was (empty when none came)."""
        stale = self.stale[i]
        if not stale:
            return ""
        return (f"; {stale} answer{'s' if stale > 1 else ''} came whose toggle bit did not "
                "change: no sign of life (a hung node's CAN controller answering by itself?)")
