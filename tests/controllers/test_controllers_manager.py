"""controllers/ with rocoma_can/manager.py, plugins.py: the controllers library under the real
ControllerManager, loaded from the shipped example YAML, on the rigid-joint plant: switching
(bumpless), tuples, e-stops, workers."""
from __future__ import annotations

import threading
import time

import numpy as np
import pytest
import yaml
from fixtures.joint_plant import JointPlant
from fixtures.paths import ROOT

from rocoma_can import ControllerManager, ManagerState, SwitchResult
from rocoma_can.controllers import example_path
from rocoma_can.controllers.pd import JointPD
from rocoma_can.controllers.quick_stop import QuickStop
from rocoma_can.controllers.torque_off import TorqueOff
from rocoma_can.controllers.tracking_monitor import WORKER_NAME
from rocoma_can.drivers.protocol.joints import JointMode
from rocoma_can.plugins import add_to_manager

NAMES = ("left_hip", "left_knee", "right_hip", "right_knee", "shoulder", "elbow")
STAND = np.array([0.3, -0.6, 0.3, -0.6, 0.0, 0.5])
WAIT = 10.0


class Robot:
    """The plant and a manager; the test thread is the cycle thread. The plant's time is
    simulated, so wall-time supervision is off (timing=None): a loaded machine must not
    change the outcome."""

    def __init__(self, **manager_kwargs) -> None:
        self.plant = JointPlant(NAMES)
        manager_kwargs.setdefault("timing", None)
        self.mgr = ControllerManager(failproof=TorqueOff(), dt=self.plant.dt,
                                     state=self.plant.state, command=self.plant.command,
                                     **manager_kwargs)

    def cycle(self, n: int = 1) -> ManagerState:
        state = self.mgr.state
        for _ in range(n):
            state = self.mgr.update()
            self.plant.step()
        return state

    def switch(self, name: str, each_cycle=None) -> None:
        """Switch while the loop keeps running (as the seed's table 3)."""
        future = self.mgr.request_switch(name)
        deadline = time.monotonic() + WAIT
        while not future.done() and time.monotonic() < deadline:
            self.cycle()
            if each_cycle is not None:
                each_cycle()
        assert future.result(timeout=0) == SwitchResult.SWITCHED
        assert self.mgr.active_controller_name == name

    def controller(self, name: str):
        return self.mgr.adapters()[name].controller


@pytest.fixture
def robot():
    made = []

    def make(config: bool = True, **manager_kwargs) -> Robot:
        r = Robot(**manager_kwargs)
        made.append(r)
        if config:
            add_to_manager(r.mgr, yaml.safe_load(example_path().read_text()))
        return r

    yield make
    for r in made:
        assert r.mgr.shutdown()


def test_example_yaml_loads_every_controller(robot):
    r = robot()
    assert r.mgr.available_controllers() == ["float", "sit", "stand", "stand_and_wave",
                                             "stand_monitored"]
    assert r.mgr.switch_controller("damp") == SwitchResult.NOT_FOUND  # emergency layer
    assert r.cycle() == ManagerState.FAILPROOF
    assert (r.plant.command.mode == JointMode.TORQUE_OFF).all()


def test_stand_reaches_its_pose(robot):
    r = robot()
    r.switch("stand")
    assert r.cycle(3000) == ManagerState.OK
    np.testing.assert_allclose(r.plant.state.position, STAND, atol=1e-3)
    assert (r.plant.command.mode == JointMode.CST).all()


def test_tuple_legs_stand_while_the_arm_waves(robot):
    r = robot()
    r.switch("stand_and_wave")
    r.cycle(2000)  # the legs' ramp and the arm's blend are over
    arm = []
    for _ in range(2000):  # one period at 0.5 Hz
        r.cycle()
        arm.append(r.plant.state.position[4:].copy())
    arm = np.array(arm)
    np.testing.assert_allclose(r.plant.state.position[:4], STAND[:4], atol=1e-3)
    np.testing.assert_allclose(arm.max(axis=0) - arm.min(axis=0), [0.8, 0.4], atol=1e-3)
    np.testing.assert_allclose((arm.max(axis=0) + arm.min(axis=0)) / 2, [0.0, 0.5], atol=1e-3)
    mode = r.plant.command.mode
    assert list(mode) == [JointMode.CST] * 4 + [JointMode.CSP] * 2


