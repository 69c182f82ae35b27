"""What a cycle's read found that the manager must act on before this cycle's update.

The hardware never holds the manager: ``CanopenHardware.read`` returns these, and the loop
(``rocoma_can.runtime.loop.run_cycle``) applies each to the manager before update(), so a
fault found in a read is acted on in the same cycle. A finished recovery comes first: an
e-stop read in the same cycle then latches again after the recovery's clear.
"""
from __future__ import annotations

from concurrent.futures import Future, InvalidStateError
from dataclasses import dataclass
from typing import Protocol


class StopTarget(Protocol):
    """The manager as the hardware's findings see it (rocoma_can's ControllerManager)."""
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

    def apply(self, manager: StopTarget) -> None:
        if self.failproof:
            manager.failproof_stop(cause=self.cause)
        else:
            manager.emergency_stop(cause=self.cause)


@dataclass(frozen=True, slots=True)
class RecoveryDone:
    """Every drive came back (recovery.py): the e-stop latch is cleared, then the recovery's
    future says True, so its caller may switch at once. A clear that raises leaves the latch
    and ends the recovery as failed."""
    future: Future[bool]

    def apply(self, manager: StopTarget) -> None:
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


CycleEvent = StopRequest | RecoveryDone
