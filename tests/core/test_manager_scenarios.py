"""rocoma's own test scenarios, plus the precise points the manager adds (rocoma_can/manager.py).

Wall-time supervision is off in these managers (timing=None): they test semantics, and on a
loaded machine a preempted call must not count as a controller failure; test_manager_timing.py
tests the supervision itself."""
from __future__ import annotations

import logging
import threading
import time
from collections.abc import Iterator
from contextlib import contextmanager

import pytest
from fixtures.manager_probes import (
    EMERGENCY,
    FAILPROOF,
    LAYER_METHODS,
    OK,
    WAIT,
    CommandLog,
    EmergencyProbe,
    FailproofProbe,
    Journal,
    Probe,
    add_probe,
    layered_manager,
)

from rocoma_can import ControllerManager, EventKind, SwitchResult
from rocoma_can.remote import STOP_CALLS, StopAnswers, Transport, serve
from rocoma_can.stop_surfaces import StopSurface


def test_starts_in_failproof(rig):
    assert rig.mgr.state is FAILPROOF
    assert rig.mgr.active_controller_name == "failproof"
    assert rig.step() == (FAILPROOF, ["failproof"])


def test_switch_failproof_to_a_then_a_to_b(rig):
    add_probe(rig, "a"), add_probe(rig, "b")
    assert rig.mgr.switch_controller("a") == SwitchResult.SWITCHED
    assert rig.step() == (OK, ["a"])
    assert rig.mgr.switch_controller("b") == SwitchResult.SWITCHED
    assert rig.step() == (OK, ["b"])
    assert rig.mgr.active_controller_name == "b"
    rig.journal.wait_for("a", "stop")


def test_switch_to_the_active_controller_is_running(rig):
    add_probe(rig, "a")
    assert rig.mgr.switch_controller("a") == SwitchResult.SWITCHED
    assert rig.mgr.switch_controller("a") == SwitchResult.RUNNING
    assert len(rig.journal.of("a", "initialize")) == 1


def test_not_found_for_unknown_emergency_and_failproof_names(rig):
    add_probe(rig, "a", emergency=EmergencyProbe("e", rig.journal))
    for name in ("nope", "e", "failproof"):
        assert rig.mgr.switch_controller(name) == SwitchResult.NOT_FOUND
    assert rig.mgr.available_controllers() == ["a"]


def test_available_controllers_sorted(rig):
    for name in ("zeta", "alpha", "mid"):
        add_probe(rig, name)
    assert rig.mgr.available_controllers() == ["alpha", "mid", "zeta"]


def test_no_emergency_controller_goes_failproof(rig):
    a = add_probe(rig, "a")
    rig.mgr.switch_controller("a")
    a.fail.add("advance")
    assert rig.step() == (FAILPROOF, ["failproof"])


def test_second_estop_goes_failproof(rig):
    add_probe(rig, "a", emergency=EmergencyProbe("e", rig.journal))
    rig.mgr.switch_controller("a")
    rig.mgr.emergency_stop()
    assert rig.step() == (EMERGENCY, ["e"])
    rig.mgr.emergency_stop()
    assert rig.step() == (FAILPROOF, ["failproof"])
    rig.journal.wait_for("e", "stop")


def test_estop_from_another_thread_takes_effect_by_the_next_update(rig):
    add_probe(rig, "a", emergency=EmergencyProbe("e", rig.journal))
    rig.mgr.switch_controller("a")
    t = threading.Thread(target=rig.mgr.emergency_stop, args=("remote",))
    t.start()
    t.join(WAIT)
    assert rig.step() == (EMERGENCY, ["e"])


def test_failproof_stop_from_ok_skips_the_emergency_layer(rig):
    add_probe(rig, "a", emergency=EmergencyProbe("e", rig.journal))
    rig.mgr.switch_controller("a")
    rig.mgr.failproof_stop()
    assert rig.step() == (FAILPROOF, ["failproof"])
    assert not rig.journal.of("e", "initialize_fast")


@pytest.mark.parametrize("via_emergency", [True, False])
def test_must_clear_blocks_switching_until_cleared(via_emergency):
    journal = Journal(update_thread=threading.get_ident())
    command = CommandLog()
    with ControllerManager(FailproofProbe("failproof", journal), dt=0.001, timing=None,
                           command=command,
                           estop_must_be_cleared=True) as mgr:
        journal.manager = mgr
        e = EmergencyProbe("e", journal)
        assert mgr.add_controller(Probe("a", journal), emergency=e)
        assert mgr.estop_latched  # latched at start, like an e-stop button after power-on
        assert mgr.switch_controller("a") == SwitchResult.ERROR
        assert mgr.clear_emergency_stop()
        assert mgr.switch_controller("a") == SwitchResult.SWITCHED
        if via_emergency:
            mgr.emergency_stop()
            assert mgr.update() is EMERGENCY
        else:
            mgr.failproof_stop()
            assert mgr.update() is FAILPROOF
        assert mgr.estop_latched
        assert mgr.switch_controller("a") == SwitchResult.ERROR
        mgr.update()
        mgr.clear_emergency_stop()
        assert mgr.switch_controller("a") == SwitchResult.SWITCHED
        assert mgr.update() is OK


