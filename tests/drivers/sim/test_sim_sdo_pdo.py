"""drivers/sim/objects.py, pdo.py: the simulated drive's SDO server and PDOs, driven by a canopen
client on another bus."""
from __future__ import annotations

import struct
import time
from pathlib import Path

import can
import pytest
from canopen.sdo import SdoAbortedError, SdoCommunicationError
from fixtures.paths import TESTS

from rocoma_can.drivers.protocol import cia301 as c301
from rocoma_can.drivers.protocol import cia402 as c
from rocoma_can.drivers.protocol.cia301 import NmtCommand
from rocoma_can.drivers.protocol.cia402 import Mode, State402

WRITES = {0x6040: 0x06, 0x6060: int(Mode.CSV), 0x6071: 123, 0x607A: -4567, 0x60FF: 890,
          0x60B1: 11, 0x60B2: -12, 0x6072: 2500}


def test_every_mappable_object_reads_and_writes_by_sdo(sim_bench, sim_interface):
    bench = sim_bench(2, sim_interface)
    node, drive = bench.node(2), bench.drive(2)
    mappable = [v for v in node.object_dictionary.values()
                if getattr(v, "pdo_mappable", False)]
    assert {v.index for v in mappable} >= set(WRITES) | {0x6041, 0x6061, 0x6064, 0x606C,
                                                          0x6077, 0x603F, 0x1001}
    for var in mappable:
        assert node.sdo[var.index].raw == drive.od_value(var.index), hex(var.index)
        if var.index in WRITES:
            node.sdo[var.index].raw = WRITES[var.index]
            assert node.sdo[var.index].raw == WRITES[var.index]
            assert drive.od_value(var.index) == WRITES[var.index]
        else:
            assert not var.writable
            with pytest.raises(SdoAbortedError) as err:
                node.sdo[var.index].raw = 0
            assert err.value.code == 0x06010002  # read-only
    # the writes took effect in the drive, not only in its dictionary
    assert drive.state402 == State402.READY_TO_SWITCH_ON
    assert node.sdo[0x6061].raw == Mode.CSV
    assert node.sdo[0x6041].raw & 0x6F == 0x21


def test_sdo_aborts_like_a_real_drive(sim_bench):
    bench = sim_bench(1)
    node = bench.node(1)
    with pytest.raises(SdoAbortedError) as err:
        node.sdo[0x6060].raw = int(Mode.PROFILE_POSITION)  # not in 0x6502
    assert err.value.code == 0x06090030
    assert bench.drive().mode_display == Mode.NONE
    with pytest.raises(SdoAbortedError) as err:
        node.sdo.upload(0x2FFF, 0)
    assert err.value.code == 0x06020000
    with pytest.raises(SdoAbortedError) as err:  # wrong length for an UNSIGNED16
        node.sdo.download(0x6040, 0, b"\x06\x00\x00\x00")
    assert err.value.code == 0x06070010
    assert node.sdo[0x1018][2].raw == 0x402
    bench.nmt(NmtCommand.STOP, 1)
    node.sdo.RESPONSE_TIMEOUT = 0.2
    with pytest.raises(SdoCommunicationError):  # no SDO in STOPPED: no answer
        _ = node.sdo[0x6041].raw


def _remap_tpdo1(node, *variables, trans_type=1):
    node.tpdo.read()
    pdo = node.tpdo[1]
    pdo.clear()
    for index in variables:
        pdo.add_variable(index)
    pdo.trans_type = trans_type
    pdo.enabled = True
    pdo.save()


def test_pdo_remapping_by_sdo_changes_the_tpdo_layout(sim_bench, sim_interface):
    bench = sim_bench(1, sim_interface)
    node, rec = bench.node(1), bench.recorder
    bench.nmt(NmtCommand.START)
    bench.sync(1)
    default = rec.wait_for_count(1, bench.stall, 0x181)[0]
    assert len(default.data) == 5  # statusword, mode display, torque actual
    _remap_tpdo1(node, 0x6064, 0x6041)
    assert node.sdo[0x1A00][0].raw == 2
    assert node.sdo[0x1A00][1].raw == 0x60640020
    mark = rec.mark()
    bench.sync(1)
    frame = rec.wait_for_count(1, bench.stall, 0x181, since=mark)[0]
    position, statusword = struct.unpack("<iH", frame.data)
    assert statusword == bench.drive().statusword
    assert position == bench.drive().position_increments


