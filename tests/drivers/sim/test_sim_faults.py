"""drivers/sim/faults.py: fault injection: each fault produces the frames (or the silence) a real
drive would."""
from __future__ import annotations

import os
import signal
import struct
import threading

import numpy as np
import pytest
from fixtures.budgets import STALL, within

from rocoma_can import cli
from rocoma_can.cli.sim import parse_node_ids
from rocoma_can.drivers.protocol import cia301 as c301
from rocoma_can.drivers.protocol.cia301 import NmtCommand, NmtState
from rocoma_can.drivers.protocol.cia402 import Mode, State402


def _emcy(frame):
    code, register, vendor = struct.unpack("<HB5s", frame.data)
    assert len(frame.data) == 8 and vendor == bytes(5)
    return code, register


def test_trip_fault_emcy_error_objects_and_reset(sim_bench, sim_interface):
    bench = sim_bench(1, sim_interface)
    node, drive, rec = bench.node(1), bench.drive(1), bench.recorder
    bench.enable(1, Mode.CST)
    mark = rec.mark()
    drive.trip_fault(c301.EMCY_OVERCURRENT)
    bench.sync(2)
    (emcy,) = rec.wait_for_count(1, bench.stall, 0x81, since=mark)
    assert _emcy(emcy) == (c301.EMCY_OVERCURRENT, 0x03)
    assert drive.state402 == State402.FAULT
    assert node.sdo[0x603F].raw == c301.EMCY_OVERCURRENT
    assert node.sdo[0x1001].raw == 0x03  # generic + current
    assert (node.sdo[0x1003][0].raw, node.sdo[0x1003][1].raw) == (1, c301.EMCY_OVERCURRENT)
    node.sdo[0x6040].raw = 0x00
    mark = rec.mark()
    node.sdo[0x6040].raw = 0x80
    assert _emcy(rec.wait_for_count(1, bench.stall, 0x81, since=mark)[0]) == (0x0000, 0x00)
    assert drive.state402 == State402.SWITCH_ON_DISABLED
    assert (node.sdo[0x603F].raw, node.sdo[0x1001].raw) == (0, 0)
    node.sdo[0x1003][0].raw = 0  # clears the history
    assert node.sdo[0x1003][0].raw == 0


def test_fault_while_moving_ramps_down_before_fault(sim_bench):
    bench = sim_bench(1)
    drive = bench.drive(1)
    bench.spin(1)
    drive.trip_fault(c301.EMCY_OVERTEMPERATURE)
    bench.sync(10)
    assert drive.state402 == State402.FAULT_REACTION_ACTIVE
    assert drive.statusword & 0x4F == 0x0F
    bench.sync(200)  # 0x6085 default 10 rev/s^2: 1 rev/s is gone in 0.1 s
    assert drive.state402 == State402.FAULT
    bench.sync(2)
    assert drive.torque_nm == 0.0


def test_silent_drive_sends_nothing_the_others_go_on(sim_bench, sim_interface):
    bench = sim_bench(2, sim_interface)
    node, rec = bench.node(1), bench.recorder
    period = 0.020  # both drives' heartbeat
    node.sdo[0x1017].raw = round(period * 1000)
    bench.node(2).sdo[0x1017].raw = round(period * 1000)
    bench.nmt(NmtCommand.START)
    bench.drive(1).set_silent(True)
    mark = bench.barrier(2)  # node 1 frames sent before silence may still be on their way
    bench.sync(5)
    bench.drive(1).trip_fault()
    rec.wait_for_count(5, bench.stall, 0x182, since=mark)
    rec.wait_for_count(3, bench.within(3 * period), 0x702, since=mark)  # > 2 periods have passed
    assert [f for f in rec.frames(since=mark) if f.cob_id & 0x7F == 1] == []
    bench.drive(1).set_silent(False)
    rec.wait_for_count(1, bench.within(period), 0x701, since=rec.mark())


def test_drive_that_stops_answering_sync(sim_bench):
    bench = sim_bench(2)
    rec = bench.recorder
    bench.nmt(NmtCommand.START)
    bench.drive(2).set_sync_response(False)
    mark = rec.mark()
    bench.sync(4)
    rec.wait_for_count(4, bench.stall, 0x181, since=mark)
    bench.nmt(NmtCommand.START)  # a frame after the SYNCs: everything before has been seen
    bench.sync(1)
    rec.wait_for_count(5, bench.stall, 0x181, since=mark)
    assert rec.count((0x182, 0x282), since=mark) == 0
    assert bench.drive(2).nmt_state == NmtState.OPERATIONAL


def test_late_tpdo(sim_bench, sim_interface):
    bench = sim_bench(1, sim_interface)
    rec = bench.recorder
    bench.nmt(NmtCommand.START)
    delay = 0.08
    bench.drive(1).set_tpdo_delay(delay)
    mark = rec.mark()
    bench.send(0x080)
    sync = rec.wait_for(lambda f: f.cob_id == 0x080, bench.stall, since=mark)
    tpdo = rec.wait_for(lambda f: f.cob_id == 0x181, bench.within(delay), since=mark)
    # bus timestamps (taken when sent): the recorder's own arrival times may lag either
    assert tpdo.message.timestamp - sync.message.timestamp >= delay
    # SYNC first, then its TPDO (the drive's heartbeat may come in between)
    assert [i for i in rec.cob_ids(since=mark) if i in (0x080, 0x181)][:2] == [0x080, 0x181]


