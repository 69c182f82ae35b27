"""rocoma_can/runtime/loop.py, system.py: the loop runner against real drives (simulated, virtual
bus): fixed rate, bounded stop, torque-off frames on every stop path, timing statistics."""
from __future__ import annotations

import gc
import os
import signal
import subprocess
import sys
import threading
import time

import can
import pytest
from fixtures.running import DEMO_RUN, DEMO_WAIT

from rocoma_can.cli.demo.config import demo_config
from rocoma_can.cli.status_watch import cycle_text
from rocoma_can.runtime import ControlLoop, CycleStats, Runtime
from rocoma_can.runtime.config import validate
from rocoma_can.runtime.host import try_sched_fifo
from rocoma_can.runtime.loop import DEFAULT_SPIN, PLAIN_SPIN, YIELD_PAUSE, runs_realtime


@pytest.fixture
def runtime(virtual_channel, sim_segment_factory):
    sim_segment_factory(2)
    cfg = demo_config(virtual_channel, drives=2, rate=100.0)
    cfg["manager"]["estop_must_be_cleared"] = False
    with Runtime(validate(cfg)) as rt:
        yield rt


def test_stop_from_another_thread_ends_in_torque_off(runtime, frame_recorder):
    rec = frame_recorder()
    rt = runtime
    result = {}

    def operate():
        deadline = time.monotonic() + DEMO_WAIT  # a switch needs every drive brought up
        while rt.manager.switch_blocked() is not None and time.monotonic() < deadline:
            time.sleep(0.01)
        if rt.manager.switch_controller("pd", timeout=DEMO_WAIT) == 0:
            rec.wait_for(lambda f: f.cob_id == 0x201 and f.data[:2] == b"\x0f\x00",
                         timeout=DEMO_WAIT)  # enable operation: the pd commands
            result["mark"] = rec.mark()
        rt.loop.stop("test")

    t = threading.Thread(target=operate)
    t.start()
    summary = rt.run(duration=DEMO_RUN, signals=False)
    t.join(DEMO_WAIT)
    assert "mark" in result and rt.loop.stop_reason == "test"
    assert int(rt.loop.last_state) == 0
    after = rec.frames(since=result["mark"])
    # the stop's own cycles send controlword 0x0000 to both drives, then SYNC
    for cob in (0x201, 0x202):
        assert any(f.cob_id == cob and f.data[:2] == b"\x00\x00" for f in after), cob
    assert summary.cycles >= 3 and summary.overruns <= summary.cycles
    assert gc.isenabled()  # restored after the loop


def test_duration_stops_the_loop(runtime):
    summary = runtime.run(duration=0.3, signals=False)
    assert runtime.loop.stop_reason == "duration reached"
    assert 0 < summary.cycles <= 0.3 * 100 + 2


def test_a_run_ends_with_every_cycles_timing_beyond_its_ring(runtime):
    runtime.loop.stats = CycleStats(runtime.loop.period, size=4)
    starts: list[float] = []
    runtime.loop.on_cycle = starts.append
    summary = runtime.run(duration=0.3, signals=False)
    assert summary.cycles == len(starts) > 4
    assert summary.period_mean == pytest.approx((starts[-1] - starts[0]) / (len(starts) - 1))
    assert summary.period_max == pytest.approx(max(b - a for a, b in zip(starts, starts[1:])))


def test_the_gil_is_handed_over_often_while_the_loop_runs(runtime):
    """A tenth of the period (1 ms at 100 Hz) instead of Python's 5 ms, and restored."""
    import sys
    before = sys.getswitchinterval()
    seen: list[float] = []
    runtime.loop.on_cycle = lambda now: seen.append(sys.getswitchinterval())
    runtime.run(duration=0.1, signals=False)
    assert seen and all(s == pytest.approx(min(before, 0.1 * 0.01)) for s in seen)
    assert sys.getswitchinterval() == before


