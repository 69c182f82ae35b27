"""drivers/sim/state_machine.py: the CiA 402 state machine of the simulated drive, transition by
transition."""
from __future__ import annotations

import struct

import numpy as np
import pytest

from rocoma_can.drivers.protocol import cia301 as c301
from rocoma_can.drivers.protocol import cia402 as c
from rocoma_can.drivers.protocol.cia301 import NmtCommand
from rocoma_can.drivers.protocol.cia402 import Mode, State402

S = State402


def _step(bench, cw, expected, syncs=1):
    """Controlword by SDO, then SYNCs (ramps end on the drive's cycle); check the
    statusword by SDO, by the drive, and in the TPDO that SYNC produced."""
    node, drive, rec = bench.node(1), bench.drive(1), bench.recorder
    node.sdo[0x6040].raw = cw
    mark = rec.mark()
    bench.sync(syncs)
    statusword = node.sdo[0x6041].raw
    assert c.state_from_statusword(statusword) == expected, (hex(cw), hex(statusword))
    assert statusword == drive.statusword
    assert bool(statusword & c.SW_QUICK_STOP) == (expected != S.QUICK_STOP_ACTIVE)
    if syncs:  # the TPDO a SYNC produced carries it (TPDOs are not ordered with SDO answers)
        rec.wait_for(lambda f: f.cob_id == 0x181
                     and struct.unpack_from("<H", f.data)[0] == statusword, bench.stall, since=mark)


def test_walk_through_every_transition(sim_bench, sim_interface):
    bench = sim_bench(1, sim_interface)
    drive, node = bench.drive(1), bench.node(1)
    assert drive.state402 == S.SWITCH_ON_DISABLED  # 0, 1 at power-on
    node.sdo[0x6060].raw = int(Mode.CSV)
    bench.nmt(NmtCommand.START)
    walk = [
        (0x06, S.READY_TO_SWITCH_ON),   # 2
        (0x07, S.SWITCHED_ON),          # 3
        (0x0F, S.OPERATION_ENABLED),    # 4
        (0x07, S.SWITCHED_ON),          # 5 (0x605C = 1: ramp, ends on the SYNC)
        (0x06, S.READY_TO_SWITCH_ON),   # 6
        (0x00, S.SWITCH_ON_DISABLED),   # 7 disable voltage
        (0x06, S.READY_TO_SWITCH_ON),
        (0x02, S.SWITCH_ON_DISABLED),   # 7 quick stop
        (0x06, S.READY_TO_SWITCH_ON),
        (0x0F, S.OPERATION_ENABLED),    # 3 + 4 in one command
        (0x06, S.READY_TO_SWITCH_ON),   # 8
        (0x0F, S.OPERATION_ENABLED),
        (0x00, S.SWITCH_ON_DISABLED),   # 9
        (0x06, S.READY_TO_SWITCH_ON),
        (0x07, S.SWITCHED_ON),
        (0x00, S.SWITCH_ON_DISABLED),   # 10 disable voltage
        (0x06, S.READY_TO_SWITCH_ON),
        (0x07, S.SWITCHED_ON),
        (0x02, S.SWITCH_ON_DISABLED),   # 10 quick stop
        (0x0F, S.SWITCH_ON_DISABLED),   # no transition from SOD without shutdown first
        (0x06, S.READY_TO_SWITCH_ON),
        (0x0F, S.OPERATION_ENABLED),
    ]
    for cw, expected in walk:
        _step(bench, cw, expected)
    _step(bench, 0x0B, S.QUICK_STOP_ACTIVE, syncs=0)  # 11 (bit 2 low)
    bench.sync(1)  # 12: 0x605A = 2, at standstill the ramp is over on the next cycle
    assert drive.state402 == S.SWITCH_ON_DISABLED
    for cw, expected in [(0x06, S.READY_TO_SWITCH_ON), (0x0F, S.OPERATION_ENABLED)]:
        _step(bench, cw, expected)
    drive.trip_fault(c301.EMCY_OVERCURRENT)  # 13
    assert drive.state402 == S.FAULT_REACTION_ACTIVE
    assert node.sdo[0x6041].raw & 0x4F == 0x0F
    _step(bench, 0x0F, S.FAULT)            # 14 once the reaction ramp is over
    _step(bench, 0x0F, S.FAULT)            # no enable out of FAULT
    _step(bench, 0x80, S.SWITCH_ON_DISABLED)  # 15 on the rising edge of bit 7
    drive.trip_fault(c301.EMCY_GENERIC)
    _step(bench, 0x80, S.FAULT)            # bit 7 still high: no edge, no reset
    _step(bench, 0x00, S.FAULT)
    _step(bench, 0x80, S.SWITCH_ON_DISABLED)