def test_babble_is_bounded(sim_bench):
    bench = sim_bench(1)
    rec = bench.recorder
    bench.drive(1).babble(count=300, cob_id=0x001, data=b"\xff" * 8, burst=50)
    frames = rec.wait_for_count(300, bench.within(300 / 50 * 0.001), 0x001)  # 50 per ms
    assert all(f.data == b"\xff" * 8 for f in frames)
    bench.nmt(NmtCommand.START)
    bench.sync(3)  # the segment still works while/after babbling
    rec.wait_for_count(3, bench.stall, 0x181)
    assert rec.count(0x001) == 300
    with pytest.raises(ValueError):
        bench.drive(1).babble(count=10 ** 6)


def test_sto_low_drops_out_of_operation_enabled(sim_bench, sim_interface):
    bench = sim_bench(1, sim_interface)
    node, drive, rec = bench.node(1), bench.drive(1), bench.recorder
    bench.spin(1, syncs=100)
    mark = rec.mark()
    drive.set_sto(True)
    code, register = _emcy(rec.wait_for_count(1, bench.stall, 0x81, since=mark)[0])
    assert (code, register & 0x01) == (c301.EMCY_STO, 0x01)
    assert drive.state402 == State402.SWITCH_ON_DISABLED
    bench.sync(5)
    assert drive.torque_nm == 0.0 and drive.velocity_rad_s > 1.0  # power off: it coasts
    node.sdo[0x6040].raw = 0x06
    assert drive.state402 == State402.SWITCH_ON_DISABLED
    mark = rec.mark()
    drive.set_sto(False)
    assert _emcy(rec.wait_for_count(1, bench.stall, 0x81, since=mark)[0]) == (0x0000, 0x00)
    node.sdo[0x6040].raw = 0x06
    assert drive.state402 == State402.READY_TO_SWITCH_ON


def test_position_sensor_noise(sim_bench):
    bench = sim_bench(1, seed=3)
    rec = bench.recorder
    bench.nmt(NmtCommand.START)
    bench.sync(20)
    clean = [struct.unpack("<ii", f.data)[0] for f in rec.wait_for_count(20, bench.stall, 0x281)]
    assert set(clean) == {0}
    bench.drive(1).set_position_noise(100.0)
    mark = rec.mark()
    bench.sync(200)
    noisy = [struct.unpack("<ii", f.data)[0]
             for f in rec.wait_for_count(200, bench.stall, 0x281, since=mark)]
    assert 70 < np.std(noisy) < 130
    assert bench.drive(1).position_rad == 0.0  # the joint itself did not move


def test_parse_node_ids():
    assert parse_node_ids("1-4,7") == [1, 2, 3, 4, 7]
    assert parse_node_ids("3") == [3]
    for bad in ("0", "1-200", "a", "", "1-999999999", "5-3"):
        with pytest.raises(Exception, match="node ids"):
            parse_node_ids(bad)


@pytest.mark.parametrize("args", [
    ["--duration", "nan"], ["--duration", "-1"], ["--status-interval", "inf"],
    ["--sync-period", "0"], ["--rated-torque-nm", "nan"], ["--fault", "1@nan"],
    ["--fault", "1@-2"], ["--nodes", "1-999999999"], ["--increments-per-rev", "0"],
])
def test_sim_numbers_out_of_range_are_usage_errors(args, virtual_channel, capsys):
    """A non-finite or out-of-range number is argparse's usage error (exit 2) naming the
    option, before any bus opens: not a traceback, nor a timer thread spinning on nan."""
    with pytest.raises(SystemExit) as exited:
        cli.main(["sim", "--interface", "virtual", "--channel", virtual_channel, *args])
    assert exited.value.code == 2
    assert f"argument {args[0]}" in capsys.readouterr().err


def test_cli_runs_a_segment_with_faults_and_status(frame_recorder, virtual_channel, capsys):
    rec = frame_recorder()
    duration = 1.5  # the CLI's run; the fault is injected 0.1 s into it

    def ask_for_status() -> None:  # SIGUSR1 once the segment runs and the fault is in
        rec.wait_for(lambda f: f.cob_id == 0x82, within(duration))
        os.kill(os.getpid(), signal.SIGUSR1)

    # a SIGUSR1 before the CLI has its handler must not kill the test run
    previous = signal.signal(signal.SIGUSR1, lambda *_: None)
    asker = threading.Thread(target=ask_for_status)
    asker.start()
    try:
        code = cli.main(["sim", "--interface", "virtual", "--channel", virtual_channel,
                         "--nodes", "1-2", "--duration", str(duration), "--fault", "2:0x2310@0.1",
                         "--sto-low", "1"])
    finally:
        asker.join(within(duration) + STALL)
        signal.signal(signal.SIGUSR1, previous)
    assert code == 0
    assert [f.data for f in rec.frames(0x701)][:1] == [b"\x00"]
    emcys = {f.cob_id: struct.unpack("<H", f.data[:2])[0] for f in rec.frames((0x81, 0x82))}
    assert emcys == {0x81: c301.EMCY_STO, 0x82: c301.EMCY_OVERCURRENT}
    out = capsys.readouterr().out
    status = [line for line in out.splitlines() if line.startswith("node")]
    assert len(status) >= 2 and "FAULT" in status[-1] and "STO" in status[-2]
    assert cli.main(["sim", "--interface", "virtual", "--channel", virtual_channel,
                     "--nodes", "1", "--fault", "5"]) == 2
