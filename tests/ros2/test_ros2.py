"""The manager as a ROS 2 node (issue 54): a real Runtime on python-can's virtual bus with
simulated drives, a Zenoh client of a router in this process (as rmw_zenoh's nodes reach
theirs), seen by an rmw_zenoh client this project did not write (zenoh-ros2-sdk) and by a
plain Zenoh session whose payloads an independent CDR implementation decodes (Foxglove's
mcap_ros2, from the ROS message definitions as text: not rosbags, which encodes them)."""
from __future__ import annotations

import json
import threading
import time
from contextlib import contextmanager

import numpy as np
import pytest
import zenoh
from fixtures.budgets import odd_late, within
from fixtures.paths import ROOT
from fixtures.running import DEMO_RUN, DEMO_WAIT, free_port, runtime_running
from fixtures.running import wait_for as wait_until
from mcap_ros2._dynamic import generate_dynamic
from zenoh_ros2_sdk import ROS2Publisher, ROS2ServiceClient, ROS2Subscriber, ZenohSession

from rocoma_can import ManagerState
from rocoma_can.cli.demo.config import demo_config
from rocoma_can.ros2.interfaces import JOINT_STATE, Interfaces
from rocoma_can.ros2.node import EVENT_QUEUE, Ros2Error

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


#: the follower: its timeout the default's three periods of its 50 Hz with a loaded host's
#: stall on top (budgets.within): a test's publisher thread, held up longer than 60 ms
#: beside CPU hogs, made the follower fall for a stale command before the fault a test sends
COMMANDED = {"name": "follow", "plugin": "ros2_command", "emergency": "damp",
             "params": {"rate": 50.0, "timeout": within(3 / 50.0), "position_min": -3.0,
                        "position_max": 3.0}}


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


