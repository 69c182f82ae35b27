"""Modes beyond CSP/CSV/CST (drivers/plan/modes.py): IP, PP and PV carry the same controller
commands as CSP and CSV. Units here; on the bus against simulated drives that emulate a
robot-arm joint's EDS (PP, VL, IP only) and a drive listing PV."""
from __future__ import annotations

import struct

import pytest
from fixtures.driver_rig import (
    INCREMENTS_PER_REV,
    RATED_TORQUE_NM,
    VIRTUAL,
    Rig,
    pd_settle,
    position_settle,
)
from fixtures.paths import ROOT, TESTS
from fixtures.rig_controllers import Sine

from rocoma_can import Controller, ManagerState, SwitchResult
from rocoma_can.drivers.plan.config import DriveConfig
from rocoma_can.drivers.plan.modes import (
    CW_CHANGE_IMMEDIATELY,
    CW_NEW_SETPOINT,
    SW_SETPOINT_ACK,
    DriveMode,
    SetPointHandshake,
    interpolation_period,
)
from rocoma_can.drivers.protocol import cia402
from rocoma_can.drivers.protocol.cia402 import State402
from rocoma_can.drivers.protocol.joints import JointMode

EDS = TESTS / "fixtures" / "eds"
ARM = str(EDS / "arm_ip_pp_vl.eds")


def pp_step_time(drive, distance: float) -> float:
    """PP moves at most at 0x6081 (profile velocity), then the drive's position loop
    settles (into PP's target window, 100 increments)."""
    speed = drive.od_value(cia402.PROFILE_VELOCITY) / drive.increments_per_rad
    return abs(distance) / speed + position_settle(VIRTUAL.joint)


# --- units -------------------------------------------------------------------------------------
def test_modes_by_name_one_per_kind_of_target():
    d = DriveConfig("j", 1, 4096, 1.0, modes=["ip", "pv", "cst"])
    assert d.modes == (DriveMode.IP, DriveMode.PV, DriveMode.CST)
    with pytest.raises(ValueError, match="modes csp and ip both carry CSP targets"):
        DriveConfig("j", 1, 4096, 1.0, modes=["csp", "ip"])
    with pytest.raises(ValueError, match="unknown mode 'vl'.*position: csp, ip or pp"):
        DriveConfig("j", 1, 4096, 1.0, modes=["vl"])


def test_set_point_handshake_raises_holds_and_drops_bit_4():
    hs = SetPointHandshake(1)
    both = CW_NEW_SETPOINT | CW_CHANGE_IMMEDIATELY
    assert hs.step(0, 100, 0) == (both, 100)                  # new target: bit 4 up
    assert hs.step(0, 200, 0) == (both, 100)                  # held until acknowledged
    assert hs.step(0, 200, SW_SETPOINT_ACK) == (CW_CHANGE_IMMEDIATELY, 100)  # bit 4 down
    assert hs.step(0, 200, SW_SETPOINT_ACK) == (CW_CHANGE_IMMEDIATELY, 100)  # ack still up
    assert hs.step(0, 200, 0) == (both, 200)                  # ack dropped: the next one
    assert hs.step(0, 200, SW_SETPOINT_ACK) == (CW_CHANGE_IMMEDIATELY, 200)
    assert hs.step(0, 200, 0) == (CW_CHANGE_IMMEDIATELY, 200)  # unchanged: no set-point
    hs.reset(0)
    assert hs.step(0, 200, 0) == (both, 200)                  # after a reset: new again


@pytest.mark.parametrize("dt, expected", [(0.004, (4, -3)), (0.001, (1, -3)),
                                          (0.0005, (5, -4)), (0.04, (40, -3)), (0.2, (200, -3)),
                                          (0.5, (50, -2))])
def test_interpolation_period_for_the_loop(dt, expected):
    assert interpolation_period(dt) == expected


def test_an_impossible_interpolation_period_is_refused():
    with pytest.raises(ValueError, match="cannot be an IP interpolation period"):
        interpolation_period(300.0)


