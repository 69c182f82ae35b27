"""The nodes on a simulated segment's bus and where each received frame goes.

A drive is found by its node id (``drives``), its SDO requests by their COB-ID (``fixed``),
its RPDOs by theirs (``rpdo``, replaced whenever the master remaps them). LSS may move a
node to another node id (lss.py): off the bus at the old one, a drive booted afresh at the
new one. The segment (segment.py) dispatches with these tables, its lock held.
"""
from __future__ import annotations

import logging
from collections.abc import Mapping
from typing import Any

from canopen.objectdictionary import ObjectDictionary

from ..commission.lss import UNCONFIGURED
from ..files.identity import Identity
from ..protocol import cia301
from .drive import SimulatedDrive
from .lss import LssSlave
from .objects import load_object_dictionary
from .port import Route, Segment

log = logging.getLogger("rocoma_can.drivers.sim.segment")


class NodesOnBus:
    """``segment``: what the drives are made on; ``eds``, ``fallbacks``: their file and the
    values they assume where it has none; ``overrides``: object values replacing the file's."""

    def __init__(self, segment: Segment, eds: str, fallbacks: Mapping[tuple[int, int], Any],
                 overrides: Mapping[tuple[int, int], Any]) -> None:
        self._segment, self._eds = segment, eds
        self._fallbacks, self._overrides = fallbacks, overrides
        self.drives: dict[int, SimulatedDrive] = {}
        self.fixed: dict[int, Route] = {}  # a node's SDO server, by request COB-ID
        self.rpdo: dict[int, Route] = {}   # every node's RPDOs, by COB-ID
        self._rpdo_of_drive: dict[int, dict[int, Route]] = {}
        self.lss_slaves: list[LssSlave] = []

    def put_on_bus(self, node_id: int, joint: int, axes: int, identity: Identity,
                   od: ObjectDictionary | None = None) -> SimulatedDrive:
        drive = SimulatedDrive(self._segment, node_id, joint,
                               od or load_object_dictionary(self._eds, node_id),
                               self._fallbacks, axes)
        for values in (drive.objects.defaults, drive.objects.values):
            values.update(self._overrides)  # values the file gives that a run replaces
            values.update(identity.objects())
        self.drives[node_id] = drive
        self.fixed[cia301.SDO_RX + node_id] = drive.on_sdo
        return drive

    def set_rpdo_routes(self, node_id: int, routes: dict[int, Route]) -> None:
        for cob_id in self._rpdo_of_drive.get(node_id, {}):
            self.rpdo.pop(cob_id, None)
        self._rpdo_of_drive[node_id] = routes
        self.rpdo.update(routes)

    def reset_moves(self, node_id: int, command: int) -> bool:
        """An NMT reset that gives the node its pending LSS node id (then it has booted
        at that id: True)."""
        for slave in self.lss_slaves:
            if slave.active_id == node_id:
                return slave.on_reset(command)
        return False

    def move(self, slave: LssSlave, old: int) -> None:
        """An LSS slave's node took another node id: off the bus at the old one, a drive
        booted at the new one (the node's joints; its drive state starts afresh). A node
        id already taken leaves the node without one (a real bus would have two nodes
        answering at it)."""
        if old in self.drives:
            del self.drives[old]
            del self.fixed[cia301.SDO_RX + old]
            self.set_rpdo_routes(old, {})
        new = slave.active_id
        if new == UNCONFIGURED:
            return
        if new in self.drives:
            log.warning("simulated node %s: node id %d is taken, the node stays without one",
                        slave.identity.describe(), new)
            slave.active_id = UNCONFIGURED
            return
        self.put_on_bus(new, slave.joint, slave.axes, slave.identity).power_on()
