"""What a cycle's read found that the manager must act on before this cycle's update.

The hardware never holds the manager: ``CanopenHardware.read`` returns these, and the loop
(``rocoma_can.runtime.loop.run_cycle``) applies each to the manager before update(), so a
fault found in a read is acted on in the same cycle. A finished recovery comes first: an
e-stop read in the same cycle then latches again after the recovery's clear.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Protocol

from .recovery import RecoveryDone


class ManagerLatch(Protocol):
    """The manager as the hardware's findings see it (rocoma_can's ControllerManager):
    its two stops, and the clear of its e-stop latch (a finished recovery's)."""
    def emergency_stop(self, cause: str = ...) -> None: ...
    def failproof_stop(self, cause: str = ...) -> None: ...
    def clear_emergency_stop(self) -> bool: ...


@dataclass(frozen=True, slots=True)
class StopRequest:
    """A drive's fault or an e-stop frame (emergency stop), or a whole bus failed
    (``failproof``: an emergency controller written for the whole robot cannot stop it
    smartly with a bus of joints gone)."""
    cause: str
    failproof: bool = False

    def apply(self, manager: ManagerLatch) -> None:
        if self.failproof:
            manager.failproof_stop(cause=self.cause)
        else:
            manager.emergency_stop(cause=self.cause)


#: what ``CanopenHardware.read`` returns: stops, and a finished recovery (recovery.py)
CycleFinding = StopRequest | RecoveryDone
