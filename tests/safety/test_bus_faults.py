"""drivers/link/bus_port.py, rocoma_can/manager.py: the bus and the threads around the loop, against
a holding manager and simulated drives: a bus that refuses frames, and switch / e-stop / clear /
recover storms from several threads. Each ends with torque-off frames for every drive seen on the
bus, the loop cycling and the manager still able to switch (the served fixture checks that no thread
is left)."""
from __future__ import annotations

import random
import threading
from concurrent.futures import Future

from safety_rig import CW_DISABLE_VOLTAGE, NODES, SAFETY, Served

from rocoma_can import ManagerState, SwitchResult
from rocoma_can.drivers.protocol.cia402 import State402


def _torque_off_seen_for_every_drive(served: Served, since: int) -> None:
    for n in NODES:
        served.recorder.wait_for(lambda f, n=n: f.cob_id == 0x200 + n
                                 and f.data[:2] == CW_DISABLE_VOLTAGE,
                                 SAFETY.detect_budget(), since=since)


def _back_to_holding(served: Served) -> None:
    rig = served.rig
    recovered = rig.hw.recover(SAFETY.recovery_budget())
    assert rig.run_until(recovered.done, SAFETY.recovery_budget() + SAFETY.stall)
    assert recovered.result() is True, rig.hw.drive_status()
    assert rig.switch("hold") == SwitchResult.SWITCHED
    assert rig.run_until(lambda: rig.hw.all_enabled, SAFETY.enable_budget())


def test_a_bus_that_refuses_frames_is_a_bus_fault(served, bus_factory, virtual_channel):
    """A node on the bus that stops reading (python-can's virtual bus: its queue of one frame
    full) makes every send fail, while the drives still get the frames. One cycle of refused
    frames is tolerated; as many in a row as missing TPDOs are is a bus fault: an e-stop,
    with the cause, and torque-off frames that are tried every cycle."""
    rig = served.rig
    mark = served.recorder.mark()
    stuck = bus_factory(virtual_channel, rx_queue_size=1)
    budget = rig.hw.supervisor.tpdo_timeout_cycles
    for _ in range(budget - 1):
        assert rig.cycle() is ManagerState.OK
    assert rig.hw.tx_errors > 0 and rig.hw.bus_fault is None
    assert rig.run_until(lambda: rig.mgr.state is not ManagerState.OK, SAFETY.detect_budget())
    assert "refused frames" in rig.hw.bus_fault
    assert rig.cycle() is ManagerState.FAILPROOF  # "hold" has no emergency controller
    _torque_off_seen_for_every_drive(served, mark)
    assert rig.run_until(lambda: all(d.state402 == State402.SWITCH_ON_DISABLED
                                     for d in served.segment.drives.values()),
                         SAFETY.enable_budget())

    # still refusing: recovery does not succeed, and the fault stays
    failed = rig.hw.recover(SAFETY.recovery_budget())
    assert rig.run_until(failed.done, SAFETY.recovery_budget() + SAFETY.stall)
    assert failed.result() is False and "refused frames" in rig.hw.bus_fault
    # the node reads again (here: leaves the bus): recovery, and holding again
    stuck.shutdown()
    _back_to_holding(served)
    assert rig.hw.bus_fault is None


def test_switch_and_estop_storms_from_several_threads(served):
    """Four threads hammer the manager with switches, e-stops, failproof stops, clears and
    recoveries while the loop cycles; afterwards the manager answers, nothing escaped, and
    the operator's e-stops still give torque-off frames for every drive."""
    rig = served.rig
    actions = {
        "switch hold": lambda: rig.mgr.request_switch("hold"),
        "switch other": lambda: rig.mgr.request_switch("other"),
        "switch unknown": lambda: rig.mgr.request_switch("no such controller"),
        "e-stop": lambda: rig.mgr.emergency_stop(cause="storm"),
        "failproof": lambda: rig.mgr.failproof_stop(cause="storm"),
        "clear": rig.mgr.clear_emergency_stop,
        "recover": rig.hw.recover,
    }
    errors: list[BaseException] = []
    futures: list[tuple[str, Future[object]]] = []

    def storm(seed: int) -> None:
        pick = random.Random(seed)
        try:
            for _ in range(200):
                what = pick.choice(sorted(actions))
                result = actions[what]()
                if isinstance(result, Future):
                    futures.append((what, result))
        except BaseException as exc:  # noqa: BLE001 - reported on the test's thread
            errors.append(exc)
    threads = [threading.Thread(target=storm, args=(seed,)) for seed in range(4)]
    for t in threads:
        t.start()
    while any(t.is_alive() for t in threads):
        rig.cycle()
    for t in threads:
        t.join()
    assert not errors
    # every switch and recovery ends (the loop keeps cycling) with a result, never an error
    assert rig.run_until(lambda: all(f.done() for _, f in futures),
                         rig.mgr.timeouts.being_stopped + SAFETY.recovery_budget()), \
        sorted({what for what, f in futures if not f.done()})  # which never ended
    assert {type(f.result()) for _, f in futures} <= {SwitchResult, bool}
    assert rig.mgr.internal_errors == 0

    mark = served.recorder.mark()
    rig.mgr.emergency_stop()
    rig.cycle()
    rig.mgr.emergency_stop()
    assert rig.cycle() is ManagerState.FAILPROOF
    _torque_off_seen_for_every_drive(served, mark)
    _back_to_holding(served)
