"""rocoma_can/node/sdo_server.py, drivers/protocol/sdo_block_server.py: SDO block upload from the
manager node (CiA 301), frame by frame on a virtual bus: the client commands as raw frames, so every
answer, sequence number and resume point is seen. The node serves its text objects this way because
a segmented upload of 0x2140's JSON is one round trip per 7 bytes (~250 for a few drives): in a
stalled host that took 20 s and failed `rocoma-can status` during a fault. Hostile or out-of-order
commands get an abort and never data; a client asking a short object with a protocol switch
threshold gets a normal upload."""
from __future__ import annotations

import json
import struct
import time
from types import SimpleNamespace

import can
import pytest
from canopen.sdo.base import CrcXmodem
from fixtures.budgets import STALL
from safety_rig import SDO_RX, sdo_exchange

from rocoma_can.node.client import ManagerClient
from rocoma_can.node.objects import (
    ABORT_BLOCK_SIZE,
    ABORT_COMMAND_SPECIFIER,
    ABORT_SEQUENCE_NUMBER,
    CONTROLLER_LIST,
    DRIVE_STATUS,
    MAX_BLOCK_SIZE,
)

INITIATE, END, ACK, START = 0xA0, 0xA1, 0xA2, 0xA3  # client command specifiers (ccs 5)
CRC = 0x04


def _initiate(index: int, blksize: int, *, crc: bool = True, pst: int = 0) -> bytes:
    return struct.pack("<BHBBBxx", INITIATE | (CRC if crc else 0), index, 0, blksize, pst)


def _segments(bus: can.BusABC, request: bytes, count: int, timeout: float = 2.0) -> list[bytes]:
    """Send ``request`` and collect the node's next ``count`` answers, or fewer when the
    last segment (bit 7) comes first (bounded)."""
    bus.send(can.Message(arbitration_id=SDO_RX, data=request, is_extended_id=False))
    got: list[bytes] = []
    deadline = time.monotonic() + timeout
    while len(got) < count and time.monotonic() < deadline:
        msg = bus.recv(0.1)
        if msg is not None and msg.arbitration_id == SDO_RX - 0x80:
            got.append(bytes(msg.data))
            if msg.data[0] & 0x80:
                break
    return got


def _abort_code(answer: bytes) -> int:
    assert answer[0] == 0x80, answer.hex()
    code: int = struct.unpack_from("<I", answer, 4)[0]
    return code


def _quiet(bus: can.BusABC, seconds: float = 0.3) -> list[bytes]:
    """The node's SDO answers within ``seconds`` (there should be none)."""
    deadline = time.monotonic() + seconds
    seen = []
    while time.monotonic() < deadline:
        msg = bus.recv(0.05)
        if msg is not None and msg.arbitration_id == SDO_RX - 0x80:
            seen.append(bytes(msg.data))
    return seen


def _twelve_drives(service) -> None:
    """0x2140 as a 12-drive manager reports it (~2.5 KB: the node serves what it is given)."""
    drive = {"phase": "READY", "enabled": False, "fault": "EMCY 0x2310 (overcurrent)",
             "homing": "", "bus": "front"}
    report = {"startup_finished": True, "recovery": "",
              "drives": [{"name": f"j{n}", "node_id": n, **drive} for n in range(1, 13)]}
    service.node.drive_status = lambda: SimpleNamespace(as_dict=lambda: report)


def test_status_in_blocks_resumes_from_the_acked_segment_and_ends_with_the_crc(service):
    bus = service.raw
    _twelve_drives(service)
    answer = sdo_exchange(bus, _initiate(DRIVE_STATUS, blksize=4))
    assert answer[0] == 0xC6  # block upload response, size indicated, CRC supported
    assert struct.unpack_from("<HB", answer, 1) == (DRIVE_STATUS, 0)
    size = struct.unpack_from("<I", answer, 4)[0]
    assert size > 4 * 7 * 2  # more than two blocks

    data = b""
    block = _segments(bus, bytes([START]) + bytes(7), 4)
    assert [s[0] for s in block] == [1, 2, 3, 4]
    # only segments 1 and 2 arrived: the next block starts with segment 3's data again
    data += b"".join(s[1:] for s in block[:2])
    resent = block[2]
    block = _segments(bus, bytes([ACK, 2, 4]) + bytes(5), 4)
    assert block[0] == bytes([1]) + resent[1:]
    while True:  # ack whole blocks until the last segment
        data += b"".join(s[1:] for s in block)
        assert [s[0] & 0x7F for s in block] == list(range(1, len(block) + 1))
        if block[-1][0] & 0x80:
            break
        block = _segments(bus, bytes([ACK, len(block), 4]) + bytes(5), 4)
    end = sdo_exchange(bus, bytes([ACK, len(block), 4]) + bytes(5))
    unused = (end[0] >> 2) & 0x7
    assert end[0] & 0xE3 == 0xC1  # end of block upload
    data = data[:len(data) - unused]
    assert len(data) == size
    crc = CrcXmodem()
    crc.process(data)
    assert struct.unpack_from("<H", end, 1)[0] == crc.final()
    assert len(json.loads(data)["drives"]) == 12
    bus.send(can.Message(arbitration_id=SDO_RX, data=bytes([END]) + bytes(7),
                         is_extended_id=False))
    assert _quiet(bus) == []  # the client's end is not answered


