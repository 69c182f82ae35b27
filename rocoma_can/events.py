"""Manager notifications (rocoma's "notify other nodes via topic"), delivered off the cycle.

The update thread only puts events on a queue; one dispatcher thread calls the subscribers
and writes the log records of failures seen in the cycle, so neither a slow subscriber nor
log I/O can delay a control cycle.
"""
from __future__ import annotations

import enum
import logging
import queue
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass, field

log = logging.getLogger("rocoma_can.manager")


#: How the failproof stop of the control loop's own ending is worded (runtime/loop.py): the
#: flight recorder and the plot do not take it for a fault.
STOP_CAUSE = "loop stopping:"

#: why a switch is refused while the e-stop latch is set (switcher.py; ``clear`` lifts it)
LATCHED = "emergency stop not cleared"


class ManagerState(enum.IntEnum):
    FAILPROOF = 0
    EMERGENCY = 1
    OK = 2


class EventKind(enum.Enum):
    STATE_CHANGED = "state_changed"
    ACTIVE_CONTROLLER_CHANGED = "active_controller_changed"
    EMERGENCY_STOP = "emergency_stop"
    RECOVERY = "recovery"  # of the drives: started, done or failed (its cause says)
    #: an operator's request and its answer, as the surface that took it tells it (its
    #: cause: "SDO (node 100): switch to 'pd': SWITCHED"): the audit trail (audit.py)
    REQUEST = "request"


@dataclass(frozen=True)
class ManagerEvent:
    kind: EventKind
    state: ManagerState
    active_controller: str
    cause: str = ""
    time: float = field(default_factory=time.monotonic)
    #: the e-stop latch as this event left it: a recording reads the latch of every cycle
    #: from its events' (the latch's own rise, at an e-stop's request, comes a cycle or more
    #: before the e-stop takes effect; a clear is an event of its own)
    latched: bool = False


Subscriber = Callable[[ManagerEvent], None]


@dataclass(frozen=True)
class _LogRecord:
    level: int
    message: str
    exc: BaseException | None


class EventDispatcher:
    """One thread that runs subscribers and failure logging for the manager."""

    def __init__(self, name: str) -> None:
        self._queue: queue.SimpleQueue[_LogRecord | ManagerEvent | None] = queue.SimpleQueue()
        self._subscribers: list[Subscriber] = []
        self._lock = threading.Lock()  # guards the subscriber list, never taken in the cycle
        self._thread = threading.Thread(target=self._run, name=f"{name}/events", daemon=True)
        self._thread.start()

    def subscribe(self, callback: Subscriber) -> Callable[[], None]:
        with self._lock:
            self._subscribers.append(callback)

        def unsubscribe() -> None:
            with self._lock:
                if callback in self._subscribers:
                    self._subscribers.remove(callback)
        return unsubscribe

    def emit(self, event: ManagerEvent) -> None:
        """Non-blocking; safe from any thread, including the update thread."""
        self._queue.put(event)

    def log(self, level: int, message: str, exc: BaseException | None = None) -> None:
        """Log from the update thread without doing log I/O there."""
        self._queue.put(_LogRecord(level, message, exc))

    def close(self, timeout: float) -> bool:
        self._queue.put(None)
        self._thread.join(timeout)
        return not self._thread.is_alive()

    def _run(self) -> None:
        while True:
            item = self._queue.get()
            if item is None:
                return
            if isinstance(item, _LogRecord):
                exc_info = (type(item.exc), item.exc, item.exc.__traceback__) if item.exc else None
                log.log(item.level, "%s", item.message, exc_info=exc_info)
                continue
            with self._lock:
                subscribers = list(self._subscribers)
            for callback in subscribers:
                try:
                    callback(item)
                except Exception:  # a subscriber must not silence the others
                    log.exception("manager event subscriber %r raised", callback)
