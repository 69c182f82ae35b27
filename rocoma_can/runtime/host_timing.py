"""Does this host run a control loop at a steady speed: the loop (``ControlLoop``, as
``run`` uses it) with a cycle that is nothing but a fixed amount of Python work, no CAN, no
other thread (``rocoma-can doctor --timing``; benchmarks/host_floor.py tabulates it).

Whatever such a loop counts as overruns is the host's, and a loop whose real cycle does as
much work meets the same host. Two kinds of host trouble are told apart. Work that
stays in the CPU's cache sees the scheduler (the loop woken late, another task on its CPU)
and a CPU that runs slow. Work that reads a few MiB of objects in no particular order, as a
Python program's objects lie, also sees the caches and memory the host's other work
shares: on a shared virtual machine the same work's median took up to 1.5x longer in one
run than in one a minute before (no steal time shows it), and a loop with 40 % of its period as work
then overruns for seconds at a time. Software cannot fix that; a robot's computer needs
cores of its own, or a loop that leaves that much headroom.
"""
from __future__ import annotations

import random
import time
from collections.abc import Collection, Sequence
from dataclasses import dataclass

import numpy as np

from ..events import ManagerState
from .host import Check
from .loop import ControlLoop, CycleEvent

#: bytes one walked object takes, its slot in the list and the allocator's share included
#: (tracemalloc, CPython 3.11: a pair of an int and a float)
OBJECT_BYTES = 120
#: the footprint of the memory-bound work: past a core's second-level cache (0.5-2 MiB),
#: within a server's shared third-level cache (which a virtual machine's neighbours share)
MEMORY_FOOTPRINT = 4 << 20
#: the work a cycle, as a share of the period: about the demo's loop's, with its simulated
#: drives, at 1 kHz (benchmarks/README.md, "Figures behind constants")
WORK_SHARE = 0.4
#: doctor's verdicts: overruns above this share of the cycles, or a work whose slowest
#: cycles (p99.9) took more than this many times its median, warn; a check has at least
#: MIN_CYCLES (fewer cannot tell 0.1 % from chance)
OVERRUN_SHARE = 0.001
SPREAD = 2.0
MIN_CYCLES = 1000