def test_internal_failure_latches_with_must_clear():
    journal = Journal(update_thread=threading.get_ident())
    with ControllerManager(FailproofProbe("failproof", journal), dt=0.001, timing=None,
                           command=CommandLog(), estop_must_be_cleared=True) as mgr:
        journal.manager = mgr
        a = Probe("a", journal)
        mgr.add_controller(a)
        mgr.clear_emergency_stop()
        assert mgr.switch_controller("a") == SwitchResult.SWITCHED
        a.fail.add("advance")
        assert mgr.update() is FAILPROOF
        assert mgr.estop_latched


def test_check_state_and_limit_command_failures_are_failures():
    journal = Journal(update_thread=threading.get_ident())
    verdict = {"state": True, "command": True}
    with ControllerManager(FailproofProbe("failproof", journal), dt=0.001, timing=None,
                           command=CommandLog(),
                           check_state=lambda s: verdict["state"],
                           limit_command=lambda c: verdict["command"]) as mgr:
        journal.manager = mgr
        e = EmergencyProbe("e", journal)
        mgr.add_controller(Probe("a", journal), emergency=e)
        mgr.switch_controller("a")
        assert mgr.update() is OK
        verdict["command"] = False
        assert mgr.update() is FAILPROOF  # a rejected, then e's command rejected too
        mgr.switch_controller("a")
        verdict["command"] = True
        verdict["state"] = False
        n = len(journal.of("a", "advance"))
        assert mgr.update() is FAILPROOF
        assert len(journal.of("a", "advance")) == n  # not advanced on a bad state


@pytest.mark.parametrize("layer,method", LAYER_METHODS)
def test_exceptions_in_every_callback_of_every_layer(layer, method, caplog):
    mgr, added = layered_manager(layer, raises={method})
    if (layer, method) == ("controller", "create"):
        assert not added and mgr.available_controllers() == ["b"]
    else:
        result = mgr.switch_controller("a")
        assert result == (SwitchResult.ERROR if method == "initialize" else SwitchResult.SWITCHED)
        for _ in range(3):
            mgr.update()
        if method == "get_swap_state":  # the successor starts without a swap state
            assert mgr.switch_controller("b") == SwitchResult.SWITCHED
            assert mgr.update() is OK
        mgr.emergency_stop()
        mgr.update()
        mgr.emergency_stop()
        assert mgr.update() is FAILPROOF
    with caplog.at_level(logging.ERROR, logger="rocoma_can.manager"):
        assert mgr.shutdown() == (method != "cleanup")  # a failed cleanup is reported
    assert "raised on purpose" in caplog.text or (layer, method) == ("controller", "create")
    assert not [t for t in threading.enumerate() if t.name.startswith("rocoma/")]


def test_adding_to_the_wrong_layer_raises_type_error(rig):
    with pytest.raises(TypeError):
        rig.mgr.add_controller(EmergencyProbe("e", rig.journal))
    with pytest.raises(TypeError):
        rig.mgr.add_controller(Probe("a", rig.journal), emergency=Probe("x", rig.journal))
    with pytest.raises(TypeError):
        ControllerManager(Probe("p", rig.journal), dt=0.001)


def test_duplicate_emergency_name_is_dropped_and_the_first_shared(rig, caplog):
    first, second = EmergencyProbe("e", rig.journal), EmergencyProbe("e", rig.journal)
    add_probe(rig, "a", emergency=first)
    with caplog.at_level(logging.WARNING, logger="rocoma_can.manager"):
        add_probe(rig, "b", emergency=second)
    assert "dropped" in caplog.text
    rig.mgr.switch_controller("b")
    rig.mgr.emergency_stop()
    assert rig.step() == (EMERGENCY, ["e"])
    assert rig.mgr.adapters()["e"].controller is first


def test_subscribers_see_switch_state_and_estop_events(rig):
    events = []
    got = threading.Event()

    def on_event(ev):
        events.append(ev)
        if ev.kind is EventKind.EMERGENCY_STOP:
            got.set()
    rig.mgr.subscribe(on_event)
    add_probe(rig, "a", emergency=EmergencyProbe("e", rig.journal))
    rig.mgr.switch_controller("a")
    rig.mgr.emergency_stop("big red button")
    rig.step()
    assert got.wait(WAIT)
    kinds = [(ev.kind, ev.state, ev.active_controller) for ev in events]
    assert (EventKind.ACTIVE_CONTROLLER_CHANGED, OK, "a") in kinds
    assert (EventKind.STATE_CHANGED, EMERGENCY, "e") in kinds
    estop = [ev for ev in events if ev.kind is EventKind.EMERGENCY_STOP]
    assert estop[0].cause == "big red button"


