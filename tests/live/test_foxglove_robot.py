"""rocoma_can/live/server.py, urdf.py, rocoma_can/cli/demo/ (``--foxglove``): the robot live in
Foxglove's 3D panel: the demo serves its robot, and the transforms follow the joints."""
from __future__ import annotations

import json
import math
from typing import Any

import pytest
from fixtures.running import DEMO_RUN, DEMO_WAIT, runtime_running, wait_for

from rocoma_can.cli.demo.config import demo_urdf
from rocoma_can.live.foxglove import LAYOUT
from rocoma_can.live.messages import ROBOT
from rocoma_can.live.urdf import parse_urdf

pytest.importorskip("foxglove")
pytest.importorskip("websockets.sync.client")
from fixtures.foxglove_layout import layout_topics
from fixtures.foxglove_viewer import Viewer, live_config, loopback_view  # noqa: E402 - after the skips


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
                                     foxglove=loopback_view()), out=out).run()
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
    config = {**live_config(virtual_channel), "urdf": str(tmp_path / "arm.urdf")}
    with runtime_running(config, DEMO_RUN, foxglove=loopback_view()) as rt:
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
