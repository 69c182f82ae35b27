"""controllers/params.py: parameters of the controllers library: validated at construction (or, for
list lengths and joint names, in create) with errors naming the controller, the parameter and the
reason."""
from __future__ import annotations

import math
from importlib.metadata import entry_points

import numpy as np
import pytest
from fixtures.joint_plant import JointPlant, attach

from rocoma_can.controllers.damp import Damp
from rocoma_can.controllers.float import Float
from rocoma_can.controllers.hold import Hold
from rocoma_can.controllers.pd import JointPD
from rocoma_can.controllers.quick_stop import QuickStop
from rocoma_can.controllers.ros2_command import Ros2Command
from rocoma_can.controllers.torque_off import TorqueOff
from rocoma_can.controllers.tracking_monitor import TrackingMonitor
from rocoma_can.controllers.trajectory import Trajectory

ENTRY_POINTS = {
    "torque_off": TorqueOff, "damp": Damp, "hold": Hold, "quick_stop": QuickStop,
    "pd": JointPD, "trajectory": Trajectory, "float": Float,
    "worker_example": TrackingMonitor, "ros2_command": Ros2Command,
}


def test_every_controller_is_registered_as_an_entry_point():
    found = {e.name: e.load() for e in entry_points(group="rocoma_can.controllers")}
    for name, cls in ENTRY_POINTS.items():
        assert found.get(name) is cls, name


@pytest.mark.parametrize("cls, params, param, reason", [
    (JointPD, {"kp": -1.0}, "kp", "must be >= 0"),
    (JointPD, {"kd": [1.0, "x"]}, "kd", "expected a number"),
    (JointPD, {"kp": math.nan}, "kp", "must be finite"),
    (JointPD, {"kp": [1.0, -2.0]}, "kp", "element 1"),
    (JointPD, {"kp": []}, "kp", "empty"),
    (JointPD, {"kp": True}, "kp", "expected a number"),
    (JointPD, {"torque_limit": 0.0}, "torque_limit", "must be > 0"),
    (JointPD, {"velocity_limit": -1.0}, "velocity_limit", "must be > 0"),
    (JointPD, {"target": math.inf}, "target", "must be finite"),
    (JointPD, {"mode": "CSV"}, "mode", "must be one of CST, CSP"),
    (JointPD, {"mode": 3}, "mode", "must be one of"),
    (JointPD, {"joints": "joint0"}, "joints", "list of joint names"),
    (JointPD, {"joints": []}, "joints", "empty"),
    (JointPD, {"joints": ["a", "a"]}, "joints", "unique"),
    (JointPD, {"joints": ["a", 3]}, "joints", "non-empty strings"),
    (Trajectory, {"kind": "circle"}, "kind", "must be one of sine, min_jerk"),
    (Trajectory, {"kind": "min_jerk"}, "target", "required for kind 'min_jerk'"),
    (Trajectory, {"kind": "min_jerk", "target": 0.0, "duration": 0.0}, "duration", "> 0"),
    (Trajectory, {"target": 0.5}, "target", "only for kind 'min_jerk'"),
    (Trajectory, {"frequency": -1.0}, "frequency", ">= 0"),
    (Trajectory, {"amplitude": [0.1, -0.1]}, "amplitude", ">= 0"),
    (Trajectory, {"blend_time": -0.5}, "blend_time", ">= 0"),
    (Trajectory, {"mode": "CSV"}, "mode", "must be one of CSP, CST"),
    (Damp, {"damping": 0.0}, "damping", "must be > 0"),
    (Damp, {"still_velocity": 0.0}, "still_velocity", "must be > 0"),
    (Damp, {"still_time": -1.0}, "still_time", ">= 0"),
    (Damp, {"timeout": 0.0}, "timeout", "> 0"),
    (Hold, {"kd": -1.0}, "kd", ">= 0"),
    (Hold, {"mode": "torque"}, "mode", "must be one of CST, CSP"),
    (QuickStop, {"torque_off_after": -1.0}, "torque_off_after", "> 0"),
    (TrackingMonitor, {"monitor_frequency": 0.0}, "monitor_frequency", "> 0"),
    (TrackingMonitor, {"kp": -3.0}, "kp", ">= 0"),
    (Float, {"joints": 3}, "joints", "list of joint names"),
    # a ROS 2 topic name: a wildcard would follow every JointState it matches (the robot's
    # own joint_states among them)
    (Ros2Command, {"topic": "/*"}, "topic", "expected a topic name"),
    (Ros2Command, {"topic": "**"}, "topic", "expected a topic name"),
    (Ros2Command, {"topic": "/robot_$*"}, "topic", "expected a topic name"),
    (Ros2Command, {"topic": "/a//b"}, "topic", "expected a topic name"),
    (Ros2Command, {"topic": "/1st"}, "topic", "expected a topic name"),
    (Ros2Command, {"topic": "/a b"}, "topic", "expected a topic name"),
    (Ros2Command, {"topic": 5}, "topic", "expected a topic name"),
])
def test_bad_parameter_is_a_clear_value_error(cls, params, param, reason):
    with pytest.raises(ValueError) as info:
        cls("ctl", **params)
    message = str(info.value)
    assert f"{cls.__name__} 'ctl'" in message
    assert f"parameter {param!r}" in message
    assert reason in message


