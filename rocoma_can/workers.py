"""Worker threads owned by one controller (rocoma's worker extension).

A controller that needs work beside its control cycle (publishing, planning, logging) asks its
WorkerManager for a worker instead of starting a bare thread, so the manager can cancel every
worker of a controller when it is cleaned up and no thread outlives its controller unnoticed.

Timing: periodic workers run on absolute monotonic deadlines (start + k * period), so the
callback's own run time does not make the rate drift; a deadline already missed is skipped
rather than caught up in a burst, and counted in ``WorkerHandle.missed_deadlines``.
Cancelling sets an Event the worker sleeps on, so a sleeping worker ends at once; every join
is bounded, and a worker stuck in its callback is reported instead of waited on forever.
"""
from __future__ import annotations

import logging
import math
import os
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass

log = logging.getLogger(__name__)

#: Linux SCHED_FIFO priorities are 1..99; 0 means "leave the thread's scheduling alone".
MAX_PRIORITY = 99


@dataclass(frozen=True)
class WorkerEvent:
    """What a worker callback learns about the current iteration."""
    iteration: int   # 0 for the first call after (re)start
    time: float      # time.monotonic() when the callback was called
    name: str        # the worker's name (without the owner prefix)


@dataclass(frozen=True)
class WorkerOptions:
    """How to run a worker (rocoma's roco::WorkerOptions).

    ``callback`` returns True to keep running; False (or raising) ends the worker; None
    (a callback that forgot to return) ends it with a warning.
    ``frequency`` in Hz; 0 runs the callback once. ``priority`` > 0 asks for SCHED_FIFO at that
    priority for the worker's thread (needs CAP_SYS_NICE; a warning is logged otherwise).
    """
    name: str
    callback: Callable[[WorkerEvent], bool | None]
    frequency: float = 0.0
    priority: int = 0
    autostart: bool = False

    def __post_init__(self) -> None:
        if not isinstance(self.name, str) or not self.name or "/" in self.name:
            raise ValueError(f"WorkerOptions.name must be a non-empty string without '/', "
                             f"got {self.name!r}")
        if not callable(self.callback):
            raise ValueError(f"WorkerOptions.callback of worker {self.name!r} must be callable, "
                             f"got {self.callback!r}")
        if (isinstance(self.frequency, bool) or not isinstance(self.frequency, (int, float))
                or not math.isfinite(self.frequency) or self.frequency < 0):
            raise ValueError(f"WorkerOptions.frequency of worker {self.name!r} must be a finite "
                             f"number >= 0 (Hz; 0 = run once), got {self.frequency!r}")
        if (isinstance(self.priority, bool) or not isinstance(self.priority, int)
                or not 0 <= self.priority <= MAX_PRIORITY):
            raise ValueError(f"WorkerOptions.priority of worker {self.name!r} must be an int in "
                             f"0..{MAX_PRIORITY} (0 = normal scheduling), got {self.priority!r}")
        if not isinstance(self.autostart, bool):
            raise ValueError(f"WorkerOptions.autostart of worker {self.name!r} must be a bool, "
                             f"got {self.autostart!r}")


class WorkerHandle:
    """One worker: its options and, while running, its thread."""

    def __init__(self, owner_name: str, options: WorkerOptions) -> None:
        self.options = options
        self.thread_name = f"{owner_name}/{options.name}"
        self._thread: threading.Thread | None = None
        self._cancel = threading.Event()
        self.missed_deadlines = 0
        #: True once SCHED_FIFO was applied, False if it was asked for and refused, None if
        #: not asked for (priority 0) or the thread has not got that far yet.
        self.realtime: bool | None = None

    @property
    def name(self) -> str:
        return self.options.name

    @property
    def is_running(self) -> bool:
        thread = self._thread
        return thread is not None and thread.is_alive()

    def __repr__(self) -> str:
        return f"WorkerHandle({self.thread_name!r}, running={self.is_running})"

    def _start(self) -> None:
        # A fresh Event per run: a cancel aimed at the previous run must not end this one.
        self._cancel = threading.Event()
        self.missed_deadlines = 0
        self.realtime = None
        # Daemon so that a callback stuck beyond every timeout cannot keep the process alive;
        # normal ends are joined by cancel_worker/cancel_all.
        self._thread = threading.Thread(target=self._run, args=(self._cancel,),
                                        name=self.thread_name, daemon=True)
        self._thread.start()

    def _run(self, cancel: threading.Event) -> None:
        if self.options.priority > 0:
            self._apply_priority()
        frequency = self.options.frequency
        period = 1.0 / frequency if frequency > 0 else 0.0
        start = time.monotonic()
        iteration = 0
        while not cancel.is_set():
            now = time.monotonic()
            try:
                keep_going = self.options.callback(WorkerEvent(iteration, now, self.name))
            except Exception:
                log.exception("worker %r: callback raised; the worker ends", self.thread_name)
                return
            if period == 0.0:
                return
            if not keep_going:
                if keep_going is None:
                    log.warning("worker %r: callback returned None; the worker ends "
                                "(return True to keep it running)", self.thread_name)
                return
            iteration += 1
            deadline = start + iteration * period
            now = time.monotonic()
            if now > deadline:
                # Skip the deadlines already missed (no catch-up burst), staying on the grid.
                missed = math.ceil((now - deadline) / period)
                self.missed_deadlines += missed
                start += missed * period
                deadline += missed * period
            cancel.wait(deadline - now)

    def _apply_priority(self) -> None:
        priority = self.options.priority
        setscheduler = getattr(os, "sched_setscheduler", None)
        fifo = getattr(os, "SCHED_FIFO", None)
        if setscheduler is None or fifo is None:
            self.realtime = False
            log.warning("worker %r: priority %d asks for SCHED_FIFO, which this platform does "
                        "not offer; running with normal scheduling", self.thread_name, priority)
            return
        try:
            setscheduler(threading.get_native_id(), fifo, os.sched_param(priority))
        except OSError as exc:  # PermissionError without CAP_SYS_NICE / RLIMIT_RTPRIO
            self.realtime = False
            log.warning("worker %r: could not set SCHED_FIFO priority %d (%s); running with "
                        "normal scheduling (run as root or grant CAP_SYS_NICE / rtprio)",
                        self.thread_name, priority, exc)
            return
        self.realtime = True