def test_quick_stop_option_6_stays_and_transition_16(sim_bench):
    bench = sim_bench(1)
    node, drive = bench.node(1), bench.drive(1)
    node.sdo[0x605A].raw = 6
    bench.spin(1)
    _step(bench, 0x02, S.QUICK_STOP_ACTIVE, syncs=300)  # ramped to standstill, stays
    assert abs(drive.velocity_rad_s) < 0.01
    _step(bench, 0x0F, S.OPERATION_ENABLED)  # 16


def test_quick_stop_ramp_follows_0x6085(sim_bench):
    bench = sim_bench(1)
    node, drive = bench.node(1), bench.drive(1)
    node.sdo[0x6085].raw = 2 ** 20  # 1 rev/s^2: 1 rev/s stops in 1 s
    bench.spin(1)
    v0 = drive.velocity_rad_s
    assert v0 == pytest.approx(2 * 3.14159, rel=0.01)
    node.sdo[0x6040].raw = 0x02
    bench.sync(250)  # 0.5 s of ramp
    assert drive.state402 == S.QUICK_STOP_ACTIVE
    assert drive.velocity_rad_s == pytest.approx(v0 / 2, abs=0.15)
    bench.sync(300)
    assert drive.state402 == S.SWITCH_ON_DISABLED
    assert abs(drive.velocity_rad_s) < 0.01


def test_quick_stop_option_0_coasts(sim_bench):
    bench = sim_bench(1)
    node, drive = bench.node(1), bench.drive(1)
    node.sdo[0x605A].raw = 0
    bench.spin(1)
    node.sdo[0x6040].raw = 0x02
    assert drive.state402 == S.SWITCH_ON_DISABLED
    bench.sync(5)
    assert drive.torque_nm == 0.0
    assert drive.velocity_rad_s > 5.0


def test_halt_bit_stops_and_holds_in_operation_enabled(sim_bench):
    bench = sim_bench(1)
    node, drive = bench.node(1), bench.drive(1)
    bench.spin(1)
    node.sdo[0x6040].raw = 0x0F | c.CW_HALT
    bench.sync(500)  # 0x6085 default is 10 rev/s^2
    assert drive.state402 == S.OPERATION_ENABLED
    assert abs(drive.velocity_rad_s) < 0.01
    node.sdo[0x6040].raw = 0x0F
    bench.sync(300)
    assert drive.velocity_rad_s == pytest.approx(2 * 3.14159, rel=0.01)


def test_shutdown_refused_while_sto_is_low(sim_bench):
    bench = sim_bench(1)
    drive = bench.drive(1)
    drive.set_sto(True)
    bench.nmt(NmtCommand.START)
    _step(bench, 0x06, S.SWITCH_ON_DISABLED)
    assert drive.statusword & c.SW_WARNING
    drive.set_sto(False)
    _step(bench, 0x06, S.READY_TO_SWITCH_ON)
    assert not drive.statusword & c.SW_WARNING


def test_the_vectorised_decode_agrees_with_the_pattern_table_for_every_statusword():
    """The hardware decodes a cycle's statuswords with one table lookup; the table must
    agree with CiA 402's patterns for all 65,536 words (the high bits never decide)."""
    words = np.arange(1 << 16, dtype=np.uint16)
    out = np.empty(len(words), dtype=np.int8)
    c.states_from_statuswords(words, out)
    assert out.tolist() == [c.state_from_statusword(w) for w in range(1 << 16)]