def test_an_empty_text_is_one_empty_segment(service):
    """0x2124 (the e-stop cause) is empty until an e-stop: a value of no bytes, not an abort."""
    bus = service.raw
    answer = sdo_exchange(bus, _initiate(0x2124, blksize=MAX_BLOCK_SIZE, crc=False))
    assert answer[0] == 0xC2 and struct.unpack_from("<I", answer, 4)[0] == 0
    assert _segments(bus, bytes([START]) + bytes(7), MAX_BLOCK_SIZE) \
        == [bytes([0x81]) + bytes(7)]
    end = sdo_exchange(bus, bytes([ACK, 1, MAX_BLOCK_SIZE]) + bytes(5))
    assert end[0] == 0xC1 | 7 << 2  # all 7 bytes of the one segment unused, no CRC


def test_a_short_object_under_the_switch_threshold_is_a_normal_upload(service):
    answer = sdo_exchange(service.raw, _initiate(CONTROLLER_LIST, blksize=MAX_BLOCK_SIZE, pst=64))
    assert answer[0] == 0x41  # initiate upload response, segmented, size indicated
    assert struct.unpack_from("<I", answer, 4)[0] == len("pd,trajectory")


@pytest.mark.parametrize("request_, code", [
    (bytes([ACK, 1, 16]) + bytes(5), ABORT_COMMAND_SPECIFIER),     # nothing open
    (bytes([START]) + bytes(7), ABORT_COMMAND_SPECIFIER),          # nothing initiated
    (bytes([END]) + bytes(7), ABORT_COMMAND_SPECIFIER),
    (_initiate(DRIVE_STATUS, blksize=0), ABORT_BLOCK_SIZE),
    (_initiate(DRIVE_STATUS, blksize=128), ABORT_BLOCK_SIZE),
    (_initiate(DRIVE_STATUS, blksize=255), ABORT_BLOCK_SIZE),
], ids=["ack-without-upload", "start-without-initiate", "end-without-upload", "blksize-0",
        "blksize-128", "blksize-255"])
def test_a_block_command_out_of_place_is_an_abort(service, request_, code):
    assert _abort_code(sdo_exchange(service.raw, request_)) == code


def test_acks_beyond_what_was_sent_or_a_second_start_abort_the_upload(service):
    bus = service.raw
    sdo_exchange(bus, _initiate(DRIVE_STATUS, blksize=2))
    assert len(_segments(bus, bytes([START]) + bytes(7), 2)) == 2
    assert _abort_code(sdo_exchange(bus, bytes([START]) + bytes(7))) == ABORT_COMMAND_SPECIFIER
    # the abort closed the upload: an ack now is out of place, not a resume
    assert _abort_code(sdo_exchange(bus, bytes([ACK, 2, 2]) + bytes(5))) \
        == ABORT_COMMAND_SPECIFIER

    sdo_exchange(bus, _initiate(DRIVE_STATUS, blksize=2))
    assert len(_segments(bus, bytes([START]) + bytes(7), 2)) == 2
    assert _abort_code(sdo_exchange(bus, bytes([ACK, 3, 2]) + bytes(5))) == ABORT_SEQUENCE_NUMBER
    assert _quiet(bus) == []


