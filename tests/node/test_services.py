"""rocoma_can/node/server.py, client.py: the manager's CANopen node in-process on the virtual bus:
SDO services through a real canopen client, the e-stop COB-ID, and the state / EMCY frames seen by a
third listener."""
from __future__ import annotations

import struct
import threading
import time
from collections.abc import Callable
from types import SimpleNamespace

import can
import pytest
from can.interfaces.virtual import VirtualBus
from fixtures.budgets import STALL, within
from fixtures.joint_plant import JointPlant
from fixtures.node_rig import ESTOP_COB, NODE, STATUS_PERIOD, Rig

from rocoma_can import ControllerManager
from rocoma_can.controllers.torque_off import TorqueOff
from rocoma_can.errors import NoAnswer, Refused
from rocoma_can.node.client import ManagerClient
from rocoma_can.node.objects import ABORT_NOT_FOUND, ABORT_REFUSED
from rocoma_can.node.server import ManagerNode


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
    rec.wait_for(lambda f: f.cob_id == tpdo and f.data == bytes([2, 1]), timeout=STALL)
    mark = rec.mark()
    raw = rig.client.bus  # any bus handle on the segment: a third node sending one frame
    raw.send(can.Message(arbitration_id=ESTOP_COB, data=b"", is_extended_id=False))
    assert rig.wait_state(1)
    assert rig.wait_cause("CAN e-stop") == f"CAN e-stop from 0x{ESTOP_COB:03X}"
    emcy = rec.wait_for(lambda f: f.cob_id == 0x80 + NODE, timeout=STALL, since=mark)
    assert emcy.data[:4] == bytes([0x00, 0x90, 0x01, 1])
    rec.wait_for(lambda f: f.cob_id == tpdo and f.data == bytes([1, 0]), timeout=STALL, since=mark)
    # periodic repeats of the state frame
    rec.wait_for_count(3, within(3 * STATUS_PERIOD), tpdo, since=mark,
                       where=lambda f: f.data == bytes([1, 0]))


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
    frame = rec.wait_for(lambda f: f.cob_id == 0x80 + NODE, timeout=STALL)
    assert frame.data == bytes(8)


class LosesOneAnswer(VirtualBus):
    """python-can's virtual bus that loses the first answer of the manager node that
    ``lost(number, data)`` picks (a receiver that overflowed, a host that stalled): the frame
    never reaches the client."""

    def __init__(self, channel: str, lost: Callable[[int, bytes], bool]) -> None:
        super().__init__(channel=channel, receive_own_messages=False)
        self.lost, self.answers, self.dropped = lost, 0, 0

    def _recv_internal(self, timeout):
        msg, filtered = super()._recv_internal(timeout)
        if msg is not None and msg.arbitration_id == 0x580 + NODE:
            self.answers += 1
            if not self.dropped and self.lost(self.answers, bytes(msg.data)):
                self.dropped += 1
                return None, filtered
        return msg, filtered


LOST = {  # which answer of a block upload is lost
    "initiate": lambda n, data: n == 1,
    "segment": lambda n, data: n == 3,  # 1: initiate, 2..: the first block's segments
    "last-segment": lambda n, data: n > 1 and bool(data[0] & 0x80),
    "end": lambda n, data: data[0] & 0xE3 == 0xC1,
}


@pytest.mark.parametrize("lost", list(LOST.values()), ids=list(LOST))
def test_a_status_answer_lost_mid_upload_is_asked_again(bus_factory, virtual_channel, lost):
    """One answer of the node's 0x2140 block upload is lost: a segment's gap is asked for
    again by the block's ack, a lost initiate or end starts the read again
    (client.READ_ATTEMPTS, after an abort), and the status is whole. Before,
    `rocoma-can status` failed with "no answer" (exit 3) on one lost frame, and canopen's
    own block upload raised AttributeError on a lost end."""
    rig = Rig(bus_factory, must_clear=False)
    lossy = LosesOneAnswer(virtual_channel, lost)
    try:
        with ManagerClient(lossy, NODE, timeout=0.2) as client:
            status = client.status()
        assert lossy.dropped == 1
        assert status["state"] == rig.manager.state.name
        assert status["startup_finished"] is True and status["drives"] == []
    finally:
        lossy.shutdown()
        rig.close()


