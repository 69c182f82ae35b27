"""drivers/commission/scan.py, lss.py, rocoma_can/cli/scan.py: `rocoma-can scan` and `rocoma-can
lss` against simulated drives over a CAN bus: the real CLI entry, the simulator's identities and LSS
slaves (CiA 305).

The tests taking ``sim_interface`` or ``can_setup`` run on python-can's virtual bus and
again on SocketCAN vcan0 (the vcan suite, through tools/vcan-run)."""
from __future__ import annotations

import errno
import json
import os
import threading

import can
import pytest
from can.interfaces.virtual import VirtualBus
from fixtures.budgets import GUEST_STALL, STALL, within
from fixtures.bus import scan_bus_args
from fixtures.driver_rig import bring_up, enable_with
from fixtures.odd_node import OddNode
from fixtures.rig_controllers import HoldPD

from rocoma_can import ManagerState
from rocoma_can.cli.main import main
from rocoma_can.drivers.commission.lss import LSS_REQUEST
from rocoma_can.drivers.files.identity import Identity
from rocoma_can.drivers.protocol import cia301
from rocoma_can.drivers.protocol.cia402 import State402

IDENTITIES = {1: Identity(vendor_id=0x9A, product_code=0x10, revision=0x2, serial=0x1001),
              2: Identity(vendor_id=0x9A, product_code=0x10, revision=0x2, serial=0x1002),
              3: Identity(vendor_id=0x9A, product_code=0x20, revision=0x1, serial=0x0B0B)}
#: an unconfigured node: few one bits in its address, so a fastscan waits few timeouts
BLANK = Identity(serial=0x11)


def _stall(interface: str) -> float:
    return GUEST_STALL if interface == "socketcan" else STALL


def scan_json(capsys, interface: str, channel: str, *extra: str) -> dict:
    capsys.readouterr()
    assert main(["scan", "--json", *scan_bus_args(interface, channel, _stall(interface)),
                 *extra]) == 0
    return json.loads(capsys.readouterr().out)


def _channel(interface: str, virtual_channel: str) -> str:
    return virtual_channel if interface == "virtual" else "vcan0"


def test_scan_lists_exactly_the_drives_with_their_identities(
        sim_segment_factory, sim_interface, virtual_channel, capsys):
    sim_segment_factory([1, 2, 3], interface=sim_interface, identities=IDENTITIES)
    found = scan_json(capsys, sim_interface, _channel(sim_interface, virtual_channel))
    assert [n["node_id"] for n in found["nodes"]] == [1, 2, 3]
    for node in found["nodes"]:
        assert Identity(**node["identity"]) == IDENTITIES[node["node_id"]]
        assert node["device_type"] == 0x00020192  # the file's: CiA 402
        assert node["device_name"] == "rocoma-can simulated CiA 402 drive"  # segmented
        assert node["software_version"] == "1.0"
        assert node["heartbeat_ms"] == 100
        assert node["nmt_state"] == "PRE-OPERATIONAL"
        assert node["seen_by"] == "heartbeat" and node["problem"] is None
    assert "unconfigured" not in found


def test_scan_table_and_an_empty_bus(sim_segment_factory, virtual_channel, capsys):
    sim_segment_factory([4], identities={4: IDENTITIES[1]})
    assert main(["scan", *scan_bus_args("virtual", virtual_channel, STALL)]) == 0
    head, row = capsys.readouterr().out.splitlines()
    assert head.split()[:5] == ["node", "vendor", "product", "revision", "serial"]
    assert row.split()[:5] == ["4", "0x0000009A", "0x00000010", "0x00000002", "0x00001001"]
    assert "PRE-OPERATIONAL" in row and "100 ms" in row
    # nobody there: the scan ran (exit 0) and says what to check
    assert main(["scan", *scan_bus_args("virtual", virtual_channel + "-empty", STALL)]) == 0
    out = capsys.readouterr().out
    assert "no nodes answered" in out and "bit rate" in out and "termination" in out


