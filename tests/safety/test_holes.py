"""Issue 11's safety holes, each driven over the virtual bus against simulated drives with the
real hardware layer, manager and manager node: what a hostile or garbled input gets, and that
the last line of defence (the drives' own switch-off) still holds afterwards.

Only the control loop may produce the manager's heartbeat: if anything else kept beating
after the loop hung, the drives' heartbeat consumers would never time out and 0x6007 would
never switch them off.
"""
from __future__ import annotations

import logging
import struct
import threading
import time

import can
import numpy as np
import pytest
from canopen.sdo.constants import ABORT_WRITE_READONLY
from canopen.sdo.exceptions import SdoAbortedError
from fixtures.driver_rig import MANAGER_NODE_ID, seconds_until_all_off
from fixtures.manager_probes import (
    LAYER_METHODS,
    CommandLog,
    EmergencyProbe,
    FailproofProbe,
    Journal,
    Probe,
    layered_manager,
)
from safety_rig import SAFETY, SDO_RX, cycle_while, sdo_exchange
from test_services import ESTOP_COB as SERVICE_ESTOP

from rocoma_can import ControllerManager, ManagerState, SwitchResult
from rocoma_can.drivers.cia402 import State402
from rocoma_can.errors import Refused
from rocoma_can.node.client import ManagerClient
from rocoma_can.node.objects import (
    ABORT_NOT_FOUND,
    ABORT_REFUSED,
    ABORT_TOO_LONG,
    MAX_DOWNLOAD,
)
from rocoma_can.runtime.config import ConfigError, load, validate

NMT_START, NMT_STOP, NMT_PRE_OP, NMT_RESET_NODE, NMT_RESET_COMM = 0x01, 0x02, 0x80, 0x81, 0x82
OK, FAILPROOF = ManagerState.OK, ManagerState.FAILPROOF


SEQUENCES = {
    "sdo-write-1017": [("sdo", 0x1017, 10)],
    "sdo-write-1017-zero-then-ten": [("sdo", 0x1017, 0), ("sdo", 0x1017, 10)],
    "nmt-reset-communication": [("nmt", NMT_RESET_COMM, MANAGER_NODE_ID)],
    "nmt-reset-node-broadcast": [("nmt", NMT_RESET_NODE, 0)],
    "nmt-pre-op-start-stop": [("nmt", NMT_PRE_OP, MANAGER_NODE_ID),
                              ("nmt", NMT_START, MANAGER_NODE_ID),
                              ("nmt", NMT_STOP, MANAGER_NODE_ID)],
    "nmt-reset-then-sdo-1017": [("nmt", NMT_RESET_COMM, 0), ("sdo", 0x1017, 5),
                                ("nmt", NMT_START, 0)],
}


@pytest.mark.parametrize("sequence", list(SEQUENCES.values()), ids=list(SEQUENCES))
def test_only_the_loop_produces_the_manager_heartbeat(served, sequence):
    segment, rig, client, network = served.segment, served.rig, served.client, served.network

    def traffic() -> None:
        for kind, a, b in sequence:
            if kind == "sdo":
                with pytest.raises(SdoAbortedError) as refused:
                    client.sdo.download(0x1017, 0, struct.pack("<H", b))
                assert refused.value.code == ABORT_WRITE_READONLY
            else:
                network.send_message(0x000, bytes((a, b)))
    cycle_while(rig, traffic)
    rig.run(10 * rig.dt)
    # the period the loop uses is what 0x1017 says
    assert struct.unpack("<H", client.sdo.upload(0x1017, 0))[0] == SAFETY.heartbeat_ms
    # the loop hangs (no more cycles): nothing else beats, every drive switches itself off
    stopped = time.monotonic()
    consumer = rig.hw.consumer_ms / 1000
    elapsed = seconds_until_all_off(segment, stopped, consumer + SAFETY.stall)
    assert elapsed <= consumer + SAFETY.stall
    assert all(d.state402 == State402.SWITCH_ON_DISABLED for d in segment.drives.values())


# --- every callback result is judged inside the adapter's guard --------------------------------
class NoTruthValue:
    """A result that cannot even be judged or printed: its __bool__ and __repr__ raise."""

    def __bool__(self) -> bool:
        raise RuntimeError("no truth value")

    def __repr__(self) -> str:
        raise RuntimeError("no repr either")


BAD_RESULTS = {"none": None, "false": False, "one": 1, "non-empty-list": ["ok"],
               "numpy-array": np.array([True, False]), "no-truth-value": NoTruthValue()}
# get_swap_state returns a state, the failproof advance nothing: every other call is judged
JUDGED_CALLS = [lm for lm in LAYER_METHODS
                if lm not in (("controller", "get_swap_state"), ("failproof", "advance"))]