# --- on the bus ----------------------------------------------------------------------------------
class Step(Controller):
    """Position targets: hold where the joint was, then ``offset`` further after ``after`` s."""

    def __init__(self, name: str, offset: float, after: float = 0.1) -> None:
        super().__init__(name)
        self.offset, self.after = offset, after
        self.t = 0.0
        self.start = None

    def initialize(self, dt: float) -> bool:
        self.t, self.start = 0.0, self.state.position.copy()
        return True

    def advance(self, dt: float) -> bool:
        self.t += dt
        self.command.mode.fill(JointMode.CSP)
        self.command.position[:] = self.start + (self.offset if self.t >= self.after else 0.0)
        return True


class Spin(Controller):
    """A constant velocity target."""

    def __init__(self, name: str, velocity: float) -> None:
        super().__init__(name)
        self.velocity = velocity

    def initialize(self, dt: float) -> bool:
        return True

    def advance(self, dt: float) -> bool:
        self.command.mode.fill(JointMode.CSV)
        self.command.velocity.fill(self.velocity)
        return True


@pytest.fixture
def mode_rig(sim_segment_factory, bus_factory, frame_recorder, virtual_channel):
    rigs: list[Rig] = []

    def make(eds: str, modes: tuple[str, ...]):
        segment = sim_segment_factory([1], eds_path=eds)
        recorder = frame_recorder(virtual_channel)
        rig = Rig.for_setup(bus_factory(), [1], VIRTUAL, modes=modes, drive={"eds": eds})
        rigs.append(rig)
        budget = VIRTUAL.bring_up_budget(1)
        assert rig.run_until(lambda: not rig.hw.starting, budget), rig.hw.drive_status()
        assert rig.hw.all_ready, rig.hw.drive_status()
        return rig, segment.drives[1], recorder

    yield make
    for rig in rigs:
        rig.close()


def _enable(rig: Rig, controller: Controller) -> None:
    rig.mgr.add_controller(controller)
    assert rig.switch(controller.name) == SwitchResult.SWITCHED
    assert rig.run_until(lambda: rig.hw.all_enabled, VIRTUAL.enable_budget()), \
        rig.hw.drive_status()


def test_ip_carries_csp_commands_to_the_interpolation_record(mode_rig):
    rig, drive, recorder = mode_rig(ARM, ("ip",))
    assert drive.od_value(cia402.INTERPOLATION_PERIOD, 1) == 5  # dt 5 ms = 5 x 10^-3 s
    assert drive.od_value(cia402.INTERPOLATION_PERIOD, 2) == -3
    (rpdo,) = rig.hw.layouts[0].rpdos
    assert [(e.index, e.subindex) for e in rpdo.entries] == [
        (cia402.CONTROLWORD, 0), (cia402.MODES_OF_OPERATION, 0), (cia402.INTERPOLATION_DATA, 1)]
    sine = Sine("sine", JointMode.CSP, amplitude=0.2, frequency=1.0)
    _enable(rig, sine)
    mark = recorder.mark()
    rig.run(0.5)
    assert drive.mode_display == DriveMode.IP and drive.statusword & SW_SETPOINT_ACK
    frames = recorder.wait_for_count(10, VIRTUAL.stall, rpdo.cob_id, since=mark)
    controlword, mode = struct.unpack_from("<Hb", frames[-1].data)
    assert controlword == 0x1F and mode == DriveMode.IP  # enable operation + interpolation
    # it follows the sine: half the amplitude within its first period
    assert rig.run_until(lambda: abs(drive.position_rad) > 0.1, VIRTUAL.motion_budget(1 / sine.f))
    rig.mgr.emergency_stop("test")
    rig.run(5 * rig.dt)
    assert rig.states[-1] == ManagerState.FAILPROOF
    assert rig.run_until(lambda: drive.state402 == State402.SWITCH_ON_DISABLED,
                         VIRTUAL.detect_budget())


def test_pp_reaches_a_step_through_the_set_point_handshake(mode_rig):
    rig, drive, recorder = mode_rig(ARM, ("pp",))
    step = Step("step", offset=0.3)
    _enable(rig, step)
    mark = recorder.mark()
    start = drive.position_rad
    assert rig.run_until(lambda: abs(drive.position_rad - start - 0.3) < 0.01
                         and drive.statusword & cia402.SW_TARGET_REACHED,
                         VIRTUAL.motion_budget(step.after + pp_step_time(drive, 0.3))), \
        drive.status_line()
    rpdo = rig.hw.layouts[0].rpdos[0].cob_id
    words = [struct.unpack_from("<H", f.data)[0] for f in recorder.frames(rpdo, since=mark)]
    rises = sum(1 for a, b in zip(words, words[1:]) if b & CW_NEW_SETPOINT
                and not a & CW_NEW_SETPOINT)
    assert rises >= 1 and all(w & 0x0F == 0x0F for w in words[-5:])
    assert rig.mgr.state == ManagerState.OK


