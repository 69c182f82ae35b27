"""The live view on a Foxglove WebSocket (rocoma_can/live/foxglove.py), seen by a client
speaking the Foxglove WebSocket protocol on loopback: channels advertised, joint states with
the joints' names, services under the remote rules, a stalled viewer that costs the loop
nothing."""
from __future__ import annotations

import json
import math
import os
import signal
import socket
import struct
import time
from pathlib import Path
from typing import Any

import pytest
from fixtures.budgets import odd_late
from fixtures.paths import ROOT
from fixtures.running import DEMO_RUN, DEMO_WAIT, runtime_running, wait_for

from rocoma_can.cli.demo.config import demo_config, demo_urdf
from rocoma_can.live.foxglove import LAYOUT, FoxgloveConfig
from rocoma_can.live.front import LEGACY_SUBPROTOCOL
from rocoma_can.live.messages import INFO, MANAGER_CHANNELS, ROBOT, WARNING, event_log
from rocoma_can.live.urdf import parse_urdf
from rocoma_can.record.trace import read_messages
from rocoma_can.remote import COMMANDS

pytest.importorskip("foxglove")
pytest.importorskip("websockets.sync.client")
from fixtures.foxglove_layout import layout_paths, layout_topics, shipped_layout
from fixtures.foxglove_viewer import SUBPROTOCOL, Viewer  # noqa: E402 - after the skips

TOPICS = [c.topic for c in MANAGER_CHANNELS]


def _config(channel: str, drives: int = 2, rate: float = 100.0) -> dict[str, Any]:
    cfg = demo_config(channel, drives=drives, rate=rate)
    cfg["manager"]["estop_must_be_cleared"] = False
    return cfg


def _view(**options: Any) -> FoxgloveConfig:
    return FoxgloveConfig(host="127.0.0.1", port=0, **options)


def _listener_pids(port: int) -> set[int]:
    """The processes holding the socket that listens on loopback ``port`` (Linux's /proc)."""
    inodes = set()
    for line in Path("/proc/net/tcp").read_text().splitlines()[1:]:
        fields = line.split()
        local, state, inode = fields[1], fields[3], fields[9]
        if state == "0A" and int(local.split(":")[1], 16) == port:  # 0A: LISTEN
            inodes.add(f"socket:[{inode}]")
    holders = set()
    for proc in Path("/proc").iterdir():
        if not proc.name.isdigit():
            continue
        try:
            links = {os.readlink(fd) for fd in (proc / "fd").iterdir()}
        except OSError:  # gone meanwhile, or not ours to look at
            continue
        if links & inodes:
            holders.add(int(proc.name))
    return holders


def test_a_recovery_is_a_log_line_as_it_starts_and_ends():
    """The log line of each recovery event; a failed one is a warning."""
    def line(cause: str) -> tuple[str, int]:
        return event_log({"kind": "recovery", "state": "FAILPROOF", "controller": "torque_off",
                          "cause": cause})
    assert line("started") == ("recovery started (FAILPROOF)", INFO)
    assert line("done: every drive is back")[1] == INFO
    assert line("failed: not every drive came back") == (
        "recovery failed: not every drive came back (FAILPROOF)", WARNING)


