"""The control loop: one thread, a fixed rate on the monotonic clock, and a safe way out.

Each cycle is ``run_cycle``, the one place that writes its order: ``hardware.read(now)``,
whose findings (faults, e-stop frames, a finished recovery) are applied to the manager ->
``manager.update()`` -> ``hardware.write(state, switch_count)`` -> ``manager.post_cycle()``
(the threads the update has work for are woken only once the cycle's frames are out).
Timing: sleep until shortly before the deadline, then spin to it (``time.sleep`` alone
overshoots by the scheduler's slack). While the loop runs, Python's GIL hand-over interval
is a tenth of the period (at most its 5 ms default; restored afterwards), so a thread
running Python code cannot hold the loop off for several periods, and the spin releases the
GIL at each turn to the bus readers and an in-process simulator, until a turn costs a
cycle (YIELD_LATE). The garbage collector is
frozen after start-up and disabled; a generation-0 collection runs between cycles only when
the cycle left slack, so a collection never lands inside a cycle. Statistics go to a
preallocated numpy ring.

Stopping (``stop()``, SIGINT, SIGTERM, or ``duration``) always ends with torque-off: the
manager is failproof-stopped and ``stop_cycles`` more cycles run, which send the hardware's
pre-encoded torque-off frames, before the loop returns. Every wait is bounded.
"""
from __future__ import annotations

import gc
import logging
import math
import os
import signal
import sys
import threading
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from types import FrameType
from typing import Protocol

import numpy as np

from ..adapters import p99
from ..drivers.cycle.stop_requests import ManagerLatch
from ..events import STOP_CAUSE, ManagerState
from ..overrun import overran, waited

log = logging.getLogger(__name__)

#: Seconds before each deadline where the loop stops sleeping and spins (config
#: ``realtime.spin_us``; by default this or half a period, whichever is shorter): a sleep
#: wakes late by the thread's timer slack and the scheduler's wake-up latency (more in a
#: virtual machine, whose idle CPU the host must wake), a spin does not. Each turn of the
#: spin is an ``os.sched_yield()``: it hands the GIL and the CPU to the process's threads
#: that wait for them (bus readers, an in-process simulator, the timers), so they run in
#: the loop's slack rather than at its next deadline. 0 sleeps to the deadline. A loop
#: that runs SCHED_FIFO (``realtime.priority``) or SCHED_RR spins ``PLAIN_SPIN`` unless told: it is
#: woken at once, and a long spin is CPU that the kernel's real-time throttling (95 % of
#: each second by default) takes back in one stall of up to 50 ms (what a long and a short
#: spin missed: benchmarks/README.md, "Figures behind constants").
DEFAULT_SPIN = 0.0005

#: A yield hands the core to any task that can run there, a nice-19 one too, and that
#: task keeps it until the scheduler's next tick (4 ms at HZ=250): a yield after which the
#: loop woke this share of a period or more past its deadline has cost it a cycle (a
#: shorter lateness is left alone: the process's own threads, or a moment of the host).
#: The spin then stops yielding for ``YIELD_PAUSE`` s: it sleeps to ``PLAIN_SPIN`` (or the
#: spin, if shorter) before the deadline and spins on the CPU, as a thread that slept is
#: woken ahead of one that kept running. Yielding every turn loses beside CPU hogs, always
#: sleeping loses when the machine is quiet; this way holds both (``loop_run.py
#: --nice-hogs 2``: benchmarks/README.md, "Figures behind constants").
YIELD_LATE = 1.0
YIELD_PAUSE = 5.0
PLAIN_SPIN = 0.0001

#: The GIL hand-over interval while the loop runs, as a fraction of the period (Python's
#: default is 5 ms): a thread running Python code keeps the GIL for up to this long, so at
#: 5 ms a loop that wakes for its 1 ms deadline can wait five periods for a busy simulator
#: or reader thread.
SWITCH_FRACTION = 0.1
SWITCH_MIN, SWITCH_MAX = 5e-5, 5e-3


