"""controllers/trajectory.py, pose_swap.py: Trajectory on the rigid-joint plant: sine and
minimum-jerk tracking, bumpless hand-overs."""
from __future__ import annotations

import math

import numpy as np
import pytest
from fixtures.joint_plant import JointPlant, attach

from rocoma_can.controllers.hold import Hold
from rocoma_can.controllers.pd import JointPD
from rocoma_can.controllers.pose_swap import PoseSwapState
from rocoma_can.controllers.trajectory import Trajectory, min_jerk
from rocoma_can.tuples import ControllerTuple, TupleSwapState

DT = 0.001


def created(ctrl, plant):
    attach(ctrl, plant)
    assert ctrl.create(DT)
    return ctrl


def test_min_jerk_profile_endpoints_and_symmetry():
    assert min_jerk(0.0) == (0.0, 0.0) and min_jerk(1.0) == (1.0, 0.0)
    assert min_jerk(-1.0) == (0.0, 0.0) and min_jerk(2.0) == (1.0, 0.0)
    assert min_jerk(0.5)[0] == pytest.approx(0.5)
    assert min_jerk(0.5)[1] == pytest.approx(1.875)  # peak speed 15/8 of the mean
    for tau in np.linspace(0.0, 1.0, 11):
        s, ds = min_jerk(tau)
        assert s + min_jerk(1.0 - tau)[0] == pytest.approx(1.0)
        h = 1e-6
        if 0 < tau < 1:
            assert ds == pytest.approx((min_jerk(tau + h)[0] - min_jerk(tau - h)[0]) / (2 * h),
                                       rel=1e-6)


def test_min_jerk_move_arrives_on_time_at_rest_in_csp():
    plant = JointPlant(3)
    plant.set([0.0, 1.0, -0.5])
    ctrl = created(Trajectory("move", kind="min_jerk", target=[1.0, 1.0, 0.5], duration=0.5),
                   plant)
    assert ctrl.initialize(DT)
    peak = np.zeros(3)
    for _i in range(500):
        assert not ctrl.finished
        ctrl.advance(DT)
        np.maximum(peak, np.abs(ctrl.reference_velocity), out=peak)
        plant.step()
    assert ctrl.finished
    np.testing.assert_allclose(plant.state.position, [1.0, 1.0, 0.5], atol=1e-12)
    np.testing.assert_allclose(ctrl.reference_velocity, 0.0, atol=1e-12)
    # Peak speed of a minimum-jerk move: 1.875 * distance / duration.
    np.testing.assert_allclose(peak, 1.875 * np.array([1.0, 0.0, 1.0]) / 0.5, rtol=1e-4)
    plant.run(ctrl.advance, 100)  # stays there
    np.testing.assert_allclose(plant.state.position, [1.0, 1.0, 0.5], atol=1e-12)


def test_min_jerk_in_cst_tracks_within_5_mrad():
    plant = JointPlant(2)
    ctrl = created(Trajectory("move", kind="min_jerk", target=[0.8, -0.4], duration=1.0,
                              mode="CST", kp=400.0, kd=8.0), plant)
    assert ctrl.initialize(DT)
    worst = 0.0
    for _ in range(1500):
        ctrl.advance(DT)
        plant.step()
        worst = max(worst, float(np.abs(ctrl.reference - plant.state.position).max()))
    assert worst < 5e-3
    np.testing.assert_allclose(plant.state.position, [0.8, -0.4], atol=1e-4)


@pytest.mark.parametrize("mode, tolerance", [("CSP", 1e-12), ("CST", 0.02)])
def test_sine_is_tracked_after_the_blend(mode, tolerance):
    plant = JointPlant(3)
    plant.set([0.2, 0.0, -0.1])
    amplitude = np.array([0.3, 0.1, 0.0])
    frequency = np.array([1.0, 2.0, 0.5])
    offset = np.array([0.0, 0.5, -0.1])
    phase = np.array([0.0, math.pi / 2, 0.0])
    ctrl = created(Trajectory("sine", amplitude=list(amplitude), frequency=list(frequency),
                              offset=list(offset), phase=list(phase), blend_time=0.5,
                              mode=mode, kp=400.0, kd=8.0), plant)
    assert ctrl.initialize(DT)
    np.testing.assert_allclose(ctrl.reference, [0.2, 0.0, -0.1])  # starts where it is
    worst = 0.0
    for i in range(1, 3001):
        ctrl.advance(DT)
        plant.step()
        if i * DT > 0.5:
            t = i * DT
            expected = offset + amplitude * np.sin(2 * math.pi * frequency * t + phase)
            np.testing.assert_allclose(ctrl.reference, expected, atol=1e-12)
            worst = max(worst, float(np.abs(plant.state.position - expected).max()))
    assert worst < tolerance


def test_sine_reference_starts_at_rest_and_is_smooth_through_the_blend():
    plant = JointPlant(1)
    ctrl = created(Trajectory("sine", amplitude=0.5, frequency=2.0, offset=0.3,
                              blend_time=0.2), plant)
    assert ctrl.initialize(DT)
    assert ctrl.reference_velocity[0] == 0.0
    refs, vels = [], []
    for _ in range(400):
        ctrl.advance(DT)
        refs.append(ctrl.reference[0])
        vels.append(ctrl.reference_velocity[0])
    refs, vels = np.array(refs), np.array(vels)
    # The reported velocity is the derivative of the reference, through the blend too.
    np.testing.assert_allclose(np.diff(refs) / DT, (vels[1:] + vels[:-1]) / 2, atol=0.02)
    # Bounded acceleration (< 500 rad/s²): no velocity step (starting on the sine would
    # be a step of amplitude * omega = 6.3 rad/s).
    assert np.abs(np.diff(vels)).max() < 0.5


