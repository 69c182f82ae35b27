"""The simulated drive's NMT slave: its NMT state, heartbeat producer and heartbeat consumer.

The consumer watches the heartbeats of the nodes listed in 0x1016 (the manager's, on a
rocoma-can bus). Monitoring of a node starts with its first heartbeat. A deadline is judged
only once every frame that arrived before it has been handled (``Segment.judge_at``): on a
loaded machine the receive thread may run late, and a heartbeat that came in time must not
be reported lost because it was still queued. What a loss does (EMCY, 0x1029, 0x6007) is
the drive's reaction, given as ``on_lost``.
"""
from __future__ import annotations

from collections.abc import Callable
from typing import Any

from .. import cia301 as c301
from ..cia301 import NmtState
from .objects import Key
from .port import Segment


class NmtSlave:
    def __init__(self, node_id: int, segment: Segment, values: dict[Key, Any],
                 send: Callable[[int, bytes], None], on_lost: Callable[[], None],
                 on_regained: Callable[[], None]) -> None:
        self._hb_cob_id = c301.HEARTBEAT + node_id
        self._seg = segment
        self._values = values
        self._send = send
        self._on_lost = on_lost
        self._on_regained = on_regained
        self.state = NmtState.BOOT_UP
        self._producer_generation = 0
        self._consumer_generation = 0
        self._consumers: dict[int, float] = {}  # node -> consumer time (s)
        self._deadline: dict[int, float] = {}
        self._armed: set[int] = set()
        self.lost: set[int] = set()              # nodes whose heartbeat is lost now

    def boot_up(self) -> None:
        """The boot-up message, then PRE-OPERATIONAL."""
        self.state = NmtState.BOOT_UP
        self._send(self._hb_cob_id, b"\x00")
        self.state = NmtState.PRE_OPERATIONAL

    def apply_error_behaviour(self) -> None:
        """0x1029:1 on a communication error: 0 = to PRE-OPERATIONAL (if OPERATIONAL),
        1 = no change, 2 = to STOPPED."""
        behaviour = self._values.get((c301.ERROR_BEHAVIOR, 1), 1)
        if behaviour == 0 and self.state == NmtState.OPERATIONAL:
            self.state = NmtState.PRE_OPERATIONAL
        elif behaviour == 2:
            self.state = NmtState.STOPPED

    # ------------------------------------------------------------------ producer
    def start_heartbeat(self) -> None:
        """(Re)start the producer on 0x1017; period 0 = no heartbeat."""
        self._producer_generation += 1
        period_ms = self._values[(c301.PRODUCER_HEARTBEAT_TIME, 0)]
        if period_ms:
            due = self._seg.clock() + period_ms / 1000.0
            self._seg.schedule(due, self._tick, self._producer_generation, due)

    def _tick(self, generation: int, due: float) -> None:
        if generation != self._producer_generation:
            return
        self._send(self._hb_cob_id, bytes((self.state,)))
        period = self._values[(c301.PRODUCER_HEARTBEAT_TIME, 0)] / 1000.0
        nxt = due + period
        now = self._seg.clock()
        if nxt <= now:  # fell behind (loaded machine): no burst of catch-up heartbeats
            nxt = now + period
        self._seg.schedule(nxt, self._tick, generation, nxt)

    # ------------------------------------------------------------------ consumer
    def load_consumers(self) -> None:
        """(Re)read 0x1016; monitoring restarts from the next heartbeat of each node."""
        self._consumer_generation += 1
        self._consumers.clear()
        self._armed.clear()
        self.lost.clear()
        count = self._values.get((c301.CONSUMER_HEARTBEAT_TIME, 0), 0)
        for sub in range(1, count + 1):
            entry = self._values[(c301.CONSUMER_HEARTBEAT_TIME, sub)]
            node, ms = (entry >> 16) & 0xFF, entry & 0xFFFF
            if node and ms:
                self._consumers[node] = ms / 1000.0

    def on_heartbeat(self, node: int, arrived: float) -> None:
        period = self._consumers.get(node)
        if period is None:
            return
        self._deadline[node] = arrived + period
        if node in self.lost:
            self.lost.discard(node)
            self._on_regained()
        if node not in self._armed:  # monitoring starts with the first heartbeat
            self._armed.add(node)
            self._seg.schedule(arrived + period, self._check, node, self._consumer_generation)

    def _check(self, node: int, generation: int) -> None:
        if generation != self._consumer_generation or node not in self._armed:
            return
        later = self._seg.judge_at(self._deadline[node])
        if later is not None:  # a heartbeat that came in time may still be queued
            self._seg.schedule(later, self._check, node, generation)
            return
        self._armed.discard(node)
        self.lost.add(node)
        self._on_lost()
