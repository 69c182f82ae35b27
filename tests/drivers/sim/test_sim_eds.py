"""eds/*.eds: the shipped EDS files import cleanly and hold what the driver and the manager node
need."""
from __future__ import annotations

import logging
import warnings

import canopen
import pytest

from rocoma_can import eds
from rocoma_can.drivers.protocol import cia301, cia402


def _import_quietly(name: str, node_id: int, caplog: pytest.LogCaptureFixture):
    caplog.set_level(logging.DEBUG)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        od = canopen.import_od(str(eds.path(name)), node_id)
    noisy = [r for r in caplog.records if r.levelno >= logging.WARNING]
    assert not noisy, [r.getMessage() for r in noisy]
    return od


def test_drive_eds_imports_without_warnings(caplog):
    od = _import_quietly(eds.CIA402_DRIVE, 7, caplog)
    assert od[cia301.DEVICE_TYPE].default == cia402.DEVICE_TYPE_SERVO
    for index in (0x1000, 0x1001, 0x1003, 0x1016, 0x1017, 0x1018, 0x1029,
                  0x6040, 0x6041, 0x6060, 0x6061, 0x6064, 0x606C, 0x6076, 0x6077, 0x607A,
                  0x60FF, 0x6071, 0x6072, 0x605A, 0x605B, 0x605C, 0x6007, 0x603F, 0x6085,
                  0x6502, 0x608F, 0x6091, 0x60B1, 0x60B2):
        assert index in od, f"0x{index:04X} missing"
    for n in range(4):
        for base in (0x1400, 0x1600, 0x1800, 0x1A00):
            assert base + n in od
        # $NODEID resolved in every PDO COB-ID, PDOs 3 and 4 disabled (bit 31)
        assert od[0x1800 + n][1].default & 0x7FF == cia301.TPDO_BASE[n] + 7
        assert od[0x1400 + n][1].default & 0x7FF == cia301.RPDO_BASE[n] + 7
        assert bool(od[0x1800 + n][1].default & 0x80000000) == (n >= 2)
    assert od[0x608F][1].default == 2 ** 20
    assert od[0x6076].default == 1000
    for index in (0x6040, 0x6041, 0x6060, 0x6061, 0x6064, 0x606C, 0x6071, 0x6077, 0x607A,
                  0x60FF, 0x60B1, 0x60B2):
        assert od[index].pdo_mappable, f"0x{index:04X} must be PDO-mappable"


def test_manager_eds_imports_without_warnings(caplog):
    od = _import_quietly(eds.MANAGER_NODE, 1, caplog)
    expected = {0x2100: "VISIBLE_STRING", 0x2101: "UNSIGNED8", 0x2102: "UNSIGNED8",
                0x2110: "UNSIGNED8", 0x2111: "UNSIGNED8", 0x2112: "UNSIGNED8",
                0x2113: "UNSIGNED8", 0x2120: "UNSIGNED8", 0x2121: "VISIBLE_STRING",
                0x2122: "UNSIGNED8", 0x2123: "VISIBLE_STRING", 0x2124: "VISIBLE_STRING",
                0x2130: "UNSIGNED32", 0x2131: "UNSIGNED8"}
    types = {"VISIBLE_STRING": 0x9, "UNSIGNED8": 0x5, "UNSIGNED32": 0x7}
    for index, type_name in expected.items():
        assert od[index].data_type == types[type_name], f"0x{index:04X}"
    for index in (0x2102, 0x2120, 0x2121, 0x2122, 0x2123, 0x2124, 0x2131):
        assert not od[index].writable, f"0x{index:04X} must be read-only"
    for index in (0x2100, 0x2101, 0x2110, 0x2111, 0x2112, 0x2113, 0x2130):
        assert od[index].writable, f"0x{index:04X} must be writable"
    assert od[0x1800][1].default == 0x181
    assert [od[0x1A00][s].default for s in (0, 1, 2)] == [2, 0x21200008, 0x21220008]
