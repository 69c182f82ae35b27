"""drivers/plan/drive_clashes.py: the checks across drives, written once. ``drive_problems``
collects every finding; the Python API (``check_drives``) raises the first by the drives'
names, check-config says each at its YAML path (tests/runtime/test_config.py)."""
from __future__ import annotations

import pytest

from rocoma_can.drivers.plan.config import DriveConfig
from rocoma_can.drivers.plan.drive_clashes import check_drives, drive_problems


def drive(name: str, node_id: int, bus: str = "", axis: int = 1) -> DriveConfig:
    return DriveConfig(name, node_id, 4096, 1.0, bus=bus, axis=axis)


def test_every_clash_is_found_in_the_drives_order_and_said_both_ways():
    drives = [drive("a", 1, "lf"), drive("a", 2, "lf"), drive("c", 1, "lf"),
              drive("d", 100, "rf"), drive("e", 3, "tail")]
    clashes = drive_problems(drives, 100, ["lf", "rf"])
    assert [(c.kind, c.drive, c.key) for c in clashes] == [
        ("name", 1, "name"), ("node_id", 2, "node_id"), ("manager", 3, "node_id"),
        ("bus", 4, "bus")]
    place = [0, 1, 2, 3, 5]  # drives[4] of the YAML did not build
    assert [c.at(drives, place) for c in clashes] == [
        "drives[1].name: 'a' is already drives[0]",
        "drives[2].node_id: 1 is already used by drives[0] on bus 'lf'",
        "drives[3].node_id: 100 is the manager's node id (manager.node_id)",
        "drives[5].bus: no bus named 'tail' (buses: 'lf', 'rf')"]
    assert [c.by_name(drives) for c in clashes] == [
        "drive name 'a' is used twice",
        "drive 'c': node_id 1 is already used by drive 'a' on bus 'lf'",
        "drive 'd': node_id 100 is the manager's node id",
        "drive 'e': no bus named 'tail' (buses: 'lf', 'rf')"]


def test_a_taken_node_id_is_not_also_the_managers_and_axes_are_their_own():
    drives = [drive("a", 100), drive("b", 100), drive("c", 5), drive("d", 5, axis=2)]
    assert [(c.kind, c.drive) for c in drive_problems(drives, 100)] == [
        ("manager", 0), ("node_id", 1)]


def test_the_api_raises_the_first_problem_in_the_drives_order():
    """As before the checks were written once: a node whose axes disagree (drive 'b') is
    said before a clash of a later drive ('c' takes 'a''s name)."""
    drives = [drive("a", 5), DriveConfig("b", 5, 4096, 1.0, axis=2, heartbeat_ms=50),
              drive("a", 6)]
    with pytest.raises(ValueError, match="drive 'b': node 5 is also drive 'a'"):
        check_drives(drives, 100)
    with pytest.raises(ValueError, match="drive name 'a' is used twice"):
        check_drives([drives[0], drives[2], drives[1]], 100)