@pytest.mark.parametrize("result", list(BAD_RESULTS.values()), ids=list(BAD_RESULTS))
@pytest.mark.parametrize("layer,method", JUDGED_CALLS, ids=[f"{a}.{b}" for a, b in JUDGED_CALLS])
def test_only_true_is_success_and_nothing_escapes(layer, method, result, caplog):
    """Whatever a callback returns, only True is success; anything else is that call's
    failure, handled as rocoma does (the same as a raise): nothing escapes update(), the
    switcher, the stoppers or shutdown, every e-stop ends in FAILPROOF, no thread is left."""
    mgr, added = layered_manager(layer, returns={method: result})
    if (layer, method) == ("controller", "create"):
        assert not added and mgr.available_controllers() == ["b"]
    else:
        switched = mgr.switch_controller("a")
        assert switched == (SwitchResult.ERROR if method == "initialize" else SwitchResult.SWITCHED)
        states = [mgr.update() for _ in range(3)]
        if (layer, method) == ("controller", "advance"):  # fails at once: never commands
            assert states[0] is not OK
        mgr.emergency_stop()
        mgr.update()
        mgr.emergency_stop()
        assert mgr.update() is FAILPROOF
        assert mgr.switch_controller("b") == SwitchResult.SWITCHED  # the switcher survived
        assert mgr.update() is OK
    with caplog.at_level(logging.ERROR, logger="rocoma_can.manager"):
        assert mgr.shutdown() == (method != "cleanup")  # a failed cleanup is reported
    assert "must return True" in caplog.text
    assert not [t for t in threading.enumerate() if t.name.startswith("rocoma/")]
    assert mgr.internal_errors == 0


# --- the manager node's services refuse what they cannot honour -----------------------------
@pytest.mark.parametrize("value", [0x800, 0x7FFFFFFF, 0x40000000])
def test_estop_cob_id_out_of_range_is_refused_never_masked(service, value):
    service.manager.failproof_stop()  # a stopped manager: changing it is allowed
    assert service.wait_state(0)
    with pytest.raises(Refused) as refused:
        service.client.write(0x2130, value)
    assert refused.value.code == ABORT_NOT_FOUND
    assert service.node.estop_cob_id == SERVICE_ESTOP  # unchanged: the CAN e-stop still works


def test_estop_cob_id_changes_only_while_stopped_or_latched(service, caplog):
    assert service.client.switch("pd") == 0
    with pytest.raises(Refused) as refused:
        service.client.write(0x2130, 0x0B0)
    assert refused.value.code == ABORT_REFUSED and service.node.estop_cob_id == SERVICE_ESTOP
    service.client.write(0x2111, 1)  # failproof stop
    assert service.wait_state(0)
    with caplog.at_level(logging.WARNING, logger="rocoma_can.node.server"):
        service.client.write(0x2130, 0x0B0)
    assert service.node.estop_cob_id == 0x0B0 and "e-stop COB-ID changed" in caplog.text
    service.client.write(0x2130, 0x80000000)  # bit 31: not valid = off
    assert service.node.estop_cob_id == 0


def test_switch_name_that_is_not_utf8_is_refused(service):
    """b"p\xffd" used to be decoded with errors ignored, as "pd", and switched."""
    name = b"p\xffd"
    answer = sdo_exchange(service.raw, bytes([0x21, 0x00, 0x21, 0x00, len(name), 0, 0, 0]))
    assert answer[0] == 0x60  # segmented download initiated
    answer = sdo_exchange(service.raw,
                           bytes([(7 - len(name)) << 1 | 1]) + name.ljust(7, b"\x00"))
    assert answer[0] == 0x80 and struct.unpack_from("<I", answer, 4)[0] == ABORT_NOT_FOUND
    assert service.manager.active_controller_name == "torque_off"


def test_aborted_segmented_write_never_takes_effect(service):
    bus = service.raw
    name = b"pd"
    answer = sdo_exchange(bus, bytes([0x21, 0x00, 0x21, 0x00, len(name), 0, 0, 0]))
    assert answer[0] == 0x60
    # the client aborts the transfer, then a stray last segment arrives
    bus.send(can.Message(arbitration_id=SDO_RX, is_extended_id=False,
                         data=bytes([0x80, 0x00, 0x21, 0x00]) + struct.pack("<I", 0x08000000)))
    answer = sdo_exchange(bus, bytes([(7 - len(name)) << 1 | 1]) + name.ljust(7, b"\x00"))
    assert answer[0] == 0x80  # refused: no download is open
    time.sleep(0.2)
    assert service.manager.active_controller_name == "torque_off"


def test_an_sdo_download_longer_than_any_name_is_aborted_as_it_comes(service, bus_factory):
    """A sender streaming segments for ever (or announcing 100 kB) is aborted 0x06070012 at
    MAX_DOWNLOAD bytes, never buffered on and never echoed back; the node serves on."""
    announce = bytes([0x21, 0x00, 0x21, 0x00]) + struct.pack("<I", 100_000)
    answer = sdo_exchange(service.raw, announce)
    assert answer[0] == 0x80 and struct.unpack_from("<I", answer, 4)[0] == ABORT_TOO_LONG
    answer = sdo_exchange(service.raw, bytes([0x20, 0x00, 0x21, 0x00, 0, 0, 0, 0]))  # no size
    assert answer[0] == 0x60
    toggle, sent = 0, 0
    while True:
        answer = sdo_exchange(service.raw, bytes([toggle << 4]) + b"x" * 7)
        if answer[0] == 0x80:
            break
        assert answer[0] == 0x20 | toggle << 4, answer.hex()
        toggle, sent = toggle ^ 1, sent + 7
    assert struct.unpack_from("<I", answer, 4)[0] == ABORT_TOO_LONG
    assert sent <= MAX_DOWNLOAD < sent + 7  # aborted at the limit, not later
    assert service.manager.active_controller_name == "torque_off"
    # the node serves on: a client of its own (service.client's bus saw the raw exchange,
    # and its reader may hand the last abort over late, as if it answered this switch)
    with ManagerClient(bus_factory(), MANAGER_NODE_ID, timeout=SAFETY.stall) as client:
        assert client.switch("pd") == 0


