"""drivers/plan/config.py, pdo_layout.py, scaling.py: pure parts of the CAN driver: config checks,
PDO layouts and codecs, scaling, limit_command."""
from __future__ import annotations

import math
import struct

import canopen
import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st

from rocoma_can import eds
from rocoma_can.drivers.cycle.enable import ENABLE_STEP, EnableSequence
from rocoma_can.drivers.hardware import CanopenHardware
from rocoma_can.drivers.plan.config import DriveConfig
from rocoma_can.drivers.plan.drive_clashes import check_drives
from rocoma_can.drivers.plan.pdo_layout import (
    CONTROLWORD,
    MODE,
    STATUSWORD,
    TARGET_POSITION,
    check_against_od,
    first_fit,
    layout_for,
)
from rocoma_can.drivers.plan.scaling import Scaling
from rocoma_can.drivers.protocol import cia402
from rocoma_can.drivers.protocol.joints import JointCommand, JointMode
from rocoma_can.drivers.protocol.wire import fd_length, frame_bits
from rocoma_can.runtime.system import manager_for


def drive(name="j0", node_id=1, **kw) -> DriveConfig:
    kw.setdefault("increments_per_rev", 4096)
    kw.setdefault("rated_torque_nm", 2.0)
    return DriveConfig(name=name, node_id=node_id, **kw)


# --- config -------------------------------------------------------------------------------
@pytest.mark.parametrize("kw, field", [
    (dict(node_id=0), "node_id"), (dict(node_id=128), "node_id"),
    (dict(increments_per_rev=0), "increments_per_rev"),
    (dict(rated_torque_nm=-1.0), "rated_torque_nm"), (dict(gear_ratio=0), "gear_ratio"),
    (dict(modes=["vl"]), "modes"), (dict(modes=[]), "modes"),
    (dict(feedback=["current"]), "feedback"), (dict(max_torque_nm=0), "max_torque_nm"),
    (dict(position_min=1.0, position_max=0.0), "position_min"),
    (dict(heartbeat_ms=0), "heartbeat_ms"), (dict(eds="/no/such.eds"), "eds"),
    (dict(pdo_bytes=7), "pdo_bytes"), (dict(pdo_bytes=65), "pdo_bytes"),
])
def test_bad_drive_config_names_the_field(kw, field):
    with pytest.raises(ValueError, match=field):
        drive(**kw)


def test_modes_accept_names_and_numbers_and_drop_duplicates():
    d = drive(modes=["CSP", 9, "csp", JointMode.CST])
    assert d.modes == (JointMode.CSP, JointMode.CSV, JointMode.CST)


def test_from_dict_rejects_unknown_and_missing_keys():
    with pytest.raises(ValueError, match="gear_ration"):
        DriveConfig.from_dict(dict(name="a", node_id=1, increments_per_rev=1,
                                   rated_torque_nm=1, gear_ration=3))
    with pytest.raises(ValueError, match="rated_torque_nm"):
        DriveConfig.from_dict(dict(name="a", node_id=1, increments_per_rev=1))
    d = DriveConfig.from_dict(dict(name="a", node_id=3, increments_per_rev=10,
                                   rated_torque_nm=1.5, modes=["csv"]))
    assert d.node_id == 3 and d.modes == (JointMode.CSV,)


def test_drive_set_checks():
    with pytest.raises(ValueError, match="node_id 1 is already used"):
        check_drives([drive("a", 1), drive("b", 1)], 100)
    with pytest.raises(ValueError, match="used twice"):
        check_drives([drive("a", 1), drive("a", 2)], 100)
    with pytest.raises(ValueError, match="manager's node id"):
        check_drives([drive("a", 100)], 100)