@pytest.mark.parametrize("subprotocol", [SUBPROTOCOL, LEGACY_SUBPROTOCOL])
def test_channels_joint_states_and_an_estop(virtual_channel, sim_segment_factory,
                                            subprotocol):
    """Under the protocol's either name: the SDK's, and the specification's that viewers
    written before the SDK ask for (the front renames it, live/front.py)."""
    sim_segment_factory(2)
    with runtime_running(_config(virtual_channel), DEMO_RUN, foxglove=_view()) as rt:
        # served by the writer process: its socket is that process's, not the loop's
        assert rt.recorder is not None
        assert _listener_pids(rt.foxglove.port) == {rt.recorder.pid}
        viewer = Viewer(rt.foxglove.port, subprotocol)
        try:
            assert viewer.ws.subprotocol == subprotocol
            viewer.subscribe(*TOPICS)
            assert {t: viewer.channels[t]["schemaName"] for t in TOPICS} == {
                c.topic: c.schema_name for c in MANAGER_CHANNELS}
            assert "/robot_description" not in viewer.channels  # no URDF in the config
            viewer.pump(lambda: {f"/rocoma/{c}" for c in COMMANDS} <= set(viewer.services),
                        "every command service advertised")
            for command in COMMANDS:  # with its request's and answer's JSON schemas
                service = viewer.services[f"/rocoma/{command}"]
                for part in ("request", "response"):
                    assert service[part]["schemaEncoding"] == "jsonschema", service
                    doc = json.loads(service[part]["schema"])
                    assert doc["title"] == service[part]["schemaName"]
            switch = json.loads(viewer.services["/rocoma/switch"]["request"]["schema"])
            assert set(switch["properties"]) == {"controller"}
            viewer.pump(lambda: viewer.received.get("/joint_states"), "joint states")
            joints = viewer.received["/joint_states"][-1]
            assert joints["name"] == [d["name"] for d in _config(virtual_channel)["drives"]]
            assert len(joints["position"]) == len(joints["velocity"]) == len(
                joints["effort"]) == 2
            viewer.pump(lambda: viewer.received.get("/rocoma/status"), "a status report")
            assert {"cycle", "buses", "drives"} <= set(viewer.received["/rocoma/status"][-1])
            wait_for(lambda: rt.manager.switch_blocked() is None, "drives up", DEMO_WAIT)
            assert rt.manager.switch_controller("pd", timeout=DEMO_WAIT) == 0  # to OK
            viewer.pump(lambda: any(m["state"] == "OK" and m["controller"] == "pd"
                                    for m in viewer.received.get("/rocoma/manager", [])),
                        "the manager in OK on /rocoma/manager")
            shown = viewer.received["/rocoma/manager"][-1]
            assert 0 <= shown["overruns_waiting"] <= shown["overruns"] <= shown["cycles"]

            answer = viewer.call("/rocoma/estop", {"anything": "ignored"})
            assert answer == {"ok": True, "state": "EMERGENCY"}  # acted on, then answered
            viewer.pump(lambda: any(m["state"] == "EMERGENCY" and m["cause"]
                                    == "Foxglove e-stop"
                                    for m in viewer.received.get("/rocoma/manager", [])),
                        "the manager's e-stop on /rocoma/manager")
            viewer.pump(lambda: any("e-stop" in m["message"] and m["level"] == 3
                                    for m in viewer.received.get("/rocoma/log", [])),
                        "the e-stop in the log")
        finally:
            viewer.close()


def test_switch_is_refused_unless_allowed_and_failproof_is_not(virtual_channel,
                                                               sim_segment_factory, tmp_path):
    sim_segment_factory(2)
    with runtime_running(_config(virtual_channel), DEMO_RUN, foxglove=_view(),
                         record=str(tmp_path)) as rt:
        viewer = Viewer(rt.foxglove.port)
        try:
            wait_for(lambda: rt.manager.switch_blocked() is None, "drives up", DEMO_WAIT)
            # a request that names no controller gets the same refusal: nothing about
            # the controllers is said to a caller who may not switch
            for request in ({"controller": "pd"}, [1]):
                answer = viewer.call("/rocoma/switch", request)
                assert answer["result"] == "ERROR"
                assert "--foxglove-allow-commands: false" in answer["error"]
            assert viewer.call("/rocoma/clear")["ok"] is False
            assert rt.manager.active_controller_name != "pd"
            assert viewer.call("/rocoma/failproof") == {"ok": True, "state": "FAILPROOF"}
            assert rt.foxglove.info()["refused"] == 3
        finally:
            viewer.close()
    # the calls' lines are in the recording's log as the live view showed them
    logged = [m["message"] for topic, _, m in read_messages(str(tmp_path / "trace.mcap"))
              if topic == "/rocoma/log" and "from Foxglove" in m["message"]]
    assert [line.split(":")[0] for line in logged] == [
        "switch from Foxglove", "switch from Foxglove", "clear from Foxglove",
        "failproof from Foxglove"], logged
    assert "refused" in logged[0] and logged[3].endswith(": done")


