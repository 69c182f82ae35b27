"""The controllers one manager holds, by name: each switchable controller paired with its
emergency controller (one instance per name, shared by the pairs that name it), and the
failproof controller under them all. Names are unique across the layers: a switch, an
event and a statistic name one controller.

Apart from the manager (manager.py: the cycle and its e-stops) because this is its set-up
and its end: adding is done before the loop runs, and shutdown's last steps (the stops
still under way, each controller's cleanup) are the only other users.
"""
from __future__ import annotations

import logging
import time
from typing import Any

from .adapters import (
    ControllerAdapter,
    ControllerPair,
    EmergencyControllerAdapter,
    FailproofControllerAdapter,
    Report,
    StateCheck,
    TimingBudget,
)
from .interfaces import Controller, EmergencyController, FailproofController
from .manager_timing import TimingSupervision
from .workers import WorkerManager

# The manager's logger: adding a controller is the manager's work, and its records are
# found there.
log = logging.getLogger("rocoma_can.manager")


class ControllerSet:
    """The controllers of one manager; ``pairs`` and ``emergencies`` by name."""

    def __init__(self, failproof: FailproofControllerAdapter, dt: float, state: Any,
                 command: Any, report: Report, check_state: StateCheck | None,
                 limit_command: StateCheck | None, timing: TimingSupervision | None) -> None:
        self.failproof = failproof
        self.pairs: dict[str, ControllerPair] = {}
        self.emergencies: dict[str, EmergencyControllerAdapter] = {}
        self._dt = dt
        self._state = state
        self._command = command
        self._report = report
        self._check_state = check_state
        self._limit_command = limit_command
        self._timing = timing

    def attach(self, controller: Controller | FailproofController) -> None:
        """Give a controller the manager's time step, state and command (and workers)."""
        controller.dt = self._dt
        controller.state = self._state
        controller.command = self._command
        if isinstance(controller, Controller) and controller.workers is None:
            controller.workers = WorkerManager(controller.name)

    def add(self, controller: Controller, emergency: EmergencyController | None,
            closed: bool) -> bool:
        """ControllerManager.add_controller, once its arguments are checked (``closed``:
        the manager is shut down: nothing is added)."""
        name = controller.name
        if name in self.pairs or name in self.emergencies or name == self.failproof.name:
            log.error("controller name %r is already taken; not added", name)
            return False
        if closed:
            log.error("manager is shut down; controller %r not added", name)
            return False
        emcy_adapter = None
        if emergency is not None:
            emcy_adapter = self._emergency(emergency, name)
            if emcy_adapter is None:
                return False
        adapter = ControllerAdapter(controller, self._report, self._check_state,
                                    self._limit_command, self._budget_for(controller))
        self.attach(controller)
        if not adapter.create(self._dt):
            log.error("controller %r could not be created: %s", name, adapter.failure)
            return False
        self.pairs[name] = ControllerPair(adapter, emcy_adapter)
        return True

    def _emergency(self, emergency: EmergencyController,
                   name: str) -> EmergencyControllerAdapter | None:
        """The adapter of controller ``name``'s emergency controller: the one registered
        under its name (rocoma's behaviour: a second instance of that name is dropped with
        a warning), else a new one, created; None when it cannot be (said why)."""
        emcy_adapter = self.emergencies.get(emergency.name)
        if emcy_adapter is not None:
            if emcy_adapter.controller is not emergency:
                log.warning("a second emergency controller named %r was dropped; "
                            "the first instance is shared", emergency.name)
            return emcy_adapter
        if emergency.name in self.pairs or emergency.name == self.failproof.name:
            log.error("emergency controller name %r is taken by another layer; "
                      "controller %r not added", emergency.name, name)
            return None
        emcy_adapter = EmergencyControllerAdapter(
            emergency, self._report, self._check_state, self._limit_command,
            self._budget_for(emergency))
        self.attach(emergency)
        if not emcy_adapter.create(self._dt):
            log.error("emergency controller %r could not be created (%s); "
                      "controller %r not added", emergency.name, emcy_adapter.failure, name)
            return None
        self.emergencies[emergency.name] = emcy_adapter
        return emcy_adapter

    def _budget_for(self, controller: object) -> TimingBudget:
        if self._timing is None:
            return TimingBudget()
        return self._timing.budget_for(controller, self._dt)

    def __len__(self) -> int:
        """The controllers that may be stopped (the failproof one never is)."""
        return len(self.pairs) + len(self.emergencies)

    def adapters(self) -> dict[str, ControllerAdapter | FailproofControllerAdapter]:
        """Every controller's adapter by name (flags and call statistics)."""
        out: dict[str, ControllerAdapter | FailproofControllerAdapter] = {
            p.controller.name: p.controller for p in self.pairs.values()}
        out.update(self.emergencies)
        out[self.failproof.name] = self.failproof
        return out

    def finish(self, limit: float) -> bool:
        """Shutdown's end: wait (at most ``limit`` s) for the stops under way, then clean
        up every controller created and not still stopping. False when one did not."""
        deadline = time.monotonic() + limit
        pending = [a for a in self.adapters().values()
                   if isinstance(a, ControllerAdapter) and a.being_stopped]
        while pending and time.monotonic() < deadline:
            time.sleep(0.005)
            pending = [a for a in pending if a.being_stopped]
        for adapter in pending:
            log.error("shutdown: controller %r still stopping after %.1f s", adapter.name, limit)
        ok = not pending
        for each in self.adapters().values():
            if each.created and each not in pending:
                ok = each.cleanup() and ok
        return ok
