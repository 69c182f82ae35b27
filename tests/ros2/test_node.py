"""rocoma_can/ros2/node.py: the manager as a ROS 2 node (issue 54): a real Runtime on python-can's
virtual bus with simulated drives, a Zenoh client of a router in this process (as rmw_zenoh's
nodes reach theirs), seen by an rmw_zenoh client this project did not write (zenoh-ros2-sdk) and
by a plain Zenoh session whose payloads an independent CDR implementation decodes (Foxglove's
mcap_ros2, from the ROS message definitions as text: not rosbags, which encodes them). Its
services: test_ros2_services.py; the ros2_command controller: test_ros2_command.py; the section
and the options: test_ros2_config.py; the rig: tests/fixtures/ros2_rig.py."""
from __future__ import annotations

import json
import threading

import zenoh
from fixtures.budgets import odd_late
from fixtures.ros2_rig import (
    DEFINITIONS,
    DOMAIN,
    HASHES,
    RATE,
    attachment_of,
    decode,
    key,
    node,
    sdk_knows,
    wait_for,
)
from fixtures.running import DEMO_RUN, DEMO_WAIT
from zenoh_ros2_sdk import ROS2ServiceClient, ROS2Subscriber

from rocoma_can import ManagerState
from rocoma_can.cli.demo.config import demo_config
from rocoma_can.ros2.interfaces import JOINT_STATE
from rocoma_can.ros2.node import EVENT_QUEUE


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
