"""controllers/damp.py, hold.py, quick_stop.py: emergency controllers on the rigid-joint plant: a
moving robot is brought to rest."""
from __future__ import annotations

import numpy as np
import pytest
from fixtures.joint_plant import JointPlant, attach

from rocoma_can.controllers.damp import Damp
from rocoma_can.controllers.hold import Hold
from rocoma_can.controllers.quick_stop import QuickStop
from rocoma_can.drivers.protocol.cia402 import State402
from rocoma_can.drivers.protocol.joints import JointMode

DT = 0.001
MOVING = [3.0, -2.0, 1.0, 0.0]


def engaged(ctrl, plant):
    """Created earlier, engaged by initialize_fast in the failure's cycle."""
    attach(ctrl, plant)
    assert ctrl.create(DT)
    assert ctrl.initialize_fast(DT)
    return ctrl


def test_damp_brakes_then_switches_torque_off_once_still():
    plant = JointPlant(4, friction=0.0)  # no friction: only the controller brakes
    plant.set(0.0, MOVING)
    ctrl = engaged(Damp("damp", damping=0.5, torque_limit=1.0, still_velocity=0.05,
                        still_time=0.1), plant)
    ctrl.advance(DT)
    assert (plant.command.mode == JointMode.CST).all()
    np.testing.assert_allclose(plant.command.torque, [-1.0, 1.0, -0.5, 0.0])  # clipped
    cycles = 1
    plant.step()
    while not ctrl.torque_is_off and cycles < 5000:
        ctrl.advance(DT)
        if not ctrl.torque_is_off:
            assert (plant.command.mode == JointMode.CST).all()
            assert np.all(plant.command.torque * plant.state.velocity <= 0.0)  # only brakes
        plant.step()
        cycles += 1
    assert ctrl.torque_is_off
    assert (plant.command.mode == JointMode.TORQUE_OFF).all()
    np.testing.assert_array_equal(plant.command.torque, 0.0)
    assert np.abs(plant.state.velocity).max() < 0.05
    # Exponential braking from 3 rad/s to 0.05 with tau = I / d = 0.1 s, after the clipped
    # phase: about 0.5 s; then the still time. Without braking it would never stop.
    assert 300 < cycles < 1500
    plant.run(ctrl.advance, 100)  # stays off
    assert (plant.command.mode == JointMode.TORQUE_OFF).all()
    assert (plant.state.cia402_state == State402.SWITCH_ON_DISABLED).all()


def test_damp_timeout_switches_torque_off_even_if_pushed():
    plant = JointPlant(2)
    plant.disturbance[:] = 2.0  # keeps the joints moving against the damping
    ctrl = engaged(Damp("damp", damping=1.0, timeout=0.2), plant)
    plant.run(ctrl.advance, 199)
    assert not ctrl.torque_is_off
    plant.run(ctrl.advance, 2)
    assert ctrl.torque_is_off
    assert (plant.command.mode == JointMode.TORQUE_OFF).all()


def test_damp_initialize_fast_rearms_after_a_torque_off():
    plant = JointPlant(2)
    ctrl = engaged(Damp("damp", still_time=0.0), plant)
    ctrl.advance(DT)
    assert ctrl.torque_is_off
    plant.set(0.0, 1.0)
    assert ctrl.initialize_fast(DT)
    ctrl.advance(DT)
    assert not ctrl.torque_is_off
    assert (plant.command.mode == JointMode.CST).all()
    np.testing.assert_allclose(plant.command.torque, -1.0)


@pytest.mark.parametrize("mode", ["CST", "CSP"])
def test_hold_stops_a_moving_joint_near_where_it_took_over(mode):
    plant = JointPlant(4)
    plant.set([0.5, -0.5, 0.0, 1.0], MOVING)
    ctrl = engaged(Hold("hold", kp=400.0, kd=10.0, mode=mode), plant)
    np.testing.assert_array_equal(ctrl.hold_position, [0.5, -0.5, 0.0, 1.0])
    plant.run(ctrl.advance, 1000)
    np.testing.assert_allclose(plant.state.velocity, 0.0, atol=1e-3)
    np.testing.assert_allclose(plant.state.position, [0.5, -0.5, 0.0, 1.0], atol=1e-3)
    plant.disturbance[:] = 4.0
    plant.run(ctrl.advance, 1000)
    # Stiff: a 4 Nm push moves it by 4 / kp = 10 mrad in CST (the CSP drive holds exactly).
    expected_sag = 4.0 / 400.0 if mode == "CST" else 0.0
    np.testing.assert_allclose(plant.state.position,
                               np.array([0.5, -0.5, 0.0, 1.0]) + expected_sag, atol=1e-4)


def test_hold_torque_limit_bounds_the_stop():
    plant = JointPlant(1)
    plant.set(0.0, 5.0)
    ctrl = engaged(Hold("hold", kp=1000.0, kd=50.0, torque_limit=2.0), plant)
    peak = 0.0
    for _ in range(3000):
        ctrl.advance(DT)
        peak = max(peak, abs(plant.command.torque[0]))
        plant.step()
    assert peak == pytest.approx(2.0)
    assert abs(plant.state.velocity[0]) < 1e-3
    assert abs(plant.state.position[0]) < 1e-3


def test_quick_stop_commands_the_drive_ramp_and_the_joints_stop():
    plant = JointPlant(4, quick_stop_deceleration=50.0)
    plant.set([0.1, 0.2, 0.3, 0.4], MOVING)
    ctrl = engaged(QuickStop("quick_stop"), plant)
    ctrl.advance(DT)
    assert (plant.command.mode == JointMode.QUICK_STOP).all()
    np.testing.assert_array_equal(plant.command.position, [0.1, 0.2, 0.3, 0.4])
    np.testing.assert_array_equal(plant.command.torque, 0.0)
    plant.run(ctrl.advance, 100)  # 3 rad/s at 50 rad/s² takes 60 ms
    np.testing.assert_array_equal(plant.state.velocity, 0.0)
    assert (plant.state.cia402_state == State402.QUICK_STOP_ACTIVE).all()
    assert (plant.command.mode == JointMode.QUICK_STOP).all()  # stays in quick stop


def test_quick_stop_then_torque_off_after_the_given_time():
    plant = JointPlant(2)
    ctrl = engaged(QuickStop("quick_stop", torque_off_after=0.05), plant)
    plant.run(ctrl.advance, 49)
    assert (plant.command.mode == JointMode.QUICK_STOP).all()
    plant.run(ctrl.advance, 2)
    assert (plant.command.mode == JointMode.TORQUE_OFF).all()
    assert ctrl.initialize_fast(DT)  # re-engaging starts with the quick stop again
    ctrl.advance(DT)
    assert (plant.command.mode == JointMode.QUICK_STOP).all()


@pytest.mark.parametrize("cls", [Damp, Hold, QuickStop])
def test_emergency_controllers_on_a_subset_leave_other_joints_alone(cls):
    plant = JointPlant(["a", "b", "c"])
    plant.set(0.0, [1.0, 1.0, 1.0])
    plant.command.mode[:] = JointMode.CSP
    plant.command.position[:] = 9.0
    ctrl = engaged(cls("e", joints=["b"]), plant)
    ctrl.advance(DT)
    assert plant.command.mode[0] == plant.command.mode[2] == JointMode.CSP
    assert plant.command.position[0] == plant.command.position[2] == 9.0
    assert plant.command.mode[1] != JointMode.CSP
