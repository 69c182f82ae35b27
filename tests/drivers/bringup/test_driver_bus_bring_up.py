"""drivers/bringup/drive_bringup.py: the CAN driver's bring-up against simulated CiA 402 drives,
over a real python-can bus.

What must hold: every drive is configured as the safety model needs it (heartbeat consumer
on the manager, 0x6007, its PDOs) and reaches operation enabled; a drive that cannot (STO
low) or does not answer is reported and does not hold the others back; the phases are
reported; the configuration workers exist before the first cycle; every ready drive
already watches the manager's heartbeat.

The tests that take the segment, make_rig or recorder fixture run twice: on python-can's
virtual bus at 200 Hz with six drives (fast suite) and on SocketCAN vcan0 at 25 Hz with three
(vcan suite, through tools/vcan-run; see driver_rig.VCAN for why). Assertions are on states,
events and the frames seen on the bus, never on wall time.
"""
from __future__ import annotations

import struct
import threading
import time

import canopen
import pytest
from fixtures.driver_rig import MANAGER_NODE_ID, bring_up, drive_configs, enable_with, synced_mark
from fixtures.odd_node import OddNode
from fixtures.rig_controllers import HoldPD

from rocoma_can import ManagerState, SwitchResult
from rocoma_can.drivers.bringup.drive_bringup import BringupPhase
from rocoma_can.drivers.protocol import cia301, cia402
from rocoma_can.drivers.protocol.cia402 import State402


def test_bring_up_six_drives_to_operation_enabled(segment, make_rig, can_setup):
    rig = make_rig()
    bring_up(rig)
    assert rig.hw.all_ready, rig.hw.drive_status()
    # every drive was configured as the safety model needs it
    for _n, drive in segment.drives.items():
        assert drive.nmt_state == cia301.NmtState.OPERATIONAL
        assert drive.od_value(cia301.CONSUMER_HEARTBEAT_TIME, 1) == \
            (MANAGER_NODE_ID << 16) | rig.hw.consumer_ms
        assert drive.od_value(cia402.ABORT_CONNECTION_OPTION) == \
            cia402.AbortConnectionOption.DISABLE_VOLTAGE
    assert rig.hw.consumer_ms == round(can_setup.consumer_factor * can_setup.heartbeat_ms)
    # 3 modes per drive: 2 RPDOs + 2 TPDOs each, + SYNC
    assert rig.hw.frames_per_cycle == len(segment.drives) * 4 + 1
    enable_with(rig, HoldPD())
    assert rig.mgr.state == ManagerState.OK
    assert all(d.state402 == State402.OPERATION_ENABLED for d in segment.drives.values())
    assert all(s.enabled and s.fault is None for s in rig.hw.drive_status())


def test_drive_with_sto_low_does_not_hold_the_others_back(segment, make_rig):
    nodes = tuple(segment.drives)
    sto = nodes[-1]
    segment.drives[sto].set_sto(True)
    rig = make_rig(required=range(len(nodes) - 1))  # run degraded without the STO drive
    bring_up(rig)
    status = {s.node_id: s for s in rig.hw.drive_status()}
    assert status[sto].phase == "FAILED" and "STO" in status[sto].fault
    assert all(status[n].phase == "READY" for n in nodes if n != sto)
    refusal = rig.hw.not_ready()  # with every drive required, a switch would be refused
    assert refusal is not None and f"j{sto} (FAILED: " in refusal and "STO" in refusal
    rig.mgr.add_controller(HoldPD())
    assert rig.switch("hold") == SwitchResult.SWITCHED
    others = [n for n in nodes if n != sto]
    assert rig.run_until(lambda: all(segment.drives[n].state402 == State402.OPERATION_ENABLED
                                     for n in others), rig.setup.enable_budget()), \
        rig.hw.drive_status()
    rig.run(0.2)
    assert rig.mgr.state == ManagerState.OK
    assert segment.drives[sto].state402 == State402.SWITCH_ON_DISABLED


def test_drive_that_does_not_answer_is_reported(segment, make_rig):
    nodes = tuple(segment.drives)
    rig = make_rig(nodes=nodes + (9,))  # no drive 9 on the segment
    bring_up(rig)
    status = {s.node_id: s for s in rig.hw.drive_status()}
    assert status[9].phase == "FAILED" and "did not answer (SDO 0x1000" in status[9].fault
    assert all(status[n].phase == "READY" for n in nodes)