def test_the_loop_spins_what_the_config_says(virtual_channel, sim_segment_factory):
    """realtime.spin_us reaches the loop; 0 sleeps to each deadline and runs cycles, never
    more than the rate allows; unset: 500 µs, or half a period at a higher rate."""
    sim_segment_factory(2)
    cfg = demo_config(virtual_channel, drives=2, rate=100.0)
    assert validate(cfg).spin is None
    assert ControlLoop(None, None, 100.0).spin == 0.0005
    assert ControlLoop(None, None, 4000.0).spin == 0.000125
    with pytest.raises(ValueError, match="spin"):
        ControlLoop(None, None, 100.0, spin=0.01)
    cfg["realtime"] = {"spin_us": 200}
    assert validate(cfg).spin == pytest.approx(200e-6)
    cfg["realtime"] = {"spin_us": 0}
    with Runtime(validate(cfg)) as rt:
        assert rt.loop.spin == 0.0
        summary = rt.run(duration=0.5, signals=False)
    assert 0 < summary.cycles <= 0.5 * 100 + 2


def test_a_yield_that_costs_a_cycle_stops_the_spin_yielding(virtual_channel,
                                                          sim_segment_factory):
    """The spin yields the CPU to the process's threads; a yield also hands the core to a
    nice-19 task until the scheduler's next tick, a period or more at 2 kHz. A CPU hog at
    nice 19 pinned to the loop's CPU (realtime.cpus): the loop sees a yield come back a
    period late and stops yielding for YIELD_PAUSE, longer than this run, so it pauses
    exactly once (what that buys is measured in benchmarks/loop_run.py --nice-hogs; a
    count of cycles would depend on the machine). The caller's thread is given back its
    CPU affinity."""
    sim_segment_factory(2)
    cfg = demo_config(virtual_channel, drives=2, rate=2000.0)
    cfg["manager"]["estop_must_be_cleared"] = False
    cpu = min(os.sched_getaffinity(0))
    cfg["realtime"] = {"cpus": [cpu]}
    hog = subprocess.Popen([sys.executable, "-c", f"import os\nos.sched_setaffinity(0, "
                            f"{{{cpu}}})\nos.nice(19)\nwhile 1: pass"])
    lent = os.sched_getaffinity(0)
    try:
        with Runtime(validate(cfg)) as rt:
            summary = rt.run(duration=2.0, signals=False)
            status = rt.status_report().as_dict()["cycle"]
    finally:
        hog.kill()
        hog.wait()
    assert 2.0 < YIELD_PAUSE and summary.cycles > 0
    assert rt.loop.yield_pauses == 1
    assert status["spin_pauses"] == 1  # what status --json says
    assert cycle_text(status).endswith(", spin pauses 1 (a yield cost a period)")
    assert os.sched_getaffinity(0) == lent


def test_a_sched_fifo_loop_spins_short_and_gives_its_thread_back(virtual_channel,
                                                              sim_segment_factory):
    """realtime.priority: the loop runs SCHED_FIFO where this process may (checked apart)
    and then spins PLAIN_SPIN, not half a period (a long spin ends in the kernel's
    real-time throttling); refused, it warns and keeps the default spin. Either way its
    thread's policy is put back when the loop returns."""
    sim_segment_factory(2)
    cfg = demo_config(virtual_channel, drives=2, rate=500.0)
    cfg["realtime"] = {"priority": 10}
    seen: list[tuple[bool, float]] = []
    policies: list[int] = []
    with Runtime(validate(cfg)) as rt:
        rt.loop.on_cycle = lambda now: seen.append((runs_realtime(), rt.loop.spin))

        def run() -> None:
            policies.append(os.sched_getscheduler(0))
            rt.run(duration=0.3, signals=False)
            policies.append(os.sched_getscheduler(0))
        thread = threading.Thread(target=run)
        thread.start()
        thread.join(DEMO_WAIT)
    assert seen and len(policies) == 2 and policies[0] == policies[1]
    fifo, spin = seen[-1]
    assert fifo == (try_sched_fifo(10) is None)
    assert spin == (PLAIN_SPIN if fifo else min(DEFAULT_SPIN, 0.5 / 500.0))