def test_pv_carries_csv_commands(mode_rig, tmp_path):
    pv = tmp_path / "pv.eds"  # the generic drive, listing PV too
    pv.write_text((ROOT / "eds" / "cia402_drive.eds").read_text()
                  .replace("DefaultValue=0x000003A0", "DefaultValue=0x000003A4"))
    rig, drive, _ = mode_rig(str(pv), ("csp", "pv"))
    _enable(rig, Spin("spin", 0.5))
    rig.run(0.5)
    assert drive.mode_display == DriveMode.PV
    assert drive.velocity_rad_s == pytest.approx(0.5, abs=0.1)


def test_a_drive_config_of_only_ip_refuses_velocity_commands():
    from rocoma_can.drivers.plan.drive_plan import plan_drive
    plan = plan_drive(DriveConfig("j", 1, INCREMENTS_PER_REV, RATED_TORQUE_NM, eds=ARM,
                                  modes=["ip"], accept_unsupervised=False))
    assert plan.drive.modes == (DriveMode.IP,)
    assert any("no 0x6007" in n for n in plan.notes)


def test_pp_after_another_mode_starts_a_new_set_point_never_the_old_one(mode_rig, tmp_path):
    """PP -> CST (the joint moved elsewhere) -> PP: the first set-point after coming back is
    the new target, not the one latched before (the handshake restarts)."""
    from fixtures.driver_rig import HoldPD
    both = tmp_path / "pp_cst.eds"  # the generic drive, listing PP too
    both.write_text((ROOT / "eds" / "cia402_drive.eds").read_text()
                    .replace("DefaultValue=0x000003A0", "DefaultValue=0x000003A1"))
    rig, drive, recorder = mode_rig(str(both), ("pp", "cst"))
    per_rad = drive.increments_per_rad
    out = Step("out", offset=0.3)
    _enable(rig, out)
    assert rig.run_until(lambda: drive.statusword & cia402.SW_TARGET_REACHED
                         and drive.position_rad > 0.25,
                         VIRTUAL.motion_budget(out.after + pp_step_time(drive, 0.3))), \
        drive.status_line()
    home = HoldPD("home", target=0.0)  # CST back to 0
    rig.mgr.add_controller(home)
    assert rig.switch("home") == SwitchResult.SWITCHED
    settle = pd_settle(home.kp, home.kd, VIRTUAL.joint)
    assert rig.run_until(lambda: abs(drive.position_rad) < 0.05,
                         VIRTUAL.motion_budget(settle)), drive.status_line()
    rig.mgr.add_controller(Step("stay", offset=0.0))  # PP again, holding where it is
    mark = recorder.mark()
    assert rig.switch("stay") == SwitchResult.SWITCHED
    rig.run(0.3)
    rpdo = rig.hw.layouts[0].rpdos[0].cob_id
    set_points = [struct.unpack_from("<Hbi", f.data) for f in recorder.frames(rpdo, since=mark)
                  if struct.unpack_from("<Hb", f.data) == (
                      struct.unpack_from("<H", f.data)[0], DriveMode.PP)
                  and struct.unpack_from("<H", f.data)[0] & CW_NEW_SETPOINT]
    assert set_points, "no set-point after coming back to PP"
    first_target = set_points[0][2] / per_rad
    # Where the joint was when PP came back: near 0, but the CST hold may still be settling
    # (a loaded CI run saw 0.0504 rad against the 0.05 rad used to end the homing). Half way
    # between 0 and the 0.3 rad latched before tells the new set-point from the old one.
    assert abs(first_target) < 0.15, first_target
    # and PP holds the joint at that new set-point
    assert abs(drive.position_rad - first_target) < 0.05, (first_target, drive.status_line())
