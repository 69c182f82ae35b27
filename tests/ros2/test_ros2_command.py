"""controllers/ros2_command.py, rocoma_can/inputs.py: a controller following a ROS 2 topic, fed by
the node: it follows, falls to its emergency controller when the topic goes stale or a command is
bad, and the configuration docs/ros2.md gives holds a robot still."""
from __future__ import annotations

import threading
import time

import numpy as np
import pytest
from fixtures.paths import ROOT
from fixtures.ros2_rig import (
    COMMANDED,
    RATE,
    command,
    decode,
    documented_hardware_interface,
    estop_cause,
    following,
    key,
    node,
    publisher,
    wait_for,
)
from fixtures.running import DEMO_WAIT, runtime_running

from rocoma_can import ManagerState
from rocoma_can.cli.demo.config import demo_config
from rocoma_can.ros2.interfaces import JOINT_STATE


def test_ros2_command_follows_the_topic_and_falls_to_its_emergency_when_it_goes_stale(
        virtual_channel, sim_segment_factory, router, ros2_sdk):
    """Commands published by a third-party client reach the drives' command; when they
    stop for longer than the timeout (COMMANDED's), the controller fails and its emergency
    controller takes over, as from any failing controller."""
    sim_segment_factory(2)
    with node(virtual_channel, router[2]) as rt:
        with following(rt, ros2_sdk) as message:
            here = list(message["position"])
            target = [here[0] + 0.05, here[1] - 0.05]
            message["position"] = np.array(target)
            wait_for(lambda: list(rt.hardware.command.position) == target,
                     "the command reaching the drives")
            assert rt.manager.state is ManagerState.OK
            assert rt.ros2.info()["commands"] > 0
        wait_for(lambda: rt.manager.state is ManagerState.EMERGENCY, "the stale command's fall")
        assert rt.manager.active_controller_name == "damp"
        assert "no command on /robot_joint_command" in estop_cause(rt)


@pytest.mark.parametrize("names,position,why", [
    (["joint1", "joint2"], [float("nan"), 0.0], "outside -3..3"),
    (["joint1", "elbow"], [0.0, 0.0], "names joint 'elbow'"),
    (["joint1", "joint2"], [0.0, 5.0], "position 5.0 for joint2 outside -3..3"),
])
def test_a_nan_unknown_or_out_of_limits_command_falls_to_the_emergency_controller(
        virtual_channel, sim_segment_factory, router, ros2_sdk, names, position, why):
    sim_segment_factory(2)
    with node(virtual_channel, router[2]) as rt:
        with following(rt, ros2_sdk) as message:
            message.update(name=names, position=np.array(position))
            wait_for(lambda: rt.manager.state is ManagerState.EMERGENCY, f"the fall ({why})")
        assert rt.manager.active_controller_name == "damp"
        cause = estop_cause(rt)
        assert why in cause, cause


def test_the_configuration_docs_ros2_md_gives_is_taken(virtual_channel):
    """docs/ros2.md's ``ros2:`` section and its ``ros2_command`` controller, copied into a
    config, are taken as they read: docs that cannot rot silently."""
    import re

    import yaml

    from rocoma_can.runtime.config import validate
    text = (ROOT / "docs" / "ros2.md").read_text()
    blocks = [yaml.safe_load(b) for b in re.findall(r"```yaml\n(.*?)```", text, re.S)]
    cfg = demo_config(virtual_channel, drives=2, rate=RATE)
    for block in blocks:
        cfg["controllers"] += block.pop("controllers", [])
        cfg.update(block)
    config = validate(cfg)
    assert config.ros2 is not None and config.ros2.namespace == "/robot1"
    # the controller follows the topic the documented hardware interface publishes on
    from rocoma_can.controllers.ros2_command import Ros2Command
    follow = next(c for c in cfg["controllers"] if c["plugin"] == "ros2_command")
    assert Ros2Command(follow["name"], **follow["params"]).command_topic \
        == documented_hardware_interface()["joint_commands_topic"]