# --- layouts --------------------------------------------------------------------------------
@pytest.mark.parametrize("modes, feedback, rpdos, tpdos", [
    (["csp"], ["position", "velocity", "torque"], 1, 2),
    (["cst"], ["position", "torque"], 1, 1),
    (["csv"], ["position", "velocity"], 1, 2),
    (["csp", "csv", "cst"], ["position", "velocity", "torque"], 2, 2),
    (["csp", "cst"], ["position"], 2, 1),
])
def test_layout_frame_counts(modes, feedback, rpdos, tpdos):
    layout = layout_for(drive(modes=modes, feedback=feedback))
    assert (len(layout.rpdos), len(layout.tpdos)) == (rpdos, tpdos)
    for pdo in layout.rpdos + layout.tpdos:
        assert pdo.size <= 8
    assert layout.rpdos[0].entries[:2] == (CONTROLWORD, MODE)
    assert layout.tpdos[0].entries[0] == STATUSWORD
    assert [p.cob_id for p in layout.rpdos] == [0x201, 0x301][:rpdos]
    assert [p.cob_id for p in layout.tpdos] == [0x181, 0x281][:tpdos]


def test_longer_pdos_make_one_rpdo_and_one_tpdo_padded_to_a_can_fd_length():
    """pdo_bytes 64 (a drive on a CAN FD bus that maps longer PDOs): everything in one RPDO
    and one TPDO; a PDO of 13 bytes goes out as a 16-byte FD frame (its codec pads, and
    the receive check expects that length); 8 bytes and less stay as they are."""
    layout = layout_for(drive(modes=["csp", "csv", "cst"], pdo_bytes=64))
    (rpdo,), (tpdo,) = layout.rpdos, layout.tpdos
    assert rpdo.names == ("controlword", "mode", "target_position", "target_velocity",
                          "target_torque")
    assert tpdo.names == ("statusword", "position", "velocity", "torque")
    assert (sum(e.size for e in rpdo.entries), rpdo.size) == (13, 16)
    assert (sum(e.size for e in tpdo.entries), tpdo.size) == (12, 12)
    assert rpdo.codec.pack(0x0F, 8, -1, 2, -3) == \
        struct.pack("<Hbiih", 0x0F, 8, -1, 2, -3) + bytes(3)
    assert tpdo.codec.unpack(bytes(range(12)))[0] == 0x0100
    assert [fd_length(n) for n in (0, 8, 9, 12, 13, 17, 33, 49, 64)] == \
        [0, 8, 12, 12, 16, 20, 48, 64, 64]
    assert frame_bits(9, data_ratio=0.2) == frame_bits(12, data_ratio=0.2)
    with pytest.raises(ValueError, match="0..64 data bytes"):
        fd_length(65)
    assert layout_for(drive(modes=["csp"])).rpdos[0].size == 7  # classic: never padded


def test_first_fit_fills_earlier_pdos():
    groups = first_fit([STATUSWORD, TARGET_POSITION, TARGET_POSITION, STATUSWORD])
    assert [sum(e.size for e in g) for g in groups] == [8, 4]


def test_mapping_values():
    assert CONTROLWORD.mapping == 0x60400010
    assert MODE.mapping == 0x60600008
    assert TARGET_POSITION.mapping == 0x607A0020


def test_layout_fits_the_shipped_eds_and_bad_objects_are_named():
    layout = layout_for(drive(modes=["csp", "csv", "cst"]))
    od = canopen.import_od(str(eds.path(eds.CIA402_DRIVE)), 1)
    check_against_od(layout, od, "j0")
    del od[cia402.TARGET_TORQUE]
    with pytest.raises(ValueError, match="0x6071"):
        check_against_od(layout, od, "j0")


def test_codec_round_trip():
    layout = layout_for(drive(modes=["csp"]))
    rpdo = layout.rpdos[0]
    data = rpdo.codec.pack(0x0F, 8, -123456)
    assert data == struct.pack("<HbI", 0x0F, 8, (-123456) & 0xFFFFFFFF)


# --- scaling ---------------------------------------------------------------------------------
@given(st.floats(-50, 50), st.floats(-100, 100), st.floats(-5, 5))
def test_scaling_round_trip(q, v, t):
    drives = [drive(gear_ratio=50.0, max_torque_nm=1e9),
              drive("j1", 2, gear_ratio=-3.0, increments_per_rev=1 << 20)]
    sc = Scaling(drives)
    si = np.array([q, -q]), np.array([v, v]), np.array([t, 2 * t])
    raw = [np.zeros(2, dtype=np.int64) for _ in range(3)]
    sc.encode_position(si[0], raw[0])
    sc.encode_velocity(si[1], raw[1])
    sc.encode_torque(si[2], raw[2])
    out = [np.zeros(2) for _ in range(3)]
    sc.decode(raw[0], sc.position, out[0])
    sc.decode(raw[1], sc.velocity, out[1])
    sc.decode(raw[2], sc.torque, out[2])
    for a, b, f in zip(out, si, (sc.position, sc.velocity, sc.torque)):
        assert np.all(np.abs(a - b) <= np.abs(f) / 2 + 1e-12)