class RepeatsAnswers(VirtualBus):
    """python-can's virtual bus that delivers every answer of the manager node twice (a
    frame seen again after an error frame's retransmission, a bridge that echoes)."""

    def __init__(self, channel: str) -> None:
        super().__init__(channel=channel, receive_own_messages=False)
        self._again: can.Message | None = None
        self.repeated = 0

    def _recv_internal(self, timeout):
        if self._again is not None:
            msg, self._again = self._again, None
            self.repeated += 1
            return msg, False
        msg, filtered = super()._recv_internal(timeout)
        if msg is not None and msg.arbitration_id == 0x580 + NODE:
            self._again = msg
        return msg, filtered


def test_every_answer_twice_still_reads_the_status_whole(bus_factory, virtual_channel):
    """Repeated frames are skipped (a repeated initiate answer or segment), so each block
    is taken once and the CRC matches; nothing is retried for ever."""
    rig = Rig(bus_factory, must_clear=False)
    echoing = RepeatsAnswers(virtual_channel)
    try:
        with ManagerClient(echoing, NODE, timeout=0.2) as client:
            status = client.status()
        assert echoing.repeated > 20
        assert status["state"] == rig.manager.state.name and status["drives"] == []
    finally:
        echoing.shutdown()
        rig.close()


class RefusesOneSend(VirtualBus):
    """The node's bus, refusing its ``refuse_at``-th send as a full SocketCAN transmit
    queue does (python-can's "Transmit buffer full")."""

    def __init__(self, channel: str, refuse_at: int) -> None:
        super().__init__(channel=channel, receive_own_messages=False)
        self.refuse_at, self.sends = refuse_at, 0

    def send(self, msg: can.Message, timeout: float | None = None) -> None:
        self.sends += 1
        if self.sends == self.refuse_at:
            raise can.CanOperationError("Transmit buffer full")
        super().send(msg, timeout)


def test_a_burst_the_interface_cuts_short_goes_on_from_the_refused_segment(
        bus_factory, virtual_channel):
    """The interface refuses a segment in the middle of a block: the node stops the burst
    (its reader thread does not wait, nothing is raised or logged per frame) and sends the
    rest of the block from that segment on, one burst gap later; the status is whole."""
    plant = JointPlant(3, dt=0.005)
    manager = ControllerManager(TorqueOff(), 0.005, plant.state, plant.command, timing=None)
    refusing = RefusesOneSend(virtual_channel, refuse_at=1_000_000)
    drive = {"name": "j", "phase": "READY", "fault": "EMCY 0x2310 (overcurrent)"}
    report = {"startup_finished": True, "drives": [drive] * 12}
    node = ManagerNode(manager, NODE, refusing,
                       drive_status=lambda: SimpleNamespace(as_dict=lambda: report)).start()
    try:
        with ManagerClient(bus_factory(), NODE, timeout=0.2) as client:
            refusing.refuse_at = refusing.sends + 4  # the initiate answer, then segment 3
            status = client.status()
        assert node._node.sdo.refused_sends == 1
        assert status["drives"] == [drive] * 12
    finally:
        node.close()
        refusing.shutdown()
        manager.shutdown()


def test_a_node_without_block_upload_is_read_segmented(bus_factory):
    """A manager from before block upload (canopen's own SDO server, which answers a block
    upload with a normal one, as CiA 301 allows): text objects still read, the first by
    falling back, the rest segmented from the start."""
    import canopen

    from rocoma_can import eds
    network = canopen.Network(bus_factory())
    node = canopen.LocalNode(NODE, str(eds.path(eds.MANAGER_NODE)))
    network.add_node(node)
    network.connect()
    node.set_data(0x2123, 0, b"pd,trajectory")
    node.set_data(0x2121, 0, b"pd")
    try:
        with ManagerClient(bus_factory(), NODE, timeout=0.5) as client:
            assert client.controllers() == ["pd", "trajectory"]
            assert client.read_text(0x2121) == "pd"
            assert client._blocks is False
    finally:
        network.disconnect()


def test_no_answer_from_a_wrong_node(bus_factory):
    with ManagerClient(bus_factory(), 42, timeout=0.2) as client:
        with pytest.raises(NoAnswer):
            client.status()