def test_mapping_rules_of_cia301_are_enforced(sim_bench):
    node = sim_bench(1).node(1)
    with pytest.raises(SdoAbortedError) as err:  # mapping of a valid PDO
        node.sdo[0x1A00][0].raw = 0
    assert err.value.code == 0x08000022
    node.sdo[0x1800][1].raw = 0x80000181
    with pytest.raises(SdoAbortedError) as err:  # entries only while sub 0 is 0
        node.sdo[0x1A00][1].raw = 0x60640020
    assert err.value.code == 0x08000022
    node.sdo[0x1A00][0].raw = 0
    node.sdo[0x1A00][1].raw = 0x60760020  # rated torque: not mappable
    with pytest.raises(SdoAbortedError) as err:
        node.sdo[0x1A00][0].raw = 1
    assert err.value.code == 0x06040041
    for sub, entry in enumerate((0x60640020, 0x606C0020, 0x60410010), start=1):
        node.sdo[0x1A00][sub].raw = entry
    with pytest.raises(SdoAbortedError) as err:  # 80 bits
        node.sdo[0x1A00][0].raw = 3
    assert err.value.code == 0x06040042
    node.sdo[0x1800][1].raw = 0x181
    with pytest.raises(SdoAbortedError) as err:  # COB-ID change of a valid PDO
        node.sdo[0x1800][1].raw = 0x191
    assert err.value.code == 0x06090030
    node.sdo[0x1400][1].raw = 0x80000201
    node.sdo[0x1600][0].raw = 0
    node.sdo[0x1600][1].raw = 0x60410010
    with pytest.raises(SdoAbortedError) as err:  # statusword is read-only: not in an RPDO
        node.sdo[0x1600][0].raw = 1
    assert err.value.code == 0x06040041


def test_rpdos_only_in_operational_and_remappable(sim_bench, sim_interface):
    bench = sim_bench(1, sim_interface)
    node, drive = bench.node(1), bench.drive()
    node.rpdo.read()
    pdo = node.rpdo[1]
    pdo.clear()
    pdo.add_variable(0x6040)
    pdo.add_variable(0x60FF)
    pdo.trans_type = 255
    pdo.enabled = True
    pdo.save()
    node.sdo[0x6060].raw = int(Mode.CSV)
    frame = struct.pack("<Hi", 0x06, 1000)
    bench.send(0x201, frame)
    bench.sync(1)  # the RPDO was sent before: the segment has seen it by now
    assert drive.state402 == State402.SWITCH_ON_DISABLED  # PRE-OPERATIONAL: ignored
    bench.nmt(NmtCommand.START)
    for cw in (0x06, 0x07, 0x0F):
        bench.send(0x201, struct.pack("<Hi", cw, 1000))
    bench.sync(1)
    assert drive.state402 == State402.OPERATION_ENABLED
    assert drive.od_value(c.TARGET_VELOCITY) == 1000


def test_synchronous_rpdo_takes_effect_at_the_next_sync(sim_bench):
    bench = sim_bench(1)
    node, drive = bench.node(1), bench.drive()
    node.sdo[0x1400][2].raw = 1
    bench.nmt(NmtCommand.START)
    bench.send(0x201, struct.pack("<HbH", 0x06, int(Mode.CST), 0))
    bench.send(0x600 + 1, bytes((0x40, 0x41, 0x60, 0, 0, 0, 0, 0)))  # any frame after it
    bench.wait(lambda: bench.recorder.count(0x581) >= 1, what="SDO answer")
    assert drive.state402 == State402.SWITCH_ON_DISABLED
    bench.sync(1)
    assert drive.state402 == State402.READY_TO_SWITCH_ON
    assert drive.mode_display == Mode.CST


