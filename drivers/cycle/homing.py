"""Homing (CiA 402 mode 6) of one drive while the manager keeps the others under control.

Homing is a service, not a controller: ``CanopenHardware.home`` queues a request and the
cycle runs it. For the drive being homed, the cycle sends mode 6 and the enable sequence
(enable.py), then raises controlword bit 4 ("homing operation start") and keeps it up until
the drive reports statusword bit 12 + bit 10 (homing attained, target reached) or bit 13
(homing error), or the time is up. A bit 12 already set when homing starts (left over
from the previous mode, or from an earlier homing) counts only once the drive has shown it
low: a drive still answering the start edge late is not taken as homed. The drive's own
homing method (0x6098, from the config at bring-up or as commissioned) and speeds move it.
Every other drive stays with the active controller; the homed drive's command from it is
ignored meanwhile.

Afterwards the drive's position reference has changed, so it stays torque-off until the
next switch (like a drive that became ready after one: the controller never saw it). An
e-stop, a fault of the drive or leaving operation enabled ends homing as failed; the
failproof path is untouched (FAILPROOF sends torque-off to every drive, homing or not).
"""
from __future__ import annotations

import collections
import enum
import threading
from concurrent.futures import Future

from ...errors import HomingFailed
from ..bringup.drive_bringup import BringupPhase
from ..files.capabilities import DriveCapabilities
from ..plan.pdo_layout import DriveLayout
from ..protocol import cia402
from .drive_table import DriveEntry
from .supervision import FaultEvent

HOMING_MODE = int(cia402.Mode.HOMING)
CW_HOMING_START = int(cia402.Controlword.ENABLE_OPERATION) | (1 << 4)
SW_HOMING_ATTAINED = 1 << 12
SW_HOMING_ERROR = 1 << 13
#: cycles with bit 4 up before the statusword is judged: a drive clears "attained" when it
#: starts, and answers the edge a cycle or two later
SETTLE_CYCLES = 3


class HomingPhase(enum.Enum):
    REQUESTED = "requested"
    ENABLING = "enabling"
    HOMING = "homing"


class HomingJob:
    """One drive's homing; ``step`` is called by the cycle for that drive."""

    def __init__(self, index: int, name: str, timeout: float,
                 future: Future[str]) -> None:
        self.index = index
        self.name = name
        self.timeout = timeout
        self.future = future
        self.phase = HomingPhase.REQUESTED
        self.deadline: float | None = None
        self._cycles = 0
        # statusword bit 12 before the start edge: set (left over from the previous mode or
        # an earlier homing), a set bit 12 counts only after it has been seen low
        self._stale_attained: bool | None = None
        self._seen_in_progress = False

    def step(self, enabled: bool, statusword: int, now: float) -> int | None:
        """This cycle's controlword once the drive is enabled (None while the enable sequence
        still runs); resolves the future when homing ends."""
        if self.deadline is None:
            self.deadline = now + self.timeout
        if now > self.deadline:
            self.fail(f"not homed within {self.timeout:g} s")
            return None
        if not enabled:
            if self.phase == HomingPhase.HOMING:
                self.fail("left operation enabled while homing")
            self.phase = HomingPhase.ENABLING
            return None
        if self.phase != HomingPhase.HOMING:  # the start edge goes out now
            self.phase = HomingPhase.HOMING
            self._stale_attained = bool(statusword & SW_HOMING_ATTAINED)
        self._cycles += 1
        if not statusword & SW_HOMING_ATTAINED:
            self._seen_in_progress = True
        if self._cycles > SETTLE_CYCLES:
            if statusword & SW_HOMING_ERROR:
                self.fail("the drive reports a homing error (statusword bit 13)")
                return None
            attained = statusword & SW_HOMING_ATTAINED and statusword & cia402.SW_TARGET_REACHED
            if attained and (self._seen_in_progress or not self._stale_attained):
                self.future.set_result(f"{self.name}: homed")
                return None
        return CW_HOMING_START

    def fail(self, why: str) -> None:
        if not self.future.done():
            self.future.set_exception(HomingFailed(f"{self.name}: {why}"))

    def done(self) -> bool:
        return self.future.done()

    def describe(self) -> str:
        if not self.future.done():
            return self.phase.value
        exc = self.future.exception()
        return "homed" if exc is None else f"failed: {exc}"


def refusal(caps: DriveCapabilities, layout: DriveLayout, phase: BringupPhase | None,
            latched: FaultEvent | None, manager_ok: bool) -> str | None:
    """Why a drive cannot be homed now, or None: ``phase`` its bring-up's (None: not
    started), ``manager_ok`` whether the manager was OK as of the last cycle."""
    if not caps.supports(HOMING_MODE):
        return (f"its 0x6502 (0x{caps.supported_modes or 0:X}) has no homing mode; "
                f"it lists {', '.join(caps.mode_names)}")
    if not layout.maps("mode"):
        return "its RPDO mapping carries no 0x6060, so the cycle cannot select homing"
    if phase is not BringupPhase.READY:
        return "it is not READY (start-up or recovery not finished)"
    if latched is not None:
        return f"it is faulted ({latched}); recover it first"
    if not manager_ok:
        return ("the manager is not OK: homing runs while a controller holds the other "
                "joints (clear the e-stop and switch to one first)")
    return None


class HomingQueue:
    """Homing requests from any thread (``submit``), taken by the cycle (``take``): the
    cycle never takes the lock, which only orders callers among themselves."""

    def __init__(self, drives: int) -> None:
        self.jobs: list[HomingJob | None] = [None] * drives  # running: the cycle's own
        self.seen: list[HomingJob | None] = [None] * drives  # the latest job, for status
        self._requests: collections.deque[HomingJob] = collections.deque()
        self._lock = threading.Lock()

    def request(self, entry: DriveEntry, phase: BringupPhase | None,
                latched: FaultEvent | None, manager_ok: bool,
                timeout: float | None) -> Future[str]:
        """Home the drive of ``entry`` (``refusal`` says what the other arguments are), within
        ``timeout`` (None: its config's ``homing_timeout``): the future says how it ended
        ("NAME: homed", or HomingFailed); HomingFailed at once when it cannot be homed now."""
        why = refusal(entry.plan.caps, entry.layout, phase, latched, manager_ok)
        future: Future[str] = Future()
        name = entry.config.name
        self.submit(HomingJob(entry.index, name, timeout or entry.config.homing_timeout,
                              future), why)
        return future

    def submit(self, job: HomingJob, refused: str | None) -> None:
        """Queue ``job`` unless ``refused`` (why it cannot run) or its drive is homing:
        HomingFailed then, at once."""
        with self._lock:
            seen = self.seen[job.index]
            if refused is None and seen is not None and not seen.done():
                refused = "it is already homing"
            if refused is not None:
                raise HomingFailed(f"{job.name}: cannot home: {refused}")
            self.seen[job.index] = job  # status shows this request, not the last result
            self._requests.append(job)

    @property
    def busy(self) -> bool:
        """A job queued or running (checked every cycle: no allocation)."""
        return bool(self._requests) or any(self.jobs)

    def take(self) -> None:
        """The cycle: requests become running jobs."""
        while self._requests:
            job = self._requests.popleft()
            self.jobs[job.index] = job

    def end_all(self, why: str) -> list[int]:
        """Fail queued and running jobs; the drives whose running job ended (they stay off
        until the next switch: their position reference may have changed)."""
        while self._requests:
            self._requests.popleft().fail(f"{why} before homing started")
        ended = []
        for i, job in enumerate(self.jobs):
            if job is not None:
                job.fail(why)
                self.jobs[i] = None
                ended.append(i)
        return ended
