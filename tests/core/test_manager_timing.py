"""rocoma_can/manager.py, adapters.py, stopper.py: timing supervision: budgets, overruns in a row, a
hung advance, no false trips."""
from __future__ import annotations

import gc
import threading
import time

from fixtures.manager_probes import (
    EMERGENCY,
    FAILPROOF,
    OK,
    WAIT,
    CommandLog,
    EmergencyProbe,
    FailproofProbe,
    Journal,
    Probe,
)

from rocoma_can import ControllerManager, EventKind, SwitchResult, TimingSupervision
from rocoma_can.manager_timing import ManagerTimeouts

DT = 0.01  # budgets: advance 5 ms, initialize_fast 5 ms, hang 200 ms


def manager(journal, **kwargs):
    mgr = ControllerManager(FailproofProbe("failproof", journal), dt=DT, command=CommandLog(),
                            timing=TimingSupervision(advance=0.5, initialize_fast=0.5,
                                                     overruns=3, hang=20), **kwargs)
    journal.manager = mgr
    return mgr


def test_advance_over_budget_k_times_in_a_row_is_a_failure():
    journal = Journal(update_thread=threading.get_ident())
    with manager(journal) as mgr:
        a = Probe("a", journal)
        mgr.add_controller(a, emergency=EmergencyProbe("e", journal))
        assert mgr.switch_controller("a") == SwitchResult.SWITCHED
        a.delay["advance"] = 2 * 0.5 * DT  # always twice the budget
        assert [mgr.update() for _ in range(3)] == [OK, OK, EMERGENCY]
        assert "over its budget" in mgr.adapters()["a"].failure


def test_an_overrun_streak_is_reset_by_a_cycle_within_budget():
    journal = Journal(update_thread=threading.get_ident())
    with manager(journal) as mgr:
        a = Probe("a", journal)
        mgr.add_controller(a)
        mgr.switch_controller("a")
        for _ in range(4):
            a.delay["advance"] = DT
            assert mgr.update() is OK
            assert mgr.update() is OK
            a.delay.pop("advance")
            assert mgr.update() is OK


def test_slow_initialize_fast_goes_failproof():
    journal = Journal(update_thread=threading.get_ident())
    with manager(journal) as mgr:
        e = EmergencyProbe("e", journal, delay={"initialize_fast": DT})
        mgr.add_controller(Probe("a", journal), emergency=e)
        mgr.switch_controller("a")
        mgr.emergency_stop()
        assert mgr.update() is FAILPROOF
        assert "over its budget" in mgr.adapters()["e"].failure


def test_a_controller_may_set_its_own_advance_budget():
    journal = Journal(update_thread=threading.get_ident())
    with manager(journal) as mgr:
        a = Probe("a", journal)
        a.advance_budget = 4 * DT
        mgr.add_controller(a)
        mgr.switch_controller("a")
        a.delay["advance"] = DT
        assert [mgr.update() for _ in range(4)] == [OK] * 4


def test_hung_advance_torques_off_through_the_watchdog_then_falls_through():
    journal = Journal(update_thread=threading.get_ident())
    hang_calls_before_return = []
    release = threading.Event()

    def on_hang():  # the CAN layer sends the failproof frames here
        hang_calls_before_return.append(time.monotonic())
        if len(hang_calls_before_return) >= 3:
            release.set()

    with manager(journal, on_hang=on_hang) as mgr:
        a = Probe("a", journal)
        mgr.add_controller(a, emergency=EmergencyProbe("e", journal))
        mgr.switch_controller("a")
        assert mgr.update() is OK
        a.gates["advance"] = release  # advance blocks until on_hang ran three times
        # the hung advance failed when it returned; on_hang had switched the drives off,
        # so there is no smart stop left to run: FAILPROOF, not EMERGENCY
        assert mgr.update() is FAILPROOF
        assert len(hang_calls_before_return) >= 3
        assert "hung for" in mgr.adapters()["a"].failure
        assert journal.of("e", "initialize_fast") == []
        calls = len(hang_calls_before_return)
        assert mgr.update() is FAILPROOF
        time.sleep(30 * DT)
        assert len(hang_calls_before_return) == calls  # quiet once update() returns


def test_a_hung_advance_within_a_budget_of_its_own_still_goes_failproof():
    """A controller may allow itself more than the hang limit (``advance_budget``): the
    watchdog has torqued the drives off all the same, so an advance that then returns True
    must not leave the manager OK (the next write would command the drives again)."""
    journal = Journal(update_thread=threading.get_ident())
    release = threading.Event()
    hangs = []

    def on_hang():
        hangs.append(time.monotonic())
        release.set()

    with manager(journal, on_hang=on_hang) as mgr:
        a = Probe("a", journal)
        a.advance_budget = 100 * DT  # above the hang limit (20 x DT)
        mgr.add_controller(a, emergency=EmergencyProbe("e", journal))
        mgr.switch_controller("a")
        assert mgr.update() is OK
        a.gates["advance"] = release  # returns True once on_hang ran
        assert mgr.update() is FAILPROOF
        assert hangs and journal.of("e", "initialize_fast") == []