def test_a_viewer_gone_without_closing_is_counted_not_said(virtual_channel,
                                                          sim_segment_factory, capfd):
    """A viewer whose connection is reset (its tab closed, its machine gone) is a viewer's
    right: counted as viewers_gone, not an error line from the SDK on the run's
    terminal."""
    sim_segment_factory(2)
    with runtime_running(_config(virtual_channel), DEMO_RUN, foxglove=_view()) as rt:
        viewer = Viewer(rt.foxglove.port)
        viewer.pump(lambda: len(viewer.channels) >= len(TOPICS), "the channels advertised")
        sock = viewer.ws.socket
        sock.setsockopt(socket.SOL_SOCKET, socket.SO_LINGER, struct.pack("ii", 1, 0))
        sock.close()  # a reset, no closing handshake
        wait_for(lambda: rt.foxglove.info().get("viewers_gone", 0) >= 1, "the viewer gone",
                 DEMO_WAIT)
    assert "reset by peer" not in capfd.readouterr().err


def test_an_allowed_switch_switches(virtual_channel, sim_segment_factory):
    sim_segment_factory(2)
    with runtime_running(_config(virtual_channel), DEMO_RUN,
                         foxglove=_view(allow_commands=True)) as rt:
        viewer = Viewer(rt.foxglove.port)
        try:
            wait_for(lambda: rt.manager.switch_blocked() is None, "drives up", DEMO_WAIT)
            # subscribed first: the server takes a client's messages in order, so the log
            # channel has this viewer by the time the switch (and its event) happens
            viewer.subscribe("/rocoma/log")
            # a request no controller name needs is refused by the server, never parsed
            # in the loop's process (no call reaches it)
            answer = viewer.call("/rocoma/switch", {"controller": "x" * 2000})
            assert answer["result"] == "NOT_FOUND" and "bytes" in answer["error"]
            assert rt.foxglove.info()["calls"] == 0
            assert viewer.call("/rocoma/switch", {"controller": "pd"}) == {
                "result": "SWITCHED"}
            assert rt.manager.active_controller_name == "pd"
            # every form docs/foxglove.md gives: a JSON string is the name (not a name in
            # quotes), a number is list's, text that is not JSON the bare name
            for request, raw, active in (("trajectory", None, "trajectory"),
                                         (1, None, "pd"), ({"controller": 2}, None,
                                                           "trajectory"),
                                         (None, b"pd", "pd")):
                assert viewer.call("/rocoma/switch", request, raw) == {
                    "result": "SWITCHED"}, (request, raw)
                assert rt.manager.active_controller_name == active
            # one that names no controller is refused saying why, and what is accepted
            forms = 'a controller is named by a string, its number, or {"controller": NAME}'
            for request, why in (
                    ({"controler": "pd"}, "the request has no \"controller\" (its keys: "
                                          "'controler')"),
                    ({"controller": None}, "the request's \"controller\" is null"),
                    (["pd"], "the request is an array"), (True, "the request is true or false")):
                assert viewer.call("/rocoma/switch", request) == {
                    "result": "NOT_FOUND", "error": f"no controller: {why}; {forms} "
                                                    "(controllers: pd, trajectory)"}
            assert viewer.call("/rocoma/switch", "nope")["error"] == (
                "no controller 'nope' (controllers: pd, trajectory)")
            assert rt.manager.active_controller_name == "pd"
            # a stop is obeyed whatever it carries, however much
            assert viewer.call("/rocoma/estop", {"junk": "y" * 100_000})["ok"] is True
            wait_for(lambda: rt.manager.state.name != "OK", "the e-stop", DEMO_WAIT)
            viewer.pump(lambda: any("switched to pd" in m["message"]
                                    for m in viewer.received.get("/rocoma/log", [])),
                        "the switch in the log")
        finally:
            viewer.close()