def test_the_documented_hardware_interface_keeps_a_robot_holding_still_followed(
        virtual_channel, sim_segment_factory, router, peer, ros2_sdk):
    """docs/ros2.md's URDF snippet, run as joint_state_topic_hardware_interface runs its
    write(): it publishes the command only while the states it reads differ from it by more
    than ``trigger_joint_command_threshold`` (summed over the joints; 1e-5 unless set). A
    robot holding its commanded pose (a trajectory's end, JointTrajectoryController's hold)
    must stay followed, not fall to its emergency controller for a command gone stale."""
    params = documented_hardware_interface()
    threshold = float(params.get("trigger_joint_command_threshold", "1e-5"))
    commands = params["joint_commands_topic"]
    assert commands == COMMANDED["params"].get("topic", "/robot_joint_command")
    sim_segment_factory(2)
    with node(virtual_channel, router[2]) as rt:
        z = peer()
        states: list = []
        z.declare_subscriber(key(params["joint_states_topic"].strip("/"), JOINT_STATE),
                             lambda s: states.append(decode(JOINT_STATE, s.payload.to_bytes())))
        pub = publisher(ros2_sdk)
        wait_for(lambda: rt.manager.switch_blocked() is None and states, "the drives up")
        held = [float(v) for v in states[-1].position]  # the pose the controller holds
        message = command(ros2_sdk, ["joint1", "joint2"], held)
        stop, sent = threading.Event(), [0, 0]

        def write() -> None:  # the interface's write(), every period of its update rate
            while not stop.wait(0.02):
                state = states[-1].position
                if sum(abs(a - b) for a, b in zip(state, held)) <= threshold:
                    sent[1] += 1
                    continue
                pub.publish(**message)
                sent[0] += 1
        thread = threading.Thread(target=write, name="test-hardware-interface")
        thread.start()
        try:
            assert rt.manager.switch_controller("follow", timeout=DEMO_WAIT).name == "SWITCHED"
            timeout = COMMANDED["params"]["timeout"]
            time.sleep(2 * timeout)
            assert (rt.manager.state, rt.manager.active_controller_name) == (
                ManagerState.OK, "follow"), (rt.status()["estop_cause"], sent)
        finally:
            stop.set()
            thread.join(DEMO_WAIT)


class CountedNames(tuple):
    """A command's joint names that count, per thread, the names read from them."""
    reads: dict[int, int]

    def __iter__(self):
        for name in tuple.__iter__(self):
            self.reads[threading.get_ident()] = self.reads.get(threading.get_ident(), 0) + 1
            yield name


def test_a_command_of_any_size_costs_the_cycle_only_the_joints_it_drives(
        virtual_channel, sim_segment_factory):
    """A command is checked where it arrives (the transport's thread, here the test's): the
    cycle reads at most one name past the joints it drives, however many the message
    holds, and falls to the emergency controller on the first it does not drive."""
    from rocoma_can.inputs import JointCommandSample
    sim_segment_factory(2)
    cfg = demo_config(virtual_channel, drives=2, rate=RATE)
    cfg["controllers"].append({**COMMANDED, "params": {**COMMANDED["params"], "timeout": 30.0}})
    cfg["manager"]["estop_must_be_cleared"] = False
    with runtime_running(cfg, DEMO_WAIT) as rt:
        follow = rt.manager.adapters()["follow"].controller
        wait_for(lambda: rt.manager.switch_blocked() is None, "the drives up")
        assert rt.manager.switch_controller("follow", timeout=DEMO_WAIT).name == "SWITCHED"
        here = [float(v) for v in rt.hardware.state.position]
        names = CountedNames(["joint1", "joint2"] + [f"extra{i}" for i in range(10_000)])
        names.reads = {}
        follow.take_command(JointCommandSample(names, tuple(here + [0.0] * 10_000), (), (),
                                               time.monotonic()))
        wait_for(lambda: rt.manager.state is ManagerState.EMERGENCY, "the fall")
        assert "names joint 'extra0'" in estop_cause(rt)
        elsewhere = sum(n for thread, n in names.reads.items() if thread != threading.get_ident())
        assert elsewhere <= 3, names.reads


def test_a_controller_following_a_topic_without_a_node_is_said(virtual_channel, caplog):
    from rocoma_can.runtime import Runtime
    from rocoma_can.runtime.config import validate
    cfg = demo_config(virtual_channel, drives=2, rate=RATE)
    cfg["controllers"].append(COMMANDED)
    with Runtime(validate(cfg)) as rt:
        assert rt.ros2 is None
    assert "controller 'follow' follows /robot_joint_command, but no ROS 2 node runs" \
        in caplog.text