def test_a_plain_remote_node_from_the_eds_reads_what_the_node_serves(rig, bus_factory):
    """canopen's RemoteNode built from eds/rocoma_manager.eds, nothing else: every readable
    object answers, decoded with the EDS's type, with what the node really does; the command
    objects are write-only; no object is missing from the answers or aborts."""
    import canopen
    from canopen.sdo.exceptions import SdoAbortedError

    from rocoma_can import eds
    network = canopen.Network(bus_factory())
    network.connect()
    try:
        node = network.add_node(NODE, str(eds.path(eds.MANAGER_NODE)))
        node.sdo.RESPONSE_TIMEOUT = 1.0
        expected = {
            (0x1017, 0): 100,                      # no heartbeat_ms given: the EDS default
            (0x1800, 1): 0x180 + NODE, (0x1800, 2): 255, (0x1800, 5): 50,  # status_period
            (0x1A00, 0): 2, (0x1A00, 1): 0x21200008, (0x1A00, 2): 0x21220008,
            (0x2102, 0): 0xFE, (0x2103, 0): "", (0x2120, 0): 0, (0x2121, 0): "torque_off",
            (0x2122, 0): 0,
            (0x2123, 0): "pd,trajectory", (0x2124, 0): "", (0x2130, 0): ESTOP_COB,
            (0x2131, 0): 0, (0x2151, 0): "",
        }
        read, write_only = {}, []
        for obj in node.object_dictionary.values():
            variables = obj.values() if hasattr(obj, "values") else [obj]
            for var in variables:
                sdo_var = node.sdo[var.index] if var.subindex == 0 and not hasattr(obj, "values") \
                    else node.sdo[var.index][var.subindex]
                if not var.readable:
                    write_only.append(var.index)
                    with pytest.raises(SdoAbortedError) as refused:
                        _ = sdo_var.raw
                    assert refused.value.code == 0x06010001, hex(var.index)
                    continue
                read[var.index, var.subindex] = sdo_var.raw
        assert sorted(write_only) == [0x2100, 0x2101, 0x2110, 0x2111, 0x2112, 0x2113,
                                      0x2150]
        assert {k: read[k] for k in expected} == expected
    finally:
        network.disconnect()


def test_a_name_that_is_not_ascii_is_escaped_not_an_abort(rig):
    """VISIBLE_STRING is ASCII: a cause naming a drive "jé" used to abort the whole read."""
    rig.node.last_cause = "drive 'jé' (node 2): EMCY 0x2310"
    assert rig.client.read(0x2124) == "drive 'j\\xe9' (node 2): EMCY 0x2310"
    assert rig.client.status()["estop_cause"].startswith("drive 'j\\xe9'")


def test_a_write_takes_only_its_own_answer_from_a_busy_channel(bus_factory):
    """The node's one SDO channel, busy with another client's block upload: before this
    write's answer come a segment of that upload and an abort the node sends the other
    client. canopen took the first as the answer (an e-stop reported failed, though
    applied); ManagerClient skips both and takes its own, and an abort naming this object
    is still a refusal."""
    node_side = bus_factory()
    answered: list[bytes] = []

    def node() -> None:  # a node that answers after two frames of another transfer
        for _ in range(2):
            request = node_side.recv(STALL)
            if request is None or request.arbitration_id != 0x600 + NODE:
                return
            answered.append(bytes(request.data))
            strays = (b"\x01" + b'{"drive',  # a block segment, another's abort
                      b"\x80\x40\x21\x00" + struct.pack("<I", 0x05040001))
            for stray in strays:
                node_side.send(can.Message(arbitration_id=0x580 + NODE, data=stray,
                                           is_extended_id=False))
            index = bytes(request.data[1:4])
            answer = b"\x60" + index + bytes(4) if index != b"\x12\x21\x00" else \
                b"\x80" + index + struct.pack("<I", 0x08000022)
            node_side.send(can.Message(arbitration_id=0x580 + NODE, data=answer,
                                       is_extended_id=False))

    server = threading.Thread(target=node)
    server.start()
    with ManagerClient(bus_factory(), NODE, timeout=STALL) as client:
        client.write(0x2110, 1)  # the e-stop: its own answer, after the strays
        with pytest.raises(Refused) as refused:
            client.write(0x2112, 1)  # refused: the abort names this object
        assert refused.value.code == 0x08000022
    server.join(STALL)
    assert [a[:4] for a in answered] == [b"\x2f\x10\x21\x00", b"\x2f\x12\x21\x00"]


def test_writes_succeed_while_another_client_polls_the_status(rig, bus_factory):
    """An operator's `status --watch` and an `estop` in another terminal share the node's
    one SDO channel: every write is answered (no write taken for failed, none sent twice)."""
    stop = threading.Event()
    reads: list[int] = []

    def watch() -> None:
        with ManagerClient(bus_factory(), NODE, timeout=STALL) as viewer:
            while not stop.is_set():
                try:
                    viewer.status()
                    reads.append(1)
                except (NoAnswer, Refused):
                    pass

    viewer = threading.Thread(target=watch)
    viewer.start()
    try:
        deadline = time.monotonic() + within(1.0)
        while not reads and time.monotonic() < deadline:
            time.sleep(0.01)
        for _ in range(30):
            rig.client.write(0x2112, 1)  # clear: answered every time, never refused
    finally:
        stop.set()
        viewer.join(within(STALL))
    assert reads