def test_cycle_stats_ring():
    stats = CycleStats(period=0.01, size=8)
    for k in range(20):
        late = 0.02 if k == 5 else 0.001
        work = 0.0095 if k == 7 else 0.0005  # on time, but it ends 0.5 ms past its period
        stats.record(start=k * 0.01 + late, deadline=k * 0.01, work=work, cpu=work)
    s = stats.summary()
    assert (s.cycles, s.overruns) == (20, 2)
    assert s.jitter_max == pytest.approx(0.001)  # the late cycle fell out of the ring
    assert s.period_mean == pytest.approx(0.01)
    assert s.work_max == pytest.approx(0.0005)  # (k == 7 fell out too)
    whole = stats.summary(whole=True)  # what a run ends with: every cycle's
    assert (whole.cycles, whole.overruns) == (20, 2)
    assert whole.jitter_max == pytest.approx(0.02)
    assert whole.period_max == pytest.approx(0.029)  # k 4 -> 5, the late start
    assert whole.period_mean == pytest.approx(0.01)  # 19 periods from k 0 to k 19
    assert whole.work_max == pytest.approx(0.0095)
    assert whole.jitter_p99 == s.jitter_p99  # the ring's


def test_an_overrun_is_waiting_when_it_was_off_the_cpu_longer_than_on_it():
    """An overrun off the CPU longer than on it (a late start, or work preempted or
    waiting for the GIL) is counted as waiting; one of mostly CPU work (a heavy cycle, a
    CPU running slow) is not; a cycle within its period is neither."""
    stats = CycleStats(period=0.01, size=8)
    cycles = [  # (late, work, cpu) in periods
        (0.0, 1.5, 0.1),   # work slept or waited for the GIL: waiting
        (0.9, 0.2, 0.2),   # woken 0.9 periods late: waiting
        (0.0, 1.5, 1.4),   # its own CPU work: not waiting
        (0.0, 1.2, 0.7),   # both, more on the CPU: not waiting
        (0.0, 0.9, 0.1),   # waited, but ended in time: no overrun
    ]
    for k, (late, work, cpu) in enumerate(cycles):
        deadline = k * 0.1
        stats.record(start=deadline + late * 0.01, deadline=deadline, work=work * 0.01,
                     cpu=cpu * 0.01)
    for summary in (stats.summary(), stats.summary(whole=True)):
        assert (summary.overruns, summary.overruns_waiting) == (4, 2)
    assert "overruns 4 (2 waiting)" in stats.summary().line()


def test_the_loop_times_each_cycles_cpu_on_its_own_thread(runtime):
    """The loop's real clocks: a cycle that sleeps 3 periods in on_cycle has little CPU
    time and is a waiting overrun; one that computes for 3 periods of its thread's CPU time
    has at least that, however busy the machine (a wall clock in place of the thread's CPU
    clock, or none, fails one of the two)."""
    period = runtime.loop.period
    seen: dict[int, tuple[float, float, float]] = {}  # cycle -> (late, work, cpu)

    class Observed(CycleStats):
        def record(self, start: float, deadline: float, work: float, cpu: float) -> None:
            seen[self.cycles] = (start - deadline, work, cpu)
            super().record(start, deadline, work, cpu)
    runtime.loop.stats = Observed(period)

    def on_cycle(now: float) -> None:
        k = runtime.loop.stats.cycles
        if k in (5, 15):
            time.sleep(3 * period)
        elif k in (10, 20):
            until = time.thread_time() + 3 * period
            while time.thread_time() < until:
                pass
        elif k == 25:  # by count, not by time: a busy machine stretches the computing ones
            runtime.loop.stop("test")
    runtime.loop.on_cycle = on_cycle
    summary = runtime.run(duration=DEMO_RUN, signals=False)
    assert runtime.loop.stop_reason == "test"
    for k in (5, 15):
        late, work, cpu = seen[k]
        assert work >= 3 * period and cpu < period, seen[k]
    for k in (10, 20):
        assert seen[k][2] >= 3 * period, seen[k]
    overran = [(late, work, cpu) for late, work, cpu in seen.values()
               if late + work > period]
    assert summary.overruns == len(overran) >= 4
    assert summary.overruns_waiting == sum(late + work > 2 * cpu for late, work, cpu in overran)
    assert summary.overruns_waiting >= 2  # the sleepers
    status = runtime.status_report().as_dict()["cycle"]
    assert (status["overruns"], status["overruns_waiting"]) == (summary.overruns,
                                                                summary.overruns_waiting)