def test_short_rpdo_gives_emcy_8210(sim_bench):
    bench = sim_bench(1)
    bench.nmt(NmtCommand.START)
    bench.send(0x201, b"\x06\x00")  # mapping is 5 bytes
    frame = bench.recorder.wait_for(lambda f: f.cob_id == 0x81, bench.stall)
    assert struct.unpack("<HB5s", frame.data)[0] == c301.EMCY_PDO_LENGTH
    assert bench.drive().state402 == State402.SWITCH_ON_DISABLED


def test_transmission_type_n_sends_every_nth_sync(sim_bench):
    bench = sim_bench(1)
    node, rec = bench.node(1), bench.recorder
    node.sdo[0x1801][2].raw = 3
    bench.nmt(NmtCommand.START)
    bench.sync(9)
    rec.wait_for_count(9, bench.stall, 0x181)
    rec.wait_for_count(3, bench.stall, 0x281)
    bench.nmt(NmtCommand.PRE_OPERATIONAL)
    mark = rec.mark()
    bench.sync(3)
    bench.nmt(NmtCommand.START)  # a frame after the SYNCs: the recorder has seen them
    bench.sync(1)
    rec.wait_for_count(1, bench.stall, 0x181, since=mark)
    assert rec.count((0x181, 0x281), since=mark) == 1  # none while PRE-OPERATIONAL


def test_remapping_one_pdo_leaves_the_others_state_alone(sim_bench):
    """A PDO object written by SDO compiles that PDO again, not all eight: TPDO2 (every
    3rd SYNC) keeps its count and a received synchronous RPDO still waits for its SYNC
    while TPDO1 is remapped, entry by entry, in OPERATIONAL."""
    bench = sim_bench(1)
    node, drive, rec = bench.node(1), bench.drive(), bench.recorder
    node.sdo[0x1801][2].raw = 3
    node.sdo[0x1400][2].raw = 1
    bench.nmt(NmtCommand.START)
    bench.sync(2)
    rec.wait_for_count(2, bench.stall, 0x181)
    assert rec.count(0x281) == 0
    bench.send(0x201, struct.pack("<HbH", 0x06, int(Mode.CST), 0))
    _remap_tpdo1(node, 0x6064, 0x6041)
    assert drive.state402 == State402.SWITCH_ON_DISABLED  # the RPDO waits for the SYNC
    mark = rec.mark()
    bench.sync(1)
    frame = rec.wait_for_count(1, bench.stall, 0x181, since=mark)[0]
    rec.wait_for_count(1, bench.stall, 0x281, since=mark)  # the 3rd SYNC since START
    assert struct.unpack("<iH", frame.data)[0] == drive.position_increments
    assert drive.state402 == State402.READY_TO_SWITCH_ON
    assert drive.mode_display == Mode.CST


def test_event_driven_tpdo_on_state_change(sim_bench):
    bench = sim_bench(1)
    node, rec = bench.node(1), bench.recorder
    node.sdo[0x1802][1].raw = 0x80000381
    node.sdo[0x1A02][0].raw = 0
    node.sdo[0x1A02][1].raw = 0x60410010
    node.sdo[0x1A02][0].raw = 1
    node.sdo[0x1802][2].raw = 255
    node.sdo[0x1802][1].raw = 0x381
    bench.nmt(NmtCommand.START)
    for cw in (0x06, 0x07, 0x0F):
        node.sdo[0x6040].raw = cw
    frames = rec.wait_for_count(4, bench.stall, 0x381)
    states = [c.state_from_statusword(struct.unpack("<H", f.data)[0]) for f in frames]
    assert states == [State402.SWITCH_ON_DISABLED, State402.READY_TO_SWITCH_ON,
                      State402.SWITCHED_ON, State402.OPERATION_ENABLED]


#: 0x1008 (manufacturer device name) of 54 bytes, as the drive in issue 33 had
DEVICE_NAME = "rocoma-can simulated CiA 402 servo drive, firmware 1.0"