def test_every_payload_decodes_with_an_independent_cdr_implementation(
        virtual_channel, sim_segment_factory, router, peer):
    """Every publication and every answer, read by a plain Zenoh session and decoded by
    mcap_ros2 from the definitions' text; each carries the 33-byte attachment (sequence
    number, timestamp, GID), and an answer echoes the request's sequence number and GID.
    The graph: the node's liveliness tokens, as ros2 node/topic/service list read them."""
    sim_segment_factory(2)
    with node(virtual_channel, router[2], namespace="/robot1") as rt:
        z = peer()
        got: dict[str, list] = {}
        for name, kind in (("robot1/joint_states", "sensor_msgs/msg/JointState"),
                           ("diagnostics", "diagnostic_msgs/msg/DiagnosticArray"),
                           ("rosout", "rcl_interfaces/msg/Log"),
                           ("robot1/rocoma/state", "std_msgs/msg/String")):
            z.declare_subscriber(key(name, kind), lambda s, k=kind: got.setdefault(k, []).append(
                (decode(k, s.payload.to_bytes()), s.attachment.to_bytes())))
        wait_for(lambda: rt.manager.switch_blocked() is None, "the drives up")
        rt.manager.emergency_stop(cause="test")  # an event: on /rosout
        wait_for(lambda: len(got) == 4, "every topic published")
        joints, attached = got["sensor_msgs/msg/JointState"][-1]
        assert list(joints.name) == ["joint1", "joint2"] and len(joints.position) == 2
        assert len(attached) == 33 and attached[16] == 16
        # each publisher numbers its own samples one by one, as rmw_zenoh's do: its
        # subscribers count a gap in a publisher's numbers as messages lost (`ros2 topic
        # echo` prints "A message was lost!!!"), so /diagnostics, /rosout and rocoma/state
        # going out between two joint states must leave no gap in theirs
        for kind in ("sensor_msgs/msg/JointState", "diagnostic_msgs/msg/DiagnosticArray"):
            sequences = [int.from_bytes(a[:8], "little") for _, a in got[kind]]
            steps = {b - a for a, b in zip(sequences, sequences[1:])}
            assert steps <= {1}, (kind, sequences)
        status = json.loads(got["std_msgs/msg/String"][-1][0].data)
        assert status["state"] == rt.manager.state.name and status["ros2"]["domain_id"] == DOMAIN
        diagnostics = got["diagnostic_msgs/msg/DiagnosticArray"][-1][0]
        assert [s.name for s in diagnostics.status] == [
            "/robot1/rocoma: manager", "/robot1/rocoma: joint1", "/robot1/rocoma: joint2"]
        wait_for(lambda: any("e-stop" in m.msg for m, _ in got["rcl_interfaces/msg/Log"]),
                 "the e-stop on /rosout")
        log = next(m for m, _ in got["rcl_interfaces/msg/Log"] if "e-stop" in m.msg)
        assert log.level == 30 and log.name == "robot1.rocoma" and "test" in log.msg

        gid = bytes(range(16))
        for service, kind, response in (
                ("robot1/rocoma/failproof", "std_srvs/srv/Trigger",
                 "std_srvs/srv/Trigger_Response"),
                ("robot1/controller_manager/list_controllers",
                 "controller_manager_msgs/srv/ListControllers",
                 "controller_manager_msgs/srv/ListControllers_Response")):
            replies = list(z.get(key(service, kind), payload=b"\x00\x01\x00\x00",
                                 attachment=attachment_of(41, gid),
                                 target=zenoh.QueryTarget.ALL_COMPLETE, timeout=DEMO_WAIT))
            assert len(replies) == 1 and replies[0].ok is not None, replies
            reply = replies[0].ok
            decode(response, reply.payload.to_bytes())
            echoed = reply.attachment.to_bytes()
            assert int.from_bytes(echoed[:8], "little") == 41 and echoed[17:] == gid

        tokens = {str(r.ok.key_expr) for r in z.liveliness().get(f"@ros2_lv/{DOMAIN}/**",
                                                                timeout=DEMO_WAIT)
                  if r.ok is not None}
        zid = {t.split("/")[2] for t in tokens}
        assert len(zid) == 1, tokens  # one session: the node's
        for token in tokens:  # as rmw_zenoh's graph cache splits one (else it drops it)
            parts = token.split("/")
            assert all(parts) and len(parts) == (9 if parts[5] == "NN" else 13), token
            if len(parts) == 13:  # the QoS: six groups, depth / deadline / lifespan / lease
                groups = [g.split(",") for g in parts[12].split(":")]
                assert [len(g) for g in groups] == [1, 1, 2, 2, 2, 3], token
        shown = {"/".join(t.split("/")[5:10]) for t in tokens}
        assert "NN/%/%robot1/rocoma" in shown
        for entry in ("MP/%/%robot1/rocoma/%robot1%joint_states",
                      "MP/%/%robot1/rocoma/%rosout",  # absolute names stay absolute
                      "SS/%/%robot1/rocoma/%robot1%rocoma%estop",
                      "SS/%/%robot1/rocoma/%robot1%controller_manager%switch_controller",
                      "MS/%/%robot1/rocoma/%robot_joint_command"):
            assert entry in shown, sorted(shown)
        joint_token = next(t for t in tokens if "%robot1%joint_states" in t)
        assert joint_token.endswith(f"/sensor_msgs::msg::dds_::JointState_/"
                                    f"{HASHES.hash(JOINT_STATE)}/::,10:,:,:,,")


def attachment_of(sequence: int, gid: bytes) -> bytes:
    """A request's attachment, written here as the design doc gives it."""
    return (sequence.to_bytes(8, "little") + time.time_ns().to_bytes(8, "little")
            + bytes([len(gid)]) + gid)


def trigger(z, name: str, payload: bytes | None = b"") -> tuple[bool, str]:
    """One std_srvs/Trigger call through a plain session: (success, message)."""
    for reply in z.get(key(name, "std_srvs/srv/Trigger"), payload=payload,
                       target=zenoh.QueryTarget.ALL_COMPLETE, timeout=DEMO_WAIT):
        assert reply.ok is not None, reply.err.payload.to_string()
        answer = decode("std_srvs/srv/Trigger_Response", reply.ok.payload.to_bytes())
        return answer.success, answer.message
    raise AssertionError(f"no answer on {name}")


