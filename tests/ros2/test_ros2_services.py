"""rocoma_can/ros2/node.py (its services): the Trigger services stop whatever the request holds,
switch_controller switches one controller and says why it does not, a request past its size is
refused undecoded, and a refused call is said on /rosout."""
from __future__ import annotations

import zenoh
from fixtures.ros2_rig import attachment_of, decode, key, node, switch, trigger, wait_for
from fixtures.running import DEMO_WAIT

from rocoma_can import ManagerState
from rocoma_can.ros2.interfaces import JOINT_STATE


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
