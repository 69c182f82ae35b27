"""Homing one drive (drivers/cycle/homing.py) while the active controller keeps the others: in
the cycle, against simulated drives on the virtual bus; refusals; an e-stop during homing;
and the whole path from `rocoma-can home` over the manager node."""
from __future__ import annotations

import struct
import threading
import time

import pytest
from fixtures.driver_rig import VIRTUAL, Rig
from fixtures.paths import TESTS
from fixtures.rig_controllers import Sine
from fixtures.running import DEMO_RUN, DEMO_WAIT

from rocoma_can import ManagerState, SwitchResult
from rocoma_can.cli.demo.config import demo_config
from rocoma_can.cli.main import main
from rocoma_can.drivers.cycle.homing import CW_HOMING_START, HOMING_MODE
from rocoma_can.drivers.protocol.cia402 import State402
from rocoma_can.drivers.protocol.joints import JointMode
from rocoma_can.drivers.sim.state_machine import HOMING_TIME
from rocoma_can.errors import HomingFailed
from rocoma_can.runtime import Runtime
from rocoma_can.runtime.config import validate

EDS = TESTS / "fixtures" / "eds"
# a homing: the drive enabled in mode 6, then the simulated drive's homing time
HOMING = VIRTUAL.enable_budget() + VIRTUAL.motion_budget(HOMING_TIME)
# a homing that ends without running (an e-stop, a refusal): a few cycles
ENDED = VIRTUAL.cycles_budget(10)


@pytest.fixture
def rig(sim_segment_factory, bus_factory, frame_recorder, virtual_channel):
    segment = sim_segment_factory([1, 2])
    recorder = frame_recorder(virtual_channel)
    r = Rig.for_setup(bus_factory(), [1, 2], VIRTUAL, modes=("csp",))
    r.segment, r.recorder = segment, recorder
    assert r.run_until(lambda: not r.hw.starting, VIRTUAL.bring_up_budget(2)), \
        r.hw.drive_status()
    r.mgr.add_controller(Sine("sine", JointMode.CSP, amplitude=0.2))
    assert r.switch("sine") == SwitchResult.SWITCHED
    assert r.run_until(lambda: r.hw.all_enabled, VIRTUAL.enable_budget()), r.hw.drive_status()
    r.run(0.3)  # moving: the sine has left the start position
    yield r
    r.close()


def _run_until_done(rig: Rig, future, timeout: float) -> None:
    assert rig.run_until(future.done, timeout), rig.hw.drive_status()


def test_homing_one_drive_while_the_other_keeps_tracking(rig):
    j1, j2 = rig.segment.drives[1], rig.segment.drives[2]
    assert j1.position_rad != 0.0
    mark = rig.recorder.mark()
    future = rig.hw.home("j1")
    _run_until_done(rig, future, HOMING)
    assert future.result() == "j1: homed"
    assert abs(j1.position_increments) < 5000  # its reported position is the home offset
    # the homed drive got mode 6 and "homing operation start"; the other its CSP targets
    frames = [struct.unpack_from("<Hb", f.data) for f in rig.recorder.frames(0x201, since=mark)]
    assert (CW_HOMING_START, HOMING_MODE) in frames
    assert j2.state402 == State402.OPERATION_ENABLED and j2.mode_display == 8
    assert rig.hw.drive_status()[0].homing == "homed"
    # its reference changed: off until the next switch, then commanded again
    assert rig.run_until(lambda: j1.state402 == State402.SWITCH_ON_DISABLED,
                         VIRTUAL.detect_budget())
    rig.mgr.add_controller(Sine("sine2", JointMode.CSP, amplitude=0.1))
    assert rig.switch("sine2") == SwitchResult.SWITCHED
    assert rig.run_until(lambda: rig.hw.all_enabled, VIRTUAL.enable_budget())