def test_the_trigger_services_stop_whatever_the_request_holds_and_keep_the_rules(
        virtual_channel, sim_segment_factory, router, peer):
    """A stop acts on any request (no attachment, bytes that are no Trigger request,
    megabytes); clear and recover follow the rules of every remote surface: refused
    without ros2.allow_commands, saying which setting allows them."""
    sim_segment_factory(2)
    with node(virtual_channel, router[2], allow_commands=False) as rt:
        z = peer()
        wait_for(lambda: rt.manager.switch_blocked() is None, "the drives up")
        assert rt.manager.switch_controller("pd", timeout=DEMO_WAIT).name == "SWITCHED"
        assert trigger(z, "rocoma/estop", b"\xff" * 1_000_000) == (True, "state EMERGENCY")
        assert trigger(z, "rocoma/estop", None) == (True, "state FAILPROOF")
        assert rt.manager.state is ManagerState.FAILPROOF
        ok, why = trigger(z, "rocoma/clear")
        assert not ok and "ros2.allow_commands: false" in why, why
        ok, why = trigger(z, "rocoma/recover")
        assert not ok and "ros2.allow_commands" in why, why
        assert trigger(z, "rocoma/failproof", b"junk") == (True, "state FAILPROOF")
        assert rt.ros2.info()["refused"] == 2


def switch(z, activate: list[str],
           manager: str = "controller_manager") -> tuple[bool, str]:
    """A SwitchController call through a plain session, its request encoded by rosbags'
    own definitions (the answer is decoded independently)."""
    i = HASHES
    request = i.encode(i.message(
        "controller_manager_msgs/srv/SwitchController_Request", activate_controllers=activate,
        deactivate_controllers=[], strictness=2, activate_asap=True,
        timeout=i.message("builtin_interfaces/msg/Duration", sec=0, nanosec=0)),
        "controller_manager_msgs/srv/SwitchController_Request")
    for reply in z.get(key(f"{manager}/switch_controller",
                           "controller_manager_msgs/srv/SwitchController"), payload=request,
                       target=zenoh.QueryTarget.ALL_COMPLETE, timeout=DEMO_WAIT):
        answer = decode("controller_manager_msgs/srv/SwitchController_Response",
                        reply.ok.payload.to_bytes())
        return answer.ok, answer.message
    raise AssertionError("no answer on switch_controller")


def test_switch_controller_switches_one_and_says_why_it_does_not(
        virtual_channel, sim_segment_factory, router, peer):
    sim_segment_factory(2)
    with node(virtual_channel, router[2]) as rt:
        z = peer()
        wait_for(lambda: rt.manager.switch_blocked() is None, "the drives up")
        ok, why = switch(z, ["pd", "trajectory"])
        assert not ok and "2 controllers to activate" in why, why
        ok, why = switch(z, ["damp"])  # an emergency controller is not switchable
        assert not ok and why.startswith("NOT_FOUND: no controller 'damp'"), why
        assert switch(z, ["trajectory"]) == (True, "SWITCHED")
        assert rt.manager.active_controller_name == "trajectory"
    with node(virtual_channel, router[2], allow_commands=False):
        ok, why = switch(peer(), ["pd"])
        assert not ok and "ros2.allow_commands: false" in why, why


def test_a_request_or_command_past_its_size_is_refused_undecoded(
        virtual_channel, sim_segment_factory, router, peer, caplog):
    """A peer's megabytes are refused by their length, before a decoder spends the
    interpreter (which the loop's thread shares) on them: a switch request answers why, a
    command on the topic is counted rejected and said."""
    from rocoma_can.ros2.node import MAX_REQUEST
    sim_segment_factory(2)
    with node(virtual_channel, router[2]) as rt:
        z = peer()
        wait_for(lambda: rt.manager.switch_blocked() is None, "the drives up")
        ok, why = switch(z, ["x" * MAX_REQUEST])
        assert not ok and f"more than the {MAX_REQUEST} this node reads" in why, why
        z.put(key("robot_joint_command", JOINT_STATE),
              b"\x00\x01\x00\x00" + bytes(MAX_REQUEST))
        wait_for(lambda: rt.ros2.counters["rejected"] == 1, "the command rejected")
        assert any(f"more than the {MAX_REQUEST} this node reads" in r.getMessage()
                   for r in caplog.records), caplog.text


