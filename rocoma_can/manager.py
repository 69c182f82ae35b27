"""The controller manager: run-time switching over two safety layers (rocoma, made exact).

Threads and who calls what (rocoma's timestep tables, made exact; docs/controllers.md):

* update thread (whoever calls ``update()``): advances exactly one layer per call. A failure
  (advance False or raising, check_state or limit_command False) or a pending e-stop request
  is handled inside that same call: the emergency controller's ``initialize_fast`` and first
  ``advance`` run there (or the failproof's ``advance``), so the command written in a cycle
  never comes from a controller that failed in it. Nothing slow runs here.
* stopper threads: ``pre_stop`` + ``stop`` of controllers handed over to be stopped. A
  controller is "being stopped" from the hand-over until its ``stop`` returns; while it is,
  it is never advanced, never used as an emergency layer and never swapped in.
* switcher thread: old ``pre_stop`` (the old keeps advancing), wait until the new one is not
  being stopped, ``old.get_swap_state()``, ``new.swap(dt, state)``, then commit under the
  cycle lock only if no e-stop happened meanwhile; the old one's ``stop`` follows on a
  stopper thread. A failed pre_stop or swap e-stops, as rocoma does: the old controller was
  already told to stop and is no longer trusted to run on.
* event thread: subscriber callbacks and the log records of failures seen in the cycle.

The cycle lock is held by ``update()`` and by the switcher's commit only; the commit is a few
assignments, so the update thread never waits on slow work.

This module is the cycle and its e-stops: update() and the fall failure -> emergency ->
failproof read top to bottom here. The threads it starts live apart, each in its own
module: the switch protocol in ``switcher.py``, the stopper threads and the hang watchdog
in ``stopper.py``.
"""
from __future__ import annotations

import itertools
import logging
import threading
import time
from collections import deque
from collections.abc import Callable
from concurrent.futures import Future
from typing import Any

from .adapters import ControllerAdapter, ControllerPair, FailproofControllerAdapter, StateCheck
from .controller_set import ControllerSet
from .events import EventDispatcher, EventKind, ManagerEvent, ManagerState, Subscriber
from .interfaces import Controller, EmergencyController, FailproofController
from .manager_timing import ManagerTimeouts, TimingSupervision
from .stopper import Stoppers, Watchdog
from .switcher import Switcher
from .switcher import SwitchResult as SwitchResult  # re-exported: imported from here

log = logging.getLogger("rocoma_can.manager")


#: The least update() waits for the cycle lock with timing supervision (see __init__)
LOCK_WAIT_MIN = 0.05