def default_spin(period: float, realtime: bool = False) -> float:
    """The spin when the config gives none (DEFAULT_SPIN; PLAIN_SPIN under a real-time
    policy), at most half a ``period``."""
    return min(PLAIN_SPIN if realtime else DEFAULT_SPIN, 0.5 * period)


def spin_fits(spin: float, rate: float) -> bool:
    """The one rule for a spin (s) at a loop rate (Hz): 0 <= spin < one period."""
    return 0 <= spin < 1.0 / rate


@dataclass(frozen=True)
class TimingSummary:
    """Cycle timing over the whole run (``CycleStats.summary(whole=True)``: what a run ends
    with) or over its last cycles (the ring: what a status report shows); the p99 is always
    the ring's."""
    cycles: int
    overruns: int             # cycles that ended after the next cycle's deadline (overran)
    overruns_waiting: int     # of those, the ones that waited (see CycleStats.record)
    period_mean: float        # s
    period_max: float
    jitter_max: float         # s, |start - deadline|
    jitter_p99: float         # s, over the ring
    work_max: float           # s, time spent inside read/update/write

    def line(self) -> str:
        """In ms, as ``status`` says the same figures (live.cycle_text)."""
        if not self.cycles:  # stopped before its first cycle: no figure to give
            return "no cycle ran"
        return (f"cycles {self.cycles}, overruns {self.overruns} ({self.overruns_waiting} "
                f"waiting), period mean {self.period_mean * 1e3:.3f} ms max "
                f"{self.period_max * 1e3:.3f} ms, jitter p99 {self.jitter_p99 * 1e3:.3f} ms "
                f"max {self.jitter_max * 1e3:.3f} ms, work max {self.work_max * 1e3:.3f} ms")


class CycleStats:
    """Per-cycle start times, lateness and work time in a ring allocated once, and the
    whole run's first and last start and maxima (a demo's 16 s at 1 kHz are four rings)."""

    def __init__(self, period: float, size: int = 4096) -> None:
        self.period = period
        self._start = np.zeros(size)
        self._late = np.zeros(size)
        self._work = np.zeros(size)
        self._size = size
        self.cycles = 0
        self.overruns = 0
        self.overruns_waiting = 0
        self._first = self._last = math.nan  # the run's first and latest cycle start
        self._period_max = self._late_max = self._work_max = 0.0

    def record(self, start: float, deadline: float, work: float, cpu: float) -> None:
        """One cycle: its start, the deadline it had, its work (s, start to end) and the
        loop thread's CPU time in that work: overruns, and those that waited
        (rocoma_can/overrun.py)."""
        k = self.cycles % self._size
        self._start[k] = start
        late = start - deadline
        self._late[k] = late
        self._work[k] = work
        if overran(work, late, self.period):
            self.overruns += 1
            if waited(work, late, cpu):
                self.overruns_waiting += 1
        if self.cycles:  # (compare and store: half the time of max() on this hot path)
            gap = start - self._last
            if gap > self._period_max:
                self._period_max = gap
        else:
            self._first = start
        self._last = start
        late = abs(late)
        if late > self._late_max:
            self._late_max = late
        if work > self._work_max:
            self._work_max = work
        self.cycles += 1

    def summary(self, whole: bool = False) -> TimingSummary:
        """Over the ring's cycles, or (``whole``) the whole run's (the p99 is the ring's)."""
        n = min(self.cycles, self._size)
        if n == 0:
            return TimingSummary(0, 0, 0, math.nan, math.nan, math.nan, math.nan, math.nan)
        late = np.abs(self._late[:n])
        late_p99 = p99(late)
        if whole:
            mean = (self._last - self._first) / (self.cycles - 1) if self.cycles > 1 \
                else self.period
            return TimingSummary(self.cycles, self.overruns, self.overruns_waiting, mean,
                                 self._period_max if self.cycles > 1 else self.period,
                                 self._late_max, late_p99, self._work_max)
        k = self.cycles % self._size
        # Read from other threads (status reports) while the loop writes: with a full ring,
        # slot k, the oldest, may be overwritten meanwhile; it is left out.
        starts = np.concatenate((self._start[k + 1:n], self._start[:k])) if n == self._size \
            else self._start[:n]
        periods = np.diff(starts) if n > 1 else np.array([self.period])
        return TimingSummary(self.cycles, self.overruns, self.overruns_waiting,
                             float(periods.mean()),
                             float(periods.max()), float(late.max()), late_p99,
                             float(self._work[:n].max()))