HandleOrName = WorkerHandle | str


class WorkerManager:
    """The workers of one controller, named ``f"{owner}/{worker}"``."""

    def __init__(self, owner_name: str) -> None:
        self.owner_name = owner_name
        self._workers: dict[str, WorkerHandle] = {}
        self._lock = threading.Lock()

    def add_worker(self, options: WorkerOptions) -> WorkerHandle:
        """Register a worker (and start it when ``options.autostart``).

        A name may be reused once its previous worker has ended; reusing the name of a
        worker that is still running is a ValueError.
        """
        if not isinstance(options, WorkerOptions):
            raise TypeError(f"add_worker expects WorkerOptions, got {type(options).__name__}")
        handle = WorkerHandle(self.owner_name, options)
        with self._lock:
            previous = self._workers.get(options.name)
            if previous is not None and previous.is_running:
                raise ValueError(f"worker {previous.thread_name!r} is already running; cancel "
                                 "it before adding another worker with that name")
            self._workers[options.name] = handle
            if options.autostart:
                handle._start()
        return handle

    def start_worker(self, handle_or_name: HandleOrName) -> bool:
        """Start a registered worker (again, if it has ended); False if unknown or running."""
        with self._lock:
            handle = self._find(handle_or_name, "start")
            if handle is None:
                return False
            if handle.is_running:
                log.warning("worker %r is already running", handle.thread_name)
                return False
            handle._start()
        return True

    def cancel_worker(self, handle_or_name: HandleOrName, wait: bool = True,
                      timeout: float = 1.0) -> bool:
        """Ask a worker to end; with ``wait``, join it for at most ``timeout`` seconds.

        True when the worker has ended (or was not running), or, without ``wait``, when
        the request was made. False for an unknown worker or one that did not end in time.
        """
        _check_timeout(timeout)
        with self._lock:
            handle = self._find(handle_or_name, "cancel")
            if handle is None:
                return False
            handle._cancel.set()
        return not wait or _join(handle, time.monotonic() + timeout)

    def cancel_all(self, wait: bool = True, timeout: float = 1.0) -> bool:
        """Cancel every worker; joins share one ``timeout``. True if all have ended."""
        _check_timeout(timeout)
        with self._lock:
            handles = list(self._workers.values())
            for handle in handles:
                handle._cancel.set()
        if not wait:
            return True
        deadline = time.monotonic() + timeout
        # Join every worker even after one timed out, so each straggler gets reported.
        return all([_join(handle, deadline) for handle in handles])

    @property
    def active_workers(self) -> list[str]:
        """Names of the workers whose thread is running, sorted."""
        with self._lock:
            return sorted(name for name, h in self._workers.items() if h.is_running)

    def _find(self, handle_or_name: HandleOrName, action: str) -> WorkerHandle | None:
        if isinstance(handle_or_name, WorkerHandle):
            name = handle_or_name.name
        elif isinstance(handle_or_name, str):
            name = handle_or_name
        else:
            raise TypeError(f"{action}_worker expects a WorkerHandle or a worker name, "
                            f"got {type(handle_or_name).__name__}")
        handle = self._workers.get(name)
        if handle is None or (isinstance(handle_or_name, WorkerHandle)
                              and handle is not handle_or_name):
            log.warning("cannot %s worker %r: not registered with %r (known: %s)", action,
                        name, self.owner_name, ", ".join(sorted(self._workers)) or "none")
            return None
        return handle


def _check_timeout(timeout: float) -> None:
    if isinstance(timeout, bool) or not isinstance(timeout, (int, float)) \
            or not timeout >= 0 or not math.isfinite(timeout):
        raise ValueError(f"timeout must be a finite number of seconds >= 0, got {timeout!r}")


def _join(handle: WorkerHandle, deadline: float) -> bool:
    thread = handle._thread
    if thread is None or thread is threading.current_thread():
        # Never started, or a worker cancelling itself: it ends when its callback returns.
        return True
    thread.join(max(0.0, deadline - time.monotonic()))
    if thread.is_alive():
        log.error("worker %r did not end within its timeout; it is left running as a daemon "
                  "thread (its callback does not return)", handle.thread_name)
        return False
    return True