def test_a_controller_manager_name_of_its_own_keeps_clear_of_ros2_controls(
        virtual_channel, sim_segment_factory, router, peer):
    """Beside ros2_control's own controller_manager (the topic-based hardware interface and
    its JointTrajectoryController run in one), two servers of /controller_manager/... would
    both answer every `ros2 control` call, the caller taking whichever came first:
    ``ros2.controller_manager`` names the node's. Each name then answers alone."""
    sim_segment_factory(2)
    lists = "controller_manager_msgs/srv/ListControllers"
    with node(virtual_channel, router[2], controller_manager="rocoma_manager") as rt:
        z = peer()
        theirs = z.declare_queryable(  # ros2_control's controller_manager, as a stand-in
            key("controller_manager/list_controllers", lists),
            lambda q: q.reply(q.key_expr, b"theirs"), complete=True)
        wait_for(lambda: rt.manager.switch_blocked() is None, "the drives up")

        def answers(name: str) -> list[bytes]:
            return [r.ok.payload.to_bytes() for r in z.get(
                key(name, lists), payload=b"\x00\x01\x00\x00\x00",
                attachment=attachment_of(1, bytes(16)), target=zenoh.QueryTarget.ALL_COMPLETE,
                timeout=DEMO_WAIT) if r.ok is not None]
        assert answers("controller_manager/list_controllers") == [b"theirs"]
        ours = answers("rocoma_manager/list_controllers")
        assert len(ours) == 1, ours
        listed = decode("controller_manager_msgs/srv/ListControllers_Response", ours[0])
        assert "follow" in [c.name for c in listed.controller]
        ok, why = switch(z, ["pd"], "rocoma_manager")
        assert ok and rt.manager.active_controller_name == "pd", why
        theirs.undeclare()


def test_a_refused_call_is_said_on_rosout(virtual_channel, sim_segment_factory, router, peer):
    """`ros2 control switch_controllers` answers a refusal with "Error switching
    controllers, check controller_manager logs" and shows no reason (nor has the
    SwitchController of ros2_control before 4.28 a field for one): the reason goes to
    /rosout, where rqt_console shows it, as a warning naming the service."""
    sim_segment_factory(2)
    with node(virtual_channel, router[2], allow_commands=False) as rt:
        z = peer()
        logs: list = []
        z.declare_subscriber(key("rosout", "rcl_interfaces/msg/Log"),
                             lambda s: logs.append(decode("rcl_interfaces/msg/Log",
                                                          s.payload.to_bytes())))
        wait_for(lambda: rt.manager.switch_blocked() is None, "the drives up")
        assert not switch(z, ["pd"])[0]
        assert not trigger(z, "rocoma/clear")[0]
        for service in ("switch_controller", "clear"):
            wait_for(lambda s=service: any(s in m.msg and "ros2.allow_commands: false" in m.msg
                                           for m in logs), f"{service}'s refusal on /rosout")
        said = [m for m in logs if "allow_commands" in m.msg]
        assert all(m.level == 30 and m.name == "rocoma" for m in said), said


def publisher(ros2_sdk):
    sdk_knows(ros2_sdk, JOINT_STATE)
    return ROS2Publisher("/robot_joint_command", JOINT_STATE,
                         msg_definition=DEFINITIONS[JOINT_STATE][0],
                         type_hash=HASHES.hash(JOINT_STATE))


def command(ros2_sdk, names, position):
    types = ros2_sdk.store.types
    return dict(header=types["std_msgs/msg/Header"](
        stamp=types["builtin_interfaces/msg/Time"](sec=0, nanosec=0), frame_id=""),
        name=list(names), position=np.array(position, dtype=float),
        velocity=np.zeros(0), effort=np.zeros(0))


@contextmanager
def following(rt, ros2_sdk, period: float = 0.02):
    """The drives up, a third-party publisher sending the pose they are at every
    ``period`` s on a thread, and the manager switched to ``follow``: the message (a dict
    read at every send: change it to command) until the block ends, when sending stops."""
    pub = publisher(ros2_sdk)
    wait_for(lambda: rt.manager.switch_blocked() is None, "the drives up")
    message = command(ros2_sdk, ["joint1", "joint2"],
                      [float(v) for v in rt.hardware.state.position])
    stop = threading.Event()

    def run() -> None:
        while not stop.wait(period):
            pub.publish(**message)
    thread = threading.Thread(target=run, name="test-commands")
    thread.start()
    try:
        assert rt.manager.switch_controller("follow", timeout=DEMO_WAIT).name == "SWITCHED"
        yield message
    finally:
        stop.set()
        thread.join(DEMO_WAIT)


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