@pytest.fixture
def named_drive_eds(tmp_path):
    """The shipped drive EDS with a 54-byte 0x1008, longer than a client's switch threshold."""
    from rocoma_can import eds
    assert len(DEVICE_NAME) == 54
    path = tmp_path / "named_drive.eds"
    path.write_text(eds.path(eds.CIA402_DRIVE).read_text() + (
        "\n[1008]\nParameterName=Manufacturer device name\nObjectType=0x7\n"
        f"DataType=0x0009\nAccessType=const\nDefaultValue={DEVICE_NAME}\nPDOMapping=0\n"))
    return path


class _RawSdo:
    """Raw SDO requests to drive 1 on a bus of the test's own: its answers in the order
    the drive sent them, each wait bounded by the bench's stall."""

    def __init__(self, bench, bus) -> None:
        self.bench, self.bus = bench, bus

    def __call__(self, request: bytes, answers: int) -> list[bytes]:
        self.bus.send(can.Message(arbitration_id=0x601, data=request, is_extended_id=False))
        got: list[bytes] = []
        deadline = time.monotonic() + self.bench.stall
        while len(got) < answers and time.monotonic() < deadline:
            msg = self.bus.recv(max(0.0, deadline - time.monotonic()))
            if msg is not None and msg.arbitration_id == 0x581:
                got.append(bytes(msg.data))
        assert len(got) == answers, (request.hex(), got)
        return got


def test_a_block_upload_above_the_switch_threshold_is_a_block_upload(sim_bench, bus_factory,
                                                                     named_drive_eds):
    """Issue 33: asked with blksize 127 and threshold 21, the 54-byte 0x1008 came back as a
    segmented upload, which CiA 301 allows only at or below the threshold. Now: the block
    upload's answer (size, CRC), eight segments in order with the last one marked, the end
    with the unused bytes and the CRC; the client's end is not answered."""
    from canopen.sdo.base import CrcXmodem
    bench = sim_bench(1, eds_path=str(named_drive_eds))
    raw = _RawSdo(bench, bus_factory())
    value = DEVICE_NAME.encode()
    (answer,) = raw(bytes.fromhex("A40810007F150000"), 1)
    assert answer == bytes([0xC6, 0x08, 0x10, 0x00]) + struct.pack("<I", len(value))
    segments = raw(bytes([0xA3]) + bytes(7), 8)
    assert [s[0] for s in segments] == [1, 2, 3, 4, 5, 6, 7, 0x88]
    assert b"".join(s[1:] for s in segments)[:len(value)] == value
    (end,) = raw(bytes([0xA2, 8, 127]) + bytes(5), 1)
    crc = CrcXmodem()
    crc.process(value)
    assert end[0] == 0xC1 | (-len(value) % 7) << 2
    assert struct.unpack_from("<H", end, 1)[0] == crc.final()
    # the client's end is not answered: the next answer is the one to an upload of 0x1000
    raw.bus.send(can.Message(arbitration_id=0x601, data=bytes([0xA1]) + bytes(7),
                             is_extended_id=False))
    (answer,) = raw(bytes([0x40, 0x00, 0x10, 0x00]) + bytes(4), 1)
    assert answer[:4] == bytes([0x43, 0x00, 0x10, 0x00])
    # at or below the threshold: a normal upload, as CiA 301 allows
    (answer,) = raw(bytes.fromhex("A40810007F360000"), 1)
    assert answer == bytes([0x41, 0x08, 0x10, 0x00]) + struct.pack("<I", len(value))


