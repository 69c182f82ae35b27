"""What bring-up tells a person, each thing once: a drive's failure as it happens, and the
end of the start-up on the audit trail (rocoma_can/audit.py).

A drive that never answered is the one failure told late: when no drive of a bus answers
(a bus unplugged, unpowered, at another bit rate) every drive fails alike, and a line per
drive followed by their summary said one thing many times. Its failure waits until every
drive of its bus has ended its start-up: if none of them answered, one line says so for the
bus, with what to check; otherwise each is told as the others are.

``ended`` is called on the cycle thread when a drive's bring-up ends (READY or FAILED): it
reads the phases and keeps indices; the lines are made and written by ``say`` (the
hardware's configuration workers), so the cycle does no I/O and formats nothing.
"""
from __future__ import annotations

import logging
from collections.abc import Callable, Sequence
from typing import Protocol

from ...audit import AUDIT
from .drive_bringup import BringupPhase

# The hardware's logger: start-up is the hardware's work, and its records are found there
# (a log filter on it, the demo's among them, keeps working).
log = logging.getLogger("rocoma_can.drivers.hardware")
audit = logging.getLogger(AUDIT)

#: what a bus where nothing answers asks a person to look at
SILENT_BUS_CHECKS = ("check that the drives have power, the bit rate (every node's and the "
                     "interface's must be the same), the cable and its termination (120 ohm "
                     "at both ends of the bus), and the node ids (rocoma-can scan lists what "
                     "answers)")


class Started(Protocol):
    """A drive's bring-up as the report reads it (drive_bringup.DriveBringup)."""
    @property
    def name(self) -> str: ...
    phase: BringupPhase
    failure: str | None
    unanswered: str


class BringupReport:
    """``names``/``node_ids``: the drives'; ``bus_of``: each drive's bus (an index of
    ``channel``'s, which names a bus's channel as a person reads it, asked only when a bus
    is told); ``say``: runs a call off the cycle (the hardware's executor's submit)."""

    def __init__(self, node_ids: Sequence[int], bus_of: Sequence[int],
                 channel: Callable[[int], str], say: Callable[..., object]) -> None:
        self._node_ids, self._bus_of, self._channel = list(node_ids), list(bus_of), channel
        self._say = say
        # silent drives not told yet, per bus
        self._held: list[list[int]] = [[] for _ in range(max(bus_of, default=-1) + 1)]
        #: the start-up has ended, every drive READY or FAILED (once: a recovery that
        #: restarts drives later is no start-up)
        self.finished = False
        self.started_at = 0.0

    def ended(self, i: int, drives: Sequence[Started], now: float) -> None:
        """Drive i's bring-up ended this cycle (READY or FAILED); ``drives``: every one's."""
        b = drives[i]
        bus = self._bus_of[i]
        if b.phase == BringupPhase.FAILED:
            if b.unanswered:
                self._held[bus].append(i)
            else:
                self._say(self._tell_failure, b.name, self._node_ids[i], b.failure)
        mine = [k for k, on in enumerate(self._bus_of) if on == bus]
        held = sorted(self._held[bus])  # (in the config's order, not the failures')
        if held and not any(_starting(drives[k]) for k in mine):
            self._held[bus] = []
            if len(held) == len(mine):
                self._say(self._tell_silent_bus, self._channel(bus),
                          [(drives[k].name, self._node_ids[k]) for k in held],
                          drives[held[0]].unanswered)
            else:
                for k in held:
                    self._say(self._tell_failure, drives[k].name, self._node_ids[k],
                              drives[k].failure)
        if not self.finished and not any(_starting(d) for d in drives):
            self.finished = True
            self._say(self._tell_finished,
                      [(d.name, d.phase == BringupPhase.READY) for d in drives],
                      now - self.started_at)

    @staticmethod
    def _tell_failure(name: str, node_id: int, failure: str | None) -> None:
        log.error("drive %r (node %d): start-up failed: %s", name, node_id, failure)

    @staticmethod
    def _tell_silent_bus(channel: str, drives: list[tuple[str, int]], what: str) -> None:
        log.error("no drive answers on %s: %s %s; %s", channel,
                  ", ".join(f"{name} (node {node})" for name, node in drives),
                  what if len(drives) == 1 else f"each {what}", SILENT_BUS_CHECKS)

    @staticmethod
    def _tell_finished(drives: list[tuple[str, bool]], took: float) -> None:
        ready = [name for name, ok in drives if ok]
        failed = [name for name, ok in drives if not ok]
        if not failed:
            audit.info("bring-up finished in %.1f s: %d drives ready (%s)", took, len(ready),
                       ", ".join(ready))
        else:
            audit.info("bring-up ended in %.1f s: %d of %d drives ready%s; failed: %s "
                       "(said above)", took, len(ready), len(drives),
                       f" ({', '.join(ready)})" if ready else "", ", ".join(failed))


def _starting(b: Started) -> bool:
    return b.phase not in (BringupPhase.READY, BringupPhase.FAILED)