def test_a_node_without_heartbeat_is_found_by_its_sdo_answer(
        sim_segment_factory, virtual_channel, capsys):
    sim_segment_factory([7], overrides={(cia301.PRODUCER_HEARTBEAT_TIME, 0): 0})
    (node,) = scan_json(capsys, "virtual", virtual_channel)["nodes"]
    assert node["node_id"] == 7 and node["seen_by"] == "sdo"
    assert node["heartbeat_ms"] == 0 and node["nmt_state"] == "unknown"  # 0x1017 = 0: off
    assert node["identity"]["serial"] == 7  # the node id, where the file has none


def test_a_scan_beside_a_running_manager_only_reads(segment, make_rig, can_setup,
                                                    frame_recorder, virtual_channel, capsys):
    """No NMT command, no SDO download, no LSS on the bus while the scan runs; the manager
    stays OK and every drive enabled."""
    rig = make_rig()
    bring_up(rig)
    enable_with(rig, HoldPD())
    recorder = frame_recorder(interface=can_setup.interface)
    mark = recorder.mark()
    result: dict[str, int] = {}
    args = ["scan", "--json", *scan_bus_args(can_setup.interface,
                                         can_setup.channel(virtual_channel), can_setup.stall)]
    scanner = threading.Thread(target=lambda: result.update(rc=main(args)), daemon=True)
    scanner.start()
    rig.run_until(lambda: not scanner.is_alive(), within(30.0, can_setup.stall))
    assert result.get("rc") == 0
    found = json.loads(capsys.readouterr().out)["nodes"]
    assert {n["node_id"] for n in found} >= set(segment.drives)
    assert all(n["nmt_state"] == "OPERATIONAL" for n in found if n["node_id"] in segment.drives)
    frames = recorder.frames(since=mark)
    sdo_requests = [f for f in frames if cia301.SDO_RX < f.cob_id <= cia301.SDO_RX + 0x7F]
    assert sdo_requests, "the scan sent no SDO request"
    # upload initiate / segment requests, or an abort: never a download (ccs 1)
    assert {f.data[0] & 0xE0 for f in sdo_requests} <= {0x40, 0x60, 0x80}, sdo_requests[:5]
    assert not [f for f in frames if f.cob_id in (cia301.NMT, LSS_REQUEST)]
    assert rig.mgr.state == ManagerState.OK and rig.hw.all_enabled
    assert all(d.state402 == State402.OPERATION_ENABLED for d in segment.drives.values())


def test_lss_fastscan_finds_an_unconfigured_node_and_lss_gives_it_an_id(
        sim_segment_factory, sim_interface, virtual_channel, capsys):
    segment = sim_segment_factory([1], interface=sim_interface, unconfigured=[BLANK])
    channel = _channel(sim_interface, virtual_channel)
    found = scan_json(capsys, sim_interface, channel, "--lss")
    assert [n["node_id"] for n in found["nodes"]] == [1]  # silent until it has a node id
    (blank,) = found["unconfigured"]
    assert blank["serial"] == 0x11 and blank["product_code"] == 0x402  # the file's
    bus = ["--interface", sim_interface, "--channel", channel,
           "--timeout", f"{_stall(sim_interface) / 4:g}"]
    assert main(["lss", *bus, "--fastscan", "--set-node-id", "9", "--store"]) == 0
    assert "node id 9, stored" in capsys.readouterr().out
    found = scan_json(capsys, sim_interface, channel, "--lss")
    assert [n["node_id"] for n in found["nodes"]] == [1, 9]
    assert found["nodes"][1]["identity"]["serial"] == 0x11
    assert found["unconfigured"] == []
    assert segment.drives[9].nmt_state == cia301.NmtState.PRE_OPERATIONAL  # it booted


