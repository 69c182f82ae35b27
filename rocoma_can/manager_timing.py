"""How long the manager waits, and how long its controllers may take: the bounds of every
wait (ManagerTimeouts, seconds) and the wall-time budgets of each controller call
(TimingSupervision, in cycles), which the config's ``timing:`` section sets.
"""
from __future__ import annotations

from dataclasses import dataclass

from .adapters import TimingBudget


@dataclass
class ManagerTimeouts:
    """Upper bounds, in seconds, for every wait the manager does."""
    being_stopped: float = 5.0  # a switch waits this long for the new controller's stop
    switch: float = 60.0        # switch_controller() waits this long for the result
    shutdown: float = 5.0       # shutdown waits this long for stops and for each thread


@dataclass(frozen=True)
class TimingSupervision:
    """What rocoma left to the user ("make sure you have no deadlocks"), supervised.

    Budgets are fractions of dt; a controller may set its own ``advance_budget`` (seconds).
    Budgets are wall time, what the cycle experiences: without real-time priority a
    preempted advance counts too, so ``overruns`` in a row (not one) makes a failure.
    A controller over its advance budget ``overruns`` cycles in a row, or an emergency
    controller whose initialize_fast overruns, has failed. An update() that has not returned
    after ``hang`` × dt is hung: the watchdog thread calls ``on_hang`` every dt until it
    returns (the CAN layer sends the failproof torque-off frames from there), and the hung
    advance counts as a failure when it finally returns: straight to FAILPROOF when
    ``on_hang`` ran (the drives are off already), as any failure otherwise.
    """
    advance: float = 0.5
    initialize_fast: float = 0.5
    overruns: int = 5
    hang: float = 20.0

    def budget_for(self, controller: object, dt: float) -> TimingBudget:
        advance = getattr(controller, "advance_budget", None) or self.advance * dt
        return TimingBudget(advance_ns=int(advance * 1e9),
                            initialize_fast_ns=int(self.initialize_fast * dt * 1e9),
                            overruns=self.overruns, hang_ns=int(self.hang * dt * 1e9))
