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
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import numpy as np

from .interfaces import Controller, EmergencyController, FailproofController, SwapState

Report = Callable[[int, str, "BaseException | None"], None]
StateCheck = Callable[[Any], bool]


def p99(values: np.ndarray) -> float:
    """``np.percentile(values, 99)`` (linear) by one partition: a quarter of its time, and
    none of its first call's import of numpy.ma (~10 ms in the loop's process, whose
    statistics other threads read while the loop runs)."""
    at = 0.99 * (len(values) - 1)
    low = int(at)
    high = min(low + 1, len(values) - 1)
    part = np.partition(values, (low, high))
    return float(part[low] + (part[high] - part[low]) * (at - low))


class CallStats:
    """Duration of one kind of call, in nanoseconds; with a window, also the p99 of the
    latest ``window`` calls (a preallocated ring, so recording allocates nothing)."""
    __slots__ = ("count", "last_ns", "max_ns", "total_ns", "_ring", "_mask")

    def __init__(self, window: int = 0) -> None:
        self.count = 0
        self.last_ns = 0
        self.max_ns = 0
        self.total_ns = 0
        size = 1 << max(0, window - 1).bit_length() if window else 0
        self._ring = np.zeros(size, dtype=np.int64) if size else None
        self._mask = size - 1

    def add(self, ns: int) -> None:
        if self._ring is not None:
            self._ring[self.count & self._mask] = ns
        self.count += 1
        self.last_ns = ns
        self.total_ns += ns
        if ns > self.max_ns:
            self.max_ns = ns

    @property
    def mean_ns(self) -> float:
        return self.total_ns / self.count if self.count else 0.0

    @property
    def p99_ns(self) -> float:
        if self._ring is None or not self.count:
            return float(self.max_ns)
        return p99(self._ring[:min(self.count, len(self._ring))])

    def summary(self) -> dict[str, float]:
        return {"count": self.count, "mean_us": self.mean_ns / 1e3, "p99_us": self.p99_ns / 1e3,
                "max_us": self.max_ns / 1e3, "last_us": self.last_ns / 1e3}


@dataclass(frozen=True)
class TimingBudget:
    """Timing supervision of one controller, in nanoseconds (0 = not supervised).

    An advance over ``advance_ns`` ``overruns`` times in a row, or once over ``hang_ns``,
    is a failure; so is an initialize_fast over ``initialize_fast_ns``.
    """
    advance_ns: int = 0
    initialize_fast_ns: int = 0
    overruns: int = 5
    hang_ns: int = 0


def _succeeded(result: Any) -> bool:
    """Only True (a Python or numpy bool) is success. Anything else is the call's failure:
    None, 1, a non-empty list, and values with no clear truth value (a numpy array, an
    object whose ``__bool__`` raises), which would otherwise raise outside the guard."""
    return result is True or (type(result) is np.bool_ and bool(result))


def _describe(result: Any) -> str:
    if result is None:
        return "returned None (must return True on success)"
    try:
        text = repr(result)
    except Exception:  # a hostile __repr__ must not turn a failure into an escape
        text = f"<{type(result).__name__}>"
    if len(text) > 80:
        text = text[:77] + "..."
    return f"returned {text} (must return True on success)"


def _exc_text(exc: BaseException) -> str:
    try:
        return repr(exc)
    except Exception:
        return f"<{type(exc).__name__}>"


class _Adapter:
    """Call wrapper shared by the layers: failures become False plus a reason."""

    CALLS: tuple[str, ...] = ()
    controller: Any  # each layer's adapter narrows it

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
            if _succeeded(result):
                return True
            why = _describe(result)
        except Exception as exc:
            return self._fail(call, f"raised {_exc_text(exc)}", exc)
        finally:
            self.stats[call].add(time.perf_counter_ns() - t0)
        return self._fail(call, why)

    def create(self, dt: float) -> bool:
        self.created = self._call("create", self.controller.create, dt)
        return self.created


class ControllerAdapter(_Adapter):
    """Adapter for switchable controllers (and, by subclassing, emergency controllers)."""

    CALLS: tuple[str, ...] = ("create", "initialize", "reset", "swap", "advance", "pre_stop",
                              "stop", "cleanup")
    controller: Controller

    def __init__(self, controller: Controller, report: Report,
                 check_state: StateCheck | None = None,
                 limit_command: StateCheck | None = None,
                 budget: TimingBudget = TimingBudget()) -> None:
        super().__init__(controller, report)
        self._check_state = check_state
        self._limit_command = limit_command
        self.budget = budget
        self.overruns_in_a_row = 0
        self._advance_stats = self.stats["advance"] = CallStats(window=4096)
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
            self._fail("get_swap_state", f"raised {_exc_text(exc)}", exc)
            return None

    def advance(self, dt: float) -> bool:
        """The hot path: state check, advance, command limit, timing budget.
        No allocation on success."""
        controller = self.controller
        t0 = time.perf_counter_ns()
        try:
            if self._check_state is not None and not self._check_state(controller.state):
                return self._fail("advance", "not called: check_state failed")
            result = controller.advance(dt)
            if result is not True and not _succeeded(result):
                return self._fail("advance", _describe(result))
            if self._limit_command is not None and not self._limit_command(controller.command):
                return self._fail("advance", "wrote a command that limit_command rejected")
        except Exception as exc:
            return self._fail("advance", f"raised {_exc_text(exc)}", exc)
        finally:
            ns = time.perf_counter_ns() - t0
            self._advance_stats.add(ns)
        return self._within_budget(ns)

    def _within_budget(self, ns: int) -> bool:
        budget = self.budget
        if not budget.advance_ns or ns <= budget.advance_ns:
            self.overruns_in_a_row = 0
            return True
        self.overruns_in_a_row += 1
        if budget.hang_ns and ns > budget.hang_ns:
            return self._fail("advance", f"hung for {ns / 1e6:.1f} ms "
                              f"(limit {budget.hang_ns / 1e6:.1f} ms)")
        if self.overruns_in_a_row >= budget.overruns:
            return self._fail("advance", f"over its budget of {budget.advance_ns / 1e3:.0f} us "
                              f"{self.overruns_in_a_row} cycles in a row "
                              f"(last {ns / 1e3:.0f} us)")
        return True

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
        ok = self._call("initialize_fast", self.controller.initialize_fast, dt)
        limit = self.budget.initialize_fast_ns
        took = self.stats["initialize_fast"].last_ns
        if ok and limit and took > limit:
            ok = self._fail("initialize_fast", f"took {took / 1e3:.0f} us, over its budget of "
                            f"{limit / 1e3:.0f} us")
        return self._set_initialized(ok)


@dataclass
class ControllerPair:
    """A switchable controller and the emergency layer it falls to: what the manager
    registers, switches into and runs (one emergency adapter may serve several pairs)."""
    controller: ControllerAdapter
    emergency: EmergencyControllerAdapter | None


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
                self._fail("advance", f"raised {_exc_text(exc)} ({self.errors} times)", exc)
        finally:
            self._advance_stats.add(time.perf_counter_ns() - t0)

    def cleanup(self) -> bool:
        return self._call("cleanup", self.controller.cleanup)