def test_scaling_saturates_instead_of_wrapping():
    sc = Scaling([drive(rated_torque_nm=1.0)])
    raw = np.zeros(1, dtype=np.int64)
    sc.encode_torque(np.array([1e6]), raw)
    assert raw[0] == 32767
    sc.encode_position(np.array([-1e12]), raw)
    assert raw[0] == -(1 << 31)


def test_gear_ratio_and_rated_torque_scale_the_joint():
    sc = Scaling([drive(increments_per_rev=1000, gear_ratio=10.0, rated_torque_nm=2.0)])
    assert math.isclose(sc.position[0], 2 * math.pi / 10000)
    assert math.isclose(sc.torque[0], 2.0 * 10.0 / 1000)  # per mille of motor torque x ratio


# --- hardware without a bus: limit_command, pre-encoded frames -------------------------------
@pytest.fixture
def hw():
    drives = [drive("a", 1, modes=["csp"], position_min=-1.0, position_max=1.0),
              drive("b", 2, modes=["cst", "csv"], max_torque_nm=3.0)]
    return CanopenHardware(None, drives, manager_node_id=100, dt=0.01)


def test_limit_command_rejects_unconfigured_mode(hw):
    cmd = JointCommand.zeros(["a", "b"])
    cmd.mode[:] = [JointMode.CSP, JointMode.CST]
    assert hw.limit_command(cmd)
    cmd.mode[:] = [JointMode.CSV, JointMode.CST]  # a is CSP only
    assert not hw.limit_command(cmd)
    cmd.mode[:] = [JointMode.TORQUE_OFF, JointMode.QUICK_STOP]  # always allowed
    assert hw.limit_command(cmd)
    cmd.mode[:] = [JointMode.CSP, 200]
    assert not hw.limit_command(cmd)


def test_limit_command_rejects_nan_and_clips(hw):
    cmd = JointCommand.zeros(["a", "b"])
    cmd.mode[:] = [JointMode.CSP, JointMode.CST]
    cmd.position[:] = [5.0, 0.0]
    cmd.torque[:] = [0.0, -10.0]
    assert hw.limit_command(cmd)
    assert cmd.position[0] == 1.0 and cmd.torque[1] == -3.0
    cmd.velocity[1] = math.nan
    assert not hw.limit_command(cmd)


def test_torque_off_frames_are_preencoded(hw):
    frames = hw.frames._torque_off
    assert [m.arbitration_id for m in frames[0]] == [0x201]
    assert bytes(frames[0][0].data) == struct.pack("<HbI", 0, 8, 0)
    assert [m.arbitration_id for m in frames[1]] == [0x202, 0x302]
    assert bytes(frames[1][0].data)[:2] == b"\0\0"
    assert bytes(hw.frames._fault_reset[0][0].data)[:2] == struct.pack("<H", 0x80)
    assert hw.frames_per_cycle == (1 + 2) + (2 + 2) + 1


def test_enable_steps():
    def step(s):
        return ENABLE_STEP[int(s) + 1]
    S = cia402.State402
    assert step(S.SWITCH_ON_DISABLED) == 0x06
    assert step(S.READY_TO_SWITCH_ON) == 0x07
    assert step(S.SWITCHED_ON) == 0x0F
    assert step(S.OPERATION_ENABLED) == 0x0F
    for s in (S.UNKNOWN, S.NOT_READY_TO_SWITCH_ON, S.FAULT, S.FAULT_REACTION_ACTIVE,
              S.QUICK_STOP_ACTIVE):
        assert step(s) == 0x00