def test_lss_by_address_moves_a_configured_node_at_its_next_reset(
        sim_bench, virtual_channel, capsys):
    bench = sim_bench([2], identities={2: IDENTITIES[2]})
    i = IDENTITIES[2]
    bus = ["--interface", "virtual", "--channel", virtual_channel, "--timeout", f"{STALL / 4:g}"]
    assert main(["lss", *bus, "--vendor", hex(i.vendor_id), "--product", hex(i.product_code),
                 "--revision", str(i.revision), "--serial", hex(i.serial),
                 "--set-node-id", "5", "--bitrate", "500000"]) == 0
    assert "not stored" in capsys.readouterr().out
    assert list(bench.segment.drives) == [2]  # a node with an id keeps it until a reset
    bench.nmt(cia301.NmtCommand.RESET_COMMUNICATION, 2)
    assert list(bench.segment.drives) == [5]
    assert bench.recorder.wait_for_count(1, bench.within(0.1), cob_id=cia301.HEARTBEAT + 5,
                                         where=lambda f: f.data == b"\x00")  # boot-up
    # nobody at that address: exit 1 and what was asked
    assert main(["lss", *bus, "--vendor", "1", "--product", "2", "--revision", "3",
                 "--serial", "4", "--set-node-id", "6"]) == 1
    assert "no node answered" in capsys.readouterr().err


@pytest.mark.parametrize("args", [
    ["lss", "--channel", "x", "--serial", "1", "--set-node-id", "3"],  # no --vendor etc.
    ["lss", "--channel", "x", "--fastscan", "--set-node-id", "3", "--bitrate", "100000"],
    ["scan", "--channel", "x", "--interface", "nonesuch"],
])
def test_usage_errors_exit_2_with_one_line(args, capsys):
    assert main([*args, "--interface", "virtual"] if "nonesuch" not in args else args) == 2
    err = capsys.readouterr().err.strip()
    assert err.startswith("rocoma-can: ") and "\n" not in err and "Traceback" not in err


@pytest.fixture
def odd_node(virtual_channel):
    nodes: list[OddNode] = []

    def start(answer) -> OddNode:
        nodes.append(OddNode(virtual_channel, answer))
        return nodes[-1]
    yield start
    for node in nodes:
        node.close()


@pytest.mark.parametrize("garbage", [b"", b"\x80\x00\x10\x00\x00"])
def test_a_node_answering_garbled_sdo_frames_is_listed_with_the_problem(
        odd_node, virtual_channel, capsys, garbage):
    """Shorter than an SDO frame (empty, a 5-byte abort): the scan goes on and
    lists the node with what went wrong, no traceback."""
    odd_node(lambda request: [garbage])
    (node,) = scan_json(capsys, "virtual", virtual_channel)["nodes"]
    assert node["node_id"] == OddNode.NODE and node["device_type"] is None
    assert "malformed SDO answer reading 0x1000:0" in node["problem"]


def test_a_node_that_never_ends_a_segmented_upload_is_cut_off(odd_node, virtual_channel,
                                                              capsys):
    """Every object as a segmented upload of no stated size whose segments never say
    "last": the scan stops reading each after a bounded length and goes on (a node that
    streams for ever must not hang it)."""
    def endless(request: bytes) -> list[bytes]:
        if request[0] & 0xE0 == 0x40:  # initiate upload: segmented, no size
            return [b"\x40" + request[1:4] + bytes(4)]
        if request[0] & 0xE0 == 0x60:  # upload segment: the toggle echoed, never the last
            return [bytes([request[0] & 0x10]) + b"ABCDEFG"]
        return []
    odd_node(endless)
    result: dict[str, object] = {}
    scanner = threading.Thread(target=lambda: result.update(
        found=scan_json(capsys, "virtual", virtual_channel)), daemon=True)
    scanner.start()
    scanner.join(within(10.0))
    assert not scanner.is_alive(), "the scan never ended"
    (node,) = result["found"]["nodes"]  # type: ignore[index]
    assert node["device_name"].startswith("ABCDEFGABCDEFG")
    assert len(node["device_name"]) <= 256
    assert "0x1008:0 longer than 256 bytes" in node["problem"]


