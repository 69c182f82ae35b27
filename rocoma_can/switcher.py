"""The switch protocol: switching controllers on the manager's switcher thread.

Apart from the manager because a switch is slow work (user ``pre_stop`` and ``swap``, a wait
for a stop) that must never run in the update thread, and that touches the manager's state
only at two short points under its cycle lock: a consistent look at who runs when the
switch begins, and the commit. The sequence, as rocoma does it, made exact:

1. old ``pre_stop``; the old controller keeps advancing meanwhile;
2. wait, at most ``timeouts.being_stopped``, until the new one is not being stopped;
3. ``old.get_swap_state()``, ``new.swap(dt, state)``;
4. commit under the cycle lock, between two cycles, only if no e-stop happened meanwhile
   (nor was requested, nor the switch guard objects now);
5. the old one's ``stop`` on a stopper thread.

A failed pre_stop or swap e-stops, as rocoma does: the old controller was already told to
stop and is no longer trusted to run on.
"""
from __future__ import annotations

import enum
import logging
import queue
import threading
import time
from collections import deque
from collections.abc import Callable
from concurrent.futures import Future
from typing import TYPE_CHECKING, Protocol

from .adapters import ControllerAdapter, ControllerPair
from .controller_set import ControllerSet
from .events import LATCHED, ManagerState
from .stopper import Stoppers

if TYPE_CHECKING:
    from .manager_timing import ManagerTimeouts

# The manager's logger: a switch is the manager's work, and its records are found there.
log = logging.getLogger("rocoma_can.manager")


class SwitchResult(enum.IntEnum):
    SWITCHED = 0
    RUNNING = 1    # already the active controller in OK
    NOT_FOUND = 2  # unknown name, or an emergency / failproof controller's name
    ERROR = 3      # refused (busy, latched e-stop, shutting down) or failed / interrupted


class SwitchHost(Protocol):
    """The manager as a switch sees it: its cycle lock and what that lock guards. These are
    the manager's own fields: a switch reads who runs, and changes it, only with the cycle
    lock held, so update() never sees half a switch."""

    dt: float
    timeouts: ManagerTimeouts
    last_refusal: str
    switch_count: int
    _cycle_lock: threading.Lock
    _stoppers: Stoppers
    _controllers: ControllerSet
    _state: ManagerState
    _active: ControllerPair | None
    _latched: bool
    _closed: bool
    _estop_serial: int                   # changes with every e-stop
    _requests: deque[tuple[bool, str]]   # e-stops requested, not yet applied

    def available_controllers(self) -> list[str]: ...

    def _running_adapter(self) -> ControllerAdapter | None: ...

    def _emit_changed(self) -> None: ...

    def _apply_requests(self) -> None: ...

    def _estop(self, to_failproof: bool, cause: str) -> None: ...


