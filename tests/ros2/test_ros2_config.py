"""rocoma_can/ros2/config.py, the ``--ros2`` options of ``run`` and ``demo``: a missing router is
an error or a warning as configured, a bad section lists every problem, and the numbers YAML
turns into other types are taken or refused for what they are."""
from __future__ import annotations

import pytest
from fixtures.ros2_rig import DOMAIN, RATE, decode
from fixtures.running import free_port

from rocoma_can.cli.demo.config import demo_config
from rocoma_can.ros2.interfaces import JOINT_STATE
from rocoma_can.ros2.node import Ros2Error


def test_no_router_is_an_error_or_a_warning_as_configured(virtual_channel, caplog):
    from rocoma_can.runtime import Runtime
    from rocoma_can.runtime.config import validate
    cfg = demo_config(virtual_channel, drives=2, rate=RATE)
    nobody = f"tcp/127.0.0.1:{free_port()}"
    cfg["ros2"] = {"connect": [nobody]}
    with pytest.raises(Ros2Error, match=f"Zenoh session .*{nobody}.* could not be opened"):
        Runtime(validate(cfg))
    cfg["ros2"]["required"] = False
    with Runtime(validate(cfg)) as rt:
        assert rt.ros2 is None and "could not be opened" in rt.status()["ros2"]["error"]
    assert "running without the ROS 2 node" in caplog.text


def test_a_bad_ros2_section_lists_every_problem(virtual_channel):
    from rocoma_can.errors import ConfigError
    from rocoma_can.runtime.config import validate
    cfg = demo_config(virtual_channel, drives=2, rate=RATE)
    cfg["ros2"] = {"node": "1robot", "namespace": "/a//b", "domain_id": 300,
                   "distro": "humble", "ros2_control": "3.0", "connect": "7447",
                   "joint_states_rate": 0, "allow_commands": "yes", "nodes": 1,
                   "controller_manager": "cm/*"}
    with pytest.raises(ConfigError) as caught:
        validate(cfg)
    said = "\n".join(caught.value.problems)
    for part in ("ros2.nodes: unknown key, did you mean 'node'?", "ros2.node: expected a ROS 2",
                 "ros2.namespace:", "ros2.domain_id: expected 0..232", "ros2.distro:",
                 "ros2.ros2_control:", "ros2.connect:", "ros2.joint_states_rate:",
                 "ros2.allow_commands: expected true or false",
                 "ros2.controller_manager: expected a name such as controller_manager"):
        assert part in said, said


def test_a_ros2_control_release_written_as_a_yaml_number_is_taken(virtual_channel):
    """``ros2_control: 4.28`` is a float to YAML: taken as the release it names, not refused
    with "expected one of 4.0, 4.13, 4.28, got 4.28"."""
    import yaml

    from rocoma_can.errors import ConfigError
    from rocoma_can.runtime.config import validate
    cfg = demo_config(virtual_channel, drives=2, rate=RATE)
    for text, release in (("4.28", "4.28"), ("4.13", "4.13"), ("4.0", "4.0"), ("'4.0'", "4.0")):
        cfg["ros2"] = yaml.safe_load(f"{{ros2_control: {text}}}")
        assert validate(cfg).ros2.ros2_control == release
    cfg["ros2"] = yaml.safe_load("{ros2_control: 4.1}")
    with pytest.raises(ConfigError, match=r"ros2.ros2_control: expected one of .* got 4\.1"):
        validate(cfg)


