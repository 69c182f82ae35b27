"""The checks across a robot's drives, each written once and returning what it finds, so
the Python API (``check_drives``: ValueError at the first) and check-config (every problem,
each at its YAML path: rocoma_can/runtime/config_drives.py) say the same findings.
"""
from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from typing import Literal

from ..protocol import cia301
from .config import DriveConfig, is_node_id


@dataclass(frozen=True)
class DriveClash:
    """A problem across drives (``drive_problems``), said two ways from one finding: by the
    drives' names for the Python API (``by_name``: ``check_drives`` raises it), by their
    places in the YAML for check-config (``at``). ``drive``, ``other``: indices into the
    drives checked (``other``: the drive that has the name or node first)."""
    kind: Literal["name", "bus", "node_id", "manager"]
    drive: int
    other: int = -1
    on: str = ""     # node_id: " on bus 'x'" where there are several buses
    buses: str = ""  # bus: the buses there are, "'lf', 'rf'"

    @property
    def key(self) -> str:
        """The drive's key at fault."""
        return "node_id" if self.kind == "manager" else self.kind

    def by_name(self, drives: Sequence[DriveConfig]) -> str:
        d = drives[self.drive]
        if self.kind == "name":
            return f"drive name {d.name!r} is used twice"
        if self.kind == "bus":
            return f"drive {d.name!r}: no bus named {d.bus!r} (buses: {self.buses})"
        if self.kind == "manager":
            return f"drive {d.name!r}: node_id {d.node_id} is the manager's node id"
        return (f"drive {d.name!r}: node_id {_node(d)} is already used by drive "
                f"{drives[self.other].name!r}{self.on}")

    def at(self, drives: Sequence[DriveConfig], place: Sequence[int]) -> str:
        """"drives[1].node_id: ...": ``place`` holds each drive's index in the YAML's list."""
        d = drives[self.drive]
        where = f"drives[{place[self.drive]}].{self.key}"
        if self.kind == "name":
            return f"{where}: {d.name!r} is already drives[{place[self.other]}]"
        if self.kind == "bus":
            return f"{where}: no bus named {d.bus!r} (buses: {self.buses})"
        if self.kind == "manager":
            return f"{where}: {d.node_id} is the manager's node id (manager.node_id)"
        return f"{where}: {_node(d)} is already used by drives[{place[self.other]}]{self.on}"


def _node(d: DriveConfig) -> str:
    """A drive's node id, and its axis where it is not the first."""
    return f"{d.node_id} axis {d.axis}" if d.axis > 1 else str(d.node_id)


def drive_problems(drives: Sequence[DriveConfig], manager_node_id: int,
                   buses: Sequence[str] = ("",)) -> list[DriveClash]:
    """Every problem across drives, in the drives' order: a name used twice, a bus not
    among ``buses`` ("" = the first), a node id (and axis) used twice on one bus, or one
    equal to the manager's (the manager is a node on every bus: its heartbeat goes to all
    of them). A node id said taken is not also the manager's."""
    clashes: list[DriveClash] = []
    names: dict[str, int] = {}
    nodes: dict[tuple[str, int, int], int] = {}
    listed = ", ".join(repr(b) for b in buses)
    for i, d in enumerate(drives):
        if d.name in names:
            clashes.append(DriveClash("name", i, names[d.name]))
        if d.bus and d.bus not in buses:
            clashes.append(DriveClash("bus", i, buses=listed))
        bus = d.bus or buses[0]
        node = (bus, d.node_id, d.axis)
        if node in nodes:
            clashes.append(DriveClash("node_id", i, nodes[node],
                                      on=f" on bus {bus!r}" if len(buses) > 1 else ""))
        elif d.node_id == manager_node_id:
            clashes.append(DriveClash("manager", i))
        names.setdefault(d.name, i)
        nodes.setdefault(node, i)
    return clashes


def check_drives(drives: list[DriveConfig], manager_node_id: int,
                 buses: Sequence[str] = ("",)) -> None:
    """The Python API's check across drives: ValueError for the first problem in the drives'
    order, a drive's clash (``drive_problems``) before its node's axes disagreeing
    (``node_mismatch``)."""
    if not drives:
        raise ValueError("drives: at least one drive is needed")
    if not is_node_id(manager_node_id):
        raise ValueError(f"manager_node_id must be an integer 1..127, got {manager_node_id!r}")
    clashes = drive_problems(drives, manager_node_id, buses)
    first_of_node: dict[tuple[str, int], DriveConfig] = {}
    for i, d in enumerate(drives):
        if clashes and clashes[0].drive == i:
            raise ValueError(clashes[0].by_name(drives))
        why = node_mismatch(first_of_node.setdefault((d.bus or buses[0], d.node_id), d), d)
        if why is not None:
            raise ValueError(why)


def node_mismatch(a: DriveConfig, b: DriveConfig) -> str | None:
    """Why two axes of one node cannot be configured as given, or None: what belongs to
    the node (its file, its heartbeat or guarding, its identity) must be said alike for each."""
    for key in ("eds", "heartbeat_ms", "guarding", "identity", "pdo_bytes"):
        if getattr(a, key) != getattr(b, key):
            return (f"drive {b.name!r}: node {b.node_id} is also drive {a.name!r} (axis "
                    f"{a.axis}), whose {key} is {getattr(a, key)!r}, not "
                    f"{getattr(b, key)!r}: one node has one {key}")
    return None


def estop_conflict(cob_id: int, drives: Sequence[DriveConfig],
                   manager_node_id: int) -> str | None:
    """Why ``cob_id`` cannot be the e-stop COB-ID with these drives (on any of their buses)
    and this manager node, or None."""
    why = cia301.reserved_cob_id(cob_id)
    if why is not None:
        return why
    for d in drives:
        used = cia301.node_cob_ids(d.node_id).get(cob_id)
        if used is not None:
            return f"{used} (drive {d.name!r})"
    used = cia301.node_cob_ids(manager_node_id).get(cob_id)
    return None if used is None else f"{used}, the manager's own"
