"""Shared instruments of the safety matrix: a served rig (simulated drives, the real hardware
layer, manager and manager node, brought up and holding) and raw-frame helpers."""
from __future__ import annotations

import threading
import time
from collections.abc import Callable, Iterator
from dataclasses import dataclass, replace

import can
import canopen
from fixtures.driver_rig import MANAGER_NODE_ID, VIRTUAL, Can, Rig
from fixtures.recorder import FrameRecorder
from fixtures.rig_controllers import HoldPD

from rocoma_can import SwitchResult, eds
from rocoma_can.drivers.sim.segment import SimulatedSegment
from rocoma_can.node.server import ManagerNode

NODES = (1, 2, 3)
#: The virtual-bus setup on three drives (its supervision outlasts the host's stall: the
#: matrix checks which documented state each fault ends in, and a stall of this one process
#: taken for a second, unrelated drive fault would end EMERGENCY in FAILPROOF).
SAFETY: Can = replace(VIRTUAL, nodes=NODES)
ESTOP_COB = 0x0A0
SDO_RX, SDO_TX = 0x600 + MANAGER_NODE_ID, 0x580 + MANAGER_NODE_ID
CW_DISABLE_VOLTAGE = b"\x00\x00"  # RPDO1 bytes 0-1: controlword 0x0000


@dataclass
class Served:
    segment: SimulatedSegment
    rig: Rig
    node: ManagerNode
    client: canopen.RemoteNode
    network: canopen.Network
    recorder: FrameRecorder


def served_rig(segment: SimulatedSegment, rig_bus: can.BusABC, node_bus: can.BusABC,
               client_bus: can.BusABC, recorder: FrameRecorder) -> Iterator[Served]:
    """Generator for a fixture: drives brought up, controllers "hold" (active, enabled) and
    "other", the manager node (e-stop COB-ID 0x0A0) on a bus of its own and a canopen SDO/NMT
    client on a third; closed in order afterwards."""
    rig = Rig.for_setup(rig_bus, NODES, SAFETY)
    node = ManagerNode(rig.mgr, MANAGER_NODE_ID, node_bus, estop_cob_id=ESTOP_COB,
                       heartbeat_ms=SAFETY.heartbeat_ms).start()
    network = canopen.Network(client_bus)
    network.connect()
    client = network.add_node(MANAGER_NODE_ID, str(eds.path(eds.MANAGER_NODE)))
    client.sdo.RESPONSE_TIMEOUT = 1.0
    try:
        assert rig.run_until(lambda: not rig.hw.starting,
                             SAFETY.bring_up_budget(len(NODES))), rig.hw.drive_status()
        rig.mgr.add_controller(HoldPD())
        rig.mgr.add_controller(HoldPD(name="other"))
        assert rig.switch("hold") == SwitchResult.SWITCHED
        assert rig.run_until(lambda: rig.hw.all_enabled, SAFETY.enable_budget())
        yield Served(segment, rig, node, client, network, recorder)
    finally:
        network.disconnect()
        node.close()
        rig.close()
    left = [t.name for t in threading.enumerate() if t.name.startswith("rocoma/")]
    assert not left, f"threads left after shutdown: {left}"


def cycle_while(rig: Rig, action: Callable[[], object]) -> None:
    """Run ``action`` (SDO/NMT traffic) on a thread while the loop keeps cycling, as in the
    field; its exception is raised here."""
    done = threading.Event()
    errors: list[BaseException] = []

    def run() -> None:
        try:
            action()
        except BaseException as exc:  # noqa: BLE001 - re-raised on the test's thread
            errors.append(exc)
        finally:
            done.set()
    thread = threading.Thread(target=run)
    thread.start()
    while not done.is_set():
        rig.cycle()
    thread.join()
    if errors:
        raise errors[0]


def sdo_exchange(bus: can.BusABC, request: bytes, node_id: int = MANAGER_NODE_ID,
                 timeout: float = 2.0,
                 answers: Callable[[bytes], bool] = lambda data: True) -> bytes:
    """One raw SDO request, the first answer that ``answers`` accepts (bounded)."""
    bus.send(can.Message(arbitration_id=0x600 + node_id, data=request, is_extended_id=False))
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        msg = bus.recv(0.1)
        if msg is not None and msg.arbitration_id == 0x580 + node_id and answers(bytes(msg.data)):
            return bytes(msg.data)
    raise AssertionError(f"no SDO answer to {request.hex()} within {timeout} s")
