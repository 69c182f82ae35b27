"""What a simulated drive sees of the bus segment it sits on.

A drive owns no thread and no socket: the segment (segment.SimulatedSegment) feeds it frames
and timer events with the segment lock held, and sends what it transmits. This Protocol is
the drive's whole view of the world, so no module of the drive imports the segment.
"""
from __future__ import annotations

import threading
from collections.abc import Callable
from typing import Protocol

import can
import numpy as np

from .dynamics import JointDynamics

Route = Callable[[bytes], None]


class Segment(Protocol):
    lock: threading.RLock
    rng: np.random.Generator
    dynamics: JointDynamics

    def clock(self) -> float:
        """Monotonic time of the segment (seconds)."""
        ...

    def schedule(self, when: float, fn: Callable[..., object], *args: object) -> None:
        """Call ``fn(*args)`` at ``when`` on the segment's timer thread, lock held."""
        ...

    @property
    def fd(self) -> bool:
        """An FD bus: the drives' pre-encoded frames are FD frames."""
        ...

    def send(self, cob_id: int, data: bytes) -> None: ...

    def send_frame(self, msg: can.Message) -> None:
        """A frame the caller keeps and re-fills (sent as it is now)."""
        ...

    def judge_at(self, deadline: float) -> float | None:
        """None once every frame that arrived before ``deadline`` has been handled;
        otherwise when to look again (a timeout must not fire on a queued frame)."""
        ...

    def finish_pending_step(self) -> None:
        """Take a SYNC's deferred dynamics step now, if one waits (lock held)."""
        ...

    def set_rpdo_routes(self, node_id: int, routes: dict[int, Route]) -> None:
        """Replace the RPDO COB-IDs this node receives, each with its handler."""
        ...
