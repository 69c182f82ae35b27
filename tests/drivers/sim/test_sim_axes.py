"""drivers/sim/drive.py (two axes): a simulated node with two CiA 402 axes (CiA 402-2,
tests/fixtures/eds/two_axes.eds: axis 2's objects at +0x800), driven over a python-can virtual bus
by canopen's SDO client, raw PDO frames and SYNC: one CANopen node (one boot-up, one heartbeat, one
EMCY producer), two state machines, two joints."""
from __future__ import annotations

import math
import struct
import time
from collections.abc import Callable

import pytest
from canopen.sdo import SdoAbortedError
from fixtures.paths import TESTS

from rocoma_can import cli
from rocoma_can.drivers.protocol import cia301 as c301
from rocoma_can.drivers.protocol.cia301 import NmtCommand
from rocoma_can.drivers.protocol.cia402 import AbortConnectionOption, Mode, State402
from rocoma_can.drivers.sim.dynamics import JointParams

EDS = TESTS / "fixtures" / "eds"
TWO_AXES = str(EDS / "two_axes.eds")
AXIS2 = 0x800  # CiA 402-2: axis 2's objects
MASTER = 0x7F
RPDO2 = struct.Struct("<Hi")  # axis 2's controlword, target position
TPDO2 = struct.Struct("<Hi")  # axis 2's statusword, position actual


def _bench(sim_bench, **kwargs):
    bench = sim_bench(1, eds_path=TWO_AXES, axes={1: 2}, **kwargs)
    return bench, bench.node(1, TWO_AXES), bench.drive(1)


def _sync_until(bench, predicate: Callable[[], bool], what: str, seconds: float) -> None:
    """SYNCs one at a time until ``predicate`` (the segment steps its joints only on SYNC
    with a fixed sync period): within the budget for something that takes ``seconds``."""
    deadline = time.monotonic() + bench.within(seconds)
    while not predicate():
        if time.monotonic() > deadline:
            raise TimeoutError(f"{what} not reached within {bench.within(seconds)} s")
        bench.sync(1)


def _enable_both_by_sdo(bench, node, first: Mode, second: Mode) -> None:
    """NMT start, each axis's mode, then shutdown, switch on, enable operation on both."""
    bench.nmt(NmtCommand.START, 1)
    for index, mode in ((0x6060, first), (0x6860, second)):
        node.sdo[index].raw = int(mode)
    for cw in (0x06, 0x07, 0x0F):
        node.sdo[0x6040].raw = cw
        node.sdo[0x6840].raw = cw


def test_two_axis_node_boots_once_and_beats_once(sim_bench):
    bench, node, drive = _bench(sim_bench)
    rec = bench.recorder
    period = node.sdo[0x1017].raw / 1000
    frames = rec.wait_for_count(7, bench.within(6 * period), 0x701)
    assert [f.data for f in frames] == [b"\x00"] + [b"\x7f"] * 6  # one boot-up
    # One producer: its n-th heartbeat is due (n + 1) periods after the boot-up at the
    # earliest (a late one never brings the next one forward); two would beat twice as often.
    boot, last = frames[0].time, frames[-1].time
    assert len(frames) - 1 <= (last - boot) / period + 1, [f.time - boot for f in frames]
    assert [a.number for a in drive.axes] == [1, 2] and drive.axis(2) is drive.axes[1]
    assert [a.joint for a in drive.axes] == [0, 1]
    assert drive.axis(1).state402 == drive.axis(2).state402 == State402.SWITCH_ON_DISABLED
    with pytest.raises(ValueError, match="axes 1..2, not 3"):
        drive.axis(3)
    lines = bench.segment.status_lines()
    assert [line.split()[:4] for line in lines] == [
        ["node", "1", "axis", "1"], ["node", "1", "axis", "2"]]


