"""The manager's CANopen node in-process on the virtual bus: SDO services through a real
canopen client, the e-stop COB-ID, and the state / EMCY frames seen by a third listener."""
from __future__ import annotations

import threading
import time

import can
import pytest

from joint_plant import JointPlant
from rocoma_can import ControllerManager, add_to_manager
from rocoma_can.controllers.torque_off import TorqueOff
from rocoma_can.services import (ABORT_NOT_FOUND, ABORT_REFUSED, ManagerClient, ManagerNode,
                                 NoAnswer, Refused)

NODE = 100
ESTOP_COB = 0x0A0
CONTROLLERS = {
    "controllers": [
        {"name": "pd", "plugin": "pd", "emergency": "damp", "params": {"mode": "CSP"}},
        {"name": "trajectory", "plugin": "trajectory", "emergency": "damp",
         "params": {"amplitude": 0.1, "frequency": 1.0}},
    ],
    "emergency_controllers": [{"name": "damp", "plugin": "damp"}],
}


class Rig:
    """A manager cycled by a thread (200 Hz) over a joint plant, served as node 100."""

    def __init__(self, bus_factory, must_clear: bool) -> None:
        self.plant = JointPlant(3, dt=0.005)
        self.manager = ControllerManager(TorqueOff(), 0.005, self.plant.state, self.plant.command,
                                         estop_must_be_cleared=must_clear)
        add_to_manager(self.manager, CONTROLLERS)
        self.recovered = 0
        self.node = ManagerNode(self.manager, NODE, bus_factory(), estop_cob_id=ESTOP_COB,
                                status_period=0.05, recover=self._recover).start()
        self.client = ManagerClient(bus_factory(), NODE, timeout=1.0)
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._loop, name="test-cycle")
        self._thread.start()

    def _recover(self) -> None:
        self.recovered += 1

    def _loop(self) -> None:
        while not self._stop.wait(0.005):
            self.manager.update()
            self.plant.step()

    def wait_state(self, state: int, timeout: float = 2.0) -> bool:
        deadline = time.monotonic() + timeout
        while time.monotonic() < deadline:
            if int(self.manager.state) == state:
                return True
            time.sleep(0.005)
        return False

    def wait_cause(self, text: str, timeout: float = 2.0) -> str:
        """0x2124 is set from the manager's event thread, just after the state changes."""
        deadline = time.monotonic() + timeout
        while True:
            cause = self.client.read(0x2124)
            if text in cause or time.monotonic() > deadline:
                return cause
            time.sleep(0.01)

    def close(self) -> None:
        self._stop.set()
        self._thread.join(5.0)
        self.client.close()
        self.node.close()
        self.manager.shutdown()


@pytest.fixture
def rig(bus_factory, request):
    r = Rig(bus_factory, must_clear=getattr(request, "param", False))
    yield r
    r.close()


def test_status_and_list(rig):
    assert rig.client.controllers() == ["pd", "trajectory"]
    status = rig.client.status()
    assert status["state"] == "FAILPROOF" and status["active"] == "torque_off"
    assert status["estop_cob_id"] == ESTOP_COB and status["latched"] is False


def test_switch_by_name_and_index(rig):
    assert rig.client.switch("pd") == 0
    assert rig.manager.active_controller_name == "pd" and int(rig.manager.state) == 2
    assert rig.client.switch("pd") == 1  # RUNNING: already active
    assert rig.client.switch("2") == 0
    assert rig.manager.active_controller_name == "trajectory"
    assert rig.client.read(0x2122) == 2 and rig.client.read(0x2121) == "trajectory"


def test_unknown_controller_is_a_distinct_abort(rig):
    for name in ("nope", "damp", "9"):  # emergency controllers are not switchable
        with pytest.raises(Refused) as info:
            rig.client.switch(name)
        assert info.value.code == ABORT_NOT_FOUND
        assert rig.client.read(0x2102) == 2
    assert int(rig.manager.state) == 0


@pytest.mark.parametrize("rig", [True], indirect=True)
def test_latched_estop_refuses_switch_until_cleared(rig):
    assert rig.client.status()["latched"] is True
    with pytest.raises(Refused) as info:
        rig.client.switch("pd")
    assert info.value.code == ABORT_REFUSED and rig.client.read(0x2102) == 3
    rig.client.write(0x2112, 1)
    assert rig.client.switch("pd") == 0


def test_sdo_estop_failproof_and_recover(rig):
    assert rig.client.switch("pd") == 0
    rig.client.write(0x2110, 1)
    assert rig.wait_state(1)
    assert rig.manager.active_controller_name == "damp"
    rig.client.write(0x2111, 1)
    assert rig.wait_state(0)
    assert "SDO failproof stop" in rig.wait_cause("SDO failproof stop")
    rig.client.write(0x2113, 1)
    assert rig.recovered == 1


def test_estop_frame_from_any_node_and_broadcasts(rig, frame_recorder):
    rec = frame_recorder()
    assert rig.client.switch("pd") == 0
    tpdo = 0x180 + NODE
    rec.wait_for(lambda f: f.cob_id == tpdo and f.data == bytes([2, 1]), timeout=2.0)
    mark = rec.mark()
    raw = rig.client.bus  # any bus handle on the segment: a third node sending one frame
    raw.send(can.Message(arbitration_id=ESTOP_COB, data=b"", is_extended_id=False))
    assert rig.wait_state(1)
    assert rig.wait_cause("CAN e-stop") == f"CAN e-stop from 0x{ESTOP_COB:03X}"
    emcy = rec.wait_for(lambda f: f.cob_id == 0x80 + NODE, timeout=2.0, since=mark)
    assert emcy.data[:4] == bytes([0x00, 0x90, 0x01, 1])
    rec.wait_for(lambda f: f.cob_id == tpdo and f.data == bytes([1, 0]), timeout=2.0, since=mark)
    # periodic repeats of the state frame
    rec.wait_for_count(3, 2.0, tpdo, since=mark, where=lambda f: f.data == bytes([1, 0]))


def test_estop_cob_id_can_be_moved_by_sdo(rig):
    rig.client.write(0x2130, 0x0B5)
    assert rig.node.estop_cob_id == 0x0B5
    assert rig.client.switch("pd") == 0
    rig.client.bus.send(can.Message(arbitration_id=ESTOP_COB, is_extended_id=False))
    time.sleep(0.1)
    assert int(rig.manager.state) == 2  # the old COB-ID no longer e-stops
    rig.client.bus.send(can.Message(arbitration_id=0x0B5, is_extended_id=False))
    assert rig.wait_state(1)


@pytest.mark.parametrize("rig", [True], indirect=True)
def test_clear_sends_emcy_reset(rig, frame_recorder):
    rec = frame_recorder()
    rig.client.write(0x2112, 1)
    frame = rec.wait_for(lambda f: f.cob_id == 0x80 + NODE, timeout=2.0)
    assert frame.data == bytes(8)


def test_no_answer_from_a_wrong_node(bus_factory):
    with ManagerClient(bus_factory(), 42, timeout=0.2) as client:
        with pytest.raises(NoAnswer):
            client.status()