def test_an_estop_during_homing_ends_it_as_failed(rig):
    future = rig.hw.home("j1")
    rig.run(3 * rig.dt)
    rig.mgr.emergency_stop("test")
    _run_until_done(rig, future, ENDED)
    with pytest.raises(HomingFailed, match="j1: the manager left OK"):
        future.result()
    assert rig.hw.drive_status()[0].homing.startswith("failed")


def test_homing_is_refused_with_the_reason(rig, sim_segment_factory, bus_factory):
    with pytest.raises(HomingFailed, match="no drive named 'j9'"):
        rig.hw.home("j9")
    rig.hw.home("j1")
    with pytest.raises(HomingFailed, match="j1: cannot home: it is already homing"):
        rig.hw.home("j1")
    rig.mgr.failproof_stop("test")
    rig.run(3 * rig.dt)
    with pytest.raises(HomingFailed, match="j2: cannot home: the manager is not OK"):
        rig.hw.home("j2")


def test_a_drive_without_homing_mode_is_refused(virtual_channel, sim_segment_factory,
                                                bus_factory):
    fixed = str(EDS / "fixed_pdo.eds")  # PP + CSP, and no 0x6060 in its fixed RPDO
    sim_segment_factory([1], eds_path=fixed)
    r = Rig.for_setup(bus_factory(), [1], VIRTUAL, modes=("csp",), drive={"eds": fixed})
    try:
        assert r.run_until(lambda: not r.hw.starting, VIRTUAL.bring_up_budget(1))
        with pytest.raises(HomingFailed, match=r"no homing mode; it lists PP, CSP"):
            r.hw.home("j1")
    finally:
        r.close()


def test_rocoma_can_home_over_the_manager_node(virtual_channel, sim_segment_factory, capsys):
    sim_segment_factory(2)
    cfg = demo_config(virtual_channel, drives=2, rate=100.0)
    cfg["manager"]["estop_must_be_cleared"] = False
    outcome: dict[str, int] = {}
    seen: dict[str, object] = {}
    bus = ["--interface", "virtual", "--channel", virtual_channel, "--timeout", "2"]
    with Runtime(validate(cfg)) as rt:
        def operate() -> None:
            deadline = time.monotonic() + DEMO_WAIT
            while rt.manager.switch_blocked() is not None and time.monotonic() < deadline:
                time.sleep(0.01)
            outcome["refused"] = main(["home", "joint1", *bus])  # FAILPROOF: refused
            outcome["switch"] = int(rt.manager.switch_controller("pd", timeout=DEMO_WAIT))
            outcome["home"] = main(["home", "joint1", "--timeout-homing", "10", *bus])
            seen.update(rt.status())  # why, should the home have been refused
            rt.loop.stop("test")
        t = threading.Thread(target=operate)
        t.start()
        rt.run(duration=DEMO_RUN, signals=False)
        t.join(DEMO_WAIT)
    out, err = capsys.readouterr()
    assert outcome == {"refused": 1, "switch": 0, "home": 0}, (out, err, seen)
    assert "cannot home: the manager is not OK" in err
    assert "joint1: homed" in out


def test_a_queued_request_does_not_survive_an_estop(rig):
    """Requested, then e-stopped before the cycle took it: it fails, and never starts."""
    mark = rig.recorder.mark()
    future = rig.hw.home("j1")
    rig.mgr.emergency_stop("test")
    _run_until_done(rig, future, ENDED)
    with pytest.raises(HomingFailed, match="before homing started"):
        future.result()
    rig.run(10 * rig.dt)
    frames = [struct.unpack_from("<Hb", f.data) for f in rig.recorder.frames(0x201, since=mark)]
    assert all(mode != HOMING_MODE for _, mode in frames)


def test_status_shows_a_new_request_not_the_last_result(rig):
    first = rig.hw.home("j1")
    _run_until_done(rig, first, HOMING)
    assert rig.hw.drive_status()[0].homing == "homed"
    rig.mgr.add_controller(Sine("again", JointMode.CSP, amplitude=0.1))
    assert rig.switch("again") == SwitchResult.SWITCHED
    assert rig.run_until(lambda: rig.hw.all_enabled, VIRTUAL.enable_budget())
    rig.hw.home("j1")
    assert rig.hw.drive_status()[0].homing == "requested"


