"""The manager's threads that stop things off the cycle: controllers' stops, and torque-off
while an update() hangs.

Both exist so that nothing slow or stuck runs in the update thread: a controller's
``pre_stop`` + ``stop`` may take many cycles, and a hung ``advance`` cannot switch the drives
off from inside the call that hangs.
"""
from __future__ import annotations

import logging
import queue
import threading
import time
from collections.abc import Callable
from typing import Protocol

from .adapters import ControllerAdapter, Report


class Stoppers:
    """Threads that run pre_stop + stop. One per controller, so a slow stop never delays
    another controller's (a controller has at most one stop in flight)."""

    def __init__(self, name: str) -> None:
        self._name = name
        self._queue: queue.SimpleQueue[ControllerAdapter | None] = queue.SimpleQueue()
        self._threads: list[threading.Thread] = []

    def grow_to(self, n: int) -> None:
        while len(self._threads) < n:
            t = threading.Thread(target=self._run, daemon=True,
                                 name=f"{self._name}/stopper{len(self._threads)}")
            t.start()
            self._threads.append(t)

    def hand_over(self, adapter: ControllerAdapter) -> None:
        """Non-blocking; the caller has set adapter.being_stopped."""
        self._queue.put(adapter)

    def close(self, timeout: float) -> list[str]:
        for _ in self._threads:
            self._queue.put(None)
        deadline = time.monotonic() + timeout
        for t in self._threads:
            t.join(max(0.0, deadline - time.monotonic()))
        return [t.name for t in self._threads if t.is_alive()]

    def _run(self) -> None:
        while True:
            adapter = self._queue.get()
            if adapter is None:
                return
            try:
                adapter.stop()
            finally:
                adapter.being_stopped = False


class Watched(Protocol):
    """The manager as its watchdog sees it. Plain fields, no calls and no lock: the update
    thread that writes ``_update_started`` is the one that may be stuck."""

    _update_started: float  # monotonic start of the update() in progress, else 0
    hang_calls: int         # on_hang calls; update() compares it to know a hang was acted on


class Watchdog:
    """Torque off through on_hang while an update() is stuck (a hung advance)."""

    def __init__(self, watched: Watched, name: str, hang: float, dt: float,
                 on_hang: Callable[[], None] | None, log: Report) -> None:
        self._watched = watched
        self._hang = hang
        self._dt = dt
        self._on_hang = on_hang
        self._log = log
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, daemon=True, name=f"{name}/watchdog")
        self._thread.start()

    def close(self, timeout: float) -> list[str]:
        self._stop.set()
        self._thread.join(timeout)
        return [self._thread.name] if self._thread.is_alive() else []

    def _run(self) -> None:
        watched, hang = self._watched, self._hang
        reported = 0.0
        while not self._stop.wait(hang / 4):
            started = watched._update_started
            while started and started == watched._update_started \
                    and time.monotonic() - started > hang:
                if reported != started:
                    reported = started
                    self._log(logging.ERROR, f"update() stuck for more than "
                              f"{hang * 1e3:.1f} ms: commanding torque-off", None)
                if self._on_hang is not None:
                    watched.hang_calls += 1
                    try:
                        self._on_hang()
                    except Exception as exc:  # keep trying: this is the last line
                        self._log(logging.ERROR, f"on_hang raised {exc!r}", exc)
                if self._stop.wait(self._dt):
                    return