def test_sdo_to_axis_2_objects_drives_axis_2_only(sim_bench):
    bench, node, drive = _bench(sim_bench)
    axis1, axis2 = drive.axes
    node.sdo[0x6060 + AXIS2].raw = int(Mode.CSP)
    node.sdo[0x6040 + AXIS2].raw = 0x06
    assert axis2.state402 == State402.READY_TO_SWITCH_ON
    assert axis1.state402 == State402.SWITCH_ON_DISABLED
    assert node.sdo[0x6861].raw == Mode.CSP and axis2.mode_display == Mode.CSP
    assert node.sdo[0x6061].raw == 0 and axis1.mode_display == 0
    assert node.sdo[0x6841].raw & 0x6F == 0x21  # ready to switch on
    assert node.sdo[0x6041].raw & 0x4F == 0x40  # switch on disabled
    node.sdo[0x6840].raw = 0x07
    node.sdo[0x6840].raw = 0x0F
    assert axis2.state402 == State402.OPERATION_ENABLED
    assert axis1.state402 == State402.SWITCH_ON_DISABLED
    assert (drive.state402, drive.statusword) == (axis1.state402, axis1.statusword)
    with pytest.raises(SdoAbortedError) as err:  # CST is not in axis 2's 0x6D02 (CSP, CSV)
        node.sdo[0x6860].raw = int(Mode.CST)
    assert err.value.code == 0x06090030
    assert axis2.mode_display == Mode.CSP


def test_each_axis_has_its_own_scaling(sim_bench):
    bench, node, drive = _bench(sim_bench, increments_per_rev=4096)
    axis1, axis2 = drive.axes
    # no 0x608F/0x6091 in the file: both axes take the segment's fallback
    assert axis1.increments_per_rad == axis2.increments_per_rad == pytest.approx(
        4096 / (2 * math.pi))
    node.sdo[0x6876].raw = 2500  # axis 2's rated torque, mNm
    assert axis2.nm_per_permille == pytest.approx(2.5e-3)
    assert axis1.nm_per_permille == pytest.approx(1e-3)  # 0x6076 = 1000
    with pytest.raises(SdoAbortedError) as err:  # a rated torque of 0 is refused on axis 2 too
        node.sdo[0x6876].raw = 0
    assert err.value.code == 0x06090032


def test_nmt_stop_aborts_the_connection_of_every_axis(sim_bench):
    bench, node, drive = _bench(sim_bench)
    axis1, axis2 = drive.axes
    _enable_both_by_sdo(bench, node, Mode.CSV, Mode.CSV)
    assert axis1.state402 == axis2.state402 == State402.OPERATION_ENABLED
    bench.nmt(NmtCommand.STOP, 1)  # 0x6007 = 0x6807 = 2 (the file's): disable voltage
    assert axis1.state402 == axis2.state402 == State402.SWITCH_ON_DISABLED


def _map(node, comm: int, mapping: int, entries: tuple[int, ...], cob_id: int,
         trans_type: int) -> None:
    """CiA 301: COB-ID invalid, sub 0 = 0, the entries, sub 0, transmission type, valid."""
    node.sdo[comm][1].raw = 0x80000000 | cob_id
    node.sdo[mapping][0].raw = 0
    for sub, entry in enumerate(entries, start=1):
        node.sdo[mapping][sub].raw = entry
    node.sdo[mapping][0].raw = len(entries)
    node.sdo[comm][2].raw = trans_type
    node.sdo[comm][1].raw = cob_id