@pytest.mark.parametrize("method, timeout, why", [
    (99, 60.0, "homing error \\(statusword bit 13\\)"),  # the simulator knows 1..37
    (35, 0.05, "not homed within 0.05 s"),              # it takes 0.2 s
])
def test_a_homing_error_or_timeout_ends_as_failed(method, timeout, why, sim_segment_factory,
                                                  bus_factory):
    sim_segment_factory([1])
    r = Rig.for_setup(bus_factory(), [1], VIRTUAL, modes=("csp",),
                      drive={"homing_method": method, "homing_timeout": timeout})
    try:
        assert r.run_until(lambda: not r.hw.starting, VIRTUAL.bring_up_budget(1))
        r.mgr.add_controller(Sine("sine", JointMode.CSP, amplitude=0.1))
        assert r.switch("sine") == SwitchResult.SWITCHED
        future = r.hw.home("j1")
        _run_until_done(r, future, HOMING)
        with pytest.raises(HomingFailed, match=why):
            future.result()
    finally:
        r.close()


def test_a_bit_12_left_set_before_the_start_counts_only_after_it_was_low():
    from concurrent.futures import Future

    from rocoma_can.drivers.cycle.homing import SW_HOMING_ATTAINED, HomingJob
    homed = SW_HOMING_ATTAINED | 0x0400  # bit 12 + target reached
    job = HomingJob(0, "j", 10.0, Future())
    assert job.step(True, homed, 0.0) is not None       # stale: set before the start edge
    for t in range(1, 6):
        assert job.step(True, homed, t * 0.01) is not None  # never seen low: not homed
    job.step(True, 0x0400, 0.1)                          # homing in progress
    assert job.step(True, homed, 0.11) is None and job.future.result() == "j: homed"
    fresh = HomingJob(0, "j", 10.0, Future())            # low before the start: a set bit
    fresh.step(True, 0x0400, 0.0)                        # after it is the drive's answer
    t = 0.0
    while not fresh.done() and t < 1.0:
        t += 0.01
        fresh.step(True, homed, t)
    assert fresh.future.result() == "j: homed"


def test_a_home_right_after_a_switch_is_taken(rig):
    """The manager is OK once a switch commits, and the hardware hears of it at its next
    write: a home asked in between was refused as "the manager is not OK" (the CLI test
    over the node lost that race once, at 100 Hz). It is judged on the manager's state, which
    the caller passes (the hardware does not hold the manager)."""
    rig.mgr.failproof_stop("test")
    rig.run(3 * rig.dt)
    assert rig.mgr.clear_emergency_stop() or not rig.mgr.estop_latched
    rig.mgr.add_controller(Sine("again", JointMode.CSP, amplitude=0.1))
    switched = rig.mgr.request_switch("again")
    assert switched.result(timeout=VIRTUAL.stall) == SwitchResult.SWITCHED  # no cycle ran
    future = rig.hw.home("j1", manager_state=rig.mgr.state)  # as runtime.system does
    _run_until_done(rig, future, HOMING)
    assert future.result() == "j1: homed"


def test_the_manager_state_the_caller_passes_is_judged_even_when_failproof(rig):
    """FAILPROOF is 0, a false value: the state the caller passes must still be the one
    judged, never the last cycle's OK (a home asked right after an e-stop is refused)."""
    assert rig.mgr.state is ManagerState.OK  # the cycles so far wrote OK
    with pytest.raises(HomingFailed, match="j1: cannot home: the manager is not OK"):
        rig.hw.home("j1", manager_state=ManagerState.FAILPROOF)
    assert rig.hw.drive_status()[0].homing == ""  # nothing was queued
