"""rocoma_can/live/foxglove_layout.json: the shipped layout is one Foxglove can import, reads only
what the view serves, and an installed package has it."""
from __future__ import annotations

from typing import Any

import pytest
from fixtures.paths import ROOT

from rocoma_can.live.foxglove import LAYOUT
from rocoma_can.live.messages import MANAGER_CHANNELS, ROBOT

pytest.importorskip("foxglove")
pytest.importorskip("websockets.sync.client")
from fixtures.foxglove_layout import layout_paths, layout_topics, shipped_layout


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
