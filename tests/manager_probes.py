"""Controllers that record every call (which method, in which update call, on which thread)
and can be told to fail, raise, be slow or wait on a gate: the instruments for the seed's
tables and rocoma's own scenarios."""
from __future__ import annotations

import threading
import time
from dataclasses import dataclass, field

import pytest

from rocoma_can import (
    ControllerManager,
    EmergencyController,
    FailproofController,
    ManagerState,
    SwapState,
)
from rocoma_can.interfaces import Controller

WAIT = 10.0  # upper bound for any wait in these tests; a hit means the test failed


@dataclass(frozen=True, eq=False)  # each call is its own record: index() by identity
class Call:
    controller: str
    method: str
    cycle: int        # manager.cycle_count when the call started
    thread: str
    update_thread: bool


@dataclass
class Journal:
    manager: ControllerManager | None = None
    update_thread: int | None = None
    calls: list[Call] = field(default_factory=list)
    _lock: threading.Lock = field(default_factory=threading.Lock)
    _changed: threading.Condition = field(init=False)

    def __post_init__(self) -> None:
        self._changed = threading.Condition(self._lock)

    def add(self, controller: str, method: str) -> None:
        cycle = self.manager.cycle_count if self.manager is not None else 0
        me = threading.current_thread()
        call = Call(controller, method, cycle, me.name, me.ident == self.update_thread)
        with self._changed:
            self.calls.append(call)
            self._changed.notify_all()

    def of(self, controller: str | None = None, method: str | None = None) -> list[Call]:
        with self._lock:
            return [c for c in self.calls
                    if (controller is None or c.controller == controller)
                    and (method is None or c.method == method)]

    def wait_for(self, controller: str, method: str, count: int = 1,
                 timeout: float = WAIT) -> list[Call]:
        deadline = time.monotonic() + timeout
        with self._changed:
            while True:
                found = [c for c in self.calls
                         if c.controller == controller and c.method == method]
                if len(found) >= count:
                    return found
                left = deadline - time.monotonic()
                if left <= 0:
                    raise AssertionError(f"{controller}.{method} not called {count}x "
                                         f"within {timeout} s; calls: {self.calls[-20:]}")
                self._changed.wait(left)


#: (layer, method) of every user callback the manager calls, for fault matrices
LAYER_METHODS = [
    ("controller", "create"), ("controller", "initialize"), ("controller", "advance"),
    ("controller", "pre_stop"), ("controller", "stop"), ("controller", "get_swap_state"),
    ("controller", "cleanup"), ("emergency", "initialize_fast"), ("emergency", "advance"),
    ("emergency", "stop"), ("failproof", "advance"), ("failproof", "cleanup"),
]


class NumberSwapState(SwapState):
    def __init__(self, value: float) -> None:
        self.value = value


class _Behaviour:
    """Mixin: record, then delay / wait on a gate / raise / return False or a given value
    (``returns``: method -> what to return instead of True) as configured."""

    def _setup(self, journal: Journal, fail=(), raises=(), delay=None, gates=None,
               returns=None) -> None:
        self.journal = journal
        self.fail = set(fail)
        self.raises = set(raises)
        self.returns = dict(returns or {})
        self.delay = dict(delay or {})
        self.gates = dict(gates or {})
        self.received_swap_state: SwapState | None = None
        self.value = 0.0

    def _do(self, method: str) -> bool:
        self.journal.add(self.name, method)
        if method in self.delay:
            time.sleep(self.delay[method])
        if method in self.gates:
            if not self.gates[method].wait(WAIT):
                raise AssertionError(f"gate for {self.name}.{method} never opened")
        if method in self.raises:
            raise RuntimeError(f"{self.name}.{method} raised on purpose")
        if method in self.returns:
            return self.returns[method]
        return method not in self.fail


class Probe(_Behaviour, Controller):
    def __init__(self, name: str, journal: Journal, **behaviour) -> None:
        Controller.__init__(self, name)
        self._setup(journal, **behaviour)

    def create(self, dt): return self._do("create")
    def initialize(self, dt): return self._do("initialize")
    def reset(self, dt): return self._do("reset")
    def pre_stop(self): return self._do("pre_stop")
    def stop(self): return self._do("stop")
    def cleanup(self): return self._do("cleanup")

    def advance(self, dt):
        ok = self._do("advance")
        if ok is True and self.command is not None:
            self.command.append(self.name)  # who wrote this cycle's command
        return ok

    def swap(self, dt, swap_state):
        self.received_swap_state = swap_state
        self._do("swap")
        return super().swap(dt, swap_state)

    def get_swap_state(self):
        self._do("get_swap_state")
        return NumberSwapState(self.value)


class EmergencyProbe(Probe, EmergencyController):
    def initialize_fast(self, dt): return self._do("initialize_fast")


class FailproofProbe(_Behaviour, FailproofController):
    def __init__(self, name: str, journal: Journal, **behaviour) -> None:
        FailproofController.__init__(self, name)
        self._setup(journal, **behaviour)

    def create(self, dt): return self._do("create")
    def cleanup(self): return self._do("cleanup")

    def advance(self, dt):
        self._do("advance")
        if self.command is not None:
            self.command.append(self.name)


class CommandLog(list):
    """The shared 'command': each advance appends its writer; the test reads who wrote
    cycle k and clears it per cycle."""


@dataclass
class Rig:
    mgr: ControllerManager
    journal: Journal
    command: CommandLog

    def step(self) -> tuple[ManagerState, list[str]]:
        """One update call: the layer returned and who wrote the command in it."""
        self.command.clear()
        state = self.mgr.update()
        return state, list(self.command)

    def calls_in_cycle(self, cycle: int) -> list[tuple[str, str]]:
        return [(c.controller, c.method) for c in self.journal.calls
                if c.cycle == cycle and c.update_thread]


@pytest.fixture
def rig():
    journal = Journal(update_thread=threading.get_ident())
    command = CommandLog()
    # Wall-time supervision off: these are the seed's tables and rocoma's semantics; on a
    # loaded machine a preempted call must not count as a failure (test_manager_timing.py
    # tests the supervision itself).
    mgr = ControllerManager(FailproofProbe("failproof", journal), dt=0.001, command=command,
                            timing=None)
    journal.manager = mgr
    yield Rig(mgr, journal, command)
    assert mgr.shutdown()
    assert not [t for t in threading.enumerate() if t.name.startswith("rocoma/")]


def layered_manager(layer: str, **behaviour) -> tuple[ControllerManager, bool]:
    """A manager with failproof probe, controller "a" paired with emergency "e", and a
    healthy "b"; ``behaviour`` (raises=, returns=, fail=...) goes to the probe of ``layer``.
    Returns the manager and whether adding "a" succeeded."""
    journal = Journal(update_thread=threading.get_ident())

    def of(name: str) -> dict:
        return behaviour if layer == name else {}
    mgr = ControllerManager(FailproofProbe("failproof", journal, **of("failproof")), dt=0.001,
                            command=CommandLog(), timing=None)
    journal.manager = mgr
    added = mgr.add_controller(Probe("a", journal, **of("controller")),
                               emergency=EmergencyProbe("e", journal, **of("emergency")))
    mgr.add_controller(Probe("b", journal))
    return mgr, added

