"""controllers/pd.py, pd_law.py, float.py: JointPD and Float on the rigid-joint plant:
convergence, limits, subsets, live targets."""
from __future__ import annotations

import threading

import numpy as np
import pytest
from fixtures.joint_plant import JointPlant, attach

from rocoma_can.controllers.float import Float
from rocoma_can.controllers.pd import JointPD
from rocoma_can.drivers.protocol.joints import JointMode

DT = 0.001


def started(ctrl, plant):
    attach(ctrl, plant)
    assert ctrl.create(DT)
    assert ctrl.initialize(DT)
    return ctrl


@pytest.mark.parametrize("mode", ["CST", "CSP"])
def test_pd_converges_to_the_target_within_1e_4_rad(mode):
    plant = JointPlant(4)
    plant.set([0.3, -0.2, 0.0, 1.0])
    target = [0.5, 0.5, -1.0, 1.0]
    ctrl = started(JointPD("pd", kp=50.0, kd=2.0, target=target, mode=mode), plant)
    plant.run(ctrl.advance, 2000)  # 2 s: ~6 time constants of the CST loop
    np.testing.assert_allclose(plant.state.position, target, atol=1e-4)
    np.testing.assert_allclose(plant.state.velocity, 0.0, atol=1e-3)
    assert (plant.command.mode == JointMode[mode]).all()


def test_pd_without_target_holds_the_position_at_initialize():
    plant = JointPlant(3)
    plant.set([0.1, 0.2, 0.3])
    plant.disturbance[:] = 1.0  # pushes; the PD pulls back to the start pose
    ctrl = started(JointPD("pd", kp=200.0, kd=5.0), plant)
    plant.run(ctrl.advance, 2000)
    # Steady-state error of a PD under a constant disturbance: d / kp.
    np.testing.assert_allclose(plant.state.position, [0.1 + 1 / 200, 0.2 + 1 / 200,
                                                      0.3 + 1 / 200], atol=1e-4)


def test_feedforward_cancels_a_known_disturbance():
    plant = JointPlant(2)
    plant.disturbance[:] = [2.0, -1.0]
    ctrl = started(JointPD("pd", kp=50.0, kd=2.0, target=0.4, feedforward=[-2.0, 1.0]), plant)
    plant.run(ctrl.advance, 2000)
    np.testing.assert_allclose(plant.state.position, 0.4, atol=1e-4)


def test_torque_is_clipped_to_the_limit_per_joint():
    plant = JointPlant(2)
    ctrl = started(JointPD("pd", kp=500.0, kd=10.0, target=2.0, torque_limit=[1.0, 3.0]),
                   plant)
    peak = np.zeros(2)
    for _ in range(3000):
        ctrl.advance(DT)
        np.maximum(peak, np.abs(plant.command.torque), out=peak)
        plant.step()
    np.testing.assert_allclose(peak, [1.0, 3.0])  # saturated at first, never beyond
    np.testing.assert_allclose(plant.state.position, 2.0, atol=1e-3)


def test_reference_ramps_at_the_velocity_limit_and_reaches_the_clipped_target():
    plant = JointPlant(2)
    ctrl = started(JointPD("pd", target=[1.0, -5.0], velocity_limit=[2.0, 4.0],
                           position_min=-0.8, position_max=0.8, mode="CSP"), plant)
    np.testing.assert_array_equal(ctrl.target, [0.8, -0.8])
    previous = ctrl.reference.copy()
    for _ in range(100):
        ctrl.advance(DT)
        plant.step()
        step = np.abs(ctrl.reference - previous)
        assert (step <= np.array([2.0, 4.0]) * DT + 1e-12).all()
        previous[:] = ctrl.reference
    np.testing.assert_allclose(ctrl.reference, [0.2, -0.4])
    np.testing.assert_allclose(ctrl.reference_velocity, [2.0, -4.0])
    np.testing.assert_allclose(plant.command.velocity, [2.0, -4.0])  # CSP velocity offset
    plant.run(ctrl.advance, 400)
    np.testing.assert_allclose(plant.state.position, [0.8, -0.8])
    np.testing.assert_allclose(ctrl.reference_velocity, 0.0)


def test_set_target_from_another_thread_is_taken_at_the_next_advance():
    plant = JointPlant(3)
    ctrl = started(JointPD("pd", target=0.0, mode="CSP"), plant)
    plant.run(ctrl.advance, 5)
    setter = threading.Thread(target=ctrl.set_target, args=([0.1, 0.2, 0.3],))
    setter.start()
    setter.join(5.0)
    assert not setter.is_alive()
    np.testing.assert_array_equal(ctrl.target, 0.0)  # not before the cycle takes it
    ctrl.advance(DT)
    np.testing.assert_array_equal(plant.command.position, [0.1, 0.2, 0.3])
    ctrl.set_target(0.5)
    ctrl.set_target(0.6)  # the latest wins
    ctrl.advance(DT)
    np.testing.assert_array_equal(plant.command.position, 0.6)
    with pytest.raises(ValueError, match="'target': has 2 values"):
        ctrl.set_target([1.0, 2.0])


def test_a_joint_subset_writes_only_its_joints():
    plant = JointPlant(["a", "b", "c", "d"])
    plant.command.mode[:] = JointMode.QUICK_STOP
    plant.command.torque[:] = 7.0
    ctrl = started(JointPD("pd", joints=["d", "b"], kp=10.0, kd=0.0, target=[1.0, -1.0]),
                   plant)
    ctrl.advance(DT)
    c = plant.command
    assert list(c.mode) == [JointMode.QUICK_STOP, JointMode.CST, JointMode.QUICK_STOP,
                            JointMode.CST]
    np.testing.assert_allclose(c.torque, [7.0, -10.0, 7.0, 10.0])  # order of `joints` kept


def test_float_commands_zero_torque_and_the_joints_coast():
    plant = JointPlant(3)
    plant.set(0.0, [1.0, -1.0, 0.5])
    plant.command.torque[:] = 3.0
    ctrl = started(Float("float"), plant)
    plant.run(ctrl.advance, 100)
    assert (plant.command.mode == JointMode.CST).all()
    np.testing.assert_array_equal(plant.command.torque, 0.0)
    # Only friction acts: v(t) = v0 exp(-b t / I) (semi-implicit Euler, to 1e-3).
    np.testing.assert_allclose(plant.state.velocity,
                               np.array([1.0, -1.0, 0.5]) * np.exp(-0.1 * 0.1 / 0.05),
                               rtol=1e-3)