class _RefusingBus(VirtualBus):
    """A bus whose every send fails as SocketCAN's does: ENOBUFS (a transmit queue that
    stays full: nothing acknowledges the frames) or ENETDOWN (the link is down)."""

    error = errno.ENOBUFS

    def send(self, msg, timeout=None):
        raise can.CanOperationError(f"Failed to transmit: {os.strerror(self.error)}",
                                    self.error)


@pytest.mark.parametrize("error, hint", [
    (errno.ENOBUFS, "no node acknowledges the frames"),
    (errno.ENETDOWN, "sudo ip link set CH up"),
])
@pytest.mark.parametrize("verb", [
    ["scan"], ["scan", "--lss"], ["init-config", "--eds-dir", "."],
    ["lss", "--fastscan", "--set-node-id", "3"],
])
def test_a_bus_that_refuses_every_frame_is_one_line_and_exit_2(
        monkeypatch, virtual_channel, capsys, verb, error, hint):
    """What a real bus with nothing on it does (no acknowledgement: the transmit queue
    fills, ENOBUFS) or a link set down: one line naming the bus and what to check."""
    from rocoma_can.drivers.link import bus as bus_module
    monkeypatch.setattr(_RefusingBus, "error", error)
    monkeypatch.setattr(bus_module, "open_bus", lambda interface, channel, **kw: _RefusingBus(
        channel=channel))
    assert main([*verb, "--channel", virtual_channel, "--interface", "virtual",
                 "--timeout", "0.05"]) == 2
    err = capsys.readouterr().err.strip()
    assert err.startswith("rocoma-can: ") and "\n" not in err, err
    assert f"virtual:{virtual_channel}" in err and os.strerror(error) in err
    assert hint.replace("CH", virtual_channel) in err


@pytest.mark.parametrize("failure", [NameError("name 'canGetNumberOfChannels' is not defined"),
                                     ImportError("Please install python-ics"),
                                     TypeError("__init__() missing 2 required positional "
                                               "arguments: 'host' and 'port'")])
def test_an_adapter_backend_that_fails_to_start_is_one_line_and_exit_2(
        monkeypatch, capsys, failure):
    """python-can's kvaser backend without Kvaser's canlib raises NameError, neovi without
    python-ics ImportError, socketcand without host/port TypeError: what a person meets with
    a USB adapter whose vendor library is not installed. One line naming the interface."""
    def broken(**kwargs):
        raise failure
    monkeypatch.setattr(can, "Bus", broken)
    assert main(["scan", "--interface", "kvaser", "--channel", "0"]) == 2
    err = capsys.readouterr().err.strip()
    assert err.startswith("rocoma-can: cannot open CAN bus kvaser:0: ") and "\n" not in err
    assert type(failure).__name__ in err and str(failure) in err


@pytest.mark.parametrize("verb", [["scan"], ["init-config", "--eds-dir", "."],
                                  ["lss", "--fastscan", "--set-node-id", "3"]])
def test_a_channel_that_is_not_a_can_link_is_one_line_and_exit_2(verb, capsys):
    """lo (every host has it) is up and exists: it is no CAN link, which the command says
    before it opens anything (as doctor judges it)."""
    assert main([*verb, "--channel", "lo"]) == 2
    err = capsys.readouterr().err.strip()
    assert err.startswith("rocoma-can: socketcan:lo: link/loopback, not a CAN link"), err
    assert "\n" not in err and "link/can" in err


# -- two devices at one node id; an answer that is malformed ---------------------------------