def test_the_client_reads_text_in_a_few_round_trips(service, frame_recorder, virtual_channel):
    """What `rocoma-can status` does: its requests for 0x2140 are counted (one per block and
    three to open and close), not one per 7 bytes; no burst is longer than a block."""
    _twelve_drives(service)
    rec = frame_recorder(virtual_channel)
    with ManagerClient(service.raw, service.node.node_id, timeout=1.0) as client:
        size = len(client.read_text(DRIVE_STATUS))
    requests = rec.count(SDO_RX)
    assert size > 10 * MAX_BLOCK_SIZE * 7  # many blocks
    assert requests <= 3 + -(-size // (MAX_BLOCK_SIZE * 7)), (requests, size)
    burst = longest = 0
    # in send order (the stamps): python-can's virtual bus hands a frame to its receivers one
    # by one, so a client preempted mid-send (a busy machine) can reach this listener with
    # its ack after the node's answer to that ack
    for frame in sorted(rec.frames(), key=lambda f: f.time):
        burst = burst + 1 if frame.cob_id == SDO_RX - 0x80 else 0
        longest = max(longest, burst)
    assert longest == MAX_BLOCK_SIZE


def test_a_one_byte_object_asked_as_a_stock_client_asks_is_an_expedited_upload(service):
    """Issue 33, as CANopenNode's client asks (blksize 127, switch threshold 21): the node
    refused 0x2120 with 0x05040002; a value of one byte is answered with a normal upload."""
    answer = sdo_exchange(service.raw, bytes.fromhex("A42021007F150000"))
    assert answer == bytes([0x4F, 0x20, 0x21, 0x00, int(service.manager.state), 0, 0, 0])


def test_canopens_block_upload_of_127_segments_is_served_in_paced_bursts(
        service, frame_recorder, bus_factory):
    """canopen's own BlockUploadStream (blksize 127, no switch threshold) reads 0x2140 whole:
    every block has its segments 1..127 in order on the bus, the last block ends with the
    last segment, the end names the unused bytes and the CRC; and the node hands the
    interface at most BURST segments at a time, the next burst no sooner than its gap."""
    import canopen

    from rocoma_can.node.sdo_server import BURST
    _twelve_drives(service)
    expected = service.node._on_read(DRIVE_STATUS, 0, None).encode()  # type: ignore[arg-type]
    network = canopen.Network(bus_factory())
    network.connect()
    rec = frame_recorder()
    try:
        client = network.add_node(service.node.node_id).sdo
        client.RESPONSE_TIMEOUT = STALL  # a loaded host may hold a frame up that long
        with client.open(DRIVE_STATUS, 0, "rb", block_transfer=True) as stream:
            data = stream.read()
    finally:
        network.disconnect()
    # the client's end is the exchange's last frame: the recorder has all of it then
    rec.wait_for(lambda f: f.cob_id == SDO_RX and f.data[0] == END, timeout=STALL)
    assert data == expected and len(data) > 127 * 7  # more than one block
    answers = rec.frames(SDO_RX - 0x80)
    assert answers[0].data[0] == 0xC6  # block upload, size indicated, CRC
    assert struct.unpack_from("<I", answers[0].data, 4)[0] == len(expected)
    segments, end = answers[1:-1], answers[-1]
    blocks, block = [], []
    for frame in segments:
        block.append(frame)
        if frame.data[0] & 0x7F == 127 or frame.data[0] & 0x80:
            blocks.append(block)
            block = []
    assert block == [] and len(blocks) == -(-len(expected) // (127 * 7))
    for block in blocks:
        assert [f.data[0] & 0x7F for f in block] == list(range(1, len(block) + 1))
    assert [bool(f.data[0] & 0x80) for f in segments].count(True) == 1
    assert segments[-1].data[0] & 0x80
    assert end.data[0] & 0xE3 == 0xC1 and (end.data[0] >> 2) & 7 == -len(expected) % 7
    crc = CrcXmodem()
    crc.process(expected)
    assert struct.unpack_from("<H", end.data, 1)[0] == crc.final()
    # the acks and the end came from the client, one per block and one at the end
    acks = [f.data for f in rec.frames(SDO_RX) if f.data[0] == ACK]
    assert [a[1] for a in acks] == [len(b) for b in blocks]
    # paced: within a block, a burst is BURST segments, the next one at least the gap later
    sdo = service.node._node.sdo
    assert sdo.longest_burst == BURST
    gap = sdo.burst_gap
    assert gap > 0
    for block in blocks:
        for k in range(BURST, len(block), BURST):
            assert block[k].time - block[k - 1].time >= gap / 2, (k, gap)