def set_realtime(priority: int | None, cpus: set[int] | None) -> list[str]:
    """SCHED_FIFO and CPU affinity for the calling thread; a warning per thing not permitted."""
    warnings = []
    if cpus:
        try:
            os.sched_setaffinity(0, cpus)
        except (OSError, AttributeError) as exc:
            warnings.append(f"CPU affinity {sorted(cpus)} not set: {exc}")
    if priority:
        try:
            os.sched_setscheduler(0, os.SCHED_FIFO, os.sched_param(priority))
        except (OSError, AttributeError) as exc:
            warnings.append(f"SCHED_FIFO priority {priority} not set ({exc}); the loop runs "
                            "with normal priority. Grant CAP_SYS_NICE or an rtprio limit "
                            "(ulimit -r) to get it")
    for w in warnings:
        log.warning("%s", w)
    return warnings


def scheduling_restorer() -> Callable[[], None]:
    """A function that gives the calling thread back its CPU affinity and scheduling policy
    as they are now: the loop's caller gets its thread back as it lent it."""
    try:
        cpus, policy, param = (os.sched_getaffinity(0), os.sched_getscheduler(0),
                               os.sched_getparam(0))
    except (OSError, AttributeError):  # (no such calls on this platform: nothing was set)
        return lambda: None

    def restore() -> None:
        try:
            os.sched_setscheduler(0, policy, param)
        except OSError as exc:
            log.warning("the loop's thread keeps its real-time scheduling policy: %s", exc)
        try:
            os.sched_setaffinity(0, cpus)
        except OSError as exc:
            log.warning("the loop's thread keeps its CPU affinity: %s", exc)
    return restore


def runs_realtime() -> bool:
    """Whether the calling thread runs a real-time policy (SCHED_FIFO, SCHED_RR)."""
    try:
        return os.sched_getscheduler(0) in (os.SCHED_FIFO, os.SCHED_RR)
    except (OSError, AttributeError):
        return False


class CycleManager(ManagerLatch, Protocol):
    """What the loop needs of a manager (rocoma_can.ControllerManager)."""

    @property
    def switch_count(self) -> int: ...
    def update(self) -> ManagerState: ...
    def post_cycle(self) -> None: ...


class CycleEvent(Protocol):
    """A finding of the hardware's read for the manager (drivers/cycle/stop_requests.py)."""

    def apply(self, manager: ManagerLatch) -> None: ...


class CycleHardware(Protocol):
    """What the loop needs of a hardware layer (drivers.hardware.CanopenHardware)."""

    def read(self, now: float) -> Sequence[CycleEvent]: ...
    def write(self, manager_state: ManagerState, switch_count: int | None = ...) -> None: ...


def run_cycle(hardware: CycleHardware, manager: CycleManager, now: float) -> ManagerState:
    """One cycle, in the order every caller uses (the loop, the tests' rigs, benchmarks):
    what the read found reaches the manager before its update, so a fault is acted on in
    the cycle it is seen; the frames go out after the update; the manager's threads are
    woken after the frames."""
    state = _read_update_write(hardware, manager, now)
    manager.post_cycle()
    return state