def test_a_stalled_viewer_costs_the_loop_nothing(virtual_channel, sim_segment_factory):
    """A viewer subscribed to everything that never reads (a tiny receive buffer, at most
    one frame queued in the client), then vanishes, while another keeps reading: the view
    keeps publishing, the other viewer keeps receiving, and the loop keeps its rate over
    hundreds of messages published to the stalled viewer, counted from the loop's 300th
    cycle: its first seconds (bring-up, first calls) may cost it a cycle, with or without a
    view. A view that made the loop wait on the stalled socket would overrun every cycle it
    published in; a busy machine makes the odd cycle late whatever the view does."""
    sim_segment_factory(2)
    with runtime_running(_config(virtual_channel), DEMO_RUN,
                         foxglove=_view(rate=500.0, backlog=8)) as rt:
        wait_for(lambda: rt.manager.switch_blocked() is None, "drives up", DEMO_WAIT)
        assert rt.manager.switch_controller("pd", timeout=DEMO_WAIT) == 0  # drives enabled
        wait_for(lambda: rt.loop.stats.cycles >= 300, "300 cycles", DEMO_RUN)
        raw = socket.socket()
        raw.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, 4096)
        raw.connect(("127.0.0.1", rt.foxglove.port))
        stalled = Viewer(rt.foxglove.port, sock=raw, max_queue=1)
        healthy = Viewer(rt.foxglove.port)
        try:
            stalled.subscribe(*TOPICS)  # reads the advertisements, then never again
            healthy.subscribe("/joint_states")
            healthy.pump(lambda: len(healthy.received.get("/joint_states", [])) >= 100,
                         "a first hundred joint states")
            stats = rt.loop.stats
            cycles, overruns = stats.cycles, stats.overruns
            published = rt.foxglove.info()["published"]
            healthy.pump(lambda: len(healthy.received["/joint_states"]) >= 400,
                         "300 joint states while another viewer stalls", DEMO_RUN)
            # (the server's counters reach this process up to COUNTS_PERIOD late)
            wait_for(lambda: rt.foxglove.info()["published"] - published >= 600,
                     "600 messages published meanwhile", DEMO_WAIT)
            assert stats.cycles > cycles
            assert stats.overruns - overruns <= odd_late(stats.cycles - cycles)
            assert rt.foxglove.info()["events_dropped"] == 0
            raw.shutdown(socket.SHUT_RDWR)  # vanished: the view serves the other one on
            stalled.close()
            n = len(healthy.received["/joint_states"])
            healthy.pump(lambda: len(healthy.received["/joint_states"]) >= n + 100,
                         "joint states after the stalled viewer vanished", DEMO_RUN)
            assert stats.overruns - overruns <= odd_late(stats.cycles - cycles)
        finally:
            raw.close()
            stalled.close()
            healthy.close()


def test_a_viewer_that_never_reads_has_its_drops_counted_and_shown(
        virtual_channel, sim_segment_factory, capfd):
    """Once a stalled viewer's outbox in the SDK is full, messages for it are dropped (the
    view never waits): counted as viewer_drops, in info() and on /rocoma/manager for the
    other viewers. A viewer that unsubscribes and leaves makes no callback fail (the SDK
    would say so on the stderr of the writer process, which serves the view)."""
    sim_segment_factory(2)
    # the view publishes a row at most once: a loop at 1 kHz gives it 1000 a second
    with runtime_running(_config(virtual_channel, rate=1000.0), DEMO_RUN,
                         foxglove=_view(rate=1000.0, backlog=8)) as rt:
        raw = socket.socket()
        raw.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, 4096)
        raw.connect(("127.0.0.1", rt.foxglove.port))
        stalled = Viewer(rt.foxglove.port, sock=raw, max_queue=1)
        try:
            stalled.subscribe(*TOPICS)  # then never reads again
            wait_for(lambda: rt.foxglove.info()["viewer_drops"] >= 1,
                     "messages dropped for the stalled viewer", DEMO_RUN)
            healthy = Viewer(rt.foxglove.port)
            try:
                healthy.subscribe("/rocoma/manager")
                healthy.pump(lambda: healthy.received.get("/rocoma/manager"),
                             "a manager message")
                shown = healthy.received["/rocoma/manager"][-1]["foxglove"]
                assert shown["viewer_drops"] >= 1, shown
            finally:
                healthy.close()
        finally:
            raw.close()
            stalled.close()
    err = capfd.readouterr().err
    assert "Callback failed" not in err, err


