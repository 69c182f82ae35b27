"""What a cycle's read found that the manager must act on before this cycle's update.

The hardware never holds the manager: ``CanopenHardware.read`` returns these, and the loop
(``rocoma_can.runtime.loop.run_cycle``) applies each to the manager before update(), so a
fault found in a read is acted on in the same cycle. A finished recovery comes first: an
e-stop read in the same cycle then latches again after the recovery's clear.

``ReadFindings`` collects them in one read: e-stop frames, a bus that failed, the faults
supervision delivered. A drive's fault is also its controlword 0x0000 by SDO, from a thread
of its own (switch_off.py): a drive that no longer applies RPDOs still switches off.
"""
from __future__ import annotations

from collections.abc import Callable, Sequence
from concurrent.futures import Future
from dataclasses import dataclass
from typing import Protocol

from ...stop_surfaces import CAN_FRAME
from ..bringup.drive_bringup import DriveBringup
from ..link.bus_port import BusPort
from .recovery import RecoveryDone
from .supervision import FaultEvent, Supervisor
from .switch_off import SdoSwitchOff


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


class ReadFindings:
    """What one read found, in the order found: ``events``, which ``CanopenHardware.read``
    hands to the loop (cleared by ``begin``, at the start of the next read).

    ``on_fault``: the hardware's hook, told every fault (counted in ``hook_errors`` when it
    raises, never raised: a reporting hook must not take the cycle down)."""

    def __init__(self, supervisor: Supervisor,
                 on_fault: Callable[[FaultEvent], None] | None) -> None:
        self.events: list[CycleFinding] = []
        self.estop_frames = 0  # e-stop frames received (any bus)
        self.hook_errors = 0   # on_fault calls that raised
        self.switch_off = SdoSwitchOff()  # started with the buses (the hardware's start)
        self._sup, self._on_fault = supervisor, on_fault
        self._bringups: Sequence[DriveBringup] = ()

    def attach_bringups(self, bringups: Sequence[DriveBringup]) -> None:
        """The drives' bring-ups, once the hardware has started them (the SDO switch-off
        writes through theirs)."""
        self._bringups = bringups

    def begin(self) -> list[CycleFinding]:
        """A new read: the last one's findings are gone."""
        self.events.clear()
        return self.events

    def estops(self, port: BusPort, count: int, cob_id: int) -> None:
        """E-stop frames (``cob_id``) on one bus in this read: one request, whatever their
        count."""
        self.estop_frames += count
        self.events.append(StopRequest(CAN_FRAME.cause(
            "estop", f" from 0x{cob_id:03X} on bus {port.name!r}")))

    def bus_failed(self, port: BusPort, cause: str, now: float) -> None:
        """A fault of every drive on the bus and one event (Supervisor.bus_fault), latched
        on the port until recovery; ``deliver`` makes it a failproof stop, so every other
        bus gets torque-off frames from this cycle on."""
        if port.latched is None:
            port.latched = cause
            self._sup.bus_fault(cause, now, port.drives, bus=port.name)

    def end_of_write(self, ports: Sequence[BusPort], now: float) -> None:
        """After a write: a bus that refuses frames cycle after cycle (transmit queue full,
        interface down) delivers no command and no heartbeat: after as many cycles as
        missing TPDOs are tolerated it is a bus fault, an e-stop like bus-off. A recovery
        succeeds only after as many cycles in a row without a refused frame on every bus."""
        limit = self._sup.tpdo_timeout_cycles
        for port in ports:
            cause = port.end_of_write(limit)
            if cause is not None:
                self.bus_failed(port, cause, now)

    def recovered(self, future: Future[bool]) -> None:
        """The running recovery brought every drive back: first, so an e-stop of this read
        latches after its clear."""
        self.events.insert(0, RecoveryDone(future))

    def deliver(self, faults: list[FaultEvent]) -> None:
        """The faults supervision found: a stop each, an SDO switch-off for a drive still
        latched by it, and the hook."""
        sup, bringups = self._sup, self._bringups
        for event in faults:
            # a whole bus (index -1): no smart stop without those joints
            self.events.append(StopRequest(str(event), failproof=event.index < 0))
            i = event.index
            if (0 <= i < len(bringups) and bringups[i].mapped
                    and sup.latched[i] is event):  # a queue append: cannot block
                self.switch_off.request(bringups[i], _still_latched(sup, i, event))
            if self._on_fault is not None:
                try:
                    self._on_fault(event)
                except Exception:
                    self.hook_errors += 1


def _still_latched(sup: Supervisor, i: int, event: FaultEvent) -> Callable[[], bool]:
    """For the SDO switch-off: whether drive i is still latched by ``event``."""
    latched = sup.latched
    return lambda: latched[i] is event
