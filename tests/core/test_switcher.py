"""rocoma_can/switcher.py, stopper.py: rocoma's switch scenarios on the manager's switcher thread: a
concurrent switch, an e-stop during a switch (requested or applied), a failed swap, a switch that
waits for the new controller to finish stopping, and bounded waits.

Wall-time supervision is off in these managers (timing=None), as in test_manager_scenarios.py."""
from __future__ import annotations

import threading

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
    add_probe,
)

from rocoma_can import ControllerManager, ManagerTimeouts, SwitchResult


def test_concurrent_switch_gets_error_at_once(rig):
    gate = threading.Event()
    add_probe(rig, "a", gates={"initialize": gate})
    add_probe(rig, "b")
    first = rig.mgr.request_switch("a")
    rig.journal.wait_for("a", "initialize")
    second = rig.mgr.request_switch("b")
    assert second.done() and second.result() == SwitchResult.ERROR
    gate.set()
    assert first.result(WAIT) == SwitchResult.SWITCHED


def test_estop_during_switch_returns_error_and_stops_both(rig):
    gate = threading.Event()
    add_probe(rig, "a", emergency=EmergencyProbe("e", rig.journal))
    add_probe(rig, "b", gates={"initialize": gate})
    rig.mgr.switch_controller("a")
    assert rig.step() == (OK, ["a"])
    future = rig.mgr.request_switch("b")
    rig.journal.wait_for("b", "initialize")
    assert rig.step() == (OK, ["a"])  # the old one keeps advancing meanwhile
    rig.mgr.emergency_stop("button")
    assert rig.step() == (EMERGENCY, ["e"])
    gate.set()
    assert future.result(WAIT) == SwitchResult.ERROR
    rig.journal.wait_for("a", "stop")
    rig.journal.wait_for("b", "stop")
    assert len(rig.journal.of("a", "pre_stop")) == 1  # once, although switch and e-stop met
    assert len(rig.journal.of("b", "pre_stop")) == 1
    assert rig.step() == (EMERGENCY, ["e"])


def test_estop_requested_but_not_yet_applied_still_interrupts_the_switch(rig):
    gate = threading.Event()
    add_probe(rig, "a")
    add_probe(rig, "b", gates={"initialize": gate})
    rig.mgr.switch_controller("a")
    future = rig.mgr.request_switch("b")
    rig.journal.wait_for("b", "initialize")
    rig.mgr.emergency_stop()  # no update() runs before the commit
    gate.set()
    assert future.result(WAIT) == SwitchResult.ERROR
    assert rig.mgr.state is FAILPROOF  # applied by the switcher before a's stop
    rig.journal.wait_for("a", "stop")
    assert rig.step() == (FAILPROOF, ["failproof"])


def test_switch_completes_with_no_update_loop_running(rig):
    add_probe(rig, "a")
    assert rig.mgr.switch_controller("a", timeout=WAIT) == SwitchResult.SWITCHED
    assert rig.mgr.state is OK


def test_second_estop_completes_while_the_first_stop_still_runs(rig):
    a_stop = threading.Event()
    e = EmergencyProbe("e", rig.journal)
    add_probe(rig, "a", emergency=e, gates={"stop": a_stop})
    rig.mgr.switch_controller("a")
    rig.mgr.emergency_stop()
    assert rig.step() == (EMERGENCY, ["e"])
    rig.journal.wait_for("a", "stop")  # hanging on its gate
    rig.mgr.emergency_stop()
    assert rig.step() == (FAILPROOF, ["failproof"])
    rig.journal.wait_for("e", "stop")  # not queued behind a's stop
    a_stop.set()
    rig.journal.wait_for("a", "stop")


def test_switching_works_again_after_an_interrupted_switch_with_the_loop_running(rig):
    gate = threading.Event()
    add_probe(rig, "a", emergency=EmergencyProbe("e", rig.journal))
    add_probe(rig, "b", gates={"initialize": gate})
    rig.mgr.switch_controller("a")
    stop = threading.Event()

    def loop():
        while not stop.wait(0.001):
            rig.mgr.update()
    t = threading.Thread(target=loop)
    rig.journal.update_thread = None
    t.start()
    try:
        future = rig.mgr.request_switch("b")
        rig.journal.wait_for("b", "initialize")
        rig.mgr.emergency_stop()
        gate.set()
        assert future.result(WAIT) == SwitchResult.ERROR
        rig.journal.wait_for("b", "stop")
        assert rig.mgr.switch_controller("b") == SwitchResult.SWITCHED
        rig.journal.wait_for("b", "advance")
        assert rig.mgr.switch_controller("a") == SwitchResult.SWITCHED
        rig.journal.wait_for("a", "advance", count=len(rig.journal.of("a", "advance")) + 1)
    finally:
        stop.set()
        t.join(WAIT)
    assert rig.mgr.state is OK and rig.mgr.active_controller_name == "a"


def test_failed_swap_estops_and_stops_the_new_controller(rig):
    add_probe(rig, "a", emergency=EmergencyProbe("e", rig.journal))
    add_probe(rig, "b", fail={"initialize"})
    rig.mgr.switch_controller("a")
    assert rig.mgr.switch_controller("b") == SwitchResult.ERROR
    assert rig.mgr.state is EMERGENCY  # a was pre-stopped, so it may not run on
    rig.journal.wait_for("a", "stop")
    rig.journal.wait_for("b", "stop")
    assert rig.step() == (EMERGENCY, ["e"])


def test_switch_waits_for_the_new_controller_to_finish_stopping(rig):
    gate = threading.Event()
    add_probe(rig, "a", gates={"stop": gate})
    add_probe(rig, "b")
    rig.mgr.switch_controller("a")
    rig.mgr.switch_controller("b")
    rig.journal.wait_for("a", "stop")  # hanging: a is being stopped
    future = rig.mgr.request_switch("a")
    assert not future.done()
    gate.set()
    assert future.result(WAIT) == SwitchResult.SWITCHED
    stop_call = rig.journal.of("a", "stop")[0]
    swap_call = rig.journal.of("a", "swap")[-1]
    assert rig.journal.calls.index(stop_call) < rig.journal.calls.index(swap_call)


def test_being_stopped_wait_is_bounded():
    journal = Journal(update_thread=threading.get_ident())
    gate = threading.Event()
    with ControllerManager(FailproofProbe("failproof", journal), dt=0.001, timing=None,
                           command=CommandLog(),
                           timeouts=ManagerTimeouts(being_stopped=0.2)) as mgr:
        journal.manager = mgr
        mgr.add_controller(Probe("a", journal, gates={"stop": gate}))
        mgr.add_controller(Probe("b", journal))
        mgr.switch_controller("a")
        mgr.switch_controller("b")
        journal.wait_for("a", "stop")
        assert mgr.switch_controller("a") == SwitchResult.ERROR
        gate.set()