def test_nothing_is_built_for_channels_nobody_watches(virtual_channel, sim_segment_factory):
    """With no viewer the view publishes nothing and the loop's process builds no status
    report (the one message made there); a viewer's subscription starts exactly the
    channels it asked for, and the report only once a viewer subscribes to it."""
    sim_segment_factory(2)
    with runtime_running(_config(virtual_channel), DEMO_RUN,
                         foxglove=_view(rate=200.0)) as rt:
        wait_for(lambda: rt.loop.stats.cycles >= 100, "100 cycles", DEMO_WAIT)
        rt.manager.emergency_stop("nobody watches")  # an event: a log line for nobody
        time.sleep(0.2)
        assert rt.foxglove.info()["published"] == 0
        viewer = Viewer(rt.foxglove.port)
        try:
            viewer.subscribe("/joint_states")
            viewer.pump(lambda: len(viewer.received.get("/joint_states", [])) >= 5,
                        "joint states")
            assert set(viewer.received) == {"/joint_states"}
            wait_for(lambda: rt.foxglove.info()["published"] >= 5, "the count of them",
                     DEMO_WAIT)
            assert rt.foxglove.info()["status_reports"] == 0
            viewer.subscribe("/rocoma/status")
            viewer.pump(lambda: viewer.received.get("/rocoma/status"), "a status report")
            assert rt.foxglove.info()["status_reports"] >= 1
        finally:
            viewer.close()


def test_a_view_whose_process_dies_is_said_and_the_loop_runs_on(virtual_channel,
                                                                  sim_segment_factory,
                                                                  caplog):
    """The writer process serves the view: killed, the view is gone (said once, no
    connection taken any more, no status report built for it) and the loop keeps its
    cycles; the close waits for nothing."""
    sim_segment_factory(2)
    with runtime_running(_config(virtual_channel), DEMO_RUN, foxglove=_view()) as rt:
        port = rt.foxglove.port
        viewer = Viewer(port)
        viewer.subscribe("/joint_states", "/rocoma/status")
        viewer.pump(lambda: viewer.received.get("/rocoma/status"), "a status report")
        assert rt.recorder is not None
        os.kill(rt.recorder.pid, signal.SIGKILL)
        wait_for(lambda: any("the Foxglove live view is gone" in r.getMessage()
                             for r in caplog.records), "the view's end said", DEMO_WAIT)
        # the report a viewer was watching is no longer built in the loop's process
        built = rt.foxglove.info()["status_reports"]
        time.sleep(3 * rt.foxglove.config.status_period)
        assert rt.foxglove.info()["status_reports"] == built
        cycles = rt.loop.stats.cycles
        wait_for(lambda: rt.loop.stats.cycles >= cycles + 50, "50 more cycles", DEMO_WAIT)
        with pytest.raises(OSError):
            socket.create_connection(("127.0.0.1", port), timeout=DEMO_WAIT).close()
        viewer.close()
    said = [r for r in caplog.records if "the Foxglove live view is gone" in r.getMessage()]
    assert len(said) == 1


def test_the_manager_channel_goes_on_when_the_loop_stops(virtual_channel,
                                                         sim_segment_factory):
    """No new cycle, no new joint states; /rocoma/manager goes on at the view's rate, so a
    latch cleared after the loop's stop is seen."""
    sim_segment_factory(2)
    cfg = _config(virtual_channel)
    cfg["manager"]["estop_must_be_cleared"] = True  # the manager starts latched
    with runtime_running(cfg, DEMO_RUN, foxglove=_view(rate=50.0)) as rt:
        viewer = Viewer(rt.foxglove.port)
        try:
            viewer.subscribe("/rocoma/manager", "/joint_states")
            viewer.pump(lambda: any(m["latched"] for m in
                                    viewer.received.get("/rocoma/manager", [])),
                        "the latch on /rocoma/manager")
            rt.loop.stop("test")

            def stopped() -> bool:
                before = rt.loop.stats.cycles
                time.sleep(0.1)  # ten periods at the test's 100 Hz
                return rt.loop.stats.cycles == before
            wait_for(stopped, "the loop's stop", DEMO_WAIT)
            cycles = rt.loop.stats.cycles
            assert rt.manager.clear_emergency_stop()
            viewer.pump(lambda: not viewer.received["/rocoma/manager"][-1]["latched"],
                        "the cleared latch after the loop's stop")
            assert viewer.received["/rocoma/manager"][-1]["cycles"] <= cycles
            # the server sent every joint state of the last rows before this message (it
            # reads the rows before it publishes; one socket keeps the order): none since
            joints = len(viewer.received["/joint_states"])
            managers = len(viewer.received["/rocoma/manager"])
            viewer.pump(lambda: len(viewer.received["/rocoma/manager"]) >= managers + 5,
                        "the manager's messages going on")
            assert len(viewer.received["/joint_states"]) == joints
        finally:
            viewer.close()