def test_closing_ends_a_configuration_waiting_on_a_silent_drive(segment, make_rig,
                                                                  recorder):
    """The hardware closes (the run's end, a Ctrl-C) while a drive that is not there holds
    a configuration worker in its SDO wait: the close waited out canopen's timeout and then
    the attempts left (seconds, a drive and a retry at a time) before it could return. The
    wait ends at once, no further attempt is made, the worker ends with the close."""
    sdo_timeout = 30.0
    rig = make_rig(nodes=(9,), sdo_timeout=sdo_timeout)
    request = 0x600 + 9
    assert rig.run_until(lambda: recorder.count(request) > 0, rig.setup.bring_up_budget(1)), \
        rig.hw.drive_status()
    asked = recorder.frames(request)[0]  # the upload of 0x1000, the drive's first question
    assert asked.data[:4] == bytes([0x40, 0x00, 0x10, 0x00]), asked
    started = time.monotonic()
    rig.close()
    took = time.monotonic() - started
    assert took < sdo_timeout / 2, took  # the wait was cut short, not timed out
    assert recorder.count(request) == 1  # no attempt after the close
    assert not [t for t in threading.enumerate() if t.name.startswith("canopen-config")]


@pytest.mark.parametrize("garbage", [b"", b"\x43\x00"])
def test_a_node_answering_garbled_sdo_frames_fails_its_bring_up_in_one_line(virtual_channel,
                                                                              garbage):
    """A device at the drive's node id that answers SDO with frames shorter than SDO's
    8 bytes: canopen's struct.error text was the drive's failure ("unpack requires a buffer
    of 3 bytes"). The failure says what it means and what to check."""
    from rocoma_can.drivers.bringup.configure import configure
    from rocoma_can.drivers.plan.drive_plan import plan_drive
    odd = OddNode(virtual_channel, lambda request: [garbage])
    network = canopen.Network()
    network.connect(interface="virtual", channel=virtual_channel, ignore_config=True)
    try:
        node = network.add_node(OddNode.NODE, canopen.ObjectDictionary())
        with pytest.raises(RuntimeError) as failed:
            configure(node, plan_drive(drive_configs((OddNode.NODE,))[0]), MANAGER_NODE_ID,
                      200, attempts=1)
        assert str(failed.value).startswith("a malformed SDO answer (shorter than an SDO "
                                            "frame: "), failed.value
        assert str(failed.value).endswith(f"is node {OddNode.NODE} the CANopen drive the "
                                          "config says, or is another device answering at "
                                          "its id?")
    finally:
        network.disconnect()
        odd.close()


def test_bring_up_phases_are_reported(segment, make_rig):
    rig = make_rig()
    assert {s.phase for s in rig.hw.drive_status()} == {BringupPhase.WAIT_BOOT.name}
    bring_up(rig)
    assert {s.phase for s in rig.hw.drive_status()} == {BringupPhase.READY.name}


def test_the_configuration_workers_are_started_before_the_first_cycle(make_rig):
    """Bring-up submits SDO work from the cycle; a ThreadPoolExecutor starts a thread on a
    submit that finds none idle, which the cycle must never do: start() starts them all."""
    before = set(threading.enumerate())  # threads, not idents: an ident is reused
    rig = make_rig()
    workers = [t for t in threading.enumerate()
               if t.name.startswith("canopen-config") and t not in before]
    assert len(workers) == min(rig.hw.config_workers, len(rig.hw.drives_config))


def test_every_ready_drive_already_watches_the_manager_heartbeat(segment, make_rig, recorder):
    """A heartbeat consumer only starts watching with the first heartbeat it receives, so the
    hardware sends one as soon as a drive's consumer is configured: a loop that stops right
    after bring-up still makes every drive report the loss (EMCY 0x8130)."""
    rig = make_rig()
    bring_up(rig)
    mark = synced_mark(recorder, rig)  # and the loop stops here
    nodes = tuple(segment.drives)
    emcy = {cia301.EMCY + n for n in nodes}
    lost = recorder.wait_for_count(
        len(nodes), rig.hw.consumer_ms / 1000 + rig.setup.stall, emcy, since=mark,
        where=lambda f: struct.unpack_from("<H", f.data)[0] == cia301.EMCY_HEARTBEAT)
    assert {f.cob_id - cia301.EMCY for f in lost} == set(nodes)