def pd_at_rest(plant, **params):
    pd = created(JointPD("pd", **params), plant)
    assert pd.initialize(DT)
    plant.run(pd.advance, 1500)
    return pd


@pytest.mark.parametrize("mode", ["CST", "CSP"])
def test_pd_to_trajectory_hand_over_is_bumpless(mode):
    """The trajectory starts from the PD's reference, not from the measured position (which
    sags under the load here), so neither the reference nor the command jumps."""
    plant = JointPlant(3)
    plant.disturbance[:] = [-2.0, 1.0, 0.0]
    pd = pd_at_rest(plant, kp=100.0, kd=4.0, target=[0.4, -0.3, 0.2], mode=mode)
    ctrl = created(Trajectory("move", kind="min_jerk", target=0.0, duration=1.0, mode=mode,
                              kp=100.0, kd=4.0), plant)
    swap_state = pd.get_swap_state()
    assert isinstance(swap_state, PoseSwapState)
    np.testing.assert_allclose(swap_state.reference, [0.4, -0.3, 0.2])
    if mode == "CST":
        assert np.abs(swap_state.measured - swap_state.reference).max() > 0.005  # sagging
    pd.advance(DT)
    before = plant.command.torque.copy(), plant.command.position.copy()
    assert ctrl.swap(DT, swap_state)
    np.testing.assert_allclose(ctrl.reference, pd.reference)  # continuous reference
    ctrl.advance(DT)
    np.testing.assert_allclose(plant.command.torque, before[0], atol=1e-3)
    np.testing.assert_allclose(plant.command.position, before[1], atol=1e-5)


def test_trajectory_to_pd_hand_over_continues_from_the_reference():
    plant = JointPlant(2)
    ctrl = created(Trajectory("sine", amplitude=0.3, frequency=1.0, blend_time=0.0), plant)
    assert ctrl.initialize(DT)
    plant.run(ctrl.advance, 200)
    pd = created(JointPD("pd", velocity_limit=0.5, mode="CSP"), plant)  # no target: hold
    assert pd.swap(DT, ctrl.get_swap_state())
    np.testing.assert_allclose(pd.reference, ctrl.reference)
    np.testing.assert_allclose(pd.target, ctrl.reference)
    pd.advance(DT)
    np.testing.assert_allclose(plant.command.position, ctrl.reference)


def test_swap_without_a_pose_state_starts_from_the_measured_position():
    plant = JointPlant(2)
    plant.set([0.1, 0.2])
    ctrl = created(Trajectory("move", kind="min_jerk", target=1.0), plant)
    assert ctrl.swap(DT, None)
    np.testing.assert_allclose(ctrl.reference, [0.1, 0.2])


def test_hold_hands_its_held_pose_over_to_a_pd():
    plant = JointPlant(2)
    plant.set([0.3, -0.3])
    hold = created(Hold("hold"), plant)
    assert hold.initialize_fast(DT)
    plant.disturbance[:] = 5.0
    plant.run(hold.advance, 500)
    pd = created(JointPD("pd"), plant)
    assert pd.swap(DT, hold.get_swap_state())
    np.testing.assert_allclose(pd.target, [0.3, -0.3])


def test_tuple_to_tuple_and_single_to_tuple_hand_overs_match_joints_by_name():
    plant = JointPlant(["hip", "knee", "shoulder", "elbow"])
    plant.set([0.1, 0.2, 0.3, 0.4])
    legs = JointPD("legs", joints=["hip", "knee"], target=[0.5, 0.6], mode="CSP")
    arm = JointPD("arm", joints=["elbow", "shoulder"], target=[0.8, 0.7], mode="CSP")
    first = ControllerTuple("first", [legs, arm])
    created(first, plant)
    assert first.initialize(DT)
    plant.run(first.advance, 3)
    state = first.get_swap_state()
    assert isinstance(state, TupleSwapState)

    # Same joints, different split and order: matched by name through the merged state.
    whole = created(Trajectory("whole", joints=["elbow", "knee", "hip", "shoulder"],
                               kind="min_jerk", target=0.0), plant)
    assert whole.swap(DT, state)
    np.testing.assert_allclose(whole.reference, [0.8, 0.6, 0.5, 0.7])

    # A single controller's state handed to each member of a tuple.
    arm_move = Trajectory("arm_move", joints=["shoulder", "elbow"], kind="min_jerk",
                          target=0.0)
    leg_pd = JointPD("leg_pd", joints=["hip", "knee"], mode="CSP")
    second = created(ControllerTuple("second", [leg_pd, arm_move]), plant)
    assert second.swap(DT, whole.get_swap_state())
    np.testing.assert_allclose(arm_move.reference, [0.7, 0.8])
    np.testing.assert_allclose(leg_pd.reference, [0.5, 0.6])
