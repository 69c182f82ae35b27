"""The demo's walk-through and an operator's e-stop: one from outside the walk-through
(Foxglove's or Zenoh's e-stop service, ``rocoma-can estop``) ends it, the robot left
stopped; the demo never clears or switches away an operator's stop."""
from __future__ import annotations

import threading

from ...events import EventKind, ManagerEvent

#: how the causes of stops asked from outside the walk-through begin: the live view's and
#: Zenoh's services (remote.py) and the manager node's SDO objects (``rocoma-can estop``);
#: the walk-through itself stops the robot only by drive faults and the CAN e-stop frame
OUTSIDE_STOPS = ("Foxglove ", "Zenoh ", "SDO ")


class Ended(Exception):
    """The walk-through ends early: an operator stopped the robot (OutsideStop)."""


class LoopStopped(Exception):
    """The walk-through ends early: the loop stopped under it (a Ctrl-C or SIGTERM, its
    time up); the loop's stop sends the torque-off frames, nothing is commanded after."""


def loop_running(stop_reason: str) -> None:
    """LoopStopped when the loop has stopped (``stop_reason``: the loop's, "" while it runs)."""
    if stop_reason:
        raise LoopStopped(stop_reason)


class OutsideStop:
    """The first e-stop from outside the walk-through (OUTSIDE_STOPS: an operator's, from
    Foxglove, Zenoh or ``rocoma-can estop``), heard on the manager's event thread. The
    walk-through ends at its next step and commands nothing more: an operator's stop is
    never cleared or switched away by the demo; the loop's stop and its torque-off frames
    follow as after any walk-through."""

    def __init__(self, stop: threading.Event) -> None:
        self.cause: str | None = None
        self._stop = stop

    def __call__(self, event: ManagerEvent) -> None:
        if event.kind is EventKind.EMERGENCY_STOP and self.cause is None \
                and event.cause.startswith(OUTSIDE_STOPS):
            self.cause = event.cause
            self._stop.set()  # the walk-through's waits and pauses end at once

    def go_on(self, requested: str = "") -> None:
        """Ended once an operator has stopped the robot: the event heard, or the manager's
        ``estop_requested`` (given before a command that would undo a stop: the event
        comes a cycle later) naming an operator's stop."""
        if self.cause is None and requested.startswith(OUTSIDE_STOPS):
            self.cause = requested
        if self.cause is not None:
            raise Ended(self.cause)