@pytest.mark.parametrize("in_cycle", [False, True], ids=["node-takes-estops", "hardware-does"])
def test_the_node_receives_only_what_it_serves(bus_factory, in_cycle):
    """The node's bus handle is filtered to its SDO requests, NMT and (when the node takes
    them) e-stop frames: the loop's PDO traffic on that bus never reaches its reader (on
    the in-process bus not even its queue; on SocketCAN the kernel drops it). Moving the
    e-stop COB-ID by SDO moves the filter, for data and remote frames; ``close`` lifts it."""
    plant = JointPlant(3, dt=0.005)
    manager = ControllerManager(TorqueOff(), 0.005, plant.state, plant.command, timing=None)
    handed: list[int] = []
    node_bus = bus_factory(interface="inproc")
    node = ManagerNode(manager, NODE, node_bus, estop_cob_id=ESTOP_COB,
                       estop_in_cycle=handed.append if in_cycle else None)
    seen: list[int] = []  # every frame the node's reader hands the node
    served = node.on_message_received
    node.on_message_received = lambda msg: (seen.append(msg.arbitration_id), served(msg))
    node.start()
    try:
        traffic = bus_factory(interface="inproc")

        def send(cob_id: int, **kwargs: object) -> None:
            traffic.send(can.Message(arbitration_id=cob_id, **kwargs))

        for cob_id in (0x080, 0x181, 0x201, 0x281, 0x301, 0x701, 0x581, 0x600 + NODE + 1):
            for _ in range(20):
                send(cob_id, data=bytes(8), is_extended_id=False)
        send(0x600 + NODE, data=bytes(8), is_extended_id=True)  # 29 bits: another id
        with ManagerClient(bus_factory(interface="inproc"), NODE, timeout=STALL) as client:
            # answered after the node's reader handled every frame sent before it
            assert client.status()["state"] == "FAILPROOF"
            client.write(0x2130, 0x0B5)
            send(0x0B5, is_extended_id=False, is_remote_frame=True)
            send(0x0B5, data=b"\x01", is_extended_id=False)
            assert client.status()["state"] == "FAILPROOF"
        assert set(seen) == {0x600 + NODE} | ({0x0B5} if not in_cycle else set())
        if not in_cycle:
            assert seen.count(0x0B5) == 2 and len(node.estop_frames) == 2
        wanted = [0x600 + NODE, 0x000] + ([] if in_cycle else [0x0B5])
        assert [f["can_id"] for f in node_bus.filters] == wanted
        assert all(f["can_mask"] == 0x7FF and f["extended"] is False for f in node_bus.filters)
        if in_cycle:
            assert handed[-1] == 0x0B5
    finally:
        node.close()
        manager.shutdown()
    assert node_bus.filters is None


def test_only_an_accepted_estop_cob_id_is_logged_as_a_change(bus_factory, caplog):
    """A write of 0x2130 the hardware refuses (a drive's identifier) was logged as a change
    before it was refused: the log then told of an e-stop path that was never set."""
    plant = JointPlant(3, dt=0.005)
    manager = ControllerManager(TorqueOff(), 0.005, plant.state, plant.command, timing=None)
    drives = {0x181}

    def in_cycle(cob_id: int) -> None:
        if cob_id in drives:
            raise ValueError(f"0x{cob_id:03X} is drive 1's TPDO1")

    node = ManagerNode(manager, NODE, bus_factory(), estop_cob_id=ESTOP_COB,
                       estop_in_cycle=in_cycle).start()
    changed = "e-stop COB-ID changed by SDO"
    try:
        with ManagerClient(bus_factory(), NODE, timeout=STALL) as client, \
                caplog.at_level("WARNING", logger="rocoma_can.node.server"):
            with pytest.raises(Refused) as info:
                client.write(0x2130, 0x181)
            assert info.value.code == ABORT_NOT_FOUND and node.estop_cob_id == ESTOP_COB
            assert not [r for r in caplog.records if changed in r.getMessage()]
            client.write(0x2130, 0x0B5)
        assert node.estop_cob_id == 0x0B5
        changes = [r.getMessage() for r in caplog.records if changed in r.getMessage()]
        assert len(changes) == 1 and "from 0x0A0 to 0x0B5" in changes[0]
    finally:
        node.close()
        manager.shutdown()