def test_pdos_enable_and_move_axis_2_while_axis_1_stays(sim_bench):
    bench, node, drive = _bench(sim_bench)
    axis1, axis2 = drive.axes
    rec = bench.recorder
    _map(node, 0x1401, 0x1601, (0x68400010, 0x687A0020), 0x301, 1)
    _map(node, 0x1801, 0x1A01, (0x68410010, 0x68640020), 0x281, 1)
    node.sdo[0x6860].raw = int(Mode.CSP)
    bench.nmt(NmtCommand.START, 1)
    for cw in (0x06, 0x07, 0x0F):
        bench.send(0x301, RPDO2.pack(cw, 0))
        bench.sync(1)
    assert axis2.state402 == State402.OPERATION_ENABLED
    target = 0.2  # rad
    increments = round(target * axis2.increments_per_rad)
    ramp = 100
    for k in range(1, ramp + 1):
        bench.send(0x301, RPDO2.pack(0x0F, increments * k // ramp))
        bench.sync(1)
    bench.sync(200)  # 0.4 s at the fixed 2 ms: the position loop (40/s) has settled
    assert axis2.position_rad == pytest.approx(target, abs=0.005)
    assert axis1.state402 == State402.SWITCH_ON_DISABLED
    assert (axis1.position_rad, axis1.velocity_rad_s, axis1.torque_nm) == (0.0, 0.0, 0.0)
    assert drive.od_value(0x6041) & 0x4F == 0x40 and drive.od_value(0x6064) == 0
    mark = bench.barrier()
    bench.sync(1)
    frame = rec.wait_for_count(1, bench.stall, 0x281, since=mark)[0]
    statusword, position = TPDO2.unpack(frame.data)
    assert statusword & 0x6F == 0x27  # operation enabled
    assert (statusword, position) == (axis2.statusword, axis2.position_increments)
    assert position == pytest.approx(increments, abs=0.005 * axis2.increments_per_rad)


def test_one_rpdo_drives_both_axes_and_refuses_one_unsupported_mode(sim_bench):
    bench, node, drive = _bench(sim_bench)
    axis1, axis2 = drive.axes
    layout = struct.Struct("<HHbb")
    _map(node, 0x1400, 0x1600, (0x60400010, 0x68400010, 0x60600008, 0x68600008), 0x201, 255)
    bench.nmt(NmtCommand.START, 1)
    bench.send(0x201, layout.pack(0x06, 0x06, int(Mode.CSV), int(Mode.CST)))
    bench.sync(1)  # event-driven: applied on arrival, before this SYNC
    assert axis1.state402 == axis2.state402 == State402.READY_TO_SWITCH_ON
    assert axis1.mode_display == Mode.CSV
    assert axis2.mode_display == 0 and node.sdo[0x6860].raw == 0  # CST: not axis 2's
    bench.send(0x201, layout.pack(0x06, 0x07, int(Mode.CSV), int(Mode.CSP)))
    bench.sync(1)
    assert (axis1.state402, axis2.state402) == (State402.READY_TO_SWITCH_ON,
                                                State402.SWITCHED_ON)
    assert axis2.mode_display == Mode.CSP


def test_fault_of_axis_2_is_its_own_and_the_nodes_emcy(sim_bench):
    bench, node, drive = _bench(sim_bench)
    axis1, axis2 = drive.axes
    rec = bench.recorder
    mark = rec.mark()
    axis2.trip_fault(c301.EMCY_OVERCURRENT)
    emcy = rec.wait_for_count(1, bench.stall, 0x81, since=mark)[0]
    code, register, _ = struct.unpack("<HB5s", emcy.data)
    assert (code, register) == (c301.EMCY_OVERCURRENT, 0x03)  # generic + current
    assert axis2.state402 == State402.FAULT and node.sdo[0x6841].raw & 0x08
    assert node.sdo[0x683F].raw == c301.EMCY_OVERCURRENT
    assert axis1.state402 == State402.SWITCH_ON_DISABLED
    assert not node.sdo[0x6041].raw & 0x08 and node.sdo[0x603F].raw == 0
    assert node.sdo[0x1001].raw == 0x03
    # axis 1 faults too; axis 2's reset leaves axis 1's error in the register
    axis1.trip_fault(c301.EMCY_GENERIC)
    mark = bench.barrier()  # after axis 1's EMCY
    node.sdo[0x6840].raw = 0x80
    emcy = rec.wait_for_count(1, bench.stall, 0x81, since=mark)[0]
    assert struct.unpack("<HB5s", emcy.data)[:2] == (c301.EMCY_NO_ERROR, 0x01)
    assert axis2.state402 == State402.SWITCH_ON_DISABLED and node.sdo[0x683F].raw == 0
    assert axis1.state402 == State402.FAULT and drive.error_register == 0x01
    node.sdo[0x6040].raw = 0x80
    assert axis1.state402 == State402.SWITCH_ON_DISABLED and drive.error_register == 0


def test_lost_master_heartbeat_switches_each_axis_off_by_its_own_option(sim_bench):
    bench, node, drive = _bench(sim_bench)
    axis1, axis2 = drive.axes
    rec = bench.recorder
    consumer = 0.300
    node.sdo[0x1016][1].raw = (MASTER << 16) | round(consumer * 1000)
    node.sdo[0x6007].raw = int(AbortConnectionOption.DISABLE_VOLTAGE)
    node.sdo[0x6807].raw = int(AbortConnectionOption.FAULT)
    _enable_both_by_sdo(bench, node, Mode.CSV, Mode.CSP)
    assert axis1.state402 == axis2.state402 == State402.OPERATION_ENABLED
    mark = rec.mark()
    bench.send(0x700 + MASTER, b"\x05")  # monitoring starts; then the master is gone
    emcy = rec.wait_for(lambda f: f.cob_id == 0x81, bench.within(consumer), since=mark)
    assert struct.unpack("<H", emcy.data[:2])[0] == c301.EMCY_HEARTBEAT
    assert axis1.state402 == State402.SWITCH_ON_DISABLED  # 0x6007: disable voltage
    _sync_until(bench, lambda: axis2.state402 == State402.FAULT,  # 0x6807: fault (its ramp)
                "axis 2's fault", 0.1)
    assert axis2.error_code == c301.EMCY_HEARTBEAT and axis1.error_code == 0
    bench.barrier()  # every frame the segment sent so far has been recorded
    assert rec.count(0x81, since=mark) == 1  # axis 2's fault reported the loss, once


def test_node_asked_for_an_axis_its_file_lacks_is_refused(sim_segment_factory):
    with pytest.raises(ValueError, match="drive 4: axis 2 needs its controlword 0x6840"):
        sim_segment_factory([3, 4], eds_path=str(EDS / "minimal.eds"), axes={4: 2})
    with pytest.raises(ValueError, match="drive 1: axis 3 needs its controlword 0x7040"):
        sim_segment_factory(1, eds_path=TWO_AXES, axes={1: 3})
    with pytest.raises(ValueError, match="1..8 axes"):
        sim_segment_factory(1, eds_path=TWO_AXES, axes={1: 9})
    with pytest.raises(ValueError, match=r"node ids \[2\]"):
        sim_segment_factory(1, eds_path=TWO_AXES, axes={2: 2})


def test_joints_in_order_of_node_then_axis_with_params_per_node_or_axis(sim_segment_factory):
    node_params, axis_params = JointParams(inertia=0.5), JointParams(inertia=0.7)
    segment = sim_segment_factory([5, 2], eds_path=TWO_AXES, axes={2: 2},
                                  params={2: node_params, (2, 2): axis_params})
    assert [a.joint for a in segment.drives[2].axes] == [0, 1]
    assert [a.joint for a in segment.drives[5].axes] == [2]
    assert segment.dynamics.inertia.tolist() == [0.5, 0.7, JointParams().inertia]
    assert len(segment.status_lines()) == 3


def test_cli_axes_flag(virtual_channel, capsys):
    args = ["sim", "--interface", "virtual", "--channel", virtual_channel, "--nodes", "1",
            "--axes", "2"]
    assert cli.main([*args, "--duration", "0.3", "--status-interval", "0.1",
                     "--eds", TWO_AXES]) == 0
    out = capsys.readouterr().out
    status = [line.split()[:4] for line in out.splitlines() if line.startswith("node")]
    assert ["node", "1", "axis", "1"] in status and ["node", "1", "axis", "2"] in status
    assert cli.main(args) == 2  # the shipped EDS has one axis
    assert "--axes 2: axis 2 needs its controlword 0x6840" in capsys.readouterr().err
    assert cli.main([*args[:-1], "9", "--eds", TWO_AXES]) == 2
    assert "--axes 9: a node has 1..8 axes" in capsys.readouterr().err