def test_the_port_taken_is_said_in_one_line(virtual_channel, sim_segment_factory, tmp_path,
                                            capsys):
    import yaml

    from rocoma_can.cli.main import main
    sim_segment_factory(2)
    taken = socket.socket()
    taken.bind(("127.0.0.1", 0))
    taken.listen()
    try:
        path = tmp_path / "robot.yaml"
        path.write_text(yaml.safe_dump(_config(virtual_channel)))
        code = main(["run", str(path), "--no-flight", "--duration", "0.1",
                     "--foxglove", f"127.0.0.1:{taken.getsockname()[1]}"])
    finally:
        taken.close()
    err = capsys.readouterr().err
    assert code == 2 and "Foxglove: cannot serve on 127.0.0.1:" in err
    assert "Traceback" not in err


def test_the_demo_serves_its_robot_live(capsys):
    """`demo --foxglove`: the walk-through's manager on the live view, said where, and a
    viewer sees the demo's joints move by name while it runs."""
    import re
    import threading

    from rocoma_can.cli.demo.walkthrough import DemoOptions, Walkthrough
    lines: list[str] = []
    served = threading.Event()

    def out(line: str) -> None:
        lines.append(line)
        if "ws://" in line:
            served.set()
    seen: dict[str, Any] = {}

    def watch() -> None:
        assert served.wait(DEMO_WAIT)
        port = int(re.search(r"ws://127\.0\.0\.1:(\d+)", next(
            line for line in lines if "ws://" in line)).group(1))
        viewer = Viewer(port)
        try:
            viewer.subscribe("/joint_states", "/robot_description")
            viewer.pump(lambda: len(viewer.received.get("/joint_states", [])) >= 10
                        and viewer.received.get("/robot_description"),
                        "ten joint states and the robot from the demo")
            seen["names"] = viewer.received["/joint_states"][-1]["name"]
            seen["movable"] = parse_urdf(viewer.received["/robot_description"][0][
                "data"].encode(), "sent").movable
            seen["topics"] = set(viewer.channels)
        finally:
            viewer.close()
    viewer = threading.Thread(target=watch)
    viewer.start()
    report = Walkthrough(DemoOptions(drives=2, rate=100.0, duration=3.0, record=None,
                                     foxglove=_view()), out=out).run()
    viewer.join(DEMO_WAIT)
    assert report.ok, "\n".join(lines)
    assert seen.get("names") == ["joint1", "joint2"], (seen, lines)
    assert seen["movable"] == ("joint1", "joint2")  # the demo's arm: a joint per drive
    said = next(line for line in lines if "ws://" in line)
    assert said.endswith(f"layout to import in Foxglove: {LAYOUT}") and LAYOUT.is_file()
    assert layout_topics() <= seen["topics"]  # the layout shows what the demo serves


def _angle_about_z(q: dict[str, float]) -> float:
    assert abs(q["x"]) < 1e-12 and abs(q["y"]) < 1e-12  # joint1 of the demo arm turns about z
    return 2 * math.atan2(q["z"], q["w"])


