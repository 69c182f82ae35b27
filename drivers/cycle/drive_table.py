"""The drive table: what the cycle's parts know of each drive, built once at start-up.

The hardware measures every drive against its file (plan/) and puts each on a bus; the
cycle's parts (receive.py, command.py, frames_out.py, recovery.py) each take this one table
and precompute from it the per-drive lists their loops index, so none of them is handed a
dozen parallel lists in an order it must trust, and no cycle looks anything up in it.
(Supervision and node guarding, which tests build alone, and the bring-ups, a stage below
this table, still take the few per-drive lists they need.)
"""
from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass

import numpy as np

from ..link.bus_port import Bus, BusPort
from ..plan.config import DriveConfig
from ..plan.drive_plan import DrivePlan
from ..plan.pdo_layout import IGNORED, DriveLayout


@dataclass(frozen=True, slots=True)
class DriveEntry:
    """One drive: its plan (config, capabilities, PDO layout), its bus and its node."""
    index: int         # the drive's place in JointState / JointCommand
    plan: DrivePlan
    port: BusPort      # the bus it is on
    node: tuple[int, ...]  # the drives of its node (the axes of a multi-axis device, which
    # share its NMT state, heartbeat or guarding, EMCY and SDO server), lowest axis first

    @property
    def config(self) -> DriveConfig:
        return self.plan.drive

    @property
    def layout(self) -> DriveLayout:
        return self.plan.layout

    @property
    def node_id(self) -> int:
        return self.plan.drive.node_id

    @property
    def leads_node(self) -> bool:
        """The node's lowest axis: it configures the node, hears its heartbeat and EMCY."""
        return self.plan.leads_node


DriveTable = tuple[DriveEntry, ...]


def wire_drives(plans: Sequence[DrivePlan], buses: Mapping[str, Bus],
                manager_node_id: int) -> tuple[list[BusPort], DriveTable]:
    """One BusPort per bus, and each drive on the bus its config names (``DriveConfig.bus``,
    "" = the first), grouped with the other axes of its node."""
    drives = [p.drive for p in plans]
    first = next(iter(buses))
    ports = [BusPort(name, arg, [i for i, d in enumerate(drives) if (d.bus or first) == name],
                     manager_node_id) for name, arg in buses.items()]
    port_of = {p.name: p for p in ports}
    on = [port_of[d.bus or first] for d in drives]
    node_of: dict[tuple[str, int], list[int]] = {}
    for i, d in enumerate(drives):
        node_of.setdefault((on[i].name, d.node_id), []).append(i)
    return ports, tuple(
        DriveEntry(i, plan, on[i], tuple(sorted(node_of[on[i].name, plan.drive.node_id],
                                                key=lambda k: drives[k].axis)))
        for i, plan in enumerate(plans))


def raw_values(n: int) -> dict[str, np.ndarray]:
    """The raw bus values of N drives, one slot per drive: the TPDO codecs unpack into them
    (receive.py), the RPDO targets are encoded into them (command.py)."""
    return {name: np.zeros(n, dtype=np.int64) for name in
            ("statusword", "position", "velocity", "torque",
             "target_position", "target_velocity", "target_torque", IGNORED)}