def test_stand_to_sit_is_bumpless_while_the_loop_runs(robot):
    """The legs sag under a load, so the PD's reference differs from the measured pose; the
    trajectory starts from the reference and the torque command does not jump."""
    r = robot()
    r.plant.disturbance[:4] = -3.0
    r.switch("stand")
    r.cycle(3000)
    assert np.abs(r.plant.state.position[:4] - STAND[:4]).max() > 0.02  # sagging 3/100 rad
    torques = [r.plant.command.torque.copy()]
    r.switch("sit", each_cycle=lambda: torques.append(r.plant.command.torque.copy()))
    for _ in range(5):
        r.cycle()
        torques.append(r.plant.command.torque.copy())
    jumps = np.abs(np.diff(np.array(torques), axis=0)).max()
    assert jumps < 0.05  # from the measured pose instead, it would jump by 3 Nm
    r.cycle(4000)
    np.testing.assert_allclose(r.plant.state.position,
                               [1.2, -2.0, 1.2, -2.0, 0.0, 1.2], atol=0.035)


def test_estop_while_moving_damps_to_rest_then_torque_off(robot):
    r = robot()
    r.switch("sit")
    r.cycle(1000)  # mid-move
    assert np.abs(r.plant.state.velocity).max() > 0.5
    r.mgr.emergency_stop("test")
    assert r.cycle() == ManagerState.EMERGENCY
    assert r.mgr.active_controller_name == "damp"
    for cycles in range(1, 5001):  # noqa: B007 - read after the loop
        r.cycle()
        if (r.plant.command.mode == JointMode.TORQUE_OFF).all():
            break
    assert (r.plant.command.mode == JointMode.TORQUE_OFF).all()
    assert np.abs(r.plant.state.velocity).max() < 0.05
    assert cycles < 5000
    assert r.mgr.state == ManagerState.EMERGENCY


def test_estop_in_stand_holds_the_pose_of_the_failure_cycle(robot):
    r = robot()
    r.switch("stand")
    r.cycle(300)  # ramping at 1 rad/s
    r.mgr.emergency_stop("test")
    at_failure = r.plant.state.position.copy()
    assert r.cycle() == ManagerState.EMERGENCY
    hold = r.controller("hold")
    np.testing.assert_array_equal(hold.hold_position, at_failure)
    r.cycle(2000)
    np.testing.assert_allclose(r.plant.state.position, at_failure, atol=1e-3)
    r.mgr.emergency_stop("second")  # a second e-stop: failproof
    assert r.cycle() == ManagerState.FAILPROOF
    assert (r.plant.command.mode == JointMode.TORQUE_OFF).all()


def test_estop_at_speed_with_quick_stop_uses_the_drive_ramp(robot):
    r = robot(config=False)
    assert r.mgr.add_controller(JointPD("reach", target=2.0, velocity_limit=2.0, mode="CSP"),
                                emergency=QuickStop("quick_stop"))
    r.switch("reach")
    for _ in range(2000):
        if r.plant.state.position.max() > 1.0:  # a supervisor on the cycle thread e-stops
            r.mgr.emergency_stop("beyond 1 rad")
        if r.cycle() == ManagerState.EMERGENCY:
            break
    assert r.mgr.active_controller_name == "quick_stop"
    assert (r.plant.command.mode == JointMode.QUICK_STOP).all()
    r.cycle(100)
    np.testing.assert_array_equal(r.plant.state.velocity, 0.0)
    # Past 1 rad at 2 rad/s, then the 50 rad/s² ramp: at most 2² / (2 * 50) = 0.04 rad more.
    assert (r.plant.state.position > 1.0).all()
    assert (r.plant.state.position < 1.0 + 0.04 + 0.005).all()


def test_worker_example_runs_only_while_its_controller_is_active(robot):
    r = robot()
    thread_name = f"stand_monitored/{WORKER_NAME}"

    def worker_alive() -> bool:
        return any(t.name == thread_name for t in threading.enumerate())

    r.switch("stand_monitored")
    assert worker_alive()
    monitor = r.controller("stand_monitored")
    deadline = time.monotonic() + WAIT
    while (monitor.snapshot() is None or monitor.snapshot().samples < 2) \
            and time.monotonic() < deadline:
        r.cycle(10)
        time.sleep(0.005)
    assert monitor.snapshot().samples >= 2
    r.switch("stand")  # pre_stop of the monitor cancels its worker (stopper thread)
    deadline = time.monotonic() + WAIT
    while worker_alive() and time.monotonic() < deadline:
        r.cycle()
        time.sleep(0.001)
    assert not worker_alive()


def test_docs_yaml_snippet_builds_and_runs(robot):
    page = (ROOT / "docs" / "controllers.md").read_text()
    section = page.split("<!-- section: controllers library -->", 1)[1]
    snippet = section.split("```yaml\n", 1)[1].split("```", 1)[0]
    r = robot(config=False)
    loaded = add_to_manager(r.mgr, yaml.safe_load(snippet))
    assert [item.controller.name for item in loaded] == [
        "stand", "wave", "sit", "float", "stand_monitored", "stand_and_wave"]
    for name in ("stand", "wave", "stand_and_wave", "stand_monitored"):
        r.switch(name)
        assert r.cycle(100) == ManagerState.OK
