"""Adapters: how the manager calls user controllers (rocoma's ControllerAdapter).

The manager never calls a user method directly. An adapter keeps the lifecycle flags that
decide what may be called next, turns any exception into a failed call (logged once, with
traceback, off the update thread), runs the state check before and the command limit after
each advance, and measures every call. User code therefore cannot corrupt the manager's
state machine, whatever it raises or returns.
"""
from __future__ import annotations

import logging
import time
from typing import Any, Callable

from .interfaces import Controller, EmergencyController, FailproofController, SwapState

Report = Callable[[int, str, "BaseException | None"], None]
StateCheck = Callable[[Any], bool]


class CallStats:
    """Duration of one kind of call, in nanoseconds."""
    __slots__ = ("count", "last_ns", "max_ns", "total_ns")

    def __init__(self) -> None:
        self.count = 0
        self.last_ns = 0
        self.max_ns = 0
        self.total_ns = 0

    def add(self, ns: int) -> None:
        self.count += 1
        self.last_ns = ns
        self.total_ns += ns
        if ns > self.max_ns:
            self.max_ns = ns

    @property
    def mean_ns(self) -> float:
        return self.total_ns / self.count if self.count else 0.0


def _describe(result: Any) -> str:
    return "returned None (must return True on success)" if result is None else \
        f"returned {result!r}"


class _Adapter:
    """Call wrapper shared by the layers: failures become False plus a reason."""

    CALLS: tuple[str, ...] = ()

    def __init__(self, controller: Any, report: Report) -> None:
        self.controller = controller
        self.name: str = controller.name
        self._report = report
        self.stats = {kind: CallStats() for kind in self.CALLS}
        self.failure = ""  # why the latest call failed, for the e-stop cause
        self.created = False

    def _fail(self, call: str, why: str, exc: BaseException | None = None) -> bool:
        self.failure = f"{self.name}.{call} {why}"
        self._report(logging.ERROR, f"controller {self.failure}", exc)
        return False

    def _call(self, call: str, fn: Callable[..., Any], *args: Any) -> bool:
        """For the calls that are not on the cycle's hot path."""
        t0 = time.perf_counter_ns()
        try:
            result = fn(*args)
        except Exception as exc:
            return self._fail(call, f"raised {exc!r}", exc)
        finally:
            self.stats[call].add(time.perf_counter_ns() - t0)
        return True if result else self._fail(call, _describe(result))

    def create(self, dt: float) -> bool:
        self.created = self._call("create", self.controller.create, dt)
        return self.created


class ControllerAdapter(_Adapter):
    """Adapter for switchable controllers (and, by subclassing, emergency controllers)."""

    CALLS = ("create", "initialize", "reset", "swap", "advance", "pre_stop", "stop", "cleanup")

    def __init__(self, controller: Controller, report: Report,
                 check_state: StateCheck | None = None,
                 limit_command: StateCheck | None = None) -> None:
        super().__init__(controller, report)
        self._check_state = check_state
        self._limit_command = limit_command
        self._advance_stats = self.stats["advance"]
        self.running = False         # the manager advances it
        self.being_stopped = False   # handed over to be stopped, stop not yet returned
        self.pre_stopped = False     # pre_stop ran for the current activation

    @property
    def initialized(self) -> bool:
        return self.controller._initialized

    def _set_initialized(self, ok: bool) -> bool:
        self.controller._initialized = ok
        if ok:
            self.pre_stopped = False
        return ok

    def initialize(self, dt: float) -> bool:
        return self._set_initialized(self._call("initialize", self.controller.initialize, dt))

    def swap(self, dt: float, swap_state: SwapState | None) -> bool:
        """Take over from a predecessor (controller.swap: by default reset or initialize)."""
        return self._set_initialized(
            self._call("swap", self.controller.swap, dt, swap_state))

    def get_swap_state(self) -> SwapState | None:
        try:
            return self.controller.get_swap_state()
        except Exception as exc:
            self._fail("get_swap_state", f"raised {exc!r}", exc)
            return None

    def advance(self, dt: float) -> bool:
        """The hot path: state check, advance, command limit. No allocation on success."""
        controller = self.controller
        t0 = time.perf_counter_ns()
        try:
            if self._check_state is not None and not self._check_state(controller.state):
                return self._fail("advance", "not called: check_state failed")
            result = controller.advance(dt)
            if not result:
                return self._fail("advance", _describe(result))
            if self._limit_command is not None and not self._limit_command(controller.command):
                return self._fail("advance", "wrote a command that limit_command rejected")
            return True
        except Exception as exc:
            return self._fail("advance", f"raised {exc!r}", exc)
        finally:
            self._advance_stats.add(time.perf_counter_ns() - t0)

    def pre_stop(self) -> bool:
        self.pre_stopped = True
        return self._call("pre_stop", self.controller.pre_stop)

    def stop(self) -> bool:
        """Stop (pre_stop first if this activation has not had it): after this the
        controller is uninitialized whatever stop returned, as in rocoma."""
        if not self.pre_stopped:
            self.pre_stop()
        try:
            return self._call("stop", self.controller.stop)
        finally:
            self.running = False
            self._set_initialized(False)

    def cleanup(self) -> bool:
        workers = self.controller.workers
        if workers is not None:
            workers.cancel_all(wait=True)
        ok = self._call("cleanup", self.controller.cleanup)
        self.created = False
        return ok


class EmergencyControllerAdapter(ControllerAdapter):
    CALLS = ControllerAdapter.CALLS + ("initialize_fast",)

    controller: EmergencyController

    def initialize_fast(self, dt: float) -> bool:
        return self._set_initialized(
            self._call("initialize_fast", self.controller.initialize_fast, dt))


class FailproofControllerAdapter(_Adapter):
    """The last layer cannot fail: whatever advance raises is counted and reported."""

    CALLS = ("create", "advance", "cleanup")

    controller: FailproofController

    def __init__(self, controller: FailproofController, report: Report) -> None:
        super().__init__(controller, report)
        self._advance_stats = self.stats["advance"]
        self.errors = 0

    def advance(self, dt: float) -> None:
        t0 = time.perf_counter_ns()
        try:
            self.controller.advance(dt)
        except Exception as exc:  # swallowed by contract; the hardware layer still torques off
            self.errors += 1
            if self.errors == 1 or self.errors % 1000 == 0:
                self._fail("advance", f"raised {exc!r} ({self.errors} times)", exc)
        finally:
            self._advance_stats.add(time.perf_counter_ns() - t0)

    def cleanup(self) -> bool:
        return self._call("cleanup", self.controller.cleanup)