def test_update_does_not_wait_for_a_switch_stuck_in_a_callback():
    """An aborted switch e-stops on the switcher thread with the cycle lock held, and runs
    the emergency controller's initialize_fast there: one that never returns must not stop
    the cycle. update() gives up on the lock after the hang limit and returns FAILPROOF (the
    caller writes torque-off frames), and the failproof stop it queued is applied once the
    lock is free: the manager does not come back in the layer the stuck switch chose."""
    journal = Journal(update_thread=threading.get_ident())
    gate = threading.Event()
    with manager(journal) as mgr:
        e = EmergencyProbe("e", journal, gates={"initialize_fast": gate})
        mgr.add_controller(Probe("a", journal), emergency=e)
        mgr.add_controller(Probe("b", journal, fail={"initialize"}))  # its swap fails
        assert mgr.switch_controller("a") == SwitchResult.SWITCHED
        assert mgr.update() is OK
        switch = mgr.request_switch("b")
        journal.wait_for("e", "initialize_fast")  # the switcher is stuck in it, lock held
        assert mgr.update() is FAILPROOF
        assert not gate.is_set() and not switch.done()  # returned while still stuck
        assert mgr.lock_timeouts == 1
        assert mgr.update() is FAILPROOF
        assert mgr.lock_timeouts == 2
        gate.set()
        assert switch.result(WAIT) == SwitchResult.ERROR
        assert mgr.update() is FAILPROOF  # the queued failproof stop, not EMERGENCY
        assert mgr.state is FAILPROOF


def test_shutdown_gives_up_on_a_switch_stuck_in_a_callback():
    """The stuck switch of the test above holds the cycle lock: shutdown waits for it as for
    anything else, at most timeouts.shutdown, says so (False) and goes on."""
    journal = Journal(update_thread=threading.get_ident())
    gate = threading.Event()
    mgr = manager(journal, timeouts=ManagerTimeouts(shutdown=0.3))
    try:
        e = EmergencyProbe("e", journal, gates={"initialize_fast": gate})
        mgr.add_controller(Probe("a", journal), emergency=e)
        mgr.add_controller(Probe("b", journal, fail={"initialize"}))
        assert mgr.switch_controller("a") == SwitchResult.SWITCHED
        mgr.request_switch("b")
        journal.wait_for("e", "initialize_fast")
        assert mgr.shutdown() is False  # returned, bounded, with the switch still stuck
        assert not gate.is_set()
    finally:
        gate.set()  # the switch ends; its thread then takes shutdown's last job and ends
        for thread in threading.enumerate():
            if thread.name.startswith("rocoma/"):
                thread.join(WAIT)
    assert not [t.name for t in threading.enumerate() if t.name.startswith("rocoma/")]


def test_no_false_trips_in_a_10_s_run_of_a_normal_controller():
    # Threads left running by earlier tests would compete for the GIL and starve this loop.
    # A thread Python did not start (the Foxglove SDK's native runtime, which called back into
    # Python once) stays listed as a dummy for good, running or not: not one of ours.
    others = [t.name for t in threading.enumerate() if t is not threading.current_thread()
              and not isinstance(t, threading._DummyThread)]
    assert not others, f"threads left over by earlier tests: {others}"
    journal = Journal()
    events = []
    dt = 0.001
    gc.collect()  # as the runtime loop does: no collection inside a cycle (a gen-2 pass
    gc.freeze()   # after hundreds of tests takes tens of ms, which the hang limit catches)
    gc.disable()
    with ControllerManager(FailproofProbe("failproof", journal), dt=dt,
                           command=CommandLog()) as mgr:
        journal.manager = mgr
        mgr.subscribe(lambda ev: events.append(ev) if ev.kind is EventKind.EMERGENCY_STOP
                      else None)
        mgr.add_controller(Probe("a", journal), emergency=EmergencyProbe("e", journal))
        assert mgr.switch_controller("a") == SwitchResult.SWITCHED
        end = time.monotonic() + 10.0
        next_t = time.monotonic()
        states = set()
        while time.monotonic() < end:
            mgr.command_object.clear()
            states.add(mgr.update())
            next_t += dt
            time.sleep(max(0.0, next_t - time.monotonic()))
        gc.enable()
        gc.unfreeze()
        assert states == {OK}, [ev.cause for ev in events]
        stats = mgr.statistics()["a"]["advance"]
        assert stats["count"] == mgr.cycle_count
        assert 0 < stats["mean_us"] <= stats["p99_us"] <= stats["max_us"]
    assert [ev.cause for ev in events] == ["shutdown"]  # nothing tripped before it
    assert journal.manager.hang_calls == 0


def test_without_supervision_slow_advances_are_tolerated():
    journal = Journal(update_thread=threading.get_ident())
    with ControllerManager(FailproofProbe("failproof", journal), dt=DT, command=CommandLog(),
                           timing=None) as mgr:
        journal.manager = mgr
        a = Probe("a", journal, delay={"advance": DT})
        mgr.add_controller(a)
        mgr.switch_controller("a")
        assert [mgr.update() for _ in range(5)] == [OK] * 5
        assert not [t for t in threading.enumerate() if t.name == "rocoma/watchdog"]

