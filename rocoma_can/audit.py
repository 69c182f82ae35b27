"""The audit trail: every operator request (who asked, through which surface, what, and
the answer), every manager state change and every bring-up result, one line each, as
log records of the ``rocoma_can.audit`` logger at INFO (``rocoma-can run`` prints them on
its console; a library user routes the logger where a record is kept).

The lines are written off the control loop: a manager's events are delivered on its event
thread (events.py), which runs ``Audit``, and the hardware writes its bring-up results from
its configuration workers. What a request surface answered reaches the trail as a manager
event too (``ControllerManager.notify_request``), so recordings and Zenoh carry it alike.

``event_text`` is the one wording of a manager event, for these lines and for the
recordings' /rocoma/log (live/messages.py).
"""
from __future__ import annotations

import logging
from collections.abc import Mapping
from typing import Any

from .events import STOP_CAUSE, EventKind, ManagerEvent

#: the logger of the audit trail (see the module)
AUDIT = "rocoma_can.audit"
log = logging.getLogger(AUDIT)


def event_text(event: Mapping[str, Any]) -> tuple[str, int]:
    """A manager event (as record/trace.event_message gives it: ``kind``, ``state``,
    ``controller``, ``cause``) as a line and its level (an e-stop, a failed recovery: a
    warning)."""
    kind, state, cause = event["kind"], event["state"], event["cause"]
    if kind == EventKind.EMERGENCY_STOP.value and cause.startswith(STOP_CAUSE):
        return f"torque-off ({state}): {cause}", logging.INFO  # the loop's own ending
    if kind == EventKind.EMERGENCY_STOP.value:
        return f"e-stop ({state}): {cause or 'no cause given'}", logging.WARNING
    if kind == EventKind.ACTIVE_CONTROLLER_CHANGED.value:
        return f"switched to {event['controller']} ({state})", logging.INFO
    if kind == EventKind.RECOVERY.value:
        return (f"recovery {cause} ({state})",
                logging.WARNING if cause.startswith("failed") else logging.INFO)
    if kind == EventKind.REQUEST.value:
        return cause, logging.INFO
    return f"state {state}, controller {event['controller']}" + (
        f": {cause}" if cause else ""), logging.INFO


class Audit:
    """A manager subscriber (its event thread) that writes each event as an audit line.
    The manager tells a change of state and of controller as two events, which the
    recordings keep; here the second, which says nothing new, is left out."""

    def __init__(self) -> None:
        self._said: tuple[str, str] | None = None  # the (state, controller) last said

    def __call__(self, event: ManagerEvent) -> None:
        now = (event.state.name, event.active_controller)
        repeat = event.kind in (EventKind.STATE_CHANGED, EventKind.ACTIVE_CONTROLLER_CHANGED) \
            and not event.cause and now == self._said
        if event.kind is not EventKind.REQUEST:
            self._said = now
        if repeat:
            return
        text, _ = event_text({"kind": event.kind.value, "state": event.state.name,
                              "controller": event.active_controller, "cause": event.cause})
        log.info("%s", text)