def test_unknown_parameter_is_a_type_error_naming_it():
    with pytest.raises(TypeError, match="gain"):
        JointPD("pd", gain=3.0)


@pytest.mark.parametrize("cls, params, param", [
    (JointPD, {"kp": [1.0, 2.0]}, "kp"),
    (JointPD, {"target": [0.1] * 4}, "target"),
    (Trajectory, {"amplitude": [0.1, 0.2, 0.3, 0.4]}, "amplitude"),
    (Damp, {"damping": [1.0, 1.0]}, "damping"),
    (Hold, {"torque_limit": [5.0] * 4}, "torque_limit"),
])
def test_per_joint_list_of_wrong_length_fails_create(cls, params, param):
    ctrl = attach(cls("ctl", **params), JointPlant(3))
    with pytest.raises(ValueError, match=rf"'ctl': parameter '{param}': has \d values but "
                                         r"the controller drives 3 joints"):
        ctrl.create(0.001)


def test_per_joint_list_matches_the_selected_joints_not_the_robot():
    plant = JointPlant(["hip", "knee", "shoulder", "elbow"])
    ctrl = attach(JointPD("legs", joints=["hip", "knee"], kp=[10.0, 20.0]), plant)
    assert ctrl.create(0.001)
    np.testing.assert_array_equal(ctrl.law.kp, [10.0, 20.0])


def test_unknown_joint_fails_create_naming_the_robots_joints():
    ctrl = attach(JointPD("pd", joints=["joint0", "wrist"]), JointPlant(2))
    with pytest.raises(ValueError, match=r"'joints': unknown joints \['wrist'\]; the robot "
                                         r"has \['joint0', 'joint1'\]"):
        ctrl.create(0.001)


def test_position_limits_must_be_ordered():
    ctrl = attach(JointPD("pd", position_min=[0.0, 1.0], position_max=[1.0, 0.5]),
                  JointPlant(2))
    with pytest.raises(ValueError, match=r"'position_min': exceeds position_max for joints "
                                         r"\['joint1'\]"):
        ctrl.create(0.001)


def test_create_without_state_says_to_add_the_controller_to_a_manager():
    with pytest.raises(RuntimeError, match="'float' has no state yet: add it to a "
                                           "ControllerManager first"):
        Float("float").create(0.001)
    with pytest.raises(RuntimeError, match="'torque_off' has no command yet"):
        TorqueOff().advance(0.001)


def test_mode_accepts_names_in_any_case_and_joint_modes():
    from rocoma_can.drivers.protocol.joints import JointMode
    assert JointPD("a", mode="csp").mode is JointMode.CSP
    assert Hold("b", mode=JointMode.CSP).mode is JointMode.CSP