def estop_cause(rt) -> str:
    """The last e-stop's cause as the status report says it, once it says one: the report
    learns it from the manager's event, a moment after the state changed."""
    wait_for(lambda: rt.status()["estop_cause"], "the e-stop's cause in the status report")
    return str(rt.status()["estop_cause"])


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


def documented_hardware_interface() -> dict[str, str]:
    """The hardware parameters of docs/ros2.md's URDF snippet (the ``<ros2_control>`` block
    a user copies into the robot's description)."""
    import re
    import xml.etree.ElementTree as ET
    text = (ROOT / "docs" / "ros2.md").read_text()
    snippet = re.search(r"```xml\n(<ros2_control.*?</ros2_control>)\n```", text, re.S)
    assert snippet, "docs/ros2.md has no <ros2_control> snippet"
    hardware = ET.fromstring(snippet.group(1)).find("hardware")
    return {p.get("name", ""): (p.text or "").strip() for p in hardware.iter("param")}


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


def test_a_peer_that_stops_reading_leaves_the_loop_its_period(
        virtual_channel, sim_segment_factory, router, peer, ros2_sdk):
    """A subscriber to everything the node publishes that never returns from its first
    sample (its session reads no more), at 200 Hz of joint states: the node keeps
    publishing and another subscriber keeps receiving, and the loop keeps its rate
    (overruns counted, not wall time: odd_late), counted from its 300th cycle."""
    sim_segment_factory(2)
    with node(virtual_channel, router[2], joint_states_rate=200) as rt:
        sdk_knows(ros2_sdk, JOINT_STATE)
        healthy: list = []
        ROS2Subscriber("/joint_states", JOINT_STATE, healthy.append,
                       msg_definition=DEFINITIONS[JOINT_STATE][0],
                       type_hash=HASHES.hash(JOINT_STATE))
        wait_for(lambda: rt.loop.stats.cycles >= 300, "300 cycles", DEMO_RUN)
        release = threading.Event()
        stalled = peer()
        stalled.declare_subscriber(f"{DOMAIN}/**", lambda sample: release.wait(DEMO_RUN))
        try:
            stats = rt.loop.stats
            cycles, overruns = stats.cycles, stats.overruns
            published, received = rt.ros2.info()["published"], len(healthy)
            wait_for(lambda: rt.ros2.info()["published"] - published >= 600,
                     "600 publications while a peer stalls", DEMO_RUN)
            wait_for(lambda: len(healthy) - received >= 300,
                     "300 joint states to the other subscriber meanwhile", DEMO_RUN)
            assert stats.cycles > cycles
            assert stats.overruns - overruns <= odd_late(stats.cycles - cycles)
        finally:
            release.set()


def test_events_past_the_queue_are_dropped_and_counted(virtual_channel, router):
    """The node's event queue is bounded: the manager's dispatcher never waits for it."""
    from rocoma_can.events import EventKind, ManagerEvent
    from rocoma_can.runtime import Runtime
    from rocoma_can.runtime.config import validate
    cfg = demo_config(virtual_channel, drives=2, rate=RATE)
    cfg["ros2"] = {"connect": [router[2]]}
    with Runtime(validate(cfg)) as rt:  # not run: the publisher thread takes none
        # refused calls (a caller's flood) take half the queue at most: the manager's
        # events keep the other half
        for _ in range(EVENT_QUEUE):
            rt.ros2._refused("rocoma/clear", "not allowed")
        assert rt.ros2.info()["dropped"] == EVENT_QUEUE // 2
        event = ManagerEvent(EventKind.STATE_CHANGED, ManagerState.FAILPROOF, "torque_off")
        for _ in range(EVENT_QUEUE // 2 + 3):
            rt.ros2._on_event(event)
        assert rt.ros2.info()["dropped"] == EVENT_QUEUE // 2 + 3


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


def test_a_controller_following_a_topic_without_a_node_is_said(virtual_channel, caplog):
    from rocoma_can.runtime import Runtime
    from rocoma_can.runtime.config import validate
    cfg = demo_config(virtual_channel, drives=2, rate=RATE)
    cfg["controllers"].append(COMMANDED)
    with Runtime(validate(cfg)) as rt:
        assert rt.ros2 is None
    assert "controller 'follow' follows /robot_joint_command, but no ROS 2 node runs" \
        in caplog.text