def _read_update_write(hardware: CycleHardware, manager: CycleManager,
                       now: float) -> ManagerState:
    events = hardware.read(now)
    if events:
        for event in events:
            event.apply(manager)
    state = manager.update()
    hardware.write(state, manager.switch_count)
    return state


class CycleTrace(Protocol):
    """What records every cycle's signals (trace.SignalTrace): called on the loop thread
    after the cycle, it must only copy into memory allocated beforehand."""

    def record(self, now: float, work: float, late: float, state: ManagerState,
               cpu: float) -> None: ...


class ControlLoop:
    """Runs ``hardware`` + ``manager`` at ``rate`` Hz on the calling thread until stopped.

    ``on_cycle(now)`` (optional) runs after each cycle on the loop thread; it must be cheap
    (the demo uses it for its script and status line).
    """

    def __init__(self, hardware: CycleHardware, manager: CycleManager, rate: float, *,
                 priority: int | None = None, cpus: set[int] | None = None,
                 stop_cycles: int = 3, on_cycle: Callable[[float], None] | None = None,
                 stats_size: int = 4096, trace: CycleTrace | None = None,
                 spin: float | None = None) -> None:
        if not rate > 0:
            raise ValueError(f"rate must be > 0 Hz, got {rate!r}")
        self._spin_default = spin is None
        if spin is None:
            spin = default_spin(1.0 / rate)
        if not spin_fits(spin, rate):
            raise ValueError(f"spin must be 0 <= spin < one period ({1e6 / rate:.1f} µs), "
                             f"got {spin * 1e6:g} µs")
        self.spin = spin
        self.hardware = hardware
        self.manager = manager
        self.period = 1.0 / rate
        self.priority = priority
        self.cpus = cpus
        self.stop_cycles = max(1, stop_cycles)
        self.on_cycle = on_cycle
        self.trace = trace
        self.stats = CycleStats(self.period, stats_size)
        self.stop_reason = ""
        self._stop = threading.Event()
        self._plain_until = -math.inf  # the spin yields from then on (YIELD_LATE)
        #: times a yield cost the loop its deadline and the spin stopped yielding a while
        self.yield_pauses = 0
        #: the last run's scheduling as it took effect: what its priority and CPUs asked
        #: for and did not get (set_realtime), whether its thread ran a real-time policy,
        #: the CPUs it could run on
        self.realtime_refused: list[str] = []
        self.ran_realtime = False
        self.ran_cpus: set[int] = set()
        self._signalled: str | None = None  # set by the signal handler, taken by the loop
        self.last_state = ManagerState.FAILPROOF  # the manager's start state

    def stop(self, reason: str = "stop requested") -> None:
        """From any thread (not a signal handler: see ``on_signal``): the loop torque-offs
        and returns."""
        if not self._stop.is_set():
            self.stop_reason = reason
            self._stop.set()

    def on_signal(self, signum: int, frame: FrameType | None) -> None:
        """SIGINT/SIGTERM handler. It takes no lock: Python runs it on the main thread (the
        loop's) between two bytecodes, possibly while that thread holds the stop Event's
        lock inside ``Event.wait``; ``Event.set`` here would then wait for that lock for ever
        and the process would never stop. A plain attribute is set instead; the loop sees it
        within one period."""
        self._signalled = f"signal {signal.Signals(signum).name}"

    def install_signal_handlers(self) -> Callable[[], None]:
        """SIGINT/SIGTERM -> on_signal; returns a function restoring the previous handlers."""
        previous = {}
        for sig in (signal.SIGINT, signal.SIGTERM):
            previous[sig] = signal.signal(sig, self.on_signal)

        def restore() -> None:
            for sig, old in previous.items():
                signal.signal(sig, old)
        return restore

    def run(self, duration: float | None = None) -> TimingSummary:
        restore_scheduling = scheduling_restorer() if self.priority or self.cpus \
            else None
        self.realtime_refused = set_realtime(self.priority, self.cpus)
        self.ran_realtime = runs_realtime()
        self.ran_cpus = os.sched_getaffinity(0) if hasattr(os, "sched_getaffinity") else set()
        if self._spin_default:  # (per run: DEFAULT_SPIN says why real-time spins short)
            self.spin = default_spin(self.period, self.ran_realtime)
        switch_interval = sys.getswitchinterval()
        sys.setswitchinterval(min(switch_interval, max(SWITCH_MIN, min(
            SWITCH_MAX, SWITCH_FRACTION * self.period))))
        gc.collect()
        gc.freeze()
        gc_was_enabled = gc.isenabled()
        gc.disable()
        hw, mgr, stats, period = self.hardware, self.manager, self.stats, self.period
        on_cycle, trace = self.on_cycle, self.trace
        clock, cpu_clock = time.monotonic, time.thread_time  # (thread_time: cheap, a read)
        start = clock()
        end = start + duration if duration is not None else math.inf
        deadline = start
        try:
            while not self._stop.is_set():
                if self._signalled is not None:
                    self.stop(self._signalled)
                    break
                now = clock()
                if now >= end:
                    self.stop("duration reached")
                    break
                cpu = cpu_clock()
                state = run_cycle(hw, mgr, now)
                self.last_state = state
                if on_cycle is not None:
                    on_cycle(now)
                done = clock()
                cpu = cpu_clock() - cpu
                stats.record(now, deadline, done - now, cpu)
                if trace is not None:
                    trace.record(now, done - now, now - deadline, state, cpu)
                deadline += period
                if done > deadline:  # overrun: start again from now, do not burst
                    deadline = done
                    continue
                if deadline - done > 0.25 * period and gc.get_count()[0] > 200:
                    gc.collect(0)
                self._wait_until(deadline)
        finally:
            try:
                self._torque_off()
            finally:  # (a KeyboardInterrupt in the torque-off's sleeps too)
                if gc_was_enabled:
                    gc.enable()
                gc.unfreeze()
                sys.setswitchinterval(switch_interval)
                if restore_scheduling is not None:
                    restore_scheduling()
        return stats.summary(whole=True)

    def _wait_until(self, deadline: float) -> None:
        clock, stop = time.monotonic, self._stop
        yielding = clock() >= self._plain_until
        spin = self.spin if yielding else min(self.spin, PLAIN_SPIN)
        remaining = deadline - clock() - spin
        if remaining > 0:
            stop.wait(remaining)
        late = deadline + YIELD_LATE * self.period
        while clock() < deadline and not stop.is_set() and self._signalled is None:
            if not yielding:
                continue  # on the CPU: a yield lately cost a cycle (YIELD_LATE)
            os.sched_yield()  # the GIL and the CPU to a thread that waits (DEFAULT_SPIN)
            now = clock()
            if now > late:  # another task had the core: no yields for a while
                self._plain_until = now + YIELD_PAUSE
                self.yield_pauses += 1
                return

    def _torque_off(self) -> None:
        """Failproof stop, then cycles that send the torque-off frames (bounded count)."""
        try:
            self.manager.failproof_stop(cause=f"{STOP_CAUSE} {self.stop_reason or 'exit'}")
        except Exception:
            log.exception("failproof_stop raised while stopping the loop")
        for _ in range(self.stop_cycles):
            try:  # run_cycle's steps, with post_cycle in any case
                self.last_state = _read_update_write(self.hardware, self.manager,
                                                     time.monotonic())
            except Exception:
                log.exception("torque-off cycle raised while stopping the loop")
                try:
                    # the pre-encoded torque-off frames
                    self.hardware.write(ManagerState.FAILPROOF)
                except Exception:
                    log.exception("torque-off frames could not be sent")
            finally:
                try:
                    self.manager.post_cycle()  # the stop's events reach the subscribers
                except Exception:
                    log.exception("post_cycle raised while stopping the loop")
            time.sleep(min(self.period, 0.02))