class ControllerManager:
    """Runs one controller at a time over an emergency and a failproof layer."""

    def __init__(self, failproof: FailproofController, dt: float, state: Any = None,
                 command: Any = None, *, estop_must_be_cleared: bool = False,
                 check_state: StateCheck | None = None,
                 limit_command: StateCheck | None = None,
                 reset_command: Callable[[Any], None] | None = None,
                 switch_guard: Callable[[], str | None] | None = None,
                 timeouts: ManagerTimeouts | None = None,
                 timing: TimingSupervision | None = TimingSupervision(),
                 on_hang: Callable[[], None] | None = None, name: str = "rocoma") -> None:
        if not isinstance(failproof, FailproofController):
            raise TypeError(f"failproof must be a FailproofController, got {failproof!r}")
        if not dt > 0:
            raise ValueError(f"dt must be a positive time step in seconds, got {dt!r}")
        self.name = name
        self.dt = float(dt)
        self.state_object = state
        self.command_object = command
        self.timeouts = timeouts or ManagerTimeouts()
        self._must_clear = estop_must_be_cleared
        self._check_state = check_state
        self._limit_command = limit_command
        # On every fall to a lower layer, before that layer writes the command: a smart stop
        # must not inherit the failed controller's targets (a NaN in a field the emergency
        # controller does not write would fail it too and skip the smart stop).
        self._reset_command = reset_command
        self.last_refusal = ""  # why the last switch request was refused ("" = it was not)
        self.switch_count = 0   # switches committed: the hardware arms the drives ready then
        self.timing = timing
        self.hang_calls = 0       # how often on_hang ran while update() was stuck
        self._update_started = 0.0  # monotonic start of the update() in progress, else 0
        # The longest update() waits for the cycle lock (the hang limit): the switcher holds
        # it around user code (an aborted switch runs the emergency controller's
        # initialize_fast), and a callback that never returns must not stop the cycle.
        # Without timing supervision (simulated time, tests) nothing is judged on the wall
        # clock: the switch timeout bounds the wait. With it, the hang limit, at least
        # LOCK_WAIT_MIN: the switcher is no real-time thread, and a routine commit preempted
        # for a few ms must not stop the robot.
        if timing is not None and timing.hang > 0:
            self._lock_wait = max(timing.hang * self.dt, LOCK_WAIT_MIN)
        else:
            self._lock_wait = self.timeouts.switch
        self.lock_timeouts = 0  # update() calls that could not take the cycle lock
        self._locked_out = False  # the last update() could not (its failproof stop queued)

        self._events = EventDispatcher(name)
        # Wake-ups of other threads (events, log records, stop hand-overs) that an update()
        # produced, held until post_cycle(): see update().
        self._held: deque[tuple[Callable[..., None], tuple[Any, ...]]] = deque()
        self._in_update = False
        self._deferring = False  # a caller calls post_cycle (the loop does): hold till then
        self._failproof = FailproofControllerAdapter(failproof, self._log)
        self._controllers = ControllerSet(self._failproof, self.dt, state, command, self._log,
                                          check_state, limit_command, timing)
        self._controllers.attach(failproof)
        if not self._failproof.create(self.dt):
            self._events.close(self.timeouts.shutdown)
            raise RuntimeError(f"failproof controller {failproof.name!r} could not be created: "
                               f"{self._failproof.failure}")

        self._state = ManagerState.FAILPROOF
        self._active: ControllerPair | None = None
        self._cycle_lock = threading.Lock()
        self._requests: deque[tuple[bool, str]] = deque()  # (failproof?, cause), any thread
        self._estop_counter = itertools.count(1)
        self._estop_serial = 0   # changes with every e-stop; a switch commits only if unchanged
        self._requested_cause = ""  # the last requested e-stop's (estop_requested)
        self._latched = estop_must_be_cleared  # like an e-stop button after power-on
        self._closed = False
        self.cycle_count = 0
        self.internal_errors = 0  # update() steps that raised inside the manager itself

        self._stoppers = Stoppers(name)
        self._switcher = Switcher(self, name, switch_guard)
        self._watchdog: Watchdog | None = None
        if timing is not None and timing.hang > 0:
            self._watchdog = Watchdog(self, name, timing.hang * self.dt, self.dt, on_hang,
                                      self._events.log)

    # --- set-up ---------------------------------------------------------------------------
    def add_controller(self, controller: Controller,
                       emergency: EmergencyController | None = None) -> bool:
        """Create and register a controller, paired with an optional emergency controller.

        An emergency controller whose name is already registered is dropped with a warning
        and the registered instance is shared (rocoma's behaviour).
        """
        if isinstance(controller, EmergencyController) or not isinstance(controller, Controller):
            raise TypeError(f"{controller!r} is not a switchable Controller "
                            "(emergency controllers go in add_controller(..., emergency=...))")
        if emergency is not None and not isinstance(emergency, EmergencyController):
            raise TypeError(f"{emergency!r} is not an EmergencyController")
        if not self._controllers.add(controller, emergency, self._closed):
            return False
        self._stoppers.grow_to(len(self._controllers))
        return True

    # --- the cycle ------------------------------------------------------------------------
    def update(self) -> ManagerState:
        """One control cycle; returns the layer that wrote this cycle's command.

        It wakes no other thread while it runs: the events, log records and stop hand-overs
        it produces (an e-stop makes all three) are held to its end, and, once the caller
        has called ``post_cycle`` (the loop does, after the cycle's frames are written),
        until post_cycle. A thread woken earlier would take the GIL at the next point that
        releases it (a numpy call, a socket send) and run its work (the failed controller's
        stop, subscribers, logging) before this cycle's command is out."""
        if not self._cycle_lock.acquire(timeout=self._lock_wait):
            return self._lock_timed_out()
        try:
            self._locked_out = False
            if self._held:  # a caller that stopped calling post_cycle
                self._wake()
            self._update_started = time.monotonic()
            self._in_update = True
            try:
                return self._update()
            except Exception as exc:  # a bug in the manager itself: never kill the loop
                return self._internal_failure(exc)
            finally:
                self._in_update = False
                self._update_started = 0.0
                if self._held and not self._deferring:
                    self._wake()
        finally:
            self._cycle_lock.release()

    def _lock_timed_out(self) -> ManagerState:
        """update() waited the hang limit for the cycle lock: the switcher holds it in a user
        callback that does not return. Without the lock nothing of the manager's state may
        be touched, so this cycle is the failproof layer's (the caller writes torque-off
        frames for FAILPROOF) and a failproof stop is queued, once, for the update() that
        gets the lock: the manager never comes back with the controller that was running."""
        self.lock_timeouts += 1
        if not self._locked_out:
            self._locked_out = True
            self._request(True, f"update() waited {self._lock_wait * 1e3:.0f} ms for the "
                                "cycle lock (a switch stuck in a callback): torque-off")
        return ManagerState.FAILPROOF

    def post_cycle(self) -> None:
        """After the cycle's write: wake the threads the last update() has work for (the
        stopper of a failed controller, event delivery). From the thread that calls update;
        from the first call on, update() leaves that to it."""
        self._deferring = True
        self._wake()

    def _wake(self) -> None:
        held = self._held
        while held:  # the usual cycle holds nothing: no exception raised per cycle
            try:
                fn, args = held.popleft()  # atomic: a second caller never gets an item twice
            except IndexError:  # another caller took the last one meanwhile
                return
            try:
                fn(*args)
            except Exception:  # noqa: BLE001 - a queue put; nothing may stop the others
                self.internal_errors += 1

    def _internal_failure(self, exc: Exception) -> ManagerState:
        """The last resort of update(): the failproof layer commands, latched if must-clear.

        Adapters already turn every controller failure into False, so this only runs when
        the manager's own step failed (e.g. no thread could be started for a stopper): the
        state is forced to FAILPROOF and the call returns normally, so the hardware still
        writes its torque-off frames this cycle.
        """
        self.internal_errors += 1
        previous = self._state
        self._state = ManagerState.FAILPROOF
        if self._must_clear:
            self._latched = True
        self._failproof.advance(self.dt)
        try:
            self._log(logging.CRITICAL, f"manager update failed: {exc!r}", exc)
            if previous is not ManagerState.FAILPROOF:
                self._emit(EventKind.EMERGENCY_STOP, f"manager error: {exc!r}")
                self._emit_changed()
        except Exception:  # noqa: BLE001 - counted above; the state is safe already
            pass
        return self._state

    def _update(self) -> ManagerState:
        self.cycle_count += 1
        hangs = self.hang_calls  # before the requests: a stall in one is a hang too
        if self._requests:
            self._apply_requests()
        dt = self.dt
        while True:  # a failure falls through to the next layer within this call
            state = self._state
            if state is ManagerState.OK:
                pair = self._active
                assert pair is not None  # OK and EMERGENCY always have an active pair
                adapter = pair.controller
                advanced = adapter.advance(dt)
                if self.hang_calls != hangs:
                    # The watchdog already switched the drives off while this advance hung
                    # (even one that returned True within a budget of its own): nothing is
                    # left for an emergency controller to stop smartly, nor to go on with.
                    failure = adapter.failure if not advanced else \
                        f"{adapter.name}: advance hung past the hang limit"
                    self._estop(True, f"{failure}; on_hang commanded torque-off")
                elif advanced:
                    break
                else:
                    self._estop(False, adapter.failure)
            elif state is ManagerState.EMERGENCY:
                pair = self._active
                assert pair is not None and pair.emergency is not None
                advanced = pair.emergency.advance(dt)
                if advanced and self.hang_calls == hangs:
                    break
                self._estop(True, pair.emergency.failure if not advanced else
                            f"{pair.emergency.name}: advance hung past the hang limit; "
                            "on_hang commanded torque-off")
            else:
                self._failproof.advance(dt)
                break
        return self._state

    def _estop(self, to_failproof: bool, cause: str) -> None:
        """Fall one layer (or to failproof). Update thread only, cycle lock held.

        The emergency controller's initialize_fast runs here; its first advance follows in
        the caller's loop, in the same update call.
        """
        self._estop_serial = next(self._estop_counter)
        if self._must_clear:
            self._latched = True
        previous = self._state
        pair = self._active
        if self._reset_command is not None and previous is not ManagerState.FAILPROOF:
            try:
                self._reset_command(self.command_object)
            except Exception as exc:  # noqa: BLE001 - the safe way on is the failproof layer
                self.internal_errors += 1
                to_failproof = True
                self._log(logging.CRITICAL, f"reset_command failed: {exc!r}", exc)
        if previous is ManagerState.OK:
            assert pair is not None
            self._stop_in_background(pair.controller)
            emcy = pair.emergency
            if (not to_failproof and emcy is not None and not emcy.being_stopped
                    and emcy.initialize_fast(self.dt)):
                emcy.running = True
                self._state = ManagerState.EMERGENCY
            else:
                self._state = ManagerState.FAILPROOF
        elif previous is ManagerState.EMERGENCY:
            assert pair is not None and pair.emergency is not None
            self._stop_in_background(pair.emergency)
            self._state = ManagerState.FAILPROOF
        self._emit(EventKind.EMERGENCY_STOP, cause)
        if self._state is not previous:
            self._emit_changed()

    def _apply_requests(self) -> None:
        """E-stops requested from any thread; cycle lock held."""
        while self._requests:
            to_failproof, cause = self._requests.popleft()
            self._estop(to_failproof, cause)

    def _stop_in_background(self, adapter: ControllerAdapter) -> None:
        adapter.running = False
        if not adapter.being_stopped:  # else its stop is owned by a switch in progress
            adapter.being_stopped = True
            if self._in_update:
                self._held.append((self._stoppers.hand_over, (adapter,)))
            else:
                self._stoppers.hand_over(adapter)

    # --- e-stop requests (any thread) -----------------------------------------------------
    def emergency_stop(self, cause: str = "request") -> None:
        """OK → EMERGENCY (or FAILPROOF), EMERGENCY → FAILPROOF; effective by the next update."""
        self._request(False, cause)

    def failproof_stop(self, cause: str = "failproof request") -> None:
        """Straight to the failproof layer; effective by the next update."""
        self._request(True, cause)

    def _request(self, to_failproof: bool, cause: str) -> None:
        if self._must_clear:
            self._latched = True
        self._requested_cause = cause
        # queued before the serial changes: a switch that sees the new serial finds the
        # request to apply (the other order let it stop a controller still running)
        self._requests.append((to_failproof, cause))
        self._estop_serial = next(self._estop_counter)  # a switch under way will not commit

    def clear_emergency_stop(self) -> bool:
        """Unlatch (with estop_must_be_cleared): switching is allowed again."""
        was = self._latched
        self._latched = False
        if was:
            self._emit(EventKind.STATE_CHANGED, "emergency stop cleared")
        return True

    # --- switching ------------------------------------------------------------------------
    def request_switch(self, name: str) -> Future[SwitchResult]:
        """Start a switch on the switcher thread; the future resolves to a SwitchResult."""
        return self._switcher.request(name)

    def switch_blocked(self) -> str | None:
        """Why a switch would be refused now, or None: the e-stop latch, then the switch
        guard's reason (a guard that raises blocks too: it could not say all is well)."""
        return self._switcher.blocked()

    def switch_controller(self, name: str, timeout: float | None = None) -> SwitchResult:
        """Switch and wait for the result (at most ``timeout``, default timeouts.switch)."""
        future = self.request_switch(name)
        wait = self.timeouts.switch if timeout is None else timeout
        try:
            return future.result(timeout=wait)
        except TimeoutError:
            log.error("switch to %r: no result within %.1f s; it goes on in the background",
                      name, wait)
            return SwitchResult.ERROR

    def _running_adapter(self) -> ControllerAdapter | None:
        pair = self._active
        if pair is None or self._state is ManagerState.FAILPROOF:
            return None
        return pair.controller if self._state is ManagerState.OK else pair.emergency

    # --- what others read -----------------------------------------------------------------
    @property
    def state(self) -> ManagerState:
        return self._state

    @property
    def estop_latched(self) -> bool:
        return self._latched

    @property
    def estop_requested(self) -> str:
        """The cause of the last e-stop (or failproof stop) requested from another thread,
        as soon as it is requested: the event saying it comes with the update that acts
        on it ("" before any)."""
        return self._requested_cause

    @property
    def active_controller_name(self) -> str:
        adapter = self._running_adapter()
        return adapter.name if adapter is not None else self._failproof.name

    def available_controllers(self) -> list[str]:
        return sorted(self._controllers.pairs)

    def notify_recovery(self, cause: str) -> None:
        """Tell the subscribers of a recovery of the drives (``cause``: "started", "done:
        ...", "failed: ..."): the hardware recovers them, the manager only hears of it. From
        any thread, the cycle's included: it only queues the event."""
        self._emit(EventKind.RECOVERY, cause)

    def notify_request(self, text: str) -> None:
        """Tell the subscribers of an operator's request and how it was answered: ``text``
        says who (the surface), what and the answer ("SDO (node 100): clear: the e-stop
        latch is cleared"). The request surfaces call it (node/server.py, remote.py);
        stops need not: their e-stop events name them in the cause. From any thread, the
        cycle's included: it only queues the event."""
        self._emit(EventKind.REQUEST, text)

    def subscribe(self, callback: Subscriber) -> Callable[[], None]:
        """Call ``callback(event)`` on the event thread; returns the unsubscribe function."""
        return self._events.subscribe(callback)

    def _emit(self, kind: EventKind, cause: str = "") -> None:
        event = ManagerEvent(kind, self._state, self.active_controller_name, cause,
                             latched=self._latched)
        if self._in_update or self._held:  # behind what this cycle holds, in order
            self._held.append((self._events.emit, (event,)))
        else:
            self._events.emit(event)

    def _log(self, level: int, message: str, exc: BaseException | None = None) -> None:
        """Log without I/O, and from update() without waking the event thread (update)."""
        if self._in_update or self._held:
            self._held.append((self._events.log, (level, message, exc)))
        else:
            self._events.log(level, message, exc)

    def _emit_changed(self) -> None:
        self._emit(EventKind.STATE_CHANGED)
        self._emit(EventKind.ACTIVE_CONTROLLER_CHANGED)

    def statistics(self) -> dict[str, dict[str, dict[str, float]]]:
        """Call durations per controller and call (count, mean, p99, max, last in µs)."""
        return {name: {call: st.summary() for call, st in adapter.stats.items() if st.count}
                for name, adapter in self.adapters().items()}

    def adapters(self) -> dict[str, ControllerAdapter | FailproofControllerAdapter]:
        """Every registered controller's adapter by name (flags and call statistics)."""
        return self._controllers.adapters()

    # --- shutdown -------------------------------------------------------------------------
    def shutdown(self) -> bool:
        """Failproof, stop and clean up every controller, join every thread (all bounded).

        Returns False when something did not finish in time (it is logged by name).
        """
        if self._closed:
            return True
        self._closed = True
        limit = self.timeouts.shutdown
        ok = True
        if self._cycle_lock.acquire(timeout=limit):  # no update() holds anything back
            try:
                self._wake()
            finally:
                self._cycle_lock.release()
        if not self._switcher.wait_idle(limit):
            log.error("shutdown: a switch did not finish within %.1f s", limit)
            ok = False
        if self._cycle_lock.acquire(timeout=limit):
            try:
                if self._state is not ManagerState.FAILPROOF:
                    self._estop(True, "shutdown")
                self._failproof.advance(self.dt)
            finally:
                self._cycle_lock.release()
        else:  # a switch stuck in a callback holds it: update() returns FAILPROOF anyway
            log.error("shutdown: the cycle lock was not free within %.1f s (a switch stuck "
                      "in a controller callback)", limit)
            ok = False
        ok = self._controllers.finish(limit) and ok
        switcher_stuck = self._switcher.close(limit)
        watchdog_stuck = self._watchdog.close(limit) if self._watchdog is not None else []
        stuck = self._stoppers.close(limit) + switcher_stuck + watchdog_stuck
        if not self._events.close(limit):
            stuck.append(f"{self.name}/events")
        for thread_name in stuck:
            log.error("shutdown: thread %s did not end within %.1f s", thread_name, limit)
        return ok and not stuck

    def __enter__(self) -> ControllerManager:
        return self

    def __exit__(self, *exc: object) -> None:
        self.shutdown()