def test_a_run_ends_with_the_whole_runs_timing_not_its_last_ring():
    """A 16 s demo at 1 kHz is four rings of 4096 cycles: its summary's mean and maxima
    must be the run's, not its last four seconds'."""
    stats = CycleStats(period=0.001, size=4)
    starts = [0.0, 0.001, 0.005, 0.006, 0.007, 0.008, 0.009, 0.010]  # a 4 ms gap, early
    for start in starts:
        stats.record(start=start, deadline=start, work=0.0001, cpu=0.0001)
    whole, ring = stats.summary(whole=True), stats.summary()
    assert whole.period_max == pytest.approx(0.004) and ring.period_max == pytest.approx(0.001)
    assert whole.period_mean == pytest.approx(0.010 / 7)


def test_rate_must_be_positive():
    with pytest.raises(ValueError):
        ControlLoop(object(), object(), 0)


def test_start_up_timeouts_come_from_the_yaml(virtual_channel):
    from rocoma_can.drivers.plan.config import Timeouts
    cfg = demo_config(virtual_channel, drives=2, rate=100.0)
    cfg["supervision"] = {"boot_wait": 0.5, "start_timeout": 3.0, "reset_timeout": 4.0,
                          "enable_timeout": 2.0}
    with Runtime(validate(cfg)) as rt:
        assert rt.hardware.timeouts == Timeouts(boot_wait=0.5, start=3.0, reset=4.0, enable=2.0)


def test_the_signal_handler_takes_no_lock(runtime):
    """Python runs a signal handler on the main thread (the loop's) between two bytecodes,
    possibly while that thread holds the stop Event's lock inside ``Event.wait``. A handler
    calling ``Event.set`` then waits for ever for that lock: SIGTERM hung `rocoma-can run`
    (seen once in the vcan end-to-end test). Here the handler runs while its thread holds
    exactly that lock (CPython's Event keeps it in ``_cond``): it must return, and the loop
    must then stop for that signal, with torque-off."""
    loop = runtime.loop
    returned = threading.Event()

    def interrupted_inside_wait() -> None:
        with loop._stop._cond:
            loop.on_signal(signal.SIGTERM, None)
        returned.set()
    threading.Thread(target=interrupted_inside_wait, daemon=True).start()
    assert returned.wait(5.0), "the signal handler blocked on the stop Event's lock"
    runtime.run(duration=5.0, signals=False)
    assert loop.stop_reason == "signal SIGTERM" and int(loop.last_state) == 0


def test_timing_supervision_comes_from_the_yaml(virtual_channel):
    from rocoma_can import TimingSupervision
    cfg = demo_config(virtual_channel, drives=2, rate=100.0)
    cfg["timing"] = {"advance": 2.0, "initialize_fast": 3.0, "overruns": 7, "hang": 50}
    with Runtime(validate(cfg)) as rt:
        assert rt.manager.timing == TimingSupervision(advance=2.0, initialize_fast=3.0,
                                                      overruns=7, hang=50)