def test_remote_frame_on_the_estop_cob_id_estops(service):
    assert service.client.switch("pd") == 0
    service.client.bus.send(can.Message(arbitration_id=SERVICE_ESTOP, is_extended_id=False,
                                        is_remote_frame=True, dlc=0))
    assert service.wait_state(1)  # EMERGENCY: the smart stop runs


def test_expedited_estop_without_size_indicated_estops(service):
    assert service.client.switch("pd") == 0
    answer = sdo_exchange(service.raw, bytes([0x22, 0x10, 0x21, 0x00, 1, 0, 0, 0]))
    assert answer[0] == 0x60, answer.hex()  # accepted
    assert service.wait_state(1)


# --- bad input is a clear error, never a traceback --------------------------------------------
BILLION_LAUGHS = "a: &a [x, x, x, x, x, x, x, x, x, x]\n" + "".join(
    f"{chr(ord('b') + i)}: &{chr(ord('b') + i)} [{', '.join(['*' + chr(ord('a') + i)] * 10)}]\n"
    for i in range(8))


def _good_config(tmp_path, **drive) -> dict:
    return {"bus": {"interface": "virtual", "channel": "x"}, "rate": 100,
            "drives": [dict({"name": "j1", "node_id": 1, "increments_per_rev": 1 << 20,
                             "rated_torque_nm": 1.0}, **drive)]}


@pytest.mark.parametrize("case", ["alias-bomb", "self-reference", "too-big", "not-utf8",
                                  "deep-nesting"])
def test_hostile_yaml_is_refused_quickly_and_clearly(tmp_path, case):
    path = tmp_path / "robot.yaml"
    content = {"alias-bomb": BILLION_LAUGHS.encode(),
               "self-reference": b"a: &a [*a]\n",
               "too-big": b"# " + b"x" * (2 << 20) + b"\n",
               "not-utf8": b"rate: \xff\xfe\n",
               "deep-nesting": b"[" * 5000 + b"]" * 5000 + b"\n"}[case]
    path.write_bytes(content)
    with pytest.raises(ConfigError) as refused:
        load(path)
    assert all(p.startswith(f"{path}: ") for p in refused.value.problems), refused.value.problems


@pytest.mark.parametrize("key", ["node_id", "increments_per_rev", "heartbeat_ms"])
def test_a_bool_is_not_a_whole_number(tmp_path, key):
    with pytest.raises(ConfigError) as refused:
        validate(_good_config(tmp_path, **{key: True}))
    assert any(f"drives[0]: drive 'j1': {key}" in p for p in refused.value.problems), \
        refused.value.problems


@pytest.mark.parametrize("content", [b"\x00\x01\x02binary\xff" * 100, b"just some text\n",
                                     b"[1000]\nParameterName=Device type\n"],
                         ids=["binary", "not-ini", "no-pdo-objects"])
def test_every_eds_is_parsed_and_checked_at_config_time(tmp_path, content):
    eds_path = tmp_path / "vendor.eds"
    eds_path.write_bytes(content)
    with pytest.raises(ConfigError) as refused:
        validate(_good_config(tmp_path, eds=str(eds_path)), source="robot.yaml")
    problem = "\n".join(refused.value.problems)
    assert problem.startswith("robot.yaml: drives[0]: drive 'j1': ") and (
        "vendor.eds" in problem or "EDS has no" in problem), problem


# --- a lower layer never inherits the failed layer's command ----------------------------------
def test_a_failing_reset_command_falls_through_to_failproof():
    """reset_command (the hardware's neutral command) runs on every fall; if it raises, the
    emergency controller would start from the failed controller's command: FAILPROOF."""
    journal = Journal(update_thread=threading.get_ident())
    resets: list[object] = []

    def reset(command) -> None:
        resets.append(command)
        raise RuntimeError("reset_command broken")
    mgr = ControllerManager(FailproofProbe("failproof", journal), dt=0.001, timing=None,
                            command=CommandLog(), reset_command=reset)
    mgr.add_controller(Probe("a", journal, fail={"advance"}),
                       emergency=EmergencyProbe("e", journal))
    try:
        assert mgr.switch_controller("a") == SwitchResult.SWITCHED
        assert mgr.update() is FAILPROOF
        assert len(resets) == 1 and mgr.internal_errors == 1
        assert not journal.of("e", "initialize_fast")
    finally:
        assert mgr.shutdown()
