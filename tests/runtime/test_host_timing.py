"""The bare control loop that measures a host (runtime/host_timing.py, ``doctor --timing``):
it counts what the real loop counts, leaves the calling thread as it was, and its verdicts
say which kind of host trouble was seen and what fixes it. Timing itself is never asserted
(a shared machine): the overruns here are forced by a work longer than the period."""
from __future__ import annotations

import gc
import os
import sys

import pytest

from rocoma_can import ManagerState
from rocoma_can.runtime.host_timing import (
    MEMORY_FOOTPRINT,
    OVERRUN_SHARE,
    SPREAD,
    BareRun,
    WorkHardware,
    _cache_check,
    _memory_check,
    bare_loop,
)


def test_a_work_longer_than_the_period_overruns_every_cycle():
    # 4 periods of work a cycle: each cycle ends after the next one's deadline
    run = bare_loop(200.0, 20_000.0, 0, 0.15)
    assert run.cycles >= 1
    assert run.overruns == run.cycles
    assert run.waiting <= run.overruns
    assert run.cpu_median_us > 5_000  # the work ran on the loop's thread, on its CPU


def test_the_calling_thread_is_left_as_it_was():
    cpu = min(os.sched_getaffinity(0))
    before = (sys.getswitchinterval(), gc.isenabled(), gc.get_freeze_count(),
              os.sched_getscheduler(0), os.sched_getaffinity(0))
    run = bare_loop(500.0, 100.0, MEMORY_FOOTPRINT, 0.05, priority=1, cpus={cpu})
    assert run.cycles > 0 and run.footprint == MEMORY_FOOTPRINT
    assert run.cpus == [cpu]  # the loop ran pinned, as asked
    assert (sys.getswitchinterval(), gc.isenabled(), gc.get_freeze_count(),
            os.sched_getscheduler(0), os.sched_getaffinity(0)) == before
    # SCHED_FIFO where this process may take it (root, CAP_SYS_NICE), said either way
    assert run.priority in (1, None)
    found = _cache_check(run).found
    assert " at SCHED_FIFO 1 " in found or "(SCHED_FIFO 1 refused)" in found


def test_the_work_walks_on_through_every_object():
    hardware = WorkHardware(MEMORY_FOOTPRINT)
    hardware.visits = 1000
    n = len(hardware.objects)
    assert n > 30_000  # a few MiB of objects, not a few that stay in a cache
    for _ in range(n // 1000 + 1):
        hardware.write(ManagerState.OK)
    assert hardware._at == (1000 * (n // 1000 + 1)) % n  # every object visited once
    assert len(WorkHardware(0).objects) == 1


def _run(overruns: int, waiting: int, median: float = 400.0, p999: float = 600.0,
         footprint: int = 0) -> BareRun:
    return BareRun(1000.0, 400.0, footprint, 5000, None, False, None, 10_000, overruns,
                   waiting, median, p999, 1.0, 1.2)


def test_a_steady_host_passes_both_checks():
    cycles_allowed = int(OVERRUN_SHARE * 10_000)
    assert _cache_check(_run(cycles_allowed, 0)).status == "ok"
    memory = _memory_check(_run(0, 0, 400.0, SPREAD * 400.0, MEMORY_FOOTPRINT))
    assert memory.status == "ok" and memory.name == "timing: work over 4 MiB"
    assert memory.found.endswith("(2.0x)")


@pytest.mark.parametrize("waiting, says", [(20, "waited for its CPU"), (3, "ran slow")])
def test_overruns_warn_with_the_fix_for_their_kind(waiting, says):
    check = _cache_check(_run(20, waiting))
    assert check.status == "warn" and says in (check.fix or "")
    assert "20 overruns in 10000 cycles (0.20 %" in check.found


def test_a_memory_speed_that_does_not_hold_warns_even_without_overruns():
    check = _memory_check(_run(0, 0, 400.0, 1_000.0, MEMORY_FOOTPRINT))
    assert check.status == "warn" and "(2.5x)" in check.found
    assert "memory speed does not hold" in (check.fix or "")


def test_a_thread_cpu_clock_coarser_than_a_pass_still_sizes_the_work(monkeypatch):
    """Where the thread CPU clock moves in ticks (user-mode Linux, the vcan suite's guest:
    10 ms), most passes of the sizing read 0 s: taken as 1 ns, the work grew a million-fold
    and `doctor --timing` never ended. The size must stay near the one a fine clock gives
    (here a 4 ms tick)."""
    import threading
    import time

    from rocoma_can.runtime import host_timing
    fine = WorkHardware(0)
    fine.size(400.0, 0.001)
    tick = 0.004
    real = time.thread_time
    monkeypatch.setattr(host_timing.time, "thread_time", lambda: real() // tick * tick)
    coarse = WorkHardware(0)
    sizing = threading.Thread(target=coarse.size, args=(400.0, 0.001), daemon=True)
    sizing.start()
    sizing.join(30.0)
    assert not sizing.is_alive(), "sizing the work never ended"
    assert coarse.visits < 20 * fine.visits, (coarse.visits, fine.visits)
