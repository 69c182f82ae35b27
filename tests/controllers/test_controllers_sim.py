"""controllers/ over drivers/hardware.py: the controllers library over a CAN bus: ControllerManager
+ CanopenHardware against six simulated CiA 402 drives on python-can's virtual bus (200 Hz),
controllers loaded from YAML.

Assertions are on joint states decoded from the TPDOs, on the drives' CiA 402 states and on
manager states; waits are bounded. The drives integrate wall time between SYNCs, so
tolerances leave room for a loaded machine.
"""
from __future__ import annotations

import math

import numpy as np
import pytest
import yaml
from fixtures.budgets import STALL
from fixtures.driver_rig import VIRTUAL, Can, Rig, outlasting, pd_settle, position_settle

from rocoma_can import ManagerState, SwitchResult, TimingSupervision
from rocoma_can.drivers.protocol.cia402 import QUICK_STOP_DECELERATION, State402
from rocoma_can.drivers.protocol.joints import JointMode
from rocoma_can.drivers.sim.dynamics import JointParams
from rocoma_can.plugins import add_to_manager

NODES = tuple(range(1, 7))
DT = 0.005
# Gains for the simulated joints (0.01 kg m², 1 Nm rated torque): ω = 20 rad/s, ζ = 0.75.
CONFIG = yaml.safe_load("""
emergency_controllers:
  - {name: damp, plugin: damp, params: {damping: 0.1, torque_limit: 0.8, still_velocity: 0.05,
                                        still_time: 0.1}}
  - {name: hold, plugin: hold, params: {mode: CSP}}
  - {name: quick_stop, plugin: quick_stop}
controllers:
  - name: pd
    plugin: pd
    params: {kp: 4.0, kd: 0.3, torque_limit: 0.8, velocity_limit: 1.0, target: 0.2}
    emergency: damp
  - name: move
    plugin: trajectory
    params: {kind: min_jerk, target: [-0.2, -0.1, 0.0, 0.1, 0.2, 0.3], duration: 1.0}
    emergency: hold
  - name: wave
    plugin: trajectory
    params: {kind: sine, amplitude: 0.5, frequency: 1.0, blend_time: 0.5}
    emergency: damp
  - name: wave_fast
    plugin: trajectory
    params: {kind: sine, amplitude: 0.5, frequency: 1.0, blend_time: 0.5}
    emergency: quick_stop
  - name: legs_and_arm
    tuple:
      - {name: legs, plugin: pd, params: {joints: [j1, j2, j3, j4], kp: 4.0, kd: 0.3,
                                          torque_limit: 0.8, target: -0.3}}
      - {name: arm, plugin: trajectory, params: {joints: [j5, j6], kind: sine,
                                                 amplitude: 0.3, frequency: 0.5}}
    emergency: damp
""")


def _params(name: str) -> dict:
    return next(c["params"] for section in ("controllers", "emergency_controllers")
                for c in CONFIG[section] if c["name"] == name)


PD, MOVE, WAVE, DAMP = _params("pd"), _params("move"), _params("wave"), _params("damp")
JOINT = JointParams()  # the simulator's joints
# Motion times the waits are budgets of (SETUP.motion_budget): the PD ramps its reference to
# the target at its velocity limit, then settles; the drive's own position loop settles a
# CSP hold or a trajectory's end; the tuple's legs are the same PD
SETTLE_TIME = max(PD["target"] / PD["velocity_limit"] + pd_settle(PD["kp"], PD["kd"], JOINT),
                  position_settle(JOINT))
# These tests are about the controllers: supervision of the simulated drives outlasts the
# host's stall as in every setup (fixtures/driver_rig.py), with 100 ms heartbeats; the waits
# are this setup's budgets.
SETUP = Can("virtual", NODES, DT, (PD["kp"], PD["kd"], 0.01, SETTLE_TIME), heartbeat_ms=100,
            drive_heartbeat_ms=100, timeouts=VIRTUAL.timeouts, joints=JOINT,
            **outlasting(STALL, DT, heartbeat_ms=100, drive_heartbeat_ms=100))
SETTLE = SETUP.motion_budget(SETTLE_TIME)
WAVE_SPEED = WAVE["amplitude"] * 2 * math.pi * WAVE["frequency"]  # its peak, rad/s


@pytest.fixture
def rig(virtual_channel, sim_segment_factory, bus_factory):
    segment = sim_segment_factory(NODES, channel=virtual_channel)
    # the manager's wall-time supervision ~1 s too (a preempted initialize_fast over its
    # 2.5 ms budget sent an e-stop straight to FAILPROOF once in CI)
    second = 1.0 / DT
    r = Rig.for_setup(bus_factory(virtual_channel), NODES, SETUP,
                      timing=TimingSupervision(advance=second, initialize_fast=second,
                                               hang=second))
    r.segment = segment
    r.events = []  # every manager event, so a failing assertion can show the causes
    r.mgr.subscribe(r.events.append)
    try:
        add_to_manager(r.mgr, CONFIG)
        assert r.run_until(lambda: not r.hw.starting, SETUP.bring_up_budget(len(NODES))), \
            r.hw.drive_status()
        assert r.hw.all_ready, r.hw.drive_status()
        yield r
    finally:
        r.close()
        for event in r.events:  # shown by pytest when the test failed
            print(f"{event.time:.3f} {event.kind.name} {event.state.name} "
                  f"{event.active_controller} {event.cause}")


def switch_and_enable(rig: Rig, name: str) -> None:
    assert rig.switch(name) == SwitchResult.SWITCHED
    assert rig.run_until(lambda: rig.hw.all_enabled, SETUP.enable_budget()), \
        rig.hw.drive_status()