def test_each_enable_step_gets_the_whole_timeout_and_a_stuck_drive_is_found():
    """A drive that answers every step late (each under the timeout, all of them together
    over it) is not stuck; one that stays in a state for longer than the timeout is, and
    going back a step does not buy it more time."""
    S = cia402.State402
    faults: list[tuple[int, str, float]] = []
    seq = EnableSequence(2, timeout=1.0, fault=lambda i, cause, now: faults.append((i, cause, now)))
    t = 0.0
    for state in (S.SWITCH_ON_DISABLED, S.READY_TO_SWITCH_ON, S.SWITCHED_ON):
        for _ in range(9):  # 0.9 s in each state, 0.1 s per cycle
            assert seq.controlword(0, int(state), t) == ENABLE_STEP[int(state) + 1]
            t += 0.1
    assert seq.controlword(0, int(S.OPERATION_ENABLED), t) == 0x0F
    assert faults == []  # 2.7 s in all, never 1 s without a step

    seq.controlword(1, int(S.SWITCH_ON_DISABLED), 0.0)
    seq.controlword(1, int(S.READY_TO_SWITCH_ON), 0.5)   # progress: clock restarts
    seq.controlword(1, int(S.SWITCH_ON_DISABLED), 0.9)   # back a step: no new time
    seq.controlword(1, int(S.READY_TO_SWITCH_ON), 1.4)   # not further than before
    assert faults == []
    seq.controlword(1, int(S.READY_TO_SWITCH_ON), 1.6)
    assert [(i, now) for i, _, now in faults] == [(1, 1.6)]
    assert "stuck in READY_TO_SWITCH_ON" in faults[0][1]
    seq.reset(1)  # not being enabled: a later attempt starts afresh
    faults.clear()
    seq.controlword(1, int(S.READY_TO_SWITCH_ON), 5.0)
    seq.controlword(1, int(S.READY_TO_SWITCH_ON), 5.9)
    assert faults == []


def test_a_frozen_process_is_not_a_stuck_drive():
    """A step's time is time the drive was asked: a freeze (nothing sent) adds at most
    ``timeout / min_cycles``, wherever in the step it falls; while cycles run, wall time."""
    S = cia402.State402
    faults: list[tuple[int, str, float]] = []
    seq = EnableSequence(1, timeout=1.0, fault=lambda i, cause, now: faults.append((i, cause, now)),
                         min_cycles=5)  # a freeze adds at most 0.2 s
    for k in range(6):  # 0.5 s asked, 0.1 s per cycle
        seq.controlword(0, int(S.SWITCH_ON_DISABLED), k / 10)
    seq.controlword(0, int(S.SWITCH_ON_DISABLED), 30.0)  # a 29.5 s freeze: + 0.2
    t = 30.0
    while not faults:
        t = round(t + 0.1, 6)
        seq.controlword(0, int(S.SWITCH_ON_DISABLED), t)
        assert t < 31.0, "a stuck drive must still be found"
    assert faults[0][2] in (30.3, 30.4)  # 0.5 + 0.2 + 0.3 (or 0.4: float sums) > 1.0
    assert "stuck in SWITCH_ON_DISABLED" in faults[0][1]


def test_a_raising_on_fault_hook_is_counted_and_the_estop_still_requested():
    import threading
    import time

    import can

    from rocoma_can import EventKind, ManagerState

    def hook(event):
        raise RuntimeError("reporting failed")

    bus = can.Bus(interface="virtual", channel="hook-errors", ignore_config=True)
    hw = CanopenHardware(bus, [DriveConfig(name="j1", node_id=1, increments_per_rev=4096,
                                           rated_torque_nm=1.0)], 100, 0.01, on_fault=hook)
    mgr = manager_for(hw)
    estops = []
    seen = threading.Event()
    mgr.subscribe(lambda ev: (estops.append(ev.cause), seen.set())
                  if ev.kind is EventKind.EMERGENCY_STOP else None)
    try:
        hw.supervisor.fault(0, "test", time.monotonic())
        for event in hw.read(time.monotonic()):  # as the loop's run_cycle does
            event.apply(mgr)
        assert hw.hook_errors == 1
        assert mgr.update() is ManagerState.FAILPROOF
        assert seen.wait(5.0) and "test" in estops[0]
    finally:
        mgr.shutdown()
        hw.close()
        bus.shutdown()