class Switcher:
    """The switcher thread and the one switch it runs at a time."""

    def __init__(self, manager: SwitchHost, name: str,
                 guard: Callable[[], str | None] | None) -> None:
        self._manager = manager
        # Why a switch into a controller must be refused now (e.g. drives not ready), or
        # None: asked when a switch is requested, from the requesting thread.
        self._guard = guard
        self._busy = threading.Lock()
        self._jobs: queue.SimpleQueue[tuple[ControllerPair, Future[SwitchResult]] | None] = \
            queue.SimpleQueue()
        self._thread = threading.Thread(target=self._run, daemon=True, name=f"{name}/switcher")
        self._thread.start()

    def request(self, name: str) -> Future[SwitchResult]:
        """ControllerManager.request_switch: refused at once, or queued for the thread."""
        m = self._manager
        future: Future[SwitchResult] = Future()
        pair = m._controllers.pairs.get(name)
        if pair is None:
            m.last_refusal = f"no controller {name!r}"
            log.warning("switch to %r: no such controller (available: %s)",
                        name, ", ".join(m.available_controllers()) or "none")
            future.set_result(SwitchResult.NOT_FOUND)
        elif m._closed:
            log.error("switch to %r refused: manager is shut down", name)
            future.set_result(SwitchResult.ERROR)
        elif (blocked := self.blocked()) is not None:
            m.last_refusal = blocked
            log.error("switch to %r refused: %s", name, blocked)
            future.set_result(SwitchResult.ERROR)
        elif not self._busy.acquire(blocking=False):
            m.last_refusal = "another switch is in progress"
            log.error("switch to %r refused: another switch is in progress", name)
            future.set_result(SwitchResult.ERROR)
        else:
            m.last_refusal = ""
            future.set_running_or_notify_cancel()
            self._jobs.put((pair, future))
        return future

    def blocked(self) -> str | None:
        """ControllerManager.switch_blocked (which says why a raising guard blocks)."""
        if self._manager._latched:
            return LATCHED
        return self._guard_reason()

    def _guard_reason(self) -> str | None:
        if self._guard is None:
            return None
        try:
            return self._guard()
        except Exception as exc:  # noqa: BLE001 - reported as the reason
            return f"switch guard failed: {exc!r}"

    def wait_idle(self, timeout: float) -> bool:
        """Wait until no switch is in progress; False when one still is after ``timeout``."""
        if not self._busy.acquire(timeout=timeout):
            return False
        self._busy.release()
        return True

    def close(self, timeout: float) -> list[str]:
        self._jobs.put(None)
        self._thread.join(timeout)
        return [self._thread.name] if self._thread.is_alive() else []

    def _run(self) -> None:
        while True:
            job = self._jobs.get()
            if job is None:
                return
            pair, future = job
            try:
                result = self._switch(pair)
            except Exception:  # a bug here must not leave the caller waiting
                log.exception("switch to %r failed unexpectedly", pair.controller.name)
                result = SwitchResult.ERROR
            finally:
                self._busy.release()
            future.set_result(result)

    def _switch(self, pair: ControllerPair) -> SwitchResult:
        m = self._manager
        new = pair.controller
        with m._cycle_lock:  # a consistent view of who runs, between two cycles
            if m._latched:
                log.error("switch to %r refused: %s", new.name, LATCHED)
                return SwitchResult.ERROR
            if m._state is ManagerState.OK and m._active is pair:
                return SwitchResult.RUNNING
            serial = m._estop_serial
            old = m._running_adapter()
            if old is not None:
                old.being_stopped = True  # this switch owns its stop from here on

        if old is not None and not old.pre_stop():
            return self._abort(old, f"switch: {old.failure}")

        deadline = time.monotonic() + m.timeouts.being_stopped
        while new.being_stopped:
            if time.monotonic() > deadline:
                return self._abort(old, f"switch: {new.name} still being stopped "
                                   f"after {m.timeouts.being_stopped:.1f} s")
            time.sleep(0.001)

        swap_state = old.get_swap_state() if old is not None else None
        if not new.swap(m.dt, swap_state):
            new.being_stopped = True  # its swap may have left half-initialized state
            m._stoppers.hand_over(new)
            return self._abort(old, f"switch: {new.failure}")

        with m._cycle_lock:
            # asked again at the commit: a drive may have faulted while the new controller
            # initialized (the switch then fails like any other, with an e-stop)
            blocked = self._guard_reason() if m._estop_serial == serial else None
            committed = (m._estop_serial == serial and not m._requests
                         and not m._closed and blocked is None)
            if committed:
                previous = m._state
                new.running = True
                m._active = pair
                m._state = ManagerState.OK
                m.switch_count += 1
                m._emit_changed()
            elif blocked is None:  # a requested e-stop may not have reached update() yet:
                m._apply_requests()  # the old one must stop running before its stop
        if blocked is not None:
            m.last_refusal = blocked
            new.being_stopped = True
            m._stoppers.hand_over(new)
            return self._abort(old, f"switch: {blocked}")
        if not committed:
            log.error("switch to %r interrupted by an emergency stop", new.name)
            new.being_stopped = True
            m._stoppers.hand_over(new)
            return self._finish_old(old, SwitchResult.ERROR)
        log.info("switched to %r (from %s)", new.name, previous.name)
        return self._finish_old(old, SwitchResult.SWITCHED)

    def _abort(self, old: ControllerAdapter | None, cause: str) -> SwitchResult:
        """A switch failed after the old controller was told to stop: e-stop, like rocoma.
        The e-stop is applied here, between two cycles, so the old controller no longer runs
        when its stop is handed over."""
        m = self._manager
        log.error("%s; emergency stop", cause)
        with m._cycle_lock:
            m._apply_requests()
            m._estop(False, cause)
        return self._finish_old(old, SwitchResult.ERROR)

    def _finish_old(self, old: ControllerAdapter | None, result: SwitchResult) -> SwitchResult:
        if old is not None:
            old.running = False
            self._manager._stoppers.hand_over(old)  # being_stopped was set when the switch began
        return result