def test_a_runtime_on_two_buses_takes_the_estop_frame_from_either(
        virtual_channel, sim_segment_factory, frame_recorder, bus_factory):
    """``buses:`` with two buses of two drives each (node ids 1, 2 on both): one manager
    brings all four up and commands them; an e-stop frame on the second bus (the manager's
    node serves on the first) e-stops, taken by the hardware in the cycle, not by the node."""
    from rocoma_can import ManagerState, SwitchResult
    channels = [f"{virtual_channel}-a", f"{virtual_channel}-b"]
    for ch in channels:
        sim_segment_factory(2, channel=ch)
    cfg = demo_config(channels[0], drives=4, rate=100.0)
    del cfg["bus"]
    cfg["buses"] = [{"name": n, "interface": "virtual", "channel": ch}
                    for n, ch in zip("ab", channels)]
    for k, d in enumerate(cfg["drives"]):
        d["bus"], d["node_id"] = "ab"[k // 2], k % 2 + 1
    cfg["manager"]["estop_must_be_cleared"] = False
    rec_b = frame_recorder(channels[1])
    estop_bus = bus_factory(channels[1])
    result = {}
    with Runtime(validate(cfg)) as rt:
        def operate():
            deadline = time.monotonic() + DEMO_WAIT  # a switch needs every drive brought up
            while rt.manager.switch_blocked() is not None and time.monotonic() < deadline:
                time.sleep(0.01)
            result["switch"] = rt.manager.switch_controller("pd", timeout=DEMO_WAIT)
            rec_b.wait_for(lambda f: f.cob_id == 0x202 and f.data[:2] == b"\x0f\x00",
                           timeout=DEMO_WAIT)  # the second bus's drive 2 is enabled
            estop_bus.send(can.Message(arbitration_id=0x0A0, data=b"", is_extended_id=False))
            deadline = time.monotonic() + DEMO_WAIT
            while rt.manager.state is ManagerState.OK and time.monotonic() < deadline:
                time.sleep(0.01)
            result["state"] = rt.manager.state
            rt.loop.stop("test")

        t = threading.Thread(target=operate)
        t.start()
        rt.run(duration=DEMO_RUN, signals=False)
        t.join(DEMO_WAIT)
        assert result["switch"] == SwitchResult.SWITCHED
        assert result["state"] is ManagerState.EMERGENCY
        assert rt.hardware.estop_frames == 1 and not rt.node.estop_frames
        assert [p.name for p in rt.hardware.ports] == ["a", "b"]


def test_a_ctrl_c_while_one_part_closes_still_closes_the_rest(demo_bench, tmp_path):
    """An impatient second Ctrl-C lands in one part's close (the recorder waiting for its
    writer): the parts after it (the hardware: its bus reader and workers, the node's bus)
    are still closed, the writer process has ended, and the interrupt goes on up."""
    config, _segment = demo_bench
    rt = Runtime(config, flight=str(tmp_path / "flight"))
    rt.run(duration=0.3, signals=False)
    recorder = rt.recorder
    assert recorder is not None
    original = recorder.close

    def interrupted() -> None:
        original()
        raise KeyboardInterrupt
    rt._parts[rt._parts.index(recorder.close)] = interrupted
    with pytest.raises(KeyboardInterrupt):
        rt.close()
    assert all(port.canopen is None for port in rt.hardware.ports)  # the hardware closed
    assert recorder._process.poll() is not None
    assert not [t.name for t in threading.enumerate() if t.name.startswith("can-reader")]


@pytest.mark.parametrize("n", [1, 2, 3, 100, 4096])
def test_the_p99_is_numpys_without_numpys_cost(n):
    """adapters.p99 (the loop's jitter p99, a controller call's p99): np.percentile's
    linear 99th percentile by one partition."""
    import numpy as np

    from rocoma_can.adapters import p99
    values = np.random.default_rng(n).random(n)
    assert p99(values) == pytest.approx(float(np.percentile(values, 99)), rel=1e-12, abs=0)
