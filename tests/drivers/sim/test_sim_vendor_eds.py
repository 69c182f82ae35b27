"""drivers/sim/objects.py, drivers/sim/drive.py: the simulated drive emulates exactly the
vendor-like file it is given (tests/fixtures/eds/): its objects and their access, no 0x6007 where
the file has none, files with empty defaults and no factor group, plausible values where the file
has none."""
from __future__ import annotations

import struct

import pytest
from canopen.sdo.exceptions import SdoAbortedError
from fixtures.paths import EDS

from rocoma_can.drivers.protocol import cia301, cia402
from rocoma_can.drivers.protocol.cia402 import State402

ABORT_NOT_IN_OD = 0x06020000
ABORT_WRITE_READONLY = 0x06010002
ABORT_INVALID_VALUE = 0x06090030


# --- the simulator emulates the file ---------------------------------------------------------
def _abort_code(call) -> int:
    with pytest.raises(SdoAbortedError) as info:
        call()
    return info.value.code


def test_the_simulator_has_exactly_the_files_objects_and_access(sim_bench):
    bench = sim_bench(1, eds_path=str(EDS / "fixed_pdo.eds"))
    sdo = bench.node(1).sdo
    assert _abort_code(lambda: sdo.upload(cia402.TARGET_VELOCITY, 0)) == ABORT_NOT_IN_OD
    assert _abort_code(lambda: sdo.upload(cia301.RPDO_COMM + 1, 1)) == ABORT_NOT_IN_OD
    # a fixed mapping stays fixed
    assert _abort_code(lambda: sdo.download(cia301.RPDO_MAP, 0, b"\0")) == ABORT_WRITE_READONLY
    # only the modes of its 0x6502 (CSP, PP)
    assert _abort_code(lambda: sdo.download(cia402.MODES_OF_OPERATION, 0,
                                            struct.pack("<b", 9))) == ABORT_INVALID_VALUE
    sdo.download(cia402.MODES_OF_OPERATION, 0, struct.pack("<b", 8))
    assert bench.drive(1).mode_display == 8


def test_a_simulated_drive_without_0x6007_does_not_switch_itself_off(sim_bench):
    """The honest emulation: losing the manager's heartbeat gives EMCY 0x8130 and 0x1029's
    NMT change, but no CiA 402 reaction (a drive that cannot be told one)."""
    bench = sim_bench(1, eds_path=str(EDS / "no_abort_option.eds"))
    assert _abort_code(lambda: bench.node(1).sdo.upload(cia402.ABORT_CONNECTION_OPTION, 0)) \
        == ABORT_NOT_IN_OD
    drive_ = bench.drive(1)
    with bench.segment.lock:
        drive_.cia402.set_state(State402.OPERATION_ENABLED)
        drive_._heartbeat_lost()
    assert drive_.state402 == State402.OPERATION_ENABLED  # the joint keeps its command
    (emcy,) = bench.recorder.wait_for_count(1, bench.stall, cia301.EMCY + 1)
    assert struct.unpack_from("<H", emcy.data)[0] == cia301.EMCY_HEARTBEAT


def test_a_simulator_loads_files_with_empty_defaults_and_no_factor_group(sim_bench):
    bench = sim_bench(1, eds_path=str(EDS / "minimal.eds"), increments_per_rev=4096)
    assert bench.drive(1).increments_per_rad == pytest.approx(4096 / (2 * 3.141592653589793))
    assert bench.node(1).sdo.upload(0x1018, 2) == b"\0\0\0\0"  # empty default: 0


def test_the_simulator_answers_plausible_values_where_the_file_has_none(sim_bench):
    bench = sim_bench(1, eds_path=str(EDS / "hand_written.eds"))
    sdo = bench.node(1).sdo
    assert struct.unpack("<I", sdo.upload(0x1000, 0))[0] == 0x00020192  # a CiA 402 servo
    modes = struct.unpack("<I", sdo.upload(cia402.SUPPORTED_DRIVE_MODES, 0))[0]
    assert modes == 0x381 | 0x4  # its targets' modes it implements: PP, PV, CSP, CSV, CST
    assert sdo.upload(cia402.GEAR_RATIO, 1) == sdo.upload(cia402.GEAR_RATIO, 2) == b"\1\0\0\0"
    assert bench.drive(1).objects.assumed[(0x1000, 0)] == 0x00020192