class WorkHardware:
    """A hardware layer with nothing to read and a fixed amount of Python work in its write:
    ``visits`` items read from a list of ``footprint`` bytes of small objects, shuffled
    (their order unrelated to where they lie), each cycle on from where the last stopped.
    Footprint 0 is one object: the work stays in the first-level cache."""

    def __init__(self, footprint: int) -> None:
        objects = [(k, float(k)) for k in range(max(1, footprint // OBJECT_BYTES))]
        random.Random(1).shuffle(objects)
        self.objects, self.visits, self.total, self._at = objects, 0, 0, 0

    def size(self, work_us: float, period: float) -> None:
        """``visits`` for ``work_us`` of thread CPU as the loop will run this work now: a
        first size from 200 passes back to back, then the median of 50 passes of that size
        each after the rest of a ``period`` asleep, as the loop's cycles come (between
        them other work takes the caches: sized back to back only, the work over 4 MiB
        took 1.6-2.5x its size in the loop). Medians: the fastest pass would size it on a
        moment the host rarely gives."""
        self.visits = 2000
        self.visits = round(work_us * 2000 / (self._median_pass(200, 0.0) * 1e6))
        pause = max(0.0, period - work_us * 1e-6)
        self.visits = round(self.visits * work_us / (self._median_pass(50, pause) * 1e6))

    def _median_pass(self, passes: int, pause: float) -> float:
        """The median thread CPU time (s) of ``passes`` writes, ``pause`` s apart. Where the
        thread CPU clock moves in ticks longer than a pass (user-mode Linux: most passes
        read 0, and a size taken from 0 would make the work endless) the mean, which counts
        the ticks all passes crossed, else the median wall time."""
        took, wall = [], []
        for _ in range(passes):
            if pause:
                time.sleep(pause)
            start, start_wall = time.thread_time(), time.perf_counter()
            self.write(ManagerState.OK)
            took.append(time.thread_time() - start)
            wall.append(time.perf_counter() - start_wall)
        cpu = float(np.median(took)) or float(np.mean(took)) or float(np.median(wall))
        return max(cpu, 1e-9)

    def read(self, now: float) -> Sequence[CycleEvent]:
        return ()

    def write(self, manager_state: ManagerState, switch_count: int | None = None) -> None:
        objects, at = self.objects, self._at
        n = len(objects)
        total = 0
        for k in range(at, at + self.visits):
            total += objects[k % n][0]
        self.total, self._at = total, (at + self.visits) % n


class AlwaysOk:
    """A manager that is always OK; the loop's stop calls failproof_stop: nothing to do."""

    switch_count = 0

    def update(self) -> ManagerState:
        return ManagerState.OK

    def post_cycle(self) -> None:
        pass

    def emergency_stop(self, cause: str = "") -> None:
        pass

    def failproof_stop(self, cause: str = "") -> None:
        pass

    def clear_emergency_stop(self) -> bool:
        return True


class CpuTrace:
    """Each cycle's thread CPU time, in an array allocated before the run."""

    def __init__(self, cycles: int) -> None:
        self.cpu = np.zeros(cycles)
        self.n = 0

    def record(self, now: float, work: float, late: float, state: ManagerState,
               cpu: float) -> None:
        if self.n < len(self.cpu):
            self.cpu[self.n] = cpu
            self.n += 1


@dataclass(frozen=True)
class BareRun:
    """One run of the bare loop: its cycles and overruns (rocoma_can/overrun.py), how many
    of those waited off the CPU, and what the same work took, cycle by cycle."""
    rate: float
    work_us: float
    footprint: int
    visits: int
    priority: int | None          # the SCHED_FIFO priority asked for
    realtime: bool                # the loop's thread ran a real-time policy
    cpus: list[int] | None        # the CPUs it ran on, when pinned
    cycles: int
    overruns: int
    waiting: int
    cpu_median_us: float
    cpu_p999_us: float
    period_mean_ms: float
    period_max_ms: float

    @property
    def share(self) -> float:
        return self.overruns / max(self.cycles, 1)

    @property
    def spread(self) -> float:
        """The slowest cycles' CPU (p99.9) over the median's: 1 on a steady host."""
        return self.cpu_p999_us / max(self.cpu_median_us, 1e-9)


def bare_loop(rate: float, work_us: float, footprint: int, duration: float,
              priority: int | None = None, cpus: Collection[int] | None = None,
              spin: float | None = None) -> BareRun:
    """The loop at ``rate`` for ``duration`` s, each cycle ``work_us`` of work (sized now)
    over ``footprint`` bytes, at SCHED_FIFO ``priority`` on ``cpus`` with ``spin`` if given
    (as ``realtime:`` runs the real loop; the run says what took effect); it leaves nothing
    running and the calling thread as it was (ControlLoop restores what it set)."""
    trace = CpuTrace(int(rate * duration) + 16)
    hardware = WorkHardware(footprint)
    hardware.size(work_us, 1.0 / rate)
    pinned = set(cpus) if cpus else None
    loop = ControlLoop(hardware, AlwaysOk(), rate, priority=priority, cpus=pinned,
                       trace=trace, spin=spin)
    summary = loop.run(duration=duration)
    cpu = trace.cpu[:trace.n] * 1e6 if trace.n else np.zeros(1)
    return BareRun(rate, work_us, footprint, hardware.visits, priority,
                   loop.ran_realtime, sorted(loop.ran_cpus) if pinned else None,
                   summary.cycles, summary.overruns,
                   summary.overruns_waiting, float(np.median(cpu)),
                   float(np.percentile(cpu, 99.9)), summary.period_mean * 1e3,
                   summary.period_max * 1e3)


def timing_checks(rate: float, seconds: float, priority: int | None = None,
                  cpus: Collection[int] | None = None,
                  spin: float | None = None) -> list[Check]:
    """doctor's two measured checks at ``rate`` (and the config's ``realtime:``): the bare
    loop with WORK_SHARE of the period as work in the cache, then over MEMORY_FOOTPRINT,
    ``seconds`` / 2 each (the caller sees to MIN_CYCLES)."""
    work = WORK_SHARE * 1e6 / rate
    cache = bare_loop(rate, work, 0, seconds / 2, priority, cpus, spin)
    memory = bare_loop(rate, work, MEMORY_FOOTPRINT, seconds / 2, priority, cpus, spin)
    return [_cache_check(cache), _memory_check(memory)]


def _said(run: BareRun) -> str:
    how = "".join((f" at SCHED_FIFO {run.priority}" if run.priority and run.realtime else
                   f" at normal priority (SCHED_FIFO {run.priority} refused)" if run.priority
                   else "", f" on CPUs {run.cpus}" if run.cpus else ""))
    return (f"{run.rate:g} Hz{how}, {run.work_us:.0f} µs of Python work a cycle: {run.overruns} "
            f"overruns in {run.cycles} cycles ({100 * run.share:.2f} %, {run.waiting} waiting "
            f"off the CPU); the work's CPU median {run.cpu_median_us:.0f} µs, p99.9 "
            f"{run.cpu_p999_us:.0f} µs")


def _cache_check(run: BareRun) -> Check:
    name = "timing: work in the cache"
    if run.share <= OVERRUN_SHARE:
        return Check(name, "ok", _said(run))
    mostly_waiting = run.waiting * 2 >= run.overruns
    fix = ("the loop waited for its CPU: realtime.priority (SCHED_FIFO) and a CPU of its own "
           "(realtime.cpus, isolcpus); on a virtual machine, dedicated host cores"
           if mostly_waiting else
           "the CPU itself ran slow: a fixed CPU clock (governor performance), no other busy "
           "work on the loop's core; on a virtual machine, dedicated host cores")
    return Check(name, "warn", _said(run), fix)


def _memory_check(run: BareRun) -> Check:
    name = f"timing: work over {run.footprint >> 20} MiB"
    said = f"{_said(run)} ({run.spread:.1f}x)"
    if run.share <= OVERRUN_SHARE and run.spread <= SPREAD:
        return Check(name, "ok", said)
    return Check(name, "warn", said,
                 "this host's memory speed does not hold (other tenants of a virtual "
                 "machine's host, or other busy work here): give the loop cores and memory of "
                 "its own, or leave it that much headroom (a lower rate, fewer drives a loop)")