def test_a_raising_subscriber_does_not_silence_the_others(rig):
    seen = threading.Event()
    rig.mgr.subscribe(lambda ev: 1 / 0)
    rig.mgr.subscribe(lambda ev: seen.set())
    add_probe(rig, "a")
    rig.mgr.switch_controller("a")
    assert seen.wait(WAIT)


def test_shutdown_stops_cleans_up_and_joins_everything():
    journal = Journal(update_thread=threading.get_ident())
    mgr = ControllerManager(FailproofProbe("failproof", journal), dt=0.001, timing=None,
                            command=CommandLog())
    journal.manager = mgr
    e = EmergencyProbe("e", journal)
    mgr.add_controller(Probe("a", journal), emergency=e)
    mgr.add_controller(Probe("b", journal), emergency=e)
    mgr.switch_controller("a")
    mgr.update()
    assert mgr.shutdown()
    assert mgr.state is FAILPROOF
    assert {c.controller for c in journal.of(method="cleanup")} == {"a", "b", "e", "failproof"}
    assert journal.of("a", "stop")
    assert not [t for t in threading.enumerate() if t.name.startswith("rocoma/")]
    assert mgr.switch_controller("a") == SwitchResult.ERROR


def test_an_update_wakes_no_thread_before_post_cycle(rig):
    """Once the loop calls post_cycle (after the cycle's frames are written), the stop of a
    failed controller and the events of the e-stop wait for it: no thread woken inside the
    cycle can take the GIL from the frames. Without post_cycle (a caller that only calls
    update) they go out at the end of update, as the tests above rely on."""
    a = add_probe(rig, "a", emergency=EmergencyProbe("e", rig.journal))
    events = []
    delivered = threading.Event()
    rig.mgr.subscribe(lambda ev: (events.append(ev.kind),
                                  delivered.set() if ev.kind is EventKind.EMERGENCY_STOP
                                  else None)
                      if ev.kind in (EventKind.EMERGENCY_STOP, EventKind.STATE_CHANGED)
                      else None)
    assert rig.mgr.switch_controller("a") == SwitchResult.SWITCHED
    rig.mgr.post_cycle()  # the loop's way from here on
    a.fail.add("advance")
    assert rig.step() == (EMERGENCY, ["e"])
    # nothing was handed over: however long we wait, a's stop cannot have started
    assert not delivered.wait(0.2) and not rig.journal.of("a", "pre_stop")
    rig.mgr.post_cycle()
    rig.journal.wait_for("a", "stop")
    assert delivered.wait(WAIT) and events[-2:] == [EventKind.EMERGENCY_STOP,
                                                    EventKind.STATE_CHANGED]


def test_an_event_from_another_thread_queues_behind_the_cycles():
    """Between an update() that held its e-stop events and post_cycle, a clear from the
    node's SDO thread must not overtake them: subscribers see e-stop, then cleared."""
    journal = Journal(update_thread=threading.get_ident())
    mgr = ControllerManager(FailproofProbe("failproof", journal), dt=0.001,
                            command=CommandLog(), timing=None, estop_must_be_cleared=True)
    try:
        a = Probe("a", journal)
        assert mgr.add_controller(a, emergency=EmergencyProbe("e", journal))
        seen = []
        done = threading.Event()
        mgr.subscribe(lambda ev: (seen.append((ev.kind, ev.cause)),
                                  done.set() if ev.cause == "emergency stop cleared" else None))
        mgr.clear_emergency_stop()  # it starts latched
        assert mgr.switch_controller("a") == SwitchResult.SWITCHED
        assert done.wait(WAIT)  # that clear's event is through: from here on, only ours
        done.clear()
        seen.clear()
        mgr.post_cycle()
        a.fail.add("advance")
        assert mgr.update() is EMERGENCY
        clearing = threading.Thread(target=mgr.clear_emergency_stop)
        clearing.start()
        clearing.join(WAIT)
        mgr.post_cycle()
        assert done.wait(WAIT)
        kinds = [kind for kind, _ in seen]
        cleared = seen.index((EventKind.STATE_CHANGED, "emergency stop cleared"))
        assert kinds.index(EventKind.EMERGENCY_STOP) < cleared, seen
    finally:
        assert mgr.shutdown()