def near(values, expected, tolerance: float) -> bool:
    return bool(np.abs(np.asarray(values) - expected).max() < tolerance)


def drive_states(rig: Rig) -> set[State402]:
    return {d.state402 for d in rig.segment.drives.values()}


def controller(rig: Rig, name: str):
    return rig.mgr.adapters()[name].controller


def test_pd_reaches_its_target_then_a_min_jerk_move_takes_over_from_its_reference(rig):
    switch_and_enable(rig, "pd")
    assert rig.run_until(lambda: near(rig.hw.state.position, 0.2, 0.01), SETTLE), \
        rig.hw.state.position
    assert set(rig.hw.command.mode) == {JointMode.CST}

    pd = controller(rig, "pd")
    switch_and_enable(rig, "move")
    move = controller(rig, "move")
    np.testing.assert_array_equal(move.start, pd.reference)  # not the measured pose
    end = [-0.2, -0.1, 0.0, 0.1, 0.2, 0.3]
    assert rig.run_until(lambda: move.finished and near(rig.hw.state.position, end, 0.01),
                         SETUP.motion_budget(MOVE["duration"] + SETTLE_TIME)), rig.hw.state.position
    assert rig.mgr.state == ManagerState.OK
    assert drive_states(rig) == {State402.OPERATION_ENABLED}
    assert all(d.mode_display == JointMode.CSP for d in rig.segment.drives.values())


def test_tuple_drives_cst_legs_and_csp_arm_in_the_same_cycle(rig):
    switch_and_enable(rig, "legs_and_arm")
    arm = controller(rig, "legs_and_arm").controllers[1]
    q = rig.hw.state.position
    rig.run(1.0)  # past the arm's blend into the sine
    # The drive's CSP loop lags a moving reference by a few cycles: 0.08 rad at most here.
    assert rig.run_until(lambda: near(q[:4], -0.3, 0.02) and near(q[4:], arm.reference, 0.08),
                         SETTLE), (q, arm.reference)
    modes = {n: d.mode_display for n, d in rig.segment.drives.items()}
    assert modes == {1: JointMode.CST, 2: JointMode.CST, 3: JointMode.CST, 4: JointMode.CST,
                     5: JointMode.CSP, 6: JointMode.CSP}


def wave_at_speed(rig: Rig, name: str) -> None:
    switch_and_enable(rig, name)
    # the wave blends in, then every joint passes its peak speed within half a period
    assert WAVE_SPEED > 1.0
    assert rig.run_until(lambda: np.abs(rig.hw.state.velocity).min() > 1.0,
                         SETUP.motion_budget(WAVE["blend_time"] + 0.5 / WAVE["frequency"])), \
        rig.hw.state.velocity


def test_estop_at_speed_damps_the_joints_then_switches_torque_off(rig):
    wave_at_speed(rig, "wave")
    rig.mgr.emergency_stop("test")
    assert rig.cycle() == ManagerState.EMERGENCY
    damp = controller(rig, "damp")
    assert not damp.torque_is_off
    assert set(rig.hw.command.mode) == {JointMode.CST}
    # damping + viscous friction: the speed decays at (damping + b) / J per second from at
    # most the wave's peak to the still velocity, which it then keeps for the still time
    decay = (DAMP["damping"] + JOINT.viscous) / JOINT.inertia
    damped = math.log(WAVE_SPEED / DAMP["still_velocity"]) / decay + DAMP["still_time"]
    assert rig.run_until(lambda: damp.torque_is_off, SETUP.motion_budget(damped)), \
        rig.hw.state.velocity
    assert np.abs(rig.hw.state.velocity).max() < 0.1
    assert rig.run_until(lambda: drive_states(rig) == {State402.SWITCH_ON_DISABLED},
                         SETUP.cycles_budget(10))
    assert rig.mgr.state == ManagerState.EMERGENCY  # a commanded torque-off is no fault


def test_estop_at_speed_with_quick_stop_uses_the_drives_ramp(rig):
    wave_at_speed(rig, "wave_fast")
    rig.mgr.emergency_stop("test")
    assert rig.cycle() == ManagerState.EMERGENCY
    assert set(rig.hw.command.mode) == {JointMode.QUICK_STOP}
    drive = rig.segment.drives[NODES[0]]  # the quick-stop ramp (0x6085) from the peak
    decel = drive.od_value(QUICK_STOP_DECELERATION) / drive.increments_per_rad
    ramp = WAVE_SPEED / decel + position_settle(JOINT)  # then the velocity loop's tail
    assert rig.run_until(lambda: np.abs([d.velocity_rad_s for d in rig.segment.drives.values()])
                         .max() < 1e-3, SETUP.motion_budget(ramp))
    assert drive_states(rig) <= {State402.QUICK_STOP_ACTIVE, State402.SWITCH_ON_DISABLED}
    assert rig.mgr.state == ManagerState.EMERGENCY


def test_estop_during_a_move_holds_the_pose_of_the_failure_cycle(rig):
    switch_and_enable(rig, "move")
    rig.run(0.5)  # mid-move, at about full speed
    rig.mgr.emergency_stop("test")
    assert rig.cycle() == ManagerState.EMERGENCY
    hold = controller(rig, "hold")
    held = hold.hold_position.copy()
    assert rig.run_until(lambda: near(rig.hw.state.position, held, 0.01)
                         and near(rig.hw.state.velocity, 0.0, 0.05), SETTLE)
    rig.run(0.5)
    assert near(rig.hw.state.position, held, 0.02)
    assert drive_states(rig) == {State402.OPERATION_ENABLED}