@pytest.mark.parametrize("value", ["abc", "300", "-1", "7x"])
def test_a_ros_domain_id_that_is_no_domain_id_is_refused_not_taken_for_0(
        virtual_channel, monkeypatch, tmp_path, capfd, value):
    """ROS_DOMAIN_ID set to something that is no domain id: the node would otherwise join
    domain 0, another graph, and follow that graph's commands. Said, in one line, where
    the domain would come from it (the section or the flag naming one, it is not read)."""
    import yaml

    from rocoma_can.cli.main import main
    from rocoma_can.errors import ConfigError
    from rocoma_can.runtime.config import validate
    monkeypatch.setenv("ROS_DOMAIN_ID", value)
    cfg = demo_config(virtual_channel, drives=2, rate=RATE)
    cfg["ros2"] = {"node": "rocoma"}
    with pytest.raises(ConfigError) as caught:
        validate(cfg)
    assert f"ros2.domain_id: ROS_DOMAIN_ID is {value!r}" in "\n".join(caught.value.problems)
    cfg["ros2"]["domain_id"] = 3
    assert validate(cfg).ros2.domain_id == 3
    del cfg["ros2"]
    path = tmp_path / "robot.yaml"
    path.write_text(yaml.safe_dump(cfg))
    assert main(["run", str(path), "--ros2"]) == 2
    err = capfd.readouterr().err
    assert f"--ros2.domain_id: ROS_DOMAIN_ID is {value!r}" in err and "Traceback" not in err
    monkeypatch.setenv("ROS_DOMAIN_ID", "")  # empty: unset, as rcl has it
    cfg["ros2"] = {}
    assert validate(cfg).ros2.domain_id == 0


def test_run_ros2_serves_the_node_and_refuses_a_bad_flag(
        tmp_path, virtual_channel, sim_segment_factory, router, peer, capfd):
    """``run --ros2 --zenoh-connect ROUTER``: the node on that router (and no fleet bridge:
    --zenoh-connect alone names the node's router); a flag out of range is a usage error
    in one line, before anything starts."""
    import yaml

    from rocoma_can.cli.main import main
    sim_segment_factory(2)
    path = tmp_path / "robot.yaml"
    path.write_text(yaml.safe_dump(demo_config(virtual_channel, drives=2, rate=RATE)))
    assert main(["run", str(path), "--ros2", "--ros-domain-id", "999"]) == 2
    assert "--ros2.domain_id: expected 0..232, got 999" in capfd.readouterr().err
    z = peer()
    seen: list = []
    z.declare_subscriber(f"{DOMAIN}/joint_states/**", seen.append)
    assert main(["run", str(path), "--ros2", "--zenoh-connect", router[2], "--ros-domain-id",
                 str(DOMAIN), "--duration", "2", "--no-flight"]) == 0
    out = capfd.readouterr().out
    assert f"ROS 2 node /rocoma (domain {DOMAIN}, jazzy" in out and "on Zenoh as" not in out
    assert seen and decode(JOINT_STATE, seen[-1].payload.to_bytes()).name == [
        "joint1", "joint2"]


def test_demo_ros2_serves_the_demos_joints_and_says_a_missing_router_in_one_line(
        router, peer, capfd):
    """``demo --ros2`` (docs/ros2.md): the demo's manager is the node on the router
    --zenoh-connect names, its joint states carry the demo's joint names; with no router
    there, one line and exit 2 before anything is brought up."""
    from rocoma_can.cli.main import main
    nobody = f"tcp/127.0.0.1:{free_port()}"
    assert main(["demo", "--ros2", "--zenoh-connect", nobody, "--drives", "2",
                 "--duration", "2", "--no-record", "--no-flight"]) == 2
    said = [line.strip() for line in capfd.readouterr().out.splitlines()]  # (demo: stdout)
    assert said == [
        f"demo: ROS 2 node: Zenoh session (client; connect {nobody}) could not be opened: "
        f"Unable to connect to any of [Single({nobody})]! (a ROS 2 machine starts its router "
        "with `ros2 run rmw_zenoh_cpp rmw_zenohd`; --zenoh-connect names another; "
        "ros2.required: false runs without the node)"], said
    z = peer()
    seen: list = []
    z.declare_subscriber(f"{DOMAIN}/joint_states/**", seen.append)
    assert main(["demo", "--ros2", "--zenoh-connect", router[2], "--ros-domain-id",
                 str(DOMAIN), "--drives", "2", "--duration", "2", "--no-record",
                 "--no-flight"]) == 0
    out = capfd.readouterr().out
    assert f"rocoma-can demo: ROS 2 node /rocoma (domain {DOMAIN}, jazzy" in out, out
    assert seen and decode(JOINT_STATE, seen[-1].payload.to_bytes()).name == [
        "joint1", "joint2"]