def test_each_event_carries_the_latch_it_left():
    """A recording reads the e-stop latch of every cycle from the events (record/
    live_channels.py): an e-stop's event carries it set (with estop_must_be_cleared), a
    clear's carries it off, and no event says it before it is so."""
    journal = Journal(update_thread=threading.get_ident())
    mgr = ControllerManager(FailproofProbe("failproof", journal), dt=0.001,
                            command=CommandLog(), timing=None, estop_must_be_cleared=True)
    try:
        assert mgr.add_controller(Probe("a", journal), emergency=EmergencyProbe("e", journal))
        seen = []
        done = threading.Event()
        mgr.subscribe(lambda ev: (seen.append((ev.kind, ev.cause, ev.latched)),
                                  done.set() if ev.cause == "emergency stop cleared" else None))
        mgr.clear_emergency_stop()  # it starts latched
        assert done.wait(WAIT)
        assert seen == [(EventKind.STATE_CHANGED, "emergency stop cleared", False)]
        assert mgr.switch_controller("a") == SwitchResult.SWITCHED
        assert mgr.estop_requested == ""
        mgr.emergency_stop("big red button")  # latched at once; its event at the update
        assert mgr.estop_latched
        assert mgr.estop_requested == "big red button"  # said at once too (cli/demo/stops.py)
        assert mgr.update() is EMERGENCY
        mgr.post_cycle()
        done.clear()
        mgr.clear_emergency_stop()
        assert done.wait(WAIT)
        estop = seen.index((EventKind.EMERGENCY_STOP, "big red button", True))
        assert estop > 1 and {latched for _, _, latched in seen[1:estop]} == {False}, seen
        assert seen[estop:] == [(EventKind.EMERGENCY_STOP, "big red button", True),
                                (EventKind.STATE_CHANGED, "", True),
                                (EventKind.ACTIVE_CONTROLLER_CHANGED, "", True),
                                (EventKind.STATE_CHANGED, "emergency stop cleared", False)]
    finally:
        assert mgr.shutdown()


#: a remote caller without commands (stops are anyone's)
TRANSPORT = Transport(StopSurface("test", "test", "a test's calls"), "test.allow_commands",
                      allow_commands=False)


@contextmanager
def _running_a() -> Iterator[ControllerManager]:
    """A manager with controller "a" (emergency "e") switched to and updated once: OK."""
    journal = Journal(update_thread=threading.get_ident())
    with ControllerManager(FailproofProbe("failproof", journal), dt=0.001, timing=None,
                           command=CommandLog()) as mgr:
        journal.manager = mgr
        assert mgr.add_controller(Probe("a", journal), emergency=EmergencyProbe("e", journal))
        assert mgr.switch_controller("a") == SwitchResult.SWITCHED
        assert mgr.update() is OK
        yield mgr


def test_a_remote_stops_answer_says_the_state_after_it_or_that_it_is_pending():
    """remote.serve (Zenoh, Foxglove): a stop is answered once the manager's updates have
    acted on it, with the state after it; a loop that does not update (not running here)
    gets an answer at once, saying the stop is pending."""
    with _running_a() as mgr:
        assert serve(mgr, "estop", TRANSPORT, running=False, recover=None) == {
            "ok": True, "state": "OK", "pending": True}
        assert mgr.update() is EMERGENCY  # the loop's next update acts on it
        updating = threading.Event()

        def loop() -> None:  # the loop, as far as the stop's answer can tell
            while not updating.is_set():
                mgr.update()
                time.sleep(0.001)
        thread = threading.Thread(target=loop)
        thread.start()
        try:
            assert serve(mgr, "estop", TRANSPORT, running=True, recover=None) == {
                "ok": True, "state": "FAILPROOF"}  # EMERGENCY -> FAILPROOF, then answered
        finally:
            updating.set()
            thread.join()


def test_stop_answers_never_hold_the_transports_thread():
    """StopAnswers (Zenoh's and Foxglove's stop calls): the stop is requested at once, the
    caller's thread goes on at once, and the answer comes once the manager's updates have
    acted on it; beyond STOP_CALLS waiting answers, one is given at once, pending."""
    with _running_a() as mgr:
        stops = StopAnswers(mgr, "test")
        answers: list[dict] = []
        for _ in range(STOP_CALLS):  # the loop does not update: each waits
            stops.answer("estop", TRANSPORT, True, answers.append)
        assert answers == []  # nobody waited here
        stops.answer("estop", TRANSPORT, True, answers.append)  # no slot: at once, pending
        assert answers == [{"ok": True, "state": "OK", "pending": True}]
        assert mgr.update() is FAILPROOF  # the queued e-stops, in one update: OK ->
        assert answers[1:] == []          # EMERGENCY -> FAILPROOF; the answers wait for
        mgr.update()                      # the update after it to have begun
        deadline = time.monotonic() + WAIT
        while len(answers) < STOP_CALLS + 1 and time.monotonic() < deadline:
            time.sleep(0.001)
        assert answers[1:] == [{"ok": True, "state": "FAILPROOF"}] * STOP_CALLS
