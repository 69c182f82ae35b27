"""The simulated drive's own limits (drivers/sim/limits.py), set by SDO as a master does:
0x607D software position limits, 0x607F/0x6080 velocity, 0x6065/0x6066 following error."""
from __future__ import annotations

import math
import struct

import pytest

from rocoma_can.drivers.protocol import cia301, cia402
from rocoma_can.drivers.protocol.cia402 import Mode, State402

REV = 1 << 20                  # the shipped EDS's increments per revolution (gear 1:1)
PER_RAD = REV / (2 * math.pi)
LIMIT = 0.5                    # rad
# How far past a limit the drive's own loops may carry the joint before they hold it: the
# simulated position loop's overshoot (it is well damped; a few mrad), with margin.
OVERSHOOT = 0.02


def _position_limits(node, low: float = -LIMIT, high: float = LIMIT) -> None:
    node.sdo[0x607D][1].raw = math.floor(low * PER_RAD)
    node.sdo[0x607D][2].raw = math.ceil(high * PER_RAD)


def test_the_generic_eds_has_the_limit_objects_writable(sim_bench):
    node = sim_bench(1).node(1)
    for index, sub in ((0x607D, 1), (0x607D, 2), (0x607F, 0), (0x6080, 0), (0x6072, 0),
                       (0x6065, 0), (0x6066, 0)):
        var = node.sdo[index] if sub == 0 else node.sdo[index][sub]
        assert var.od.writable, hex(index)
    assert node.sdo[0x6065].raw == 0xFFFF_FFFF  # monitoring off until a master sets it


def test_a_position_target_outside_the_limit_is_clamped_to_it(sim_bench):
    bench = sim_bench(1)
    node, drive = bench.node(1), bench.drive(1)
    _position_limits(node)
    bench.enable(1, Mode.CSP)
    node.sdo[0x607A].raw = round(2 * LIMIT * PER_RAD)  # twice the limit
    bench.sync(400)
    assert LIMIT - OVERSHOOT < drive.position_rad <= LIMIT + OVERSHOOT
    assert drive.state402 == State402.OPERATION_ENABLED


@pytest.mark.parametrize("mode", [Mode.CSV, Mode.CST])
def test_velocity_and_torque_modes_stop_at_the_limit(sim_bench, mode):
    """No target to clamp: the drive slows down into the limit (velocity) or holds it
    (a torque pushing past), and stays there while the command goes on."""
    bench = sim_bench(1)
    node, drive = bench.node(1), bench.drive(1)
    _position_limits(node)
    bench.enable(1, mode)
    if mode == Mode.CSV:
        node.sdo[0x60FF].raw = round(2.0 * PER_RAD)  # 2 rad/s towards the limit
    else:
        node.sdo[0x6071].raw = 100  # 0.1 Nm on a 0.01 kg m^2 joint
    bench.sync(600)  # 1.2 s: without the limit it would be far beyond 0.5 rad
    assert LIMIT - OVERSHOOT < drive.position_rad <= LIMIT + OVERSHOOT
    assert abs(drive.velocity_rad_s) < 0.05


@pytest.mark.parametrize("index, value", [(0x607F, round(0.5 * PER_RAD)),  # increments/s
                                          (0x6080, 5)])                   # motor rpm
def test_the_velocity_command_is_bounded_by_0x607F_and_0x6080(sim_bench, index, value):
    bench = sim_bench(1)
    node, drive = bench.node(1), bench.drive(1)
    node.sdo[index].raw = value
    bench.enable(1, Mode.CSV)
    node.sdo[0x60FF].raw = round(3.0 * PER_RAD)  # 3 rad/s asked
    bench.sync(300)
    bound = 0.5 if index == 0x607F else 5 / 60 * 2 * math.pi
    assert drive.velocity_rad_s == pytest.approx(bound, rel=0.02)


def test_a_following_error_beyond_the_window_past_the_time_out_is_a_fault(sim_bench):
    bench = sim_bench(1)
    node, drive, rec = bench.node(1), bench.drive(1), bench.recorder
    node.sdo[0x6065].raw = round(0.01 * PER_RAD)  # 10 mrad
    node.sdo[0x6066].raw = 10                     # ms: five SYNCs of 2 ms
    bench.enable(1, Mode.CSP)
    bench.sync(5)
    assert drive.state402 == State402.OPERATION_ENABLED  # within the window at rest
    mark = rec.mark()
    node.sdo[0x607A].raw = round(0.3 * PER_RAD)  # a step the joint cannot follow at once
    bench.sync(4)
    assert drive.state402 == State402.OPERATION_ENABLED  # beyond, not yet for 10 ms
    bench.sync(4)
    assert drive.state402 in (State402.FAULT_REACTION_ACTIVE, State402.FAULT)
    assert drive.error_code == cia301.EMCY_FOLLOWING_ERROR
    assert drive.statusword & cia402.SW_FOLLOWING_ERROR
    rec.wait_for(lambda f: f.cob_id == 0x81 and struct.unpack_from("<H", f.data)[0]
                 == cia301.EMCY_FOLLOWING_ERROR, bench.stall, since=mark)
    bench.sync(100)  # the fault reaction's ramp to standstill
    assert drive.state402 == State402.FAULT and drive.statusword & cia402.SW_FOLLOWING_ERROR
    node.sdo[0x6040].raw = 0x00
    node.sdo[0x6040].raw = 0x80  # fault reset clears bit 13
    bench.wait(lambda: drive.state402 == State402.SWITCH_ON_DISABLED)
    assert not drive.statusword & cia402.SW_FOLLOWING_ERROR


def test_a_following_error_within_the_window_runs_on(sim_bench):
    bench = sim_bench(1)
    node, drive = bench.node(1), bench.drive(1)
    node.sdo[0x6065].raw = round(0.05 * PER_RAD)
    node.sdo[0x6066].raw = 4
    bench.enable(1, Mode.CSP)
    for k in range(1, 101):  # 0.2 rad/s ramp: the loop lags ~5 mrad
        node.sdo[0x607A].raw = round(0.2 * k * 0.002 * PER_RAD)
        bench.sync(1)
    assert drive.state402 == State402.OPERATION_ENABLED
    assert drive.position_rad == pytest.approx(0.04, abs=0.01)