def test_canopens_block_upload_reads_the_drive(sim_bench, bus_factory, named_drive_eds):
    """canopen's own BlockUploadStream (blksize 127, CRC) against the simulated drive, and a
    lost segment resumed by the ack: the value whole, the CRC checked by canopen."""
    bench = sim_bench(1, eds_path=str(named_drive_eds))
    sdo = bench.node(1).sdo
    with sdo.open(0x1008, 0, "rb", block_transfer=True) as stream:
        assert stream.read() == DEVICE_NAME.encode()
    raw = _RawSdo(bench, bus_factory())
    # an ack of 3: segments 4.. again, renumbered from 1, then the end
    raw(bytes.fromhex("A40810007F000000"), 1)
    first = raw(bytes([0xA3]) + bytes(7), 8)
    again = raw(bytes([0xA2, 3, 127]) + bytes(5), 5)
    assert [s[0] for s in again] == [1, 2, 3, 4, 0x85]
    assert [s[1:] for s in again] == [s[1:] for s in first[3:]]
    # an ack beyond what was sent aborts (0x05040003), naming the object
    answer, = raw(bytes([0xA2, 6, 127]) + bytes(5), 1)
    assert answer == bytes([0x80, 0x08, 0x10, 0x00]) + struct.pack("<I", 0x05040003)
    # and a block command with nothing open is an abort, not an upload
    answer, = raw(bytes([0xA3]) + bytes(7), 1)
    assert answer[0] == 0x80 and struct.unpack_from("<I", answer, 4)[0] == 0x05040001


def test_each_drive_answers_the_identity_it_was_given(sim_bench, bus_factory):
    """0x1018 is what tells drives apart on a bus (a scan, a generated config, bring-up's
    check): the fields given replace the file's; a drive given none answers the file's
    vendor and product and its node id as serial number, so no two are alike."""
    from rocoma_can.drivers.files.identity import Identity
    from rocoma_can.drivers.sim.segment import SimulatedSegment
    from rocoma_can.drivers.sim.segment_options import SegmentOptions

    bench = sim_bench([1, 2], identities={2: Identity(vendor_id=0x9A, product_code=0x77,
                                                      serial=0x1234_5678)})
    one, two = bench.node(1), bench.node(2)
    assert [one.sdo[0x1018][s].raw for s in (1, 2, 4)] == [0, 0x402, 1]
    assert [two.sdo[0x1018][s].raw for s in (1, 2, 4)] == [0x9A, 0x77, 0x1234_5678]
    assert two.sdo[0x1018][3].raw == one.sdo[0x1018][3].raw  # the file's revision
    with pytest.raises(ValueError, match=r"identities given for node ids \[5\]"):
        SimulatedSegment(bus_factory(), [1], SegmentOptions(identities={5: Identity(serial=1)}))


def test_nodes_simulated_from_a_file_with_a_serial_number_are_each_their_own(sim_bench):
    """A file read off one device (a DCF) carries that device's serial number: several nodes
    simulated from it are still each a device of their own (an LSS address, a serial
    bring-up may hold each to): node 1 keeps the file's, the next one more."""
    bench = sim_bench([1, 2, 5], eds_path=str(TESTS / "fixtures" / "eds"
                                              / "serial_in_file.eds"))
    assert [bench.node(n).sdo[0x1018][4].raw for n in (1, 2, 5)] == \
        [0xC0FFEE, 0xC0FFEF, 0xC0FFF2]


def test_a_files_limits_hold_for_profile_objects_not_for_communication_objects(sim_bench,
                                                                                 tmp_path):
    """Elmo's DCF limits 0x1016:1 to 65535 as if it were a plain time: its drives take the
    CiA 301 layout (the producer's node id in bits 16..23) all the same, and so does the
    simulator; a profile object's limit (0x6072 HighLimit=300) is refused as a drive does."""
    from rocoma_can import eds
    text = Path(eds.path(eds.CIA402_DRIVE)).read_text().replace("\r\n", "\n")
    for section, extra in (("[1016sub1]\n", "LowLimit=0\nHighLimit=65535\n"),
                           ("[6072]\n", "HighLimit=300\n")):
        assert section in text
        text = text.replace(section, section + extra)
    path = tmp_path / "limited.eds"
    path.write_text(text)
    node = sim_bench(1, eds_path=str(path)).node(1)
    node.sdo[0x1016][1].raw = (100 << 16) | 1500  # the manager's heartbeat, 1.5 s
    assert node.sdo[0x1016][1].raw == (100 << 16) | 1500
    with pytest.raises(SdoAbortedError) as err:
        node.sdo[0x6072].raw = 500
    assert err.value.code == 0x06090031  # value too high
