"""The manager as a ROS 2 node (issue 54): a real Runtime on python-can's virtual bus with
simulated drives, a Zenoh client of a router in this process (as rmw_zenoh's nodes reach
theirs), seen by an rmw_zenoh client this project did not write (zenoh-ros2-sdk) and by a
plain Zenoh session whose payloads an independent CDR implementation decodes (Foxglove's
mcap_ros2, from the ROS message definitions as text: not rosbags, which encodes them)."""
from __future__ import annotations

import json
import socket
from contextlib import contextmanager

import pytest
import zenoh
from fixtures.running import DEMO_WAIT, runtime_running
from fixtures.running import wait_for as wait_until
from mcap_ros2._dynamic import generate_dynamic
from zenoh_ros2_sdk import ROS2ServiceClient, ROS2Subscriber, ZenohSession

from rocoma_can import ManagerState
from rocoma_can.cli.demo_config import demo_config
from rocoma_can.ros2.interfaces import JOINT_STATE, Interfaces

RATE = 100.0
DOMAIN = 7
HASHES = Interfaces("jazzy")

#: the ROS message definitions, as the packages ship them (comments left out), for the
#: independent decoder
TIME = "int32 sec\nuint32 nanosec\n"
HEADER = "builtin_interfaces/Time stamp\nstring frame_id\n"
DEFINITIONS = {
    "sensor_msgs/msg/JointState": ("std_msgs/Header header\nstring[] name\nfloat64[] position\n"
                                   "float64[] velocity\nfloat64[] effort\n",
                                   {"std_msgs/Header": HEADER, "builtin_interfaces/Time": TIME}),
    "std_msgs/msg/String": ("string data\n", {}),
    "rcl_interfaces/msg/Log": ("builtin_interfaces/Time stamp\nuint8 level\nstring name\n"
                               "string msg\nstring file\nstring function\nuint32 line\n",
                               {"builtin_interfaces/Time": TIME}),
    "diagnostic_msgs/msg/DiagnosticArray": (
        "std_msgs/Header header\nDiagnosticStatus[] status\n",
        {"std_msgs/Header": HEADER, "builtin_interfaces/Time": TIME,
         "diagnostic_msgs/DiagnosticStatus": "byte level\nstring name\nstring message\n"
                                             "string hardware_id\nKeyValue[] values\n",
         "diagnostic_msgs/KeyValue": "string key\nstring value\n"}),
    "std_srvs/srv/Trigger_Response": ("bool success\nstring message\n", {}),
    "controller_manager_msgs/srv/ListControllers_Response": (
        "controller_manager_msgs/ControllerState[] controller\n",
        {"controller_manager_msgs/ControllerState":
            "string name\nstring state\nstring type\nbool is_async\nuint16 update_rate\n"
            "string[] claimed_interfaces\nstring[] required_command_interfaces\n"
            "string[] required_state_interfaces\nbool is_chainable\nbool is_chained\n"
            "string[] exported_state_interfaces\nstring[] reference_interfaces\n"
            "ChainConnection[] chain_connections\n",
         "controller_manager_msgs/ChainConnection":
            "string name\nstring[] reference_interfaces\n"}),
    "controller_manager_msgs/srv/SwitchController_Response": ("bool ok\nstring message\n", {}),
}
SEPARATOR = "=" * 80


def decode(name: str, data: bytes):
    """``data`` decoded by mcap_ros2 from the definition's text."""
    body, nested = DEFINITIONS[name]
    text = body + "".join(f"{SEPARATOR}\nMSG: {n}\n{t}" for n, t in nested.items())
    return generate_dynamic(name, text)[name](data)


def sdk_knows(session, *names: str) -> None:
    """The definitions ``names`` reference, given to zenoh-ros2-sdk's type store as a ROS
    install has them (the SDK would fetch them from GitHub), referenced ones first."""
    nested = {n: t for name in names for n, t in DEFINITIONS[name][1].items()}
    nested["builtin_interfaces/Duration"] = TIME
    for n, text in reversed(nested.items()):
        package, base = n.split("/")
        session.register_message_type(text, f"{package}/msg/{base}")


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def wait_for(predicate, what: str, timeout: float = DEMO_WAIT) -> None:
    wait_until(predicate, what, timeout)


@pytest.fixture
def router():
    """A Zenoh router in this process (rmw_zenoh's rmw_zenohd stands in its place), on a
    free loopback port: (host, port, endpoint)."""
    port = free_port()
    conf = zenoh.Config()
    conf.insert_json5("mode", '"router"')
    conf.insert_json5("listen/endpoints", json.dumps([f"tcp/127.0.0.1:{port}"]))
    conf.insert_json5("scouting/multicast/enabled", "false")
    session = zenoh.open(conf)
    yield "127.0.0.1", port, f"tcp/127.0.0.1:{port}"
    session.close()


