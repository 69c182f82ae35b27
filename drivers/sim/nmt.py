"""The simulated drive's NMT slave: its NMT state, heartbeat producer, heartbeat consumer
and node guarding.

The consumer watches the heartbeats of the nodes listed in 0x1016 (the manager's, on a
rocoma-can bus). Monitoring of a node starts with its first heartbeat. A deadline is judged
only once every frame that arrived before it has been handled (``Segment.judge_at``): on a
loaded machine the receive thread may run late, and a heartbeat that came in time must not
be reported lost because it was still queued. What a loss does (EMCY, 0x1029, 0x6007) is
the drive's reaction, given as ``on_lost``.

Node guarding (CiA 301), for a drive whose file has 0x100C/0x100D: a remote request on
0x700 + node id is answered with the NMT state and a toggle bit that changes with every
answer (reset to 0 by a reset of communication), while the drive produces no heartbeat.
Life guarding starts with the first request when guard time and life time factor are both
set: no request for guard time x factor is the same loss as a lost heartbeat.
"""
from __future__ import annotations

from collections.abc import Callable
from typing import Any

from ..protocol import cia301 as c301
from ..protocol.cia301 import NmtState, ObjectKey
from .port import Segment


class NmtSlave:
    def __init__(self, node_id: int, segment: Segment, values: dict[ObjectKey, Any],
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
        self.guardable = (c301.GUARD_TIME, 0) in values
        self._toggle = 0
        self._guard_generation = 0
        self._guard_deadline: float | None = None  # None: life guarding not running
        self.guarding_lost = False
        self.guard_requests = 0

    def boot_up(self) -> None:
        """The boot-up message, then PRE-OPERATIONAL; node guarding starts over."""
        self.state = NmtState.BOOT_UP
        self._toggle = 0
        self._guard_generation += 1
        self._guard_deadline = None
        self.guarding_lost = False
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

    # ------------------------------------------------------------------ node guarding
    def on_guard_request(self, arrived: float) -> None:
        """A remote request for this node's 0x700 frame: answer, and (re)arm life guarding."""
        if not self.guardable or self._values.get((c301.PRODUCER_HEARTBEAT_TIME, 0)):
            return  # no node guarding, or a heartbeat producer running (CiA 301)
        self.guard_requests += 1
        self._send(self._hb_cob_id, bytes((self._toggle | self.state,)))
        self._toggle ^= c301.GUARD_TOGGLE
        life = (self._values.get((c301.GUARD_TIME, 0), 0)
                * self._values.get((c301.LIFE_TIME_FACTOR, 0), 0)) / 1000.0
        if not life:
            return
        if self.guarding_lost:
            self.guarding_lost = False
            self._on_regained()
        running = self._guard_deadline is not None
        self._guard_deadline = arrived + life
        if not running:
            self._seg.schedule(self._guard_deadline, self._check_guarding,
                               self._guard_generation)

    def _check_guarding(self, generation: int) -> None:
        deadline = self._guard_deadline
        if generation != self._guard_generation or deadline is None:
            return
        later = self._seg.judge_at(deadline)
        if later is not None:  # a request that came in time may still be queued
            self._seg.schedule(later, self._check_guarding, generation)
            return
        self._guard_deadline = None  # re-armed by the next request
        self.guarding_lost = True
        self._on_lost()