@pytest.mark.parametrize("second", [Identity(serial=0x77), None])
def test_two_devices_at_one_node_id_are_said_in_the_row_and_the_json(
        sim_segment_factory, virtual_channel, capsys, second):
    """Node 1 twice (a drive given a taken id), beside a node 2 alone: every request to node
    1 has two answers. The scan showed one clean row, or a "Toggle bit mismatch"; it now says
    two devices answer there, with the values they differ in, and reads node 2 as ever."""
    sim_segment_factory([1, 2])
    sim_segment_factory([1], identities={1: second} if second else {})
    for _ in range(2):  # whichever device answers first
        found = {n["node_id"]: n for n in scan_json(capsys, "virtual", virtual_channel)["nodes"]}
        assert sorted(found) == [1, 2]
        one, two = found[1], found[2]
        assert one["several_devices"] is True
        assert one["problem"].startswith("two or more devices answer at node id 1"), one
        if second:
            assert "serial 0x00000001, 0x00000077" in one["problem"], one["problem"]
        assert "Toggle bit" not in one["problem"] and "instead" not in one["problem"]
        assert two["several_devices"] is False and two["problem"] is None
        assert two["device_name"] == "rocoma-can simulated CiA 402 drive"
    assert main(["scan", *scan_bus_args("virtual", virtual_channel, STALL)]) == 0
    rows = capsys.readouterr().out.splitlines()
    (row,) = [r for r in rows if r.startswith("1 ")]
    assert "two or more devices answer here: their answers mix" in row, rows
    assert [r for r in rows if r.startswith("node 1: two or more devices")], rows


def _segmented_0x1000(stated: bytes, segment: bytes):
    """A node whose 0x1000 comes as a segmented upload stating ``stated`` as its size, then
    one last segment of ``segment``; every other object it lacks (abort)."""
    def answer(request: bytes) -> list[bytes]:
        if request[0] & 0xE0 == 0x40 and request[1:4] == b"\x00\x10\x00":
            return [b"\x41\x00\x10\x00" + stated]
        if request[0] & 0xE0 == 0x60:  # one segment, the last, its length in the command
            return [bytes([0x01 | (7 - len(segment)) << 1 | request[0] & 0x10])
                    + segment.ljust(7, b"\x00")]
        if request[0] & 0xE0 == 0x40:
            return [b"\x80" + request[1:4] + (0x06020000).to_bytes(4, "little")]
        return []
    return answer


@pytest.mark.parametrize("answer, said", [
    (_segmented_0x1000(b"\xff\xff\xff\xff", b"\x92\x01\x02\x00ABC"),
     "7 bytes, where an UNSIGNED32 has 4; the transfer said 4294967295 bytes"),
    (_segmented_0x1000(b"\x04\x00\x00\x00", b"\x92\x01\x02\x00ABC"),
     "7 bytes, where an UNSIGNED32 has 4; the transfer said 4 bytes"),
    (_segmented_0x1000(b"\x02\x00\x00\x00", b"\x92\x01"),
     "2 bytes, where an UNSIGNED32 has 4"),
    (lambda request: [b"\x4b\x00\x10\x00\x92\x01\x00\x00"] if request[1:4] == b"\x00\x10\x00"
     else [b"\x80" + request[1:4] + (0x06020000).to_bytes(4, "little")],  # expedited, 2 bytes
     "2 bytes, where an UNSIGNED32 has 4"),
])
def test_a_malformed_0x1000_answer_is_said_not_taken_for_a_missing_object(
        odd_node, virtual_channel, capsys, answer, said):
    """The device type came as 7 bytes of a segmented upload that stated 0xFFFFFFFF (or 4,
    or as 2 bytes): the row showed "-", as for a node without 0x1000, and no problem."""
    odd_node(answer)
    (node,) = scan_json(capsys, "virtual", virtual_channel)["nodes"]
    assert node["device_type"] is None and node["malformed"] == ["0x1000:0"]
    assert node["problem"] == f"0x1000:0 (device type): a malformed answer: {said}"
    assert main(["scan", *scan_bus_args("virtual", virtual_channel, STALL)]) == 0
    head, row, problem = capsys.readouterr().out.splitlines()
    assert row.split()[5] == "malformed", row  # the device type's column
    assert problem == f"node {OddNode.NODE}: {node['problem']}"