@pytest.fixture
def peer(router):
    """A plain Zenoh client of the router, as another machine's program."""
    sessions = []

    def connect():
        conf = zenoh.Config()
        conf.insert_json5("mode", '"client"')
        conf.insert_json5("connect/endpoints", json.dumps([router[2]]))
        s = zenoh.open(conf)
        sessions.append(s)
        return s
    yield connect
    for s in sessions:
        s.close()


@pytest.fixture
def ros2_sdk(router, monkeypatch):
    """zenoh-ros2-sdk's shared session on the test's router (its singleton reset after)."""
    monkeypatch.setenv("ROS_DOMAIN_ID", str(DOMAIN))
    session = ZenohSession.get_instance(router[0], router[1])
    yield session
    session.close()


COMMANDED = {"name": "follow", "plugin": "ros2_command", "emergency": "damp",
             "params": {"rate": 50.0, "position_min": -3.0, "position_max": 3.0}}


@contextmanager
def node(channel: str, endpoint: str, **section):
    cfg = demo_config(channel, drives=2, rate=RATE)
    cfg["controllers"].append(COMMANDED)
    cfg["manager"]["estop_must_be_cleared"] = False
    cfg["ros2"] = {"connect": [endpoint], "domain_id": DOMAIN, "joint_states_rate": 50,
                   "allow_commands": True, **section}
    with runtime_running(cfg, DEMO_WAIT) as rt:
        yield rt


def key(name: str, kind: str) -> str:
    from rocoma_can.ros2.interfaces import dds_type_name
    return f"{DOMAIN}/{name}/{dds_type_name(kind)}/{HASHES.hash(kind)}"


def test_a_third_party_rmw_zenoh_client_sees_joint_states_estops_lists_and_switches(
        virtual_channel, sim_segment_factory, router, ros2_sdk):
    """The issue's done-when, with zenoh-ros2-sdk: /joint_states with the demo's joint
    names, /rocoma/estop and the state change it makes, the controllers listed (the
    emergency and failproof ones as such) and one switched."""
    sim_segment_factory(2)
    with node(virtual_channel, router[2]) as rt:
        sdk_knows(ros2_sdk, JOINT_STATE, "controller_manager_msgs/srv/ListControllers_Response")
        seen = []
        ROS2Subscriber("/joint_states", JOINT_STATE, seen.append,
                       msg_definition=DEFINITIONS[JOINT_STATE][0],
                       type_hash=HASHES.hash(JOINT_STATE))
        wait_for(lambda: len(seen) >= 3, "joint states from the node")
        assert list(seen[-1].name) == ["joint1", "joint2"]
        wait_for(lambda: rt.manager.switch_blocked() is None, "the drives up")
        lister = ROS2ServiceClient(
            "/controller_manager/list_controllers", "controller_manager_msgs/srv/ListControllers",
            request_definition="",
            response_definition="controller_manager_msgs/ControllerState[] controller",
            type_hash=HASHES.hash("controller_manager_msgs/srv/ListControllers"),
            timeout=DEMO_WAIT)
        listed = {c.name: (c.type, c.state) for c in lister.call().controller}
        assert listed == {
            "pd": ("rocoma_can/JointPD", "inactive"),
            "trajectory": ("rocoma_can/Trajectory", "inactive"),
            "follow": ("rocoma_can/Ros2Command", "inactive"),
            "damp": ("rocoma_can/emergency/Damp", "inactive"),
            "torque_off": ("rocoma_can/failproof/TorqueOff", "active")}, listed
        switcher = ROS2ServiceClient(
            "/controller_manager/switch_controller",
            "controller_manager_msgs/srv/SwitchController",
            request_definition=("string[] activate_controllers\nstring[] deactivate_controllers\n"
                                "int32 strictness\nbool activate_asap\n"
                                "builtin_interfaces/Duration timeout"),
            response_definition="bool ok\nstring message",
            type_hash=HASHES.hash("controller_manager_msgs/srv/SwitchController"),
            timeout=DEMO_WAIT)
        duration = ros2_sdk.store.types["builtin_interfaces/msg/Duration"]
        answer = switcher.call(activate_controllers=["pd"], deactivate_controllers=[],
                               strictness=1, activate_asap=True,
                               timeout=duration(sec=0, nanosec=0))
        assert answer.ok, answer.message
        assert rt.manager.state is ManagerState.OK and rt.manager.active_controller_name == "pd"
        estop = ROS2ServiceClient("/rocoma/estop", "std_srvs/srv/Trigger",
                                  request_definition="",
                                  response_definition="bool success\nstring message",
                                  type_hash=HASHES.hash("std_srvs/srv/Trigger"),
                                  timeout=DEMO_WAIT)
        answer = estop.call()
        assert answer.success and answer.message == "state EMERGENCY", answer.message
        assert rt.manager.state is ManagerState.EMERGENCY
        listed = {c.name: c.state for c in lister.call().controller}
        assert listed["damp"] == "active" and listed["pd"] == "inactive", listed
