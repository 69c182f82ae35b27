"""rocoma_can/manager.py: the seed's four tables (which thread calls what in which timestep), as
tests.

The test thread is the update thread: each ``step()`` is one update() call, and every call a
controller receives is journalled with the update call it happened in and its thread.
"""
from __future__ import annotations

import threading
import time

from fixtures.manager_probes import (
    EMERGENCY,
    FAILPROOF,
    OK,
    WAIT,
    EmergencyProbe,
    NumberSwapState,
    Probe,
)

from rocoma_can import SwitchResult


def test_table_1a_estop_in_ok_emergency_takes_over_in_the_failing_call(rig):
    j = rig.journal
    a, e = Probe("a", j), EmergencyProbe("e", j)
    assert rig.mgr.add_controller(a, emergency=e)
    assert rig.mgr.switch_controller("a") == SwitchResult.SWITCHED
    assert rig.step() == (OK, ["a"])

    a.fail.add("advance")
    assert rig.step() == (EMERGENCY, ["e"])  # the command of the failing call is e's
    failing = rig.mgr.cycle_count
    assert rig.calls_in_cycle(failing) == [("a", "advance"), ("e", "initialize_fast"),
                                           ("e", "advance")]
    for _ in range(3):
        assert rig.step() == (EMERGENCY, ["e"])

    stop = j.wait_for("a", "stop")[0]
    pre_stop = j.of("a", "pre_stop")
    assert len(pre_stop) == 1 and not pre_stop[0].update_thread and not stop.update_thread
    assert j.calls.index(pre_stop[0]) < j.calls.index(stop)
    assert all(c.cycle <= failing for c in j.of("a", "advance"))
    assert rig.mgr.active_controller_name == "e"


def test_table_1b_estop_while_emergency_controller_is_being_stopped_goes_failproof(rig):
    j = rig.journal
    e_stop_gate = threading.Event()
    e = EmergencyProbe("e", j, gates={"stop": e_stop_gate})
    a, b = Probe("a", j), Probe("b", j)
    assert rig.mgr.add_controller(a, emergency=e)
    assert rig.mgr.add_controller(b, emergency=e)
    assert rig.mgr.switch_controller("a") == SwitchResult.SWITCHED
    a.fail.add("advance")
    assert rig.step() == (EMERGENCY, ["e"])
    # Switching away from EMERGENCY hands e over to be stopped; its stop hangs on the gate.
    assert rig.mgr.switch_controller("b") == SwitchResult.SWITCHED
    e_stop = j.wait_for("e", "stop")[0]
    assert rig.mgr.adapters()["e"].being_stopped
    assert rig.step() == (OK, ["b"])

    b.fail.add("advance")
    assert rig.step() == (FAILPROOF, ["failproof"])
    failing = rig.mgr.cycle_count
    assert rig.calls_in_cycle(failing) == [("b", "advance"), ("failproof", "advance")]
    assert len(j.of("e", "initialize_fast")) == 1  # only the first e-stop used it
    for _ in range(3):
        assert rig.step() == (FAILPROOF, ["failproof"])

    b_stop = j.wait_for("b", "stop")[0]
    threads = {e_stop.thread, b_stop.thread}
    assert len(threads) == 2 and not b_stop.update_thread  # thread 2 and thread 3
    e_stop_gate.set()


def test_table_2_estop_in_emergency_goes_failproof(rig):
    j = rig.journal
    a, e = Probe("a", j), EmergencyProbe("e", j)
    assert rig.mgr.add_controller(a, emergency=e)
    assert rig.mgr.switch_controller("a") == SwitchResult.SWITCHED
    a.fail.add("advance")
    assert rig.step() == (EMERGENCY, ["e"])

    e.fail.add("advance")
    assert rig.step() == (FAILPROOF, ["failproof"])
    failing = rig.mgr.cycle_count
    assert rig.calls_in_cycle(failing) == [("e", "advance"), ("failproof", "advance")]
    for _ in range(3):
        assert rig.step() == (FAILPROOF, ["failproof"])
    e_stop = j.wait_for("e", "stop")[0]
    assert not e_stop.update_thread and len(j.of("e", "pre_stop")) == 1
    assert all(c.cycle <= failing for c in j.of("e", "advance"))


def test_table_3_old_controller_advances_through_a_slow_initialize(rig):
    j = rig.journal
    a_advances_during_init = 50
    init_may_end = threading.Event()
    a = Probe("a", j)
    b = Probe("b", j, delay={"initialize": 0.3}, gates={"initialize": init_may_end})
    a.value = 42.0
    assert rig.mgr.add_controller(a) and rig.mgr.add_controller(b)
    assert rig.mgr.switch_controller("a") == SwitchResult.SWITCHED

    writers: list[tuple[int, tuple[str, ...]]] = []
    stop_loop = threading.Event()
    init_started_at = [10**9]  # a's advance count when b's initialize began

    def update_loop() -> None:  # the update thread at dt = 1 ms
        j.update_thread = threading.get_ident()
        next_t = time.monotonic()
        while not stop_loop.is_set():
            state, cmd = rig.step()
            writers.append((rig.mgr.cycle_count, tuple(cmd)))
            if (not init_may_end.is_set()
                    and len(j.of("a", "advance")) >= init_started_at[0] + a_advances_during_init):
                init_may_end.set()
            next_t += 0.001
            time.sleep(max(0.0, next_t - time.monotonic()))

    def note_init_start() -> None:
        j.wait_for("b", "initialize")
        init_started_at[0] = len(j.of("a", "advance"))

    loop = threading.Thread(target=update_loop)
    watcher = threading.Thread(target=note_init_start)
    loop.start()
    watcher.start()
    try:
        assert rig.mgr.switch_controller("b") == SwitchResult.SWITCHED
        j.wait_for("b", "advance", count=20)
    finally:
        stop_loop.set()
        loop.join(WAIT)
        watcher.join(WAIT)
    assert not loop.is_alive()

    # No update call missed a command, and exactly one controller wrote each one.
    cycles = [c for c, _ in writers]
    assert cycles == list(range(cycles[0], cycles[0] + len(cycles)))
    assert all(len(w) == 1 for _, w in writers)
    sequence = [w[0] for _, w in writers]
    first_b = sequence.index("b")
    assert set(sequence[:first_b]) == {"a"} and set(sequence[first_b:]) == {"b"}

    # Thread 2: pre_stop, then b's swap/initialize, while a keeps advancing (>= 50 cycles).
    pre_stop, b_init = j.of("a", "pre_stop")[0], j.of("b", "initialize")[0]
    assert not pre_stop.update_thread and pre_stop.thread == b_init.thread
    assert j.calls.index(pre_stop) < j.calls.index(b_init)
    assert init_may_end.is_set()
    a_adv = j.of("a", "advance")
    assert sum(1 for c in a_adv if c.cycle > b_init.cycle) >= a_advances_during_init
    # The old controller's state reached the new one; its stop came after the commit.
    assert isinstance(b.received_swap_state, NumberSwapState)
    assert b.received_swap_state.value == 42.0
    a_stop = j.wait_for("a", "stop")[0]
    assert j.calls.index(a_stop) > j.calls.index(a_adv[-1])
    assert not a_stop.update_thread and len(j.of("a", "pre_stop")) == 1