def test_the_robot_and_its_transforms_follow_the_joints(virtual_channel, sim_segment_factory,
                                                        tmp_path):
    """With urdf: in the config, a viewer gets the URDF as it subscribes (a second one,
    later, too: a WebSocket keeps nothing for it) and a transform per joint on /tf at the
    joints' positions: each /tf sample turns joint1 by the position /joint_states sent with
    the same timestamp, and they change as the pd controller moves the joints."""
    sim_segment_factory(2)
    urdf = demo_urdf(["joint1", "joint2"])
    (tmp_path / "arm.urdf").write_text(urdf)
    config = {**_config(virtual_channel), "urdf": str(tmp_path / "arm.urdf")}
    with runtime_running(config, DEMO_RUN, foxglove=_view()) as rt:
        viewer = Viewer(rt.foxglove.port)
        late = None
        try:
            viewer.subscribe("/robot_description", "/tf", "/joint_states")
            assert {t: viewer.channels[t]["schemaName"] for t in ("/robot_description", "/tf")
                    } == {c.topic: c.schema_name for c in ROBOT}
            viewer.pump(lambda: viewer.received.get("/robot_description"), "the URDF")
            assert viewer.received["/robot_description"] == [{"data": urdf}]
            wait_for(lambda: rt.manager.switch_blocked() is None, "drives up", DEMO_WAIT)
            assert rt.manager.switch_controller("pd", timeout=DEMO_WAIT) == 0  # to 0.3 rad

            def angles() -> list[tuple[float, float]]:
                """(joint1's position, its /tf angle) per sample both arrived of."""
                by_time = {json.dumps(m["timestamp"]): m["position"][0]
                           for m in viewer.received.get("/joint_states", [])}
                pairs = []
                for m in viewer.received.get("/tf", []):
                    first = m["transforms"][0]
                    position = by_time.get(json.dumps(first["timestamp"]))
                    if position is not None:
                        pairs.append((position, _angle_about_z(first["rotation"])))
                return pairs
            viewer.pump(lambda: len(angles()) > 10 and max(p for p, _ in angles())
                        - min(p for p, _ in angles()) > 0.1, "joint1 moving on /tf")
            for position, angle in angles():
                assert angle == pytest.approx(position, abs=1e-9)
            tf = viewer.received["/tf"][-1]["transforms"]
            assert [(t["parent_frame_id"], t["child_frame_id"]) for t in tf] == [
                ("base_link", "joint1_link"), ("joint1_link", "joint2_link")]

            late = Viewer(rt.foxglove.port)
            late.subscribe("/robot_description")
            late.pump(lambda: late.received.get("/robot_description"), "the URDF, later")
            assert late.received["/robot_description"][0] == {"data": urdf}
        finally:
            viewer.close()
            if late is not None:
                late.close()


# --- the layout shipped for the demo (rocoma_can/live/foxglove_layout.json) -------------------

def _panels(node: Any) -> list[str]:
    """The panel ids of a layout's split tree, left to right."""
    if isinstance(node, str):
        return [node]
    assert set(node) <= {"first", "second", "direction", "splitPercentage"}, node
    assert node["direction"] in ("row", "column")
    return _panels(node["first"]) + _panels(node["second"])






#: the panels it has and how Foxglove names their types
PANEL_TYPES = {"3D", "Plot", "StateTransitions", "RosOut", "RawMessages"}


def test_the_layout_is_one_foxglove_can_import():
    """A layout as Foxglove exports it: configById, the split tree of the same panels,
    the 3D panel's URDF layer reading the robot from its topic."""
    layout = shipped_layout()
    assert set(layout) == {"configById", "globalVariables", "userNodes", "playbackConfig",
                           "layout"}
    ids = list(layout["configById"])
    assert sorted(_panels(layout["layout"])) == sorted(ids)
    assert {i.split("!")[0] for i in ids} == PANEL_TYPES and all(i.count("!") == 1
                                                                 for i in ids)
    urdf = [layer for layer in layout["configById"]["3D!robot"]["layers"].values()
            if layer["layerId"] == "foxglove.Urdf"]
    assert [(u["sourceType"], u["topic"], u["instanceId"]) for u in urdf] == [
        ("topic", "/robot_description", "robot")]
    assert layout["configById"]["RosOut!log"]["topicToRender"] == "/rocoma/log"


def test_the_layout_reads_only_what_the_view_serves():
    """Each topic one the view advertises (with a URDF), each field one of its schema."""
    schemas = {c.topic: c.schema for c in MANAGER_CHANNELS + ROBOT}
    for path in layout_paths():
        topic, _, field = path.partition(".")
        assert topic in schemas, path
        if field:
            assert field.split("[")[0] in schemas[topic]["properties"], path
    assert {"/joint_states", "/rocoma/manager", "/rocoma/status", "/rocoma/log",
            "/robot_description"} <= layout_topics()


def test_an_installed_package_has_the_live_view_and_its_layout():
    """pyproject lists the package and the layout as package data: a wheel without them
    has no live view (and no run: the runtime imports it)."""
    tomllib = pytest.importorskip("tomllib")  # Python 3.11
    root = ROOT
    setup = tomllib.loads((root / "pyproject.toml").read_text())["tool"]["setuptools"]
    assert "rocoma_can.live" in setup["packages"]
    shipped = setup["package-data"]["rocoma_can.live"]
    assert any(LAYOUT.match(pattern) for pattern in shipped)
    packages = {".".join(p.parent.relative_to(root).parts)
                for p in (root / "rocoma_can").rglob("__init__.py")}
    assert packages <= set(setup["packages"])
